"""The rigs of the canbus tests: a channel of its own, a frame probe, the shipped rack, a master.

The probe is up before the rack, so it sees the boot-up messages; every bus, rack and network
is stopped in the fixture's finally, whatever the test did.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator

import can
import canopen
import pytest
from support import Probe

from lca_sim import RobotParams
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.config.rack import load_rack_config

_channels = itertools.count()


@pytest.fixture
def channel(request: pytest.FixtureRequest) -> str:
    """A virtual channel no other test uses (named after the test's module)."""
    return f"{request.module.__name__}_{os.getpid()}_{next(_channels)}"


@pytest.fixture
def probe(channel: str) -> Iterator[Probe]:
    """The frame recorder and injector, up before the rack so it sees the boot-up messages."""
    recorder = Probe(channel)
    try:
        yield recorder
    finally:
        recorder.close()


@pytest.fixture
def rack(channel: str, probe: Probe, default_robot: RobotParams) -> Iterator[VirtualDriveRack]:
    """The shipped rack config on its own bus instance, started; stopped whatever happens."""
    bus = can.Bus(interface="virtual", channel=channel)
    drives = VirtualDriveRack(bus, load_rack_config(None), robot=default_robot)
    try:
        drives.start()
        yield drives
    finally:
        drives.stop()
        bus.shutdown()


@pytest.fixture
def master(channel: str, rack: VirtualDriveRack) -> Iterator[canopen.Network]:
    """A canopen master network (not our code) on a third bus instance."""
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    network.NOTIFIER_CYCLE = 0.05
    network.connect()
    try:
        yield network
    finally:
        network.sync.stop()  # type: ignore[no-untyped-call]
        network.disconnect()
