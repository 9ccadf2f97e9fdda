"""The CANopen master of the CAN bridge: configuration, the cyclic thread, safety (no ROS).

`Cia402Master` drives CiA 402 drives in cyclic synchronous torque (or velocity) mode over a
`canopen.Network`: `init()` configures every drive over SDO in PRE-OPERATIONAL and starts it;
a cyclic thread of its own sends each drive's RPDOs, SYNC and the master heartbeat, walking
the power state machine one legal step per cycle (`lca_sim.cia402.controlword`), never
blocking; TPDOs on the network's notifier thread fill a per-cycle snapshot, handed to
`on_state` once every drive has answered the SYNC. Safety is here, whatever the controller
does: command silence, stale drives, lost heartbeats, stalls, EMCYs, error frames and bus-off
(docs/can.md, "Watchdogs and safety").

Its parameters are `master_params`, its snapshot types `master_state`, its PDO layout and
TPDO decoding `master_pdo`. The ROS shell is `lca_sim.ros.can_bridge_node`.
"""

from __future__ import annotations

import logging
import math
import queue
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.sdo.base import SdoArray, SdoRecord
from canopen.sdo.client import SdoClient

from lca_sim.canbus import emcy
from lca_sim.canbus.freeze import Freeze, FreezeWatch
from lca_sim.canbus.master_params import MODE_TARGETS, BridgeError, BridgeParams
from lca_sim.canbus.master_pdo import (
    CONTROLWORD_REFRESH_CYCLES,
    CYCLIC_TPDO_OBJECTS,
    EVERY_SYNC,
    REQUIRED_TPDO_OBJECTS,
    TARGETS,
    RpdoPacker,
    Target,
    compile_apply,
    configure_compact_pdos,
)
from lca_sim.canbus.master_state import AxisState, Counters, Snapshot, copied
from lca_sim.canbus.remote import batched_sends
from lca_sim.cia402 import bus_load, cia301, codec
from lca_sim.cia402 import controlword as ctl
from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import Codec, CodecError, DriveUnits
from lca_sim.cia402.controlword import TorqueScale, Want
from lca_sim.cia402.device import CW_HALT, MODE_CST, MODE_CSV, PowerState
from lca_sim.runtime import discounted

log = logging.getLogger(__name__)

CAN_ERR_BUSOFF = 0x00000040  # SocketCAN error class bit in an error frame's identifier
CAN_ERR_CRTL = 0x00000004
# The most SYNC -> command latencies kept between two `take_command_latencies` (8 s at 500 Hz).
LATENCY_RECORDS = 4096


@dataclass(slots=True)
class _Axis:
    """The bridge's bookkeeping for one drive."""

    joint: str
    node: canopen.RemoteNode
    k_t: float
    gear: float
    scale: TorqueScale | None = None
    units: DriveUnits | None = None  # 0x6075, 0x6076, 0x608F as read by init()
    velocity: Codec | None = None  # motor rad/s <-> increments/s, from `units` (0x60FF)
    state: AxisState = field(default_factory=AxisState)
    controlword: int = 0
    command_a: float = 0.0
    command_rad_s: float = 0.0  # CSV: the joint velocity command
    mode: int = MODE_CST  # 0x6060 as init() wrote it
    last_tpdo_t: float = 0.0
    fresh: int = 0  # a bit per every-SYNC TPDO that arrived this cycle
    sync_mask: int = 0  # the bits of all its every-SYNC TPDOs: the cycle's complete at this
    seen: int = 0  # the every-SYNC TPDO bits that came since the last complete cycle
    last_heartbeat_t: float = 0.0  # monotonic reception of its last heartbeat (or the arming)
    heartbeat_lost: bool = False  # silent beyond the consumer time, until its next heartbeat
    emcy_code: int = 0  # the latched one (a fault reaction), 0: none
    advisory_code: int = 0  # the last advisory one (`emcy.ADVISORY`), 0: none
    advisory_count: int = 0
    has_drive_state: bool = False
    decoded: frozenset[str] = frozenset()  # the AxisState fields its TPDOs fill
    rpdo: Any = None  # canopen PdoMap of the RPDO with the target torque, sent each cycle
    cw_rpdo: Any = None  # the one with the controlword when it is another RPDO, else None
    cw_sent: int = -1  # the controlword last sent in `cw_rpdo`
    cw_age: int = 0  # cycles since `cw_rpdo` was last sent
    cw_var: Any = None
    target_var: Any = None  # the mode's target in `rpdo`: 0x6071 (CST) or 0x60FF (CSV)
    packer: RpdoPacker | None = None  # packs both RPDOs per cycle (None: canopen does)
    rpdo_cob_id: int = 0
    cw_cob_id: int = 0
    boot_watch: Any = None  # its boot-up callback on the network, once subscribed
    statuswords_received: int = 0
    statuswords_at_reset: int = 0  # `statuswords_received` when recover() asked for a reset


