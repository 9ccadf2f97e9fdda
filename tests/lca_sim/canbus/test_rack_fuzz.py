"""Whatever arrives on the bus, the virtual drive rack keeps running and applies no torque.

A property-based test (hypothesis): random frame sequences (random 11- and 29-bit identifiers,
lengths 0-8 and wrong ones, remote, CAN FD and error frames, floods of SDO requests and NMT
commands, SYNC bursts, heartbeats, RPDOs of the wrong length) are thrown at one running rack on
python-can's virtual bus. After each sequence the rack must still answer, no handler may have
failed, and no axis may be enabled or carry current: the sequences hold no command a master
gives (no well-formed RPDO, no SDO download), so any torque would be one nobody commanded. Then
the rack must still boot (NMT reset node), and the lca_hil bridge's master (`Cia402Master`)
must configure it, enable it, move an axis with a current command and stop it again.

Bounded: 150 sequences of at most 121 frames, about 3 s here (the test asserts < 20 s).
"""

from __future__ import annotations

import struct
import time
from functools import partial

import can
import canopen
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import Probe, bridge_params, wait_until

from lca_sim import RobotParams
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_state import Snapshot
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402.device import PowerState
from lca_sim.config.rack import eds_path

JOINTS = ("l_arm", "pivot", "c_arc", "lift")
NODE_IDS = (1, 2, 3, 4)

# --- the frames ------------------------------------------------------------------------------

_any_data = st.binary(min_size=0, max_size=8)
_node = st.sampled_from([0, 1, 2, 3, 4, 5, 127])

# Any 11-bit identifier, with the CANopen function codes of these nodes weighted in.
_standard_id = st.one_of(
    st.integers(0, 0x7FF),
    st.sampled_from([0x000, 0x080, 0x081, 0x082, 0x182, 0x282, 0x582, 0x602, 0x701, 0x77F]),
)


def _message(arbitration_id: int, data: bytes, **kwargs: bool) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, **kwargs)


def _not_a_download(data: bytes) -> bool:
    """An SDO request that writes nothing: not an initiate or segment download, block download."""
    return not data or (data[0] & 0xE0) not in (0x00, 0x20, 0xC0)


_random_standard = st.builds(
    lambda i, d: _message(i, d, is_extended_id=False),
    _standard_id.filter(lambda i: not 0x200 <= i <= 0x57F and not 0x600 <= i <= 0x67F),
    _any_data,
)
_random_extended = st.builds(
    lambda i, d: _message(i, d, is_extended_id=True), st.integers(0, 0x1FFFFFFF), _any_data
)
_remote = st.builds(
    lambda i, n: can.Message(arbitration_id=i, is_remote_frame=True, dlc=n, is_extended_id=False),
    _standard_id,
    st.integers(0, 8),
)
_fd = st.builds(
    lambda i, d: _message(i, d, is_extended_id=False, is_fd=True),
    _standard_id,
    st.binary(min_size=0, max_size=64),
)
_error_frame = st.builds(
    lambda c: can.Message(arbitration_id=c, is_error_frame=True, dlc=8, data=bytes(8)),
    st.integers(0, 0x1FFFFFFF),
)
# RPDO COB-IDs (0x200-0x4FF + node) with any length but the mapped one (4 bytes for RPDO1):
# a well-formed RPDO is a master's command, which this test does not give.
_bad_rpdo = st.builds(
    lambda base, node, d: _message(base + node, d, is_extended_id=False),
    st.sampled_from([0x200, 0x300, 0x400, 0x500]),
    _node,
    st.binary(min_size=0, max_size=8).filter(lambda d: len(d) != 4),
).filter(lambda m: not (0x300 <= m.arbitration_id <= 0x37F and len(m.data) == 3))
# SDO requests that read or abort (any length), never writes.
_sdo = st.builds(
    lambda node, d: _message(0x600 + node, d, is_extended_id=False),
    _node,
    st.one_of(
        st.builds(
            lambda index, sub: struct.pack("<BHB4x", 0x40, index, sub),
            st.sampled_from([0x1000, 0x1001, 0x1017, 0x1029, 0x1800, 0x6041, 0x6064, 0x2020]),
            st.integers(0, 8),
        ),
        _any_data.filter(_not_a_download),
    ),
)
_nmt = st.builds(
    lambda cmd, node, extra: _message(0x000, bytes([cmd, node]) + extra, is_extended_id=False),
    st.sampled_from([0x01, 0x02, 0x80, 0x81, 0x82, 0x00, 0xFF]),
    _node,
    st.sampled_from([b"", b"", b"", b"\x00"]),
)
_sync = st.builds(
    lambda d: _message(0x080, d, is_extended_id=False), st.sampled_from([b"", b"\x01", b"\x01\x02"])
)
_heartbeat = st.builds(
    lambda node, d: _message(0x700 + node, d, is_extended_id=False),
    st.sampled_from([1, 2, 5, 127]),
    st.sampled_from([b"\x05", b"\x7f", b"", b"\x05\x05"]),
)
_frame = st.one_of(
    _random_standard, _random_extended, _remote, _fd, _error_frame, _bad_rpdo, _sdo, _nmt,
    _sync, _heartbeat,
)  # fmt: skip
_flood = st.builds(lambda f, n: [f] * n, st.one_of(_sdo, _nmt, _sync), st.integers(10, 60))
_START_ALL = can.Message(arbitration_id=0x000, data=[0x01, 0], is_extended_id=False)
# Half the sequences start with every node OPERATIONAL, where PDOs and SYNCs do the most.
_sequence = st.tuples(
    st.booleans(),
    st.lists(st.one_of(_frame.map(lambda f: [f]), _flood), min_size=4, max_size=16),
).map(lambda t: ([_START_ALL] if t[0] else []) + [f for chunk in t[1] for f in chunk][:120])


