"""The rack's side of the bus: canopen's Network with a mute, its listener, lockstep sends.

docs/can.md, "Fault injection" and "Lockstep".
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import can
import canopen

from lca_sim.canbus.data_frames import DataFrames
from lca_sim.canbus.frames import ReceiveFailures, send_frame
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.rack_state import NMT_STOPPED, Drive, RackCounters
from lca_sim.canbus.remote import RemoteTransportBus
from lca_sim.canbus.wire import MAX_BASE_ID
from lca_sim.cia402 import cia301
from lca_sim.cia402.objects import ERROR_REGISTER

logger = logging.getLogger(__name__)

# canopen's NodeScanner notes the node id of frames of these services (`Network.notify`).
_SCANNED_SERVICES = frozenset(canopen.network.NodeScanner.SERVICES)
_SERVICE_MASK = 0x780
_NODE_ID_MASK = 0x7F  # CiA 301 pre-defined connection set: function code, node id
# What `RackListener` does with a frame
_DROP, _SERVICE, _RACK = object(), object(), object()


class NullTask:
    """The heartbeat task of a node whose heartbeat is injected off: sends nothing."""

    def stop(self) -> None:
        """Nothing runs."""

    def update(self, data: bytes) -> None:
        """Nothing is sent."""


class CycleTask:
    """A periodic send (a heartbeat) of a lockstep rack, timed by the rack's plant time.

    canopen's NMT slave starts its heartbeat with `send_periodic`, a wall-clock thread; in
    lockstep the rack sends it from its SYNC handling instead (`RackNetwork.send_due`), every
    `period_s` of simulated time, the first at the next SYNC, so the bus carries the same
    frames whatever the host's speed.
    """

    def __init__(self, network: RackNetwork, can_id: int, data: bytes, period_s: float) -> None:
        self._network = network
        self.can_id = can_id
        self.data = bytes(data)
        self.period_s = period_s
        self.next_s: float | None = None  # None: at the next service

    def stop(self) -> None:
        """No further sends."""
        if self in self._network.cycle_tasks:
            self._network.cycle_tasks.remove(self)

    def update(self, data: bytes) -> None:
        """The frame's new data (canopen: the NMT state byte)."""
        self.data = bytes(data)


