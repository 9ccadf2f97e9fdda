"""Sweep specs: the validated form of a sweep YAML, its points, and each point's configuration.

A spec (docs/sweeps.md has the whole format) names a base run, the parameters to vary and the
metrics to compute:

    base:
      kind: open_loop                  # closed_loop | open_loop | current_step
      robot: default
      scenario: fig9_open_loop_pivot
    # closed_loop also takes faults: a fault schedule (docs/faults.md) on the run
    parameters:
      - name: wear
        paths: [robot.axes.pivot.efficiency.load_driving.direct.eta_l]
        mode: blend                    # set | scale | offset | blend (towards `to`)
        to: 1.0
        values: [0.0, 0.5, 0.9]        # or range: {start, stop, num}, or distribution: {...}
    metrics:
      - {metric: peak_current_a, axis: pivot}

A parameter's path starts at one of the run's documents (`ROOTS`): `base` (the spec's base
block), `robot` (the robot YAML, after its `base:` merge), `controller` and `simulator` (the
nodes' parameters, closed loop), `faults` (the entries of the closed loop's fault schedule, by
index: `faults.0.start_s`), `scenario` (the open-loop scenario YAML). Below the root, a
mapping is entered by key, a list by index or, for a list of named items (the robot's axes),
by name. A node parameter is one dotted name, as ROS 2 has it: `simulator.faults.pivot.jam` is
the simulator's parameter `faults.pivot.jam` (a standing fault), `simulator.initial_position.1`
the second item of its `initial_position`. Every path must exist in the base documents, with
three exceptions: a node parameter the params file leaves at its default (`controller.*`,
`simulator.*`: the node's validation then names an unknown one), a base key the block leaves at
its default, and an axis without its own `efficiency` table, which takes the robot's top-level
one (that is what the robot file means), so `robot.axes.pivot.efficiency...` changes the
pivot's alone.

Grid sweeps take the product of the parameters' values (the last parameter varies fastest);
random sweeps draw `samples` points, point i from the generator seeded with (seed, i), the
parameters in their order, so a point's values do not depend on how many points there are or
where it runs.

Pure: the CLI reads the files and hands the documents in.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lca_sim.analysis.metrics import MetricSpec, parse_metric
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


@dataclass(frozen=True, slots=True)
class Point:
    """One point of a sweep: its index, its seed, and its parameters' values (spec order)."""

    index: int
    seed: int
    values: tuple[tuple[str, Scalar], ...]


@dataclass(frozen=True, slots=True)
class Documents:
    """The documents a run is configured from (plain data, as the YAML files hold it).

    Attributes:
        base: the spec's base block (file references resolved by the CLI, left as given).
        robot: the robot document after its `base:` merge.
        urdf_xml: the gantry URDF the robot names.
        controller, simulator: the nodes' parameters, dotted names as ROS 2 flattens them
            (closed loop; empty otherwise).
        faults: the entries of the closed loop's fault schedule (`base.faults`, else the
            simulator's `fault_schedule`), as its file lists them; empty without one.
        faults_source: that schedule's file, for its errors.
        scenario: the open-loop scenario document (empty otherwise).
    """

    base: Mapping[str, Any]
    robot: Mapping[str, Any]
    urdf_xml: str
    controller: Mapping[str, Any] = field(default_factory=dict)
    simulator: Mapping[str, Any] = field(default_factory=dict)
    scenario: Mapping[str, Any] = field(default_factory=dict)
    faults: tuple[Any, ...] = ()
    faults_source: str = ""

    def root(self, name: str) -> Any:
        """The document a path's first part names (a mapping; a list for `faults`)."""
        return getattr(self, name)


# --- parsing -----------------------------------------------------------------------------------


def _fail(source: str, key: str, expected: str) -> ConfigError:
    return ConfigError(source, key, expected)


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _finite(value: object, source: str, key: str) -> float:
    if not _is_number(value) or not math.isfinite(float(value)):  # type: ignore[arg-type]
        raise _fail(source, key, f"expected a finite number, got {value!r}")
    return float(value)  # type: ignore[arg-type]


