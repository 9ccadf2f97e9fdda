"""`lca-hil tune`: section 6's PI tuning (`lca_sim.analysis.tuning`) as a tool.

    lca-hil tune --robot default --axis pivot --out tuned_controller.yaml

Prints the tuned gains and the phase and gain margins of both loops at every operating point,
the velocity loop with the controller's period and delay (`--control-period-s`,
`--delay-periods`: 0.5 for the simulator's hold, 1.5 over a CAN drive) and at 1 and 2 periods
of delay, and writes the gains into a params file for the controller node.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import yaml

from lca_control.cascade import CONTROL_PERIOD_S
from lca_sim.analysis.linear import LoopMargins
from lca_sim.analysis.tuning import (
    HOLD_DELAY_PERIODS,
    PAPER_CURRENT_RESPONSE_TIME_S,
    PAPER_VELOCITY_CROSSOVER_RAD_S,
    TuneReport,
    tune_axis,
)
from lca_sim.config.loader import load_robot
from lca_sim.config.params_file import read_params_document, with_parameters
from lca_sim.config.paths import config_dir
from lca_sim.errors import EXIT_OK, ConfigError, OutputError, UnknownNameError, run_guarded
from lca_sim.model.simulator import Simulator
from lca_sim.output import atomic_path

REPORTED_DELAYS_PERIODS = (1.0, 2.0)  # the margins printed besides: a CAN cycle, a late one


def params_document(report: TuneReport, base: dict[str, Any]) -> dict[str, Any]:
    """The controller params file `base` with the tuned gains in place."""
    gains = {
        "velocity_kp_a_per_rad_s": round(report.velocity.kp, 3),
        "velocity_ti_s": report.velocity.ti_s,
        "current_kp_v_per_a": round(report.current.kp, 3),
        "current_ti_s": report.current.ti_s,
    }
    return with_parameters(base, gains, node="controller")


def format_report(report: TuneReport) -> str:
    """The report lca-hil tune prints: gains, then margins per operating point."""
    lines = [f"{report.axis}: gains by section 6 (Kp for |Kp P(j wc)| = 1, Ti = 1 / wc)"]
    for name, t, unit in (
        ("current ", report.current, "V/A"),
        ("velocity", report.velocity, "A per rad/s"),
    ):
        lines.append(
            f"  {name} loop: wc {t.crossover_rad_s:g} rad/s -> Ti {t.ti_s * 1e3:.3g} ms, "
            f"Kp {t.kp:.2f} {unit} ({t.kp_db:.1f} dB); plant at wc {t.plant_gain_db:.2f} dB, "
            f"spread over the points {t.plant_gain_spread_db:.2f} dB"
        )
    period_s = report.control_period_s
    lines.append(
        f"  velocity loop at {period_s * 1e3:g} ms, delay {report.delay_periods:g} periods "
        f"({report.delay_periods * period_s * 1e3:g} ms) in '(sampled)'; then the PM at "
        + " and ".join(f"{d:g}" for d in REPORTED_DELAYS_PERIODS)
        + " periods of delay"
    )
    lines.append(
        "  operating point          drive state                               "
        "current: wc rad/s  PM deg (sampled)  GM dB | velocity: wc rad/s  PM deg (sampled)  GM dB"
        "  PM at " + " / ".join(f"{d:g}" for d in REPORTED_DELAYS_PERIODS) + " periods"
    )
    for p in report.points:
        at = " / ".join(
            f"{p.velocity.phase_margin_with_delay_deg(d * period_s):5.1f}"
            for d in REPORTED_DELAYS_PERIODS
        )
        lines.append(
            f"  {p.model.point.label:22s}  {p.model.drive_state:40s}  "
            f"{_margins(p.current)} | {_margins(p.velocity)}  {at}"
        )
    for d in REPORTED_DELAYS_PERIODS:
        worst = report.velocity_margin_at_deg(d)
        verdict = "stable" if worst > 0.0 else "UNSTABLE: lower the gains or the delay"
        lines.append(
            f"  worst velocity-loop PM with {d:g} periods ({d * period_s * 1e3:g} ms) of delay: "
            f"{worst:.1f} deg ({verdict})"
        )
    return "\n".join(lines)


def _margins(m: LoopMargins) -> str:
    return (
        f"{m.crossover_rad_s:8.1f}  {m.phase_margin_deg:5.1f} ({m.sampled_phase_margin_deg:5.1f})"
        f"  {m.gain_margin_db:5.1f}"
    )


def add_arguments(tune: argparse.ArgumentParser) -> None:
    """The options of `lca-hil tune`."""
    tune.add_argument("--robot", default="default", help="robot YAML path or shipped name")
    tune.add_argument("--axis", default="pivot", help="the axis to tune (default: pivot)")
    tune.add_argument(
        "--current-response-time-s",
        type=float,
        default=PAPER_CURRENT_RESPONSE_TIME_S,
        help="wanted current response time t_r; wc = 3 / t_r (default: the paper's 3 ms)",
    )
    tune.add_argument(
        "--velocity-crossover-rad-s",
        type=float,
        default=PAPER_VELOCITY_CROSSOVER_RAD_S,
        help="velocity loop crossover wc = 1 / Ti (default: the paper's 100 rad/s)",
    )
    tune.add_argument(
        "--control-period-s",
        type=float,
        default=CONTROL_PERIOD_S,
        help="the velocity loop's period: the controller's (default 0.004 s, the simulator's "
        "lockstep); over CAN 1 / cycle_hz",
    )
    tune.add_argument(
        "--delay-periods",
        type=float,
        default=HOLD_DELAY_PERIODS,
        help="the velocity loop's delay from a state to the command's effect, in periods, hold "
        "included (default 0.5: the simulator; 1.5: a CAN drive, one cycle of transport)",
    )
    tune.add_argument(
        "--base-params",
        type=Path,
        default=None,
        help="controller params file to start from (default: the shipped controller.yaml)",
    )
    tune.add_argument(
        "--out", type=Path, default=Path("tuned_controller.yaml"), help="params file to write"
    )


def run(args: argparse.Namespace) -> int:
    """Run `lca-hil tune`."""
    return run_guarded("lca-hil tune", lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    if args.axis not in robot.axis_names:
        raise UnknownNameError("axis", args.axis, robot.axis_names)
    for name, value, low in (
        ("--control-period-s", args.control_period_s, 1e-5),
        ("--delay-periods", args.delay_periods, 0.0),
    ):
        if not (math.isfinite(value) and low <= value <= 100.0):
            raise ConfigError("arguments", name, f"expected a number in {low:g}..100, got {value}")
    sim = Simulator(robot)
    report = tune_axis(
        sim,
        args.axis,
        current_response_time_s=args.current_response_time_s,
        velocity_crossover_rad_s=args.velocity_crossover_rad_s,
        control_period_s=args.control_period_s,
        delay_periods=args.delay_periods,
    )
    base_path = args.base_params or config_dir() / "ros" / "controller.yaml"
    base = read_params_document(base_path)
    print(format_report(report))
    header = (
        f"# Written by lca-hil tune for {robot.name} ({args.axis}): section 6 gains from\n"
        f"# linearised models at {len(report.points)} operating points; base {base_path}.\n"
    )
    try:
        with atomic_path(args.out) as tmp:
            tmp.write_text(
                header + yaml.safe_dump(params_document(report, base), sort_keys=False),
                encoding="utf-8",
            )
    except OSError as exc:
        raise OutputError(f"cannot write {args.out}: {exc}") from None
    print(f"wrote {args.out} (use: lca-controller --ros-args --params-file {args.out})")
    return EXIT_OK
