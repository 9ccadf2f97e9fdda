"""The rack's watchdogs: heartbeat consumer, RPDO deadline, SYNC loss and rate, freeze discount.

A part of the virtual drive rack that owns the deadlines' bookkeeping and the stalls of this
process; what a fired watchdog does to a drive (0x603F, EMCY, 0x6007, 0x1029) is the rack's,
handed in as `on_expired`. docs/can.md, "Watchdogs and safety".
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Callable, Sequence

from lca_sim.canbus.rack_state import NMT_OPERATIONAL, Drive, RackCounters
from lca_sim.cia402 import device as cia402
from lca_sim.cia402 import objects as od
from lca_sim.cia402 import sync_rate
from lca_sim.cia402.device import PowerState
from lca_sim.runtime import Freeze, FreezeWatch, discounted

logger = logging.getLogger(__name__)

# `Drive.values` keys read at every SYNC, looked up directly (no `Drive.value` call).
_HEARTBEAT_CONSUMER_1 = (od.HEARTBEAT_CONSUMER, 1)
_CYCLE_PERIOD = (od.CYCLE_PERIOD, 0)


class RackWatchdogs:
    """The deadlines of every drive of a rack, checked at its monitor's ticks.

    Args:
        axes: the rack's drives (their last-heard stamps live on them).
        counters: the rack's counters (losses and timeouts are counted here).
        sync_loss_periods: SYNC loss after this many 0x1006 periods without a SYNC.
        max_stall_discount_s: the most of one stall of this process the deadlines discount.
        on_expired: what a fired watchdog does: (drive, EMCY code, now).
        emcy: sends an EMCY from a drive: (drive, code, manufacturer bytes).
        warn_once: logs a warning the first time its key comes: (key, message).
    """

    def __init__(
        self,
        axes: Sequence[Drive],
        counters: RackCounters,
        sync_loss_periods: float,
        max_stall_discount_s: float,
        on_expired: Callable[[Drive, int, float], None],
        emcy: Callable[[Drive, int, bytes], None],
        warn_once: Callable[[str, str], None],
    ) -> None:
        self._axes = axes
        self._counters = counters
        self._sync_loss_periods = sync_loss_periods
        self._on_expired = on_expired
        self._emcy = emcy
        self._warn_once = warn_once
        self.freeze_watch = FreezeWatch(max_stall_discount_s)  # 0x2020, 0x2021
        self.last_sync_done_s = -math.inf  # the end of the last SYNC's handling
        # The SYNC rate check (`sync_in_time`): the period it runs for, its parameters for
        # that period, and the judge's state (`lca_sim.cia402.sync_rate`).
        self._sync_period_s = 0.0
        self._sync_rate: sync_rate.SyncRateParams | None = None
        self._sync_judge = sync_rate.SyncRateState()
        self._sync_length_error = False  # in a run of SYNCs of the wrong length (EMCY sent)

    def tick(self, late_s: float, now: float) -> None:
        """A monitor tick `late_s` after it was due: discount a freeze, then check the deadlines."""
        freeze = self.freeze_watch.check(late_s)
        if freeze is not None:
            self._discount(freeze, now)
        self.check(now)

    def _discount(self, freeze: Freeze, now: float) -> None:
        """Move every armed deadline on by the freeze: this process, not the master, stood still.

        No further than `now`: a frame the receive thread took after the freeze, before this
        tick, has already stamped its deadline afresh. And no more than `max_stall_discount_s`
        (rack.yaml): a longer stall is the drive standing still for longer than a master can
        be expected to tolerate, so the rest counts against the deadlines as it would on a
        drive that froze, and each node sends EMCY 0xFF02 with the stall in ms.

        Every stall is counted (`process_freezes`, object 0x2020) and the longest is kept
        (0x2021, ms), so a master learns that the drive stood still even when nothing faulted.

        A real drive's watchdog runs on its own hardware. This one shares an interpreter with
        its receive thread (and, with interface virtual, with the master): while the process is
        frozen, frames wait unread in the bus queue, and judging the deadlines on waking would
        blame the master for the freeze. A master that is silent while this process runs is
        still caught on time.
        """
        self._counters.process_freezes += 1
        what = (
            f"this process stood still for {freeze.frozen_s * 1e3:.0f} ms; the watchdogs do not "
            f"count up to {self.freeze_watch.max_discount_s * 1e3:.0f} ms of such time against "
            "the master (objects 0x2020 / 0x2021 count the stalls)"
        )
        if freeze.beyond_bound:  # the rest counts against the deadlines; each node sends EMCY
            self._warn_once("freeze-beyond", f"{what}; this one was longer")
            self._counters.stalls_beyond_discount += 1
            stall_ms = struct.pack("<H", min(round(freeze.frozen_s * 1e3), 0xFFFF))
            for axis in self._axes:
                self._emcy(axis, cia402.EMCY_PROCESS_STALL, stall_ms)
        elif self._counters.process_freezes == 1:  # forgiven in full: a note, no alarm
            logger.info("virtual drive: %s (further ones are only counted)", what)
        skip_s = freeze.discount_s
        for axis in self._axes:
            if axis.heartbeat_last_rx_s is not None:
                axis.heartbeat_last_rx_s = discounted(axis.heartbeat_last_rx_s, skip_s, now)
            for pdo in axis.rpdos:
                if pdo.last_rx_s is not None:
                    pdo.last_rx_s = discounted(pdo.last_rx_s, skip_s, now)
            axis.sync_armed_s = discounted(axis.sync_armed_s, skip_s, now)
        self.last_sync_done_s = discounted(self.last_sync_done_s, skip_s, now)

    def check(self, now: float) -> None:
        """Fire every watchdog whose deadline passed; each re-arms on its next frame."""
        for axis in self._axes:
            _, time_ms = cia402.heartbeat_consumer_entry(axis.values[_HEARTBEAT_CONSUMER_1])
            last = axis.heartbeat_last_rx_s
            if time_ms and last is not None and now - last > time_ms * 1e-3:
                axis.heartbeat_last_rx_s = None  # re-armed by the next heartbeat
                self._counters.heartbeat_losses += 1
                self._on_expired(axis, cia402.EMCY_HEARTBEAT, now)
            if axis.nmt != NMT_OPERATIONAL:  # the reaction above may have left OPERATIONAL
                continue
            for pdo in axis.rpdos:
                last = pdo.last_rx_s
                if (
                    pdo.event_timer_ms
                    and last is not None
                    and now - last > pdo.event_timer_ms * 1e-3
                ):
                    pdo.last_rx_s = None  # re-armed by the next reception
                    self._counters.rpdo_timeouts += 1
                    self._on_expired(axis, cia402.EMCY_RPDO_TIMEOUT, now)
            period_s = axis.values[_CYCLE_PERIOD] * 1e-6
            if (
                period_s > 0.0
                and axis.drive.power is PowerState.OPERATION_ENABLED
                and not axis.sync_loss_reported
                and now - max(self.last_sync_done_s, axis.sync_armed_s)
                > self._sync_loss_periods * period_s
            ):
                axis.sync_loss_reported = True  # once per loss: re-armed by the next SYNC
                self._counters.sync_losses += 1
                self._on_expired(axis, cia402.EMCY_SYNC_LOSS, now)

    def heard(self, producer: int, data: bytes, now: float) -> None:
        """A heartbeat from node `producer`: re-arm every consumer that watches it (0x1016)."""
        if len(data) != 1:
            self._counters.bad_frames += 1
            return
        for axis in self._axes:
            node_id, time_ms = cia402.heartbeat_consumer_entry(axis.value(od.HEARTBEAT_CONSUMER, 1))
            if node_id == producer and time_ms and not axis.faults.bus_off:
                axis.heartbeat_last_rx_s = now

    def sync_length_ok(self, data: bytes) -> bool:
        """CiA 301: a SYNC carries no data, or the 1-byte counter.

        Anything else is EMCY 0x8240 "unexpected SYNC data length" from each consumer (once per
        run of them), counted, and not a SYNC.
        """
        if len(data) <= 1:
            self._sync_length_error = False
            return True
        self._counters.bad_frames += 1
        if not self._sync_length_error:
            self._sync_length_error = True
            for axis in self._axes:
                self._emcy(axis, cia402.EMCY_SYNC_LENGTH, b"")
        return False

    def sync_in_time(self, period_s: float, stamp_s: float) -> bool:
        """Whether this SYNC may advance the plant a period (0x1006 > 0), or comes too early.

        SYNCs faster than 0x1006 (a second producer, a master whose cycle does not match what
        it wrote there) would run the plant faster than the wall clock. The excess SYNCs are
        handled as any SYNC (RPDOs applied, TPDOs sent) but do not advance the plant; each is
        counted (`syncs_too_fast`), and every node sends EMCY 0x8100 once per episode (over
        after a window without excess).
        """
        verdict = self._sync_verdict(period_s, stamp_s)
        if verdict is sync_rate.SyncVerdict.IN_TIME:
            return True
        self._counters.syncs_too_fast += 1
        if verdict is sync_rate.SyncVerdict.TOO_FAST_REPORT:
            self._warn_once(
                "sync-too-fast",
                f"SYNCs faster than 0x1006 ({period_s * 1e6:.0f} us), a second SYNC producer? "
                "The excess ones do not advance the plant",
            )
            for axis in self._axes:
                self._emcy(axis, cia402.EMCY_SYNC_TOO_FAST, b"")
        return False

    def _sync_verdict(self, period_s: float, stamp_s: float) -> sync_rate.SyncVerdict:
        """Whether this SYNC, stamped `stamp_s` by the bus, comes in time for 0x1006 = `period_s`.

        CiA 301 7.2.5 gives a network one SYNC producer, 0x1006 (7.5.2.6) its period. The pure
        judge (`lca_sim.cia402.sync_rate`) counts the SYNCs against the time their bus stamps
        say passed, over a window, so jitter and stalls (up to the SYNC-loss deadline, and a
        freeze of this process up to 0.2 s) with their catch-up bursts never count.
        """
        if period_s != self._sync_period_s or self._sync_rate is None:
            self._sync_period_s = period_s
            self._sync_rate = sync_rate.sync_rate_params(period_s, self._sync_loss_periods)
            self._sync_judge = sync_rate.SyncRateState()
        self._sync_judge, verdict = sync_rate.judge_sync(self._sync_judge, stamp_s, self._sync_rate)
        return verdict
