"""Process set-up for the cyclic loops: the collector and the GIL out of their way, freezes judged.

A full (generation 2) collection walks every object the process holds. After start-up that is
Pinocchio, numba's compiled code, rclpy and canopen: about 150 000 objects here (200 000 when
numba has just compiled from a cold cache), 70-120 ms for one collection on this machine, with
the GIL held. That stalls every thread of the process: a CAN cycle, a drive's watchdog, a
lockstep loop. `settle_heap` collects once at start-up, then freezes what is alive (gc.freeze):
later collections see only the objects made since, and take well under a millisecond.

Threads of one process share the GIL. A thread that has just sent frames to another thread of
the same process (the virtual drive rack to the bridge on python-can's in-process bus) and goes
on computing keeps the reader waiting for up to the switch interval. `yield_gil` hands over at
that point instead.

A whole process can still stand still (a collection, a library load, a paused host): a
`FreezeWatch` tells its periodic thread or timer so, and the deadlines it watches forgive it.
"""

from __future__ import annotations

import gc
import logging
import math
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import FrameType

# A cyclic thread that wakes this much later than due was frozen with its whole process (the
# GIL held by a collection or a library load, the host paused). The CAN bridge's cycle, the
# virtual drive's monitor and the simulator's timers then shift their silence deadlines by the
# freeze instead of blaming the other side for it. It must stay below the tightest deadline
# they watch (SYNC loss: 10 periods, 20 ms at 500 Hz).
FREEZE_THRESHOLD_S = 0.01
# Python's default GIL switch interval (5 ms) lets one thread hold the interpreter for several
# CAN periods; every process that runs a CAN cycle (the bridge's master, the virtual rack, the
# benchmark) sets this instead.
GIL_SWITCH_INTERVAL_S = 5e-4


def discounted(stamp_s: float, frozen_s: float, now_s: float) -> float:
    """A last-heard time moved on by a freeze of this process, but never past now.

    A frame taken between the freeze and the thread that noticed it has stamped the time
    afresh already; moving that stamp on too would let the sender's silence go unseen for
    another freeze's length.
    """
    return min(stamp_s + frozen_s, now_s)


@dataclass(frozen=True, slots=True)
class Freeze:
    """One stall of this process: how long, and how much of it the deadlines discount."""

    frozen_s: float
    discount_s: float

    @property
    def beyond_bound(self) -> bool:
        """The stall was longer than the deadlines may discount."""
        return self.frozen_s > self.discount_s


class _FirstSaid:
    """Which stalls are logged: the first one, and the first longer than its deadline."""

    def __init__(self) -> None:
        self._long_said = False

    def say(
        self, count: int, length_s: float, deadline_s: float, text: str
    ) -> tuple[int, str] | None:
        """The log line of stall number `count` (from 1), `length_s` long, or None: counted.

        INFO for the first, WARNING for the first one longer than `deadline_s` (a deadline a
        peer watches would have tripped), whether or not it is the first. In `text`, `{ms}`
        becomes the length and `{longer}` ", longer than the deadline (...)" when it was.
        """
        beyond = length_s > deadline_s
        if not (count == 1 or (beyond and not self._long_said)):
            return None
        self._long_said = self._long_said or beyond
        longer = f", longer than the deadline ({deadline_s:g} s)" if beyond else ""
        line = text.replace("{ms}", f"{length_s * 1e3:.0f}").replace("{longer}", longer)
        return (logging.WARNING if beyond else logging.INFO), line


