"""The SYNC-rate judge: jitter and stalls never count, a second producer is caught within 1 s.

The SYNC stamps are built here as a producer sends them: due every 0x1006, each off its due
time by up to half a period (jitter), and after a stall the SYNCs due in it go out back to back
(python-can's periodic send and canopen's SYNC producer catch up that way).
"""

from __future__ import annotations

import random
from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lca_sim.cia402.sync_rate import (
    SYNC_RATE_TOLERANCE,
    SyncRateError,
    SyncRateParams,
    SyncRateState,
    SyncVerdict,
    judge_sync,
    sync_rate_params,
)

SHIPPED_SYNC_LOSS_PERIODS = 10.0  # config/can/rack.yaml
RATES_HZ = (250.0, 500.0, 1000.0)
JITTER_STYLES = ("uniform", "extremes", "alternate", "runs")
EPOCH_S = 1.7e9  # python-can's virtual bus stamps with time.time()


def jitter(style: str, n: int, seed: int) -> list[float]:
    """`n` offsets from the due times, in periods, each within +-0.5."""
    rng = random.Random(seed)
    if style == "uniform":
        return [rng.uniform(-0.5, 0.5) for _ in range(n)]
    if style == "extremes":
        return [rng.choice((-0.5, 0.5)) for _ in range(n)]
    if style == "alternate":  # late, early, late, ...: each late SYNC's surplus is needed next
        return [0.5 if k % 2 == 0 else -0.5 for k in range(n)]
    offsets: list[float] = []  # runs of late SYNCs, then runs of early ones
    while len(offsets) < n:
        offsets += [rng.choice((-0.5, 0.5))] * rng.randint(1, 200)
    return offsets[:n]


def producer(
    start_s: float,
    period_s: float,
    offsets: Sequence[float],
    stalls: Sequence[tuple[int, float]] = (),
    spread_s: float = 0.0,
) -> list[float]:
    """The stamps of one producer's SYNCs.

    Args:
        start_s: the first SYNC's due time, s.
        period_s: 0x1006, s.
        offsets: each SYNC's jitter, in periods.
        stalls: (index of the first SYNC it delays, length in periods): the producer stands
            still that long, then sends the SYNCs due meanwhile back to back. A stall that
            would start within an earlier one's burst is left out (it would make one longer
            stall).
        spread_s: the time between two SYNCs of such a burst, s.
    """
    stamps = [start_s + (k + offset) * period_s for k, offset in enumerate(offsets)]
    resumed = 0  # a stall starts at a SYNC sent in time, not in the burst of an earlier one
    for first, length_periods in sorted(stalls):
        if first < resumed:
            continue
        end_s = stamps[first] + length_periods * period_s
        resumed = first
        while resumed < len(stamps) and stamps[resumed] < end_s:
            stamps[resumed] = end_s + (resumed - first) * spread_s
            resumed += 1
        resumed += 1
    for k in range(1, len(stamps)):  # one producer's frames leave in order
        stamps[k] = max(stamps[k], stamps[k - 1])
    return stamps


def judge_all(stamps: Sequence[float], params: SyncRateParams) -> list[SyncVerdict]:
    """The verdict on each SYNC, in order."""
    state = SyncRateState()
    verdicts = []
    for stamp_s in stamps:
        state, verdict = judge_sync(state, stamp_s, params)
        verdicts.append(verdict)
    return verdicts


@st.composite
def single_producer(draw: st.DrawFn) -> tuple[SyncRateParams, list[float]]:
    """One producer with +-50 % jitter and stalls up to the SYNC-loss deadline, then bursts."""
    rate_hz = draw(st.sampled_from(RATES_HZ) | st.floats(20.0, 2000.0))
    period_s = 1.0 / rate_hz
    loss_periods = draw(st.just(SHIPPED_SYNC_LOSS_PERIODS) | st.floats(1.0, 20.0))
    n = draw(st.integers(2, 2500))
    offsets = jitter(draw(st.sampled_from(JITTER_STYLES)), n, draw(st.integers(0, 2**32 - 1)))
    stalls = draw(
        st.lists(
            st.tuples(st.integers(0, n - 1), st.floats(0.0, loss_periods)),
            max_size=12,
        )
    )
    spread_s = draw(st.floats(0.0, 0.2)) * period_s
    start_s = draw(st.just(EPOCH_S) | st.floats(0.0, 2.0e9))
    return (
        sync_rate_params(period_s, loss_periods),
        producer(start_s, period_s, offsets, stalls, spread_s),
    )


@settings(max_examples=300, deadline=None)
@given(case=single_producer())
def test_one_producer_with_jitter_and_stalls_is_never_too_fast(
    case: tuple[SyncRateParams, list[float]],
) -> None:
    """+-50 % jitter, stalls up to the SYNC-loss deadline and their bursts: every SYNC counts."""
    params, stamps = case
    verdicts = judge_all(stamps, params)
    assert [v for v in verdicts if v is not SyncVerdict.IN_TIME] == []
    assert verdicts.count(SyncVerdict.IN_TIME) == len(stamps)  # no plant step lost


