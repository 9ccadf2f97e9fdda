"""The virtual drive rack on python-can's in-process virtual bus.

Each test gets a channel of its own, a raw probe bus that records every frame from before the
rack boots, the rack, and where SDO is needed a canopen master network on a third bus instance.
Nothing sleeps a fixed time: waits poll a condition up to a deadline. The SYNC-driven plant only
advances on the SYNCs a test sends, so the physics checks do not depend on the machine's speed.
"""

from __future__ import annotations

import math
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import canopen
import pytest
from support import Probe, emcy_code, rack_nmt, rack_sync, remote_node, sdo_enable, wait_until

from lca_sim import RobotParams
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402.device import PowerState
from lca_sim.cli.virtual_drive import main
from lca_sim.config.rack import RackConfig, eds_path, load_rack_config
from lca_sim.errors import ConfigError

EDS = str(eds_path())
PIVOT = 2  # node ids of the shipped rack.yaml
L_ARM = 1
TIMEOUT_S = 5.0  # generous: the machine is shared


# --- NMT ------------------------------------------------------------------------------------


def test_boot_up_then_periodic_heartbeat(rack: VirtualDriveRack, probe: Probe) -> None:
    """Every node sends its boot-up (0x700 + id, 00), then heartbeats in PRE-OPERATIONAL (7F)."""
    for node_id in (1, 2, 3, 4):
        assert probe.wait(0x700 + node_id) == b"\x00"
    wait_until(lambda: len(probe.seen(0x702)) >= 4, "three heartbeats after the boot-up")
    assert probe.seen(0x702)[1:4] == [b"\x7f"] * 3
    assert rack.nmt_state("pivot") == "PRE-OPERATIONAL"


def test_nmt_stop_ignores_pdos(rack: VirtualDriveRack, probe: Probe) -> None:
    """In STOPPED, RPDOs are dropped, SYNCs bring no TPDO, the heartbeat says 04."""
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    rack_nmt(rack, probe, 0x02, PIVOT, "STOPPED")
    mark = probe.mark()
    probe.send(0x202, struct.pack("<Hh", 0x06, 0))
    rack_sync(rack, probe, 3)
    wait_until(lambda: b"\x04" in probe.seen(0x702, mark), "a STOPPED heartbeat")
    assert probe.seen(0x182, mark) == []
    assert rack.power_state("pivot") is PowerState.SWITCH_ON_DISABLED
    assert rack.counters.pdos_ignored_not_operational == 1


