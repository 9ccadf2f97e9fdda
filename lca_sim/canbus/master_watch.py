"""The master's safety watches and their latches (docs/can.md, "Watchdogs and safety").

Command silence, stale drives, lost heartbeats, EMCYs, stalls of complete cycles, restarts,
bus-off and send failures: a part of `Cia402Master` that owns the watches' state. Its
consumers (notifier thread) and `discount` take the master's lock; the master calls the rest
under it (send failures excepted) and asks it what the axes may do.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Sequence
from typing import Any

import can

from lca_sim.canbus import emcy
from lca_sim.canbus.master_axis import MasterAxis
from lca_sim.canbus.master_params import BridgeParams
from lca_sim.canbus.master_state import Counters
from lca_sim.runtime import Freeze, discounted

log = logging.getLogger(__name__)

CAN_ERR_BUSOFF = 0x00000040  # SocketCAN error class bit in an error frame's identifier


class SafetyWatch:
    """Every watch of a master over its drives.

    Args:
        params: the bridge's timeouts and limits.
        axes: the master's drives (their stamps and latched EMCY live on them).
        counters: the master's counters.
        lock, clock: the master's lock and the clock the watches judge by.
        drives_in_process: the drives run in this process (the virtual rack on a `virtual`
            bus): a stall of the process stalls them too, so no stall trips their deadlines.
    """

    def __init__(
        self,
        params: BridgeParams,
        axes: Sequence[MasterAxis],
        counters: Counters,
        lock: threading.Lock,
        clock: Callable[[], float],
        drives_in_process: bool = False,
    ) -> None:
        self._params = params
        self._drives_in_process = drives_in_process
        # Computed from the (frozen) params once, not by their properties each cycle.
        self._stall_cycles = params.stall_cycles
        self._heartbeat_timeout_s = params.drive_heartbeat_timeout_s
        self._axes = axes
        self._counters = counters
        self._long_freeze_logged = False  # one warning for a stall beyond the RPDO deadline
        self._lock = lock
        self._clock = clock
        self.silence_halt = False  # the controller is silent (or has not spoken yet)
        self.user_halt = False  # ~/halt, until the next enable
        self.quick_stopped = False
        self.stale: list[str] = []
        self.rebooted: list[str] = []  # drives that sent a boot-up after init()
        self.heartbeat_lost: list[str] = []  # drives whose heartbeat stopped (until recover)
        self.last_complete_cycle = 0  # the cycle of the last complete one (or init)
        self._stall_armed_cycle = 0  # a stall is judged from here: a complete cycle or recover
        self.stalled = False  # no complete cycle for `stall_cycles` SYNCs, until one comes
        self._stall_latched = ""  # the stall's text, latched while enabled (until recover)
        self.bus_off = False
        self.send_failures_in_row = 0  # the master skips `send_ok` while it is 0
        self.failure_halt = False
        self.last_command_t = -math.inf
        self._previous_cycle_t = -math.inf  # the start of the last cycle (commands_late)
        self.commanded = False  # a command came since the last enable

    # --- events --------------------------------------------------------------------------

    def command(self, now: float) -> None:
        """A command came from the controller."""
        self.last_command_t = now
        self.commanded = True
        if not self.quick_stopped:
            self.silence_halt = False  # the controller is back before the quick stop

    def enabled(self) -> None:
        """`enable` asked: the halts and the quick stop end, the controller must speak again."""
        self.user_halt = False
        self.silence_halt = False
        self.quick_stopped = False
        self.commanded = False

    def complete(self, cycle: int) -> int:
        """A complete cycle at SYNC `cycle`: the SYNCs a stall lasted (0: there was none)."""
        stalled_for = 0
        if self.stalled:
            self.stalled = False
            stalled_for = cycle - self.last_complete_cycle
        self.last_complete_cycle = self._stall_armed_cycle = cycle
        return stalled_for

    def heartbeat_consumer(
        self, axis: MasterAxis, initialized: Callable[[], bool]
    ) -> Callable[[int, bytearray, float], None]:
        """The master's heartbeat consumer of one drive (CiA 301 7.2.8.3.2.2) and its boot-ups.

        Every heartbeat (1 byte: the NMT state) is stamped on reception, on the clock the
        cycle's `check` judges it by (the frame's own timestamp is the bus's clock,
        and a freeze of this process is discounted from the reception time only). A boot-up
        (CiA 301 7.2.8.3.3: state byte 0) after init() means the drive restarted behind the
        master's back (power, reset, a NMT reset node from elsewhere): its configuration, PDO
        mapping included, is its boot default again, so every axis stops (latched) until
        `init()` configures it again. Counted and logged once.
        """

        def on_heartbeat(_can_id: int, data: bytearray, _timestamp: float) -> None:
            if len(data) != 1:
                return  # not a heartbeat (CiA 301: one byte)
            now = self._clock()
            with self._lock:
                axis.last_heartbeat_t = now
                back = axis.heartbeat_lost
                axis.heartbeat_lost = False
            if back:
                log.warning(
                    "heartbeat of %s again; the axes stay stopped until ~/recover", axis.joint
                )
            if data[0] != 0 or not initialized():
                return
            self._counters.drive_restarts += 1
            with self._lock:
                if axis.joint in self.rebooted:
                    return
                self.rebooted.append(axis.joint)
            log.error("drive %s restarted (boot-up): axes stopped until ~/init", axis.joint)

        return on_heartbeat

    def emcy_consumer(self, axis: MasterAxis) -> Callable[[Any], None]:
        """The master's EMCY consumer of one drive: advisory codes counted, the rest latched."""

        def on_emcy(entry: Any) -> None:
            code = int(entry.code)
            if code & 0xFF00 == 0:
                return  # "error reset / no error": nothing to latch
            self._counters.emcy_received += 1
            ours = axis.has_drive_state  # lca_hil's virtual drive: its own codes are known
            if emcy.is_advisory(code, ours):  # a frame lost or refused: reported, axes go on
                with self._lock:
                    axis.advisory_code = code
                    axis.advisory_count += 1
                log.warning("EMCY from %s: %s", axis.joint, emcy.describe(code, ours))
                return
            with self._lock:
                axis.emcy_code = code
            text = emcy.describe(code, ours)
            log.error("EMCY from %s: %s (axes stopped until recover)", axis.joint, text)

        return on_emcy

    def error_frame(self, error_class: int) -> None:
        """An error frame (SocketCAN): counted; bus-off is latched until `recover`."""
        self._counters.error_frames += 1
        if error_class & CAN_ERR_BUSOFF:
            with self._lock:
                self.bus_off = True

    def send_ok(self) -> None:
        """A send went out: the run of failures ends."""
        self.send_failures_in_row = 0

    def send_failed(self, exc: can.CanError) -> None:
        """Count a failed send; `max_send_failures` of them in a row halt the axes."""
        self.send_failures_in_row += 1
        in_row = self.send_failures_in_row
        halting = in_row >= self._params.max_send_failures and not self.failure_halt
        if in_row >= self._params.max_send_failures:
            self.failure_halt = True  # before the count: whoever sees the count sees the halt
        self._counters.send_failures += 1
        if halting:
            log.error("%d failed sends in a row: halt (%s)", in_row, exc)

    def discount(self, freeze: Freeze, now: float) -> None:
        """Move the silence deadlines on by the freeze: this process stood still, not the others.

        Two cycle starts further apart than a period plus `FREEZE_THRESHOLD_S` mean the cycle
        thread was frozen (the GIL held by a library load, a paused host). The commands and
        TPDOs sent meanwhile wait unread in the queues; judging the controller's and the drives'
        silence on waking would blame them for the freeze. A controller or drive that is silent
        while the cycle runs is still caught on time: no deadline moves past `now`.
        """
        with self._lock:
            self._counters.process_freezes += 1
            skip_s = freeze.discount_s
            self.last_command_t = discounted(self.last_command_t, skip_s, now)
            for axis in self._axes:
                axis.last_tpdo_t = discounted(axis.last_tpdo_t, skip_s, now)
                axis.last_heartbeat_t = discounted(axis.last_heartbeat_t, skip_s, now)
        # A stall the drives' RPDO deadline tolerates (the shortest deadline the master sets)
        # is only noted; a longer one would have let a real drive's deadline fire. Drives in
        # this process stood still with it (their watchdogs discount their own freeze), so for
        # them it is a note whatever its length.
        beyond = freeze.frozen_s * 1e3 > self._params.rpdo_deadline_ms
        if self._counters.process_freezes == 1 or (beyond and not self._long_freeze_logged):
            self._long_freeze_logged = self._long_freeze_logged or beyond
            longer = ""
            if beyond:
                longer = (
                    f", longer than the drives' RPDO deadline ({self._params.rpdo_deadline_ms} ms)"
                )
                if self._drives_in_process:
                    longer += ", but the drives run in this process and stood still with it"
            log.log(
                logging.WARNING if beyond and not self._drives_in_process else logging.INFO,
                "the cycle thread stood still for %.0f ms%s; silence deadlines do not count it "
                "(further freezes are only counted)",
                freeze.frozen_s * 1e3,
                longer,
            )

    def arm(self, now: float, cycle: int) -> None:
        """Start the heartbeat and stall watches (init): from now, and from this cycle.

        CiA 301 7.2.8.3.2.2 starts a consumer at the first heartbeat it receives; the master
        wrote every drive's 0x1017 itself, so it expects one from now on, and a drive that never
        sends one is caught too.
        """
        for axis in self._axes:
            axis.last_heartbeat_t = now
            axis.heartbeat_lost = False
            axis.fresh = axis.seen = 0
        self.last_complete_cycle = self._stall_armed_cycle = cycle
        self.stalled = False

    def recover(self, now: float, cycle: int) -> None:
        """Clear every latch; the heartbeat, stale and stall watches start again from now."""
        for axis in self._axes:
            axis.emcy_code = 0
            axis.advisory_code = axis.advisory_count = 0
            axis.last_tpdo_t = axis.last_heartbeat_t = now
        self.stale = []
        self.heartbeat_lost = []
        self._stall_latched = ""
        self._stall_armed_cycle = cycle
        self.bus_off = False
        self.failure_halt = False
        self.send_failures_in_row = 0
        self.quick_stopped = False
        self.user_halt = False
        self.silence_halt = False

    # --- the cycle's checks ----------------------------------------------------------------

    def count_command_timing(self, now: float) -> None:
        """Count this cycle's command as in time (newer than the last cycle) or late."""
        if self.commanded:
            if self.last_command_t >= self._previous_cycle_t:
                self._counters.commands_in_time += 1
            else:
                self._counters.commands_late += 1
        self._previous_cycle_t = now

    def check(self, now: float, cycle: int, enabled: bool) -> None:
        """Every watch, at the start of cycle `cycle`; `enabled`: the drives are wanted on."""
        p = self._params
        silent_s = now - self.last_command_t
        if enabled:
            if not self.commanded:
                self.silence_halt = True  # enabled, no controller yet: zero torque, halted
            elif silent_s > p.command_timeout_s + p.quick_stop_after_s:
                if not self.quick_stopped:
                    log.warning("no command for %.3f s: quick stop", silent_s)
                self.quick_stopped = True
            elif silent_s > p.command_timeout_s and not self.silence_halt:
                self.silence_halt = True
                self._counters.silence_halts += 1
                log.warning("no command for %.3f s: halt, zero torque", silent_s)
            for axis in self._axes:
                silent_s = now - axis.last_tpdo_t
                if silent_s > p.stale_timeout_s and axis.joint not in self.stale:
                    self.stale.append(axis.joint)
                    log.error("drive %s is stale: no TPDO for %.3f s", axis.joint, silent_s)
        self._check_heartbeats(now)
        self._check_cycle_stall(cycle, enabled)

    def _check_heartbeats(self, now: float) -> None:
        """The master's heartbeat consumer (CiA 301 7.2.8.3.2.2): a silent drive is latched.

        Whatever the drives are asked to do: a drive that lost its heartbeat may have lost its
        bus, and nothing it reports can be trusted to stop it; every axis stops until
        `recover()`. Each loss is counted and logged once, however often `recover()` latches it
        again while the drive stays silent.
        """
        timeout_s = self._heartbeat_timeout_s
        if timeout_s <= 0.0:
            return  # 0x1017 = 0: the drives send no heartbeat (CiA 301)
        for axis in self._axes:
            silent_s = now - axis.last_heartbeat_t
            if silent_s <= timeout_s:
                continue
            if axis.joint not in self.heartbeat_lost:
                self.heartbeat_lost.append(axis.joint)
            if not axis.heartbeat_lost:
                axis.heartbeat_lost = True
                self._counters.heartbeats_lost += 1
                log.error(
                    "lost heartbeat of %s: none for %.3f s (consumer time %.3f s): latched, "
                    "axes stopped until ~/recover",
                    axis.joint,
                    silent_s,
                    timeout_s,
                )

    def _check_cycle_stall(self, cycle: int, enabled: bool) -> None:
        """No complete cycle for `stall_cycles` SYNCs sent: counted, and latched while enabled.

        Judged in SYNCs the cycle sent, not in seconds: a cycle thread that stood still sent
        none. Disabled, it is a state (`cycle_stall()`, WARN on /diagnostics) that ends with the
        next complete cycle: no torque is at stake, but joint_states stop. Enabled, the
        controller has no state to close its loops on, and one that runs on a timer would
        command blind: every axis stops until `recover()`, as for a stale drive (which catches
        a drive without any TPDO, not one without its cyclic one).
        """
        if cycle - self._stall_armed_cycle <= self._stall_cycles:
            return
        if not self.stalled:
            self.stalled = True
            self._counters.cycle_stalls += 1
            log.warning("%s", self.stall_text(cycle))
        if enabled and not self._stall_latched:
            self._stall_latched = self.stall_text(cycle)
            log.error("%s: axes stopped until ~/recover", self._stall_latched)

    # --- what the axes may do ----------------------------------------------------------------

    @property
    def halted(self) -> bool:
        """Zero torque with the halt bit: the controller's silence, ~/halt, or send failures."""
        return self.silence_halt or self.user_halt or self.failure_halt

    def stall_text(self, cycle: int) -> str:
        """What stalls the complete cycles: the drives and the every-SYNC TPDOs not received."""
        missing = []
        for axis in self._axes:
            lost = axis.sync_mask & ~axis.seen
            numbers = [f"TPDO{n}" for n in range(1, lost.bit_length()) if lost >> n & 1]
            if numbers:
                missing.append(f"{axis.joint} {'+'.join(numbers)}")
        why = ", ".join(missing) + " missing" if missing else "every TPDO late"
        return f"no complete cycle for {cycle - self.last_complete_cycle} SYNCs: {why}"

    def stop_reason(self) -> str:
        """The latches that quick-stop all axes: EMCY, stale, heartbeat, stall, restart, bus-off."""
        reasons = []
        latched = []  # a loop, not a comprehension: the cycle asks each time, no call when clear
        for a in self._axes:
            if a.emcy_code:
                latched.append(f"{a.joint} {emcy.describe(a.emcy_code, a.has_drive_state)}")
        if latched:
            reasons.append("EMCY " + ", ".join(latched))
        if self.stale:
            reasons.append("stale drive " + ", ".join(self.stale))
        if self.heartbeat_lost:
            reasons.append("lost heartbeat of " + ", ".join(self.heartbeat_lost))
        if self._stall_latched:
            reasons.append(self._stall_latched)
        if self.rebooted:
            reasons.append(f"drive {', '.join(self.rebooted)} restarted (boot-up): ~/init")
        if self.bus_off:
            reasons.append("bus-off")
        return "; ".join(reasons)

    def latched_reason(self) -> str:
        """Why the axes are held (stopped or halted) until `recover()`, or ''."""
        reasons = [self.stop_reason()] if self.stop_reason() else []
        if self.failure_halt:
            reasons.append(f"{self._params.max_send_failures} send failures in a row")
        return "; ".join(reasons)

    def command_silence(self, now: float) -> tuple[bool, str] | None:
        """What the controller's silence does to drives wanted enabled: (latched, why), or None."""
        silent_s = now - self.last_command_t
        if self.quick_stopped:
            p = self._params
            return True, (
                f"quick stop: no command for {silent_s:.1f} s "
                f"(over {p.command_timeout_s + p.quick_stop_after_s:g} "
                "s); enable again (~/enable) once the controller runs"
            )
        if not self.commanded:
            return False, "enabled, waiting for the first command: halted, zero torque"
        if self.silence_halt:
            return False, f"no command for {silent_s:.1f} s: halted, zero torque"
        return None
