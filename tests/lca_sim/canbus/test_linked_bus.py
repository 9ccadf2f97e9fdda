"""The bridge's in-process link of master and rack (lca_sim.canbus.linked_bus).

Two attached `LinkedVirtualBus`es hand frames over inside `send`; a plain `virtual` bus on the
same channel still sees every frame. Over such a link the master's whole cycle (RPDOs, SYNC,
the rack's TPDOs, the complete state) happens within `cycle()`, so these tests need no wait.
"""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Iterator
from typing import Any

import can
import pytest
from support import wait_until

from lca_sim import RobotParams
from lca_sim.canbus.data_frames import DataFrameListener, DataFrames
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_frames import master_network
from lca_sim.canbus.master_params import BridgeParams
from lca_sim.canbus.master_state import Snapshot
from lca_sim.canbus.remote import batched_sends
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.config.rack import eds_path, load_rack_config

JOINTS = ("l_arm", "pivot", "c_arc", "lift")
_channels = itertools.count()


def _channel() -> str:
    return f"test_linked_bus_{os.getpid()}_{next(_channels)}"


def test_attached_buses_deliver_in_the_senders_call_and_a_probe_still_sees_it() -> None:
    """The frame is handled before send returns; a plain virtual bus gets its own copy."""
    channel = _channel()
    a, b = LinkedVirtualBus(channel=channel), LinkedVirtualBus(channel=channel)
    probe = can.Bus(interface="virtual", channel=channel)
    got: list[can.Message] = []
    try:
        b.attach([got.append])
        a.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        assert [m.arbitration_id for m in got] == [0x80]  # no thread, no wait
        assert got[0].is_rx and got[0].channel == channel
        seen = probe.recv(1.0)
        assert seen is not None and seen.arbitration_id == 0x80
        assert b.recv(0.0) is None  # not also queued for the attached bus
        assert a.direct_frames == 1
        b.detach()
        a.send(can.Message(arbitration_id=0x81, data=b"\x01", is_extended_id=False))
        assert len(got) == 1 and b.recv(1.0) is not None  # detached: through the queue again
    finally:
        for bus in (a, b, probe):
            bus.shutdown()


def test_a_failing_listener_is_counted_not_raised_into_the_sender() -> None:
    """A sender's send (the master's cycle) survives a receiver's exception, as a notifier."""
    channel = _channel()
    a, b = LinkedVirtualBus(channel=channel), LinkedVirtualBus(channel=channel)
    after: list[int] = []

    def broken(_msg: can.Message) -> None:
        raise ValueError("listener bug")

    try:
        b.attach([broken, lambda m: after.append(m.arbitration_id)])
        a.send(can.Message(arbitration_id=0x181, data=b"\x00" * 8, is_extended_id=False))
        assert b.listener_errors == 1
        assert after == [0x181]  # the next listener still got it
    finally:
        a.shutdown()
        b.shutdown()


class _Frames:
    """A `DataFrameListener` that records each call's frames and stamp."""

    def __init__(self) -> None:
        self.calls: list[tuple[list[tuple[int, bytes]], float]] = []
        self.messages: list[can.Message] = []

    def __call__(self, msg: can.Message) -> None:  # python-can's listener call
        self.messages.append(msg)

    def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
        self.calls.append((list(frames), timestamp))


def test_data_frames_reach_a_frame_listener_in_one_call_others_as_messages() -> None:
    """send_data_frames: one call per attached frame listener, messages for the rest, the probe."""
    channel = _channel()
    a, b = LinkedVirtualBus(channel=channel), LinkedVirtualBus(channel=channel)
    probe = can.Bus(interface="virtual", channel=channel)
    frame_listener = _Frames()
    messages: list[can.Message] = []
    frames = [(0x201, b"\x0f\x00\x10\x00"), (0x80, b""), (0x701, b"\x05")]
    try:
        assert isinstance(frame_listener, DataFrameListener)
        b.attach([frame_listener, messages.append])
        before = time.time()
        a.send_data_frames(frames)
        assert len(frame_listener.calls) == 1  # the cycle's frames at once, no message each
        got, stamp = frame_listener.calls[0]
        assert got == frames and before <= stamp <= time.time()
        assert [(m.arbitration_id, bytes(m.data)) for m in messages] == frames
        assert all(
            m.is_rx and not m.is_extended_id and m.channel == channel and m.timestamp == stamp
            for m in messages
        )
        seen = [probe.recv(1.0) for _ in frames]
        assert [(m.arbitration_id, bytes(m.data)) for m in seen if m is not None] == frames
        assert a.direct_frames == 3
    finally:
        for bus in (a, b, probe):
            bus.shutdown()