class RackListener(can.Listener):
    """The rack's only listener: filters every frame, then feeds canopen's services and the rack.

    It replaces canopen's own `MessageListener`, which hands any frame to the SDO server and
    the NMT slave, 29-bit and CAN FD ones included. The nodes are classical CANopen nodes with
    11-bit identifiers (CiA 301 uses CAN base frames; a 29-bit or a CAN FD frame is not
    CANopen CC traffic even when its identifier looks like an SDO or NMT one): those, remote
    frames (no object of these nodes answers RTR: TPDO COB-IDs carry bit 30) and error frames
    are counted and go no further.

    Args:
        network: the rack's network (canopen's services are fed through it).
        counters: the rack's counters.
        sdo_servers: SDO request COB-ID (0x600 + id) -> its drive.
        on_frames: the rack's handling of data frames that passed (each after canopen's), in
            order: (COB-ID, data) each, and their reception time. A run of frames read at
            once comes in one call.
        warn_once: logs a warning the first time its key comes: (key, message).
    """

    def __init__(
        self,
        network: RackNetwork,
        counters: RackCounters,
        sdo_servers: Mapping[int, Drive],
        on_frames: Callable[[list[tuple[int, bytes]], float], None],
        warn_once: Callable[[str, str], None],
    ) -> None:
        self._network = network
        self._counters = counters
        self._sdo_servers = sdo_servers
        self._on_frames = on_frames
        self._warn_once = warn_once
        self.receive_failures = ReceiveFailures()

    def on_message_received(self, msg: can.Message) -> None:
        """Filter the frame, then canopen's services, then the rack; never raises."""
        if msg.is_error_frame or msg.is_fd or msg.is_extended_id or msg.is_remote_frame:
            self._count_not_classical(msg)
            return
        self.on_data_frames(((msg.arbitration_id, bytes(msg.data)),), msg.timestamp)

    def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
        """Data frames from a linked bus or lca_remote, as `on_message_received` each.

        The rack takes a run of them in one call, in order. A frame for canopen's services
        (an SDO request, NMT, one its node scanner notes) reaches them after the rack has
        handled the frames before it, and before the rack handles it; the cycle's RPDOs and
        SYNC reach the rack only.
        """
        run: list[tuple[int, bytes]] = []
        sdo_servers = self._sdo_servers
        for cob, data in frames:
            if run and cob in sdo_servers:
                # its verdict reads the node's NMT state, which the frames before it may change
                self._on_frames(run, timestamp)
                run = []
            verdict = self._verdict(cob, data)
            if verdict is _DROP:
                continue
            if verdict is _SERVICE:
                if run:
                    self._on_frames(run, timestamp)
                    run = []
                self._notify(cob, data, timestamp)
            run.append((cob, bytes(data)))
        if run:
            self._on_frames(run, timestamp)

    def _verdict(self, cob: int, data: bytes | bytearray) -> object:
        """`_DROP` (counted), `_SERVICE` (canopen's, then the rack's) or `_RACK` (the rack's)."""
        counters = self._counters
        if len(data) > 8:
            counters.bad_frames += 1
            return _DROP
        sdo_server = self._sdo_servers.get(cob)
        if sdo_server is not None:
            if len(data) != 8:
                counters.bad_frames += 1  # CiA 301: an SDO request is 8 bytes; ignored otherwise
                return _DROP
            if sdo_server.nmt == NMT_STOPPED:
                # CiA 301 7.3.2.2 (NMT state machine, table of services per state): in STOPPED
                # only NMT and node guarding / heartbeat are active, so SDO is not answered.
                counters.sdo_ignored_stopped += 1
                return _DROP
        # An NMT frame of the wrong length goes to the rack (which counts it) only: canopen's
        # NMT slave would act on the first two bytes of a longer one.
        # Only frames canopen takes (SDO, NMT) or its node scanner notes: not the cycle's RPDOs
        # and SYNC, which would only cost the lookups. The SYNC (0x080, node id 0) is neither:
        # the scanner notes node ids 1-127 only.
        if (
            cob in self._network.subscribers
            or (cob & _SERVICE_MASK in _SCANNED_SERVICES and cob & _NODE_ID_MASK)
        ) and (cob != cia301.NMT_COB_ID or len(data) == 2):
            return _SERVICE
        return _RACK

    def _notify(self, cob: int, data: bytes | bytearray, timestamp: float) -> None:
        """Canopen's services (SDO server, NMT slave, node scanner) on one frame."""
        try:
            # canopen types the data bytearray; its SDO server and NMT slave only read it
            self._network.notify(cob, data, timestamp)  # type: ignore[arg-type]
        except Exception:
            self._counters.handler_errors += 1
            logger.exception("virtual drive: canopen failed on frame 0x%03X", cob)

    # python-can's Notifier calls its listeners: straight into the filter, not through
    # `can.Listener.__call__`, one call less per frame.
    __call__ = on_message_received

    def _count_not_classical(self, msg: can.Message) -> None:
        """Count a frame that is not an 11-bit classical CAN data frame by its kind."""
        counters = self._counters
        if msg.is_error_frame:
            counters.error_frames += 1
        elif msg.is_fd:
            counters.fd_frames += 1
        elif msg.is_extended_id:
            counters.extended_frames += 1
        else:
            counters.remote_frames += 1

    def on_error(self, exc: Exception) -> None:
        """The bus layer raised in the receive thread: count it, go on (`ReceiveFailures`).

        The notifier's thread survives because this listener handles the error; the exception
        it keeps is cleared so that the next send does not re-raise it (`RackNetwork.check`).
        A malformed datagram is one failure, retried at once; a bus that stays broken (the
        relay gone) is tried again every `RECEIVE_RETRY_S` instead of in a tight loop.
        """
        self._counters.bus_errors += 1
        self.receive_failures.failed(exc, self._network.notifier)
        self._warn_once(f"bus-error-{type(exc).__name__}", f"CAN receive error: {exc!r}")

    def stop(self) -> None:
        """Nothing to release."""


