"""The rack's PDO engine: every drive's PDOs configured over SDO, RPDOs received, TPDOs sent.

A part of the virtual drive rack that owns the PDO configuration and the RPDO routing table;
the frames go out through the rack's `send`, which counts what fails. Remapping the standard
way (COB-ID bit 31, mapping sub 0 = 0, entries, sub 0, bit 31 clear) and what is refused with
which SDO abort: docs/can.md, "Default PDO mapping".
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import can
from canopen import SdoAbortedError
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from lca_sim.canbus.rack_state import NMT_OPERATIONAL, Drive, Pdo, RackCounters, number_format
from lca_sim.canbus.remote import batched_sends
from lca_sim.cia402 import cia301
from lca_sim.cia402 import device as cia402
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import MappingEntry

# The PDO communication and mapping objects, all four ranges (CiA 301 0x1400-0x1BFF).
_PDO_OBJECTS_FIRST = od.RPDO_COMMUNICATION
_PDO_OBJECTS_LAST = od.TPDO_MAPPING + 0x1FF


class PdoEngine:
    """The PDOs of every drive of a rack.

    Args:
        axes: the rack's drives (each holds its PDOs).
        counters: the rack's counters.
        send: sends one frame (COB-ID, data); False when the send failed (counted there).
        send_frames: sends several frames in one call of the bus, in order, as one write
            (lca_remote) or one delivery (a linked bus); False when it failed (counted there).
            None on a bus that sends frame by frame (socketcan, virtual): `send` each.
        write: applies a received value: (drive, index, subindex, value, now); raises
            SdoAbortedError to refuse it.
        emcy: sends an EMCY from a drive: (drive, code).
        warn_once: logs a warning the first time its key comes: (key, message).
    """

    def __init__(
        self,
        axes: Sequence[Drive],
        counters: RackCounters,
        send: Callable[[int, bytes], bool],
        *,
        write: Callable[[Drive, int, int, int, float], None],
        emcy: Callable[[Drive, int], None],
        warn_once: Callable[[str, str], None],
        send_frames: Callable[[list[tuple[int, bytes]]], bool] | None = None,
    ) -> None:
        self._axes = axes
        self._counters = counters
        self._send = send
        self._send_frames = send_frames
        self._write = write
        self._emcy = emcy
        self._warn_once = warn_once
        # RPDO COB-ID -> the PDOs it feeds; replaced whole, so the receive thread reads it
        # without the lock.
        self.rpdo_table: dict[int, list[tuple[Drive, Pdo]]] = {}

    # --- configuration -------------------------------------------------------------------

    def load(self, axis: Drive) -> None:
        """Every PDO of `axis` from its stored objects (after boot or an NMT reset)."""
        n_rpdo = _count_pdos(axis.od, od.RPDO_COMMUNICATION)
        n_tpdo = _count_pdos(axis.od, od.TPDO_COMMUNICATION)
        axis.rpdos = [self._load(axis, n, receive=True) for n in range(1, n_rpdo + 1)]
        axis.tpdos = [self._load(axis, n, receive=False) for n in range(1, n_tpdo + 1)]
        self._rebuild_rpdo_table()
        _sort_tpdos(axis)

    def write(self, axis: Drive, index: int, subindex: int, value: int) -> int:
        """Apply a write to a PDO communication or mapping object; the value to store.

        Raises:
            SdoAbortedError: the write is refused (CiA 301 abort code).
        """
        if not _PDO_OBJECTS_FIRST <= index <= _PDO_OBJECTS_LAST:
            return value  # not a PDO object: every RPDO value comes this way
        located = _pdo_of(axis, index)
        if located is None:
            return value
        pdo, is_mapping = located
        if is_mapping:
            self._write_mapping(axis, pdo, subindex, value)
            return value
        value = self._write_communication(pdo, subindex, value)
        if not pdo.receive:
            _sort_tpdos(axis)  # its COB-ID's valid bit or its type may have changed
        return value

    def mapped_object(self, axis: Drive, raw: int, receive: bool) -> ODVariable:
        """The object a mapping entry names, if it may be mapped in this direction."""
        entry = MappingEntry.decode(raw)
        if entry.index not in axis.od:
            raise SdoAbortedError(cia301.ABORT_NOT_MAPPABLE)
        obj = axis.od[entry.index]
        if isinstance(obj, ODRecord | ODArray):
            if entry.subindex not in obj:
                raise SdoAbortedError(cia301.ABORT_NOT_MAPPABLE)
            obj = obj[entry.subindex]
        elif entry.subindex != 0:
            raise SdoAbortedError(cia301.ABORT_NOT_MAPPABLE)
        allowed = obj.writable if receive else obj.readable
        if not (obj.pdo_mappable and allowed and entry.bits == len(obj) and entry.bits % 8 == 0):
            raise SdoAbortedError(cia301.ABORT_NOT_MAPPABLE)
        number_format(obj)
        return obj

    def _mapped_objects(self, axis: Drive, slots: Sequence[int], receive: bool) -> list[ODVariable]:
        objects = [self.mapped_object(axis, raw, receive) for raw in slots]
        if sum(len(obj) for obj in objects) > cia402.PDO_MAX_BITS:
            raise SdoAbortedError(cia301.ABORT_PDO_LENGTH)
        return objects

    def _getters(
        self, axis: Drive, objects: Sequence[ODVariable], receive: bool
    ) -> list[Callable[[], int]]:
        """What a TPDO reads for each mapped object when it is sent (an RPDO reads nothing)."""
        return [] if receive else [axis.getter(obj.index, obj.subindex) for obj in objects]

    def _load(self, axis: Drive, number: int, receive: bool) -> Pdo:
        com = (od.RPDO_COMMUNICATION if receive else od.TPDO_COMMUNICATION) + number - 1
        mapping = com + (od.RPDO_MAPPING - od.RPDO_COMMUNICATION)
        cob = axis.value(com, 1)
        count = axis.value(mapping, 0)
        slots = [axis.values.get((mapping, k), 0) for k in range(1, cia402.PDO_MAX_ENTRIES + 1)]
        pdo = Pdo(
            number=number,
            receive=receive,
            cob_id=cob & 0x7FF,
            valid=not cob & cia402.PDO_COB_ID_INVALID,
            transmission_type=axis.value(com, 2),
            inhibit_100us=axis.values.get((com, 3), 0),
            event_timer_ms=axis.values.get((com, 5), 0),
            slots=slots,
            count=count,
        )
        objects = self._mapped_objects(axis, slots[:count], receive)
        pdo.map(objects, self._getters(axis, objects, receive))
        return pdo

    def _write_communication(self, pdo: Pdo, subindex: int, value: int) -> int:
        """Apply a write to a PDO communication object; returns the value to store."""
        if subindex == 1:
            if value & cia402.PDO_COB_ID_EXTENDED or value & 0x1FFFFFFF > 0x7FF:
                raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
            valid = not value & cia402.PDO_COB_ID_INVALID
            cob_id = value & 0x7FF
            if pdo.valid and valid and cob_id != pdo.cob_id:
                # the COB-ID changes only while the PDO is invalid (bit 31 set)
                raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
            pdo.valid, pdo.cob_id = valid, cob_id
            pdo.latched, pdo.last_rx_s, pdo.last_data = None, None, None
            if pdo.receive:
                self._rebuild_rpdo_table()
            else:
                # CiA 301 0x1800 sub 1 bit 30: these drives never answer a remote frame, so a
                # TPDO's COB-ID keeps "no RTR allowed" whatever a master writes (masters that
                # write only bit 31 and the id, as many do, are not refused for it).
                value |= cia402.PDO_COB_ID_NO_RTR
        elif subindex == 2:
            if not cia402.is_valid_transmission_type(value):
                raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
            pdo.transmission_type, pdo.sync_count = value, 0
        elif subindex == 3:
            pdo.inhibit_100us = value
        elif subindex == 5:
            pdo.event_timer_ms = value
        return value

    def _write_mapping(self, axis: Drive, pdo: Pdo, subindex: int, value: int) -> None:
        if pdo.valid:
            raise SdoAbortedError(cia301.ABORT_DEVICE_STATE)  # set COB-ID bit 31 first
        if subindex == 0:
            if value > cia402.PDO_MAX_ENTRIES:
                raise SdoAbortedError(cia301.ABORT_PDO_LENGTH)
            objects = self._mapped_objects(axis, pdo.slots[:value], pdo.receive)
            pdo.map(objects, self._getters(axis, objects, pdo.receive))
            pdo.count = value
            pdo.latched, pdo.last_data = None, None
            return
        if pdo.count != 0:
            raise SdoAbortedError(cia301.ABORT_DEVICE_STATE)  # set sub 0 to 0 first
        if value != 0:
            self.mapped_object(axis, value, pdo.receive)
        pdo.slots[subindex - 1] = value

    def _rebuild_rpdo_table(self) -> None:
        """Route every valid RPDO's COB-ID to it (after a COB-ID write or a reset)."""
        table: dict[int, list[tuple[Drive, Pdo]]] = {}
        for axis in self._axes:
            for pdo in axis.rpdos:
                if pdo.valid:
                    table.setdefault(pdo.cob_id, []).append((axis, pdo))
        self.rpdo_table = table  # replaced whole: the receive thread reads it without the lock

    # --- reception -----------------------------------------------------------------------

    def receive(self, axis: Drive, pdo: Pdo, data: bytes, now: float) -> None:
        """An RPDO frame: latched until the next SYNC (synchronous types) or applied now."""
        if axis.faults.bus_off:
            return  # its controller takes no frame
        self._counters.rpdos_received += 1
        if axis.nmt != NMT_OPERATIONAL or not pdo.valid:
            self._counters.pdos_ignored_not_operational += 1
            return
        size_bytes = pdo.frame.size  # the mapping's length
        if len(data) != size_bytes:
            # CiA 301 EMCY error codes: 0x8210 "PDO not processed due to length error", 0x8220
            # "PDO length exceeded". The frame is not applied; one EMCY per run of wrong frames
            # (each is counted), so that a flood of them does not flood the bus with EMCYs.
            self._counters.bad_frames += 1
            code = (
                cia402.EMCY_PDO_LENGTH
                if len(data) < size_bytes
                else cia402.EMCY_PDO_LENGTH_EXCEEDED
            )
            if pdo.length_error != code:
                pdo.length_error = code
                self._emcy(axis, code)
            self._warn_once(
                f"rpdo-length-{axis.config.node_id}-{pdo.number}",
                f"node {axis.config.node_id} RPDO{pdo.number}: {len(data)} bytes, "
                f"mapping has {size_bytes}; dropped",
            )
            return
        pdo.length_error = 0
        pdo.last_rx_s = now
        if pdo.transmission_type <= cia402.SYNC_TRANSMISSION_MAX:
            pdo.latched = data
        else:
            self._apply(axis, pdo, data, now)

    def apply_latched(self, axes: Sequence[Drive], now: float) -> None:
        """At a SYNC: each drive's synchronous RPDOs received since the last (the latest wins)."""
        for axis in axes:
            for pdo in axis.rpdos:
                if pdo.latched is not None:
                    latched, pdo.latched = pdo.latched, None
                    self._apply(axis, pdo, latched, now)

    def _apply(self, axis: Drive, pdo: Pdo, data: bytes, now: float) -> None:
        for obj, value in zip(pdo.objects, pdo.frame.unpack(data), strict=True):
            try:
                self._write(axis, obj.index, obj.subindex, int(value), now)
            except SdoAbortedError:
                self._counters.rpdo_values_rejected += 1
        self._counters.rpdos_applied += 1

    # --- transmission --------------------------------------------------------------------

    def send_sync_tpdos(self, axes: Sequence[Drive], now: float, bus: can.BusABC | None) -> None:
        """At a SYNC: the synchronous TPDOs of `axes`; over lca_remote, in one write.

        With `send_frames`, the cycle's frames go to the bus in one call instead of one chain
        of calls each (rack, network, bus, batch): a drive's SYNC answer is most of the rack's
        Python per cycle (docs/can-transport.md, tenth round).
        """
        send_frames = self._send_frames
        if send_frames is not None:
            frames = [
                (pdo.cob_id, frame)
                for axis, pdo, frame in self._due_sync_tpdos(axes)
                if self._goes_out(axis, pdo, frame, now)
            ]
            if frames and send_frames(frames):
                self._counters.tpdos_sent += len(frames)
            return
        try:
            with batched_sends(bus):
                for axis, pdo, frame in self._due_sync_tpdos(axes):
                    self._send_tpdo(axis, pdo, frame, now)
        except (can.CanError, OSError) as exc:  # the batch's one write failed
            self._counters.send_errors += 1
            self._warn_once(f"send-{type(exc).__name__}", f"send of the TPDOs failed: {exc}")

    @staticmethod
    def _due_sync_tpdos(axes: Sequence[Drive]) -> Iterator[tuple[Drive, Pdo, bytes]]:
        """Each synchronous TPDO due at this SYNC, with its frame (CiA 301 0x1800 sub 2).

        Type 0 (acyclic synchronous) when its data changed, types 1-240 at every n-th SYNC.
        """
        for axis in axes:
            for pdo in axis.sync_tpdos:
                if pdo.transmission_type == 0:
                    frame = pdo.encode()
                    if frame != pdo.last_data:
                        yield axis, pdo, frame
                    continue
                pdo.sync_count += 1
                if pdo.sync_count >= pdo.transmission_type:
                    pdo.sync_count = 0
                    yield axis, pdo, pdo.encode()

    def service_event_tpdos(self, now: float) -> None:
        """Send the event-driven TPDOs whose data changed or whose event timer expired."""
        for axis in self._axes:
            if axis.nmt != NMT_OPERATIONAL:
                continue
            for pdo in axis.event_tpdos:
                since_s = now - pdo.last_sent_s
                timer_due = pdo.event_timer_ms > 0 and since_s >= pdo.event_timer_ms * 1e-3
                inhibited = since_s < pdo.inhibit_100us * 1e-4
                if inhibited and not timer_due:
                    continue  # nothing goes out, whatever the data: not read
                frame = pdo.encode()
                if timer_due or frame != pdo.last_data:
                    self._send_tpdo(axis, pdo, frame, now)

    def _send_tpdo(self, axis: Drive, pdo: Pdo, frame: bytes, now: float) -> None:
        if self._goes_out(axis, pdo, frame, now) and self._send(pdo.cob_id, frame):
            self._counters.tpdos_sent += 1

    def _goes_out(self, axis: Drive, pdo: Pdo, frame: bytes, now: float) -> bool:
        """Whether a TPDO due now reaches the bus (not in bus-off, not lost by injection).

        It counts as sent either way: its data and time are the ones the next change and the
        inhibit and event timers compare with.
        """
        pdo.last_data, pdo.last_sent_s = frame, now
        faults = axis.faults
        if faults.bus_off:
            self._counters.frames_dropped_bus_off += 1
            return False
        if faults.lost_tpdos >> (pdo.number - 1) & 1:
            self._counters.tpdos_lost += 1  # injected: lost as if sent (0x2030 sub 1)
            return False
        return True


