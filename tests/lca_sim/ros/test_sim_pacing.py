"""The simulator's simulated time in lockstep: pause, the ~/step budget, the end, a rewind.

Pure: no rclpy context is started; realtime pacing is covered by test_sim_control.py.
"""

from __future__ import annotations

from lca_sim.config.simulator_params import SIMULATOR_PARAMETERS, validate_simulator_params
from lca_sim.ros.sim_pacing import SimPacing

# 1 ms periods of ten 0.1 ms steps; the run ends at 2.5 ms, halfway through the third period.
PARAMS = validate_simulator_params(
    {
        **SIMULATOR_PARAMETERS.defaults(),
        "timing_mode": "lockstep",
        "control_period_s": 1e-3,
        "lockstep_end_s": 2.5e-3,
    }
)


def _lockstep() -> SimPacing:
    pacing = SimPacing(lambda: PARAMS, lockstep=True)
    pacing.started = True
    return pacing


def _run_periods(pacing: SimPacing, n: int) -> list[int]:
    taken: list[int] = []
    for _ in range(n):
        steps = pacing.period_steps()
        pacing.advanced(steps)
        taken.append(steps)
    return taken


def test_the_last_period_stops_at_the_end() -> None:
    """Periods of ten steps, the last one shorter; ended at lockstep_end_s exactly."""
    pacing = _lockstep()
    assert pacing.sim_time_s == 0.0 and not pacing.ended
    assert _run_periods(pacing, 3) == [10, 10, 5]
    assert pacing.ended and abs(pacing.sim_time_s - 2.5e-3) < 1e-15


def test_a_paused_command_waits_until_step_lets_it_through() -> None:
    """Paused: a command waits; ~/step runs it and lets the next N - 1 through."""
    pacing = _lockstep()
    assert pacing.pause() and not pacing.pause()  # a second pause changes nothing
    assert not pacing.admit_paused_command() and pacing.pending
    assert pacing.budget_steps(3)  # the waiting one runs now
    assert not pacing.pending and pacing.step_budget == 2
    assert pacing.admit_paused_command() and pacing.admit_paused_command()
    assert not pacing.admit_paused_command() and pacing.pending  # the budget is spent
    assert pacing.resume() and not pacing.pending and pacing.step_budget == 0


def test_a_rewind_after_periods_starts_again_at_zero() -> None:
    """~/reset in lockstep: time back to 0, waiting commands forgotten, the end reported anew."""
    pacing = _lockstep()
    assert not pacing.rewind()  # nothing ran yet: the command taken is kept
    _run_periods(pacing, 3)
    pacing.end_reported = True
    assert pacing.pause() and not pacing.admit_paused_command()  # a command waits
    assert pacing.budget_steps(3) and pacing.step_budget == 2
    assert pacing.rewind()
    assert (pacing.steps, pacing.pending, pacing.step_budget) == (0, False, 0)
    assert not pacing.end_reported and not pacing.ended
