"""A bus whose receive keeps failing: said, counted, paced, and heard again when it comes back.

An interface that goes down (a USB-CAN adapter unplugged, `ip link set can0 down`) or the
lca_remote relay going away makes the bus's `recv` raise in python-can's notifier thread. The
master's listener used to leave it unhandled: the thread ended with a bare traceback, canopen
re-raised the error at every send, and the drives went stale with no reason given. The rack's
listener handled it, but a bus that stayed broken spun its thread in a tight loop.

Here a virtual bus is broken by hand (`BrokenBus`, read by the notifier thread as a socketcan
bus is), for the master's `FrameReceiver` and for the rack's listener.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace

import can
import pytest
from can.interfaces.virtual import VirtualBus
from support import bridge_params, wait_until

from lca_sim.canbus.frames import RECEIVE_RETRY_S
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_frames import master_network
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.config.paths import config_dir
from lca_sim.config.rack import load_rack_config
from lca_sim.model.params import RobotParams

EDS = config_dir() / "can" / "lca_drive.eds"
BROKEN_S = 0.6  # how long the bus stays broken: six retry periods


class BrokenBus(VirtualBus):
    """A virtual bus whose receive raises while `broken` is set, as a downed interface's does."""

    def __init__(self, channel: str) -> None:
        super().__init__(channel=channel)
        self.broken = threading.Event()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """As the virtual bus, in 10 ms slices: a receive under way fails once it is broken."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self.broken.is_set():
                raise can.CanOperationError("Network is down")
            left = 0.01 if deadline is None else max(deadline - time.monotonic(), 0.0)
            msg, filtered = super()._recv_internal(min(left, 0.01))
            if msg is not None or (deadline is not None and time.monotonic() >= deadline):
                return msg, filtered


@pytest.fixture
def thread_errors(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Exceptions that ended a thread (a notifier's, with its traceback on stderr)."""
    seen: list[str] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: seen.append(repr(args.exc_value)))
    return seen


@pytest.fixture
def sender(channel: str) -> Iterator[can.BusABC]:
    """Another node on the bus: it sends once the broken bus is back."""
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        yield bus
    finally:
        bus.shutdown()


def _break_for(bus: BrokenBus, seconds: float, counted: Callable[[], int]) -> tuple[int, float]:
    """Break the bus for `seconds` (polled, not slept); the failures counted, the time taken."""
    start = time.monotonic()
    bus.broken.set()
    wait_until(lambda: time.monotonic() - start >= seconds, "the outage", seconds + 30.0)
    bus.broken.clear()
    return counted(), time.monotonic() - start


def test_the_master_says_the_bus_is_not_heard_and_hears_it_again(
    channel: str, sender: can.BusABC, thread_errors: list[str], caplog: pytest.LogCaptureFixture
) -> None:
    bus = BrokenBus(channel)
    network = master_network(bus)
    try:
        master = Cia402Master(network, bridge_params(), EDS)
        assert master.receive_failure() == ""
        failures, took_s = _break_for(bus, BROKEN_S, lambda: master.counters.receive_errors)
        # said while it lasts, with the bus's own words
        message = master.receive_failure()
        assert message.startswith("CAN reception failing: Network is down ("), message
        # paced: at most one try per retry period after the first two, not a tight loop
        assert 2 <= failures <= took_s / RECEIVE_RETRY_S + 3, (failures, took_s)
        logged = [r.getMessage() for r in caplog.records if "CAN reception failed" in r.message]
        assert len(logged) == 1, logged  # the run is logged once, not per failure
        # the bus is back: a frame sent now is heard by the same notifier thread
        before = master.counters.frames_received
        sender.send(can.Message(arbitration_id=0x701, data=[0x7F], is_extended_id=False))
        wait_until(lambda: master.counters.frames_received > before, "a frame heard again")
        wait_until(lambda: master.receive_failure() == "", "the failure no longer reported")
        assert thread_errors == []  # no thread ended with a traceback
        assert network.notifier is not None and network.notifier.exception is None
    finally:
        network.disconnect()


def test_a_rack_on_a_bus_that_stays_broken_does_not_spin(
    channel: str,
    sender: can.BusABC,
    thread_errors: list[str],
    default_robot: RobotParams,
) -> None:
    bus = BrokenBus(channel)
    rack = VirtualDriveRack(
        bus, replace(load_rack_config(None), timing_mode="realtime"), robot=default_robot
    )
    try:
        rack.start(settle=False)
        failures, took_s = _break_for(bus, BROKEN_S, lambda: rack.counters.bus_errors)
        assert 2 <= failures <= took_s / RECEIVE_RETRY_S + 3, (failures, took_s)
        # back: an NMT start of node 2 is taken (its heartbeat then says OPERATIONAL, 0x05)
        sender.send(can.Message(arbitration_id=0x000, data=[0x01, 2], is_extended_id=False))
        wait_until(lambda: rack.nmt_state("pivot") == "OPERATIONAL", "node 2 started after it")
        assert thread_errors == []
    finally:
        rack.stop()
        bus.shutdown()
