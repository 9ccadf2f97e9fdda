"""The rigs of the canbus tests: a channel of its own, a frame probe, the shipped rack, a master.

The probe is up before the rack, so it sees the boot-up messages; every bus, rack, network and
master is stopped in the fixture's finally, whatever the test did. `rack_and_master` builds the
shipped rack with the bridge's master (`Cia402Master`) on a channel, for the modules' own rigs;
`lockstep_rack` builds it in lockstep timing (each SYNC advances the plant exactly 0x1006) with
a plain canopen master network, for tests that drive the physics SYNC by SYNC.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from collections.abc import Callable, Iterator

import can
import canopen
import pytest
from support import Probe, RackAndMaster

from lca_sim import RobotParams
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_params import BridgeParams
from lca_sim.canbus.master_state import Snapshot
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.config.rack import LOCKSTEP, eds_path, load_rack_config

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


@pytest.fixture
def rack_and_master() -> Iterator[Callable[..., RackAndMaster]]:
    """Build racks with a master; everything started is stopped at the end, in reverse order."""
    cleanups: list[Callable[[], None]] = []

    def build(
        channel: str,
        params: BridgeParams,
        *,
        on_state: Callable[[Snapshot], None] | None = None,
        robot: RobotParams | None = None,
        settle: bool = False,
        before_master: Callable[[str], None] | None = None,
    ) -> RackAndMaster:
        """The rack started on `channel`, then (after `before_master`) the master's network."""
        rack_bus = can.Bus(interface="virtual", channel=channel)
        cleanups.append(rack_bus.shutdown)
        rack = VirtualDriveRack(rack_bus, load_rack_config(None), robot=robot)
        rack.start(settle=settle)
        cleanups.append(rack.stop)
        if before_master is not None:
            before_master(channel)
        network = canopen.Network(can.Bus(interface="virtual", channel=channel))
        network.connect()
        cleanups.append(network.disconnect)
        bridge = Cia402Master(network, params, eds_path(), on_state=on_state)
        cleanups.append(bridge.stop)
        return RackAndMaster(channel, rack, network, bridge)

    try:
        yield build
    finally:
        for cleanup in reversed(cleanups):
            cleanup()


@pytest.fixture
def lockstep_rack(
    channel: str, default_robot: RobotParams
) -> Iterator[Callable[..., tuple[VirtualDriveRack, canopen.Network]]]:
    """Build the shipped rack in lockstep timing and a canopen master network on `channel`.

    `build(robot=None, **initial_position)` starts the rack (on the shipped robot unless given)
    with those axes' initial positions (rad, m) overridden; everything is stopped at the end.
    """
    cleanups: list[Callable[[], None]] = []

    def build(
        robot: RobotParams | None = None, **initial_position: float
    ) -> tuple[VirtualDriveRack, canopen.Network]:
        config = load_rack_config(None)
        axes = tuple(
            dataclasses.replace(
                a, initial_position=initial_position.get(a.name, a.initial_position)
            )
            for a in config.axes
        )
        config = dataclasses.replace(config, timing_mode=LOCKSTEP, axes=axes)
        rack_bus = can.Bus(interface="virtual", channel=channel)
        cleanups.append(rack_bus.shutdown)
        rack = VirtualDriveRack(rack_bus, config, robot=robot or default_robot)
        rack.start(settle=False)
        cleanups.append(rack.stop)
        network = canopen.Network(can.Bus(interface="virtual", channel=channel))
        network.NOTIFIER_CYCLE = 0.05
        network.connect()
        cleanups.append(network.disconnect)
        cleanups.append(network.sync.stop)
        return rack, network

    try:
        yield build
    finally:
        for cleanup in reversed(cleanups):
            cleanup()
