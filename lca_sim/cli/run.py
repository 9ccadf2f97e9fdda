"""`lca-hil run`: the closed loop of the controller and simulator nodes, in one process, no ROS.

    lca-hil run --out out/run                         # Fig. 15's ramp, 13 s
    lca-hil run fig15_encoder_freeze --out out/freeze # a closed-loop scenario (config/runs/)
    lca-hil run --controller-config my_gains.yaml --duration-s 5 --out out/gains

A closed-loop scenario is a small YAML file naming what a run is made of: `controller` and
`simulator` (the nodes' params files), `robot`, `faults` (a fault schedule) and `duration_s`,
each optional (the same keys as a closed-loop sweep's base, docs/sweeps.md); a file it names is
a shipped name or a path from the scenario's folder. The options override it.

Reads the two nodes' parameter files (config/ros/controller.yaml and simulator.yaml by default),
runs the composed loop (`lca_sim.analysis.closed_loop`): the same numbers as the lockstep run of
the two nodes over ROS 2 (`timing_mode` of the simulator's file is not used: the composed loop
is the lockstep one), and writes trajectory.csv (one row per control period, floats in shortest
round-trip form) and summary.json (strict JSON: duration, wall time, real-time factor, tracking
errors, drive-state changes).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lca_control.controller import validate_controller_params
from lca_control.parameters import ParameterError
from lca_sim.analysis.closed_loop import (
    ClosedLoop,
    ClosedLoopConfig,
    ClosedLoopResult,
    tracking_window,
)
from lca_sim.config.loader import (
    config_dir,
    load_fault_schedule,
    load_robot,
    read_yaml,
    resolve,
)
from lca_sim.config.simulator_params import validate_simulator_params
from lca_sim.errors import EXIT_OK, FILE_NOT_FOUND, ConfigError, run_guarded, unknown_key
from lca_sim.model.fault_schedule import standing_faults
from lca_sim.model.faults import FAULT_SCHEDULE, is_fault_parameter
from lca_sim.model.params import RobotParams
from lca_sim.output import number_cell, write_json, write_table

PROG = "lca-hil run"
SCENARIO_KEYS = ("description", "controller", "simulator", "robot", "faults", "duration_s")
DEFAULT_DURATION_S = 13.0  # Fig. 15: 1 s still, the 10 s ramp, 2 s after it
PARAMS_KEY = "ros__parameters"
MAX_LISTED_CHANGES = 50  # drive-state changes listed per joint in summary.json


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
    plant_values = {k: v for k, v in simulator_values.items() if not is_fault_parameter(k)}
    simulator = validate_simulator_params(plant_values)
    if duration_s is None:
        duration_s = simulator.lockstep_end_s
        if duration_s <= 0.0:
            raise ParameterError("lockstep_end_s", "a run's end > 0 (or --duration-s)", 0.0)
    interface = simulator.command_interface
    return ClosedLoopConfig(
        robot=load_robot(simulator.robot) if robot is None else robot,
        controller=controller,
        duration_s=duration_s,
        joints=simulator.joints,
        command_interface=interface,
        dt_s=simulator.dt_s,
        rigid_body_update_steps=simulator.rigid_body_update_steps,
        control_period_s=simulator.control_period_s,
        current_kp_v_per_a=simulator.current_kp_v_per_a,
        current_ti_s=simulator.current_ti_s,
        max_abs_command=(
            simulator.max_command_voltage_v
            if interface == "voltage"
            else simulator.max_command_current_a
        ),
        initial_position=simulator.initial_position,
        plant_enabled=simulator.enabled,
    )


def file_ref(ref: object, home: Path, kind: str, key: str) -> Path:
    """A shipped name (config/KIND/NAME.yaml) or a path from `home`'s folder, as a file.

    Raises:
        ConfigError: `home`, `key`: not a name or path, or no such file.
        UnknownNameError: no shipped file of that name.
    """
    if not isinstance(ref, str):
        raise ConfigError(str(home), key, f"expected a shipped {kind} name or a path")
    if "/" in ref or ref.endswith((".yaml", ".yml")):
        path = Path(ref) if Path(ref).is_absolute() else home.parent / ref
        if not path.is_file():
            raise ConfigError(str(home), key, f"{FILE_NOT_FOUND}: {path}")
        return path
    return resolve(ref, kind)


@dataclasses.dataclass(frozen=True, slots=True)
class RunScenario:
    """A closed-loop scenario file: what a run is made of (None: not given)."""

    controller: Path | None = None
    simulator: Path | None = None
    robot: Path | None = None
    faults: Path | None = None
    duration_s: float | None = None


def load_run_scenario(name_or_path: str) -> RunScenario:
    """A closed-loop scenario: a shipped name (config/runs/) or a path.

    Raises:
        ConfigError: the file, the bad key and what was expected.
    """
    path = resolve(name_or_path, "runs")
    document = read_yaml(path)
    if not isinstance(document, Mapping):
        raise ConfigError(str(path), "", "expected a closed-loop scenario (a mapping)")
    for key in document:
        if key not in SCENARIO_KEYS:
            raise ConfigError(str(path), str(key), unknown_key(str(key), SCENARIO_KEYS))
    duration = document.get("duration_s")
    if duration is not None and (
        isinstance(duration, bool) or not isinstance(duration, int | float) or not duration > 0
    ):
        raise ConfigError(str(path), "duration_s", f"expected a time > 0 s, got {duration!r}")
    kinds = {"controller": "ros", "simulator": "ros", "robot": "robots", "faults": "faults"}
    files = {
        key: file_ref(document[key], path, kind, key)
        for key, kind in kinds.items()
        if document.get(key) is not None
    }
    return RunScenario(**files, duration_s=None if duration is None else float(duration))


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
    controller_values = node_parameters(controller_path, "controller")
    simulator_values = node_parameters(simulator_path, "simulator")
    try:
        validate_controller_params(controller_values)
    except ParameterError as exc:
        raise _in_file(controller_path, "controller", exc) from exc
    try:
        validate_simulator_params(
            {k: v for k, v in simulator_values.items() if not is_fault_parameter(k)}
        )
    except ParameterError as exc:
        raise _in_file(simulator_path, "simulator", exc) from exc
    return closed_loop_config(controller_values, simulator_values, duration_s, robot=robot)


def _in_file(path: Path, node: str, exc: ParameterError) -> ConfigError:
    return ConfigError(str(path), f"{node}.{PARAMS_KEY}.{exc.name}", str(exc).split(": ", 1)[1])


def trajectory_header(result: ClosedLoopResult) -> list[str]:
    """trajectory.csv's header: t_s, per axis its state, per controller joint its loop."""
    unit = "a" if result.command_interface == "current" else "v"
    axis_columns = ("position", "velocity", "current_a", "voltage_v", "drive_state")
    return (
        ["t_s"]
        + [f"{axis}_{col}" for axis in result.axes for col in axis_columns]
        + [f"{j}_{col}" for j in result.joints for col in ("velocity_reference", f"command_{unit}")]
    )


