"""Exceptions of lca_hil: one base class, subclasses that carry their context; exit codes."""

from __future__ import annotations

import difflib
import sys
from collections.abc import Callable, Iterable

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


# One wording per kind of failure, in every tool: a file that is not there, one that cannot be
# read, a key that is not one, a number out of its range.
FILE_NOT_FOUND = "file not found"
FOLDER_NOT_FOUND = "folder not found"


def file_problem(exc: OSError, path: object = None) -> str:
    """What keeps a file from being read, in the tools' one wording.

    `file not found` or `cannot read the file (reason)`, with `: PATH` after `file` when the
    error is reported against another file (the one that names it).
    """
    where = "" if path is None else f": {path}"
    if isinstance(exc, FileNotFoundError):
        return f"{FILE_NOT_FOUND}{where}"
    return f"cannot read the file{where} ({exc.strerror or exc})"


def close_key(name: str, candidates: Iterable[str], cutoff: float = 0.6) -> str | None:
    """The candidate `name` is most likely a misspelling of (difflib), or None."""
    match = difflib.get_close_matches(name, list(candidates), n=1, cutoff=cutoff)
    return match[0] if match else None


def unknown_key(name: str, valid: Iterable[str]) -> str:
    """`unknown key NAME; did you mean KEY?`, or the valid keys when none is close."""
    valid = sorted(valid)
    match = close_key(name, valid)
    if match is not None:
        return f"unknown key {name}; did you mean {match}?"
    return f"unknown key {name} (valid keys here: {', '.join(valid) or 'none'})"


class UnknownNameError(LcaHilError):
    """A name (axis, joint, state, shipped config) is not one of the valid ones."""

    def __init__(self, kind: str, name: str, valid: tuple[str, ...] | list[str]) -> None:
        self.kind = kind
        self.name = name
        self.valid = tuple(valid)
        super().__init__(f"unknown {kind} {name!r}; valid: {', '.join(self.valid)}")


class InvalidValueError(LcaHilError, ValueError):
    """A value the project cannot take: out of range, malformed, or inconsistent with another.

    Also a ValueError, for callers that handle bad values of any origin alike.
    """


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


def fail(prog: str, message: str) -> int:
    """Say `prog: error: message` on stderr; returns the bad-input exit code."""
    print(f"{prog}: error: {message}", file=sys.stderr, flush=True)
    return EXIT_BAD_INPUT
