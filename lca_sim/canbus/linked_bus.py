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
from collections.abc import Callable, Iterable
from copy import deepcopy
from typing import Any

import can
from can.interfaces.virtual import VirtualBus

from lca_sim.canbus.data_frames import AttachedListeners, DataFrames, received_message

log = logging.getLogger(__name__)

# queue (by id) of a linked bus -> its attached listeners
_handlers: dict[int, AttachedListeners] = {}
_handlers_lock = threading.Lock()


class LinkedVirtualBus(VirtualBus):
    """A `VirtualBus` whose frames reach other attached linked buses without a thread hop.

    Args:
        channel: the virtual channel (any hashable name), shared with plain `virtual` buses.
        kwargs: as python-can's `VirtualBus`.
    """

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self.direct_frames = 0  # frames this bus handed over directly
        self._batcher = _LinkedBatch(self)
        self._attached: AttachedListeners | None = None
        # The channel's other queues with their handlers (None: queued), and the channel's
        # members and the handlers they were built from (`send` builds them again on a change).
        self._routes: list[tuple[Any, AttachedListeners | None]] = []
        self._routes_members: list[Any] | None = None
        self._routes_handlers: dict[int, AttachedListeners] | None = None

    def attach(self, listeners: Iterable[Callable[[can.Message], Any]]) -> None:
        """Hand frames from other linked buses to `listeners` directly, in the sender's thread.

        Pass the list a notifier calls (`can.Notifier.listeners`): listeners it gains later are
        called too. Frames from plain `virtual` buses still come through the queue. A
        `DataFrameListener` gets `send_data_frames`' frames as they are, the others as messages.
        """
        attached = AttachedListeners(listeners, self.channel_id)
        self._attached = attached
        with _handlers_lock:
            _handlers[id(self.queue)] = attached

    @property
    def listener_errors(self) -> int:
        """Exceptions of the listeners attached now (logged)."""
        return 0 if self._attached is None else self._attached.errors

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
                msg = received_message(frame, timestamp, self.channel_id)
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

    def _targets(self) -> list[tuple[Any, AttachedListeners | None]]:
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


def _put(bus_queue: Any, msg: can.Message, timeout: float | None) -> bool:
    """Queue `msg` for a plain virtual bus; False when its queue is full (as python-can's)."""
    try:
        bus_queue.put(msg, block=True, timeout=timeout)
    except Exception:  # queue.Full, as python-can's VirtualBus reports it
        return False
    return True