# --- the rig ---------------------------------------------------------------------------------


def _settled(rack: VirtualDriveRack, probe: Probe) -> None:
    """Wait until the rack has handled every frame sent so far (it answers a later request).

    NMT enter pre-operational for all, then an SDO upload of 0x1000 from l_arm: frames of one
    bus are handled in order, so its answer means everything before it was handled.
    """
    mark = probe.mark()
    probe.send(0x000, bytes([0x80, 0]))
    probe.send(0x601, struct.pack("<BHB4x", 0x40, 0x1000, 0))
    wait_until(
        lambda: any(d[:1] == b"\x43" for d in probe.seen(0x581, mark)), "the rack answers again"
    )


def _no_torque(rack: VirtualDriveRack) -> None:
    for name in JOINTS:
        assert rack.power_state(name) is not PowerState.OPERATION_ENABLED, name
    currents_a = rack.plant_state().current_a
    assert all(abs(i) < 1e-6 for i in currents_a), currents_a


# --- the test --------------------------------------------------------------------------------


def test_random_frames_then_the_master_still_boots_enables_moves_and_stops(
    rack: VirtualDriveRack, probe: Probe, channel: str, default_robot: RobotParams
) -> None:
    """Random frames: the rack survives, applies no torque, then boots, enables, moves, stops."""
    _settled(rack, probe)
    # A master has set the cycle (0x1006 = 2 ms), so SYNC floods are early SYNCs too (until a
    # random NMT reset puts it back to 0).
    mark = probe.mark()
    for node_id in NODE_IDS:
        probe.send(0x600 + node_id, struct.pack("<BHBI", 0x23, 0x1006, 0, 2000))
        probe.wait(0x580 + node_id, mark)
    started_s = time.monotonic()

    @settings(
        max_examples=150,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(frames=_sequence)
    def throw(frames: list[can.Message]) -> None:
        for msg in frames:
            probe.bus.send(msg)
        _settled(rack, probe)
        _no_torque(rack)
        assert rack.counters.handler_errors == 0

    throw()
    assert time.monotonic() - started_s < 20.0  # the bound this module promises
    counters = rack.counters
    assert counters.extended_frames > 0 and counters.fd_frames > 0 and counters.bad_frames > 0

    # Still boots: NMT reset node, four boot-up messages (CiA 301: state byte 0x00). A node's
    # heartbeat already on its way when the reset came may arrive first: one, in a valid state.
    mark = probe.mark()
    probe.send(0x000, bytes([0x81, 0]))

    def booted(cob: int) -> bool:
        return b"\x00" in probe.seen(cob, mark)

    for node_id in NODE_IDS:
        cob = 0x700 + node_id
        wait_until(partial(booted, cob), f"node {node_id}'s boot-up")
        before = probe.seen(cob, mark)
        before = before[: before.index(b"\x00")]
        assert len(before) <= 1 and set(before) <= {b"\x04", b"\x05", b"\x7f"}, before

    # Enables, moves and stops on the bridge master's command.
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    network.connect()
    currents_a = [0.0] * len(JOINTS)
    bridge: Cia402Master | None = None

    def feed(_snapshot: Snapshot) -> None:  # a controller answering every state
        assert bridge is not None
        bridge.set_currents(currents_a)

    bridge = Cia402Master(network, bridge_params(default_robot), eds_path(), on_state=feed)
    try:
        bridge.init()
        bridge.start()
        bridge.set_currents(currents_a)
        assert bridge.enable(True) == "enabling"
        wait_until(
            lambda: all(rack.power_state(j) is PowerState.OPERATION_ENABLED for j in JOINTS),
            "every drive enabled",
        )
        cycles = bridge.counters.complete_cycles
        wait_until(lambda: bridge.counters.complete_cycles > cycles + 25, "25 cycles enabled")
        assert all(abs(i) < 0.05 for i in rack.plant_state().current_a)  # none commanded
        start_position = rack.plant_state().position[0]
        currents_a[0] = 3.0  # l_arm: 3 A x 0.15 N m/A beats the static friction
        wait_until(lambda: rack.plant_state().position[0] > start_position + 0.01, "l_arm moving")
        currents_a[0] = 0.0
        assert bridge.enable(False) == "disabling"
        wait_until(
            lambda: all(rack.power_state(j) is not PowerState.OPERATION_ENABLED for j in JOINTS),
            "every drive disabled",
        )
        wait_until(lambda: all(abs(i) < 0.05 for i in rack.plant_state().current_a), "no current")
        assert bridge.latched_reason() == ""
    finally:
        bridge.stop()
        network.disconnect()


def test_random_frames_at_a_running_bridge_never_make_it_command_torque(
    rack: VirtualDriveRack, probe: Probe, channel: str, default_robot: RobotParams
) -> None:
    """The bridge's master, running with every drive enabled and a zero command, under fire.

    The same random sequences (bad PDOs, foreign and fake TPDOs, EMCYs, NMT and SDO floods,
    SYNCs of a second producer, error frames) arrive while its cycle runs. Whatever it
    concludes from them (a latched EMCY, a stale drive, a fake statusword), its cycle goes on
    (or, after a bus-off error frame, stops and says so until `recover()`), and every target
    torque it sends is 0: it never commands a torque the controller did not. Then `init()`,
    `recover()` and `enable` bring the drives back, and a command moves an axis again.
    """
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    network.connect()
    bridge = Cia402Master(network, bridge_params(default_robot), eds_path())
    try:
        bridge.init()
        bridge.start()
        assert bridge.set_currents([0.0] * len(JOINTS)) is None
        assert bridge.enable(True) == "enabling"
        wait_until(
            lambda: all(rack.power_state(j) is PowerState.OPERATION_ENABLED for j in JOINTS),
            "every drive enabled",
        )
        mark = probe.mark()
        started_s = time.monotonic()

        @settings(
            max_examples=60,
            deadline=None,
            database=None,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        )
        @given(frames=_sequence)
        def throw(frames: list[can.Message]) -> None:
            for msg in frames:
                probe.bus.send(msg)
                bridge.set_currents([0.0] * len(JOINTS))  # the controller goes on
            cycles = bridge.counters.cycles

            def bus_off() -> bool:
                return "bus-off" in bridge.latched_reason()

            def running() -> bool:
                # A bus-off error frame (of this sequence, or one still queued from an earlier
                # one): the cyclic transmission stopped, as it must, and says so; an
                # operator's ~/recover starts it again.
                if bus_off():
                    assert bridge.counters.error_frames > 0
                    bridge.recover()
                    start[0] = bridge.counters.cycles
                return bridge.counters.cycles > start[0] + 2

            start = [cycles]
            wait_until(running, "the bridge's cycle runs")

        throw()
        assert time.monotonic() - started_s < 30.0
        # RPDO1 of the compact layout: the target torque alone, INTEGER16 per mille.
        sent = [d for n in NODE_IDS for d in probe.seen(0x200 + n, mark) if len(d) == 2]
        assert len(sent) > 100
        assert {struct.unpack("<h", d)[0] for d in sent} == {0}

        # The random NMT resets may have put a drive back to its boot mapping behind the
        # master's back: configure them again (the bridge's ~/init), then clear the latches.
        bridge.stop()
        # The sequences' SDO requests used the drives' default SDO channel too (CiA 301 gives
        # it one client at a time): let the rack answer them all before the master's own.
        _settled(rack, probe)
        bridge.init()
        bridge.start()
        bridge.recover()
        bridge.set_currents([0.0] * len(JOINTS))
        wait_until(lambda: bridge.latched_reason() == "", "latches cleared")
        reset = (PowerState.SWITCH_ON_DISABLED, PowerState.READY_TO_SWITCH_ON)
        wait_until(
            lambda: all(bridge.axis_state(j).power_state in reset for j in JOINTS),
            "faults reset",
        )
        assert bridge.enable(True) == "enabling"
        wait_until(
            lambda: all(rack.power_state(j) is PowerState.OPERATION_ENABLED for j in JOINTS),
            "every drive enabled again",
        )
        start_position = rack.plant_state().position[0]
        deadline_s = time.monotonic() + 10.0
        while rack.plant_state().position[0] < start_position + 0.01:
            assert time.monotonic() < deadline_s, "l_arm did not move on a 3 A command"
            bridge.set_currents([3.0, 0.0, 0.0, 0.0])
            time.sleep(0.01)  # a controller's period, not a wait for a result
    finally:
        bridge.stop()
        network.disconnect()
