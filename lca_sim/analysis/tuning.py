"""Section 6's PI tuning on linearised models: the current loop, then the velocity loop.

For every operating point (`lca_sim.analysis.linear.default_operating_points`) the full model is
linearised; the current loop's Kp is read from the current plants at wc = 3 / t_r (the paper's
t_r ~= 3 Ti, 3 ms -> 1000 rad/s), the velocity loop's from the velocity plants (current loop
closed with the new gains) at its wc (100 rad/s); `lca_control.tuning` gives the rule. Both
loops' margins come with every point, also with the sample-and-hold delay of the rate each loop
runs at (the drive's current loop at the model step, the velocity loop at the controller's
period and delay). `lca-hil tune` prints them and writes the gains (`lca_sim.cli.tune`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.tuning import PiTuning, response_time_to_crossover, tune_pi
from lca_sim.analysis.linear import LinearAxisModel, PointLoops, cascade_loops, linearise_points
from lca_sim.model.simulator import Simulator

PAPER_CURRENT_RESPONSE_TIME_S = 3e-3
HOLD_DELAY_PERIODS = 0.5  # the controller's zero-order hold: the simulator's lockstep
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