def _mapping(value: object, source: str, key: str, what: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise _fail(source, key, f"expected {what}, got {value!r}")
    return value


def _unknown(raw: Mapping[str, Any], allowed: tuple[str, ...], source: str, where: str) -> None:
    for key in raw:
        if key not in allowed:
            prefix = f"{where}." if where else ""
            raise _fail(source, f"{prefix}{key}", f"unknown key (valid: {', '.join(allowed)})")


def _grid_values(raw: Mapping[str, Any], source: str, where: str) -> tuple[Scalar, ...]:
    if "values" in raw:
        return _listed_values(raw["values"], source, where)
    return _range_values(raw["range"], source, where)


def _listed_values(values: object, source: str, where: str) -> tuple[Scalar, ...]:
    if not isinstance(values, list) or not values:
        raise _fail(source, f"{where}.values", "expected a non-empty list")
    kinds = {"number" if _is_number(v) else type(v).__name__ for v in values}
    if len(kinds) != 1 or not kinds <= {"number", "str", "bool"}:
        raise _fail(source, f"{where}.values", "expected numbers, strings or booleans, one kind")
    if kinds != {"number"}:
        return tuple(values)
    numbers = [_finite(v, source, f"{where}.values[{i}]") for i, v in enumerate(values)]
    if all(isinstance(v, int) for v in values):
        return tuple(int(v) for v in values)
    return tuple(numbers)


def _range_values(raw: object, source: str, where: str) -> tuple[Scalar, ...]:
    rng = _mapping(raw, source, f"{where}.range", "{start, stop, num[, log]}")
    _unknown(rng, ("start", "stop", "num", "log"), source, f"{where}.range")
    for key in ("start", "stop", "num"):
        if key not in rng:
            raise _fail(source, f"{where}.range.{key}", "missing")
    start = _finite(rng["start"], source, f"{where}.range.start")
    stop = _finite(rng["stop"], source, f"{where}.range.stop")
    num = rng["num"]
    if not isinstance(num, int) or isinstance(num, bool) or num < 1:
        raise _fail(source, f"{where}.range.num", f"expected a whole number >= 1, got {num!r}")
    log = rng.get("log", False)
    if not isinstance(log, bool):
        raise _fail(source, f"{where}.range.log", "expected true or false")
    if log:
        if start <= 0.0 or stop <= 0.0:
            raise _fail(source, f"{where}.range", "expected start, stop > 0 with log: true")
        return tuple(float(v) for v in np.geomspace(start, stop, num))
    return tuple(float(v) for v in np.linspace(start, stop, num))


def _distribution(raw: object, source: str, where: str) -> Distribution:
    d = _mapping(raw, source, where, "{kind: uniform|normal, ...}")
    kind = d.get("kind")
    if kind not in DISTRIBUTIONS:
        raise _fail(source, f"{where}.kind", f"expected one of {', '.join(DISTRIBUTIONS)}")
    if kind == "uniform":
        _unknown(d, ("kind", "low", "high"), source, where)
        for key in ("low", "high"):
            if key not in d:
                raise _fail(source, f"{where}.{key}", "missing")
        low, high = (_finite(d[k], source, f"{where}.{k}") for k in ("low", "high"))
        if not low < high:
            raise _fail(source, f"{where}.high", "expected high > low")
        return Distribution("uniform", low=low, high=high)
    _unknown(d, ("kind", "mean", "std", "low", "high"), source, where)
    for key in ("mean", "std"):
        if key not in d:
            raise _fail(source, f"{where}.{key}", "missing")
    mean = _finite(d["mean"], source, f"{where}.mean")
    std = _finite(d["std"], source, f"{where}.std")
    if std < 0.0:
        raise _fail(source, f"{where}.std", "expected std >= 0")
    low = _finite(d["low"], source, f"{where}.low") if "low" in d else -math.inf
    high = _finite(d["high"], source, f"{where}.high") if "high" in d else math.inf
    if not low < high:
        raise _fail(source, f"{where}.high", "expected high > low")
    return Distribution("normal", low=low, high=high, mean=mean, std=std)


def _paths(p: Mapping[str, Any], kind: str, source: str, where: str) -> tuple[str, ...]:
    if ("path" in p) == ("paths" in p):
        raise _fail(source, f"{where}.path", "expected either path: or paths:")
    paths_raw = [p["path"]] if "path" in p else p["paths"]
    key = f"{where}.path" if "path" in p else f"{where}.paths"
    if not isinstance(paths_raw, list) or not paths_raw:
        raise _fail(source, key, "expected a list of dotted paths")
    for path in paths_raw:
        if not isinstance(path, str) or not all(path.split(".")):
            raise _fail(source, key, f"expected a dotted path, got {path!r}")
        if path in FILE_PATHS:
            raise _fail(
                source,
                key,
                f"{path} names a file the sweep reads once, before the points: vary what is "
                f"in it ({FILE_PATHS[path]}) or run one sweep per file",
            )
        root = path.split(".")[0]
        if root not in ROOTS_OF_KIND[kind]:
            raise _fail(
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
        raise _fail(source, where, "expected exactly one of values, range, distribution")
    values = distribution = None
    if given[0] == "distribution":
        distribution = _distribution(p["distribution"], source, f"{where}.distribution")
    else:
        values = _grid_values(p, source, where)
        if mode != "set" and not all(_is_number(v) for v in values):
            raise _fail(source, f"{where}.values", f"expected numbers with mode: {mode}")
    return values, distribution


def _parameter(raw: object, index: int, kind: str, source: str) -> Parameter:
    where = f"parameters[{index}]"
    p = _mapping(raw, source, where, "a mapping with name, path(s) and values")
    allowed = ("name", "path", "paths", "mode", "to", "values", "range", "distribution")
    _unknown(p, allowed, source, where)
    name = p.get("name")
    if not isinstance(name, str) or not name.isidentifier():
        raise _fail(source, f"{where}.name", f"expected a column name, got {name!r}")
    paths = _paths(p, kind, source, where)
    mode = p.get("mode", "set")
    if mode not in MODES:
        raise _fail(source, f"{where}.mode", f"expected one of {', '.join(MODES)}, got {mode!r}")
    to = None
    if mode == "blend":
        if "to" not in p:
            raise _fail(source, f"{where}.to", "missing (the value blend: 1 reaches)")
        to = _finite(p["to"], source, f"{where}.to")
    elif "to" in p:
        raise _fail(source, f"{where}.to", "only with mode: blend")
    values, distribution = _values(p, mode, source, where)
    return Parameter(name, paths, mode, to, values, distribution)


def _base(top: Mapping[str, Any], source: str) -> tuple[str, Mapping[str, Any]]:
    base = _mapping(top.get("base"), source, "base", "the base run: {kind: ..., robot: ...}")
    kind = base.get("kind")
    if kind not in KINDS:
        raise _fail(source, "base.kind", f"expected one of {', '.join(KINDS)}, got {kind!r}")
    _unknown(base, BASE_KEYS[kind], source, "base")
    if "payload" in base:
        payload = _mapping(base["payload"], source, "base.payload", "{link, mass_kg, xyz_m}")
        _unknown(payload, PAYLOAD_KEYS, source, "base.payload")
    axis = base.get("axis")
    if axis is not None and not isinstance(axis, str):
        raise _fail(source, "base.axis", "expected an axis name")
    return str(kind), base


def _sampling(
    top: Mapping[str, Any], parameters: tuple[Parameter, ...], source: str
) -> tuple[str, int, int]:
    """(sampling, samples, seed)."""
    sampling = top.get("sampling", "random" if any(p.distribution for p in parameters) else "grid")
    if sampling not in ("grid", "random"):
        raise _fail(source, "sampling", f"expected grid or random, got {sampling!r}")
    for i, p in enumerate(parameters):
        if (sampling == "random") != (p.distribution is not None):
            want = "distribution:" if sampling == "random" else "values: or range:"
            raise _fail(source, f"parameters[{i}]", f"expected {want} in a {sampling} sweep")
    samples = top.get("samples", 1 if sampling == "grid" else None)
    if sampling == "random" and (
        not isinstance(samples, int) or isinstance(samples, bool) or samples < 1
    ):
        raise _fail(source, "samples", f"expected a whole number >= 1, got {samples!r}")
    if sampling == "grid" and "samples" in top:
        raise _fail(source, "samples", "only in a random sweep")
    seed = top.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise _fail(source, "seed", f"expected a whole number >= 0, got {seed!r}")
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
            raise _fail(source, where, f"{column!r} is taken (columns must be distinct)")


def _trajectories(raw: object, axis: object, source: str) -> Trajectories | None:
    if raw is None:
        return None
    t = _mapping(raw, source, "trajectories", "{every_s, axes}")
    _unknown(t, ("every_s", "axes"), source, "trajectories")
    every = _finite(t.get("every_s"), source, "trajectories.every_s")
    if every <= 0.0:
        raise _fail(source, "trajectories.every_s", "expected > 0")
    axes = t.get("axes", [axis] if axis else None)
    if not isinstance(axes, list) or not all(isinstance(a, str) for a in axes):
        raise _fail(source, "trajectories.axes", "expected a list of axis names")
    return Trajectories(every, tuple(axes))


def parse_spec(data: object, source: str) -> SweepSpec:
    """Validate a sweep spec document (the paths are checked later, on the documents).

    Raises:
        ConfigError: the first bad key, and what was expected.
    """
    top = _mapping(data, source, "", "a sweep spec (a mapping with base, parameters, metrics)")
    _unknown(top, SPEC_KEYS, source, "")
    kind, base = _base(top, source)
    raw_parameters = top.get("parameters", [])
    if not isinstance(raw_parameters, list):
        raise _fail(source, "parameters", "expected a list")
    parameters = tuple(_parameter(p, i, kind, source) for i, p in enumerate(raw_parameters))
    sampling, samples, seed = _sampling(top, parameters, source)
    raw_metrics = top.get("metrics")
    if not isinstance(raw_metrics, list) or not raw_metrics:
        raise _fail(source, "metrics", "expected a non-empty list of metrics")
    axis = base.get("axis")
    metrics = tuple(
        parse_metric(m, source, f"metrics[{i}]", axis) for i, m in enumerate(raw_metrics)
    )
    _check_columns(parameters, metrics, source)
    plot = _mapping(top.get("plot", {}), source, "plot", "a mapping")
    _unknown(plot, ("mark", "lines_by", "degrees"), source, "plot")
    description = top.get("description", "")
    if not isinstance(description, str):
        raise _fail(source, "description", "expected text")
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
        raise _fail(source, "parameters", f"{spec.n_points} points; at most {MAX_POINTS}")
    return spec


# --- points ------------------------------------------------------------------------------------


def expand_points(spec: SweepSpec) -> tuple[Point, ...]:
    """Every point of the sweep, in index order (see the module docstring)."""
    if spec.sampling == "grid":
        grids = [p.values or () for p in spec.parameters]
        names = [p.name for p in spec.parameters]
        return tuple(
            Point(i, spec.seed, tuple(zip(names, combo, strict=True)))
            for i, combo in enumerate(itertools.product(*grids))
        )
    points = []
    for i in range(spec.samples):
        rng = np.random.default_rng([spec.seed, i])
        values = tuple(
            (p.name, p.distribution.draw(rng)) for p in spec.parameters if p.distribution
        )
        points.append(Point(i, spec.seed, values))
    return tuple(points)


def _step_into(node: Any, part: str, trail: str, source: str, where: str) -> Any:
    """The child `part` of a mapping or a list (by index or by item name)."""
    if isinstance(node, Mapping):
        if part not in node:
            valid = ", ".join(map(str, node))
            raise _fail(source, where, f"{trail}: no key {part!r} (valid: {valid})")
        return node[part]
    if isinstance(node, list):
        if part.isdigit() and int(part) < len(node):
            return node[int(part)]
        named = [item.get("name") for item in node if isinstance(item, Mapping)]
        if part in named:
            return node[named.index(part)]
        valid = ", ".join(map(str, named))
        raise _fail(source, where, f"{trail}: no item {part!r} (valid: {valid})")
    raise _fail(source, where, f"{trail}: {part!r} is below a value, not a mapping or list")


def _materialise_axis_efficiency(robot: dict[str, Any], parts: list[str]) -> None:
    """An axis path into `efficiency` gets a copy of the top-level table if it has none."""
    if len(parts) >= 3 and parts[0] == "axes" and parts[2] == "efficiency":
        axes = robot.get("axes")
        if isinstance(axes, list):
            for item in axes:
                named = isinstance(item, dict) and item.get("name") == parts[1]
                if named and "efficiency" not in item and "efficiency" in robot:
                    item["efficiency"] = copy.deepcopy(robot["efficiency"])


def _apply(
    value: Scalar, base_value: Any, parameter: Parameter, trail: str, source: str, where: str
) -> Any:
    if parameter.mode == "set":
        return value
    if not _is_number(base_value):
        raise _fail(source, where, f"{trail}: mode {parameter.mode} needs a number there")
    x, b = float(value), float(base_value)
    if parameter.mode == "scale":
        return b * x
    if parameter.mode == "offset":
        return b + x
    assert parameter.to is not None
    return b + x * (parameter.to - b)


def _set_node_parameter(
    node: dict[str, Any],
    parts: list[str],
    value: Scalar,
    parameter: Parameter,
    source: str,
    where: str,
) -> bool:
    """Set a node parameter named by the dotted rest of a path; False to walk the path instead.

    ROS 2 parameter names are flat and dotted (`faults.pivot.jam`), so the rest of the path is
    one name when the document has it, when it is one part (a parameter the file leaves at its
    default) or when it names a fault parameter; otherwise (`initial_position.1`) it is walked.
    """
    name = ".".join(parts)
    if name not in node and len(parts) > 1 and parts[0] != "faults":
        return False
    node[name] = _apply(value, node.get(name), parameter, name, source, where)
    return True


def apply_point(spec: SweepSpec, documents: Documents, point: Point) -> Documents:
    """The documents of one point: the base ones with the point's values in their places.

    Raises:
        ConfigError: `parameters[i].path`: a path the documents do not have.
    """
    roots: dict[str, Any] = {}
    for name in ROOTS:
        document = documents.root(name)
        roots[name] = copy.deepcopy(list(document) if name == "faults" else dict(document))
    values = dict(point.values)
    for i, parameter in enumerate(spec.parameters):
        where = f"parameters[{i}].path" + ("s" if len(parameter.paths) > 1 else "")
        for path in parameter.paths:
            root, *parts = path.split(".")
            document = roots[root]
            if root in NODE_ROOTS and _set_node_parameter(
                document, parts, values[parameter.name], parameter, spec.source, where
            ):
                continue
            if root == "robot":
                _materialise_axis_efficiency(document, parts)
            node: Any = document
            trail = root
            for part in parts[:-1]:
                node = _step_into(node, part, trail, spec.source, where)
                trail = f"{trail}.{part}"
            last = parts[-1]
            if isinstance(node, list):
                child = _step_into(node, last, trail, spec.source, where)
                index = node.index(child)
                node[index] = _apply(
                    values[parameter.name], child, parameter, path, spec.source, where
                )
                continue
            if not isinstance(node, dict):
                raise _fail(spec.source, where, f"{trail}: not a mapping")
            # a base key the block leaves at its default
            may_add = len(parts) == 1 and root == "base" and last in BASE_KEYS[spec.kind]
            if last not in node and not may_add:
                raise _fail(
                    spec.source,
                    where,
                    f"{trail}: no key {last!r} (valid: {', '.join(map(str, node))})",
                )
            node[last] = _apply(
                values[parameter.name], node.get(last), parameter, path, spec.source, where
            )
    return Documents(
        base=roots["base"],
        robot=roots["robot"],
        urdf_xml=documents.urdf_xml,
        controller=roots["controller"],
        simulator=roots["simulator"],
        scenario=roots["scenario"],
        faults=tuple(roots["faults"]),
        faults_source=documents.faults_source,
    )


def point_key(spec: SweepSpec, documents: Documents, version: str) -> str:
    """A hash of everything a point's result depends on, and of the package version.

    The resolved documents (so two specs that arrive at one configuration share the result),
    the URDF after the payload, the metrics and trajectories asked for, and `version`.
    """
    content = {
        "kind": spec.kind,
        "base": documents.base,
        "robot": documents.robot,
        "urdf_sha256": hashlib.sha256(documents.urdf_xml.encode()).hexdigest(),
        "controller": documents.controller,
        "simulator": documents.simulator,
        "scenario": documents.scenario,
        "faults": list(documents.faults),
        "metrics": [m.as_dict() for m in spec.metrics],
        "trajectories": (
            None
            if spec.trajectories is None
            else [spec.trajectories.every_s, list(spec.trajectories.axes)]
        ),
        "version": version,
    }
    text = json.dumps(content, sort_keys=True, default=repr, allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


# --- payload -----------------------------------------------------------------------------------


def _floats(text: str | None, n: int, what: str) -> list[float]:
    values = [float(x) for x in (text or " ".join(["0"] * n)).split()]
    if len(values) != n:
        raise ValueError(f"expected {n} numbers in {what}")
    return values


def add_payload(
    urdf_xml: str, link: str, mass_kg: float, xyz_m: tuple[float, float, float], source: str
) -> str:
    """The URDF with a point mass added to one link's inertial (mass, CoG, parallel axes).

    The combined body keeps the link's inertia about its own centre of mass, moved to the new
    centre of mass by the parallel-axis theorem, plus the point mass's m (|d|^2 E - d d^T).
    A zero mass returns the URDF unchanged.

    Raises:
        ConfigError: `base.payload.*`: an unknown link, a negative mass, a rotated inertial.
    """
    if mass_kg == 0.0:
        return urdf_xml
    if not (math.isfinite(mass_kg) and mass_kg > 0.0):
        raise _fail(source, "base.payload.mass_kg", f"expected a mass >= 0, got {mass_kg!r}")
    root = ET.fromstring(urdf_xml)
    links = {el.get("name"): el for el in root.iter("link")}
    if link not in links:
        names = ", ".join(str(n) for n in links)
        raise _fail(source, "base.payload.link", f"expected one of {names}, got {link!r}")
    inertial = links[link].find("inertial")
    if inertial is None:
        raise _fail(source, "base.payload.link", f"{link} has no inertial to add to")
    origin = inertial.find("origin")
    if origin is None:
        origin = ET.SubElement(inertial, "origin")
    if any(_floats(origin.get("rpy"), 3, "rpy")):
        raise _fail(source, "base.payload.link", f"{link}'s inertial is rotated (rpy != 0)")
    mass_el, inertia_el = inertial.find("mass"), inertial.find("inertia")
    if mass_el is None or inertia_el is None:
        raise _fail(source, "base.payload.link", f"{link}'s inertial lacks mass or inertia")
    m1 = float(mass_el.get("value", "0"))
    c1 = np.array(_floats(origin.get("xyz"), 3, "xyz"))
    ixx, ixy, ixz, iyy, iyz, izz = (
        float(inertia_el.get(k, "0")) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    )
    i1 = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    p = np.array(xyz_m, dtype=float)
    total = m1 + mass_kg
    c = (m1 * c1 + mass_kg * p) / total

    def shift(mass: float, d: np.ndarray) -> np.ndarray:
        return mass * (float(d @ d) * np.eye(3) - np.outer(d, d))

    inertia = i1 + shift(m1, c1 - c) + shift(mass_kg, p - c)
    mass_el.set("value", repr(total))
    origin.set("xyz", " ".join(repr(float(x)) for x in c))
    for (r, col), name in zip(
        ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
        ("ixx", "ixy", "ixz", "iyy", "iyz", "izz"),
        strict=True,
    ):
        inertia_el.set(name, repr(float(inertia[r, col])))
    return ET.tostring(root, encoding="unicode")


def payload_of(base: Mapping[str, Any], source: str) -> tuple[str, float, tuple[float, ...]] | None:
    """The base block's payload as (link, mass_kg, xyz_m), or None.

    Raises:
        ConfigError: `base.payload.*`: a missing or wrong value.
    """
    raw = base.get("payload")
    if raw is None:
        return None
    payload = _mapping(raw, source, "base.payload", "{link, mass_kg, xyz_m}")
    link = payload.get("link")
    if not isinstance(link, str):
        raise _fail(source, "base.payload.link", "expected a link name of the URDF")
    mass = _finite(payload.get("mass_kg"), source, "base.payload.mass_kg")
    xyz = payload.get("xyz_m", [0.0, 0.0, 0.0])
    if not isinstance(xyz, list) or len(xyz) != 3:
        raise _fail(source, "base.payload.xyz_m", "expected 3 numbers (m, in the link's frame)")
    return (
        link,
        mass,
        tuple(_finite(x, source, f"base.payload.xyz_m[{i}]") for i, x in enumerate(xyz)),
    )
