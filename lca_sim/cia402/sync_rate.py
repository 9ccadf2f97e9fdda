"""The SYNC-rate judge: whether a SYNC may advance the plant one 0x1006 period (pure core).

CiA 301 gives a network one SYNC producer, 0x1006 its period; SYNCs that come faster (a second
producer, a master whose cycle does not match 0x1006) must not run the plant faster than the
wall clock. The judge decides from the SYNCs' bus stamps alone, by a balance of periods earned
and spent over a window, so that jitter and stalls with their catch-up bursts never count;
the shell handles an excess SYNC as any other but does not advance the plant for it.
docs/can.md, "Timing on the bus", has the rules and the figures. Nothing here reads a clock.

    params = sync_rate_params(period_s=0.002, sync_loss_periods=10.0)
    state = SyncRateState()
    state, verdict = judge_sync(state, stamp_s, params)   # per SYNC, its bus stamp
    verdict is SyncVerdict.IN_TIME                        # advance the plant one period
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from lca_sim.errors import LcaHilError

# SYNCs may come this much faster than 0x1006 for good (a master's clock is not the drive's).
SYNC_RATE_TOLERANCE = 0.02
# The window over which earned time is kept, s; at least this many burst allowances long so
# that the carried credit is small beside the window (`sync_rate_params`).
SYNC_RATE_WINDOW_S = 0.5
SYNC_RATE_WINDOW_MIN_BURSTS = 8.0
# Beyond the SYNC-loss deadline, the burst allowance covers stamp jitter: two stamps each up
# to half a period off their nominal time, and one SYNC more for the rounding.
SYNC_JITTER_SYNCS = 2.0
# A balance this close to the limit still admits (the stamps' rounding, not a rate).
_EPS_SYNCS = 1e-9


class SyncRateError(LcaHilError, ValueError):
    """A SYNC-rate parameter is out of its range (the message names it and the value)."""


@dataclass(frozen=True, slots=True)
class SyncRateParams:
    """How the SYNC rate is judged.

    Attributes:
        period_s: the communication cycle period 0x1006, s (> 0).
        burst_syncs: how many SYNCs beyond the rate are admitted at any time (>= 1).
        window_s: the window over which earned time is kept, s (>= period_s).
        max_gap_s: the most time one gap between SYNCs earns, s (>= period_s): a stall's
            catch-up burst is paid up to this, a silence earns no more.
        tolerance: SYNCs may come this fraction faster than 0x1006 for good (>= 0).
    """

    period_s: float
    burst_syncs: float
    window_s: float
    max_gap_s: float
    tolerance: float = SYNC_RATE_TOLERANCE

    def __post_init__(self) -> None:
        checks = (
            ("period_s", self.period_s, 0.0, False),
            ("burst_syncs", self.burst_syncs, 1.0, True),
            ("window_s", self.window_s, self.period_s, True),
            ("max_gap_s", self.max_gap_s, self.period_s, True),
            ("tolerance", self.tolerance, 0.0, True),
        )
        for name, value, low, inclusive in checks:
            if not math.isfinite(value) or value < low or (value == low and not inclusive):
                relation = ">=" if inclusive else ">"
                raise SyncRateError(f"{name} must be finite and {relation} {low!r}, got {value!r}")


def sync_rate_params(period_s: float, sync_loss_periods: float) -> SyncRateParams:
    """The judge's parameters for a 0x1006 period and the rack's SYNC-loss deadline.

    The burst allowance is the SYNC-loss deadline plus `SYNC_JITTER_SYNCS`: any stall shorter
    than a SYNC loss may end in a burst of queued SYNCs, even where a window's end cuts it.
    The window is `SYNC_RATE_WINDOW_S`, or `SYNC_RATE_WINDOW_MIN_BURSTS` burst allowances if
    longer; one gap earns at most half a window.

    Args:
        period_s: the communication cycle period 0x1006, s (> 0).
        sync_loss_periods: the SYNC-loss deadline in periods (rack.yaml, >= 1).

    Returns:
        The parameters.

    Raises:
        SyncRateError: a value out of its range.
    """
    if not math.isfinite(sync_loss_periods) or sync_loss_periods < 1.0:
        raise SyncRateError(f"sync_loss_periods must be finite and >= 1, got {sync_loss_periods}")
    burst_syncs = math.ceil(sync_loss_periods) + SYNC_JITTER_SYNCS
    window_s = max(SYNC_RATE_WINDOW_S, SYNC_RATE_WINDOW_MIN_BURSTS * burst_syncs * period_s)
    return SyncRateParams(
        period_s=period_s, burst_syncs=burst_syncs, window_s=window_s, max_gap_s=window_s / 2.0
    )


class SyncVerdict(enum.Enum):
    """What a SYNC does to the plant."""

    IN_TIME = "in time"  # advances the plant one period
    TOO_FAST = "too fast"  # does not advance it; its episode is reported already
    TOO_FAST_REPORT = "too fast, first of an episode"  # likewise, and report it (EMCY 0x8100)


@dataclass(frozen=True, slots=True)
class SyncRateState:
    """The judge's state between SYNCs; `SyncRateState()` before the first one.

    Attributes:
        balance_syncs: periods earned by the stamps minus SYNCs admitted, in periods
            (negative: SYNCs ahead of the time that passed); set to `burst_syncs` at the
            first SYNC.
        window_start_s: the stamp the current window started at, s (None: no SYNC yet).
        last_stamp_s: the previous SYNC's stamp, s (None: no SYNC yet).
        low_balance_syncs: the lowest balance after a SYNC of the current window, in periods.
        refused_in_window: a SYNC of the current window was too fast.
        too_fast: in an episode of too-fast SYNCs (reported); it ends with a window in which
            none was too fast.
    """

    balance_syncs: float = 0.0
    window_start_s: float | None = None
    last_stamp_s: float | None = None
    low_balance_syncs: float = 0.0
    refused_in_window: bool = False
    too_fast: bool = False


def judge_sync(
    state: SyncRateState, stamp_s: float, params: SyncRateParams
) -> tuple[SyncRateState, SyncVerdict]:
    """Judge one SYNC by its bus stamp (the module docstring has the rule).

    Args:
        state: the state after the previous SYNC.
        stamp_s: this SYNC's reception stamp on the bus, s (any clock, the same for all
            SYNCs; stamps that go back are taken as no time passed).
        params: the judge's parameters (a new `SyncRateState` when they change).

    Returns:
        (the state after this SYNC, the verdict).
    """
    balance = state.balance_syncs
    window_start_s = state.window_start_s
    last_stamp_s = state.last_stamp_s
    low_balance = state.low_balance_syncs
    refused = state.refused_in_window
    too_fast = state.too_fast
    if window_start_s is None or last_stamp_s is None:
        # The first SYNC may be the first of a burst (its producer stood still before it):
        # a fresh judge holds one burst allowance of credit, as after a window of SYNCs.
        balance = low_balance = params.burst_syncs
        window_start_s = stamp_s
    else:
        if not 0.0 <= stamp_s - window_start_s < params.window_s:
            # The window ended with the previous SYNC: the credit it never touched expires,
            # a debt stays, and an episode without a too-fast SYNC in the window is over.
            balance -= max(low_balance - params.burst_syncs, 0.0)
            low_balance = balance
            window_start_s = min(last_stamp_s, stamp_s)
            too_fast = too_fast and refused
            refused = False
        elapsed_s = min(max(stamp_s - last_stamp_s, 0.0), params.max_gap_s)
        balance += elapsed_s / params.period_s * (1.0 + params.tolerance)
    if balance - 1.0 >= -params.burst_syncs - _EPS_SYNCS:
        verdict = SyncVerdict.IN_TIME
        balance -= 1.0
    else:
        verdict = SyncVerdict.TOO_FAST if too_fast else SyncVerdict.TOO_FAST_REPORT
        refused = too_fast = True
    low_balance = min(low_balance, balance)
    return (
        SyncRateState(balance, window_start_s, stamp_s, low_balance, refused, too_fast),
        verdict,
    )