class RackNetwork(canopen.Network):
    """canopen's Network, minus one trap: a bus error must not poison every later send.

    python-can's Notifier keeps the last exception of its receive thread in
    `notifier.exception` even when a listener handled it, and `canopen.Network.check()`, called
    after every send, re-raises it: one malformed datagram from the bus layer would make every
    later SDO answer, heartbeat and TPDO fail until a restart. The rack's listener counts the
    error and clears it (`RackListener.on_error`); this check only clears one that a
    send saw before the listener did (both run on different threads).
    """

    def check(self) -> None:
        """Never raise: bus errors are counted by the rack's listener, not re-raised here."""
        if self.notifier is not None:
            self.notifier.exception = None

    def __init__(self, bus: can.BusABC) -> None:
        super().__init__(bus)
        # Fault injection (0x2030): the COB-IDs of frames that must not go out (a node in
        # bus-off: its EMCY, SDO answers, boot-up and heartbeat) and of periodic ones that must
        # not start (a heartbeat injected off). Replaced whole, so the sending threads read
        # them without a lock.
        self.muted: frozenset[int] = frozenset()
        self.muted_periodic: frozenset[int] = frozenset()
        self.on_dropped: Callable[[int], None] | None = None
        # After the frame with this COB-ID goes out, call this once (bus-off set over SDO
        # takes effect after its SDO answer, which is the node's last frame).
        self.after_send: dict[int, Callable[[], None]] = {}
        # Lockstep: periodic sends are `CycleTask`s sent by `send_due`, not threads.
        self.lockstep = False
        self.cycle_tasks: list[CycleTask] = []
        # lca_remote and the bridge's linked bus take classical data frames as they are, and
        # several in one call (one write, one delivery)
        self._bus_send_frames: Callable[[list[tuple[int, bytes]]], None] | None = None
        self.send_data_frames: Callable[[list[tuple[int, bytes]]], None] | None = None
        if isinstance(bus, RemoteTransportBus | LinkedVirtualBus):
            self._bus_send_frames = bus.send_data_frames
            self.send_data_frames = self._send_frames

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """Send as canopen does, except the frames of a node that fault injection silenced."""
        # canopen's send_message, one call shorter: every TPDO goes this way.
        if self.send_data_frames is not None and can_id <= MAX_BASE_ID and not remote:
            self.send_data_frames([(can_id, data)])  # the same frame, with no can.Message built
            return
        if can_id in self.muted:
            if self.on_dropped is not None:
                self.on_dropped(can_id)
            return
        send_frame(self, can_id, data, remote)
        self._sent((can_id,))

    def _send_frames(self, frames: list[tuple[int, bytes]]) -> None:
        """`send_message` of classical 11-bit data frames, in order, in one call of the bus.

        `send_data_frames` on lca_remote and the linked bus (else None): a drive's TPDOs after
        a SYNC leave in one write, with no chain of calls per frame.
        """
        muted = self.muted
        if muted:
            for can_id, _ in frames:
                if can_id in muted and self.on_dropped is not None:
                    self.on_dropped(can_id)
            frames = [frame for frame in frames if frame[0] not in muted]
            if not frames:
                return
        send = self._bus_send_frames
        if self.bus is None or send is None:
            raise RuntimeError("Not connected to CAN bus")
        with self.send_lock:
            send(frames)
        self._sent([can_id for can_id, _ in frames])

    def _sent(self, can_ids: Sequence[int]) -> None:
        """After frames went out: canopen's check, then what waited for one of them."""
        self.check()
        if self.after_send:
            for can_id in can_ids:
                then = self.after_send.pop(can_id, None)
                if then is not None:
                    then()

    def send_periodic(self, can_id: int, data: bytes, period: float, remote: bool = False) -> Any:
        """Send periodically (the heartbeat) as canopen does, except a heartbeat injected off."""
        if can_id in self.muted_periodic:
            return NullTask()
        if self.lockstep:
            task = CycleTask(self, can_id, bytes(data), period)
            self.cycle_tasks.append(task)
            return task
        return super().send_periodic(can_id, data, period, remote)

    def send_due(self, now_s: float) -> None:
        """Lockstep: send every periodic frame that is due at the rack's time `now_s`."""
        for task in list(self.cycle_tasks):
            if task.next_s is None or now_s >= task.next_s - 1e-9:
                base = now_s if task.next_s is None else task.next_s
                task.next_s = base + task.period_s
                self.send_message(task.can_id, task.data)


class RackSender:
    """The rack's frames and EMCYs out through its network; a failed send counted, not raised.

    Args:
        network: the rack's network.
        counters: the rack's counters (`send_errors`, `emcy_sent`, `frames_dropped_bus_off`).
        warn_once: logs a warning the first time its key comes: (key, message).
    """

    def __init__(
        self,
        network: RackNetwork,
        counters: RackCounters,
        warn_once: Callable[[str, str], None],
    ) -> None:
        self._network = network
        self._counters = counters
        self._warn_once = warn_once

    @property
    def takes_frames(self) -> bool:
        """Whether the bus takes several frames in one call (`send_frames`)."""
        return self._network.send_data_frames is not None

    def send(self, cob_id: int, data: bytes) -> bool:
        """One frame; False when the send failed (counted, said once per kind of error)."""
        try:
            self._network.send_message(cob_id, data)
        except (can.CanError, OSError, RuntimeError) as exc:
            self._counters.send_errors += 1
            self._warn_once(f"send-{type(exc).__name__}", f"send of 0x{cob_id:03X} failed: {exc}")
            return False
        return True

    def send_frames(self, frames: list[tuple[int, bytes]]) -> bool:
        """`send` of several frames in one call of the bus (`RackNetwork.send_data_frames`)."""
        send_data_frames = self._network.send_data_frames
        if send_data_frames is None:  # a bus that sends frame by frame
            return all([self.send(cob_id, data) for cob_id, data in frames])
        try:
            send_data_frames(frames)
        except (can.CanError, OSError, RuntimeError) as exc:
            self._counters.send_errors += 1
            self._warn_once(f"send-{type(exc).__name__}", f"send of the TPDOs failed: {exc}")
            return False
        return True

    def emcy(self, axis: Drive, code: int, data: bytes = b"") -> None:
        """Send an EMCY: code, 0x1001, and up to 5 manufacturer-specific bytes (CiA 301 7.2.7)."""
        if axis.nmt == NMT_STOPPED:
            return  # no EMCY in STOPPED (CiA 301)
        if axis.faults.bus_off:
            self._counters.frames_dropped_bus_off += 1
            return
        register = axis.value(ERROR_REGISTER)
        try:
            axis.node.emcy.send(code, register, data)
        except (can.CanError, OSError, RuntimeError) as exc:
            self._counters.send_errors += 1
            self._warn_once("emcy", f"EMCY send failed: {exc}")
            return
        self._counters.emcy_sent += 1
