"""The master's safety watches: lost heartbeats and TPDOs on a rack (issues 14 and 16), and alone.

Each fault is injected by the master's own SDO write to the virtual drive's 0x2030 (docs/can.md,
"Fault injection") on python-can's in-process `virtual` bus. The master must report it within a
bound (`latched_reason()` for the latches, `cycle_stall()` for the stall of complete cycles
while disabled), and hold zero torque on every axis while a controller on a timer (not one
that answers each state, which would fall silent by itself) keeps commanding 2 A. With no fault
nothing is reported over several seconds. Nothing sleeps a fixed time.
"""

from __future__ import annotations

import itertools
import logging
import os
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import cast

import can
import canopen
import pytest
from support import RackAndMaster, bridge_params, wait_until

from lca_sim import RobotParams
from lca_sim.canbus.master_axis import MasterAxis
from lca_sim.canbus.master_state import Counters
from lca_sim.canbus.master_watch import SafetyWatch
from lca_sim.cia402 import objects as od
from lca_sim.runtime import Freeze

JOINTS = ("l_arm", "pivot", "c_arc", "lift")
NODE_IDS = (1, 2, 3, 4)
FAULTS = od.FAULT_INJECTION
CYCLE_HZ = 250.0
PIVOT_A = 2.0
_channels = itertools.count()


class TargetTorques(can.Listener):
    """The target torques (RPDO1 of the compact layout, per mille) the master sends, per node."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.sent: dict[int, list[int]] = {n: [] for n in NODE_IDS}
        self._lock = threading.Lock()
        self._notifier = can.Notifier(self.bus, [self], timeout=0.05)

    def on_message_received(self, msg: can.Message) -> None:
        """Keep each RPDO1's target torque (0x6071, INTEGER16)."""
        node_id = msg.arbitration_id - 0x200
        if node_id in self.sent and len(msg.data) == 2:
            with self._lock:
                self.sent[node_id].append(struct.unpack("<h", bytes(msg.data))[0])

    def mark(self) -> dict[int, int]:
        """How many each node has had so far."""
        with self._lock:
            return {n: len(v) for n, v in self.sent.items()}

    def since(self, mark: dict[int, int]) -> dict[int, list[int]]:
        """The target torques sent to each node after `mark`."""
        with self._lock:
            return {n: v[mark[n] :] for n, v in self.sent.items()}

    def close(self) -> None:
        """Stop listening."""
        self._notifier.stop()
        self.bus.shutdown()


@dataclass
class Rig(RackAndMaster):
    """The shipped rack, the bridge's master cycling at 250 Hz, a timer-driven controller."""

    torques: TargetTorques
    currents_a: tuple[float, ...] = (0.0, PIVOT_A, 0.0, 0.0)

    def enable(self) -> None:
        """Every drive to operation enabled, the pivot at its 2 A."""
        self.enable_all()
        wait_until(lambda: abs(self.current_a(1) - PIVOT_A) < 0.05, "pivot at 2 A", 10.0)

    def current_a(self, k: int) -> float:
        """Axis k's current in the rack's plant, A."""
        return float(self.rack.plant_state().current_a[k])

    def after_syncs(self, count: int) -> None:
        """Wait until the rack has processed `count` more SYNCs."""
        done = self.rack.counters.syncs + count
        wait_until(lambda: self.rack.counters.syncs >= done, f"{count} more SYNCs", 10.0)

    def holds_zero_torque(self) -> None:
        """Zero current on every axis, and only zero target torques sent for 50 SYNCs."""
        wait_until(lambda: all(abs(self.current_a(k)) < 1e-3 for k in range(4)), "0 A", 5.0)
        mark = self.torques.mark()
        self.after_syncs(50)
        sent = self.torques.since(mark)
        assert all(len(v) >= 40 for v in sent.values()), sent  # the cycle went on
        assert all(t == 0 for v in sent.values() for t in v), sent
        assert all(abs(self.current_a(k)) < 1e-3 for k in range(4))
        assert "not enabled" in self.bridge.enable(True)  # a latch holds until ~/recover


