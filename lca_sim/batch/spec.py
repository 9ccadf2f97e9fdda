"""Sweep specs: the validated form of a sweep YAML (docs/sweeps.md has the whole format).

A spec names a base run, the parameters to vary and the metrics to compute:

    base: {kind: open_loop, robot: default, scenario: fig9_open_loop_pivot}
    # kind: closed_loop | open_loop | current_step; mode: set | scale | offset | blend
    parameters:
      - name: wear
        paths: [robot.axes.pivot.efficiency.load_driving.direct.eta_l]
        mode: blend
        to: 1.0
        values: [0.0, 0.5, 0.9]
    metrics:
      - {metric: peak_current_a, axis: pivot}

A path's first part is one of the run's documents (`ROOTS`); `lca_sim.batch.point` walks it.
Pure: the CLI reads the files and hands the documents in.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lca_sim.analysis.metric_spec import MetricSpec, parse_metric
from lca_sim.batch.checks import check_keys, finite_number, is_number, mapping_of
from lca_sim.errors import ConfigError

KINDS = ("closed_loop", "open_loop", "current_step")
ROOTS = ("base", "robot", "controller", "simulator", "faults", "scenario")
NODE_ROOTS = ("controller", "simulator")  # documents of ROS 2 parameters: flat dotted names
ROOTS_OF_KIND: dict[str, tuple[str, ...]] = {
    "closed_loop": ("base", "robot", "controller", "simulator", "faults"),
    "open_loop": ("base", "robot", "scenario"),
    "current_step": ("base", "robot"),
}
MODES = ("set", "scale", "offset", "blend")
DISTRIBUTIONS = ("uniform", "normal")
SPEC_KEYS = (
    "description",
    "base",
    "parameters",
    "sampling",
    "samples",
    "seed",
    "metrics",
    "trajectories",
    "plot",
)
BASE_KEYS: dict[str, tuple[str, ...]] = {
    "closed_loop": (
        "kind",
        "robot",
        "controller",
        "simulator",
        "faults",
        "duration_s",
        "axis",
        "payload",
    ),
    "open_loop": ("kind", "robot", "scenario", "rigid_body_update_steps", "axis", "payload"),
    "current_step": (
        "kind",
        "robot",
        "axis",
        "setpoint_a",
        "duration_s",
        "dt_s",
        "current_kp_v_per_a",
        "current_ti_s",
        "payload",
    ),
}
PAYLOAD_KEYS = ("link", "mass_kg", "xyz_m")
# Keys that name a file, read once before the points: a path to them would change nothing.
FILE_PATHS: dict[str, str] = {
    "base.robot": "robot.*",
    "base.scenario": "scenario.*",
    "base.controller": "controller.*",
    "base.simulator": "simulator.*",
    "base.faults": "faults.*",
    "simulator.robot": "robot.*",
    "simulator.fault_schedule": "faults.*",
}
MAX_POINTS = 1_000_000


Scalar = float | int | str | bool


@dataclass(frozen=True, slots=True)
class Distribution:
    """A random parameter: uniform on [low, high], or normal (mean, std) clipped to [low, high]."""

    kind: str
    low: float = -math.inf
    high: float = math.inf
    mean: float = 0.0
    std: float = 0.0

    def draw(self, rng: np.random.Generator) -> float:
        """One value."""
        if self.kind == "uniform":
            return float(rng.uniform(self.low, self.high))
        return float(np.clip(rng.normal(self.mean, self.std), self.low, self.high))


@dataclass(frozen=True, slots=True)
class Parameter:
    """One swept parameter.

    Attributes:
        name: its column in the results.
        paths: where its value goes (one value, several places: e.g. every load-driving eta_l).
        mode: `set` (the value replaces the base value), `scale` (base times value), `offset`
            (base plus value), `blend` (base + value (to - base): 0 is the base, 1 is `to`).
        to: the blend's end.
        values: a grid parameter's values (None for a random one).
        distribution: a random parameter's distribution (None for a grid one).
    """

    name: str
    paths: tuple[str, ...]
    mode: str = "set"
    to: float | None = None
    values: tuple[Scalar, ...] | None = None
    distribution: Distribution | None = None


@dataclass(frozen=True, slots=True)
class Trajectories:
    """Downsampled trajectories to keep: every `every_s` seconds, of these axes."""

    every_s: float
    axes: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class SweepSpec:
    """A validated sweep spec (see the module docstring)."""

    source: str
    kind: str
    base: Mapping[str, Any]
    parameters: tuple[Parameter, ...]
    sampling: str
    samples: int
    seed: int
    metrics: tuple[MetricSpec, ...]
    trajectories: Trajectories | None
    plot: Mapping[str, Any] = field(default_factory=dict)
    description: str = ""

    @property
    def n_points(self) -> int:
        """How many points the sweep has."""
        if self.sampling == "random":
            return self.samples
        return math.prod(len(p.values or ()) for p in self.parameters)


def _grid_values(raw: Mapping[str, Any], source: str, where: str) -> tuple[Scalar, ...]:
    if "values" in raw:
        return _listed_values(raw["values"], source, where)
    return _range_values(raw["range"], source, where)


def _listed_values(values: object, source: str, where: str) -> tuple[Scalar, ...]:
    if not isinstance(values, list) or not values:
        raise ConfigError(source, f"{where}.values", "expected a non-empty list")
    kinds = {"number" if is_number(v) else type(v).__name__ for v in values}
    if len(kinds) != 1 or not kinds <= {"number", "str", "bool"}:
        raise ConfigError(
            source, f"{where}.values", "expected numbers, strings or booleans, one kind"
        )
    if kinds != {"number"}:
        return tuple(values)
    numbers = [finite_number(v, source, f"{where}.values[{i}]") for i, v in enumerate(values)]
    if all(isinstance(v, int) for v in values):
        return tuple(int(v) for v in values)
    return tuple(numbers)


def _range_values(raw: object, source: str, where: str) -> tuple[Scalar, ...]:
    rng = mapping_of(raw, source, f"{where}.range", "{start, stop, num[, log]}")
    check_keys(rng, ("start", "stop", "num", "log"), source, f"{where}.range")
    for key in ("start", "stop", "num"):
        if key not in rng:
            raise ConfigError(source, f"{where}.range.{key}", "missing")
    start = finite_number(rng["start"], source, f"{where}.range.start")
    stop = finite_number(rng["stop"], source, f"{where}.range.stop")
    num = rng["num"]
    if not isinstance(num, int) or isinstance(num, bool) or num < 1:
        raise ConfigError(
            source, f"{where}.range.num", f"expected a whole number >= 1, got {num!r}"
        )
    log = rng.get("log", False)
    if not isinstance(log, bool):
        raise ConfigError(source, f"{where}.range.log", "expected true or false")
    if log:
        if start <= 0.0 or stop <= 0.0:
            raise ConfigError(source, f"{where}.range", "expected start, stop > 0 with log: true")
        return tuple(float(v) for v in np.geomspace(start, stop, num))
    return tuple(float(v) for v in np.linspace(start, stop, num))


def _distribution(raw: object, source: str, where: str) -> Distribution:
    d = mapping_of(raw, source, where, "{kind: uniform|normal, ...}")
    kind = d.get("kind")
    if kind not in DISTRIBUTIONS:
        raise ConfigError(source, f"{where}.kind", f"expected one of {', '.join(DISTRIBUTIONS)}")
    if kind == "uniform":
        check_keys(d, ("kind", "low", "high"), source, where)
        for key in ("low", "high"):
            if key not in d:
                raise ConfigError(source, f"{where}.{key}", "missing")
        low, high = (finite_number(d[k], source, f"{where}.{k}") for k in ("low", "high"))
        if not low < high:
            raise ConfigError(source, f"{where}.high", "expected high > low")
        return Distribution("uniform", low=low, high=high)
    check_keys(d, ("kind", "mean", "std", "low", "high"), source, where)
    for key in ("mean", "std"):
        if key not in d:
            raise ConfigError(source, f"{where}.{key}", "missing")
    mean = finite_number(d["mean"], source, f"{where}.mean")
    std = finite_number(d["std"], source, f"{where}.std")
    if std < 0.0:
        raise ConfigError(source, f"{where}.std", "expected std >= 0")
    low = finite_number(d["low"], source, f"{where}.low") if "low" in d else -math.inf
    high = finite_number(d["high"], source, f"{where}.high") if "high" in d else math.inf
    if not low < high:
        raise ConfigError(source, f"{where}.high", "expected high > low")
    return Distribution("normal", low=low, high=high, mean=mean, std=std)


def _paths(p: Mapping[str, Any], kind: str, source: str, where: str) -> tuple[str, ...]:
    if ("path" in p) == ("paths" in p):
        raise ConfigError(source, f"{where}.path", "expected either path: or paths:")
    paths_raw = [p["path"]] if "path" in p else p["paths"]
    key = f"{where}.path" if "path" in p else f"{where}.paths"
    if not isinstance(paths_raw, list) or not paths_raw:
        raise ConfigError(source, key, "expected a list of dotted paths")
    for path in paths_raw:
        if not isinstance(path, str) or not all(path.split(".")):
            raise ConfigError(source, key, f"expected a dotted path, got {path!r}")
        if path in FILE_PATHS:
            raise ConfigError(
                source,
                key,
                f"{path} names a file the sweep reads once, before the points: vary what is "
                f"in it ({FILE_PATHS[path]}) or run one sweep per file",
            )
        root = path.split(".")[0]
        if root not in ROOTS_OF_KIND[kind]:
            raise ConfigError(
                source,
                key,
                f"{path}: expected a path into {', '.join(ROOTS_OF_KIND[kind])} (a {kind} run)",
            )
    return tuple(paths_raw)


def _values(
    p: Mapping[str, Any], mode: str, source: str, where: str
) -> tuple[tuple[Scalar, ...] | None, Distribution | None]:
    given = [k for k in ("values", "range", "distribution") if k in p]
    if len(given) != 1:
        raise ConfigError(source, where, "expected exactly one of values, range, distribution")
    values = distribution = None
    if given[0] == "distribution":
        distribution = _distribution(p["distribution"], source, f"{where}.distribution")
    else:
        values = _grid_values(p, source, where)
        if mode != "set" and not all(is_number(v) for v in values):
            raise ConfigError(source, f"{where}.values", f"expected numbers with mode: {mode}")
    return values, distribution


def _parameter(raw: object, index: int, kind: str, source: str) -> Parameter:
    where = f"parameters[{index}]"
    p = mapping_of(raw, source, where, "a mapping with name, path(s) and values")
    allowed = ("name", "path", "paths", "mode", "to", "values", "range", "distribution")
    check_keys(p, allowed, source, where)
    name = p.get("name")
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(source, f"{where}.name", f"expected a column name, got {name!r}")
    paths = _paths(p, kind, source, where)
    mode = p.get("mode", "set")
    if mode not in MODES:
        raise ConfigError(
            source, f"{where}.mode", f"expected one of {', '.join(MODES)}, got {mode!r}"
        )
    to = None
    if mode == "blend":
        if "to" not in p:
            raise ConfigError(source, f"{where}.to", "missing (the value blend: 1 reaches)")
        to = finite_number(p["to"], source, f"{where}.to")
    elif "to" in p:
        raise ConfigError(source, f"{where}.to", "only with mode: blend")
    values, distribution = _values(p, mode, source, where)
    return Parameter(name, paths, mode, to, values, distribution)


def _base(top: Mapping[str, Any], source: str) -> tuple[str, Mapping[str, Any]]:
    base = mapping_of(top.get("base"), source, "base", "the base run: {kind: ..., robot: ...}")
    kind = base.get("kind")
    if kind not in KINDS:
        raise ConfigError(source, "base.kind", f"expected one of {', '.join(KINDS)}, got {kind!r}")
    check_keys(base, BASE_KEYS[kind], source, "base")
    if "payload" in base:
        payload = mapping_of(base["payload"], source, "base.payload", "{link, mass_kg, xyz_m}")
        check_keys(payload, PAYLOAD_KEYS, source, "base.payload")
    axis = base.get("axis")
    if axis is not None and not isinstance(axis, str):
        raise ConfigError(source, "base.axis", "expected an axis name")
    return str(kind), base


def _sampling(
    top: Mapping[str, Any], parameters: tuple[Parameter, ...], source: str
) -> tuple[str, int, int]:
    """(sampling, samples, seed)."""
    sampling = top.get("sampling", "random" if any(p.distribution for p in parameters) else "grid")
    if sampling not in ("grid", "random"):
        raise ConfigError(source, "sampling", f"expected grid or random, got {sampling!r}")
    for i, p in enumerate(parameters):
        if (sampling == "random") != (p.distribution is not None):
            want = "distribution:" if sampling == "random" else "values: or range:"
            raise ConfigError(source, f"parameters[{i}]", f"expected {want} in a {sampling} sweep")
    samples = top.get("samples", 1 if sampling == "grid" else None)
    if sampling == "random" and (
        not isinstance(samples, int) or isinstance(samples, bool) or samples < 1
    ):
        raise ConfigError(source, "samples", f"expected a whole number >= 1, got {samples!r}")
    if sampling == "grid" and "samples" in top:
        raise ConfigError(source, "samples", "only in a random sweep")
    seed = top.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(source, "seed", f"expected a whole number >= 0, got {seed!r}")
    return str(sampling), int(samples), seed


def _check_columns(
    parameters: tuple[Parameter, ...], metrics: tuple[MetricSpec, ...], source: str
) -> None:
    names = [p.name for p in parameters]
    columns = [*names, *(m.name for m in metrics)]
    reserved = {"index", "seed", "key", "status", "error"}
    for i, column in enumerate(columns):
        where = f"parameters[{i}].name" if i < len(names) else f"metrics[{i - len(names)}].name"
        if column in reserved or column in columns[:i]:
            raise ConfigError(source, where, f"{column!r} is taken (columns must be distinct)")


def _trajectories(raw: object, axis: object, source: str) -> Trajectories | None:
    if raw is None:
        return None
    t = mapping_of(raw, source, "trajectories", "{every_s, axes}")
    check_keys(t, ("every_s", "axes"), source, "trajectories")
    every = finite_number(t.get("every_s"), source, "trajectories.every_s")
    if every <= 0.0:
        raise ConfigError(source, "trajectories.every_s", "expected > 0")
    axes = t.get("axes", [axis] if axis else None)
    if not isinstance(axes, list) or not all(isinstance(a, str) for a in axes):
        raise ConfigError(source, "trajectories.axes", "expected a list of axis names")
    return Trajectories(every, tuple(axes))


def parse_spec(data: object, source: str) -> SweepSpec:
    """Validate a sweep spec document (the paths are checked later, on the documents).

    Raises:
        ConfigError: the first bad key, and what was expected.
    """
    top = mapping_of(data, source, "", "a sweep spec (a mapping with base, parameters, metrics)")
    check_keys(top, SPEC_KEYS, source, "")
    kind, base = _base(top, source)
    raw_parameters = top.get("parameters", [])
    if not isinstance(raw_parameters, list):
        raise ConfigError(source, "parameters", "expected a list")
    parameters = tuple(_parameter(p, i, kind, source) for i, p in enumerate(raw_parameters))
    sampling, samples, seed = _sampling(top, parameters, source)
    raw_metrics = top.get("metrics")
    if not isinstance(raw_metrics, list) or not raw_metrics:
        raise ConfigError(source, "metrics", "expected a non-empty list of metrics")
    axis = base.get("axis")
    metrics = tuple(
        parse_metric(m, source, f"metrics[{i}]", axis) for i, m in enumerate(raw_metrics)
    )
    _check_columns(parameters, metrics, source)
    plot = mapping_of(top.get("plot", {}), source, "plot", "a mapping")
    check_keys(plot, ("mark", "lines_by", "degrees"), source, "plot")
    description = top.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(source, "description", "expected text")
    spec = SweepSpec(
        source=source,
        kind=kind,
        base=base,
        parameters=parameters,
        sampling=sampling,
        samples=samples,
        seed=seed,
        metrics=metrics,
        trajectories=_trajectories(top.get("trajectories"), axis, source),
        plot=plot,
        description=description,
    )
    if spec.n_points > MAX_POINTS:
        raise ConfigError(source, "parameters", f"{spec.n_points} points; at most {MAX_POINTS}")
    return spec
