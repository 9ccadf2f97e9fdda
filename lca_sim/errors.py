"""Exceptions of lca_hil: one base class, subclasses that carry their context."""

from __future__ import annotations


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
