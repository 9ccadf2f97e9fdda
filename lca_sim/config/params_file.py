"""A ROS 2 params file read as rcl reads it: a node's `ros__parameters` by dotted name.

`lca-hil run` and the closed-loop sweeps read the nodes' params files (config/ros/*.yaml) here
and check the values with the nodes' own validation, so what a node refuses is refused with
the same words, named by its file.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lca_control.controller import validate_controller_params
from lca_control.parameters import ParameterError
from lca_sim.config.ros_params import PARAMS_KEY
from lca_sim.config.simulator_params import SimulatorNodeParams, validate_simulator_params
from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import ConfigError
from lca_sim.model.faults import is_fault_parameter


def node_parameters(path: Path, node: str) -> dict[str, Any]:
    """The `ros__parameters` of `node` (or of `/**`) in a ROS 2 params file, by dotted name.

    A nested mapping is a group of parameters, as ROS 2 reads the file:
    `faults: {pivot: {jam: true}}` is the parameter `faults.pivot.jam`.

    Raises:
        ConfigError: the file, and what is missing.
    """
    document = read_yaml(path)
    if not isinstance(document, Mapping):
        raise ConfigError(str(path), "", "expected a ROS 2 params file (a mapping)")
    for key in (node, f"/{node}", "/**"):
        section = document.get(key)
        if isinstance(section, Mapping) and isinstance(section.get(PARAMS_KEY), Mapping):
            return _dotted(section[PARAMS_KEY], "")
    raise ConfigError(str(path), node, f"expected {node}: {PARAMS_KEY}: (the node's parameters)")


def _dotted(group: Mapping[str, Any], prefix: str) -> dict[str, Any]:
    """A parameter group's values by dotted name (rcl's params-file reading)."""
    values: dict[str, Any] = {}
    for key, value in group.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            values.update(_dotted(value, f"{name}."))
        else:
            values[name] = value
    return values


def plant_params(simulator_values: Mapping[str, Any]) -> SimulatorNodeParams:
    """The simulator node's typed params; its `faults.*` parameters are the fault injector's.

    Raises:
        ParameterError: a bad value, named as the node's parameter.
    """
    plant_values = {k: v for k, v in simulator_values.items() if not is_fault_parameter(k)}
    return validate_simulator_params(plant_values)


def in_file(path: Path, node: str, exc: ParameterError) -> ConfigError:
    """A node's refusal of a value, as a ConfigError naming the params file and the key."""
    return ConfigError(str(path), f"{node}.{PARAMS_KEY}.{exc.name}", str(exc).split(": ", 1)[1])


def read_node_files(
    controller_path: Path, simulator_path: Path
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The controller's and the simulator's parameters, each checked as its node checks them.

    Raises:
        ConfigError: the file, the parameter and what was expected.
    """
    controller_values = node_parameters(controller_path, "controller")
    simulator_values = node_parameters(simulator_path, "simulator")
    try:
        validate_controller_params(controller_values)
    except ParameterError as exc:
        raise in_file(controller_path, "controller", exc) from exc
    try:
        plant_params(simulator_values)
    except ParameterError as exc:
        raise in_file(simulator_path, "simulator", exc) from exc
    return controller_values, simulator_values


def read_params_document(path: Path) -> dict[str, Any]:
    """A params file as written (node sections, nesting kept), for a tool that rewrites it.

    Raises:
        ConfigError: the file is missing, not YAML, or not a mapping.
    """
    document = read_yaml(path)
    if not isinstance(document, dict):
        raise ConfigError(str(path), "", "expected a controller params mapping")
    return document


def with_parameters(
    document: Mapping[str, Any], values: Mapping[str, Any], node: str
) -> dict[str, Any]:
    """`document` with `values` set in its first node's `ros__parameters` (or in `node`'s)."""
    rewritten = dict(document)
    name = next(iter(rewritten)) if rewritten else node
    section = dict(rewritten.get(name, {}))
    section[PARAMS_KEY] = {**section.get(PARAMS_KEY, {}), **values}
    rewritten[name] = section
    return rewritten
