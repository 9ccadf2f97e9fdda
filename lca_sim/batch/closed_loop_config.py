"""The composed loop's config (`ClosedLoopConfig`) from the two nodes' parameter values.

One builder for `lca-hil run` (from the params files), `lca-hil fig15` and a closed-loop
sweep's points (from their documents): each value goes through the node's own validation, so
a point runs what `lca-hil run` would run with the same files.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lca_control.controller import validate_controller_params
from lca_control.parameters import ParameterError
from lca_sim.analysis.closed_loop import ClosedLoopConfig
from lca_sim.batch.point import Documents
from lca_sim.config.loader import load_robot
from lca_sim.config.params_file import plant_params, read_node_files
from lca_sim.config.simulator_params import plant_config
from lca_sim.model.fault_schedule import parse_fault_schedule, standing_faults
from lca_sim.model.params import RobotParams


def closed_loop_config(
    controller_values: Mapping[str, Any],
    simulator_values: Mapping[str, Any],
    duration_s: float | None = None,
    robot: RobotParams | None = None,
) -> ClosedLoopConfig:
    """The composed run of the two nodes started with these parameter values.

    Every value goes through the node's own validation, so what a node refuses is refused here
    with the same words. The simulator's `timing_mode` is ignored (this is the lockstep loop).

    Args:
        controller_values: the controller node's parameters (missing ones at their defaults).
        simulator_values: the simulator node's.
        duration_s: simulated time of the run; None takes the simulator's `lockstep_end_s`.
        robot: the robot in place of the simulator's `robot` (a sweep's varied one).

    Raises:
        ParameterError: a bad value, named as the node's parameter.
        ConfigError: a bad robot.
    """
    controller = validate_controller_params(controller_values)
    simulator = plant_params(simulator_values)
    if any(mode != simulator.command_interface for mode in simulator.joint_drive_modes):
        # The composed loop closes the position and velocity loops in the controller: a
        # simulator params file with drive modes would run here as if they were not there.
        raise ParameterError(
            "drive_modes",
            f"none, or {simulator.command_interface} for every joint (a composed run closes "
            "the loops in the controller; drive modes are the simulator node's)",
            list(simulator.drive_modes),
        )
    if duration_s is None:
        duration_s = simulator.lockstep_end_s
        if duration_s <= 0.0:
            raise ParameterError("lockstep_end_s", "a run's end > 0 (or --duration-s)", 0.0)
    return ClosedLoopConfig(
        plant=plant_config(simulator, load_robot(simulator.robot) if robot is None else robot),
        controller=controller,
        duration_s=duration_s,
        control_period_s=simulator.control_period_s,
        initial_position=simulator.initial_position,
    )


def load_config(
    controller_path: Path,
    simulator_path: Path,
    duration_s: float | None,
    robot: RobotParams | None = None,
) -> ClosedLoopConfig:
    """`closed_loop_config` from the two params files; a bad value names its file.

    Raises:
        ConfigError: the file, the parameter and what was expected.
    """
    controller_values, simulator_values = read_node_files(controller_path, simulator_path)
    return closed_loop_config(controller_values, simulator_values, duration_s, robot=robot)


def closed_loop_builder(documents: Documents, robot: RobotParams) -> ClosedLoopConfig:
    """A closed-loop point's config: the nodes' parameters validated as the nodes do.

    The spec's robot replaces the simulator's `robot`; `base.duration_s` (default: the
    simulator's `lockstep_end_s`) is the run's length. The faults are those `lca-hil run`
    applies: the simulator's standing `faults.<joint>.<kind>` values and the schedule
    (`lca_sim.config.sweep_base.base_fault_schedule`), each entry checked against the point's
    robot.

    Raises:
        ParameterError: a node parameter the node would refuse (a fault value included).
        ConfigError: a bad schedule entry, named by its file and key.
    """
    simulator = plant_params(documents.simulator)
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