class FreezeWatch:
    """Tells a periodic thread or timer that its process stood still; counts the stalls.

    A tick later than its due time by more than `FREEZE_THRESHOLD_S` means the process stood
    still, and the silence deadlines move on by the freeze, at most by `max_discount_s`, never
    past now (`discounted`). Users: the bridge's cycle thread, the virtual drive's monitor
    (docs/can.md) and the simulator's timers (docs/nodes.md).

    Args:
        max_discount_s: the most of one stall the deadlines discount (the rest counts against
            them, as it would on a device that froze); inf: all of it.
    """

    def __init__(self, max_discount_s: float = math.inf) -> None:
        self.max_discount_s = max_discount_s
        self.count = 0
        self.longest_s = 0.0
        self._said = _FirstSaid()

    def check(self, late_s: float) -> Freeze | None:
        """The stall behind a tick `late_s` after its due time, or None if it was no freeze."""
        if not late_s > FREEZE_THRESHOLD_S:  # NaN (no previous tick) is no freeze either
            return None
        self.count += 1
        self.longest_s = max(self.longest_s, late_s)
        return Freeze(late_s, min(late_s, self.max_discount_s))

    def note(self, freeze: Freeze, deadline_s: float, then: str) -> tuple[int, str] | None:
        """What to log of `freeze` (a logging level and the text), or None: only counted.

        The first freeze is said at INFO, or at WARNING when it lasted longer than
        `deadline_s` (a deadline a peer watches would have tripped); so is the first such
        longer one. `then` says what follows from it ("the controller's silence does not
        count it").
        """
        return self._said.say(
            self.count,
            freeze.frozen_s,
            deadline_s,
            f"this process stood still for {{ms}} ms{{longer}}; {then} "
            "(further freezes are only counted)",
        )


class SlowCalls:
    """Counts the calls that took longer than `FREEZE_THRESHOLD_S`; says the first ones.

    The CAN bridge times each publish of the plant's state: Fast DDS's write can wait for its
    writer's lock while discovery checks a newly joined peer's shared-memory port, with the GIL
    held, so the cycle thread and everything else in the process wait as long
    (docs/can-transport.md, "The 331 ms stall").

    Args:
        what: the call, as the log names it ("publishing the plant's state").
        deadline_s: a wait longer than this is said at WARNING (a peer's deadline would trip).
        why: what such a wait means and what to do about it, appended to the log line.
    """

    def __init__(self, what: str, deadline_s: float, why: str) -> None:
        self.what = what
        self.deadline_s = deadline_s
        self.why = why
        self._watch = FreezeWatch()  # counts the slow ones as it counts freezes
        self._said = _FirstSaid()

    @property
    def count(self) -> int:
        """How many calls were slow."""
        return self._watch.count

    @property
    def longest_s(self) -> float:
        """The slowest call's duration, s (0 before the first slow one)."""
        return self._watch.longest_s

    def took(self, duration_s: float) -> tuple[int, str] | None:
        """Count a call that lasted `duration_s`; what to log of it, or None (fast, or counted)."""
        if self._watch.check(duration_s) is None:
            return None
        return self._said.say(
            self.count,
            duration_s,
            self.deadline_s,
            f"{self.what} took {{ms}} ms{{longer}}: {self.why} "
            "(further slow ones are only counted)",
        )


def settle_heap() -> int:
    """Collect now, then move every live object out of the collector's sight.

    Call it once a process has built its long-lived objects, before its cyclic work starts.
    Returns how many objects were frozen. Cycles among frozen objects are never collected, so
    call it after start-up, not in a loop.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def yield_gil() -> None:
    """Release the GIL once, so a thread woken by what this one just sent can run first.

    `time.sleep(0)` releases the GIL and takes it back at once; a thread waiting for it usually
    takes it in between (usually: the OS decides, nothing guarantees it). It does not wait: with
    no other thread ready it returns immediately.
    Measured in bench/can_cycle.py at 500 Hz: SYNC -> last TPDO p50 from 1.1-1.2 to 0.67-0.91 ms
    (five runs).
    """
    time.sleep(0)


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def stop_signals(on_stop: Callable[[str], None]) -> Iterator[None]:
    """Inside the block, SIGINT and SIGTERM call `on_stop` with the signal's name.

    The handlers that were set before come back when the block ends, however it ends.
    """

    def handler(signum: int, _frame: FrameType | None) -> None:
        on_stop(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
