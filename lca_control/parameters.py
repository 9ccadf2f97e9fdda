"""Typed parameter tables: one declaration per node parameter, one validation rule set.

Every node of lca_hil (simulator, controller, CAN bridge) declares its ROS parameters from a
`ParameterTable`: each `ParamSpec` carries the name (SI unit in it), the kind, the default, the
documented range or choices, a description, and whether a live change takes effect (`live`) or
needs a restart (read-only). The same table

* declares the parameters (`lca_sim.ros.node_util.declare_table`: type, range and read-only
  flag go into the ROS ParameterDescriptor, so `ros2 param describe` shows them),
* checks each value (`ParameterTable.check_all`) before the node's own cross-checks,
* answers `--help` without starting ROS (`ParameterTable.describe`).

Pure: no ROS import, so the tables live beside the cores they configure. A bad value raises
`ParameterError`, the one exception type of parameter validation, whose message always reads
``<name>: expected <what>, got <value>``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from lca_control.pi import ControlParamError

_NO_VALUE = object()


class ParameterError(ControlParamError):
    """A parameter value that a node refuses: at start-up (exit code 2) or on a live set."""

    def __init__(self, name: str, expected: str, value: object = _NO_VALUE) -> None:
        self.name = name
        self.expected = expected
        self.value = value
        got = "" if value is _NO_VALUE else f", got {value!r}"
        super().__init__(f"{name}: expected {expected}{got}")


class ParamKind(enum.Enum):
    """The ROS parameter type of a spec (rcl_interfaces/ParameterType)."""

    BOOL = "bool"
    INTEGER = "integer"
    DOUBLE = "double"
    STRING = "string"
    INTEGER_ARRAY = "integer[]"
    DOUBLE_ARRAY = "double[]"
    STRING_ARRAY = "string[]"


def _is_number(value: object) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float)


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One node parameter.

    Attributes:
        name: the ROS parameter name, with its SI unit (`command_timeout_s`).
        kind: the ROS type.
        default: the value declared when the node's params file has none.
        description: what it does, with the unit spelled out.
        low, high: the documented range of a number (or of every element of a number array);
            None for unbounded. `low_open` makes the lower bound exclusive: (low, high].
        choices: the allowed values of a string (or of every element of a string array).
        live: True when a live `ros2 param set` takes effect at once; False for read-only
            parameters (model, wiring, bus), which the node rejects while running.
    """

    name: str
    kind: ParamKind
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    choices: tuple[str, ...] = ()
    live: bool = True

    def __post_init__(self) -> None:
        self.check(self.default)  # a table whose defaults fail its own rules is a bug

    def range_text(self) -> str:
        """The range or choices as a person reads them: `(0, 60]`, `one of a, b`."""
        if self.choices:
            return "one of " + ", ".join(self.choices)
        if self.low is None and self.high is None:
            return ""
        low = "-inf" if self.low is None else f"{self.low:g}"
        high = "inf" if self.high is None else f"{self.high:g}"
        opening = "(" if self.low_open or self.low is None else "["
        return f"{opening}{low}, {high}{')' if self.high is None else ']'}"

    def _check_number(self, value: object, integer: bool) -> float | int:
        kind = "an integer" if integer else "a number"
        ok_type = (
            not isinstance(value, bool) and isinstance(value, int) if integer else _is_number(value)
        )
        if not ok_type:
            raise ParameterError(self.name, kind, value)
        number = float(value)  # type: ignore[arg-type]
        too_low = self.low is not None and (
            number <= self.low if self.low_open else number < self.low
        )
        too_high = self.high is not None and number > self.high
        if not math.isfinite(number) or too_low or too_high:
            bounds = self.range_text()
            raise ParameterError(self.name, f"{kind} in {bounds}" if bounds else kind, value)
        return value if integer else number  # type: ignore[return-value]

    def _check_string(self, value: object) -> str:
        if not isinstance(value, str):
            raise ParameterError(self.name, "a string", value)
        if self.choices and value not in self.choices:
            raise ParameterError(self.name, self.range_text(), value)
        return value

    def check(self, value: object) -> Any:
        """The value in its Python type, or ParameterError naming this parameter."""
        kind = self.kind
        if kind is ParamKind.BOOL:
            if not isinstance(value, bool):
                raise ParameterError(self.name, "true or false", value)
            return value
        if kind is ParamKind.INTEGER:
            return self._check_number(value, integer=True)
        if kind is ParamKind.DOUBLE:
            return self._check_number(value, integer=False)
        if kind is ParamKind.STRING:
            return self._check_string(value)
        if isinstance(value, str | bytes) or not hasattr(value, "__iter__"):
            raise ParameterError(self.name, f"an array ({kind.value})", value)
        items = list(value)
        if kind is ParamKind.STRING_ARRAY:
            return tuple(self._check_string(v) for v in items)
        return tuple(self._check_number(v, integer=kind is ParamKind.INTEGER_ARRAY) for v in items)

    def help_line(self) -> str:
        """`name (kind, default X, range R, live): description` for --help."""
        facts = [self.kind.value, f"default {_show(self.default)}"]
        bounds = self.range_text()
        if bounds:
            facts.append(bounds)
        facts.append("live" if self.live else "read-only")
        return f"{self.name} ({'; '.join(facts)}): {self.description}"


def _show(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:g}"
    return repr(value) if isinstance(value, str) else str(value)


@dataclass(frozen=True, slots=True)
class ParameterTable:
    """The parameters of one node, in declaration order."""

    specs: tuple[ParamSpec, ...]
    _by_name: dict[str, ParamSpec] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        by_name = {spec.name: spec for spec in self.specs}
        if len(by_name) != len(self.specs):
            raise ControlParamError("a parameter table names a parameter twice")
        object.__setattr__(self, "_by_name", by_name)

    def __iter__(self) -> Iterator[ParamSpec]:
        return iter(self.specs)

    def __getitem__(self, name: str) -> ParamSpec:
        return self._by_name[name]

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    @property
    def names(self) -> tuple[str, ...]:
        """Every parameter name, in declaration order."""
        return tuple(spec.name for spec in self.specs)

    @property
    def read_only(self) -> frozenset[str]:
        """The parameters a running node rejects (restart to change them)."""
        return frozenset(spec.name for spec in self.specs if not spec.live)

    def defaults(self) -> dict[str, Any]:
        """Every parameter at its default."""
        return {spec.name: spec.default for spec in self.specs}

    def check_all(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """Each value checked against its spec, in its Python type (arrays as tuples).

        Raises:
            ParameterError: the first value outside its spec; a missing one is taken at its
                default, an unknown name is refused.
        """
        unknown = sorted(set(values) - set(self._by_name))
        if unknown:
            raise ParameterError(unknown[0], "one of " + ", ".join(self.names))
        return {spec.name: spec.check(values.get(spec.name, spec.default)) for spec in self.specs}

    def describe(self) -> str:
        """Every parameter on one line each, for a node's --help."""
        return "\n".join("  " + spec.help_line() for spec in self.specs)


def positive(
    name: str, default: float, description: str, high: float | None = None, live: bool = True
) -> ParamSpec:
    """A double in (0, high]: periods, gains' integral times, limits."""
    return ParamSpec(
        name, ParamKind.DOUBLE, default, description, 0.0, high, low_open=True, live=live
    )


def non_negative(
    name: str, default: float, description: str, high: float | None = None, live: bool = True
) -> ParamSpec:
    """A double in [0, high]: start times, gains that 0 switches off."""
    return ParamSpec(name, ParamKind.DOUBLE, default, description, 0.0, high, live=live)
