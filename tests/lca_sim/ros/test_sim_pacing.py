"""The simulator's simulated time in lockstep: pause, the ~/step budget, the end, a rewind.

And in realtime, a freeze of the process against the command deadline. Pure: no rclpy context
is started; realtime pacing is covered by test_sim_control.py, a real freeze (SIGSTOP) by
test_process_freeze.py.
"""

from __future__ import annotations

import time

import pytest
from support import ManualClock

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


# --- freezes of the process (realtime): the command deadline forgives them -------------------

REALTIME = validate_simulator_params({**SIMULATOR_PARAMETERS.defaults(), "timing_mode": "realtime"})
TICK_S = 1.0 / REALTIME.publish_rate_hz


def _realtime(monkeypatch: pytest.MonkeyPatch) -> tuple[SimPacing, ManualClock]:
    wall = ManualClock(100.0)
    monkeypatch.setattr(time, "monotonic", wall)
    pacing = SimPacing(lambda: REALTIME, lockstep=False)
    pacing.check_freeze(TICK_S)  # the first tick: before the start, never a freeze
    pacing.tick_started()
    pacing.command_came()
    return pacing, wall


def _ticks(pacing: SimPacing, wall: ManualClock, until_s: float) -> list[object]:
    """Timer callbacks every tick period up to `until_s`; the freezes they saw."""
    seen: list[object] = []
    while wall.now_s + TICK_S <= until_s + 1e-9:
        wall.now_s += TICK_S
        seen.append(pacing.check_freeze(TICK_S))
    return seen


def test_a_freeze_of_the_process_is_no_command_silence(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 0.4 s gap between two ticks moves the last command's time on by the freeze."""
    pacing, wall = _realtime(monkeypatch)
    assert _ticks(pacing, wall, 100.02) == [None] * 5
    wall.now_s = 100.42  # the process stood still since the tick at 100.02
    freeze = pacing.check_freeze(TICK_S)
    assert freeze is not None and freeze.frozen_s == pytest.approx(0.4 - TICK_S)
    # silent for 0.42 s of wall time, of which 0.396 s frozen: 0.024 s of true silence
    age_s = wall.now_s - pacing.last_command_wall
    assert age_s == pytest.approx(0.02 + TICK_S) and age_s < REALTIME.command_timeout_s
    assert (pacing.freezes.count, pacing.freezes.longest_s) == (1, freeze.frozen_s)


def test_a_silence_while_the_process_runs_is_still_caught(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ticks on time for 0.2 s without a command: no freeze, the deadline passes."""
    pacing, wall = _realtime(monkeypatch)
    assert set(_ticks(pacing, wall, 100.2)) == {None}
    assert wall.now_s - pacing.last_command_wall > REALTIME.command_timeout_s
    assert pacing.freezes.count == 0


def test_a_command_taken_after_the_freeze_is_not_moved_past_now(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The subscription ran before the tick that noticed the freeze: its time stays now at most."""
    pacing, wall = _realtime(monkeypatch)
    wall.now_s = 100.5
    pacing.command_came()  # the first callback after the freeze
    wall.now_s = 100.501
    assert pacing.check_freeze(TICK_S) is not None
    assert pacing.last_command_wall == 100.501  # not 100.5 + the freeze


def test_start_up_is_no_freeze(monkeypatch: pytest.MonkeyPatch) -> None:
    """Before simulated time starts (heap settling, the executor coming up) nothing is judged."""
    wall = ManualClock(100.0)
    monkeypatch.setattr(time, "monotonic", wall)
    pacing = SimPacing(lambda: REALTIME, lockstep=False)
    wall.now_s = 101.0
    assert pacing.check_freeze(TICK_S) is None and pacing.freezes.count == 0
