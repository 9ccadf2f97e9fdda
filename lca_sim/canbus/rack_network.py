"""The rack's side of the bus: canopen's Network with a mute, its listener, lockstep sends.

docs/can.md, "Fault injection" and "Lockstep".
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import can
import canopen


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
    the NMT slave, 29-bit and CAN FD ones included (`VirtualDriveRack._on_message`).
    """

    def __init__(
        self, on_message: Callable[[can.Message], None], on_error: Callable[[Exception], None]
    ) -> None:
        self._on_message = on_message
        self._on_error = on_error

    def on_message_received(self, msg: can.Message) -> None:
        """Hand the frame to the rack."""
        self._on_message(msg)

    def on_error(self, exc: Exception) -> None:
        """Hand the bus layer's error to the rack (it counts it)."""
        self._on_error(exc)

    def stop(self) -> None:
        """Nothing to release."""


class RackNetwork(canopen.Network):
    """canopen's Network, minus one trap: a bus error must not poison every later send.

    python-can's Notifier keeps the last exception of its receive thread in
    `notifier.exception` even when a listener handled it, and `canopen.Network.check()`, called
    after every send, re-raises it: one malformed datagram from the bus layer would make every
    later SDO answer, heartbeat and TPDO fail until a restart. The rack's listener counts the
    error and clears it (`VirtualDriveRack._on_bus_error`); this check only clears one that a
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

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """Send as canopen does, except the frames of a node that fault injection silenced."""
        if can_id in self.muted:
            if self.on_dropped is not None:
                self.on_dropped(can_id)
            return
        super().send_message(can_id, data, remote)
        then = self.after_send.pop(can_id, None) if self.after_send else None
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
