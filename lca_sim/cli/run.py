"""`lca-hil run`: the closed loop of the controller and simulator nodes, in one process, no ROS.

    lca-hil run --out out/run                         # Fig. 15's ramp, 13 s
    lca-hil run fig15_encoder_freeze --out out/freeze # a closed-loop scenario (config/runs/)
    lca-hil run --controller-config my_gains.yaml --duration-s 5 --out out/gains

A closed-loop scenario (`lca_sim.config.run_scenario`) names the nodes' params files, the
robot, a fault schedule and the length; the options override it. The params files
(config/ros/controller.yaml and simulator.yaml by default) become the composed loop's config
(`lca_sim.batch.closed_loop_config`); the loop (`lca_sim.analysis.closed_loop`) gives the same
numbers as the lockstep run of the two nodes over ROS 2. Writes trajectory.csv (one row per
control period, floats in shortest round-trip form) and summary.json (strict JSON: duration,
wall time, real-time factor, tracking errors, drive-state changes).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lca_control.parameters import ParameterError
from lca_sim.analysis.closed_loop import (
    ClosedLoop,
    ClosedLoopConfig,
    ClosedLoopResult,
    tracking_window,
)
from lca_sim.batch.closed_loop_config import load_config
from lca_sim.config.loader import load_fault_schedule, load_robot
from lca_sim.config.params_file import in_file, node_parameters
from lca_sim.config.paths import config_dir
from lca_sim.config.run_scenario import RunScenario, load_run_scenario
from lca_sim.errors import EXIT_OK, run_guarded
from lca_sim.model.fault_schedule import standing_faults
from lca_sim.model.faults import FAULT_SCHEDULE
from lca_sim.output import number_cell, write_json, write_table

PROG = "lca-hil run"
DEFAULT_DURATION_S = 13.0  # Fig. 15: 1 s still, the 10 s ramp, 2 s after it
MAX_LISTED_CHANGES = 50  # drive-state changes listed per joint in summary.json


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
        "rigid_body_update_steps": config.plant.rigid_body_update_steps,
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
        raise in_file(simulator_path, "simulator", exc) from exc
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