def test_a_batch_delivers_at_its_end_and_a_message_goes_after_what_it_held() -> None:
    """The rack's TPDOs of one SYNC reach the master in one call; order on the bus is kept."""
    channel = _channel()
    a, b = LinkedVirtualBus(channel=channel), LinkedVirtualBus(channel=channel)
    probe = can.Bus(interface="virtual", channel=channel)
    listener = _Frames()
    try:
        b.attach([listener])
        with batched_sends(a):
            a.send_data_frame(0x181, b"\x01")
            with batched_sends(a):  # nested: the outer one delivers
                a.send_data_frame(0x182, b"\x02")
            assert listener.calls == []
            a.send(can.Message(arbitration_id=0x81, data=b"\x00" * 8, is_extended_id=False))
            a.send_data_frame(0x183, b"\x03")
            assert listener.calls[0][0] == [(0x181, b"\x01"), (0x182, b"\x02")]
        assert [f for f, _ in listener.calls] == [
            [(0x181, b"\x01"), (0x182, b"\x02")],
            [(0x183, b"\x03")],
        ]
        assert [m.arbitration_id for m in listener.messages] == [0x81]
        seen = [probe.recv(1.0) for _ in range(4)]
        assert [m.arbitration_id for m in seen if m is not None] == [0x181, 0x182, 0x81, 0x183]
    finally:
        for bus in (a, b, probe):
            bus.shutdown()


def test_a_frame_listener_that_raises_is_counted_and_the_next_listener_served() -> None:
    """As for messages: the sender (the master's cycle) goes on."""
    channel = _channel()
    a, b = LinkedVirtualBus(channel=channel), LinkedVirtualBus(channel=channel)

    class Broken(_Frames):
        def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
            raise ValueError("listener bug")

    after = _Frames()
    try:
        b.attach([Broken(), after])
        a.send_data_frames([(0x181, b"\x00" * 8)])
        assert b.listener_errors == 1
        assert [f for f, _ in after.calls] == [[(0x181, b"\x00" * 8)]]
    finally:
        a.shutdown()
        b.shutdown()


_rack_of: dict[Cia402Master, VirtualDriveRack] = {}  # the fixture's rack, by its master


@pytest.fixture
def linked(default_robot: RobotParams) -> Iterator[tuple[Cia402Master, list[Snapshot]]]:
    """The shipped rack and the master on linked buses, initialised, cycled by hand.

    The master's network is opened as the bridge opens it (`master_network`): the delivery
    counts of `test_a_cycle_on_the_link_is_one_delivery_each_way` hold only if it attaches.
    """
    channel = _channel()
    rack_bus = LinkedVirtualBus(channel=channel)
    rack = VirtualDriveRack(rack_bus, load_rack_config(None), robot=default_robot)
    rack.start(settle=False)
    master_bus = LinkedVirtualBus(channel=channel)
    network = master_network(master_bus)  # the bridge's: attached to the linked bus
    axes = {a.name: a for a in default_robot.axes}
    params = BridgeParams(
        joints=JOINTS,
        node_ids=(1, 2, 3, 4),
        torque_constants_nm_per_a=tuple(axes[j].motor.torque_constant_nm_per_a for j in JOINTS),
        gear_ratios=tuple(axes[j].gear_ratio for j in JOINTS),
        drive_state_names=default_robot.state_machine.state_names,
        cycle_hz=250.0,
    )
    states: list[Snapshot] = []
    master = Cia402Master(network, params, eds_path(), on_state=states.append)
    _rack_of[master] = rack
    try:
        master.init()
        yield master, states
    finally:
        _rack_of.pop(master, None)
        master.stop()
        network.disconnect()
        rack.stop()
        rack_bus.shutdown()