def trajectory_rows(result: ClosedLoopResult) -> Iterator[list[str]]:
    """trajectory.csv's rows (floats in shortest round-trip form: the exact float64 values)."""
    names = result.state_names
    for k in range(len(result.time_s)):
        row = [number_cell(result.time_s[k])]
        for a in range(len(result.axes)):
            row += [
                number_cell(result.position[k, a]),
                number_cell(result.velocity[k, a]),
                number_cell(result.current_a[k, a]),
                number_cell(result.voltage_v[k, a]),
                names[int(result.drive_state[k, a])],
            ]
        for j in range(len(result.joints)):
            row += [
                number_cell(result.velocity_reference[k, j]),
                number_cell(result.command[k, j]),
            ]
        yield row


def summary(result: ClosedLoopResult, config: ClosedLoopConfig, wall_s: float) -> dict[str, Any]:
    """summary.json: the run, its speed, and per controller joint its tracking and current.

    The tracking error is `ClosedLoopResult.velocity_tracking`'s, over `tracking_window_s`.
    """
    joints: dict[str, Any] = {}
    for joint in result.joints:
        a = result.axes.index(joint)
        drive = result.drive_state[:, a]
        changes = np.flatnonzero(drive[1:] != drive[:-1]) + 1
        joints[joint] = {
            **result.velocity_tracking(config.controller, joint).figures(),
            "max_abs_current_a": float(np.max(np.abs(result.current_a[:, a]))),
            "start_position": float(result.position[0, a]),
            "end_position": float(result.position[-1, a]),
            "drive_state_change_count": len(changes),
            "drive_state_changes": [  # the first MAX_LISTED_CHANGES
                {
                    "t_s": float(result.time_s[k]),
                    "position": float(result.position[k, a]),
                    "from": result.state_names[int(drive[k - 1])],
                    "to": result.state_names[int(drive[k])],
                }
                for k in changes[:MAX_LISTED_CHANGES]
            ],
        }
    duration_s = float(result.time_s[-1])
    return {
        "robot": config.robot.name,
        "command_interface": config.command_interface,
        "reference_source": config.controller.reference_source,
        "duration_s": duration_s,
        "control_period_s": config.control_period_s,
        "dt_s": config.dt_s,
        "rigid_body_update_steps": config.rigid_body_update_steps,
        "states": len(result.time_s),
        "commands_rejected": result.commands_rejected,
        "wall_s": wall_s,
        "realtime_factor": duration_s / wall_s if wall_s > 0.0 else math.inf,
        "tracking_window_s": list(tracking_window(config.controller, duration_s)),
        "joints": joints,
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `lca-hil run`."""
    parser.add_argument(
        "scenario",
        nargs="?",
        default="",
        help="a closed-loop scenario: a name in config/runs/ or a YAML path (controller, "
        "simulator, robot, faults, duration_s); the options below override it",
    )
    parser.add_argument(
        "--controller-config",
        type=Path,
        help="the controller node's params file (default: the scenario's, else "
        "config/ros/controller.yaml)",
    )
    parser.add_argument(
        "--simulator-config",
        type=Path,
        help="the simulator node's params file (default: the scenario's, else "
        "config/ros/simulator.yaml)",
    )
    parser.add_argument(
        "--duration-s",
        type=float,
        help=f"simulated seconds (default: the scenario's, else {DEFAULT_DURATION_S:g}); a "
        "whole number of dt_s",
    )
    parser.add_argument(
        "--faults",
        default="",
        help="a fault schedule (docs/faults.md): a YAML path, or a name in config/faults/; "
        "overrides the scenario's and the simulator config's fault_schedule",
    )
    parser.add_argument("--out", type=Path, default=Path("out/run"), help="output folder")
    parser.add_argument(
        "--plot",
        type=Path,
        metavar="DIR",
        help="also draw the trajectory as PNGs into DIR, as lca-plot draws a bag's",
    )


def run(args: argparse.Namespace) -> int:
    """Run `lca-hil run` on parsed arguments; returns the exit code."""
    return run_guarded(PROG, lambda: _run(args))


def main(argv: Sequence[str] | None = None) -> int:
    """`lca-hil run ...` on its own (lca-hil's registry, `lca_sim.cli.hil`, holds it too)."""
    parser = argparse.ArgumentParser(prog="lca-hil")
    sub = parser.add_subparsers(dest="command", required=True)
    add_arguments(sub.add_parser("run"))
    return run(parser.parse_args(argv))


def _run(args: argparse.Namespace) -> int:
    scenario = load_run_scenario(args.scenario) if args.scenario else RunScenario()
    ros = config_dir() / "ros"
    controller_path = args.controller_config or scenario.controller or ros / "controller.yaml"
    simulator_path = args.simulator_config or scenario.simulator or ros / "simulator.yaml"
    duration_s = next(
        d for d in (args.duration_s, scenario.duration_s, DEFAULT_DURATION_S) if d is not None
    )  # an explicit 0 goes on to the validation, which refuses it
    robot = None if scenario.robot is None else load_robot(str(scenario.robot))
    config = load_config(controller_path, simulator_path, duration_s, robot=robot)
    values = node_parameters(simulator_path, "simulator")
    schedule = (
        args.faults
        or (str(scenario.faults) if scenario.faults else "")
        or str(values.get(FAULT_SCHEDULE, ""))
    )
    try:
        standing = standing_faults(values, config.robot.axis_names)
    except ParameterError as exc:
        raise _in_file(simulator_path, "simulator", exc) from exc
    faults = (*standing, *load_fault_schedule(schedule, config.robot.axis_names))
    if faults:
        config = dataclasses.replace(config, faults=faults)
        print(f"{PROG}: {len(faults)} faults ({schedule or simulator_path})")
    loop = ClosedLoop(config)
    start = time.perf_counter()
    result = loop.run()
    wall_s = time.perf_counter() - start
    out: Path = args.out
    write_table(out / "trajectory.csv", trajectory_header(result), trajectory_rows(result))
    report = summary(result, config, wall_s)
    write_json(out / "summary.json", report)
    print(
        f"{PROG}: {report['duration_s']:g} s simulated in {wall_s:.3f} s "
        f"({report['realtime_factor']:.1f}x real time), {report['states']} states; "
        f"{out / 'trajectory.csv'}, {out / 'summary.json'}"
    )
    for joint, figures in report["joints"].items():
        tracking = result.velocity_tracking(config.controller, joint)
        if figures["drive_state_changes"] or tracking.max > 0.0:
            print(
                f"  {tracking.describe()}; "
                f"max |current| {figures['max_abs_current_a']:.3g} A, "
                f"{figures['drive_state_change_count']} drive-state changes"
            )
    if args.plot is not None:
        from lca_sim.cli.bagplot import plot_run  # noqa: PLC0415  (matplotlib: when asked)

        plots = plot_run(result, args.plot, f"{PROG} {args.scenario}".strip())
        for note in plots.notes:
            print(f"{PROG}: note: {note}")
        for path in plots.written:
            print(f"wrote {path}")
    return EXIT_OK
