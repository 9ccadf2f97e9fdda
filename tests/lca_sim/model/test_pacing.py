"""The simulator node's pacing as pure clocks (`lca_sim.model.pacing`), with the time passed in.

Each test is a timeline the node goes through today (lca_sim/ros/simulator_node.py: its
realtime tick, `~/pause`, `~/resume`, `~/step`, the diagnostics' timing and a live
`realtime_factor`; in lockstep the commands, `~/step` and `~/reset`), at wall times chosen to
give whole numbers of steps.
"""

from __future__ import annotations

import pytest

from lca_sim.model.pacing import MAX_CATCH_UP_PERIODS, LockstepGate, RealtimeClock

DT_S = 1e-4
RATE_HZ = 250.0  # a tick every 4 ms: 40 steps
T0 = 1000.0  # the monotonic wall time at the node's construction


def _clock(factor: float = 1.0) -> RealtimeClock:
    return RealtimeClock(DT_S, factor, RATE_HZ, T0)


def _tick(clock: RealtimeClock, now_s: float) -> int:
    """The node's realtime tick: start at the first, nothing while paused, take what is due."""
    if not clock.started:
        clock.start(now_s)
    if clock.paused:
        return 0
    due = clock.due(now_s)
    if due > 0:
        clock.advanced(due)
    return due


def test_nothing_is_due_before_the_first_tick() -> None:
    """Simulated time starts at the first tick, not at construction."""
    clock = _clock()
    assert clock.due(T0 + 5.0) == 0 and clock.steps == 0
    assert _tick(clock, T0 + 5.0) == 0  # the first tick starts the clock at its own time
    assert _tick(clock, T0 + 5.004) == 40


def test_steps_follow_the_wall_clock_at_the_realtime_factor() -> None:
    """Steps due = wall time since the start * factor / dt_s, minus those taken."""
    clock = _clock(factor=0.5)
    _tick(clock, T0)
    assert _tick(clock, T0 + 0.004) == 20
    assert _tick(clock, T0 + 0.010) == 30
    assert clock.due(T0 + 0.010) == 0  # asking again takes nothing
    assert clock.steps == 50


def test_a_stall_beyond_the_catch_up_cap_is_skipped_and_counted() -> None:
    """At most four ticks' worth is caught up; the rest is skipped and time lags from then on."""
    clock = _clock()
    _tick(clock, T0)
    cap = MAX_CATCH_UP_PERIODS * 40
    assert _tick(clock, T0 + 1.0) == cap
    assert clock.overrun_steps == 10000 - cap
    assert _tick(clock, T0 + 1.004) == 40  # running again, from the new start
    window = clock.window(T0 + 1.004)
    assert window.stamp_lag_s == pytest.approx((10000 - cap) * DT_S)
    assert window.skipped_s == pytest.approx((10000 - cap) * DT_S)
    assert window.stalled_s == pytest.approx(window.skipped_s)


def test_a_pause_holds_time_and_resume_does_not_catch_it_up() -> None:
    """Paused: nothing due; resume returns the pause's length and goes on from where it was."""
    clock = _clock()
    _tick(clock, T0)
    _tick(clock, T0 + 0.004)
    assert clock.pause(T0 + 0.004) and not clock.pause(T0 + 0.005)
    assert _tick(clock, T0 + 3.0) == 0
    assert clock.resume(T0 + 3.004) == pytest.approx(3.0)
    assert clock.resume(T0 + 3.005) is None  # running already
    assert _tick(clock, T0 + 3.008) == 40
    assert clock.overrun_steps == 0
    window = clock.window(T0 + 3.008)
    assert window.paused_s == pytest.approx(3.0) and window.stalled_s == 0.0
    assert window.realtime_factor == pytest.approx(80 * DT_S / 0.008)


