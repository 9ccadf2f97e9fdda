"""Exceptions of lca_hil: one base class, subclasses that carry their context; exit codes."""

from __future__ import annotations

import sys
from collections.abc import Callable

from lca_control.pi import ControlParamError

# Exit codes of the command-line tools.
EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2  # a bad config, input file or argument: one line on stderr, no traceback
EXIT_INTERRUPTED = 130


class LcaHilError(Exception):
    """Base class of every error lca_hil raises on purpose."""


class ConfigError(LcaHilError):
    """A robot config or scenario is invalid.

    The message is one line: the file, the key path and what was expected, so a user can fix the
    file without reading a traceback.
    """

    def __init__(self, source: str, key: str, expected: str) -> None:
        self.source = source
        self.key = key
        self.expected = expected
        where = f"{source}: " if source else ""
        super().__init__(f"{where}{key or '<top level>'}: {expected}")


class UnknownNameError(LcaHilError):
    """A name (axis, joint, state, shipped config) is not one of the valid ones."""

    def __init__(self, kind: str, name: str, valid: tuple[str, ...] | list[str]) -> None:
        self.kind = kind
        self.name = name
        self.valid = tuple(valid)
        super().__init__(f"unknown {kind} {name!r}; valid: {', '.join(self.valid)}")


class OutputError(LcaHilError):
    """The --out folder cannot take the results."""


# What a user's input can raise: caught by every tool and node and turned into one line.
USER_ERRORS: tuple[type[Exception], ...] = (LcaHilError, ControlParamError)


def run_guarded(prog: str, body: Callable[[], int], interrupted: str = "interrupted") -> int:
    """Run a tool's `body`: an LcaHilError becomes one line on stderr, Ctrl-C a short note.

    Returns the body's exit code, EXIT_BAD_INPUT or EXIT_INTERRUPTED.
    """
    try:
        return body()
    except USER_ERRORS as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{prog}: {interrupted}", file=sys.stderr)
        return EXIT_INTERRUPTED