@pytest.fixture
def rig(default_robot: RobotParams, rack_and_master: Callable[..., RackAndMaster]) -> Iterator[Rig]:
    """The rack and the master, initialised and cycling, with a controller on a 5 ms timer."""
    torques = TargetTorques(f"test_master_watch_{os.getpid()}_{next(_channels)}")
    stop = threading.Event()
    feeder: threading.Thread | None = None
    try:
        # the master's heartbeat consumer keeps its default, 3 x 100 ms
        params = bridge_params(default_robot, cycle_hz=CYCLE_HZ, command_timeout_s=1.0)
        built = rack_and_master(torques.channel, params, robot=default_robot)
        bridge = built.bridge
        rig = Rig(built.channel, built.rack, built.network, bridge, torques)

        def controller() -> None:  # commands whether states come or not, as a timer would
            while not stop.wait(0.005):
                bridge.set_currents(rig.currents_a)

        feeder = threading.Thread(target=controller, name="timer_controller", daemon=True)
        bridge.init()
        bridge.set_currents(rig.currents_a)
        bridge.start()
        feeder.start()
        yield rig
    finally:
        stop.set()
        if feeder is not None and feeder.is_alive():
            feeder.join()
        torques.close()


def _latched_within(rig: Rig, text: str, bound_s: float) -> float:
    """Wait for `text` in the master's latched reason; the seconds it took."""
    start = time.monotonic()
    wait_until(lambda: text in rig.bridge.latched_reason(), f"'{text}' latched", bound_s)
    return time.monotonic() - start


def test_a_lost_heartbeat_is_latched_and_the_axes_hold_zero_torque(rig: Rig) -> None:
    """0x2030 sub 2 = 1 on pivot, enabled at 2 A: latched after the consumer time, 0 torque.

    CiA 301 7.2.8.3.2.2: the consumer time (3 x 0x1017 = 0.3 s) passes before the loss is
    seen, and the last heartbeat came at most one producer period before the write. The latch
    stays when heartbeats return, until recover(); then the pivot runs at 2 A again.
    """
    rig.enable()
    timeout_s = rig.bridge.params.drive_heartbeat_timeout_s
    producer_s = rig.bridge.params.heartbeat_producer_ms * 1e-3
    assert timeout_s == pytest.approx(0.3)
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_HEARTBEAT_OFF, 1)
    took_s = _latched_within(rig, "lost heartbeat of pivot", timeout_s + 2.0)
    assert took_s >= timeout_s - producer_s - 0.01
    assert "l_arm" not in rig.bridge.latched_reason()  # the others' heartbeats go on
    assert rig.bridge.counters.heartbeats_lost == 1
    assert rig.bridge.silent_heartbeats() == ("pivot",)
    rig.holds_zero_torque()

    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_HEARTBEAT_OFF, 0)
    wait_until(lambda: rig.bridge.silent_heartbeats() == (), "pivot's heartbeat again")
    rig.after_syncs(10)
    assert "lost heartbeat of pivot" in rig.bridge.latched_reason()  # until ~/recover
    rig.bridge.recover()
    assert rig.bridge.latched_reason() == ""
    rig.after_syncs(int(2 * timeout_s * CYCLE_HZ))  # twice the consumer time: not again
    assert rig.bridge.latched_reason() == ""
    assert rig.bridge.counters.heartbeats_lost == 1
    rig.enable()


@pytest.mark.parametrize("mask", [0x01, 0x0F], ids=["TPDO1", "every TPDO"])
def test_lost_tpdos_of_a_disabled_drive_are_a_reported_stall(rig: Rig, mask: int) -> None:
    """0x2030 sub 1 on a disabled pivot: `cycle_stall()` names pivot TPDO1, nothing latched.

    The stale latch watches enabled drives only; without complete cycles no joint_states go
    out, so the stall is reported (counted, WARN on /diagnostics) within `stall_cycles` SYNCs
    and ends with the next complete cycle.
    """
    wait_until(lambda: rig.bridge.counters.complete_cycles > 10, "complete cycles")
    stall_s = rig.bridge.params.stall_cycles / CYCLE_HZ
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_LOST_TPDOS, mask)
    start = time.monotonic()
    wait_until(lambda: rig.bridge.cycle_stall() != "", "the stall reported", stall_s + 3.0)
    assert time.monotonic() - start >= stall_s - 0.05
    assert rig.bridge.cycle_stall().endswith(": pivot TPDO1 missing")
    assert rig.bridge.counters.cycle_stalls == 1
    assert rig.bridge.latched_reason() == ""  # disabled: no torque at stake, not latched
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_LOST_TPDOS, 0)
    wait_until(lambda: rig.bridge.cycle_stall() == "", "complete cycles again", 5.0)
    assert rig.bridge.counters.cycle_stalls == 1
    rig.enable()  # nothing latched: it runs


