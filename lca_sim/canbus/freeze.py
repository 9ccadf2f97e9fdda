"""Freezes of this process, as a periodic thread sees them, and how much of one a deadline forgives.

The master's cycle thread and the rack's monitor share the judgement: a tick later than its due
time by more than `FREEZE_THRESHOLD_S` means the process stood still (a library load holding
the GIL, a paused host), and the silence deadlines move on by the freeze, at most by a bound,
never past now (`lca_sim.runtime.discounted`; docs/can.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lca_sim.runtime import FREEZE_THRESHOLD_S


@dataclass(frozen=True, slots=True)
class Freeze:
    """One stall of this process: how long, and how much of it the deadlines discount."""

    frozen_s: float
    discount_s: float

    @property
    def beyond_bound(self) -> bool:
        """The stall was longer than the deadlines may discount."""
        return self.frozen_s > self.discount_s


class FreezeWatch:
    """Tells a periodic thread that its process stood still; counts the stalls.

    Args:
        max_discount_s: the most of one stall the deadlines discount (the rest counts against
            them, as it would on a device that froze); inf: all of it.
    """

    def __init__(self, max_discount_s: float = math.inf) -> None:
        self.max_discount_s = max_discount_s
        self.count = 0
        self.longest_s = 0.0

    def check(self, late_s: float) -> Freeze | None:
        """The stall behind a tick `late_s` after its due time, or None if it was no freeze."""
        if not late_s > FREEZE_THRESHOLD_S:  # NaN (no previous tick) is no freeze either
            return None
        self.count += 1
        self.longest_s = max(self.longest_s, late_s)
        return Freeze(late_s, min(late_s, self.max_discount_s))
