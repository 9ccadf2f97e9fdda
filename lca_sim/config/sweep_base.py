"""The files a sweep spec's `base:` names, read as `lca-hil run` reads them (docs/sweeps.md).

Each is a shipped name or a path from the spec's folder (`file_ref`); the nodes' params files
default to config/ros/*.yaml, the robot to the simulator's `robot`, the fault schedule to the
simulator's `fault_schedule`, so a closed-loop point runs what `lca-hil run` would run with the
same files. `lca_sim.batch.plan` puts them together into a sweep's documents.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lca_sim.config.loader import file_ref, read_robot_document, resolve
from lca_sim.config.params_file import node_parameters
from lca_sim.config.paths import config_dir
from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import ConfigError
from lca_sim.model.fault_schedule import schedule_entries
from lca_sim.model.faults import FAULT_SCHEDULE


def base_node_files(
    base: Mapping[str, Any], spec_path: Path
) -> tuple[dict[str, Any], dict[str, Any], Path]:
    """The controller's and the simulator's parameters (by dotted name), and the latter's file.

    `base.controller` and `base.simulator`, else the shipped config/ros/*.yaml.

    Raises:
        ConfigError: a missing or unreadable params file.
    """
    ros = config_dir() / "ros"
    controller_path = (
        file_ref(base["controller"], spec_path, "ros", "base.controller")
        if "controller" in base
        else ros / "controller.yaml"
    )
    simulator_path = (
        file_ref(base["simulator"], spec_path, "ros", "base.simulator")
        if "simulator" in base
        else ros / "simulator.yaml"
    )
    controller = node_parameters(controller_path, "controller")
    simulator = node_parameters(simulator_path, "simulator")
    return controller, simulator, simulator_path


def base_fault_schedule(
    base: Mapping[str, Any], simulator: Mapping[str, Any], spec_path: Path, simulator_path: Path
) -> tuple[tuple[Any, ...], str]:
    """A closed-loop run's fault schedule entries and file: `base.faults`, else the simulator's.

    `base.faults` (a shipped name in config/faults/ or a path from the spec's folder) wins over
    the simulator params file's `fault_schedule`, as `lca-hil run --faults` does. The entries
    are checked against the robot when each point is built
    (`lca_sim.batch.closed_loop_config.closed_loop_builder`).

    Raises:
        ConfigError: a missing file, or one that is not a schedule (a mapping with a list).
    """
    if "faults" in base:
        path = file_ref(base["faults"], spec_path, "faults", "base.faults")
    elif simulator.get(FAULT_SCHEDULE):
        ref = simulator[FAULT_SCHEDULE]
        if not isinstance(ref, str):
            raise ConfigError(str(simulator_path), FAULT_SCHEDULE, "expected a schedule's name")
        path = resolve(ref, "faults")
    else:
        return (), ""
    return tuple(schedule_entries(read_yaml(path), str(path))), str(path)


def base_scenario(base: Mapping[str, Any], spec_path: Path) -> Mapping[str, Any]:
    """An open-loop sweep's scenario document (`base.scenario`), unparsed.

    Raises:
        ConfigError: no `base.scenario`, or a file that is not a scenario document.
    """
    if "scenario" not in base:
        raise ConfigError(str(spec_path), "base.scenario", "missing (an open-loop scenario)")
    scenario = read_yaml(file_ref(base["scenario"], spec_path, "scenarios", "base.scenario"))
    if not isinstance(scenario, Mapping):
        raise ConfigError(str(spec_path), "base.scenario", "expected a scenario document")
    return scenario


def base_robot(
    base: Mapping[str, Any], simulator: Mapping[str, Any], spec_path: Path
) -> tuple[str, Mapping[str, Any]]:
    """The robot's URDF text and its document (after its `base:` merge).

    `base.robot` (a shipped name or a path from the spec's folder); else, closed loop, the
    simulator params' `robot`, as the node and `lca-hil run` take it; else `default`.

    Raises:
        ConfigError: a missing or unreadable robot or URDF.
    """
    if "robot" in base:
        robot_path = file_ref(base["robot"], spec_path, "robots", "base.robot")
    elif isinstance(simulator.get("robot"), str) and simulator["robot"]:
        robot_path = resolve(simulator["robot"], "robots")
    else:
        robot_path = resolve("default", "robots")
    robot_doc, urdf_xml = read_robot_document(robot_path)
    return urdf_xml, robot_doc