def test_a_lost_tpdo1_while_enabled_is_latched_and_the_axes_hold_zero_torque(rig: Rig) -> None:
    """0x2030 sub 1 = 0x01 on an enabled pivot: TPDO2 still comes (no stale drive), latched.

    A controller on a timer would otherwise go on commanding from the last state it had.
    """
    rig.enable()
    stall_s = rig.bridge.params.stall_cycles / CYCLE_HZ
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_LOST_TPDOS, 0x01)
    _latched_within(rig, "no complete cycle for", stall_s + 3.0)
    reason = rig.bridge.latched_reason()
    assert "pivot TPDO1 missing" in reason and "stale" not in reason
    rig.holds_zero_torque()

    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_LOST_TPDOS, 0)
    wait_until(lambda: rig.bridge.cycle_stall() == "", "complete cycles again", 5.0)
    assert "no complete cycle" in rig.bridge.latched_reason()  # until ~/recover
    rig.bridge.recover()
    assert rig.bridge.latched_reason() == ""
    rig.enable()


def test_bus_off_of_a_disabled_drive_is_reported_and_recovered(rig: Rig) -> None:
    """0x2030 sub 5 = 600 ms on a disabled pivot: its heartbeat lost (latched) and the stall.

    Neither showed before the heartbeat consumer: a disabled drive is not watched for
    staleness. After the bus-off the drive is PRE-OPERATIONAL (0x1029 sub 1 = 0), so the stall
    lasts until recover()'s NMT start.
    """
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_BUS_OFF, 600)  # within the drive's 1 s consumer
    _latched_within(rig, "lost heartbeat of pivot", 3.0)
    wait_until(lambda: "pivot TPDO1" in rig.bridge.cycle_stall(), "the stall reported", 3.0)
    assert all(abs(rig.current_a(k)) < 1e-3 for k in range(4))
    assert "not enabled" in rig.bridge.enable(True)
    wait_until(lambda: rig.bridge.silent_heartbeats() == (), "heartbeat after bus-off", 5.0)
    assert rig.rack.nmt_state("pivot") == "PRE-OPERATIONAL"
    assert "lost heartbeat of pivot" in rig.bridge.latched_reason()
    rig.bridge.recover()
    wait_until(lambda: rig.bridge.cycle_stall() == "", "complete cycles after recover", 5.0)
    wait_until(lambda: rig.bridge.latched_reason() == "", "nothing latched", 5.0)
    rig.enable()


def test_without_faults_nothing_is_reported_over_several_seconds(rig: Rig) -> None:
    """4 s (1000 SYNCs) enabled at 2 A without a fault: no latch, no stall, cycles complete."""
    rig.enable()
    complete = rig.bridge.counters.complete_cycles
    done = rig.rack.counters.syncs + int(4.0 * CYCLE_HZ)
    seen: list[str] = []

    def quiet_until_done() -> bool:
        for text in (rig.bridge.latched_reason(), rig.bridge.cycle_stall()):
            if text:
                seen.append(text)
        return rig.rack.counters.syncs >= done

    wait_until(quiet_until_done, "1000 SYNCs", 30.0)
    assert seen == []
    assert rig.bridge.counters.heartbeats_lost == rig.bridge.counters.cycle_stalls == 0
    assert rig.bridge.counters.complete_cycles > complete + 900
    assert abs(rig.current_a(1) - PIVOT_A) < 0.05


def test_a_heartbeat_with_an_undefined_state_does_not_stop_init(rig: Rig) -> None:
    """A frame on a drive's heartbeat COB-ID with a state CiA 301 does not define (45).

    canopen records it as the drive's NMT state and then failed to log its next NMT command
    (KeyError: 45), so init() could not configure the drive (a fuzz test met it). Now init()
    goes through, and the drive runs again.
    """
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_HEARTBEAT_OFF, 1)  # only our byte arrives
    pivot = JOINTS.index("pivot")
    node = rig.bridge._axes[pivot].node
    rig.torques.bus.send(
        can.Message(arbitration_id=0x700 + NODE_IDS[pivot], data=[45], is_extended_id=False)
    )
    wait_until(lambda: node.nmt._state == 45, "canopen took the undefined state")
    rig.bridge.init()
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_HEARTBEAT_OFF, 0)
    wait_until(lambda: rig.bridge.silent_heartbeats() == (), "pivot's heartbeat again")
    rig.bridge.recover()
    rig.enable()


