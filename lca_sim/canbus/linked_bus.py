"""python-can's in-process `virtual` bus, with frames between linked buses handed over directly.

A `LinkedVirtualBus` is a `VirtualBus` on the same channels (other `virtual` buses, a test's
probe, see every frame as before), but a frame for another linked bus whose listeners are
attached (`attach`) is handed to them at once, in the sender's thread: no copy, no queue, no
thread hand-over (docs/can-transport.md, "where a cycle's time went").

The message handed over is the sender's own object, stamped and marked received; a listener
that keeps messages must copy them. Listeners called this way must not send on the bus they
were called for while their caller holds a lock they need: the master never sends from its
receive callbacks, and the rack's sends go to the master's callbacks, which do not send.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from copy import deepcopy
from typing import Any

import can
from can.interfaces.virtual import VirtualBus

log = logging.getLogger(__name__)

# queue (by id) of a linked bus -> the handler of its attached listeners
_handlers: dict[int, Callable[[can.Message], None]] = {}
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
        self.listener_errors = 0  # exceptions of its attached listeners (logged)
        # The channel's other queues with their handlers (None: queued), and the channel's
        # members and the handlers they were built from (`send` builds them again on a change).
        self._routes: list[tuple[Any, Callable[[can.Message], None] | None]] = []
        self._routes_members: list[Any] | None = None
        self._routes_handlers: dict[int, Callable[[can.Message], None]] | None = None

    def attach(self, listeners: Iterable[Callable[[can.Message], Any]]) -> None:
        """Hand frames from other linked buses to `listeners` directly, in the sender's thread.

        Pass the list a notifier calls (`can.Notifier.listeners`): listeners it gains later are
        called too. Frames from plain `virtual` buses still come through the queue.
        """
        live = listeners
        seen: list[Callable[[can.Message], Any]] = []
        receivers: tuple[Callable[[can.Message], Any], ...] = ()

        def handle(msg: can.Message) -> None:
            nonlocal seen, receivers
            with self._delivery:
                if seen != live:  # a listener came or went (compared by identity, in C)
                    seen = list(live)
                    receivers = tuple(_receiver(listener) for listener in seen)
                for receive in receivers:
                    try:
                        receive(msg)
                    except Exception:  # a notifier would survive it too: so does the sender
                        self.listener_errors += 1
                        log.exception("listener failed on frame 0x%03X", msg.arbitration_id)

        with _handlers_lock:
            _handlers[id(self.queue)] = handle

    def detach(self) -> None:
        """Back to the queue for every frame (before the listeners go)."""
        with _handlers_lock:
            _handlers.pop(id(self.queue), None)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send to every other bus of the channel: attached linked ones at once, others queued."""
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
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
            targets = self._routes
        all_sent = True
        for bus_queue, handler in targets:
            copy = deepcopy(msg) if handler is None else msg
            copy.timestamp = timestamp
            copy.channel = self.channel_id
            copy.is_rx = bus_queue is not self.queue
            if handler is not None:
                self.direct_frames += 1
                handler(copy)
                continue
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except Exception:  # queue.Full, as python-can's VirtualBus reports it
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")

    def shutdown(self) -> None:
        """Detach, then shut down as a `VirtualBus`."""
        self.detach()
        super().shutdown()


def _receiver(listener: Callable[[can.Message], Any]) -> Callable[[can.Message], Any]:
    """What to call for a frame: a `can.Listener`'s `on_message_received` without its `__call__`."""
    if isinstance(listener, can.Listener) and type(listener).__call__ is can.Listener.__call__:
        return listener.on_message_received
    return listener
