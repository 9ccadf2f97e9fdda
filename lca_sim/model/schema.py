"""A small reader for nested YAML mappings that reports one clear line per mistake.

Every getter knows the file and the dotted key path it is reading, so a `ConfigError` names
exactly what to fix. Unknown keys are errors: a misspelt key must never be silently ignored.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from lca_sim.errors import ConfigError, close_key, unknown_key

# How alike an unknown key and a missing required one must be to name it as its misspelling
# (difflib's ratio: resistence_ohm / resistance_ohm is 0.93). Higher than for a key known to be
# wrong: the unknown one may still be a valid key that is read later.
MISSPELLING_CUTOFF = 0.8


class MappingReader:
    """Typed, strict access to one mapping of a parsed YAML document."""

    def __init__(self, data: object, source: str, path: str = "") -> None:
        if not isinstance(data, Mapping):
            raise ConfigError(source, path, f"expected a mapping, got {_kind(data)}")
        self._data: Mapping[Any, Any] = data
        self.source = source
        self.path = path
        self._seen: set[str] = set()

    def key_path(self, key: str) -> str:
        """The dotted path of `key` below this mapping."""
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        """True when `key` is present (and marks it as known)."""
        self._seen.add(key)
        return key in self._data

    def key_names(self) -> list[str]:
        """All keys, as strings; a non-string key is an error."""
        out = []
        for key in self._data:
            if not isinstance(key, str):
                raise ConfigError(self.source, self.path, f"keys must be strings, got {key!r}")
            out.append(key)
        return out

    def raw(self, key: str) -> object:
        """The raw value of a required key."""
        self._seen.add(key)
        if key not in self._data:
            unseen = [k for k in self._data if isinstance(k, str) and k not in self._seen]
            typo = close_key(key, unseen, MISSPELLING_CUTOFF)
            hint = "" if typo is None else f"; unknown key {typo}; did you mean {key}?"
            raise ConfigError(self.source, self.key_path(key), f"missing required key{hint}")
        return self._data[key]

    def sub(self, key: str) -> MappingReader:
        """A reader for the nested mapping at `key`."""
        return MappingReader(self.raw(key), self.source, self.key_path(key))

    def number(
        self,
        key: str,
        *,
        default: float | None = None,
        min_value: float | None = None,
        max_value: float | None = None,
        min_exclusive: bool = False,
    ) -> float:
        """A finite real number, optionally bounded."""
        if default is not None and not self.has(key):
            return default
        return check_number(
            self.raw(key),
            self.source,
            self.key_path(key),
            min_value=min_value,
            max_value=max_value,
            min_exclusive=min_exclusive,
        )

    def boolean(self, key: str, *, default: bool | None = None) -> bool:
        """A YAML boolean."""
        if default is not None and not self.has(key):
            return default
        value = self.raw(key)
        if not isinstance(value, bool):
            raise ConfigError(
                self.source, self.key_path(key), f"expected true or false, got {value!r}"
            )
        return value

    def string(self, key: str, *, choices: tuple[str, ...] | None = None) -> str:
        """A string, optionally one of `choices`."""
        value = self.raw(key)
        if not isinstance(value, str):
            raise ConfigError(self.source, self.key_path(key), f"expected a string, got {value!r}")
        if choices is not None and value not in choices:
            raise ConfigError(
                self.source,
                self.key_path(key),
                f"expected one of {', '.join(choices)}, got {value!r}",
            )
        return value

    def sequence(self, key: str) -> list[object]:
        """A YAML list."""
        value = self.raw(key)
        if not isinstance(value, list):
            raise ConfigError(
                self.source, self.key_path(key), f"expected a list, got {_kind(value)}"
            )
        return value

    def finish(self) -> None:
        """Fail on any key that no getter asked for (a misspelling or an unsupported option)."""
        unknown = [k for k in self.key_names() if k not in self._seen]
        if unknown:
            raise ConfigError(
                self.source, self.key_path(unknown[0]), unknown_key(unknown[0], self._seen)
            )


def check_number(
    value: object,
    source: str,
    key: str,
    *,
    min_value: float | None = None,
    max_value: float | None = None,
    min_exclusive: bool = False,
) -> float:
    """Validate one finite real number (YAML int or float, not bool) against optional bounds."""
    if isinstance(value, str):
        # YAML 1.1 reads 1e-4 (no dot) as a string; accept what is plainly a number.
        try:
            value = float(value)
        except ValueError:
            raise ConfigError(source, key, f"expected a number, got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(source, key, f"expected a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ConfigError(source, key, f"expected a finite number, got {value!r}")
    if min_value is not None:
        if min_exclusive and number <= min_value:
            raise ConfigError(source, key, f"expected a number > {min_value:g}, got {number:g}")
        if not min_exclusive and number < min_value:
            raise ConfigError(source, key, f"expected a number >= {min_value:g}, got {number:g}")
    if max_value is not None and number > max_value:
        raise ConfigError(source, key, f"expected a number <= {max_value:g}, got {number:g}")
    return number


def _kind(value: object) -> str:
    if value is None:
        return "nothing (null or empty)"
    return type(value).__name__