def test_steps_taken_by_step_while_paused_are_not_taken_again() -> None:
    """~/step's steps move simulated time on; after resume, the wall pace goes on from there."""
    clock = _clock()
    _tick(clock, T0)
    _tick(clock, T0 + 0.004)
    clock.pause(T0 + 0.004)
    for _ in range(3):  # ~/step with step_periods 3, control periods of 40 steps
        clock.advanced(40)
    clock.stepped(3 * 40)
    assert clock.steps == 160 and clock.manual_steps == 120
    clock.resume(T0 + 1.004)
    assert _tick(clock, T0 + 1.008) == 40
    window = clock.window(T0 + 1.008)
    assert window.realtime_factor == pytest.approx(80 * DT_S / 0.008)  # ~/step's left out


def test_a_new_realtime_factor_keeps_simulated_time_continuous() -> None:
    """Simulated time so far stays; the steps due from then on come at the new pace."""
    clock = _clock()
    _tick(clock, T0)
    assert _tick(clock, T0 + 0.010) == 100
    clock.set_realtime_factor(2.0, T0 + 0.010)
    assert clock.due(T0 + 0.010) == 0
    assert _tick(clock, T0 + 0.014) == 80
    clock.pause(T0 + 0.014)
    clock.set_realtime_factor(1.0, T0 + 0.5)  # paused: from where it stopped
    clock.resume(T0 + 0.5)
    assert _tick(clock, T0 + 0.504) == 40


def test_the_diagnostics_window_counts_a_stall_no_tick_has_seen() -> None:
    """window() takes the steps' count of a stall before reporting it, in that window."""
    clock = _clock()
    _tick(clock, T0)
    window = clock.window(T0 + 0.5)
    assert window.stalled_s == pytest.approx((5000 - MAX_CATCH_UP_PERIODS * 40) * DT_S)
    assert clock.window(T0 + 0.5).stalled_s == 0.0  # a new window
    assert clock.window(T0 + 0.5).realtime_factor is None  # under 1 ms of wall time


def test_lockstep_runs_each_command_while_running() -> None:
    """Running, every command's period runs at once."""
    gate = LockstepGate()
    assert gate.command() and gate.command()
    assert not gate.pending and gate.budget == 0


def test_lockstep_paused_commands_wait_for_resume() -> None:
    """Paused, the latest command waits; resume runs its period, and only that one."""
    gate = LockstepGate()
    assert gate.pause() and not gate.pause()
    assert not gate.command() and not gate.command()
    assert gate.pending
    assert gate.resume() and not gate.pending
    assert not gate.resume()  # running: nothing waits
    assert gate.command()


def test_lockstep_step_lets_the_waiting_command_and_the_next_through() -> None:
    """step(3): the waiting command's period now, then two more commands, then they wait."""
    gate = LockstepGate()
    gate.pause()
    gate.command()
    assert gate.step(3) and gate.budget == 2
    assert gate.command() and gate.command()
    assert not gate.command() and gate.pending
    gate.resume()
    assert gate.budget == 0


def test_lockstep_step_without_a_waiting_command() -> None:
    """step(2) with nothing waiting: the next two commands run, one period each."""
    gate = LockstepGate()
    gate.pause()
    assert not gate.step(2) and gate.budget == 2
    assert gate.command() and gate.command() and not gate.command()


def test_lockstep_periods_end_at_the_end_time() -> None:
    """The last period is shortened to end exactly at end_steps; then the run has ended."""
    gate = LockstepGate()
    assert gate.period_steps(40, None) == 40 and not gate.ended(None)
    gate.advanced(40)
    gate.advanced(40)
    assert gate.period_steps(40, 100) == 20
    gate.advanced(20)
    assert gate.ended(100) and not gate.ended(101)


def test_lockstep_rewind_clears_what_waits_unless_at_zero() -> None:
    """A reset at t = 0 changes nothing (the command taken keeps its place); later it rewinds."""
    gate = LockstepGate()
    gate.pause()
    gate.command()
    assert not gate.rewind() and gate.pending
    gate.step(3)
    gate.advanced(40)
    assert gate.rewind()
    assert (gate.steps, gate.pending, gate.budget) == (0, False, 0)
