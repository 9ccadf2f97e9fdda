"""`lca-hil paper`: regenerate every figure of the paper, each as a PNG plus the CSV behind it.

    lca-hil paper --out out/paper

Figs 4-5 (constant velocity torques), 9-10 (open-loop voltage run with its four phases), 12 and
14 (Bode diagrams of the linearised current and velocity open loops, python-control), 13 (the
5 A current step) come from the model in this process; Fig. 15 (the closed-loop velocity ramp)
runs over ROS 2 topics through `lca-hil fig15` (`--no-ros` skips it). DIR/numbers.json holds
every reproduced number next to the paper's; docs/paper.md discusses the differences.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from lca_control.cascade import (
    PAPER_CURRENT_KP_V_PER_A,
    PAPER_CURRENT_TI_S,
    PAPER_VELOCITY_KP_A_PER_RAD_S,
    PAPER_VELOCITY_TI_S,
)
from lca_sim.analysis.linear import LinearAxisModel, linearise_points
from lca_sim.analysis.paper import (
    BodeStudy,
    ConstantVelocityTorques,
    Phase,
    StepResponse,
    bode_study,
    constant_velocity_torques,
    current_step,
    open_loop_phases,
)
from lca_sim.analysis.tuning import tune_axis
from lca_sim.cli.plotting import clip_spikes, save_png
from lca_sim.cli.ros_guard import ros_required
from lca_sim.config.loader import load_robot, load_scenario
from lca_sim.errors import EXIT_FAILED, USER_ERRORS, LcaHilError, OutputError, run_guarded
from lca_sim.model.params import RobotParams
from lca_sim.model.scenario import ScenarioResult, run_scenario
from lca_sim.model.simulator import Simulator
from lca_sim.output import output_folder, write_json, write_table

PHASE_COLOURS = {
    "starting": "#dddddd",
    "motor driving": "#cfe8ff",
    "load driving": "#ffe2c6",
    "braking": "#f3d1f4",
}
PROG = "lca-hil paper"
FIG45_SPEED_DEG_S = 7.0  # Figs 4 and 5: the pivot at +7 and -7 deg/s
# Where the paper sees the open loops stop depending on the operating point (Figs 12, 14).
PAPER_FIG12_INDEPENDENT_RAD_S = 1000.0
PAPER_FIG14_INDEPENDENT_RAD_S = 20.0
# What the paper states, for numbers.json and docs/paper.md.
PAPER = {
    "fig4_5_load_driving_deg": 60.0,
    "fig9_starting_s": [24.0, 25.0],
    "fig9_motor_driving_s": [25.0, 37.8],
    "fig9_load_driving_s": [37.8, 40.2],
    "fig9_braking_s": [40.2, 40.3],
    "fig12_independent_from_rad_s": PAPER_FIG12_INDEPENDENT_RAD_S,
    "fig14_independent_from_rad_s": PAPER_FIG14_INDEPENDENT_RAD_S,
    "fig13_response_time_s": 3e-3,
    "fig13_overshoot_pct": 24.0,
    "fig15_transition_deg": 55.0,
    "current_kp_v_per_a": PAPER_CURRENT_KP_V_PER_A,
    "current_ti_s": PAPER_CURRENT_TI_S,
    "velocity_kp_a_per_rad_s": PAPER_VELOCITY_KP_A_PER_RAD_S,
    "velocity_ti_s": PAPER_VELOCITY_TI_S,
}


# --- Figs 4 and 5 ------------------------------------------------------------------------------


def write_fig45(robot: RobotParams, reversible: RobotParams, out: Path) -> dict[str, float]:
    """Figs 4 (+7 deg/s) and 5 (-7 deg/s); returns where the load becomes driving."""
    positions = np.radians(np.arange(10.0, 110.0 + 1e-9, 0.25))
    numbers: dict[str, float] = {}
    sim, sim_rev = Simulator(robot), Simulator(reversible)
    for fig_no, speed in ((4, FIG45_SPEED_DEG_S), (5, -FIG45_SPEED_DEG_S)):
        sweep = constant_velocity_torques(sim, sim_rev, math.radians(speed), positions)
        sign = "plus" if speed > 0 else "minus"
        stem = f"fig{fig_no:02d}_constant_velocity_{sign}{abs(speed):g}deg_s"
        write_table(
            out / f"{stem}.csv",
            [
                "position_deg",
                "load_torque_nm",
                "reversible_motor_torque_nm",
                "state_machine_motor_torque_nm",
                "drive_state",
            ],
            zip(
                np.degrees(sweep.position_rad),
                sweep.load_torque_nm,
                sweep.reversible_motor_torque_nm,
                sweep.state_machine_motor_torque_nm,
                sweep.drive_state,
                strict=True,
            ),
        )
        _plot_fig45(sweep, fig_no, out / f"{stem}.png")
        numbers[f"fig{fig_no}_load_driving_deg"] = math.degrees(sweep.load_driving_from_rad)
    return numbers


def _plot_fig45(sweep: ConstantVelocityTorques, fig_no: int, path: Path) -> None:
    fig = Figure(figsize=(8, 4.8))
    ax = fig.add_subplot()
    q = np.degrees(sweep.position_rad)
    ax.plot(q, sweep.load_torque_nm, label="load torque $\\Gamma_l = N^{-1}Q(q)$")
    ax.plot(
        q, sweep.reversible_motor_torque_nm, "--", label="motor torque, reversible model (eq. 5)"
    )
    ax.plot(q, sweep.state_machine_motor_torque_nm, label="motor torque, state-machine model")
    switch = math.degrees(sweep.load_driving_from_rad)
    ax.axvline(switch, color="k", linestyle=":", label=f"load becomes driving: {switch:.1f} deg")
    ax.axhline(0.0, color="grey", linewidth=0.6)
    ax.set_xlabel("pivot position (deg)")
    ax.set_ylabel("torque at the motor shaft (N m)")
    speed = math.degrees(sweep.velocity_rad_s)
    ax.set_title(f"Fig. {fig_no}: pivot at {speed:+.0f} deg/s (paper: load driving at ~60 deg)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    save_png(fig, path)


# --- Figs 9 and 10 -----------------------------------------------------------------------------


def write_fig9_10(robot: RobotParams, out: Path) -> dict[str, Any]:
    """Figs 9 (voltage) and 10 (current, velocity, position) with the four phases shaded."""
    scenario = load_scenario("fig9_open_loop_pivot", robot.axis_names)
    sim = Simulator(robot, dt_s=scenario.dt_s)
    result = run_scenario(sim, scenario)
    phases = open_loop_phases(result, robot)
    a = result.axis_names.index("pivot")
    volts = result.signal("voltage_v", "pivot")
    current = result.signal("current_a", "pivot")

    def phase_at(t: float) -> str:
        return next((p.name for p in phases if p.start_s <= t < p.end_s), "")

    write_table(
        out / "fig09_10_open_loop.csv",
        [
            "t_s",
            "voltage_v",
            "current_a",
            "velocity_deg_s",
            "position_deg",
            "drive_state",
            "phase",
        ],
        (
            (
                float(result.time_s[k]),
                float(volts[k]),
                float(current[k]),
                math.degrees(result.velocity[k, a]),
                math.degrees(result.position[k, a]),
                result.state_names[int(result.drive[k, a])],
                phase_at(float(result.time_s[k])),
            )
            for k in range(len(result.time_s))
        ),
    )
    _plot_fig9(result, volts, phases, out / "fig09_voltage.png")
    _plot_fig10(result, current, phases, out / "fig10_outputs.png")
    return {
        f"fig9_{p.name.replace(' ', '_')}_s": [round(p.start_s, 4), round(p.end_s, 4)]
        for p in phases
    } | {
        "fig9_load_driving_from_deg": next(
            (math.degrees(p.start_position_rad) for p in phases if p.name == "load driving"),
            math.nan,
        )
    }


def _shade(panels: Sequence[Axes], phases: Sequence[Phase]) -> None:
    for k, phase in enumerate(phases):
        for panel in panels:
            panel.axvspan(
                phase.start_s,
                phase.end_s,
                color=PHASE_COLOURS.get(phase.name, "#eeeeee"),
                alpha=0.7,
                linewidth=0,
                label=phase.name if panel is panels[0] and k < len(PHASE_COLOURS) else None,
            )


def _plot_fig9(
    result: ScenarioResult, volts: np.ndarray, phases: Sequence[Phase], path: Path
) -> None:
    fig = Figure(figsize=(8, 3.6))
    ax = fig.add_subplot()
    _shade([ax], phases)
    ax.plot(result.time_s, volts, color="C0", label="pivot motor voltage")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("voltage (V)")
    ax.set_title("Fig. 9: open-loop motor command voltage")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    save_png(fig, path)


def _plot_fig10(
    result: ScenarioResult, current: np.ndarray, phases: Sequence[Phase], path: Path
) -> None:
    fig = Figure(figsize=(8, 8))
    panels = [fig.add_subplot(3, 1, k + 1) for k in range(3)]
    _shade(panels, phases)
    a = result.axis_names.index("pivot")
    panels[0].plot(result.time_s, current, color="C1")
    panels[0].set_ylabel("current (A)")
    panels[1].plot(result.time_s, np.degrees(result.velocity[:, a]), color="C2")
    panels[1].set_ylabel("velocity (deg/s)")
    panels[2].plot(result.time_s, np.degrees(result.position[:, a]), color="C3")
    panels[2].set_ylabel("position (deg)")
    panels[2].set_xlabel("time (s)")
    times = ", ".join(f"{p.name} {p.start_s:.2f}-{p.end_s:.2f} s" for p in phases)
    panels[0].set_title(f"Fig. 10: direct motion outputs\n{times}", fontsize=9)
    panels[0].legend(fontsize=8, loc="upper left")
    for panel in panels:
        panel.grid(True, alpha=0.3)
        panel.set_xlim(22.0, float(result.time_s[-1]))
    save_png(fig, path)


# --- Figs 12 and 14 ----------------------------------------------------------------------------


def write_fig12_14(sim: Simulator, models: Sequence[LinearAxisModel], out: Path) -> dict[str, Any]:
    """Bode diagrams of the current (Fig. 12) and velocity (Fig. 14) open loops."""
    study = bode_study(sim, models)
    numbers: dict[str, Any] = {
        "fig12_independent_from_rad_s": study.current_independent_from_rad_s,
        "fig14_independent_from_rad_s": study.velocity_independent_from_rad_s,
        "independence_tolerance": f"{study.tolerance_db:g} dB, {study.tolerance_deg:g} deg",
    }
    for fig_no, name, loop, margins, indep, paper in (
        (12, "current", study.current_loop, study.current_margins,
         study.current_independent_from_rad_s, PAPER_FIG12_INDEPENDENT_RAD_S),
        (14, "velocity", study.velocity_loop, study.velocity_margins,
         study.velocity_independent_from_rad_s, PAPER_FIG14_INDEPENDENT_RAD_S),
    ):  # fmt: skip
        stem = f"fig{fig_no}_{name}_open_loop_bode"
        mag_db = 20.0 * np.log10(np.abs(loop))
        phase_deg = np.degrees(np.unwrap(np.angle(loop), axis=1))
        header = ["omega_rad_s"]
        for label in study.labels:
            header += [f"{label} mag_db", f"{label} phase_deg"]
        write_table(
            out / f"{stem}.csv",
            header,
            (
                [float(w)] + [float(x) for pair in zip(m, p, strict=True) for x in pair]
                for w, m, p in zip(study.omega_rad_s, mag_db.T, phase_deg.T, strict=True)
            ),
        )
        _plot_bode(study, fig_no, name, mag_db, phase_deg, indep, paper, out / f"{stem}.png")
        numbers[f"fig{fig_no}_crossover_rad_s"] = [round(m.crossover_rad_s, 1) for m in margins]
        numbers[f"fig{fig_no}_phase_margin_deg"] = [round(m.phase_margin_deg, 1) for m in margins]
        numbers[f"fig{fig_no}_sampled_phase_margin_deg"] = [
            round(m.sampled_phase_margin_deg, 1) for m in margins
        ]
    numbers["operating_points"] = [
        f"{label}: {state}" for label, state in zip(study.labels, study.drive_states, strict=True)
    ]
    return numbers


def _plot_bode(
    study: BodeStudy,
    fig_no: int,
    name: str,
    mag_db: np.ndarray,
    phase_deg: np.ndarray,
    indep: float,
    paper: float,
    path: Path,
) -> None:
    fig = Figure(figsize=(8, 7))
    mag_ax, phase_ax = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2, sharex=None)
    for k, label in enumerate(study.labels):
        style = "-" if "+" in label else "--"
        text = f"{label} ({study.drive_states[k].replace('motor_and_load_driving_', 'm+l ')})"
        mag_ax.semilogx(study.omega_rad_s, mag_db[k], style, linewidth=1, label=text)
        phase_ax.semilogx(study.omega_rad_s, phase_deg[k], style, linewidth=1)
    for ax in (mag_ax, phase_ax):
        ax.axvline(indep, color="k", linestyle=":", linewidth=1.2)
        ax.axvline(paper, color="r", linestyle=":", linewidth=1.0)
        ax.grid(True, which="both", alpha=0.3)
    mag_ax.axhline(0.0, color="grey", linewidth=0.6)
    mag_ax.set_ylabel("|L(jw)| (dB)")
    phase_ax.set_ylabel("phase (deg)")
    phase_ax.set_xlabel("frequency (rad/s)")
    mag_ax.legend(fontsize=6, ncol=2)
    mag_ax.set_title(
        f"Fig. {fig_no}: {name} open loop (paper's PI) of the linearised pivot\n"
        f"independent of the operating point above {indep:.0f} rad/s (black, "
        f"{study.tolerance_db:g} dB / {study.tolerance_deg:g} deg); paper ~{paper:g} rad/s (red)",
        fontsize=9,
    )
    save_png(fig, path)


# --- Fig. 13 -----------------------------------------------------------------------------------


def write_fig13(robot: RobotParams, out: Path) -> dict[str, float]:
    """The 5 A current step with the paper's gains."""
    step = current_step(robot)
    write_table(
        out / "fig13_current_step.csv",
        ["t_s", "current_a", "setpoint_a"],
        (
            (float(t), float(i), step.setpoint_a)
            for t, i in zip(step.time_s, step.current_a, strict=True)
        ),
    )
    _plot_fig13(step, out / "fig13_current_step.png")
    return {
        "fig13_overshoot_pct": step.overshoot_pct,
        "fig13_response_time_s": step.response_time_s,
        "fig13_rise_time_10_90_s": step.rise_time_s,
    }