def _sort_tpdos(axis: Drive) -> None:
    """`Drive.sync_tpdos` and `event_tpdos` from its TPDOs now (lists replaced whole)."""
    valid = [pdo for pdo in axis.tpdos if pdo.valid]
    axis.sync_tpdos = [p for p in valid if p.transmission_type <= cia402.SYNC_TRANSMISSION_MAX]
    axis.event_tpdos = [p for p in valid if p.transmission_type in cia402.TRANSMISSION_EVENT_TYPES]


def _pdo_of(axis: Drive, index: int) -> tuple[Pdo, bool] | None:
    """The PDO whose communication or mapping object `index` is, and whether it is mapping."""
    for base, pdos, is_mapping in (
        (od.RPDO_COMMUNICATION, axis.rpdos, False),
        (od.RPDO_MAPPING, axis.rpdos, True),
        (od.TPDO_COMMUNICATION, axis.tpdos, False),
        (od.TPDO_MAPPING, axis.tpdos, True),
    ):
        if 0 <= index - base < len(pdos):
            return pdos[index - base], is_mapping
    return None


def _count_pdos(dictionary: ObjectDictionary, communication_base: int) -> int:
    mapping_offset = od.RPDO_MAPPING - od.RPDO_COMMUNICATION
    count = 0
    while (
        communication_base + count in dictionary
        and communication_base + count + mapping_offset in dictionary
        and count < 512
    ):
        count += 1
    return count