def _watch(
    drives_in_process: bool = False, **overrides: float
) -> tuple[SafetyWatch, list[MasterAxis], Counters]:
    """A SafetyWatch over four drives without a bus, its clock at 0."""
    params = bridge_params(None, **overrides)
    axes = [MasterAxis(j, cast("canopen.RemoteNode", None), 1.0, 1.0) for j in params.joints]
    counters = Counters()
    watch = SafetyWatch(params, axes, counters, threading.Lock(), lambda: 0.0, drives_in_process)
    return watch, axes, counters


def test_send_failures_in_a_row_halt_until_recover() -> None:
    """`max_send_failures` failed sends in a row halt the axes; a success between resets the run."""
    watch, _, counters = _watch(max_send_failures=3)
    for _ in range(2):
        watch.send_failed(can.CanError("no buffer"))
    watch.send_ok()
    watch.send_failed(can.CanError("no buffer"))
    assert not watch.halted
    watch.send_failed(can.CanError("no buffer"))
    watch.send_failed(can.CanError("no buffer"))
    assert watch.halted and "3 send failures in a row" in watch.latched_reason()
    assert counters.send_failures == 5
    watch.recover(now=1.0, cycle=10)
    assert not watch.halted and watch.latched_reason() == ""


def test_a_silent_enabled_drive_is_latched_stale_and_recover_rearms_it() -> None:
    """No TPDO beyond stale_timeout_s while enabled: latched; recover starts the watch again."""
    watch, axes, _ = _watch(stale_timeout_s=0.1)  # heartbeats: 0.3 s, not yet due
    watch.arm(now=0.0, cycle=0)
    for axis in axes[1:]:
        axis.last_tpdo_t = 0.2
    watch.command(0.2)
    watch.check(0.2, cycle=1, enabled=True)
    assert watch.stop_reason() == f"stale drive {axes[0].joint}"
    watch.recover(now=0.2, cycle=1)
    watch.check(0.25, cycle=2, enabled=True)
    assert watch.stop_reason() == ""


def test_a_freeze_the_drives_tolerate_is_a_note_and_a_longer_one_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The first stall is noted at INFO; one beyond the RPDO deadline is a WARNING, once.

    Every start of the bridge stood still once for 13-19 ms (module loads): routed to the ROS
    log, that was a WARN on every healthy first run.
    """
    watch, _, counters = _watch()
    rpdo_deadline_s = watch._params.rpdo_deadline_ms * 1e-3
    caplog.set_level(logging.INFO, logger="lca_sim.canbus.master_watch")
    for stall_s in (0.019, 0.03, rpdo_deadline_s + 0.05, rpdo_deadline_s + 0.2):
        watch.discount(Freeze(stall_s, stall_s), now=10.0)
    levels = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert [level for level, _ in levels] == [logging.INFO, logging.WARNING]
    longer = f"{(rpdo_deadline_s + 0.05) * 1e3:.0f} ms, longer than the drives' RPDO deadline"
    assert "19 ms" in levels[0][1] and longer in levels[1][1]
    assert counters.process_freezes == 4  # every one counted


def test_a_long_freeze_with_the_drives_in_this_process_is_a_note(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Drives in the bridge's process (the virtual rack) stand still with it: no WARN.

    Their watchdogs discount their own freeze, so a stall beyond the RPDO deadline trips none;
    it is said at INFO with that reason, and counted like any other.
    """
    watch, _, counters = _watch(drives_in_process=True)
    rpdo_deadline_s = watch._params.rpdo_deadline_ms * 1e-3
    caplog.set_level(logging.INFO, logger="lca_sim.canbus.master_watch")
    for stall_s in (0.019, rpdo_deadline_s + 0.05):
        watch.discount(Freeze(stall_s, stall_s), now=10.0)
    levels = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert [level for level, _ in levels] == [logging.INFO, logging.INFO]
    assert "longer than the drives' RPDO deadline" in levels[1][1]
    assert "the drives run in this process and stood still with it" in levels[1][1]
    assert counters.process_freezes == 2