class _BusWatch(can.Listener):
    """Counts every frame (for the bus load) and reports error frames."""

    def __init__(self, bridge: Cia402Master) -> None:
        self._bridge = bridge

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self._bridge._on_error_frame(int(msg.arbitration_id))
            return
        c = self._bridge.counters
        c.frames_received += 1
        c.bits_received += bus_load.frame_bits(int(msg.dlc))
        c.nominal_bits += bus_load.frame_bits_nominal(int(msg.dlc))


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
    """

    def __init__(
        self,
        network: canopen.Network,
        params: BridgeParams,
        eds: Path,
        on_state: Callable[[Snapshot], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        stamp_clock: Callable[[], float] = time.time,
    ) -> None:
        self.network = network
        self.params = params
        self.on_state = on_state
        self._clock = clock
        self._stamp_clock = stamp_clock
        self.counters = Counters()
        self._lock = threading.Lock()
        self._axes = [
            _Axis(joint, network.add_node(node_id, str(eds)), k_t, gear)
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
            raise ValueError("the network must be connected (its notifier running)")
        network.notifier.add_listener(_BusWatch(self))
        self._want = Want.DISABLED
        self._silence_halt = False  # the controller is silent (or has not spoken yet)
        self._user_halt = False  # ~/halt, until the next enable
        self._quick_stopped = False
        self._stale: list[str] = []
        self._rebooted: list[str] = []  # drives that sent a boot-up after init()
        self._heartbeat_lost: list[str] = []  # drives whose heartbeat stopped (until recover)
        self._last_complete_cycle = 0  # `_cycle` at the last complete cycle (or init)
        self._completed_cycle = -1  # the SYNC whose state went out last
        self._stall_armed_cycle = 0  # a stall is judged from here: a complete cycle or recover
        self._stalled = False  # no complete cycle for `stall_cycles` SYNCs, until one comes
        self._stall_latched = ""  # the stall's text, latched while enabled (until recover)
        self._bus_off = False
        self._send_failures_in_row = 0
        self._failure_halt = False
        self._last_command_t = -math.inf
        self._previous_cycle_t = -math.inf  # the start of the last cycle (commands_late)
        self._commanded = False  # a command came since the last enable
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

    # --- configuration -------------------------------------------------------------------

    def init(self, sdo_timeout_s: float = 0.5) -> None:
        """Configure every drive over SDO in PRE-OPERATIONAL and start it (NMT OPERATIONAL).

        Raises:
            BridgeError: a drive did not answer, or refused a setting.
        """
        p = self.params
        for k, axis in enumerate(self._axes):
            node = axis.node
            node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
            _drop_unasked_sdo_responses(node.sdo)
            _forget_invalid_nmt_state(node)
            try:
                node.nmt.state = "PRE-OPERATIONAL"
                supported = int(node.sdo[od.SUPPORTED_DRIVE_MODES].raw)
                if not supported >> (axis.mode - 1) & 1:  # CiA 402-2 0x6502: bit n-1, mode n
                    raise BridgeError(
                        f"drive {axis.joint} (node {node.id}) does not support mode {axis.mode} "
                        f"(0x6502 = 0x{supported:08X})"
                    )
                node.sdo[od.MODES_OF_OPERATION].raw = axis.mode
                node.sdo[od.CYCLE_PERIOD].raw = codec.CYCLE_PERIOD.encode(1.0 / p.cycle_hz)
                node.sdo[od.HEARTBEAT_PRODUCER].raw = p.heartbeat_producer_ms
                node.sdo[od.HEARTBEAT_CONSUMER][1].raw = (
                    p.master_node_id << 16
                ) | p.heartbeat_consumer_ms
                node.sdo[od.RPDO_COMMUNICATION][5].raw = p.rpdo_deadline_ms
                rated_torque_mnm = node.sdo[od.MOTOR_RATED_TORQUE].raw
                rated_current_ma = node.sdo[od.MOTOR_RATED_CURRENT].raw
                max_permille = int(node.sdo[od.MAX_TORQUE].raw)
                increments = node.sdo[od.POSITION_ENCODER_RESOLUTION][1].raw
                revolutions = node.sdo[od.POSITION_ENCODER_RESOLUTION][2].raw
                node.tpdo.read()  # type: ignore[no-untyped-call]
                node.rpdo.read()  # type: ignore[no-untyped-call]
                if p.pdo_layout == "compact":
                    configure_compact_pdos(node, p.slow_tpdo_every, MODE_TARGETS[axis.mode])
            except (
                canopen.SdoCommunicationError,
                canopen.SdoAbortedError,
                KeyError,
                ValueError,
            ) as exc:
                raise BridgeError(
                    f"drive {axis.joint} (node {node.id}): configuration failed: {exc}"
                ) from exc
            try:
                axis.units = DriveUnits.from_raw(
                    rated_torque_mnm, rated_current_ma, increments, revolutions
                )
                axis.scale = TorqueScale(axis.k_t, axis.units.rated_torque_nm, max_permille)
                axis.velocity = codec.velocity(axis.units)
            except (CodecError, ValueError) as exc:
                raise BridgeError(f"drive {axis.joint} (node {node.id}): {exc}") from exc
            self._bind_pdos(axis)
            node.emcy.add_callback(self._emcy_callback(axis))
            if axis.boot_watch is None:  # once: init() may run again
                axis.boot_watch = self._heartbeat_callback(axis)
                self.network.subscribe(
                    cia301.HEARTBEAT_COB_BASE + self.params.node_ids[k], axis.boot_watch
                )
        for axis in self._axes:
            _forget_invalid_nmt_state(axis.node)
            axis.node.nmt.state = "OPERATIONAL"
            axis.last_tpdo_t = self._clock()
        with self._lock:
            self._rebooted = []  # configured again: a restart before this no longer matters
            self._arm_watches(self._clock())
        self._initialized = True

    def _bind_pdos(self, axis: _Axis) -> None:
        """Bind the RPDO(s) the cycle writes and a decoder to each enabled TPDO.

        The target torque may share an RPDO with the controlword (RPDO1 of CiA 402's
        default mapping) or have one of its own, with the controlword in another RPDO that is
        sent only when it changes (and every `CONTROLWORD_REFRESH_CYCLES`): that keeps a
        4-axis 1 kHz cycle inside a 1 Mbit/s bus (docs/can.md). The TPDOs sent after every SYNC
        must carry position and velocity; they make a cycle complete.
        """
        self._bind_rpdos(axis)
        self._bind_tpdos(axis)

    def _bind_rpdos(self, axis: _Axis) -> None:
        wanted = MODE_TARGETS[axis.mode]
        cw = target = None
        for number in axis.node.rpdo:
            rpdo = axis.node.rpdo[number]
            if not rpdo.enabled:
                continue
            indices = {int(var.index) for var in rpdo}
            if wanted in indices and target is None:
                target, axis.target_var = rpdo, rpdo[wanted]
            if od.CONTROLWORD in indices and cw is None:
                cw, axis.cw_var = rpdo, rpdo[od.CONTROLWORD]
        if cw is None or target is None:
            what = "controlword" if cw is None else f"target 0x{wanted:04X} of mode {axis.mode}"
            raise BridgeError(f"drive {axis.joint}: no enabled RPDO maps the {what}")
        axis.rpdo = target
        axis.cw_rpdo = None if cw is target else cw
        axis.cw_sent, axis.cw_age = -1, 0
        axis.rpdo_cob_id = int(target.cob_id)
        axis.cw_cob_id = int(cw.cob_id)
        axis.packer = RpdoPacker.of(axis.cw_var, axis.target_var)

    def _bind_tpdos(self, axis: _Axis) -> None:
        mapped: set[int] = set()
        cyclic: set[int] = set()
        decoded: set[str] = set()
        axis.sync_mask = 0
        for number in axis.node.tpdo:
            tpdo = axis.node.tpdo[number]
            if not tpdo.enabled:
                continue
            indices = {int(var.index) for var in tpdo}
            mapped |= indices
            bit = 0
            if tpdo.trans_type == EVERY_SYNC:
                bit = 1 << number
                axis.sync_mask |= bit
                cyclic |= indices
            callback, fields = self._tpdo_callback(axis, tpdo, bit)
            decoded |= fields
            # canopen's PdoMap subscribed itself when read; decode the raw frames instead.
            self.network.unsubscribe(tpdo.cob_id, tpdo.on_message)
            self.network.subscribe(tpdo.cob_id, callback)
        if not REQUIRED_TPDO_OBJECTS.issubset(mapped):
            missing = ", ".join(f"0x{i:04X}" for i in sorted(REQUIRED_TPDO_OBJECTS - mapped))
            raise BridgeError(f"drive {axis.joint}: TPDOs do not map {missing}")
        if not CYCLIC_TPDO_OBJECTS.issubset(cyclic):
            missing = ", ".join(f"0x{i:04X}" for i in sorted(CYCLIC_TPDO_OBJECTS - cyclic))
            raise BridgeError(
                f"drive {axis.joint}: no TPDO sent after every SYNC (transmission type 1) "
                f"maps {missing}"
            )
        axis.has_drive_state = "drive_state" in decoded
        axis.decoded = frozenset(decoded)

    # --- PDO and EMCY reception (notifier thread) ----------------------------------------

    def _tpdo_callback(
        self, axis: _Axis, tpdo: Any, sync_bit: int
    ) -> tuple[Callable[[int, bytearray, float], None], frozenset[str]]:
        """A raw-frame decoder for one TPDO, compiled once from its mapping (read over SDO).

        The frame is unpacked by one struct that skips the bytes of objects the bridge does not
        use, and each value goes through its codec's decoder into `AxisState`
        (`compile_apply`): no lookups per frame. At 500 Hz x 8 TPDOs this runs on the notifier
        thread that every frame of the bus shares.

        Args:
            axis: the drive.
            tpdo: its canopen PdoMap, read from the drive.
            sync_bit: the TPDO's bit in `_Axis.sync_mask` (sent each SYNC), or 0.

        Returns:
            The callback, and the `AxisState` fields it fills.
        """
        fmt, end = "<", 0
        targets: list[Target] = []
        for var in tpdo:
            if var.offset % 8 or var.length % 8:
                raise BridgeError(
                    f"drive {axis.joint}: TPDO maps 0x{var.index:04X} at a bit offset or with a "
                    "bit length the bridge does not decode"
                )
            offset = var.offset // 8
            end = offset + var.length // 8
            target = self._target(axis, var.od)
            if target is None:
                continue  # an object the bridge has no use for: its bytes are skipped
            fmt += f"{offset - struct.calcsize(fmt)}x" + od.DataType(var.od.data_type).struct_format
            targets.append(target)
        apply = compile_apply(targets, struct.Struct(fmt).unpack_from, axis.gear)
        size = end  # the whole mapping: a shorter frame is not this PDO
        carries_statusword = any(int(var.index) == od.STATUSWORD for var in tpdo)

        def on_tpdo(_can_id: int, data: bytearray, _timestamp: float) -> None:
            now = self._clock()
            if len(data) < size:
                self.counters.bad_pdos += 1
                return
            apply(axis.state, data)
            axis.last_tpdo_t = now
            axis.statuswords_received += carries_statusword
            if sync_bit:
                self._mark_fresh(axis, sync_bit, now)

        return on_tpdo, frozenset(name for t in targets for name in t.fields)

    def _target(self, axis: _Axis, obj: Any) -> Target | None:
        """Where one mapped object goes in `AxisState` and how it is decoded; None: skip it.

        Objects the table does not know are skipped. A standard object whose EDS type differs
        from CiA 402's is refused; a manufacturer-specific one that is not lca_hil's (another
        name or type at the same index, on a real drive) is skipped.
        """
        known = od.BY_KEY.get((int(obj.index), int(obj.subindex)))
        if known is None:
            return None
        ours = int(obj.data_type) == known.data_type
        if known.manufacturer_specific and not (ours and obj.name == known.name):
            return None
        if not ours:
            raise BridgeError(
                f"drive {axis.joint}: its EDS types 0x{known.index:04X} as data type "
                f"0x{int(obj.data_type):04X}, {known.reference} is {known.data_type.name}"
            )
        units = axis.units
        assert units is not None  # init() reads them before it binds the PDOs
        make = TARGETS.get(known.index)
        if make is not None:
            return make(units)
        if known.signal:  # eta_m, eta_l, load/friction torque, voltage: AxisState fields
            return Target((known.signal,), codec.codec_for(known, units).decoder())
        return None

    def _mark_fresh(self, axis: _Axis, bit: int, now: float) -> None:
        snapshot = None
        stalled_for = 0
        with self._lock:
            axis.fresh |= bit
            axis.seen |= bit
            if all(a.fresh == a.sync_mask for a in self._axes):
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
                if self._stalled:
                    self._stalled = False
                    stalled_for = self._cycle - self._last_complete_cycle
                self._last_complete_cycle = self._stall_armed_cycle = self._cycle
                self.counters.complete_cycles += 1
                if self.keep_latencies:
                    self.latencies_s.append(time.monotonic() - self._sync_mono_s)
                snapshot = Snapshot(
                    self._sync_wall_s,
                    self._cycle,
                    tuple(copied(a.state) for a in self._axes),
                )
        if stalled_for:
            log.warning("complete cycles again after %d SYNCs without one", stalled_for)
        if snapshot is not None and self.on_state is not None:
            self.on_state(snapshot)

    def _heartbeat_callback(self, axis: _Axis) -> Callable[[int, bytearray, float], None]:
        """The master's heartbeat consumer of one drive (CiA 301 7.2.8.3.2.2) and its boot-ups.

        Every heartbeat (1 byte: the NMT state) is stamped on reception, on the clock the
        cycle's `_check_heartbeats` judges it by (the frame's own timestamp is the bus's clock,
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
            if data[0] != 0 or not self._initialized:
                return
            self.counters.drive_restarts += 1
            with self._lock:
                if axis.joint in self._rebooted:
                    return
                self._rebooted.append(axis.joint)
            log.error("drive %s restarted (boot-up): axes stopped until ~/init", axis.joint)

        return on_heartbeat

    def _emcy_callback(self, axis: _Axis) -> Callable[[Any], None]:
        def on_emcy(entry: Any) -> None:
            code = int(entry.code)
            if code & 0xFF00 == 0:
                return  # "error reset / no error": nothing to latch
            self.counters.emcy_received += 1
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

    def _on_error_frame(self, error_class: int) -> None:
        self.counters.error_frames += 1
        if error_class & CAN_ERR_BUSOFF:
            with self._lock:
                self._bus_off = True

    # --- commands and requests (any thread) ----------------------------------------------

    def set_currents(self, currents_a: Sequence[float], now: float | None = None) -> str | None:
        """Take a current command (A, joint order); None, or why it was refused."""
        if len(currents_a) != len(self._axes):
            self.counters.commands_rejected += 1
            return f"expected {len(self._axes)} currents ({', '.join(self.params.joints)})"
        if not all(math.isfinite(v) for v in currents_a):
            self.counters.commands_rejected += 1
            return f"currents must be finite, got {list(currents_a)}"
        with self._lock:
            for axis, value in zip(self._axes, currents_a, strict=True):
                axis.command_a = float(value)
            self._commands_arrived(self._clock() if now is None else now)
        self.counters.commands_accepted += 1
        return None

    def set_velocities(self, velocities: Sequence[float], now: float | None = None) -> str | None:
        """Take a velocity command (joint rad/s or m/s, joint order) for the CSV axes.

        The CST axes ignore it (they take `set_currents`); both count as the controller's
        commands for the silence watch. None, or why it was refused.
        """
        if len(velocities) != len(self._axes):
            self.counters.commands_rejected += 1
            return f"expected {len(self._axes)} velocities ({', '.join(self.params.joints)})"
        if not all(math.isfinite(v) for v in velocities):
            self.counters.commands_rejected += 1
            return f"velocities must be finite, got {list(velocities)}"
        with self._lock:
            for axis, value in zip(self._axes, velocities, strict=True):
                axis.command_rad_s = float(value)
            self._commands_arrived(self._clock() if now is None else now)
        self.counters.commands_accepted += 1
        return None

    def _commands_arrived(self, now: float) -> None:
        if self._answered_cycle != self._cycle:  # the first command after this SYNC
            self._answered_cycle = self._cycle
            self._command_latencies_s.append(time.monotonic() - self._sync_mono_s)
        self._last_command_t = now
        self._commanded = True
        if not self._quick_stopped:
            self._silence_halt = False  # the controller is back before the quick stop

    @property
    def velocity_axes(self) -> tuple[str, ...]:
        """The joints run in CSV (they take `set_velocities`)."""
        return tuple(a.joint for a in self._axes if a.mode == MODE_CSV)

    def enable(self, on: bool) -> str:
        """Walk every drive to operation enabled (or back to ready to switch on)."""
        with self._lock:
            if on and self.latched_reason():
                return f"not enabled: {self.latched_reason()}; call ~/recover first"
            self._want = Want.ENABLED if on else Want.DISABLED
            self._user_halt = False
            self._silence_halt = False
            self._quick_stopped = False
            self._commanded = False
        return "enabling" if on else "disabling"

    def halt(self) -> None:
        """Zero torque with the halt bit; the drives stay enabled."""
        with self._lock:
            self._user_halt = True

    def recover(self) -> None:
        """Clear the bridge's latches and reset drive faults.

        The latches: EMCY, stale drive, lost heartbeat, stall of complete cycles, bus-off, send
        failures.

        The heartbeat and stall watches start again from now, as the stale one does: a drive
        still silent is latched again after its consumer time (or `stall_cycles` SYNCs).

        The drives end up disabled: enabling again is a separate, explicit request. Each drive
        is also sent NMT start (CiA 301 7.2.8.3.2.1, command 0x01): a drive whose
        communication error took it to PRE-OPERATIONAL (0x1029 sub 1 = 0, CiA 301's default)
        sends its PDOs again; one already OPERATIONAL ignores it.
        """
        if self._initialized and not self._bus_off:
            for axis in self._axes:
                try:
                    axis.node.nmt.state = "OPERATIONAL"
                except can.CanError as exc:
                    log.error("NMT start of %s failed: %s", axis.joint, exc)
        with self._lock:
            for axis in self._axes:
                axis.statuswords_at_reset = axis.statuswords_received
                axis.emcy_code = 0
                axis.advisory_code = axis.advisory_count = 0
                axis.last_tpdo_t = axis.last_heartbeat_t = self._clock()
            self._stale = []
            self._heartbeat_lost = []
            self._stall_latched = ""
            self._stall_armed_cycle = self._cycle
            self._bus_off = False
            self._failure_halt = False
            self._send_failures_in_row = 0
            self._quick_stopped = False
            self._user_halt = False
            self._silence_halt = False
            self._want = Want.FAULT_RESET

    def latched_reason(self) -> str:
        """Why the axes are held (stopped or halted) until `recover()`, or ''."""
        reasons = [self._stop_reason()] if self._stop_reason() else []
        if self._failure_halt:
            reasons.append(f"{self.params.max_send_failures} send failures in a row")
        return "; ".join(reasons)

    def _stop_reason(self) -> str:
        """The latches that quick-stop all axes: EMCY, stale, heartbeat, stall, restart, bus-off."""
        reasons = []
        latched = [
            f"{a.joint} {emcy.describe(a.emcy_code, a.has_drive_state)}"
            for a in self._axes
            if a.emcy_code
        ]
        if latched:
            reasons.append("EMCY " + ", ".join(latched))
        if self._stale:
            reasons.append("stale drive " + ", ".join(self._stale))
        if self._heartbeat_lost:
            reasons.append("lost heartbeat of " + ", ".join(self._heartbeat_lost))
        if self._stall_latched:
            reasons.append(self._stall_latched)
        if self._rebooted:
            reasons.append(f"drive {', '.join(self._rebooted)} restarted (boot-up): ~/init")
        if self._bus_off:
            reasons.append("bus-off")
        return "; ".join(reasons)

    # --- the cycle -----------------------------------------------------------------------

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
            now = time.monotonic()
            freeze = self._freeze_watch.check(now - previous_start - period)
            if freeze is not None:
                self._discount_freeze(freeze, now)
            previous_start = now
            self.cycle(now)
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # more than a period late: do not burst to catch up
                next_t = time.monotonic()
            elif delay > 0.0:
                self._stop.wait(delay)

    def _count_command_timing(self, now: float) -> None:
        """Count this cycle's command as in time (newer than the last cycle) or late."""
        if self._commanded:
            if self._last_command_t >= self._previous_cycle_t:
                self.counters.commands_in_time += 1
            else:
                self.counters.commands_late += 1
        self._previous_cycle_t = now

    def cycle(self, now: float) -> None:
        """One cycle: safety checks, controlwords and RPDOs, SYNC, master heartbeat."""
        p = self.params
        if self.keep_latencies:
            self.cycle_starts_s.append(now)
        with self._lock:
            if not self._initialized or self._bus_off:
                return  # bus-off: no cyclic transmission until recover()
            if any(a.fresh for a in self._axes) and self._cycle:
                self.counters.late_cycles += 1
            self._count_command_timing(now)
            for a in self._axes:
                a.fresh = 0
            self._check_safety(now)
            want = self._want
            if want is Want.ENABLED and (self._quick_stopped or self._stop_reason()):
                want = Want.QUICK_STOP
            frames = [f for axis in self._axes for f in self._rpdo_frames(axis, want)]
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
        try:
            with batched_sends(self.network.bus):  # over lca_remote: one write for the cycle
                for cob_id, data in frames:
                    self._send(cob_id, data)
                self._send(cia301.SYNC_COB_ID, b"")
                if now >= self._next_heartbeat_t:
                    self._next_heartbeat_t = now + p.heartbeat_consumer_ms / 3000.0
                    self._send(
                        cia301.HEARTBEAT_COB_BASE + p.master_node_id,
                        bytes([cia301.NMT_STATE_OPERATIONAL]),
                    )
        except can.CanError as exc:  # the batch's one write failed
            self._send_failed(exc)

    def _discount_freeze(self, freeze: Freeze, now: float) -> None:
        """Move the silence deadlines on by `frozen_s`: this process stood still, not the others.

        Two cycle starts further apart than a period plus `FREEZE_THRESHOLD_S` mean the cycle
        thread was frozen (the GIL held by a library load, a paused host). The commands and
        TPDOs sent meanwhile wait unread in the queues; judging the controller's and the drives'
        silence on waking would blame them for the freeze. A controller or drive that is silent
        while this thread runs is still caught on time: no deadline moves past `now`.
        """
        with self._lock:
            self.counters.process_freezes += 1
            skip_s = freeze.discount_s
            self._last_command_t = discounted(self._last_command_t, skip_s, now)
            for axis in self._axes:
                axis.last_tpdo_t = discounted(axis.last_tpdo_t, skip_s, now)
                axis.last_heartbeat_t = discounted(axis.last_heartbeat_t, skip_s, now)
        if self.counters.process_freezes == 1:
            log.warning(
                "the cycle thread stood still for %.0f ms; silence deadlines do not count it "
                "(further freezes are only counted)",
                freeze.frozen_s * 1e3,
            )

    def _check_safety(self, now: float) -> None:
        p = self.params
        silent_s = now - self._last_command_t
        if self._want is Want.ENABLED:
            if not self._commanded:
                self._silence_halt = True  # enabled, no controller yet: zero torque, halted
            elif silent_s > p.command_timeout_s + p.quick_stop_after_s:
                if not self._quick_stopped:
                    log.warning("no command for %.3f s: quick stop", silent_s)
                self._quick_stopped = True
            elif silent_s > p.command_timeout_s and not self._silence_halt:
                self._silence_halt = True
                self.counters.silence_halts += 1
                log.warning("no command for %.3f s: halt, zero torque", silent_s)
            for axis in self._axes:
                silent_s = now - axis.last_tpdo_t
                if silent_s > p.stale_timeout_s and axis.joint not in self._stale:
                    self._stale.append(axis.joint)
                    log.error("drive %s is stale: no TPDO for %.3f s", axis.joint, silent_s)
        self._check_heartbeats(now)
        self._check_cycle_stall()

    def _arm_watches(self, now: float) -> None:
        """Start the heartbeat and stall watches (init): from now, and from this cycle.

        CiA 301 7.2.8.3.2.2 starts a consumer at the first heartbeat it receives; the master
        wrote every drive's 0x1017 itself, so it expects one from now on, and a drive that never
        sends one is caught too.
        """
        for axis in self._axes:
            axis.last_heartbeat_t = now
            axis.heartbeat_lost = False
            axis.fresh = axis.seen = 0
        self._last_complete_cycle = self._stall_armed_cycle = self._cycle
        self._stalled = False

    def _check_heartbeats(self, now: float) -> None:
        """The master's heartbeat consumer (CiA 301 7.2.8.3.2.2): a silent drive is latched.

        Whatever the drives are asked to do: a drive that lost its heartbeat may have lost its
        bus, and nothing it reports can be trusted to stop it; every axis stops until
        `recover()`. Each loss is counted and logged once, however often `recover()` latches it
        again while the drive stays silent.
        """
        timeout_s = self.params.drive_heartbeat_timeout_s
        if timeout_s <= 0.0:
            return  # 0x1017 = 0: the drives send no heartbeat (CiA 301)
        for axis in self._axes:
            silent_s = now - axis.last_heartbeat_t
            if silent_s <= timeout_s:
                continue
            if axis.joint not in self._heartbeat_lost:
                self._heartbeat_lost.append(axis.joint)
            if not axis.heartbeat_lost:
                axis.heartbeat_lost = True
                self.counters.heartbeats_lost += 1
                log.error(
                    "lost heartbeat of %s: none for %.3f s (consumer time %.3f s): latched, "
                    "axes stopped until ~/recover",
                    axis.joint,
                    silent_s,
                    timeout_s,
                )

    def _check_cycle_stall(self) -> None:
        """No complete cycle for `stall_cycles` SYNCs sent: counted, and latched while enabled.

        Judged in SYNCs the cycle sent, not in seconds: a cycle thread that stood still sent
        none. Disabled, it is a state (`cycle_stall()`, WARN on /diagnostics) that ends with the
        next complete cycle: no torque is at stake, but joint_states stop. Enabled, the
        controller has no state to close its loops on, and one that runs on a timer would
        command blind: every axis stops until `recover()`, as for a stale drive (which catches
        a drive without any TPDO, not one without its cyclic one).
        """
        if self._cycle - self._stall_armed_cycle <= self.params.stall_cycles:
            return
        if not self._stalled:
            self._stalled = True
            self.counters.cycle_stalls += 1
            log.warning("%s", self._stall_text())
        if self._want is Want.ENABLED and not self._stall_latched:
            self._stall_latched = self._stall_text()
            log.error("%s: axes stopped until ~/recover", self._stall_latched)

    def _stall_text(self) -> str:
        """What stalls the complete cycles: the drives and the every-SYNC TPDOs not received."""
        missing = []
        for axis in self._axes:
            lost = axis.sync_mask & ~axis.seen
            numbers = [f"TPDO{n}" for n in range(1, lost.bit_length()) if lost >> n & 1]
            if numbers:
                missing.append(f"{axis.joint} {'+'.join(numbers)}")
        why = ", ".join(missing) + " missing" if missing else "every TPDO late"
        return f"no complete cycle for {self._cycle - self._last_complete_cycle} SYNCs: {why}"

    def _rpdo_frames(self, axis: _Axis, want: Want) -> list[tuple[int, bytes]]:
        """The RPDO frame(s) of one drive: the torque's, and the controlword's if due."""
        state = axis.state.power_state
        controlword = ctl.next_controlword(state, want, axis.controlword)
        target = 0
        running = want is Want.ENABLED and state is PowerState.OPERATION_ENABLED
        if running and (self._silence_halt or self._user_halt or self._failure_halt):
            controlword |= CW_HALT
        elif running and axis.mode == MODE_CSV and axis.velocity is not None:
            target = axis.velocity.encode(axis.command_rad_s * axis.gear)
        elif running and axis.scale is not None:
            target, clamped = axis.scale.target_permille(axis.command_a)
            self.counters.commands_clamped += int(clamped)
        axis.controlword = controlword
        packer = axis.packer
        if packer is None:  # an object at a bit offset: canopen packs the mapping
            axis.cw_var.raw = controlword
            axis.target_var.raw = target
            cw_data, target_data = bytes(axis.cw_var.pdo_parent.data), bytes(axis.rpdo.data)
        else:
            cw_data, target_data = packer.pack(controlword, target)
        frames = []
        cw_rpdo = axis.cw_rpdo
        if cw_rpdo is not None:
            axis.cw_age += 1
            if controlword != axis.cw_sent or axis.cw_age >= CONTROLWORD_REFRESH_CYCLES:
                axis.cw_sent, axis.cw_age = controlword, 0
                frames.append((axis.cw_cob_id, cw_data))
        frames.append((axis.rpdo_cob_id, target_data))
        return frames

    def _send(self, cob_id: int, data: bytes) -> None:
        try:
            self.network.send_message(cob_id, data)
        except can.CanError as exc:
            self._send_failed(exc)
            return
        self._send_failures_in_row = 0
        self.counters.frames_sent += 1
        self.counters.bits_sent += bus_load.frame_bits(len(data))
        self.counters.nominal_bits += bus_load.frame_bits_nominal(len(data))

    def _send_failed(self, exc: can.CanError) -> None:
        """Count a failed send; `max_send_failures` of them in a row halt the axes."""
        self._send_failures_in_row += 1
        in_row = self._send_failures_in_row
        halting = in_row >= self.params.max_send_failures and not self._failure_halt
        if in_row >= self.params.max_send_failures:
            self._failure_halt = True  # before the count: whoever sees the count sees the halt
        self.counters.send_failures += 1
        if halting:
            log.error("%d failed sends in a row: halt (%s)", in_row, exc)

    # --- inspection ----------------------------------------------------------------------

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

        None while commands come in time, or while the drives are not wanted enabled (nobody
        needs to command a disabled drive). `latched` is True after the quick stop, which holds
        until `enable(True)` is asked again; the halt before it ends by itself when commands
        return.
        """
        with self._lock:
            if self._want is not Want.ENABLED:
                return None
            silent_s = now - self._last_command_t
            if self._quick_stopped:
                return True, (
                    f"quick stop: no command for {silent_s:.1f} s "
                    f"(over {self.params.command_timeout_s + self.params.quick_stop_after_s:g} "
                    "s); enable again (~/enable) once the controller runs"
                )
            if not self._commanded:
                return False, "enabled, waiting for the first command: halted, zero torque"
            if self._silence_halt:
                return False, f"no command for {silent_s:.1f} s: halted, zero torque"
        return None

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
            return self._stall_text() if self._stalled else ""

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
        return now - self._last_command_t

    def sdo_read(self, joint: str, index: int, subindex: int) -> int | float | str:
        """Read one object of a drive (any NMT state); raises canopen errors."""
        var = self._var(joint, index, subindex)
        value: int | float | str = var.raw
        return value

    def sdo_write(self, joint: str, index: int, subindex: int, value: int | float) -> None:
        """Write one object of a drive; raises canopen errors (SdoAbortedError with its code)."""
        self._var(joint, index, subindex).raw = value

    def _var(self, joint: str, index: int, subindex: int) -> Any:
        entry = self._axis(joint).node.sdo[index]
        return entry[subindex] if isinstance(entry, (SdoRecord, SdoArray)) else entry

    def _axis(self, joint: str) -> _Axis:
        for axis in self._axes:
            if axis.joint == joint:
                return axis
        raise KeyError(f"unknown joint {joint!r}; joints are {list(self.params.joints)}")


def _forget_invalid_nmt_state(node: canopen.RemoteNode) -> None:
    """Forget a drive's NMT state byte that CiA 301 does not define, before commanding it.

    canopen records the state byte of every frame on the drive's heartbeat COB-ID, valid or
    not (a random frame, a second producer), and its next NMT command then fails while it logs
    the old state by name (`KeyError`): `init()` could not reconfigure the drive until a valid
    heartbeat came. The command (CiA 301 7.2.8.3.1) does not depend on the recorded state, and
    the next heartbeat records the drive's real one; 0 (initialising) stands in until then.
    """
    if node.nmt._state not in canopen.nmt.NMT_STATES:  # canopen keeps it private
        node.nmt._state = 0


def _drop_unasked_sdo_responses(sdo: SdoClient) -> None:
    """Drop SDO responses that came while this master had no request out.

    canopen's client queues every frame on the drive's SDO response COB-ID, asked for or not.
    The default SDO channel serves one client at a time (CiA 301 7.2.4.1), and another client
    on it (a tool, a test, a random frame) leaves answers this master never asked for; the
    first transfer of `init()` would take such an answer for its own and fail ("Node returned
    a value for 0x1000:00 instead").
    """
    while True:
        try:
            sdo.responses.get_nowait()
        except queue.Empty:
            return