def test_nmt_reset_node_boots_again_with_defaults(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """Reset node: a new boot-up message, and written objects back at their defaults."""
    node = remote_node(master, PIVOT)
    node.sdo[0x6072].raw = 100
    node.sdo[0x1017].raw = 50
    sdo_enable(node)
    mark = probe.mark()
    probe.send(0x000, bytes([0x81, PIVOT]))
    assert probe.wait(0x702, mark) == b"\x00"
    assert node.sdo[0x6072].raw == 2000
    assert node.sdo[0x1017].raw == 100
    assert node.sdo[0x6041].raw & 0x4F == 0x40
    assert rack.nmt_state("pivot") == "PRE-OPERATIONAL"


# --- SDO and the state machine --------------------------------------------------------------


def test_enable_walk_over_sdo(rack: VirtualDriveRack, master: canopen.Network) -> None:
    """0x06, 0x07, 0x0F by SDO: statusword & 0x6F reads 0x21, 0x23, 0x27."""
    node = remote_node(master, PIVOT)
    assert node.sdo[0x6041].raw & 0x4F == 0x40
    masked = []
    for controlword in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = controlword
        masked.append(node.sdo[0x6041].raw & 0x6F)
    assert masked == [0x21, 0x23, 0x27]
    assert rack.power_state("pivot") is PowerState.OPERATION_ENABLED
    assert rack.power_state("l_arm") is PowerState.SWITCH_ON_DISABLED


def test_enable_walk_over_rpdo_applied_at_sync(rack: VirtualDriveRack, probe: Probe) -> None:
    """RPDO1 controlwords take effect at the next SYNC; TPDO1 of that SYNC shows them."""
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    probe.send(0x202, struct.pack("<Hh", 0x06, 0))
    wait_until(lambda: rack.counters.rpdos_received == 1, "the RPDO received")
    assert rack.power_state("pivot") is PowerState.SWITCH_ON_DISABLED  # not before the SYNC
    masked = []
    for controlword in (0x06, 0x07, 0x0F):
        probe.send(0x202, struct.pack("<Hh", controlword, 0))
        mark = probe.mark()
        rack_sync(rack, probe)
        statusword, position = struct.unpack("<Hi", probe.wait(0x182, mark))
        masked.append(statusword & 0x6F)
    assert masked == [0x21, 0x23, 0x27]
    assert position == round(0.6109 * 600.0 / (2.0 * math.pi) * 65536)  # pivot at rest, 35 deg


def test_illegal_jump_stays_where_it_is(rack: VirtualDriveRack, master: canopen.Network) -> None:
    """0x0F straight from SWITCH ON DISABLED, 0x07 too: nothing happens."""
    node = remote_node(master, PIVOT)
    for controlword in (0x0F, 0x07):
        node.sdo[0x6040].raw = controlword
        assert node.sdo[0x6041].raw & 0x4F == 0x40
    assert rack.power_state("pivot") is PowerState.SWITCH_ON_DISABLED


def test_sdo_aborts(rack: VirtualDriveRack, master: canopen.Network) -> None:
    """Reserved modes, unknown object, missing sub-index, read-only, max torque too high."""
    node = remote_node(master, PIVOT)
    cases = [
        # CiA 402-2 0x6060: 2 (velocity mode), 4 (torque profile), 7 (interpolated position)
        # are not run, -1 is manufacturer specific: value range exceeded.
        (lambda: node.sdo.download(0x6060, 0, struct.pack("<b", 2)), 0x06090030),
        (lambda: node.sdo.download(0x6060, 0, struct.pack("<b", 7)), 0x06090030),
        (lambda: node.sdo.download(0x6060, 0, struct.pack("<b", -1)), 0x06090030),
        (lambda: node.sdo.upload(0x5000, 0), 0x06020000),
        (lambda: node.sdo.upload(0x6041, 1), 0x06090011),
        (lambda: node.sdo.download(0x6041, 0, b"\x00\x00"), 0x06010002),
        (lambda: node.sdo.download(0x6072, 0, struct.pack("<H", 2001)), 0x06090031),
        (lambda: node.sdo.download(0x6007, 0, struct.pack("<h", 4)), 0x06090030),
    ]
    codes = []
    for request, _ in cases:
        with pytest.raises(canopen.SdoAbortedError) as aborted:
            request()  # type: ignore[no-untyped-call]
        codes.append(aborted.value.code)
    assert codes == [code for _, code in cases]
    assert node.sdo[0x6060].raw == 10
    assert node.sdo[0x6502].raw == 0x03A5  # PP, PV, HM, CSP, CSV, CST


def test_fault_reset_acts_on_the_rising_edge_only(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """Bit 7 held high resets nothing; its 0 -> 1 edge leaves FAULT, with an EMCY reset."""
    node = remote_node(master, PIVOT)
    node.sdo[0x1016][1].raw = (127 << 16) | 30  # watch the master's heartbeat, 30 ms
    sdo_enable(node)
    node.sdo[0x6040].raw = 0x8F  # bit 7 rises while enabled: nothing to reset
    assert node.sdo[0x6041].raw & 0x6F == 0x27
    probe.send(0x77F, b"\x05")  # one master heartbeat, then silence: FAULT
    wait_until(lambda: rack.power_state("pivot") is PowerState.FAULT, "the fault")
    for controlword in (0x8F, 0x80, 0x80):  # bit 7 stays high: a level, no edge
        node.sdo[0x6040].raw = controlword
        assert node.sdo[0x6041].raw & 0x4F == 0x08
    node.sdo[0x6040].raw = 0x00
    assert node.sdo[0x6041].raw & 0x4F == 0x08
    mark = probe.mark()
    node.sdo[0x6040].raw = 0x80  # the edge
    assert node.sdo[0x6041].raw & 0x4F == 0x40
    assert emcy_code(probe.wait(0x82, mark)) == (0x0000, 0x00)
    assert (node.sdo[0x603F].raw, node.sdo[0x1001].raw, rack.faults["pivot"]) == (0, 0, 0)


# --- torque ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("axis", "node_id", "target_permille", "current_a"),
    [("pivot", 2, 250, 2.5), ("l_arm", 1, -150, -1.5), ("c_arc", 3, 400, 4.0)],
)
def test_target_torque_gives_rated_current_share(
    rack: VirtualDriveRack,
    probe: Probe,
    master: canopen.Network,
    axis: str,
    node_id: int,
    target_permille: int,
    current_a: float,
) -> None:
    """N per mille of rated torque -> N / 1000 x 10 A in the plant; actuals report it back."""
    node = remote_node(master, node_id)
    node.sdo[0x1006].raw = 10_000  # 10 ms of plant per SYNC
    node.sdo[0x6071].raw = target_permille
    sdo_enable(node)
    rack_sync(rack, probe, 6)  # 60 ms: the current loop settled long ago
    index = rack.simulator.axis_names.index(axis)
    assert rack.plant_state().current_a[index] == pytest.approx(current_a, abs=0.02)
    assert node.sdo[0x6078].raw == pytest.approx(target_permille, abs=2)
    assert node.sdo[0x6077].raw == pytest.approx(target_permille, abs=2)
    assert node.sdo[0x6041].raw & 0x0C00 == 0x0400  # target reached, no internal limit
    others = [c for i, c in enumerate(rack.plant_state().current_a) if i != index]
    assert others == [0.0, 0.0, 0.0]


def test_target_beyond_max_torque_is_clamped(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """0x6072 = 100 per mille: a 500 target gives 1 A and statusword bit 11."""
    node = remote_node(master, PIVOT)
    node.sdo[0x1006].raw = 10_000
    node.sdo[0x6072].raw = 100
    node.sdo[0x6071].raw = -500
    sdo_enable(node)
    rack_sync(rack, probe, 6)
    assert rack.plant_state().current_a[1] == pytest.approx(-1.0, abs=0.02)
    assert node.sdo[0x6041].raw & 0x0800 == 0x0800
    node.sdo[0x6071].raw = -50
    assert node.sdo[0x6041].raw & 0x0800 == 0


def test_no_current_unless_operation_enabled(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """A target torque in every state short of OPERATION ENABLED, or with halt: 0 A exactly."""
    node = remote_node(master, PIVOT)
    node.sdo[0x1006].raw = 10_000
    node.sdo[0x6071].raw = 800
    currents = []
    for controlword in (0x00, 0x06, 0x07):
        node.sdo[0x6040].raw = controlword
        rack_sync(rack, probe, 2)
        currents.append(rack.plant_state().current_a[1])
    node.sdo[0x6040].raw = 0x0F
    rack_sync(rack, probe, 2)
    enabled_a = rack.plant_state().current_a[1]
    node.sdo[0x6040].raw = 0x010F  # halt
    rack_sync(rack, probe, 4)
    assert currents == [0.0, 0.0, 0.0]
    assert enabled_a == pytest.approx(8.0, abs=0.1)
    assert rack.plant_state().current_a[1] == pytest.approx(0.0, abs=0.01)
    assert node.sdo[0x6041].raw & 0x6F == 0x27  # halt keeps operation enabled


def test_tpdo3_reports_the_drive_chain_state(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """TPDO3 (on change): gear state index, motion, eta_m / eta_l per mille."""
    node = remote_node(master, PIVOT)
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    state, motion, eta_m, eta_l = struct.unpack("<BbHH", probe.wait(0x382))
    assert (state, motion, eta_m, eta_l) == (0, 0, 0xFFFF, 0xFFFF)  # stop_hold: eq. 10 idle
    node.sdo[0x1006].raw = 50_000  # SYNC loss after 150 ms: ample for a test sending SYNCs
    node.sdo[0x6071].raw = 800  # 8 A lifts the pivot: motor driving, eta_m 0.9 (Table 1)
    sdo_enable(node)
    mark = probe.mark()
    rack_sync(rack, probe, 4)
    lifting = (rack.simulator.state_names.index("motor_driving"), 1, 900, 1000)
    wait_until(
        lambda: lifting in [struct.unpack("<BbHH", data) for data in probe.seen(0x382, mark)],
        "a TPDO3 of the motor driving the lift",
    )


# --- watchdogs ------------------------------------------------------------------------------


def test_master_heartbeat_lost_faults_with_emcy(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """No master heartbeat within 0x1016: EMCY 0x8130, 0x603F / 0x1001 set, FAULT (0x6007 = 1)."""
    node = remote_node(master, PIVOT)
    node.sdo[0x1016][1].raw = (127 << 16) | 50
    sdo_enable(node)
    mark = probe.mark()
    probe.send(0x77F, b"\x05")  # one heartbeat arms the consumer, then silence
    assert emcy_code(probe.wait(0x82, mark)) == (0x8130, 0x11)
    wait_until(lambda: rack.power_state("pivot") is PowerState.FAULT, "FAULT")
    assert node.sdo[0x603F].raw == 0x8130
    assert node.sdo[0x1001].raw == 0x11
    assert rack.faults["pivot"] == 0x8130
    # the others watch the same master (250 ms) but, powered off, have nothing to react on
    assert rack.power_state("l_arm") is PowerState.SWITCH_ON_DISABLED


@pytest.mark.parametrize(
    ("option", "state"),
    [
        (0, PowerState.OPERATION_ENABLED),
        (2, PowerState.SWITCH_ON_DISABLED),
        (3, PowerState.SWITCH_ON_DISABLED),  # quick stop, at standstill at once
    ],
)
def test_heartbeat_loss_applies_the_abort_connection_option(
    rack: VirtualDriveRack,
    probe: Probe,
    master: canopen.Network,
    option: int,
    state: PowerState,
) -> None:
    """0x6007 = 0 keeps going, 2 disables voltage, 3 quick-stops; the EMCY goes out in each."""
    node = remote_node(master, PIVOT)
    node.sdo[0x6007].raw = option
    node.sdo[0x1016][1].raw = (127 << 16) | 30
    sdo_enable(node)
    mark = probe.mark()
    probe.send(0x77F, b"\x05")
    assert emcy_code(probe.wait(0x82, mark))[0] == 0x8130
    wait_until(lambda: rack.power_state("pivot") is state, f"{state}")
    assert rack.counters.heartbeat_losses >= 1


def test_rpdo_deadline(rack: VirtualDriveRack, probe: Probe, master: canopen.Network) -> None:
    """RPDO1 event timer 40 ms: after one RPDO and silence, EMCY 0x8250 and FAULT."""
    node = remote_node(master, PIVOT)
    node.sdo[0x1400][5].raw = 40
    sdo_enable(node)
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    mark = probe.mark()
    probe.send(0x202, struct.pack("<Hh", 0x0F, 0))
    assert emcy_code(probe.wait(0x82, mark)) == (0x8250, 0x11)
    wait_until(lambda: rack.power_state("pivot") is PowerState.FAULT, "FAULT")
    assert rack.counters.rpdo_timeouts == 1


def test_a_frozen_rack_does_not_blame_the_master(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """A freeze of the rack's own process is not the master's silence.

    The rack's threads stand still for 0.3 s (40 ms RPDO deadline) while the master goes on
    sending: the frozen time is discounted, no fault. Silence afterwards still faults.
    """
    node = remote_node(master, PIVOT)
    node.sdo[0x1400][5].raw = 40
    sdo_enable(node)
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    stop_sending = threading.Event()

    def master_rpdos() -> None:
        while not stop_sending.wait(0.01):
            probe.send(0x202, struct.pack("<Hh", 0x0F, 0))

    sender = threading.Thread(target=master_rpdos, daemon=True)
    sender.start()
    try:
        wait_until(lambda: rack.counters.rpdos_received > 5, "RPDOs flowing")
        with rack._lock:  # what a held GIL or a paused host does to the rack's threads
            time.sleep(0.3)  # the freeze under test: a stimulus, not a wait for a condition
        received = rack.counters.rpdos_received
        wait_until(lambda: rack.counters.rpdos_received > received + 5, "RPDOs after the freeze")
        # the receive thread may take the lock before the monitor's late tick: wait for it
        wait_until(lambda: rack.counters.process_freezes >= 1, "the freeze counted")
        assert rack.counters.rpdo_timeouts == 0
        assert rack.power_state("pivot") is PowerState.OPERATION_ENABLED
    finally:
        stop_sending.set()
        sender.join()
    mark = probe.mark()
    assert emcy_code(probe.wait(0x82, mark)) == (0x8250, 0x11)
    assert rack.counters.rpdo_timeouts == 1


def test_sync_loss(rack: VirtualDriveRack, probe: Probe, master: canopen.Network) -> None:
    """0x1006 = 20 ms, OPERATIONAL and enabled, no SYNC: EMCY 0x8700 and FAULT."""
    node = remote_node(master, PIVOT)
    node.sdo[0x1006].raw = 20_000
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    mark = probe.mark()
    sdo_enable(node)
    assert emcy_code(probe.wait(0x82, mark)) == (0x8700, 0x11)
    wait_until(lambda: rack.power_state("pivot") is PowerState.FAULT, "FAULT")
    assert rack.counters.sync_losses == 1
    assert rack.power_state("c_arc") is PowerState.SWITCH_ON_DISABLED


# --- PDO mapping ----------------------------------------------------------------------------


def test_rpdo_remap_over_sdo_takes_effect(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """RPDO1 remapped to the controlword alone: 2-byte frames drive it, 4-byte ones are bad."""
    node = remote_node(master, PIVOT)
    refused = []

    def refuse(sub: int, value: int) -> None:
        with pytest.raises(canopen.SdoAbortedError) as aborted:
            node.sdo[0x1600][sub].raw = value
        refused.append(aborted.value.code)

    refuse(0, 0)  # the PDO is still valid
    node.sdo[0x1400][1].raw = 0x80000202  # bit 31: invalid
    refuse(1, 0x60400010)  # sub 0 is still 2
    node.sdo[0x1600][0].raw = 0
    refuse(1, 0x60410010)  # the statusword cannot be received
    node.sdo[0x1600][1].raw = 0x60400010
    node.sdo[0x1600][0].raw = 1
    node.sdo[0x1400][1].raw = 0x00000202
    assert refused == [0x08000022, 0x08000022, 0x06040041]
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    probe.send(0x202, struct.pack("<Hh", 0x06, 0))  # the old layout: dropped
    rack_sync(rack, probe)
    assert rack.counters.bad_frames == 1
    assert rack.power_state("pivot") is PowerState.SWITCH_ON_DISABLED
    probe.send(0x202, struct.pack("<H", 0x06))
    rack_sync(rack, probe)
    assert rack.power_state("pivot") is PowerState.READY_TO_SWITCH_ON


def test_tpdo_remap_with_canopen_adds_torque_actual(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """The canopen library's PdoMap.save() adds torque actual to TPDO1: 8-byte TPDO1s."""
    node = remote_node(master, PIVOT)
    node.tpdo.read()  # type: ignore[no-untyped-call]
    node.tpdo[1].add_variable(0x6077)
    node.tpdo[1].save()
    assert node.sdo[0x1A00][0].raw == 3
    node.sdo[0x1006].raw = 50_000  # SYNC loss after 150 ms: ample for a test sending SYNCs
    node.sdo[0x6071].raw = -300
    sdo_enable(node)
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    mark = probe.mark()
    rack_sync(rack, probe, 3)
    wait_until(lambda: len(probe.seen(0x182, mark)) == 3, "three TPDO1s")
    frames = [struct.unpack("<Hih", data) for data in probe.seen(0x182, mark)]
    assert [statusword & 0x6F for statusword, _, _ in frames] == [0x27] * 3
    assert frames[0][2] == 0  # the state at the first SYNC: no torque yet
    assert frames[2][2] == pytest.approx(-300, abs=3)


def test_bad_frames_are_counted_and_the_rack_keeps_serving(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """SYNC with 2 bytes, NMT with 1, heartbeat with 0, a 3-byte RPDO: counted, no harm."""
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    before = rack.counters.syncs
    for cob_id, data in ((0x080, b"\x01\x02"), (0x000, b"\x01"), (0x77F, b""), (0x202, b"\x06")):
        probe.send(cob_id, data)
    wait_until(lambda: rack.counters.bad_frames == 4, "four bad frames counted")
    assert rack.counters.syncs == before
    assert rack.counters.handler_errors == 0
    assert remote_node(master, PIVOT).sdo[0x6041].raw & 0x4F == 0x40


# --- an independent master ------------------------------------------------------------------


def test_canopen_402_master_enables_and_moves_an_axis(
    rack: VirtualDriveRack, master: canopen.Network
) -> None:
    """The canopen library's BaseNode402 walks l_arm to OPERATION ENABLED in CST, moves it."""
    node = canopen.BaseNode402(L_ARM, EDS)  # type: ignore[no-untyped-call]
    master.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    node.TIMEOUT_CHECK_TPDO = 2.0
    node.TIMEOUT_SWITCH_STATE_SINGLE = 3.0
    node.TIMEOUT_SWITCH_STATE_FINAL = 6.0
    node.nmt.state = "PRE-OPERATIONAL"
    node.setup_402_state_machine()  # type: ignore[no-untyped-call]  # reads the PDOs over SDO
    node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
    assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
    node.nmt.state = "OPERATIONAL"
    wait_until(lambda: rack.nmt_state("l_arm") == "OPERATIONAL", "OPERATIONAL")
    node.rpdo[1].start(0.01)
    master.sync.start(0.01)
    try:
        node.state = "OPERATION ENABLED"
        assert rack.power_state("l_arm") is PowerState.OPERATION_ENABLED
        start = node.tpdo_values[0x6064]
        node.rpdo[1][0x6071].raw = 300  # 3 A x 0.15 N m/A beats the 0.12 N m static friction
        wait_until(lambda: node.tpdo_values[0x6064] > start + 2000, "l_arm turning forward")
        assert node.tpdo_values[0x606C] > 0
        assert rack.plant_state().velocity[0] > 0.0
    finally:
        master.sync.stop()  # type: ignore[no-untyped-call]
        node.rpdo[1].stop()


# --- configuration and the console script ---------------------------------------------------


def test_shipped_rack_config() -> None:
    """The shipped rack: node ids 1-4, 10 A, 2000 per mille, the pivot at 35 deg."""
    config = load_rack_config(None)
    assert isinstance(config, RackConfig)
    assert [(a.name, a.node_id) for a in config.axes] == [
        ("l_arm", 1),
        ("pivot", 2),
        ("c_arc", 3),
        ("lift", 4),
    ]
    assert {a.rated_current_a for a in config.axes} == {10.0}
    assert {a.max_torque_permille for a in config.axes} == {2000}
    assert [a.initial_position for a in config.axes] == [0.0, 0.6109, 0.0, 0.0]
    assert (config.dt_s, config.encoder_increments_per_rev, config.heartbeat_producer_ms) == (
        1e-4,
        65536,
        100,
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("dt_s: 1.0e-4", "dt_s: 1.0e-4\nspeed: 3"), "speed: unknown key"),
        (("{node_id: 2,", "{node_id: two,"), "axes.pivot.node_id: expected an integer"),
        (("{node_id: 2,", "{node_id: 1,"), "axes: expected distinct node ids, 1 is repeated"),
        (("{node_id: 2,", "{node_id: 200,"), "expected an integer in [1, 127], got 200"),
        (("  lift:", "  wrist:"), "axes.wrist: unknown axis"),
        (("heartbeat_producer_ms: 100", "heartbeat_producer_ms: 1.5"), "expected an integer"),
        (("rated_current_a: 10.0, max", "rated_current_a: -1, max"), "expected a number > 0"),
        (("max_torque_permille: 2000, initial_position: 0.6109", "initial_position: 0.6109"),
         "axes.pivot.max_torque_permille: missing required key"),
    ],
)  # fmt: skip
def test_rack_config_is_validated_strictly(
    tmp_path: Path, change: tuple[str, str], message: str
) -> None:
    """Unknown keys, wrong types, repeated node ids: one ConfigError line naming the key."""
    text = (eds_path().parent / "rack.yaml").read_text(encoding="utf-8")
    assert change[0] in text
    path = tmp_path / "rack.yaml"
    path.write_text(text.replace(change[0], change[1], 1), encoding="utf-8")
    with pytest.raises(ConfigError) as error:
        load_rack_config(path)
    assert message in str(error.value)
    assert str(path) in str(error.value)
    assert "\n" not in str(error.value)


def test_initial_position_outside_the_end_stops_is_a_config_error(
    tmp_path: Path, default_robot: RobotParams
) -> None:
    """A pose the URDF forbids is refused when the rack is built, naming the file."""
    text = (eds_path().parent / "rack.yaml").read_text(encoding="utf-8")
    path = tmp_path / "rack.yaml"
    path.write_text(text.replace("initial_position: 0.6109", "initial_position: 99.0"))
    bus = can.Bus(interface="virtual", channel=f"config_{os.getpid()}")
    try:
        with pytest.raises(ConfigError, match="initial position of pivot"):
            VirtualDriveRack(bus, load_rack_config(path), robot=default_robot)
    finally:
        bus.shutdown()


def test_main_reports_a_missing_interface(capsys: pytest.CaptureFixture[str]) -> None:
    """No such CAN interface: one line on stderr, exit code 2, no traceback."""
    assert main(["--interface", "socketcan", "--channel", "nope0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("lca-virtual-drive: error: cannot open CAN interface 'socketcan'")
    assert main(["--interface", "no_such_interface", "--channel", "x"]) == 2


def test_main_runs_until_sigterm() -> None:
    """The console script serves a bus until SIGTERM, then exits 0."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "lca_sim.cli.virtual_drive", "--interface", "virtual"],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # blocks until the rack is up (or the process dies)
        assert "nodes l_arm=1, pivot=2, c_arc=3, lift=4 on virtual can0" in line
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize(
    ("data_type", "mappable"),
    [(0x04, True), (0x07, True), (0x08, True), (0x10, False), (0x16, False), (0x09, False)],
)
def test_only_whole_byte_numbers_map(data_type: int, mappable: bool) -> None:
    """INTEGER32, UNSIGNED32 and REAL32 map; INTEGER24, UNSIGNED24 and strings are refused.

    canopen packs 24-bit numbers with a 32-bit struct: mapped, they would code the frame one
    byte too long.
    """
    from canopen.objectdictionary import ODVariable
    from canopen.sdo.exceptions import SdoAbortedError

    from lca_sim.canbus.rack_state import frame_codec
    from lca_sim.cia402.cia301 import ABORT_NOT_MAPPABLE

    obj = ODVariable("x", 0x2000, 0)
    obj.data_type = data_type
    if mappable:
        assert frame_codec([obj]).size == len(obj) // 8
    else:
        with pytest.raises(SdoAbortedError) as info:
            frame_codec([obj])
        assert info.value.code == ABORT_NOT_MAPPABLE


# --- the drive-chain extras (TPDO4: 0x2014-0x2016) ------------------------------------------


def test_tpdo4_goes_every_tenth_sync(rack: VirtualDriveRack, probe: Probe) -> None:
    """TPDO4 is transmission type 10: the 10th and 20th of 25 SYNCs, after that SYNC's TPDO1."""
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    mark = probe.mark()
    rack_sync(rack, probe, 25)
    wait_until(lambda: len(probe.seen(0x182, mark)) == 25, "25 TPDO1s")
    wait_until(lambda: len(probe.seen(0x482, mark)) == 2, "two TPDO4s")
    with probe._lock:
        ids = [m.arbitration_id for m in probe.frames[mark:] if m.arbitration_id in (0x182, 0x482)]
    tpdo1_before = [ids[: i + 1].count(0x182) for i, cob in enumerate(ids) if cob == 0x482]
    assert tpdo1_before == [10, 20]
    assert all(len(data) == 6 for data in probe.seen(0x482, mark))


def test_a_tpdo_made_invalid_or_event_driven_over_sdo_goes_as_its_objects_now_say(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """CiA 301 0x1803, TPDO4's communication parameters, written while OPERATIONAL.

    Its COB-ID with bit 31 set: no TPDO4 at any of 21 SYNCs (type 10 sent two before). Valid
    again with type 1: one at each SYNC. Type 254 with a 20 ms event timer: sent by the timer,
    with no SYNC at all.
    """
    node = remote_node(master, PIVOT)
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    node.sdo[0x1803][1].raw = 0x8000_0482  # not valid
    mark = probe.mark()
    rack_sync(rack, probe, 21)  # the 21st SYNC's TPDO1 comes after the 20th SYNC's TPDO4
    wait_until(lambda: len(probe.seen(0x182, mark)) == 21, "21 TPDO1s")
    assert probe.seen(0x482, mark) == []
    node.sdo[0x1803][2].raw = 1
    node.sdo[0x1803][1].raw = 0x482
    mark = probe.mark()
    rack_sync(rack, probe, 5)
    wait_until(lambda: len(probe.seen(0x482, mark)) == 5, "a TPDO4 at each of 5 SYNCs")
    node.sdo[0x1803][5].raw = 20  # event timer, ms
    node.sdo[0x1803][2].raw = 254  # event-driven (manufacturer-specific event)
    mark = probe.mark()
    wait_until(lambda: len(probe.seen(0x482, mark)) >= 3, "three TPDO4s by the event timer")
    assert probe.seen(0x080, mark) == []  # no SYNC sent meanwhile


def test_tpdo4_reports_load_friction_and_voltage(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> None:
    """Motor-side load and friction torque (per mille of 1.2 N m) and voltage (10 mV) of the plant.

    TPDO4 set to every SYNC (type 1); the pivot lifting at 8 A. A TPDO carries the plant state
    before its SYNC's step, which is the state after the previous SYNC: read then, compared
    within one quantum.
    """
    node = remote_node(master, PIVOT)
    node.sdo[0x1803][2].raw = 1
    node.sdo[0x1006].raw = 50_000  # SYNC loss after 500 ms: ample for a test sending SYNCs
    node.sdo[0x6071].raw = 800
    sdo_enable(node)
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    start = probe.mark()
    rack_sync(rack, probe, 4)  # 150 ms of plant: the pivot is moving up
    # The 4th SYNC's TPDO4 may reach the probe after the rack has counted that SYNC: let it
    # arrive, or it would be taken for the next SYNC's (one step of motion apart).
    wait_until(lambda: len(probe.seen(0x482, start)) >= 4, "the 4 SYNCs' TPDO4s")
    with rack._lock:
        signals = rack.simulator.signals
    pivot = rack.simulator.axis_names.index("pivot")
    mark = probe.mark()
    rack_sync(rack, probe)
    load, friction, voltage = struct.unpack("<hhh", probe.wait(0x482, mark))
    expected = {name: float(signals.values[name][pivot]) for name in SIGNALS}
    assert signals.motion[pivot] == 1  # direct: eq. 10 with friction and eta
    assert load * 1.2e-3 == pytest.approx(expected["load_torque_nm"], abs=0.6e-3)
    assert friction * 1.2e-3 == pytest.approx(expected["friction_torque_nm"], abs=0.6e-3)
    assert voltage * 0.01 == pytest.approx(expected["voltage_v"], abs=0.005)
    # real numbers, not zeros: gravity on the pivot, friction, 8 A through 1 ohm plus back-EMF
    assert load > 50
    assert friction > 20
    assert voltage > 800


SIGNALS = ("load_torque_nm", "friction_torque_nm", "voltage_v")
