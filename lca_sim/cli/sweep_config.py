"""A sweep read from its files: the spec, the documents it names, every point's task.

The files are read as `lca-hil run` reads a closed-loop run (`lca_sim.cli.run`: the nodes'
params files, the shipped names, the nodes' own parameter validation), so a closed-loop point
runs what `lca-hil run` would run with the same files.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lca_control.parameters import ParameterError
from lca_sim.analysis.closed_loop import ClosedLoopConfig
from lca_sim.batch.point import Documents
from lca_sim.batch.runner import SweepPlan, run_plan
from lca_sim.batch.spec import SweepSpec, parse_spec
from lca_sim.batch.tasks import build_tasks
from lca_sim.batch.version import package_version
from lca_sim.cli.run import closed_loop_config, file_ref, node_parameters
from lca_sim.config.loader import config_dir, read_robot_document, read_yaml, resolve
from lca_sim.config.simulator_params import validate_simulator_params
from lca_sim.errors import ConfigError
from lca_sim.model.fault_schedule import parse_fault_schedule, schedule_entries, standing_faults
from lca_sim.model.faults import FAULT_SCHEDULE, is_fault_parameter
from lca_sim.model.params import RobotParams


def load_spec(spec_path: Path) -> tuple[SweepSpec, Documents]:
    """The validated spec and the base documents it names.

    Raises:
        ConfigError: the spec (or a file it names), the key, what was expected.
    """
    spec = parse_spec(read_yaml(spec_path), str(spec_path))
    base = spec.base
    controller: dict[str, Any] = {}
    simulator: dict[str, Any] = {}
    scenario: Any = {}
    faults: tuple[Any, ...] = ()
    faults_source = ""
    ros = config_dir() / "ros"
    if spec.kind == "closed_loop":
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
        faults, faults_source = _fault_schedule(base, simulator, spec_path, simulator_path)
    if spec.kind == "open_loop":
        if "scenario" not in base:
            raise ConfigError(spec.source, "base.scenario", "missing (an open-loop scenario)")
        scenario = read_yaml(file_ref(base["scenario"], spec_path, "scenarios", "base.scenario"))
        if not isinstance(scenario, Mapping):
            raise ConfigError(spec.source, "base.scenario", "expected a scenario document")
    urdf_xml, robot_doc = _robot(base, simulator, spec_path)
    documents = Documents(
        base=dict(base),
        robot=dict(robot_doc),
        urdf_xml=urdf_xml,
        controller=controller,
        simulator=simulator,
        scenario=dict(scenario),
        faults=faults,
        faults_source=faults_source,
    )
    return spec, documents


def _robot(
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


def _fault_schedule(
    base: Mapping[str, Any], simulator: Mapping[str, Any], spec_path: Path, simulator_path: Path
) -> tuple[tuple[Any, ...], str]:
    """A closed-loop run's fault schedule entries and file: `base.faults`, else the simulator's.

    `base.faults` (a shipped name in config/faults/ or a path from the spec's folder) wins over
    the simulator params file's `fault_schedule`, as `lca-hil run --faults` does. The entries
    are checked against the robot when each point is built (`closed_loop_builder`).

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


def closed_loop_builder(documents: Documents, robot: RobotParams) -> ClosedLoopConfig:
    """A closed-loop point's config: the nodes' parameters validated as the nodes do.

    The spec's robot replaces the simulator's `robot`; `base.duration_s` (default: the
    simulator's `lockstep_end_s`) is the run's length. The faults are those `lca-hil run`
    applies: the simulator's standing `faults.<joint>.<kind>` values and the schedule
    (`_fault_schedule`), each entry checked against the point's robot.

    Raises:
        ParameterError: a node parameter the node would refuse (a fault value included).
        ConfigError: a bad schedule entry, named by its file and key.
    """
    plant_values = {k: v for k, v in documents.simulator.items() if not is_fault_parameter(k)}
    simulator = validate_simulator_params(plant_values)
    duration = documents.base.get("duration_s", simulator.lockstep_end_s)
    if isinstance(duration, bool) or not isinstance(duration, int | float) or duration <= 0:
        raise ParameterError("duration_s", "a run's length > 0 (base.duration_s)", duration)
    config = closed_loop_config(
        documents.controller, documents.simulator, float(duration), robot=robot
    )
    faults = standing_faults(documents.simulator, robot.axis_names)
    if documents.faults:
        schedule = {"faults": list(documents.faults)}
        faults += parse_fault_schedule(schedule, documents.faults_source, robot.axis_names)
    return dataclasses.replace(config, faults=faults) if faults else config


def plan_sweep(spec_path: Path) -> SweepPlan:
    """The sweep of a spec file, validated whole: every point's task built before any runs.

    Raises:
        ConfigError: a bad spec, a file it names, or a bad point (its key and values).
    """
    start = time.perf_counter()
    version = package_version()
    spec, documents = load_spec(spec_path)
    tasks = build_tasks(spec, documents, version, closed_loop_builder)
    return SweepPlan(spec_path, spec, tuple(tasks), version, time.perf_counter() - start)


def run_sweep(spec_path: Path, out: Path, **options: Any) -> dict[str, Any]:
    """Run the sweep of a spec file into `out`; returns the run log.

    `options` are `lca_sim.batch.runner.run_plan`'s (scheduler, workers, stream, function,
    client).

    Raises:
        ConfigError: a bad spec, before anything runs.
    """
    return run_plan(plan_sweep(spec_path), out, **options)
