"""The checks of a sweep spec's values: each failure is one ConfigError (file, key, expected)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from lca_sim.errors import ConfigError


def is_number(value: object) -> bool:
    """An int or float, not a bool."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def finite_number(value: object, source: str, key: str) -> float:
    """`value` as a float; a finite number or ConfigError."""
    if not is_number(value) or not math.isfinite(float(value)):  # type: ignore[arg-type]
        raise ConfigError(source, key, f"expected a finite number, got {value!r}")
    return float(value)  # type: ignore[arg-type]


def mapping_of(value: object, source: str, key: str, what: str) -> Mapping[str, Any]:
    """`value` if it is a mapping, else ConfigError expecting `what`."""
    if not isinstance(value, Mapping):
        raise ConfigError(source, key, f"expected {what}, got {value!r}")
    return value


def check_keys(raw: Mapping[str, Any], allowed: tuple[str, ...], source: str, where: str) -> None:
    """ConfigError at the first key of `raw` not in `allowed` (`where`: the keys' parent)."""
    for key in raw:
        if key not in allowed:
            prefix = f"{where}." if where else ""
            raise ConfigError(
                source, f"{prefix}{key}", f"unknown key (valid: {', '.join(allowed)})"
            )
