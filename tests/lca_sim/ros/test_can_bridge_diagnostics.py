"""The bridge's late-command judgement: lateness that lasts is a WARN, a one-off stall is not."""

from __future__ import annotations

import itertools

from hypothesis import given
from hypothesis import strategies as st

from lca_sim.ros.can_bridge_diagnostics import LATE_COMMAND_PERIODS, LATE_COMMAND_SHARE, LateShare

CYCLES_PER_PERIOD = 500  # 500 Hz, 1 s diagnostics period


def shares(late_per_period: list[int]) -> list[float]:
    """The judged share after each period, for these late cycles per 500-cycle period."""
    judge = LateShare()
    in_time = late = 0
    judged = []
    for period_late in late_per_period:
        late += period_late
        in_time += CYCLES_PER_PERIOD - period_late
        window = judge.update(in_time, late)
        assert window is not None
        judged.append(window[0])
    return judged


def test_a_one_off_stall_is_not_lateness_that_lasts() -> None:
    """A 70 ms freeze (35 late cycles at 500 Hz, 7 % of its second) stays under the threshold."""
    judged = shares([0, 0, 35, 0, 0, 0])
    assert max(judged) == 35 / (LATE_COMMAND_PERIODS * CYCLES_PER_PERIOD)  # 2.3 %
    assert max(judged) <= LATE_COMMAND_SHARE


def test_lasting_lateness_is_judged_within_the_window() -> None:
    """10 % late from the third period on: over the threshold from the period after it."""
    judged = shares([0, 0, 50, 50, 50, 50])
    over = [share > LATE_COMMAND_SHARE for share in judged]
    assert over == [False, False, False, True, True, True]
    assert judged[-1] == 0.10


@given(st.lists(st.integers(min_value=0, max_value=CYCLES_PER_PERIOD), min_size=1, max_size=20))
def test_the_share_is_that_of_the_last_periods(late_per_period: list[int]) -> None:
    judged = shares(late_per_period)
    for k, share in enumerate(judged):
        window = late_per_period[max(0, k + 1 - LATE_COMMAND_PERIODS) : k + 1]
        assert share == sum(window) / (len(window) * CYCLES_PER_PERIOD)


def test_no_cycle_no_judgement() -> None:
    judge = LateShare()
    assert judge.update(0, 0) is None
    counts = itertools.count(100, 100)
    assert judge.update(next(counts), 0) == (0.0, 100)