def _plot_fig13(step: StepResponse, path: Path) -> None:
    fig = Figure(figsize=(8, 4.5))
    ax = fig.add_subplot()
    t_ms = np.concatenate([[0.0], step.time_s * 1e3])
    ax.plot(t_ms, np.concatenate([[0.0], step.current_a]), label="armature current")
    ax.axhline(step.setpoint_a, color="grey", linestyle="--", label="5 A reference")
    ax.axhspan(0.95 * step.setpoint_a, 1.05 * step.setpoint_a, color="grey", alpha=0.15)
    ax.axvline(step.response_time_s * 1e3, color="k", linestyle=":", label="5 % response time")
    ax.set_xlim(0.0, 15.0)
    ax.set_xlabel("time (ms)")
    ax.set_ylabel("current (A)")
    ax.set_title(
        f"Fig. 13: current step, t_r (5 %) = {step.response_time_s * 1e3:.1f} ms, "
        f"10-90 % rise {step.rise_time_s * 1e3:.2f} ms, overshoot {step.overshoot_pct:.1f} %"
        "\n(paper: t_r ~ 3 ms, D = 24 %)",
        fontsize=9,
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    save_png(fig, path)


# --- Fig. 15 -----------------------------------------------------------------------------------


def write_fig15(out: Path, duration_s: float) -> dict[str, Any]:
    """The closed-loop velocity ramp over ROS 2 (lca-hil fig15), replotted the paper's way."""
    from lca_sim.cli import fig15  # noqa: PLC0415  (imports rclpy: only when Fig. 15 is wanted)
    from lca_sim.ros.bag_read import read_bag  # noqa: PLC0415

    run_dir = out / "fig15_run"
    if (run_dir / "bag").exists():
        raise PaperError(f"{run_dir / 'bag'} exists from an earlier run; choose another --out")
    code = fig15.run_fig15(run_dir, duration_s)
    if code != 0:
        raise PaperError(f"the Fig. 15 run failed (exit {code}); logs in {run_dir}")
    summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    summary = {k: math.nan if v is None else v for k, v in summary.items()}  # null: not reached
    data = read_bag(run_dir / "bag")
    joint, motor, drive = data.joints["pivot"], data.motors["pivot"], data.drives["pivot"]
    t = np.asarray(joint.time_s)
    ramp = fig15.ramp_profile()
    reference = np.array([ramp(x) for x in t])
    current = np.interp(t, motor.time_s, motor.values["effort"])
    drive_t = np.asarray(drive.time_s)
    state_index = np.clip(np.searchsorted(drive_t, t, side="right") - 1, 0, len(drive.state) - 1)
    states = [drive.state[k] for k in state_index]
    position = np.degrees(joint.values["position"])
    velocity = np.degrees(joint.values["velocity"])
    write_table(
        out / "fig15_velocity_ramp.csv",
        ["t_s", "velocity_ref_deg_s", "velocity_deg_s", "position_deg", "current_a", "drive_state"],
        zip(t, np.degrees(reference), velocity, position, current, states, strict=True),
    )
    fig = Figure(figsize=(8, 8))
    panels = [fig.add_subplot(3, 1, k + 1) for k in range(3)]
    panels[0].plot(t, current, color="C1", label="pivot current")
    panels[0].set_ylabel("current (A)")
    clip_spikes(panels[0], [(t, current)], "A")  # the braking peak at 11 s would squash the ramp
    panels[0].legend(fontsize=8, loc="upper right")
    panels[1].plot(t, np.degrees(reference), "--", color="grey", label="reference")
    panels[1].plot(t, velocity, color="C2", label="pivot velocity")
    panels[1].set_ylabel("velocity (deg/s)")
    panels[1].legend(fontsize=8)
    panels[2].plot(t, position, color="C3")
    panels[2].set_ylabel("position (deg)")
    panels[2].set_xlabel("simulated time (s)")
    transition_t = float(summary["transition_time_s"])
    transition_deg = float(summary["transition_from_motor_driving_deg"])
    for panel in panels:
        panel.axvline(transition_t, color="k", linestyle=":")
        panel.grid(True, alpha=0.3)
    panels[2].annotate(
        f"motor driving -> load driving\n{transition_deg:.1f} deg (paper: 55)",
        xy=(transition_t, transition_deg),
        xytext=(transition_t - 6.0, transition_deg + 2.0),
        arrowprops={"arrowstyle": "->"},
        fontsize=8,
    )
    panels[0].set_title(
        "Fig. 15: velocity ramp response, closed loop over ROS 2 topics "
        f"(max tracking error {summary['max_velocity_error_deg_s']:.3f} deg/s)",
        fontsize=9,
    )
    save_png(fig, out / "fig15_velocity_ramp.png")
    return {
        "fig15_transition_deg": transition_deg,
        "fig15_transition_time_s": transition_t,
        "fig15_max_velocity_error_deg_s": summary["max_velocity_error_deg_s"],
        "fig15_travel_deg": summary["travel_deg"],
    }


# --- section 6 tuning ---------------------------------------------------------------------------


def tuning_numbers(sim: Simulator, models: Sequence[LinearAxisModel]) -> dict[str, float]:
    """The gains `lca-hil tune` finds for the pivot, next to the paper's."""
    report = tune_axis(sim, "pivot", models=models)
    return {
        "current_kp_v_per_a": report.current.kp,
        "current_ti_s": report.current.ti_s,
        "velocity_kp_a_per_rad_s": report.velocity.kp,
        "velocity_ti_s": report.velocity.ti_s,
    }


# --- the command -------------------------------------------------------------------------------


class PaperError(LcaHilError):
    """A part of the reproduction could not be made."""


def add_arguments(paper: argparse.ArgumentParser) -> None:
    """The options of `lca-hil paper`."""
    paper.add_argument("--out", type=Path, default=Path("out/paper"), help="output folder")
    paper.add_argument("--robot", default="default", help="robot YAML path or shipped name")
    paper.add_argument(
        "--no-ros", action="store_true", help="skip Fig. 15 (the only figure run over ROS 2)"
    )
    paper.add_argument(
        "--fig15-duration-s", type=float, default=13.0, help="simulated seconds of Fig. 15"
    )


def run(args: argparse.Namespace) -> int:
    """Run `lca-hil paper`."""
    return run_guarded(PROG, lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out}: expected a folder, but it is a file")
    if not args.no_ros:
        # Fail now, not after the other figures, where ROS 2 is not there.
        with ros_required("Fig. 15", hint=", or pass --no-ros"):
            importlib.import_module("lca_sim.cli.fig15")
    robot = load_robot(args.robot)
    reversible = load_robot("reversible")
    sim = Simulator(robot)
    output_folder(out)
    numbers: dict[str, Any] = {"robot": robot.name}
    pivot_models = functools.cache(lambda: linearise_points(sim))  # Figs 12/14 and the tuning
    steps: list[tuple[str, Callable[[], dict[str, Any]]]] = [
        ("Figs 4-5", lambda: write_fig45(robot, reversible, out)),
        ("Figs 9-10", lambda: write_fig9_10(robot, out)),
        ("Figs 12 and 14", lambda: write_fig12_14(sim, pivot_models(), out)),
        ("Fig. 13", lambda: write_fig13(robot, out)),
        ("section 6 tuning", lambda: tuning_numbers(sim, pivot_models())),
    ]
    if not args.no_ros:
        steps.append(("Fig. 15", lambda: write_fig15(out, args.fig15_duration_s)))
    for name, make in steps:
        start = time.perf_counter()
        try:
            numbers.update(make())
        except USER_ERRORS as exc:
            print(f"{PROG}: error in {name}: {exc}", file=sys.stderr)
            return EXIT_FAILED
        print(f"{PROG}: {name} in {time.perf_counter() - start:.1f} s", flush=True)
    document = {"reproduced": numbers, "paper": PAPER}
    write_json(out / "numbers.json", document)  # strict: a missing number is null, with why
    for key, value in numbers.items():
        print(f"  {key}: {value}")
    print(f"wrote the figures, their CSVs and numbers.json in {out}")
    return 0
