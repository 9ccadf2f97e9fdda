"""The bridge's late-command judgement: lateness that lasts is a WARN.

The controller's start and a one-off stall of the host are not.
"""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from lca_sim.ros.can_bridge_diagnostics import LATE_COMMAND_PERIODS, LATE_COMMAND_SHARE, LateShare

CYCLES_PER_PERIOD = 500  # 500 Hz, 1 s diagnostics period


def shares(late_per_period: list[int]) -> list[float | None]:
    """The judged share after each period, for these late cycles per 500-cycle period."""
    judge = LateShare()
    in_time = late = 0
    judged = []
    for period_late in late_per_period:
        late += period_late
        in_time += CYCLES_PER_PERIOD - period_late
        window = judge.update(in_time, late)
        judged.append(None if window is None else window[0])
    return judged


def test_the_first_periods_after_the_first_command_are_not_judged() -> None:
    """The controller's start: 10 % late in the first second is no WARN; the window waits."""
    judged = shares([50, 0, 0, 0, 0])
    assert judged[:LATE_COMMAND_PERIODS] == [None] * LATE_COMMAND_PERIODS
    assert judged[LATE_COMMAND_PERIODS:] == [0.0, 0.0]  # the start is outside the window


def test_a_one_off_stall_is_not_lateness_that_lasts() -> None:
    """A 70 ms freeze (35 late cycles at 500 Hz, 7 % of its second) stays under the threshold."""
    judged = [s for s in shares([0, 0, 0, 0, 35, 0, 0, 0]) if s is not None]
    assert max(judged) == 35 / (LATE_COMMAND_PERIODS * CYCLES_PER_PERIOD)  # 2.3 %
    assert max(judged) <= LATE_COMMAND_SHARE


def test_lasting_lateness_is_judged_within_the_window() -> None:
    """10 % late from the fifth period on: over the threshold from the period after it."""
    judged = shares([0, 0, 0, 0, 50, 50, 50, 50])
    over = [share is not None and share > LATE_COMMAND_SHARE for share in judged]
    assert over == [False, False, False, False, False, True, True, True]
    assert judged[-1] == 0.10


@given(st.lists(st.integers(min_value=0, max_value=CYCLES_PER_PERIOD), min_size=1, max_size=20))
def test_the_share_is_that_of_the_last_periods(late_per_period: list[int]) -> None:
    judged = shares(late_per_period)
    for k, share in enumerate(judged):
        if k < LATE_COMMAND_PERIODS:
            assert share is None
            continue
        window = late_per_period[k + 1 - LATE_COMMAND_PERIODS : k + 1]
        assert share == sum(window) / (LATE_COMMAND_PERIODS * CYCLES_PER_PERIOD)


def test_no_command_no_judgement() -> None:
    judge = LateShare()
    assert all(judge.update(0, 0) is None for _ in range(2 * LATE_COMMAND_PERIODS))
