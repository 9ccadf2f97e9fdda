"""What every console script's `main` does alike: own arguments, a failure line, stop signals.

* `own_arguments`: the arguments outside `--ros-args ... [--]`, as rcl splits them, without
  rclpy (a script answers `--help` before it imports ROS 2).
* `fail`: one `prog: error: ...` line on stderr and the bad-input exit code.
* `stop_signals`: SIGINT and SIGTERM handled for the length of a block (a clean stop of a loop
  or a recording), the previous handlers back afterwards.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from types import FrameType

from lca_sim.errors import EXIT_BAD_INPUT

HELP_FLAGS = frozenset({"-h", "--help"})
ROS_ARGS = "--ros-args"
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def script_arguments(argv: Sequence[str] | None) -> list[str]:
    """A script's arguments: `argv`, or the process's own (sys.argv) when None."""
    return list(sys.argv[1:] if argv is None else argv)


def own_arguments(argv: Sequence[str]) -> list[str]:
    """The arguments that are not ROS arguments: outside `--ros-args ... [--]` (rcl's rule)."""
    own: list[str] = []
    in_ros = False
    for token in argv:
        if token == ROS_ARGS:
            in_ros = True
        elif in_ros and token == "--":
            in_ros = False
        elif not in_ros:
            own.append(token)
    return own


def wants_help(argv: Sequence[str]) -> bool:
    """True when `-h` or `--help` is one of the script's own arguments (not a ROS argument)."""
    return not HELP_FLAGS.isdisjoint(own_arguments(argv))


def fail(prog: str, message: str) -> int:
    """Say `prog: error: message` on stderr; returns the bad-input exit code."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return EXIT_BAD_INPUT


@contextmanager
def stop_signals(on_stop: Callable[[str], None]) -> Iterator[None]:
    """Inside the block, SIGINT and SIGTERM call `on_stop` with the signal's name.

    The handlers that were set before come back when the block ends, however it ends.
    """

    def handler(signum: int, _frame: FrameType | None) -> None:
        on_stop(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
