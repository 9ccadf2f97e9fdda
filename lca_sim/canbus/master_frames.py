"""The master's frames on the bus: what it receives (TPDOs first) and how it sends a cycle.

In the place of canopen's per-frame path (its listener, `Network.notify`, `send_message`),
with the same steps for every frame canopen still handles (docs/can-transport.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import can
import canopen
from canopen.network import MessageListener

from lca_sim.canbus.data_frames import DataFrames, received_message
from lca_sim.canbus.frames import RECEIVE_RETRY_S, ReceiveFailures, send_frame
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.master_state import Counters
from lca_sim.canbus.master_watch import SafetyWatch
from lca_sim.canbus.remote import RemoteTransportBus, batched_sends
from lca_sim.cia402 import bus_load
from lca_sim.errors import InvalidValueError

log = logging.getLogger(__name__)


# canopen's notifier waits this long for a frame per receive. Over a linked bus none of the
# rack's frames come through its queue, so its default (1 s) would hold a disconnect that long,
# long enough for the rack's RPDO deadline to fire at shutdown.
NOTIFIER_POLL_S = 0.05


def master_network(bus: can.BusABC) -> canopen.Network:
    """A connected canopen `Network` on `bus` for a master, as the CAN bridge opens it.

    On lca_hil's own buses (`LinkedVirtualBus`, lca_remote's `RemoteTransportBus`) the
    notifier's listeners are attached to the bus: a cycle's data frames reach the master's
    listener at once, and on the linked bus in the sender's thread (no copy, queue or thread
    hand-over per frame; docs/can-transport.md). Any other bus (socketcan) is read by canopen's
    notifier thread as canopen does it.
    """
    network = canopen.Network(bus)
    if isinstance(bus, LinkedVirtualBus):
        network.NOTIFIER_CYCLE = NOTIFIER_POLL_S
    network.connect()
    notifier = network.notifier
    if isinstance(bus, LinkedVirtualBus | RemoteTransportBus) and notifier is not None:
        bus.attach(notifier.listeners)
    return network


class FrameReceiver(can.Listener):
    """The master's listener of every frame, in the place of canopen's `MessageListener`.

    Counts each frame (for the bus load) and reports error frames. A frame on a TPDO COB-ID of
    the drives (`tpdo_ids`, set at `init()`) goes to the callbacks canopen's `Network.notify`
    would call: its `subscribers`, looked up per frame, so what `init()` binds (again) is
    followed. Only canopen's `NodeScanner` is skipped for them: it records the node ids of the
    frames it sees, nothing of lca_hil reads it, and the drives' heartbeats and SDO answers
    still reach it. Every other frame (SDO, EMCY, heartbeat, NMT, remote frames) goes to
    canopen's listener as before: per TPDO, canopen's listener, notify and scanner calls and a
    second listener's are saved.

    Args:
        network: the master's network, connected: its notifier's canopen listener is replaced.
        counters: the master's counters.
        on_error_frame: called with an error frame's identifier (its error class bits).

    Raises:
        InvalidValueError: the notifier has no canopen listener of this network (another
            master took its place: one master per network).
    """

    def __init__(
        self,
        network: canopen.Network,
        counters: Counters,
        on_error_frame: Callable[[int], None],
    ) -> None:
        self._counters = counters
        self._on_error_frame = on_error_frame
        self._network = network
        self.receive_failures = ReceiveFailures()
        self._subscribers = network.subscribers
        self.tpdo_ids: frozenset[int] = frozenset()
        listeners = network.notifier.listeners if network.notifier is not None else []
        for k, listener in enumerate(listeners):
            if isinstance(listener, MessageListener) and listener.network is network:
                self._canopen: Callable[[can.Message], None] = listener.on_message_received
                listeners[k] = self  # in place: a linked bus calls the list it was given
                return
        raise InvalidValueError("the network's notifier has no canopen listener of its own")

    def on_message_received(self, msg: can.Message) -> None:
        """One frame: an error frame reported, a TPDO decoded, any other to canopen; counted."""
        if msg.is_error_frame:
            self._on_error_frame(int(msg.arbitration_id))
            return
        can_id = msg.arbitration_id
        if can_id in self.tpdo_ids and not msg.is_remote_frame:
            self._tpdo(can_id, msg.data, msg.timestamp)
        else:
            self._canopen(msg)
        c = self._counters
        dlc = int(msg.dlc)
        c.frames_received += 1
        c.bits_received += bus_load.FRAME_BITS[dlc]
        c.nominal_bits += bus_load.FRAME_BITS_NOMINAL[dlc]

    def on_error(self, exc: Exception) -> None:
        """The bus's receive raised (its interface down, the relay gone): said, counted, retried.

        Without this python-can's notifier ended its thread with a traceback and canopen's
        next sends re-raised the error: the drives went unheard (stale) with no reason given.
        Now the first failure of a run is logged, `receive_failures` tells the diagnostics
        while it lasts (`Cia402Master.receive_failure`), and reception goes on when the bus
        does (`ReceiveFailures`).
        """
        self._counters.receive_errors += 1
        if self.receive_failures.failed(exc, self._network.notifier):
            log.error(
                "CAN reception failed: %s; the drives are not heard meanwhile (tried again every "
                "%g s)",
                self.receive_failures.last,
                RECEIVE_RETRY_S,
            )

    def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
        """Classical data frames from a linked bus: as `on_message_received`, no message each.

        Only a frame canopen takes (not a TPDO) is built into its message.
        """
        c = self._counters
        tpdo_ids = self.tpdo_ids
        for can_id, data in frames:
            if can_id in tpdo_ids:
                self._tpdo(can_id, data, timestamp)
            else:
                self._canopen(received_message((can_id, data), timestamp, None))
            c.frames_received += 1
            c.bits_received += bus_load.FRAME_BITS[len(data)]
            c.nominal_bits += bus_load.FRAME_BITS_NOMINAL[len(data)]

    def _tpdo(self, can_id: int, data: bytes | bytearray, timestamp: float) -> None:
        """A TPDO to the callbacks canopen's `Network.notify` would call for it."""
        try:
            for callback in self._subscribers.get(can_id, ()):
                # canopen types the data bytearray; its PDO code only reads it, as bytes
                callback(can_id, data, timestamp)  # type: ignore[arg-type]
        except Exception as exc:  # as canopen's listener: reception goes on
            log.error("TPDO 0x%03X: %s", can_id, exc)


