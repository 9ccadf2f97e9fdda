"""The rack's monitor: watchdogs and event-driven TPDOs run when something can be due (shell).

A part of the virtual drive rack (realtime timing; in lockstep the SYNCs do all of it). Its
work, a tick, is what a drive's own timer hardware does: discount a freeze of this process,
fire the watchdogs whose deadline passed (`RackWatchdogs`), send the event-driven TPDOs that
are due (`PdoEngine.service_event_tpdos`). docs/can.md, "Watchdogs and safety".

When it ticks:

* at the end of every SYNC's handling (`on_sync`): while SYNCs come, they are the ticks;
* on its thread at its due time: while SYNCs come (one within `SYNCS_FLOW_S`), the earliest
  deadline that a silence of the master could make fire (SYNC loss, RPDO deadlines, heartbeat
  consumers, event timers, the end of an inhibit time), at least `MONITOR_PERIOD_S` and at most
  `MONITOR_MAX_SLEEP_S` ahead; without SYNCs, every `MONITOR_PERIOD_S` as before. A SYNC
  moves the due time on, so at 500 Hz the thread wakes about once per SYNC-loss time, not 200
  times a second;
* within `MONITOR_PERIOD_S` of a frame or a write that may have armed a deadline or changed an
  event-driven TPDO between SYNCs (`poke`: NMT, SDO, a first heartbeat or RPDO, an RPDO
  applied at once, a fault injected by the API).

Freezes: the due time is when the monitor had to run. Whoever runs first after it, the thread
or a SYNC, judges the lateness: more than `FREEZE_THRESHOLD_S` late means this process stood
still, since the tick a period after the last one (as the ticks every 5 ms before this judged
it), and the deadlines are discounted by that (`RackWatchdogs.tick`, `FreezeWatch`). A silent
master makes no tick late (the thread runs on time), so the SYNC that ends its silence is no
freeze. A stall that ends before the due time is not counted: no deadline could fire in it.
"""

from __future__ import annotations

import logging
import math
import threading
import time

from lca_sim.canbus.rack_pdo import PdoEngine
from lca_sim.canbus.rack_state import RackCounters
from lca_sim.canbus.rack_watchdog import RackWatchdogs
from lca_sim.runtime import FREEZE_THRESHOLD_S

logger = logging.getLogger(__name__)

MONITOR_PERIOD_S = 0.005  # the ticks' resolution, and their period while no SYNC comes
MONITOR_MAX_SLEEP_S = 0.1  # the longest wait with nothing armed: a freeze is still counted
SYNCS_FLOW_S = 2 * MONITOR_PERIOD_S  # SYNCs come: the last one is no older than this


class RackMonitor:
    """Ticks the rack's watchdogs and event-driven TPDOs (see the module).

    Args:
        lock: the rack's lock (every tick and `poke` hold it).
        watchdogs: the rack's deadlines and freeze watch.
        pdos: the rack's PDOs (event-driven TPDOs).
        counters: the rack's counters (an error in a tick is counted in `handler_errors`).
    """

    def __init__(
        self,
        lock: threading.RLock,
        watchdogs: RackWatchdogs,
        pdos: PdoEngine,
        counters: RackCounters,
    ) -> None:
        self._lock = lock
        self._watchdogs = watchdogs
        self._pdos = pdos
        self._counters = counters
        self._due_s = math.inf  # when the next tick is due (monotonic s)
        self._waits_until_s = math.inf  # what the thread's wait ends at
        self._last_sync_s = -math.inf
        self._ticked_s = -math.inf  # the last tick
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.wakeups = 0  # the thread's wake-ups (timeouts and pokes)

    def start(self) -> None:
        """Start the thread: its first tick `MONITOR_PERIOD_S` from now."""
        with self._lock:
            self._ticked_s = time.monotonic()
            self._due_s = self._ticked_s + MONITOR_PERIOD_S
        self._thread = threading.Thread(target=self._run, name="virtual-drive-monitor", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and wait for it."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()

    def on_sync(self, done_s: float) -> None:
        """The end of a SYNC's handling (the lock held): a tick."""
        self._last_sync_s = done_s
        self._tick(done_s)

    def poke(self, now: float) -> None:
        """Something may be due within `MONITOR_PERIOD_S` (the lock held): tick by then."""
        if self._thread is None:
            return
        due_s = now + MONITOR_PERIOD_S
        if due_s < self._due_s:
            self._due_s = due_s
            if due_s < self._waits_until_s:
                self._wake.set()

    def _tick(self, now: float) -> None:
        late_s = now - self._due_s
        period_end_s = now + MONITOR_PERIOD_S
        self._due_s = period_end_s  # if the work below raises
        if late_s > FREEZE_THRESHOLD_S:
            # It stood still, since when a tick every period after the last would have come.
            late_s = max(late_s, now - self._ticked_s - MONITOR_PERIOD_S)
            earliest = self._watchdogs.tick(late_s, now)
        else:  # on time (at every SYNC): no freeze to judge
            earliest = self._watchdogs.check(now)
        self._ticked_s = now
        tpdo_due_s = self._pdos.service_event_tpdos(now)
        if now - self._last_sync_s < SYNCS_FLOW_S:
            earliest = min(earliest, tpdo_due_s, now + MONITOR_MAX_SLEEP_S)
            if earliest > period_end_s:
                self._due_s = earliest

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                self._waits_until_s = self._due_s
            poked = self._wake.wait(max(self._waits_until_s - time.monotonic(), 0.0))
            self.wakeups += 1
            if poked:
                self._wake.clear()
                continue
            try:
                with self._lock:
                    now = time.monotonic()
                    if now >= self._due_s:  # else a SYNC ticked meanwhile: wait again
                        self._tick(now)
            except Exception:
                self._counters.handler_errors += 1
                logger.exception("virtual drive: error in the monitor")
