"""What every console script's `main` does alike: its own arguments, and whether it wants help.

`own_arguments` gives the arguments outside `--ros-args ... [--]`, as rcl splits them, without
rclpy (a script answers `--help` before it imports ROS 2). The failure line
(`lca_sim.errors.fail`) and the stop signals (`lca_sim.runtime.stop_signals`) are in the base
layer, for the ROS tools' mains in lca_sim.ros too.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

HELP_FLAGS = frozenset({"-h", "--help"})
ROS_ARGS = "--ros-args"


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
