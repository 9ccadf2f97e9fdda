"""How the CANopen master sets a drive up: SDO configuration in PRE-OPERATIONAL, PDO binding.

A part of `Cia402Master`: it writes the bridge's settings (mode, 0x1006, heartbeats, RPDO
deadline, the compact PDO layout), reads the drive's units, binds the RPDOs the cycle writes
and compiles a decoder per TPDO (docs/can.md, "The PDO layout the bridge maps (compact)").
"""

from __future__ import annotations

import queue
import struct
from collections.abc import Callable
from typing import Any

import canopen
from canopen.sdo.client import SdoClient

from lca_sim.canbus.master_axis import MasterAxis
from lca_sim.canbus.master_params import MODE_TARGETS, BridgeError, BridgeParams
from lca_sim.canbus.master_pdo import (
    CYCLIC_TPDO_OBJECTS,
    EVERY_SYNC,
    REQUIRED_TPDO_OBJECTS,
    TARGETS,
    RpdoPacker,
    Target,
    compile_apply,
    configure_compact_pdos,
)
from lca_sim.canbus.master_state import Counters
from lca_sim.cia402 import codec
from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import CodecError, DriveUnits
from lca_sim.cia402.controlword import TorqueScale
from lca_sim.cia402.object_entry import DataType


class DriveSetup:
    """Configures a master's drives and binds their PDOs.

    Args:
        network: the master's network (the TPDO decoders subscribe on it).
        params: the bridge's settings.
        counters: the master's counters (`bad_pdos`).
        clock: the master's clock (each TPDO's reception stamp).
        on_sync_tpdo: a TPDO sent after every SYNC came: (drive, its bit, now).
    """

    def __init__(
        self,
        network: canopen.Network,
        params: BridgeParams,
        counters: Counters,
        clock: Callable[[], float],
        on_sync_tpdo: Callable[[MasterAxis, int, float], None],
    ) -> None:
        self.network = network
        self.params = params
        self.counters = counters
        self._clock = clock
        self._on_sync_tpdo = on_sync_tpdo

    def configure(self, axis: MasterAxis, sdo_timeout_s: float) -> None:
        """Configure one drive over SDO in PRE-OPERATIONAL, read its units, bind its PDOs.

        Raises:
            BridgeError: the drive did not answer, or refused a setting.
        """
        p = self.params
        node = axis.node
        node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
        _drop_unasked_sdo_responses(node.sdo)
        forget_invalid_nmt_state(node)
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
            axis.position = codec.position(axis.units)
        except (CodecError, ValueError) as exc:
            raise BridgeError(f"drive {axis.joint} (node {node.id}): {exc}") from exc
        self._bind_pdos(axis)

    def _bind_pdos(self, axis: MasterAxis) -> None:
        """Bind the RPDO(s) the cycle writes and a decoder to each enabled TPDO.

        The target torque may share an RPDO with the controlword (RPDO1 of CiA 402's
        default mapping) or have one of its own, with the controlword in another RPDO that is
        sent only when it changes (and every `CONTROLWORD_REFRESH_CYCLES`): that keeps a
        4-axis 1 kHz cycle inside a 1 Mbit/s bus (docs/can.md). The TPDOs sent after every SYNC
        must carry position and velocity; they make a cycle complete.
        """
        self._bind_rpdos(axis)
        self._bind_tpdos(axis)

    def _bind_rpdos(self, axis: MasterAxis) -> None:
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

    def _bind_tpdos(self, axis: MasterAxis) -> None:
        mapped: set[int] = set()
        cyclic: set[int] = set()
        decoded: set[str] = set()
        cob_ids: list[int] = []
        bound: list[tuple[int, Callable[[int, bytearray, float], None]]] = []
        axis.sync_mask = 0
        for cob_id, earlier in axis.tpdo_decoders:  # an earlier init()'s: decode each TPDO once
            if earlier in self.network.subscribers.get(cob_id, ()):
                self.network.unsubscribe(cob_id, earlier)
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
            cob_ids.append(int(tpdo.cob_id))
            bound.append((int(tpdo.cob_id), callback))
        axis.tpdo_cob_ids = tuple(cob_ids)
        axis.tpdo_decoders = tuple(bound)
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

    def _tpdo_callback(
        self, axis: MasterAxis, tpdo: Any, sync_bit: int
    ) -> tuple[Callable[[int, bytearray, float], None], frozenset[str]]:
        """A raw-frame decoder for one TPDO, compiled once from its mapping (read over SDO).

        The frame is unpacked by one struct that skips the bytes of objects the bridge does not
        use, and each value goes through its codec's decoder into `AxisState`
        (`compile_apply`): no lookups per frame. At 500 Hz x 8 TPDOs this runs on the notifier
        thread that every frame of the bus shares.

        Args:
            axis: the drive.
            tpdo: its canopen PdoMap, read from the drive.
            sync_bit: the TPDO's bit in `MasterAxis.sync_mask` (sent each SYNC), or 0.

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
            fmt += f"{offset - struct.calcsize(fmt)}x" + DataType(var.od.data_type).struct_format
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
                self._on_sync_tpdo(axis, sync_bit, now)

        return on_tpdo, frozenset(name for t in targets for name in t.fields)

    def _target(self, axis: MasterAxis, obj: Any) -> Target | None:
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


def forget_invalid_nmt_state(node: canopen.RemoteNode) -> None:
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
