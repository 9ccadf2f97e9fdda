"""A sweep's points and each point's documents: the base documents with its values in place.

A parameter's path starts at one of the run's documents (`ROOTS`): `base` (the spec's base
block), `robot` (the robot YAML, after its `base:` merge), `controller` and `simulator` (the
nodes' parameters, closed loop), `faults` (the closed loop's fault schedule entries, by index:
`faults.0.start_s`), `scenario` (the open-loop scenario YAML). Below the root, a mapping is
entered by key, a list by index or, for a list of named items (the robot's axes), by name. A
node parameter is one dotted name, as ROS 2 has it (`simulator.faults.pivot.jam`). Every path
must exist in the base documents, except a node parameter left at its default, a base key left
at its default, and an axis without its own `efficiency` table (it takes a copy of the robot's,
so `robot.axes.pivot.efficiency...` changes the pivot's alone). docs/sweeps.md has the rest.

Grid sweeps take the product of the parameters' values (the last varies fastest); random
sweeps draw point i from the generator seeded with (seed, i), so a point's values do not depend
on how many points there are or where it runs. Pure: no files, no clock.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lca_sim.batch.checks import is_number
from lca_sim.batch.spec import BASE_KEYS, NODE_ROOTS, ROOTS, Parameter, Scalar, SweepSpec
from lca_sim.errors import ConfigError


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
            raise ConfigError(source, where, f"{trail}: no key {part!r} (valid: {valid})")
        return node[part]
    if isinstance(node, list):
        if part.isdigit() and int(part) < len(node):
            return node[int(part)]
        named = [item.get("name") for item in node if isinstance(item, Mapping)]
        if part in named:
            return node[named.index(part)]
        valid = ", ".join(map(str, named))
        raise ConfigError(source, where, f"{trail}: no item {part!r} (valid: {valid})")
    raise ConfigError(source, where, f"{trail}: {part!r} is below a value, not a mapping or list")


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
    if not is_number(base_value):
        raise ConfigError(source, where, f"{trail}: mode {parameter.mode} needs a number there")
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
                raise ConfigError(spec.source, where, f"{trail}: not a mapping")
            # a base key the block leaves at its default
            may_add = len(parts) == 1 and root == "base" and last in BASE_KEYS[spec.kind]
            if last not in node and not may_add:
                raise ConfigError(
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