class FrameTransmitter:
    """Sends the master's frames, each as canopen's `Network.send_message` does, and counts them.

    Its steps without its call per frame: a `can.Message`, the bus's send under the network's
    `send_lock` (canopen's SDO client sends under it from other threads), then canopen's
    `check` of the notifier's error (called only when there is one to raise).
    """

    def __init__(self, network: canopen.Network, watch: SafetyWatch, counters: Counters) -> None:
        self._network = network
        self._watch = watch
        self._counters = counters
        # Only lca_remote batches (`batched_sends`); for any other bus (fixed once the network
        # is connected) its null context is skipped, three calls fewer per cycle.
        self._batching = isinstance(network.bus, RemoteTransportBus)
        self._linked = network.bus if isinstance(network.bus, LinkedVirtualBus) else None

    def send(self, frames: list[tuple[int, bytes]]) -> None:
        """Send `frames` in order; a frame that fails is counted and the next one is tried.

        On a linked bus (the bridge's own rack) the cycle is one `send_data_frames`: it fails
        only as a whole (the bus shut down), and is then counted once.
        """
        if self._linked is not None:
            self._send_linked(self._linked, frames)
            return
        if not self._batching:
            self._send_each(frames)
            return
        try:
            with batched_sends(self._network.bus):  # over lca_remote: one write for the cycle
                self._send_each(frames)
        except can.CanError as exc:  # the batch's one write failed
            self._watch.send_failed(exc)

    def _send_linked(self, bus: LinkedVirtualBus, frames: list[tuple[int, bytes]]) -> None:
        network = self._network
        try:
            if network.bus is None:
                raise RuntimeError("Not connected to CAN bus")  # canopen's error
            with network.send_lock:
                bus.send_data_frames(frames)
            notifier = network.notifier
            if notifier is not None and notifier.exception is not None:
                network.check()  # raises the notifier's error
        except can.CanError as exc:
            self._watch.send_failed(exc)
            return
        watch, counters = self._watch, self._counters
        if watch.send_failures_in_row:
            watch.send_ok()
        for _, data in frames:
            counters.frames_sent += 1
            counters.bits_sent += bus_load.FRAME_BITS[len(data)]
            counters.nominal_bits += bus_load.FRAME_BITS_NOMINAL[len(data)]

    def _send_each(self, frames: list[tuple[int, bytes]]) -> None:
        network = self._network
        watch = self._watch
        counters = self._counters
        for cob_id, data in frames:
            try:
                send_frame(network, cob_id, data)
                notifier = network.notifier
                if notifier is not None and notifier.exception is not None:
                    network.check()  # raises the notifier's error
            except can.CanError as exc:
                watch.send_failed(exc)
                continue
            if watch.send_failures_in_row:
                watch.send_ok()
            counters.frames_sent += 1
            counters.bits_sent += bus_load.FRAME_BITS[len(data)]
            counters.nominal_bits += bus_load.FRAME_BITS_NOMINAL[len(data)]