def test_one_state_per_sync_when_a_sync_s_tpdos_come_again(
    linked: tuple[Cia402Master, list[Snapshot]],
) -> None:
    """TPDOs of the SYNC before arriving after a SYNC make no second state with its stamp.

    A TPDO carries no SYNC count (CiA 301 7.2.2): on a late host the master once completed a
    set from the late TPDOs and again from the SYNC's own, two states with one stamp, and the
    controller skipped the second (no command for that cycle). Here the cycle's TPDOs are
    fed to the master a second time after its state went out.
    """
    master, states = linked
    frames: list[tuple[int, bytes]] = []
    network = master.network
    assert network.notifier is not None
    network.notifier.listeners.append(
        lambda m: (
            frames.append((m.arbitration_id, bytes(m.data)))
            if 0x180 <= m.arbitration_id < 0x500
            else None
        )
    )
    master.cycle(master.now())
    wait_until(lambda: len(states) == 1, "the first state")  # at once over the link
    tpdos = list(frames)
    assert tpdos, "the rack answered the SYNC"
    for cob_id, data in tpdos:  # the same SYNC's TPDOs again, after its state went out
        network.notify(cob_id, bytearray(data), 0.0)
    assert len(states) == 1
    assert master.counters.extra_complete_sets == 1
    master.cycle(master.now())
    assert len(states) == 2 and states[1].cycle == states[0].cycle + 1
    assert states[1].sync_wall_s >= states[0].sync_wall_s


class _CountingProxy:
    """Stands in for a listener in a notifier's list: counts the batches, forwards everything."""

    def __init__(self, inner: DataFrameListener) -> None:
        self.inner = inner
        self.batches: list[int] = []

    def __call__(self, msg: can.Message) -> None:
        self.inner(msg)  # type: ignore[operator]

    def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
        self.batches.append(len(frames))
        self.inner.on_data_frames(frames, timestamp)


def _proxy_frame_listener(listeners: list[Any]) -> _CountingProxy:
    (k,) = [k for k, x in enumerate(listeners) if isinstance(x, DataFrameListener)]
    proxy = _CountingProxy(listeners[k])
    listeners[k] = proxy  # the linked bus sees the list change and serves the proxy
    return proxy


def test_a_cycle_on_the_link_is_one_delivery_each_way(
    linked: tuple[Cia402Master, list[Snapshot]],
) -> None:
    """The master's RPDOs and SYNC reach the rack in one call, its four TPDOs the master in one.

    Counted as well by the master (frames sent and received: the bus load on /diagnostics)
    and the bus (`direct_frames`): the same counts as frame by frame.
    """
    master, states = linked
    network = master.network
    assert network.notifier is not None
    master.cycle(master.now())  # the first: the drives' state machines begin
    master_side = _proxy_frame_listener(network.notifier.listeners)
    rack_notifier = _rack_of[master]._network.notifier  # its listener list, as the bus has it
    assert rack_notifier is not None
    rack_side = _proxy_frame_listener(rack_notifier.listeners)
    sent, received = master.counters.frames_sent, master.counters.frames_received
    master_bus = network.bus
    assert isinstance(master_bus, LinkedVirtualBus)
    direct = master_bus.direct_frames
    master.cycle(master.now())
    assert len(states) == 2
    cycle_frames = master.counters.frames_sent - sent
    assert rack_side.batches == [cycle_frames]  # four RPDOs, the SYNC (the heartbeat when due)
    assert cycle_frames >= 5
    assert master_side.batches == [4]  # one TPDO per drive, after the SYNC, at once
    assert master_bus.direct_frames - direct == cycle_frames
    assert master.counters.frames_received - received == 4
