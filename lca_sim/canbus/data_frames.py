"""Classical CAN data frames handed to listeners as they are, without a `can.Message` each.

A cycle's frames (the master's RPDOs, SYNC and heartbeat, a drive's TPDOs) are classical 11-bit
data frames of at most 8 bytes. Where lca_hil's own buses receive them (the bridge's linked
in-process bus, `lca_remote`), a listener that has `on_data_frames` takes them as (COB-ID,
data) pairs, several at once; any other listener gets each as the message python-can would
have handed it. Per frame, that saves the message, its stamping and the listener's checks of
its kind (docs/can-transport.md).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol, runtime_checkable

import can

log = logging.getLogger(__name__)

DataFrames = Sequence[tuple[int, bytes]]  # classical 11-bit data frames: (COB-ID, 0-8 bytes)


@runtime_checkable
class DataFrameListener(Protocol):
    """A listener that takes classical data frames as they are, several at once.

    `on_data_frames` handles each frame's failure itself: an exception that escapes it is
    counted and logged by the bus, and the batch's later frames are lost to that listener.
    """

    def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
        """Take `frames` in order, all received at `timestamp` (python-can's time.time())."""


class AttachedListeners:
    """A notifier's listeners, called by the bus itself in the receiving (or sending) thread.

    Args:
        listeners: the list a notifier calls (`can.Notifier.listeners`), live: listeners it
            gains or loses later are followed.
        channel: the channel the messages built for message listeners name.
    """

    def __init__(self, listeners: Iterable[Callable[[can.Message], Any]], channel: Any) -> None:
        self._live = listeners
        self._channel = channel
        self._lock = threading.RLock()  # one delivery at a time into the listeners
        self._seen: list[Callable[[can.Message], Any]] = []
        self._receivers: tuple[
            tuple[Callable[[can.Message], Any], Callable[[DataFrames, float], None] | None], ...
        ] = ()
        self.errors = 0  # exceptions of the listeners (logged)

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
        with self._lock:
            if self._seen != self._live:
                self._refresh()
            for receive, _ in self._receivers:
                self._deliver(receive, msg)

    def data_frames(self, frames: DataFrames, timestamp: float) -> None:
        """Data frames to every listener: as they are, or as messages built once for all."""
        with self._lock:
            if self._seen != self._live:
                self._refresh()
            messages: list[can.Message] | None = None
            for receive, receive_frames in self._receivers:
                if receive_frames is not None:
                    try:
                        receive_frames(frames, timestamp)
                    except Exception:  # as `_deliver`: the bus goes on
                        self.errors += 1
                        log.exception("listener failed on frames %s", frame_ids(frames))
                    continue
                if messages is None:
                    messages = [received_message(f, timestamp, self._channel) for f in frames]
                for msg in messages:
                    self._deliver(receive, msg)

    def _deliver(self, receive: Callable[[can.Message], Any], msg: can.Message) -> None:
        try:
            receive(msg)
        except Exception:  # a notifier would survive it too: so does the bus
            self.errors += 1
            log.exception("listener failed on frame 0x%03X", msg.arbitration_id)


def received_message(frame: tuple[int, bytes], timestamp: float, channel: Any) -> can.Message:
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


def frame_ids(frames: DataFrames) -> str:
    """The frames' COB-IDs, for a log line."""
    return " ".join(f"0x{arbitration_id:03X}" for arbitration_id, _ in frames)


def _receiver(listener: Callable[[can.Message], Any]) -> Callable[[can.Message], Any]:
    """What to call for a frame: a `can.Listener`'s `on_message_received` without its `__call__`."""
    if isinstance(listener, can.Listener) and type(listener).__call__ is can.Listener.__call__:
        return listener.on_message_received
    return listener
