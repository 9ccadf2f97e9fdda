"""python-can's in-process `virtual` bus, with frames between linked buses handed over directly.

A `LinkedVirtualBus` is a `VirtualBus` on the same channels (other `virtual` buses, a test's
probe, see every frame as before), but a frame for another linked bus whose listeners are
attached (`attach`) is handed to them at once, in the sender's thread: no copy, no queue, no
thread hand-over (docs/can-transport.md, "where a cycle's time went").

The message handed over is the sender's own object, stamped and marked received; a listener
that keeps messages must copy them. Listeners called this way must not send on the bus they
were called for while their caller holds a lock they need: the master never sends from its
receive callbacks, and the rack's sends go to the master's callbacks, which do not send.

The cycle's own frames (the master's RPDOs, SYNC and heartbeat, the rack's TPDOs) are classical
11-bit data frames, and both ends take them without a `can.Message` (`send_data_frames`, a
listener's `on_data_frames`): per frame, the message, its stamping and the listener's checks of
its kind are saved, and a cycle's frames reach each listener in one call. A listener without
`on_data_frames` and a plain `virtual` bus get the same frames as messages.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from copy import deepcopy
from typing import Any, Protocol, runtime_checkable

import can
from can.interfaces.virtual import VirtualBus

log = logging.getLogger(__name__)

DataFrames = Sequence[tuple[int, bytes]]  # classical 11-bit data frames: (COB-ID, 0-8 bytes)


@runtime_checkable
class DataFrameListener(Protocol):
    """A listener that takes classical data frames as they are, several at once.

    `on_data_frames` handles each frame's failure itself: an exception that escapes it is
    counted and logged by the linked bus, and the batch's later frames are lost to it.
    """

    def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
        """Take `frames` in order, all received at `timestamp` (python-can's time.time())."""


# queue (by id) of a linked bus -> its attached listeners
_handlers: dict[int, _Attached] = {}
_handlers_lock = threading.Lock()


class LinkedVirtualBus(VirtualBus):
    """A `VirtualBus` whose frames reach other attached linked buses without a thread hop.

    Args:
        channel: the virtual channel (any hashable name), shared with plain `virtual` buses.
        kwargs: as python-can's `VirtualBus`.
    """

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self._delivery = threading.RLock()  # one frame at a time into the listeners
        self.direct_frames = 0  # frames this bus handed over directly
        self._batcher = _LinkedBatch(self)
        self.listener_errors = 0  # exceptions of its attached listeners (logged)
        # The channel's other queues with their handlers (None: queued), and the channel's
        # members and the handlers they were built from (`send` builds them again on a change).
        self._routes: list[tuple[Any, _Attached | None]] = []
        self._routes_members: list[Any] | None = None
        self._routes_handlers: dict[int, _Attached] | None = None

    def attach(self, listeners: Iterable[Callable[[can.Message], Any]]) -> None:
        """Hand frames from other linked buses to `listeners` directly, in the sender's thread.

        Pass the list a notifier calls (`can.Notifier.listeners`): listeners it gains later are
        called too. Frames from plain `virtual` buses still come through the queue. A
        `DataFrameListener` gets `send_data_frames`' frames as they are, the others as messages.
        """
        with _handlers_lock:
            _handlers[id(self.queue)] = _Attached(self, listeners)

    def deliver(self, receive: Callable[[can.Message], Any], msg: can.Message) -> None:
        """Hand `msg` to one attached listener; its exception is counted and logged."""
        try:
            receive(msg)
        except Exception:  # a notifier would survive it too: so does the sender
            self.listener_errors += 1
            log.exception("listener failed on frame 0x%03X", msg.arbitration_id)

    def detach(self) -> None:
        """Back to the queue for every frame (before the listeners go)."""
        with _handlers_lock:
            _handlers.pop(id(self.queue), None)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send to every other bus of the channel: attached linked ones at once, others queued."""
        self._check_if_open()
        self._batcher.flush()  # data frames held by an open batch go first, in order
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        all_sent = True
        for bus_queue, handlers in self._targets():
            copy = deepcopy(msg) if handlers is None else msg
            copy.timestamp = timestamp
            copy.channel = self.channel_id
            copy.is_rx = bus_queue is not self.queue
            if handlers is not None:
                self.direct_frames += 1
                handlers.message(copy)
                continue
            all_sent = _put(bus_queue, copy, timeout) and all_sent
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")

    def send_data_frames(self, frames: DataFrames) -> None:
        """Send classical 11-bit data frames, in order, as `send` would send each as a message.

        Each attached linked bus takes them in one call, without a message per frame; a plain
        `virtual` bus (a probe) gets each as a message in its queue. Stamped now (time.time()).

        Raises:
            can.CanOperationError: the bus is shut down, or a queue refused a frame.
        """
        self._check_if_open()
        if self._batcher.hold(frames):
            return
        self._deliver_data_frames(frames)

    def _deliver_data_frames(self, frames: DataFrames) -> None:
        timestamp = time.time()
        all_sent = True
        for bus_queue, handlers in self._targets():
            if handlers is not None:
                self.direct_frames += len(frames)
                handlers.data_frames(frames, timestamp)
                continue
            for frame in frames:
                msg = _received(frame, timestamp, self.channel_id)
                msg.is_rx = bus_queue is not self.queue
                all_sent = _put(bus_queue, msg, None) and all_sent
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")

    def send_data_frame(self, arbitration_id: int, data: bytes) -> None:
        """`send_data_frames` of one frame (the rack's TPDOs, as over lca_remote)."""
        self.send_data_frames(((arbitration_id, data),))

    def batch(self) -> contextlib.AbstractContextManager[None]:
        """Hold the data frames sent meanwhile (by any thread); deliver them at the end at once.

        As `RemoteTransportBus.batch` (`batched_sends`): a drive's TPDOs after a SYNC reach the
        master in one call. A message sent meanwhile goes after the frames held before it.
        """
        return self._batcher

    def _targets(self) -> list[tuple[Any, _Attached | None]]:
        """The channel's other queues with the handlers of their attached listeners."""
        with _handlers_lock:
            # routed again only when a bus joined or left the channel or (de)attached; the
            # lists and dicts compare their items by identity first, in C
            if self._routes_members != self.channel or self._routes_handlers != _handlers:
                self._routes_members = list(self.channel)
                self._routes_handlers = dict(_handlers)
                self._routes = [
                    (q, _handlers.get(id(q)))
                    for q in self._routes_members
                    if q is not self.queue or self.receive_own_messages
                ]
            return self._routes

    def shutdown(self) -> None:
        """Detach, then shut down as a `VirtualBus`."""
        self.detach()
        super().shutdown()


def _receiver(listener: Callable[[can.Message], Any]) -> Callable[[can.Message], Any]:
    """What to call for a frame: a `can.Listener`'s `on_message_received` without its `__call__`."""
    if isinstance(listener, can.Listener) and type(listener).__call__ is can.Listener.__call__:
        return listener.on_message_received
    return listener


class _Attached:
    """The listeners attached to one linked bus, and the two ways frames reach them."""

    def __init__(
        self, bus: LinkedVirtualBus, listeners: Iterable[Callable[[can.Message], Any]]
    ) -> None:
        self._bus = bus
        self._live = listeners
        self._seen: list[Callable[[can.Message], Any]] = []
        self._receivers: tuple[
            tuple[Callable[[can.Message], Any], Callable[[DataFrames, float], None] | None], ...
        ] = ()

    def _refresh(self) -> None:
        """The listeners again, after one came or went (the lists compared by identity, in C)."""
        self._seen = list(self._live)
        self._receivers = tuple(
            (
                _receiver(listener),
                listener.on_data_frames if isinstance(listener, DataFrameListener) else None,
            )
            for listener in self._seen
        )

    def message(self, msg: can.Message) -> None:
        """One message to every listener."""
        bus = self._bus
        with bus._delivery:
            if self._seen != self._live:
                self._refresh()
            for receive, _ in self._receivers:
                bus.deliver(receive, msg)

    def data_frames(self, frames: DataFrames, timestamp: float) -> None:
        """Data frames to every listener: as they are, or as messages built once for all."""
        bus = self._bus
        with bus._delivery:
            if self._seen != self._live:
                self._refresh()
            messages: list[can.Message] | None = None
            for receive, receive_frames in self._receivers:
                if receive_frames is not None:
                    try:
                        receive_frames(frames, timestamp)
                    except Exception:  # as `deliver`: the sender goes on
                        bus.listener_errors += 1
                        log.exception("listener failed on frames %s", _ids(frames))
                    continue
                if messages is None:
                    messages = [_received(f, timestamp, bus.channel_id) for f in frames]
                for msg in messages:
                    bus.deliver(receive, msg)


class _LinkedBatch:
    """`LinkedVirtualBus.batch()`, one per bus: open batches counted, the last one delivers."""

    __slots__ = ("_bus", "_held", "_lock", "_open")

    def __init__(self, bus: LinkedVirtualBus) -> None:
        self._bus = bus
        self._lock = threading.Lock()
        self._open = 0
        self._held: list[tuple[int, bytes]] | None = None  # the frames sent while one is open

    def __enter__(self) -> None:
        with self._lock:
            if self._held is None:
                self._held = []
            self._open += 1

    def __exit__(self, *exc_info: object) -> None:
        with self._lock:
            self._open -= 1
            if self._open:
                return
            frames, self._held = self._held, None
        if frames:
            self._bus._deliver_data_frames(frames)

    def hold(self, frames: DataFrames) -> bool:
        """Keep `frames` for the end of the open batch; False when none is open."""
        if self._held is None:  # read without the lock: the common case, no batch
            return False
        with self._lock:
            if self._held is None:
                return False
            self._held.extend(frames)
            return True

    def flush(self) -> None:
        """Deliver what an open batch holds now (a message is about to follow it)."""
        if not self._held:
            return
        with self._lock:
            frames = self._held
            if not frames:
                return
            self._held = []
        self._bus._deliver_data_frames(frames)


def _received(frame: tuple[int, bytes], timestamp: float, channel: Any) -> can.Message:
    """One data frame as the message a receiving bus hands out."""
    arbitration_id, data = frame
    return can.Message(
        timestamp=timestamp,
        arbitration_id=arbitration_id,
        is_extended_id=False,
        data=data,
        channel=channel,
        is_rx=True,
    )


def _put(bus_queue: Any, msg: can.Message, timeout: float | None) -> bool:
    """Queue `msg` for a plain virtual bus; False when its queue is full (as python-can's)."""
    try:
        bus_queue.put(msg, block=True, timeout=timeout)
    except Exception:  # queue.Full, as python-can's VirtualBus reports it
        return False
    return True


def _ids(frames: DataFrames) -> str:
    return " ".join(f"0x{arbitration_id:03X}" for arbitration_id, _ in frames)
