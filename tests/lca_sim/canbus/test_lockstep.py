"""The lockstep CAN loop's clock and gate (lca_sim.canbus.lockstep), without a bus.

The wall times are passed in, as the node passes `time.monotonic()`: each case states the
time that passed.
"""

from __future__ import annotations

import pytest

from lca_sim.canbus.lockstep import CycleClock, LockstepLoop

PERIOD_S = 0.004
RESEND_S = 1.0


class Master:
    """Stands for `Cia402Master.cycle`: records the simulated time of each SYNC sent."""

    def __init__(self) -> None:
        self.syncs: list[float] = []

    def cycle(self, now_s: float) -> None:
        """One cycle: its SYNC at `now_s`."""
        self.syncs.append(now_s)


def _loop() -> tuple[LockstepLoop, Master]:
    master = Master()
    return LockstepLoop(CycleClock(PERIOD_S), master.cycle, RESEND_S), master


def test_the_clock_counts_syncs_from_zero() -> None:
    """SYNC k is at k periods; before the first, the clock reads 0."""
    clock = CycleClock(PERIOD_S)
    assert clock.now() == 0.0
    assert [clock.next_sync() for _ in range(4)] == pytest.approx([0.0, 0.004, 0.008, 0.012])
    assert clock.now() == pytest.approx(0.012)
    with pytest.raises(ValueError, match="period_s"):
        CycleClock(0.0)


def test_one_sync_per_answer_and_none_for_a_command_answering_nothing() -> None:
    """The answer to a state releases the next SYNC; a second command in the cycle does not."""
    loop, master = _loop()
    assert not loop.on_command(0.0)  # before the start: nothing to answer
    loop.start(0.0)
    assert master.syncs == [0.0]
    loop.on_state(0.001)
    assert loop.on_command(0.002)
    assert master.syncs == pytest.approx([0.0, 0.004])
    assert not loop.on_command(0.003)  # no state awaits an answer: in force, no SYNC
    assert loop.counters.early_commands == 1
    loop.on_state(0.004)
    assert loop.on_command(0.005)
    assert len(master.syncs) == 3
    assert loop.counters.syncs == 3 and loop.counters.commands == 2


def test_a_silent_controller_gets_the_state_again_and_time_stands() -> None:
    """No answer for resend_s: 'resend' (no SYNC), again after another resend_s."""
    loop, master = _loop()
    loop.start(0.0)
    loop.on_state(0.0)
    assert loop.on_tick(RESEND_S * 0.9) == ""
    assert loop.waiting_for_command_s(RESEND_S * 0.9) == pytest.approx(RESEND_S * 0.9)
    assert loop.on_tick(RESEND_S * 1.1) == "resend"
    assert loop.on_tick(RESEND_S * 1.5) == ""
    assert loop.on_tick(RESEND_S * 2.2) == "resend"
    assert master.syncs == [0.0]  # simulated time stood still
    assert loop.counters.resent_states == 2
    assert loop.on_command(RESEND_S * 2.3)  # the controller is back: the loop goes on
    assert len(master.syncs) == 2


def test_an_incomplete_cycle_is_given_up_after_resend_s() -> None:
    """No complete state for resend_s (a TPDO lost): the next SYNC goes, counted."""
    loop, master = _loop()
    loop.start(0.0)  # SYNC 0 sent; its state never completes
    assert loop.on_tick(RESEND_S * 0.5) == ""
    assert loop.on_tick(RESEND_S * 1.1) == "incomplete"
    assert master.syncs == pytest.approx([0.0, 0.004])
    assert loop.counters.incomplete_cycles == 1
    assert loop.waiting_for_command_s(RESEND_S * 1.2) == 0.0  # it waits for a state
