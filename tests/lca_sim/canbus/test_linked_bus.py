"""The bridge's in-process link of master and rack (lca_sim.canbus.linked_bus).

Two attached `LinkedVirtualBus`es hand frames over inside `send`; a plain `virtual` bus on the
same channel still sees every frame. Over such a link the master's whole cycle (RPDOs, SYNC,
the rack's TPDOs, the complete state) happens within `cycle()`, so these tests need no wait.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator

import can
import canopen
import pytest
from support import wait_until

from lca_sim import RobotParams
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_params import BridgeParams
from lca_sim.canbus.master_state import Snapshot
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


@pytest.fixture
def linked(default_robot: RobotParams) -> Iterator[tuple[Cia402Master, list[Snapshot]]]:
    """The shipped rack and the master on linked buses, initialised, cycled by hand."""
    channel = _channel()
    rack_bus = LinkedVirtualBus(channel=channel)
    rack = VirtualDriveRack(rack_bus, load_rack_config(None), robot=default_robot)
    rack.start(settle=False)
    master_bus = LinkedVirtualBus(channel=channel)
    network = canopen.Network(master_bus)
    network.connect()
    assert network.notifier is not None
    master_bus.attach(network.notifier.listeners)
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
    try:
        master.init()
        yield master, states
    finally:
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
