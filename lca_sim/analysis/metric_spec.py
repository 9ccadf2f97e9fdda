"""A metric as a sweep spec names it: checked against the library, its arguments bound.

    metrics:
      - {metric: peak_current_a, axis: pivot}
      - {name: travel_after_cut_rad, metric: travel, axis: pivot, from_s: 40.2}

`parse_metric` checks one entry against `lca_sim.analysis.metrics.METRICS` (its arguments, their
kinds and ranges) into a `MetricSpec`, which computes its figure from a trace. Pure.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from lca_sim.analysis.metrics import METRICS, SIGNALS, MetricArgs, MetricDef, Trace
from lca_sim.errors import ConfigError


@dataclass(frozen=True, slots=True)
class MetricSpec:
    """One metric of a sweep: the column it fills, the library entry and its arguments."""

    name: str
    metric: str
    args: MetricArgs

    def compute(self, trace: Trace) -> float:
        """The metric on a trace."""
        return METRICS[self.metric].function(trace, self.args)

    def as_dict(self) -> dict[str, Any]:
        """Plain data (for the point's key and the sweep's record)."""
        a = self.args
        return {
            "name": self.name,
            "metric": self.metric,
            "axis": a.axis,
            "from_s": a.from_s,
            "to_s": a.to_s,
            "signal": a.signal,
            "target": a.target,
            "band": a.band,
            "low": a.low,
            "high": a.high,
            "states": list(a.states),
            "margin": a.margin,
            "occurrence": a.occurrence,
        }


def _number(raw: Mapping[str, Any], key: str, source: str, where: str) -> float:
    value = raw[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(source, f"{where}.{key}", f"expected a finite number, got {value!r}")
    return float(value)


def parse_metric(raw: object, source: str, where: str, default_axis: str | None) -> MetricSpec:
    """One entry of a spec's `metrics` list.

    Args:
        raw: the entry: `{metric: NAME, name: COLUMN, axis: ..., from_s: ..., ...}`.
        source: the spec file, for errors.
        where: the entry's key path (`metrics[2]`).
        default_axis: the axis when the entry names none (None: it must name one).

    Raises:
        ConfigError: the entry's bad key and what was expected.
    """
    if isinstance(raw, str):
        raw = {"metric": raw}
    if not isinstance(raw, Mapping):
        raise ConfigError(source, where, f"expected a mapping with metric: NAME, got {raw!r}")
    metric = raw.get("metric")
    if metric not in METRICS:
        raise ConfigError(
            source, f"{where}.metric", f"expected one of {', '.join(METRICS)}, got {metric!r}"
        )
    definition = METRICS[metric]
    allowed = definition.args | {"metric", "name"}
    for key in raw:
        if key not in allowed:
            raise ConfigError(
                source,
                f"{where}.{key}",
                f"not an argument of {metric} (it takes {', '.join(sorted(allowed))})",
            )
    name = raw.get("name", metric)
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(source, f"{where}.name", f"expected a column name, got {name!r}")
    return MetricSpec(name, metric, _metric_args(raw, definition, source, where, default_axis))


def _metric_args(
    raw: Mapping[str, Any], definition: MetricDef, source: str, where: str, default_axis: str | None
) -> MetricArgs:
    """A metric entry's arguments (its keys already checked against the definition)."""
    axis = raw.get("axis", default_axis)
    if not isinstance(axis, str):
        raise ConfigError(source, f"{where}.axis", "expected an axis name (or base.axis)")
    kwargs: dict[str, Any] = {"axis": axis}
    for key in ("from_s", "to_s", "target", "band", "low", "high", "margin"):
        if key in raw and raw[key] is not None:
            kwargs[key] = _number(raw, key, source, where)
    if "signal" in raw:
        if raw["signal"] not in SIGNALS:
            raise ConfigError(source, f"{where}.signal", f"expected one of {', '.join(SIGNALS)}")
        kwargs["signal"] = raw["signal"]
    if "occurrence" in raw:
        occurrence = raw["occurrence"]
        if isinstance(occurrence, bool) or not isinstance(occurrence, int) or occurrence == 0:
            raise ConfigError(
                source,
                f"{where}.occurrence",
                f"expected a whole number, 1 the first change, -1 the last; got {occurrence!r}",
            )
        kwargs["occurrence"] = occurrence
    if "states" in definition.args:
        states = raw.get("states")
        states = [states] if isinstance(states, str) else states
        if not (isinstance(states, list) and states and all(isinstance(x, str) for x in states)):
            raise ConfigError(source, f"{where}.states", "expected drive-state names")
        kwargs["states"] = tuple(states)
    _check_ranges(kwargs, source, where)
    return MetricArgs(**kwargs)


def _check_ranges(kwargs: Mapping[str, Any], source: str, where: str) -> None:
    """A window that is not empty by construction, a band and levels a step can reach."""
    from_s, to_s = kwargs.get("from_s"), kwargs.get("to_s")
    if from_s is not None and to_s is not None and not from_s <= to_s:
        raise ConfigError(source, f"{where}.to_s", f"expected to_s >= from_s ({from_s:g})")
    if "band" in kwargs and not kwargs["band"] > 0.0:
        raise ConfigError(source, f"{where}.band", "expected a fraction of the target > 0")
    if "margin" in kwargs and not kwargs["margin"] >= 0.0:
        raise ConfigError(source, f"{where}.margin", "expected a distance >= 0")
    defaults = MetricArgs(axis="")
    low = kwargs.get("low", defaults.low)
    high = kwargs.get("high", defaults.high)
    if not low < high:
        key = "high" if "high" in kwargs else "low"
        raise ConfigError(source, f"{where}.{key}", f"expected low < high (got {low:g}, {high:g})")


def check_metric_names(
    specs: tuple[MetricSpec, ...], axes: tuple[str, ...], state_names: tuple[str, ...], source: str
) -> None:
    """The axes and drive states the metrics name exist on the robot.

    Raises:
        ConfigError: `metrics[i].axis` or `.states`, with the valid names.
    """
    for i, spec in enumerate(specs):
        if spec.args.axis not in axes:
            raise ConfigError(
                source,
                f"metrics[{i}].axis",
                f"expected one of {', '.join(axes)}, got {spec.args.axis!r}",
            )
        for state in spec.args.states:
            if state not in state_names:
                raise ConfigError(
                    source,
                    f"metrics[{i}].states",
                    f"expected drive states among {', '.join(state_names)}, got {state!r}",
                )