@st.composite
def frozen_producer(draw: st.DrawFn) -> tuple[SyncRateParams, list[float]]:
    """One producer whose process stands still up to 0.8 of `max_gap_s` (0.2 s) at times."""
    period_s = 1.0 / draw(st.sampled_from(RATES_HZ))
    params = sync_rate_params(period_s, SHIPPED_SYNC_LOSS_PERIODS)
    n = round(draw(st.floats(0.5, 4.0)) / period_s)
    offsets = jitter(draw(st.sampled_from(JITTER_STYLES)), n, draw(st.integers(0, 2**32 - 1)))
    longest_periods = 0.8 * params.max_gap_s / period_s
    stalls = draw(
        st.lists(st.tuples(st.integers(1, n - 1), st.floats(0.0, longest_periods)), max_size=12)
    )
    spread_s = draw(st.floats(0.0, 0.1)) * period_s  # a burst goes out back to back
    return params, producer(EPOCH_S, period_s, offsets, stalls, spread_s)


@settings(max_examples=150, deadline=None)
@given(case=frozen_producer())
def test_a_producer_standing_still_up_to_0_2_s_is_never_too_fast(
    case: tuple[SyncRateParams, list[float]],
) -> None:
    """Stalls far beyond the SYNC-loss deadline (this process frozen), then their bursts."""
    params, stamps = case
    verdicts = judge_all(stamps, params)
    assert verdicts.count(SyncVerdict.IN_TIME) == len(stamps)


@settings(max_examples=100, deadline=None)
@given(
    rate_hz=st.sampled_from(RATES_HZ),
    loss_periods=st.floats(1.0, SHIPPED_SYNC_LOSS_PERIODS),
    lead_s=st.floats(0.0, 3.0),
    phase=st.floats(0.0, 1.0),
    styles=st.tuples(st.sampled_from(JITTER_STYLES), st.sampled_from(JITTER_STYLES)),
    seeds=st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1)),
)
def test_a_second_producer_at_the_same_rate_is_caught_within_1_s(
    rate_hz: float,
    loss_periods: float,
    lead_s: float,
    phase: float,
    styles: tuple[str, str],
    seeds: tuple[int, int],
) -> None:
    """Two interleaved producers, both jittered: one report within 1 s, the plant at wall time."""
    period_s = 1.0 / rate_hz
    params = sync_rate_params(period_s, loss_periods)
    run_s = lead_s + 2.0
    n_first = round(run_s / period_s)
    second_start_s = EPOCH_S + lead_s + phase * period_s
    n_second = round((run_s - lead_s) / period_s) - 1
    stamps = sorted(
        producer(EPOCH_S, period_s, jitter(styles[0], n_first, seeds[0]))
        + producer(second_start_s, period_s, jitter(styles[1], n_second, seeds[1]))
    )
    verdicts = judge_all(stamps, params)
    reports = [s for s, v in zip(stamps, verdicts, strict=True) if v is SyncVerdict.TOO_FAST_REPORT]
    assert len(reports) == 1  # one episode for as long as both run
    assert reports[0] - (second_start_s - 0.5 * period_s) <= 1.0
    admitted = verdicts.count(SyncVerdict.IN_TIME)
    elapsed_periods = (stamps[-1] - stamps[0]) / period_s
    # the plant runs no faster than the wall clock (+ tolerance) beyond two burst allowances
    # (the credit a fresh judge starts with, and the debt it allows)
    assert admitted <= elapsed_periods * (1.0 + SYNC_RATE_TOLERANCE) + 2 * params.burst_syncs


@settings(max_examples=100, deadline=None)
@given(
    rate_hz=st.sampled_from(RATES_HZ),
    lead_s=st.floats(0.0, 2.0),
    silence_s=st.floats(0.0, 10.0),
    phase=st.floats(0.0, 1.0),
)
def test_a_second_producer_after_a_silence_is_caught_within_1_s(
    rate_hz: float, lead_s: float, silence_s: float, phase: float
) -> None:
    """The time a bus stood silent pays for no more than half a window of extra SYNCs."""
    period_s = 1.0 / rate_hz
    params = sync_rate_params(period_s, SHIPPED_SYNC_LOSS_PERIODS)
    before = producer(EPOCH_S, period_s, [0.0] * round(lead_s / period_s))
    restart_s = EPOCH_S + lead_s + silence_s
    n = round(1.5 / period_s)
    both = producer(restart_s, period_s, [0.0] * n) + producer(
        restart_s + phase * period_s, period_s, [0.0] * n
    )
    stamps = before + sorted(both)
    verdicts = judge_all(stamps, params)
    reports = [s for s, v in zip(stamps, verdicts, strict=True) if v is SyncVerdict.TOO_FAST_REPORT]
    assert len(reports) == 1
    assert reports[0] - restart_s <= 1.0


