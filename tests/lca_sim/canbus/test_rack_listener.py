"""The rack's listener: which received frames reach canopen's services, and all reach the rack."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from types import SimpleNamespace
from typing import cast

import can
import pytest

from lca_sim.canbus.rack_network import RackListener, RackNetwork
from lca_sim.canbus.rack_state import NMT_OPERATIONAL, NMT_STOPPED, Drive, RackCounters

_channels = itertools.count()


@pytest.fixture
def network() -> Iterator[RackNetwork]:
    """A rack's network on a virtual bus of its own (nothing is sent in these tests)."""
    bus = can.Bus(
        interface="virtual", channel=f"test_rack_listener_{os.getpid()}_{next(_channels)}"
    )
    yield RackNetwork(bus)
    bus.shutdown()


def test_only_frames_canopen_acts_on_reach_it_and_every_frame_reaches_the_rack(
    network: RackNetwork, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SYNC and RPDOs skip canopen (nothing there takes them); a TPDO of node 5 is scanned.

    canopen's NodeScanner notes the node id of service frames (CiA 301 pre-defined connection
    set), node ids 1-127: the SYNC, 0x080, is function code 0x080 with node id 0, and the
    rack handles it alone, 500 times a second.
    """
    notified: list[int] = []
    monkeypatch.setattr(network, "notify", lambda cob, data, timestamp: notified.append(cob))
    runs: list[list[int]] = []

    def on_frames(frames: list[tuple[int, bytes]], timestamp: float) -> None:
        runs.append([cob for cob, _ in frames])
        notified.append(-1)  # where the rack's run came among canopen's frames

    listener = RackListener(
        network, RackCounters(), {}, on_frames, warn_once=lambda key, message: None
    )
    frames = [(0x201, b"\x00\x01"), (0x080, b""), (0x185, b"\x01" * 8), (0x085, b"\x00" * 8)]
    listener.on_data_frames(frames, 1.0)
    assert runs == [[0x201, 0x080], [0x185], [0x085]]
    # the TPDO and the EMCY of node 5 are scanned, each after the rack's frames before it
    assert notified == [-1, 0x185, -1, 0x085, -1]


def test_an_sdo_request_is_judged_after_the_frames_before_it(
    network: RackNetwork, monkeypatch: pytest.MonkeyPatch
) -> None:
    """NMT Stop, then an SDO request to that node, in one read: the SDO is not answered.

    CiA 301 7.3.2.2: a STOPPED node serves no SDO. The node's state is the rack's, changed
    when it handles the NMT frame, so the request is judged after the frames before it.
    """
    drive = SimpleNamespace(nmt=NMT_OPERATIONAL)
    notified: list[int] = []
    monkeypatch.setattr(network, "notify", lambda cob, data, timestamp: notified.append(cob))

    def on_frames(frames: list[tuple[int, bytes]], timestamp: float) -> None:
        for cob, data in frames:
            if cob == 0x000 and data[0] == 0x02:  # NMT stop (CiA 301 command specifier 2)
                drive.nmt = NMT_STOPPED

    counters = RackCounters()
    listener = RackListener(
        network, counters, {0x601: cast(Drive, drive)}, on_frames, lambda key, message: None
    )
    stop, sdo = (0x000, bytes([0x02, 0x01])), (0x601, bytes([0x40, 0x00, 0x10, 0, 0, 0, 0, 0]))
    listener.on_data_frames([stop, sdo], 1.0)
    assert drive.nmt == NMT_STOPPED
    assert 0x601 not in notified
    assert counters.sdo_ignored_stopped == 1
