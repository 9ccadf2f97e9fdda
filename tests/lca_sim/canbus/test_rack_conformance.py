"""The virtual drive rack against CiA 301 / CiA 402: issue 15's device-conformance items.

One test per numbered item of the issue (`test_item_NN_...`), each on python-can's in-process
virtual bus: a raw probe that records every frame and injects raw ones, the rack on its own bus
instance and, where SDO is needed, a canopen master network on a third. Nothing sleeps a fixed
time: where a test must show that something did NOT happen, it sends a frame the rack answers
after the one under test (frames of one bus are handled in order) and waits for that answer.
"""

from __future__ import annotations

import itertools
import os
import struct
import threading
from collections.abc import Iterator

import can
import canopen
import pytest
from can.interfaces.virtual import VirtualBus
from test_virtual_drive import Probe, nmt, remote, sync, wait_until

from lca_sim import RobotParams
from lca_sim.canbus.virtual_rack import VirtualDriveRack, load_rack_config

PIVOT = 2
L_ARM = 1
_channels = itertools.count()


class FlakyBus(VirtualBus):
    """A virtual bus whose receive raises once on demand, as a malformed datagram does."""

    def __init__(self, channel: str) -> None:
        super().__init__(channel=channel)
        self.fail_next = threading.Event()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.fail_next.is_set():
            self.fail_next.clear()
            raise can.CanOperationError("malformed datagram from the bus layer")
        return super()._recv_internal(timeout)


@pytest.fixture
def channel() -> str:
    """A virtual channel no other test uses."""
    return f"test_rack_conformance_{os.getpid()}_{next(_channels)}"


@pytest.fixture
def probe(channel: str) -> Iterator[Probe]:
    """The frame recorder, up before the rack so it sees the boot-up messages."""
    recorder = Probe(channel)
    try:
        yield recorder
    finally:
        recorder.close()


@pytest.fixture
def rack_bus(channel: str) -> Iterator[FlakyBus]:
    """The rack's bus instance (a virtual bus that can be made to fail once)."""
    bus = FlakyBus(channel)
    try:
        yield bus
    finally:
        bus.shutdown()


@pytest.fixture
def rack(
    rack_bus: FlakyBus, probe: Probe, default_robot: RobotParams
) -> Iterator[VirtualDriveRack]:
    """The shipped rack config, started; stopped whatever happens."""
    drives = VirtualDriveRack(rack_bus, load_rack_config(None), robot=default_robot)
    try:
        drives.start()
        yield drives
    finally:
        drives.stop()


@pytest.fixture
def master(channel: str, rack: VirtualDriveRack) -> Iterator[canopen.Network]:
    """A canopen master network (not our code) on a third bus instance."""
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    network.NOTIFIER_CYCLE = 0.05
    network.connect()
    try:
        yield network
    finally:
        network.disconnect()


def sdo_upload_request(index: int, subindex: int = 0) -> bytes:
    """A CiA 301 SDO initiate upload request (client -> server, 8 bytes)."""
    return struct.pack("<BHB4x", 0x40, index, subindex)


def test_item_01_a_bus_receive_error_does_not_break_the_rack(
    rack: VirtualDriveRack, rack_bus: FlakyBus, probe: Probe, master: canopen.Network
) -> None:
    """One exception from the bus layer's receive: counted, and SDO and heartbeats go on."""
    node = remote(master, PIVOT)
    assert node.sdo[0x6041].raw & 0x4F == 0x40
    rack_bus.fail_next.set()
    wait_until(lambda: rack.counters.bus_errors == 1, "the receive error counted")
    mark = probe.mark()
    assert node.sdo[0x6041].raw & 0x4F == 0x40  # the SDO server still answers ...
    nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    sync(rack, probe)
    probe.wait(0x182, mark)  # ... the TPDOs go ...
    probe.send(0x602, sdo_upload_request(0x1000))  # ... and the next request gets its answer
    wait_until(lambda: len(probe.seen(0x582, mark)) == 2, "the second SDO answer")
    answers = probe.seen(0x582, mark)
    assert [a[0] for a in answers] == [0x4B, 0x43], answers  # no abort (0x80) after an answer
    assert rack.counters.send_errors == 0
    assert rack.counters.bus_errors == 1


def test_item_02_extended_and_fd_frames_are_ignored_and_counted(
    rack: VirtualDriveRack, probe: Probe
) -> None:
    """A 29-bit or CAN FD frame with an SDO, NMT or SYNC identifier does nothing; counted."""
    mark = probe.mark()
    foreign = [
        can.Message(arbitration_id=0x602, data=sdo_upload_request(0x1000), is_extended_id=True),
        can.Message(arbitration_id=0x000, data=[0x01, PIVOT], is_extended_id=True),
        can.Message(arbitration_id=0x080, data=b"", is_extended_id=True),
        can.Message(
            arbitration_id=0x602, data=sdo_upload_request(0x1000), is_extended_id=False, is_fd=True
        ),
        can.Message(arbitration_id=0x000, data=[0x01, 0], is_extended_id=False, is_fd=True),
        can.Message(arbitration_id=0x080, data=b"", is_extended_id=False, is_fd=True),
    ]
    for msg in foreign:
        probe.bus.send(msg)
    probe.send(0x601, sdo_upload_request(0x1000))  # handled after the six above
    probe.wait(0x581, mark)
    assert probe.seen(0x582, mark) == []
    assert rack.counters.extended_frames == 3
    assert rack.counters.fd_frames == 3
    assert rack.counters.syncs == 0
    assert rack.nmt_state("pivot") == "PRE-OPERATIONAL"
    next_heartbeat = probe.mark()  # canopen's NMT slave did not see the start either
    assert probe.wait(0x702, next_heartbeat) == b"\x7f"