@pytest.mark.parametrize("rate_hz", RATES_HZ)
@pytest.mark.parametrize("start_s", [0.0, EPOCH_S])
def test_the_nominal_rate_is_never_too_fast(rate_hz: float, start_s: float) -> None:
    """20 s of SYNCs exactly every 0x1006: all of them advance the plant."""
    period_s = 1.0 / rate_hz
    stamps = [start_s + k * period_s for k in range(round(20.0 / period_s))]
    verdicts = judge_all(stamps, sync_rate_params(period_s, SHIPPED_SYNC_LOSS_PERIODS))
    assert verdicts.count(SyncVerdict.IN_TIME) == len(stamps)


@pytest.mark.parametrize(
    ("clock_ratio", "too_fast"),
    [
        (0.99, False),  # a producer whose clock is slow: fewer SYNCs, none too fast
        (1.015, False),  # 1.5 % fast: within the 2 % tolerance, for good
        (1.05, True),  # 5 % fast: beyond it, refused once the allowance is used up
    ],
)
def test_a_producer_clock_within_the_tolerance_is_not_too_fast(
    clock_ratio: float, too_fast: bool
) -> None:
    """A master's clock may run up to 2 % fast for good; beyond that the excess is refused."""
    period_s = 0.002
    stamps = [EPOCH_S + k * period_s / clock_ratio for k in range(30_000)]  # 60 s
    verdicts = judge_all(stamps, sync_rate_params(period_s, SHIPPED_SYNC_LOSS_PERIODS))
    refused = len(stamps) - verdicts.count(SyncVerdict.IN_TIME)
    if too_fast:
        # the plant keeps the wall clock's pace (+2 %): about 3 % of 30,000 are refused
        assert 0.025 * len(stamps) < refused < 0.035 * len(stamps)
        assert verdicts.count(SyncVerdict.TOO_FAST_REPORT) == 1
    else:
        assert refused == 0


def test_an_episode_ends_with_a_window_without_excess_and_a_new_one_is_reported() -> None:
    """Second producer 1 s on, 2 s off, 1 s on: two reports, none while it is off."""
    period_s = 0.002
    params = sync_rate_params(period_s, SHIPPED_SYNC_LOSS_PERIODS)
    first = producer(EPOCH_S, period_s, [0.0] * 2500)  # 5 s
    second = [s + 0.5 * period_s for s in first if 1.0 <= s - EPOCH_S < 2.0]
    second += [s + 0.5 * period_s for s in first if 4.0 <= s - EPOCH_S < 5.0]
    stamps = sorted(first + second)
    verdicts = judge_all(stamps, params)
    pairs = list(zip(stamps, verdicts, strict=True))
    reports = [s - EPOCH_S for s, v in pairs if v is SyncVerdict.TOO_FAST_REPORT]
    assert len(reports) == 2
    assert 1.0 <= reports[0] < 1.5
    assert 4.0 <= reports[1] < 4.5
    refused_while_off = [
        s for s, v in pairs if v is not SyncVerdict.IN_TIME and 2.0 <= s - EPOCH_S < 4.0
    ]
    assert refused_while_off == []  # the debt is carried, but a single producer pays its way


@pytest.mark.parametrize("step_s", [-10.0, -1e-3, 1e-3, 10.0])
def test_a_stamp_clock_step_is_not_too_fast(step_s: float) -> None:
    """The stamps' clock stepped back or forward (time.time() set): nothing refused."""
    period_s = 0.001
    stamps = [EPOCH_S + k * period_s + (step_s if k >= 1500 else 0.0) for k in range(3000)]
    verdicts = judge_all(stamps, sync_rate_params(period_s, SHIPPED_SYNC_LOSS_PERIODS))
    assert verdicts.count(SyncVerdict.IN_TIME) == len(stamps)


def test_shipped_params() -> None:
    """rack.yaml's 10 periods: 12 SYNCs of burst, a 0.5 s window, a gap earns up to 0.25 s."""
    params = sync_rate_params(0.002, SHIPPED_SYNC_LOSS_PERIODS)
    assert params == SyncRateParams(
        period_s=0.002, burst_syncs=12.0, window_s=0.5, max_gap_s=0.25, tolerance=0.02
    )
    slow = sync_rate_params(0.1, 3.0)  # 10 Hz: the window grows to 8 burst allowances
    assert (slow.burst_syncs, slow.window_s, slow.max_gap_s) == (5.0, 4.0, 2.0)


@pytest.mark.parametrize(
    "values",
    [
        {"period_s": 0.0},
        {"period_s": float("nan")},
        {"burst_syncs": 0.5},
        {"window_s": 0.001},
        {"max_gap_s": float("inf")},
        {"tolerance": -0.01},
    ],
)
def test_bad_params_are_refused(values: dict[str, float]) -> None:
    """Each parameter out of its range raises SyncRateError naming it."""
    good = {"period_s": 0.002, "burst_syncs": 12.0, "window_s": 0.5, "max_gap_s": 0.25}
    with pytest.raises(SyncRateError, match=next(iter(values))):
        SyncRateParams(**(good | values))


@pytest.mark.parametrize("loss_periods", [0.5, float("nan")])
def test_bad_sync_loss_periods_are_refused(loss_periods: float) -> None:
    """The SYNC-loss deadline must be at least one period."""
    with pytest.raises(SyncRateError, match="sync_loss_periods"):
        sync_rate_params(0.002, loss_periods)
