"""The CANopen master of the CAN bridge: the cyclic thread and its requests (no ROS).

`Cia402Master` drives CiA 402 drives in cyclic synchronous torque (or velocity) mode over a
`canopen.Network`: `init()` configures every drive over SDO in PRE-OPERATIONAL and starts it;
a cyclic thread of its own sends each drive's RPDOs, SYNC and the master heartbeat, walking
the power state machine one legal step per cycle, never blocking; TPDOs on the network's
notifier thread fill a per-cycle snapshot, handed to `on_state` once every drive has answered
the SYNC (docs/can.md, "Timing on the bus").

Its parts: `master_setup` (SDO configuration, PDO binding, TPDO decoders), `master_watch`
(safety watches and latches, docs/can.md "Watchdogs and safety"), `master_axis` (per-drive
bookkeeping and RPDO frames); its parameters `master_params`, snapshot types `master_state`,
PDO layout `master_pdo`. The ROS shell is `lca_sim.ros.can_bridge_node`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from operator import attrgetter
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.sdo.base import SdoArray, SdoRecord

from lca_sim.canbus.master_axis import MasterAxis
from lca_sim.canbus.master_frames import FrameReceiver, FrameTransmitter
from lca_sim.canbus.master_params import BridgeParams
from lca_sim.canbus.master_setup import DriveSetup, forget_invalid_nmt_state
from lca_sim.canbus.master_state import AxisState, Counters, Snapshot, copied, copied_all
from lca_sim.canbus.master_watch import SafetyWatch
from lca_sim.cia402 import cia301
from lca_sim.cia402.controlword import Want
from lca_sim.cia402.device import PowerState
from lca_sim.errors import InvalidValueError, UnknownNameError
from lca_sim.runtime import FreezeWatch

log = logging.getLogger(__name__)

# The command fields in which NaN means "no command: hold" (a CSP drive's own position).
NAN_HOLDS = frozenset({"command_rad"})
# The most SYNC -> command latencies kept between two `take_command_latencies` (8 s at 500 Hz).
LATENCY_RECORDS = 4096
# The cycle thread sleeps up to this long between cycles, waits on its stop event beyond it:
# a plain sleep costs it about 15 us of CPU less per cycle than Event.wait's condition (22 vs
# 37 us on the 2-core host), and stop() then waits at most this long.
SLEEP_AT_MOST_S = 0.02
# The master's heartbeat (CiA 301 7.2.8.3.2.1): its NMT state, OPERATIONAL.
_HEARTBEAT_OPERATIONAL = bytes([cia301.NMT_STATE_OPERATIONAL])
_STATE = attrgetter("state")  # a drive's `AxisState`, in C


def _refusal(what: str, values: Sequence[float], joints: Sequence[str], nan_holds: bool) -> str:
    """Why a command array is refused ('' when it is taken): one finite value per joint."""
    if len(values) != len(joints):
        return f"expected {len(joints)} {what} ({', '.join(joints)})"
    if not all(map(math.isfinite, values)) and not all(
        math.isfinite(v) or (nan_holds and math.isnan(v)) for v in values
    ):  # the common case, every value finite, in C
        allowed = "finite or NaN (hold)" if nan_holds else "finite"
        return f"{what} must be {allowed}, got {list(values)}"
    return ""


class Cia402Master:
    """A CANopen master for CiA 402 drives in cyclic synchronous torque mode.

    Args:
        network: a connected `canopen.Network` (its notifier running); the bridge adds nodes.
        params: robot and bus figures, timeouts.
        eds: the drives' EDS (config/can/lca_drive.eds for the virtual drive; the vendor's
            EDS for a real one).
        on_state: called (notifier thread) with each complete `Snapshot`.
        clock: the time the safety watches judge by, s (default `time.monotonic`). A lockstep
            loop passes its `CycleClock.now`: every deadline is then counted in cycles of
            simulated time, and the cycle runs only when its driver calls `cycle`.
        stamp_clock: the stamp of each SYNC's `Snapshot`, s (default `time.time`; a lockstep
            loop: the same simulated time).
        before_cycle: called by the cycle thread (`start`) before each cycle is judged: the ROS
            shell takes the commands since the last SYNC there (`BridgeCommands.poll`).
        drives_in_process: the drives are in this process (the virtual rack on a `virtual`
            bus): a stall of the cycle thread is then only noted (`SafetyWatch`).
    """

    def __init__(
        self,
        network: canopen.Network,
        params: BridgeParams,
        eds: Path,
        on_state: Callable[[Snapshot], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        stamp_clock: Callable[[], float] = time.time,
        before_cycle: Callable[[], None] | None = None,
        drives_in_process: bool = False,
    ) -> None:
        self.network = network
        self._before_cycle = before_cycle
        self.params = params
        self.on_state = on_state
        self._clock = clock
        self._stamp_clock = stamp_clock
        self.counters = Counters()
        self._lock = threading.Lock()
        self._axes = [
            MasterAxis(joint, network.add_node(node_id, str(eds)), k_t, gear)
            for joint, node_id, k_t, gear in zip(
                params.joints,
                params.node_ids,
                params.torque_constants_nm_per_a,
                params.gear_ratios,
                strict=True,
            )
        ]
        for k, axis in enumerate(self._axes):
            axis.mode = params.mode_of(k)
        if network.notifier is None:
            raise InvalidValueError("the network must be connected (its notifier running)")
        self._want = Want.DISABLED
        self._watch = SafetyWatch(
            params, self._axes, self.counters, self._lock, clock, drives_in_process
        )
        self._receiver = FrameReceiver(network, self.counters, self._watch.error_frame)
        self._transmitter = FrameTransmitter(network, self._watch, self.counters)
        self._setup = DriveSetup(network, params, self.counters, clock, self._mark_fresh)
        self._completed_cycle = -1  # the SYNC whose state went out last
        self._cycle = 0
        self._sync_wall_s = 0.0
        self._sync_mono_s = 0.0
        self._initialized = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._freeze_watch = FreezeWatch()  # the cycle thread forgives every freeze in full
        self._next_heartbeat_t = 0.0
        # Timing records for benchmarks, kept only while keep_latencies is set.
        self.latencies_s: list[float] = []  # SYNC -> last TPDO of a complete cycle
        self.cycle_starts_s: list[float] = []  # monotonic start of each cycle
        self.keep_latencies = False
        # Wall time from each SYNC to the first command after it (`take_command_latencies`).
        self._command_latencies_s: deque[float] = deque(maxlen=LATENCY_RECORDS)
        self._answered_cycle = 0

    def init(self, sdo_timeout_s: float = 0.5) -> None:
        """Configure every drive over SDO in PRE-OPERATIONAL and start it (NMT OPERATIONAL).

        Raises:
            BridgeError: a drive did not answer, or refused a setting.
        """
        for k, axis in enumerate(self._axes):
            self._setup.configure(axis, sdo_timeout_s)
            self._receiver.tpdo_ids = frozenset(
                cob_id for a in self._axes for cob_id in a.tpdo_cob_ids
            )
            if axis.emcy_watch is None:  # once: init() may run again
                axis.emcy_watch = self._watch.emcy_consumer(axis)
                axis.node.emcy.add_callback(axis.emcy_watch)
            if axis.boot_watch is None:  # once: init() may run again
                axis.boot_watch = self._watch.heartbeat_consumer(axis, lambda: self._initialized)
                self.network.subscribe(
                    cia301.HEARTBEAT_COB_BASE + self.params.node_ids[k], axis.boot_watch
                )
        for axis in self._axes:
            forget_invalid_nmt_state(axis.node)
            axis.node.nmt.state = "OPERATIONAL"
            axis.last_tpdo_t = self._clock()
        with self._lock:
            self._watch.rebooted = []  # configured again: an earlier restart no longer matters
            self._watch.arm(self._clock(), self._cycle)
        self._initialized = True

    def _mark_fresh(self, axis: MasterAxis, bit: int, now: float) -> None:
        """An every-SYNC TPDO came (notifier thread): hand on the state once the set is whole."""
        with self._lock:
            axis.fresh |= bit
            axis.seen |= bit
            for a in self._axes:  # a loop, not all(): no call per TPDO
                if a.fresh != a.sync_mask:
                    return  # the set is not whole yet
            for a in self._axes:
                a.fresh = a.seen = 0
            if self._completed_cycle == self._cycle:
                # A second complete set after one SYNC: the TPDOs of the SYNC before came
                # after this one (a TPDO carries no SYNC count, CiA 301 7.2.2). One state
                # per SYNC: a second one would carry the same stamp, and a controller
                # skips a stamp it has seen, leaving this cycle without a command.
                self.counters.extra_complete_sets += 1
                return
            self._completed_cycle = self._cycle
            stalled_for = self._watch.complete(self._cycle)
            self.counters.complete_cycles += 1
            if self.keep_latencies:
                self.latencies_s.append(time.monotonic() - self._sync_mono_s)
            snapshot = Snapshot(self._sync_wall_s, self._cycle, copied_all(map(_STATE, self._axes)))
        if stalled_for:
            log.warning("complete cycles again after %d SYNCs without one", stalled_for)
        if self.on_state is not None:
            self.on_state(snapshot)

    # --- commands and requests (any thread) ----------------------------------------------

    def set_currents(self, currents_a: Sequence[float], now: float | None = None) -> str | None:
        """Take a current command (A, joint order); None, or why it was refused."""
        return self._take("currents", currents_a, "command_a", now)

    def set_velocities(self, velocities: Sequence[float], now: float | None = None) -> str | None:
        """Take a velocity command (joint rad/s or m/s, joint order) for the CSV axes.

        The CST axes ignore it (they take `set_currents`); it counts for the silence watch.
        """
        return self._take("velocities", velocities, "command_rad_s", now)

    def set_positions(self, positions: Sequence[float], now: float | None = None) -> str | None:
        """Take a position command (joint rad or m, joint order) for the CSP axes (0x607A).

        NaN for an axis: no position command, the drive holds where it is (`csp_target`).
        """
        return self._take("positions", positions, "command_rad", now)

    def _take(self, what: str, values: Sequence[float], field: str, at: float | None) -> str | None:
        """Store one command per axis in `field` (`at`: received, default now); None or why not."""
        refused = _refusal(what, values, self.params.joints, field in NAN_HOLDS)
        if refused:
            self.counters.commands_rejected += 1
            return refused
        with self._lock:
            for axis, value in zip(self._axes, values, strict=True):
                setattr(axis, field, float(value))
            if self._answered_cycle != self._cycle:  # the first command after this SYNC
                self._answered_cycle = self._cycle  # `at` is monotonic: lockstep never gives one
                arrived_s = time.monotonic() if at is None else at
                self._command_latencies_s.append(arrived_s - self._sync_mono_s)
            self._watch.command(self._clock() if at is None else at)
        self.counters.commands_accepted += 1
        return None

    def enable(self, on: bool) -> str:
        """Walk every drive to operation enabled (or back to ready to switch on)."""
        with self._lock:
            reason = self._watch.latched_reason()
            if on and reason:
                return f"not enabled: {reason}; call ~/recover first"
            self._want = Want.ENABLED if on else Want.DISABLED
            self._watch.enabled()
        return "enabling" if on else "disabling"

    def halt(self) -> None:
        """Zero torque with the halt bit; the drives stay enabled."""
        with self._lock:
            self._watch.user_halt = True

    def recover(self) -> None:
        """Clear the latches and reset drive faults.

        The latches: EMCY, stale drive, lost heartbeat, stall of complete cycles, bus-off, send
        failures. The heartbeat and stall watches start again from now, as the stale one does:
        a drive still silent is latched again after its consumer time (or `stall_cycles`
        SYNCs). The drives end up disabled: enabling again is a separate, explicit request.
        Each drive is also sent NMT start (CiA 301 7.2.8.3.2.1, command 0x01): a drive whose
        communication error took it to PRE-OPERATIONAL (0x1029 sub 1 = 0, CiA 301's default)
        sends its PDOs again; one already OPERATIONAL ignores it.
        """
        if self._initialized and not self._watch.bus_off:
            for axis in self._axes:
                try:
                    axis.node.nmt.state = "OPERATIONAL"
                except can.CanError as exc:
                    log.error("NMT start of %s failed: %s", axis.joint, exc)
        with self._lock:
            for axis in self._axes:
                axis.statuswords_at_reset = axis.statuswords_received
            self._watch.recover(self._clock(), self._cycle)
            self._want = Want.FAULT_RESET

    def latched_reason(self) -> str:
        """Why the axes are held (stopped or halted) until `recover()`, or ''."""
        return self._watch.latched_reason()

    def receive_failure(self) -> str:
        """Why the bus is not heard now (its receive fails), or '' (`FrameReceiver.on_error`)."""
        failures = self._receiver.receive_failures
        if not failures.failing(time.monotonic()):
            return ""
        return f"CAN reception failing: {failures.last} ({failures.count} failures so far)"

    def start(self) -> None:
        """Start the cyclic thread (after init)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="can_bridge_cycle", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop the cyclic thread (the drives' watchdogs then react: RPDO deadline, heartbeat)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def _run(self) -> None:
        period = 1.0 / self.params.cycle_hz
        next_t = time.monotonic()
        previous_start = math.nan
        while not self._stop.is_set():
            if self._before_cycle is not None:
                self._before_cycle()  # the commands that came since the last SYNC
            now = time.monotonic()
            freeze = self._freeze_watch.check(now - previous_start - period)
            if freeze is not None:
                self._watch.discount(freeze, now)
            previous_start = now
            self.cycle(now)
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # more than a period late: do not burst to catch up
                next_t = time.monotonic()
            elif delay > SLEEP_AT_MOST_S:
                self._stop.wait(delay)  # a long period: stop() does not wait it out
            elif delay > 0.0:
                time.sleep(delay)

    def cycle(self, now: float) -> None:
        """One cycle: safety checks, controlwords and RPDOs, SYNC, master heartbeat."""
        p = self.params
        if self.keep_latencies:
            self.cycle_starts_s.append(now)
        with self._lock:
            if not self._initialized or self._watch.bus_off:
                return  # bus-off: no cyclic transmission until recover()
            late = False
            for a in self._axes:  # one loop, no generator: late TPDOs, then a new cycle
                late = late or a.fresh != 0
                a.fresh = 0
            if late and self._cycle:
                self.counters.late_cycles += 1
            self._watch.count_command_timing(now)
            self._watch.check(now, self._cycle, self._want is Want.ENABLED)
            want = self._want
            if want is Want.ENABLED and (self._watch.quick_stopped or self._watch.stop_reason()):
                want = Want.QUICK_STOP
            halted = self._watch.halted
            frames: list[tuple[int, bytes]] = []  # every drive's RPDOs, then SYNC, heartbeat
            for a in self._axes:
                self.counters.commands_clamped += a.add_rpdo_frames(frames, want, halted)
            if self._want is Want.FAULT_RESET and all(
                a.state.power_state is not PowerState.FAULT
                and a.statuswords_received > a.statuswords_at_reset
                for a in self._axes
            ):  # judged on states the drives sent after recover(), not on ones from before
                self._want = Want.DISABLED
            self._cycle += 1
            self.counters.cycles += 1
            self._sync_wall_s = self._stamp_clock()
            self._sync_mono_s = time.monotonic()
        frames.append((cia301.SYNC_COB_ID, b""))
        if now >= self._next_heartbeat_t:
            self._next_heartbeat_t = now + p.heartbeat_consumer_ms / 3000.0
            frames.append((cia301.HEARTBEAT_COB_BASE + p.master_node_id, _HEARTBEAT_OPERATIONAL))
        self._transmitter.send(frames)

    @property
    def joints(self) -> tuple[str, ...]:
        """Joint names in order."""
        return self.params.joints

    def axis_state(self, joint: str) -> AxisState:
        """The last reported state of one drive (a copy)."""
        axis = self._axis(joint)
        with self._lock:
            return copied(axis.state)

    def has_drive_state(self) -> bool:
        """True when every drive maps the lca_hil drive-chain objects (the virtual drive)."""
        return all(a.has_drive_state for a in self._axes)

    def decoded_fields(self) -> frozenset[str]:
        """The `AxisState` fields every drive's TPDOs fill (after `init`).

        A real CiA 402 drive fills statusword, position, velocity and current; the virtual one
        also drive_state, motion_state, eta_m, eta_l, load_torque_nm, friction_torque_nm and
        voltage_v. A field outside this set keeps its default (NaN, or -1 / 0 for the codes).
        """
        if not self._axes:
            return frozenset()
        return frozenset.intersection(*(a.decoded for a in self._axes))

    def emcy_codes(self) -> dict[str, int]:
        """The latched EMCY code per joint (0: none)."""
        return {a.joint: a.emcy_code for a in self._axes}

    def advisory_emcy(self) -> dict[str, tuple[int, int]]:
        """Per joint, the last advisory EMCY code and how many came (0, 0: none)."""
        with self._lock:
            return {a.joint: (a.advisory_code, a.advisory_count) for a in self._axes}

    def command_silence(self, now: float) -> tuple[bool, str] | None:
        """What the controller's silence does to enabled drives: (latched, why), or None.

        None while commands come in time, or while the drives are not wanted enabled. `latched`
        is True after the quick stop, which holds until `enable(True)` is asked again; the halt
        before it ends by itself when commands return.
        """
        with self._lock:
            if self._want is not Want.ENABLED:
                return None
            return self._watch.command_silence(now)

    def silent_heartbeats(self) -> tuple[str, ...]:
        """The drives whose heartbeat is silent beyond the consumer time now (latched or not)."""
        with self._lock:
            return tuple(a.joint for a in self._axes if a.heartbeat_lost)

    def cycle_stall(self) -> str:
        """While no complete cycle comes (for over `stall_cycles` SYNCs): what stalls it, or ''.

        A state, not a latch: it ends with the next complete cycle. Enabled, it is also latched
        (`latched_reason()`) until `recover()`.
        """
        with self._lock:
            return self._watch.stall_text(self._cycle) if self._watch.stalled else ""

    def take_command_latencies(self) -> list[float]:
        """The SYNC -> first command wall times (s) since the last call, and forget them."""
        with self._lock:
            taken = list(self._command_latencies_s)
            self._command_latencies_s.clear()
        return taken

    def now(self) -> float:
        """The master's clock (`clock`): monotonic wall time, or a lockstep loop's."""
        return self._clock()

    def command_age_s(self, now: float) -> float:
        """Seconds since the last accepted command."""
        return now - self._watch.last_command_t

    def sdo_read(self, joint: str, index: int, subindex: int) -> int | float | str:
        """Read one object of a drive (any NMT state); raises canopen errors."""
        value: int | float | str = self._var(joint, index, subindex).raw
        return value

    def sdo_write(self, joint: str, index: int, subindex: int, value: int | float) -> None:
        """Write one object of a drive; raises canopen errors (SdoAbortedError with its code)."""
        self._var(joint, index, subindex).raw = value

    def _var(self, joint: str, index: int, subindex: int) -> Any:
        entry = self._axis(joint).node.sdo[index]
        return entry[subindex] if isinstance(entry, (SdoRecord, SdoArray)) else entry

    def _axis(self, joint: str) -> MasterAxis:
        for axis in self._axes:
            if axis.joint == joint:
                return axis
        raise UnknownNameError("joint", joint, self.params.joints)
