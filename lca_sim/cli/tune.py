"""`lca-hil tune`: the section 6 PI tuning on linearised models, as a tool.

    lca-hil tune --robot default --axis pivot --out tuned_controller.yaml

For every operating point (`lca_sim.analysis.linear.default_operating_points`) the full model is
linearised; the current loop's Kp is read from the current plants at wc = 3 / t_r (the paper's
t_r ~= 3 Ti, 3 ms -> 1000 rad/s), the velocity loop's from the velocity plants (current loop
closed with the new gains) at its wc (100 rad/s); `lca_control.tuning` gives the rule. The
phase and gain margins of both loops are reported at every operating point, also with the
sample-and-hold delay of the rate each loop runs at (the drive's current loop at the model
step), the velocity loop with the controller's period and delay (`--control-period-s`,
`--delay-periods`: 0.5 for the simulator's hold, 1.5 over a CAN drive) and at 1 and 2 periods
of delay, and the gains are written into a params file for the controller node.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.tuning import PiTuning, response_time_to_crossover, tune_pi
from lca_sim.analysis.linear import (
    LinearAxisModel,
    LoopMargins,
    PointLoops,
    cascade_loops,
    linearise_points,
)
from lca_sim.config.loader import config_dir, load_robot, read_yaml
from lca_sim.errors import EXIT_OK, ConfigError, OutputError, UnknownNameError, run_guarded
from lca_sim.model.simulator import Simulator
from lca_sim.output import atomic_path

PAPER_CURRENT_RESPONSE_TIME_S = 3e-3
HOLD_DELAY_PERIODS = 0.5  # the controller's zero-order hold: the simulator's lockstep
REPORTED_DELAYS_PERIODS = (1.0, 2.0)  # the margins printed besides: a CAN cycle, a late one
PAPER_VELOCITY_CROSSOVER_RAD_S = 100.0


@dataclass(frozen=True, slots=True)
class TuneReport:
    """The tuned loops of one axis and their margins at every operating point."""

    axis: str
    current: PiTuning
    velocity: PiTuning
    points: tuple[PointLoops, ...]
    control_period_s: float = CONTROL_PERIOD_S
    delay_periods: float = 0.5

    def velocity_margin_at_deg(self, periods: float) -> float:
        """The velocity loop's worst phase margin over the points, with `periods` of delay."""
        delay_s = periods * self.control_period_s
        return min(p.velocity.phase_margin_with_delay_deg(delay_s) for p in self.points)


def tune_axis(
    sim: Simulator,
    axis: str,
    current_response_time_s: float = PAPER_CURRENT_RESPONSE_TIME_S,
    velocity_crossover_rad_s: float = PAPER_VELOCITY_CROSSOVER_RAD_S,
    control_period_s: float = CONTROL_PERIOD_S,
    models: Sequence[LinearAxisModel] | None = None,
    delay_periods: float = HOLD_DELAY_PERIODS,
) -> TuneReport:
    """Tune the current loop, then the velocity loop around it (section 6).

    `models` are the axis linearised at the default operating points when the caller already
    has them (`linearise_points`). `control_period_s` and `delay_periods` are the velocity
    loop's period and its delay in periods, for its margins.
    """
    if models is None:
        models = linearise_points(sim, axis)
    wc_i = response_time_to_crossover(current_response_time_s)
    current = tune_pi(wc_i, [abs(complex(m.current_plant()(1j * wc_i))) for m in models])
    wc_v = velocity_crossover_rad_s
    velocity = tune_pi(
        wc_v,
        [abs(complex(m.velocity_plant(current.kp, current.ti_s)(1j * wc_v))) for m in models],
    )
    loops = cascade_loops(
        models,
        (current.kp, current.ti_s),
        (velocity.kp, velocity.ti_s),
        sim.dt_s,
        control_period_s,
        delay_periods,
    )
    return TuneReport(
        axis=axis,
        current=current,
        velocity=velocity,
        points=loops,
        control_period_s=control_period_s,
        delay_periods=delay_periods,
    )


def params_document(report: TuneReport, base: dict[str, Any]) -> dict[str, Any]:
    """The controller params file `base` with the tuned gains in place."""
    document = dict(base)
    node = next(iter(document)) if document else "controller"
    section = dict(document.get(node, {}))
    params = dict(section.get("ros__parameters", {}))
    params.update(
        velocity_kp_a_per_rad_s=round(report.velocity.kp, 3),
        velocity_ti_s=report.velocity.ti_s,
        current_kp_v_per_a=round(report.current.kp, 3),
        current_ti_s=report.current.ti_s,
    )
    section["ros__parameters"] = params
    document[node] = section
    return document


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


def add_parser(sub: Any) -> None:
    """Register `tune` on the lca-hil subcommands."""
    tune = sub.add_parser("tune", help="section 6 PI gains from linearised models")
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
    base = read_yaml(base_path)
    if not isinstance(base, dict):
        raise ConfigError(str(base_path), "", "expected a controller params mapping")
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
