"""The CAN bridge's master (no ROS) against the virtual drive rack, on python-can's virtual bus.

Each test gets its own virtual channel: a rack on one bus instance, the bridge's canopen network
on another, and where a test injects frames (EMCY, error frames, NMT) a third. Nothing sleeps a
fixed time: `support.wait_until` polls a condition up to a deadline.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import can
import canopen
import pytest
from support import RackAndMaster, bridge_params, wait_until

from lca_sim.canbus import emcy
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_params import BridgeError
from lca_sim.canbus.master_state import Snapshot
from lca_sim.canbus.master_watch import CAN_ERR_BUSOFF
from lca_sim.canbus.relay import RelayServer
from lca_sim.canbus.remote import RemoteTransportBus
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402 import device
from lca_sim.cia402.device import PowerState
from lca_sim.config.paths import config_dir
from lca_sim.config.rack import load_rack_config

EDS = config_dir() / "can" / "lca_drive.eds"
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
NODE_IDS = (1, 2, 3, 4)
_channels = itertools.count()


@dataclass
class Rig(RackAndMaster):
    """A rack, a bridge on the same virtual channel, and a spare bus for injected frames."""

    injector: can.BusABC
    snapshots: list[Snapshot] = field(default_factory=list)
    feeding: threading.Event = field(default_factory=threading.Event)
    currents_a: list[float] = field(default_factory=lambda: [0.0] * 4)
    last_fed_s: float = 0.0  # time.monotonic() of the feeder's last command

    def states(self) -> dict[str, PowerState | None]:
        """The power state of each drive as the bridge last read it."""
        return {j: self.bridge.axis_state(j).power_state for j in JOINTS}

    def all_in(self, state: PowerState) -> bool:
        """Every drive in `state`."""
        return all(s is state for s in self.states().values())


@pytest.fixture
def rig_factory(
    rack_and_master: Callable[..., RackAndMaster],
) -> Iterator[Callable[..., Rig]]:
    """Build rigs; everything started is stopped at the end, whatever happened."""
    injectors: list[can.BusABC] = []

    def build(before_init: Callable[[str], None] | None = None, **overrides: Any) -> Rig:
        rig_holder: list[Rig] = []

        def on_state(snapshot: Snapshot) -> None:
            rig = rig_holder[0]
            rig.snapshots.append(snapshot)
            if rig.feeding.is_set():  # a controller answering every state
                rig.bridge.set_currents(rig.currents_a)
                rig.last_fed_s = time.monotonic()

        built = rack_and_master(
            f"test_master_{next(_channels)}",
            bridge_params(**overrides),
            on_state=on_state,
            settle=True,
            before_master=before_init,  # e.g. remap the drives as a real one is mapped
        )
        injector = can.Bus(interface="virtual", channel=built.channel)
        injectors.append(injector)
        rig = Rig(built.channel, built.rack, built.network, built.bridge, injector)
        rig_holder.append(rig)
        built.bridge.init()
        built.bridge.start()
        return rig

    try:
        yield build
    finally:
        for injector in injectors:
            injector.shutdown()


def _enabled(rig: Rig, feed: bool = True) -> Rig:
    rig.feeding.set() if feed else rig.feeding.clear()
    rig.bridge.set_currents(rig.currents_a)
    assert rig.bridge.enable(True) == "enabling"
    wait_until(lambda: rig.all_in(PowerState.OPERATION_ENABLED), "all drives enabled", 5.0)
    return rig


def test_init_configures_and_enable_walks_every_drive(
    rig_factory: Callable[..., Rig],
) -> None:
    rig = rig_factory()
    # Not enabled yet: the bridge walks the drives to ready to switch on (0x06), no further.
    wait_until(lambda: rig.all_in(PowerState.READY_TO_SWITCH_ON), "drives ready to switch on", 5.0)
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 25, "25 more cycles", 5.0)
    assert rig.all_in(PowerState.READY_TO_SWITCH_ON)
    _enabled(rig)
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 50, "50 more complete cycles", 5.0)
    assert rig.bridge.sdo_read("pivot", 0x6060, 0) == 10  # CST, set over SDO by init
    assert rig.bridge.sdo_read("pivot", 0x1006, 0) == 4000  # 250 Hz cycle, us


def test_current_command_becomes_drive_current(rig_factory: Callable[..., Rig]) -> None:
    """2 A on the pivot: per mille of the rated torque through k_t, the drive's loop follows."""
    rig = _enabled(rig_factory())
    rig.currents_a = [0.0, 2.0, 0.0, 0.0]
    wait_until(
        lambda: abs(rig.bridge.axis_state("pivot").current_a - 2.0) < 0.05,
        "pivot current at 2 A",
        5.0,
    )
    # no other axis got current
    assert all(abs(rig.bridge.axis_state(j).current_a) < 0.05 for j in ("l_arm", "c_arc", "lift"))


def test_command_above_max_torque_is_clamped(rig_factory: Callable[..., Rig]) -> None:
    """0x6072 = 2000 per mille of the rated torque (20 A at a 10 A rating): 50 A gets 20 A."""
    rig = _enabled(rig_factory())
    rig.currents_a = [0.0, 0.0, 0.0, 50.0]  # the lift: its current loop reaches the setpoint
    wait_until(lambda: rig.bridge.counters.commands_clamped > 10, "clamped commands counted", 5.0)
    wait_until(
        lambda: abs(rig.bridge.axis_state("lift").current_a - 20.0) < 0.5,
        "lift current at the 20 A clamp",
        5.0,
    )


def test_no_torque_unless_enabled(rig_factory: Callable[..., Rig]) -> None:
    rig = rig_factory()
    rig.currents_a = [0.0, 5.0, 0.0, 0.0]
    rig.feeding.set()
    rig.bridge.set_currents(rig.currents_a)
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 50, "50 cycles while disabled", 5.0)
    assert max(abs(s.axes[1].current_a) for s in rig.snapshots[n:]) == 0.0


def test_controller_silence_halts_then_quick_stops(rig_factory: Callable[..., Rig]) -> None:
    rig = _enabled(rig_factory(command_timeout_s=0.05, quick_stop_after_s=0.2))
    rig.currents_a = [0.0, 3.0, 0.0, 0.0]
    wait_until(lambda: rig.bridge.axis_state("pivot").current_a > 2.5, "3 A flowing", 5.0)
    rig.feeding.clear()  # the controller falls silent
    wait_until(lambda: abs(rig.bridge.axis_state("pivot").current_a) < 0.1, "current to 0", 2.0)
    assert rig.bridge.counters.silence_halts == 1
    wait_until(lambda: rig.all_in(PowerState.SWITCH_ON_DISABLED), "quick stop done", 2.0)
    # Not before timeout + quick-stop delay, counted from the last command the bridge received
    # (the feeder may answer one more state after `feeding` is cleared).
    assert time.monotonic() - rig.last_fed_s >= 0.25
    # The controller comes back: nothing moves until an explicit enable.
    rig.feeding.set()
    rig.bridge.set_currents(rig.currents_a)
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 25, "25 cycles after the comeback", 5.0)
    assert rig.all_in(PowerState.SWITCH_ON_DISABLED)
    _enabled(rig)


def test_a_frozen_bridge_does_not_blame_the_controller_or_the_drives(
    rig_factory: Callable[..., Rig],
) -> None:
    """A freeze of the whole process is nobody's silence.

    The bridge's and the rack's threads stand still for 0.3 s (what a held GIL does): with a
    0.05 s command timeout, a 0.1 s stale timeout and the drives' 40 ms SYNC-loss deadline,
    nothing trips, because both sides discount the frozen time. A silent controller is still
    caught: the halt test above runs with the same timeouts.
    """
    rig = _enabled(rig_factory(command_timeout_s=0.05, stale_timeout_s=0.1))
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 25, "25 cycles enabled", 5.0)
    with rig.rack._lock, rig.bridge._lock:
        time.sleep(0.3)  # the freeze under test: a stimulus, not a wait for a condition
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 25, "25 cycles after the freeze", 5.0)
    assert rig.bridge.counters.process_freezes >= 1
    assert rig.bridge.counters.silence_halts == 0
    assert rig.bridge.latched_reason() == ""
    assert rig.all_in(PowerState.OPERATION_ENABLED)


def test_bridge_killed_drives_react_and_send_emcy(rig_factory: Callable[..., Rig]) -> None:
    """No more SYNC, RPDO or heartbeat: each drive applies 0x6007 (fault) and sends an EMCY."""
    rig = _enabled(rig_factory())
    emcy: list[can.Message] = []
    listener = threading.Thread(target=_collect, args=(rig.injector, emcy, 2.0), daemon=True)
    listener.start()
    rig.bridge.stop()
    listener.join()
    codes = {(m.arbitration_id - 0x80, int.from_bytes(m.data[:2], "little")) for m in emcy}
    assert {node for node, _ in codes} == set(NODE_IDS), codes
    assert all(code in (0x8130, 0x8250, 0x8700) for _, code in codes), codes
    wait_until(
        lambda: all(rig.rack.power_state(j).name == "FAULT" for j in JOINTS), "drives faulted", 2.0
    )


def test_recover_starts_drives_that_a_communication_error_took_to_pre_operational(
    rig_factory: Callable[..., Rig],
) -> None:
    """0x1029 = 0 (CiA 301's default): the drives fall back to PRE-OPERATIONAL; ~/recover works.

    The bridge's cycle stops, every drive reacts (fault, EMCY) and leaves OPERATIONAL; the cycle
    starts again, the drives are stale (no PDOs in PRE-OPERATIONAL), and `recover()` (NMT start
    with the fault reset) brings them back to where `enable` walks them to operation enabled.
    """
    rig = _enabled(rig_factory())
    rig.bridge.stop()
    wait_until(
        lambda: all(rig.rack.nmt_state(j) == "PRE-OPERATIONAL" for j in JOINTS),
        "every drive in PRE-OPERATIONAL after its communication error",
        5.0,
    )
    rig.bridge.start()
    wait_until(lambda: "stale drive" in rig.bridge.latched_reason(), "the drives stale", 5.0)
    rig.bridge.recover()
    wait_until(
        lambda: all(rig.rack.nmt_state(j) == "OPERATIONAL" for j in JOINTS),
        "every drive OPERATIONAL again after recover",
        5.0,
    )
    reset = (PowerState.SWITCH_ON_DISABLED, PowerState.READY_TO_SWITCH_ON)
    wait_until(lambda: all(v in reset for v in rig.states().values()), "faults reset", 5.0)
    _enabled(rig)
    assert rig.bridge.latched_reason() == ""


def _collect(bus: can.BusABC, out: list[can.Message], duration_s: float) -> None:
    """EMCY frames (0x81..0xFF) seen on `bus` for `duration_s`."""
    end = time.monotonic() + duration_s
    while (left := end - time.monotonic()) > 0:
        msg = bus.recv(timeout=left)
        if msg is not None and 0x81 <= msg.arbitration_id <= 0xFF and len(msg.data) == 8:
            out.append(msg)


def test_one_drive_silenced_stops_every_axis(rig_factory: Callable[..., Rig]) -> None:
    rig = _enabled(rig_factory(stale_timeout_s=0.05))
    rig.injector.send(can.Message(arbitration_id=0x000, data=[0x02, 3], is_extended_id=False))
    wait_until(lambda: "c_arc" in rig.bridge.latched_reason(), "c_arc reported stale", 2.0)
    others = ("l_arm", "pivot", "lift")
    wait_until(
        lambda: all(
            rig.bridge.axis_state(j).power_state is PowerState.SWITCH_ON_DISABLED for j in others
        ),
        "the other axes quick-stopped",
        2.0,
    )
    assert "not enabled" in rig.bridge.enable(True)


def test_emcy_latches_until_recover(rig_factory: Callable[..., Rig]) -> None:
    rig = _enabled(rig_factory())
    rig.injector.send(
        can.Message(
            arbitration_id=0x80 + 2, data=[0x30, 0x55, 0x01, 0, 0, 0, 0, 0], is_extended_id=False
        )
    )
    wait_until(lambda: rig.bridge.emcy_codes()["pivot"] == 0x5530, "EMCY latched", 2.0)
    wait_until(lambda: rig.all_in(PowerState.SWITCH_ON_DISABLED), "every axis stopped", 2.0)
    assert "EMCY pivot 0x5530" in rig.bridge.enable(True)
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 25, "25 cycles later", 5.0)
    assert rig.bridge.emcy_codes()["pivot"] == 0x5530  # still latched
    rig.bridge.recover()
    assert rig.bridge.latched_reason() == ""
    _enabled(rig)


def test_bus_off_stops_cyclic_transmission(rig_factory: Callable[..., Rig]) -> None:
    rig = _enabled(rig_factory())
    rig.injector.send(
        can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, dlc=8, data=bytes(8))
    )
    wait_until(lambda: "bus-off" in rig.bridge.latched_reason(), "bus-off latched", 2.0)
    sent = rig.bridge.counters.frames_sent
    cycles = rig.bridge.counters.cycles
    wait_until(lambda: rig.rack.power_state("pivot").name == "FAULT", "SYNC loss in the drive", 2.0)
    assert rig.bridge.counters.frames_sent == sent  # not one frame more
    assert rig.bridge.counters.cycles == cycles
    assert rig.bridge.counters.error_frames == 1


def test_send_failures_are_counted_and_halt_the_axes(rig_factory: Callable[..., Rig]) -> None:
    rig = _enabled(rig_factory(max_send_failures=5))
    rig.currents_a = [0.0, 2.0, 0.0, 0.0]
    wait_until(lambda: rig.bridge.axis_state("pivot").current_a > 1.5, "2 A flowing", 5.0)
    bus = rig.network.bus
    assert bus is not None
    real_send = bus.send
    failures = {"left": 5}

    def flaky_send(msg: can.Message, timeout: float | None = None) -> None:
        if failures["left"] > 0:  # where a CAN controller's full buffer is reported
            failures["left"] -= 1
            raise can.CanOperationError("Transmit buffer full")
        real_send(msg, timeout)

    bus.send = flaky_send  # type: ignore[method-assign]
    wait_until(lambda: rig.bridge.counters.send_failures == 5, "5 failures counted", 2.0)
    assert "5 send failures in a row" in rig.bridge.latched_reason()
    wait_until(lambda: abs(rig.bridge.axis_state("pivot").current_a) < 0.1, "halted: 0 A", 2.0)
    assert math.isfinite(rig.bridge.axis_state("pivot").position)


def test_settle_heap_takes_the_start_up_objects_out_of_the_collectors_sight() -> None:
    """What every cyclic process calls before its loop.

    A later full collection walks only the objects made since (the others cost 70-120 ms per
    collection on this machine).
    """
    import gc

    from lca_sim.runtime import settle_heap

    tracked_before = len(gc.get_objects())
    try:
        frozen = settle_heap()
        assert frozen >= 0.5 * tracked_before  # the bulk of the process is now frozen
        assert len(gc.get_objects()) < 0.1 * tracked_before
    finally:
        gc.unfreeze()  # the rest of the test session collects as usual


# --- what the drives report beyond CiA 402 ------------------------------------------------


def _first_frame(bus: can.BusABC, cob_id: int, timeout_s: float) -> bytes:
    """The data of the first frame with `cob_id` in `bus`'s queue (it holds every frame)."""
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        msg = bus.recv(timeout=left)
        if msg is not None and msg.arbitration_id == cob_id:
            return bytes(msg.data)
    pytest.fail(f"no frame 0x{cob_id:03X} within {timeout_s} s")


def test_stopped_axis_reports_nan_efficiency(rig_factory: Callable[..., Rig]) -> None:
    """0xFFFF in 0x2012 / 0x2013 (eq. 10 idle: the axis is stopped) decodes to NaN, not 65.535."""
    rig = rig_factory()
    assert _first_frame(rig.injector, 0x382, 5.0)[2:6] == b"\xff\xff\xff\xff"  # pivot's TPDO3
    wait_until(
        lambda: all(rig.bridge.axis_state(j).drive_state >= 0 for j in JOINTS),
        "every drive's TPDO3 decoded",
        5.0,
    )
    for joint in JOINTS:
        state = rig.bridge.axis_state(joint)
        assert state.motion_state == 0
        assert math.isnan(state.eta_m), (joint, state.eta_m)
        assert math.isnan(state.eta_l), (joint, state.eta_l)
    assert rig.bridge.has_drive_state()


def test_bridge_decodes_load_friction_and_voltage(rig_factory: Callable[..., Rig]) -> None:
    """TPDO4: the pivot's gravity load at rest as the plant has it, then 2 A through 1 ohm."""
    rig = rig_factory()
    extras = {"load_torque_nm", "friction_torque_nm", "voltage_v"}
    assert extras <= rig.bridge.decoded_fields()
    wait_until(
        lambda: all(math.isfinite(rig.bridge.axis_state(j).voltage_v) for j in JOINTS),
        "every drive's TPDO4 decoded",
        5.0,
    )
    pivot = JOINTS.index("pivot")
    with rig.rack._lock:  # at rest, no current: the plant's signals stand still
        load_nm = float(rig.rack.simulator.signals.values["load_torque_nm"][pivot])
    state = rig.bridge.axis_state("pivot")
    assert load_nm > 0.1  # gravity on the pivot at 35 deg, seen at the motor through 600:1
    assert state.load_torque_nm == pytest.approx(load_nm, abs=0.6e-3)  # 1.2 mN m quantum
    assert (state.friction_torque_nm, state.voltage_v) == (0.0, 0.0)
    rig.currents_a = [0.0, 2.0, 0.0, 0.0]
    _enabled(rig)
    wait_until(
        lambda: abs(rig.bridge.axis_state("pivot").voltage_v - 2.0) < 0.02,
        "the pivot's amplifier at 2 V (2 A, 1 ohm, standing still)",
        5.0,
    )
    held = rig.bridge.axis_state("pivot")
    assert held.motion_state == 0
    assert held.current_a == pytest.approx(2.0, abs=0.01)


def _unmap_drive_chain(channel: str) -> None:
    """Disable TPDO3 and TPDO4 on every drive over SDO: what a real CiA 402 drive maps is left."""
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    network.connect()
    try:
        for node_id in NODE_IDS:
            node = canopen.RemoteNode(node_id, str(EDS))
            network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 2.0
            node.sdo[0x1802][1].raw = 0x80000380 + node_id
            node.sdo[0x1803][1].raw = 0x80000480 + node_id
    finally:
        network.disconnect()


def test_a_drive_mapping_only_cia402_objects_is_accepted(
    rig_factory: Callable[..., Rig],
) -> None:
    """Statusword, position, velocity, current only: the bridge runs; the rest stays unknown."""
    rig = _enabled(rig_factory(before_init=_unmap_drive_chain))
    assert not rig.bridge.has_drive_state()
    assert rig.bridge.decoded_fields() == {
        "statusword",
        "position",
        "motor_position_rad",
        "velocity",
        "motor_velocity_rad_s",
        "current_a",
    }
    rig.currents_a = [0.0, 2.0, 0.0, 0.0]
    wait_until(
        lambda: abs(rig.bridge.axis_state("pivot").current_a - 2.0) < 0.05,
        "pivot current at 2 A",
        5.0,
    )
    state = rig.bridge.axis_state("pivot")
    assert (state.drive_state, state.motion_state) == (-1, 0)
    unknown = (state.eta_m, state.eta_l, state.load_torque_nm, state.friction_torque_nm)
    assert all(math.isnan(v) for v in (*unknown, state.voltage_v))
    assert rig.bridge.counters.bad_pdos == 0


def test_compiled_tpdo_decoder_agrees_with_the_codec() -> None:
    """The bridge's per-mapping decoder gives the codec's values, NaN for 0xFFFF, skips bytes."""
    import struct

    from lca_sim.canbus.master_pdo import Target, compile_apply
    from lca_sim.canbus.master_state import AxisState
    from lca_sim.cia402 import codec

    units = codec.DriveUnits(rated_torque_nm=1.2, rated_current_a=10.0, increments_per_rev=65536)
    targets = [
        Target(("statusword",)),
        Target(("motor_position_rad", "position"), codec.position(units).decoder()),
        Target(("eta_m",), codec.EFFICIENCY.decoder()),
        Target(("voltage_v",), codec.VOLTAGE.decoder()),
    ]
    # statusword, position, 2 bytes of an object the bridge skips, eta_m, voltage
    frame = struct.pack("<Hi2xHh", 0x0237, -3823151, 0xFFFF, -1234)
    apply = compile_apply(targets, struct.Struct("<Hi2xHh").unpack_from, 600.0)
    state = AxisState()
    apply(state, bytearray(frame))
    assert state.statusword == 0x0237
    assert state.motor_position_rad == codec.position(units).decode(-3823151)
    assert state.position == pytest.approx(-0.6109, abs=1e-6)  # 35 deg below, through 600:1
    assert math.isnan(state.eta_m)
    assert state.voltage_v == pytest.approx(-12.34)
    assert math.isnan(state.load_torque_nm)  # not mapped: unknown
    with pytest.raises(ValueError, match="not AxisState fields"):
        compile_apply([Target(("__class__",))], struct.Struct("<H").unpack_from, 1.0)


def test_an_advisory_emcy_is_reported_with_its_text_and_the_axes_go_on(
    rig_factory: Callable[..., Rig],
) -> None:
    """EMCY 0x8210 (an RPDO of the wrong length, CiA 301) is counted and kept, not latched."""
    rig = _enabled(rig_factory())
    frame = can.Message(
        arbitration_id=0x80 + 2, data=[0x10, 0x82, 0x10, 0, 0, 0, 0, 0], is_extended_id=False
    )
    rig.injector.send(frame)
    rig.injector.send(frame)
    wait_until(lambda: rig.bridge.advisory_emcy()["pivot"] == (0x8210, 2), "two advisories", 2.0)
    assert rig.bridge.emcy_codes()["pivot"] == 0
    assert rig.bridge.latched_reason() == ""
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 25, "25 cycles later", 5.0)
    assert rig.all_in(PowerState.OPERATION_ENABLED)
    assert emcy.describe(0x8210) == "0x8210 PDO not processed due to length error"
    rig.bridge.recover()
    assert rig.bridge.advisory_emcy()["pivot"] == (0, 0)


def test_a_latched_emcy_is_named_in_words() -> None:
    """Each code the rack sends has its own text; others fall back to their CiA 301 class."""
    sent = {name: getattr(device, name) for name in dir(device) if name.startswith("EMCY_")}
    assert len(sent) >= 10
    for name, code in sent.items():
        assert code in emcy.SPECIFIC or code in emcy.LCA_DRIVE_SPECIFIC, name
    assert emcy.describe(0x8130) == "0x8130 life guard or heartbeat error"
    assert emcy.describe(0x8F01) == "0x8F01 monitoring error"
    assert emcy.describe(0x2391) == "0x2391 current error"
    # A vendor's 0xFF01 is not ours: only lca_hil's drive gets lca_hil's text for it.
    assert emcy.describe(0xFF01) == "0xFF01 device specific error"
    assert "0x6007 reaction" in emcy.describe(0xFF01, lca_drive=True)
    assert "second SYNC producer" in emcy.describe(0x8100, lca_drive=True)
    assert emcy.is_advisory(device.EMCY_PROCESS_STALL, lca_drive=True)
    assert not emcy.is_advisory(device.EMCY_PROCESS_STALL)
    assert not emcy.is_advisory(device.EMCY_SYNC_TOO_FAST, lca_drive=True)


def _map_for_1khz(channel: str) -> None:
    """Remap every drive over SDO (CiA 301 7.5.2.35-38: disable, sub 0 to 0, entries, enable).

    RPDO1 the target torque alone (each cycle), RPDO2 the controlword; TPDO1 position and
    velocity after every SYNC, TPDO2 the statusword and current on change (type 255).
    """
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    network.connect()

    def remap(node: canopen.RemoteNode, comm: int, cob_id: int, entries: list[int]) -> None:
        node.sdo[comm][1].raw = cob_id | 0x80000000
        mapping = node.sdo[comm + 0x200]
        mapping[0].raw = 0
        for k, entry in enumerate(entries, start=1):
            mapping[k].raw = entry
        mapping[0].raw = len(entries)
        node.sdo[comm][1].raw = cob_id

    try:
        for node_id in NODE_IDS:
            node = canopen.RemoteNode(node_id, str(EDS))
            network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 2.0
            remap(node, 0x1400, 0x200 + node_id, [0x60710010])
            remap(node, 0x1401, 0x300 + node_id, [0x60400010])
            remap(node, 0x1800, 0x40000180 + node_id, [0x60640020, 0x606C0020])
            node.sdo[0x1801][1].raw = 0xC0000280 + node_id
            node.sdo[0x1801][2].raw = 255
            remap(node, 0x1801, 0x40000280 + node_id, [0x60410010, 0x60780010])
    finally:
        network.disconnect()


def test_a_drive_with_the_controlword_in_its_own_rpdo_runs_and_gets_it_on_change(
    rig_factory: Callable[..., Rig],
) -> None:
    """Torque each cycle, controlword when it changes (and every 100 cycles); TPDO1 completes."""
    seen: list[int] = []
    rig = rig_factory(before_init=_map_for_1khz, pdo_layout="drive")
    n = len(rig.snapshots)
    _enabled(rig)
    rig.currents_a = [0.0, 2.0, 0.0, 0.0]
    wait_until(
        lambda: abs(rig.bridge.axis_state("pivot").current_a - 2.0) < 0.05,
        "pivot current at 2 A through the torque-only RPDO1",
        5.0,
    )
    watcher = can.Bus(interface="virtual", channel=rig.channel)  # from here on
    try:
        cycles = rig.bridge.counters.cycles
        deadline = time.monotonic() + 10.0
        while rig.bridge.counters.cycles < cycles + 200 and time.monotonic() < deadline:
            msg = watcher.recv(0.01)
            if msg is not None and msg.arbitration_id == 0x300 + 2:
                seen.append(int.from_bytes(msg.data[:2], "little"))
        sent = rig.bridge.counters.cycles - cycles
        assert sent >= 200
        # Enabled: the controlword stands still, so only the refresh every 100 cycles goes out.
        assert 1 <= len(seen) <= sent // 100 + 1, (len(seen), sent)
        assert all(cw & 0x000F == 0x000F for cw in seen)  # operation enabled, not halted
        assert len(rig.snapshots) - n > 100  # complete cycles from TPDO1 alone
        assert rig.bridge.counters.bad_pdos == 0
    finally:
        watcher.shutdown()


def test_the_compact_layout_sends_one_frame_per_axis_and_direction_each_cycle(
    rig_factory: Callable[..., Rig],
) -> None:
    """init() maps the drives for a fast cycle: per cycle SYNC, RPDO1 and TPDO1 per axis.

    Statusword and current (TPDO2) and the drive-chain extras (TPDO4) come every n-th SYNC,
    n = cycle_hz / slow_tpdo_rate_hz = 250 / 50 = 5; the controlword (RPDO2) on change and
    every 100 cycles. Counted on the bus over 250 cycles of an enabled, driven rig.
    """
    rig = rig_factory(slow_tpdo_rate_hz=50.0)
    assert rig.bridge.params.slow_tpdo_every == 5
    _enabled(rig)
    rig.currents_a = [0.0, 2.0, 0.0, 0.0]
    wait_until(lambda: abs(rig.bridge.axis_state("pivot").current_a - 2.0) < 0.05, "2 A", 5.0)
    watcher = can.Bus(interface="virtual", channel=rig.channel)
    counts: dict[int, int] = {}
    try:
        cycles = rig.bridge.counters.cycles
        deadline = time.monotonic() + 10.0
        while rig.bridge.counters.cycles < cycles + 250 and time.monotonic() < deadline:
            msg = watcher.recv(0.01)
            if msg is not None:
                counts[msg.arbitration_id] = counts.get(msg.arbitration_id, 0) + 1
        n = rig.bridge.counters.cycles - cycles
    finally:
        watcher.shutdown()
    assert n >= 250
    for node_id in NODE_IDS:
        assert abs(counts.get(0x180 + node_id, 0) - n) <= 2  # TPDO1: position, velocity
        assert abs(counts.get(0x200 + node_id, 0) - n) <= 2  # RPDO1: target torque
        assert abs(counts.get(0x280 + node_id, 0) - n / 5) <= 2  # TPDO2: statusword, current
        assert abs(counts.get(0x480 + node_id, 0) - n / 5) <= 2  # TPDO4: extras
        assert counts.get(0x300 + node_id, 0) <= n // 100 + 1  # RPDO2: controlword refresh
    assert abs(counts.get(0x80, 0) - n) <= 2  # SYNC
    state = rig.bridge.axis_state("pivot")
    assert state.statusword & 0x6F == 0x27  # operation enabled, read from TPDO2
    assert abs(state.current_a - 2.0) < 0.05
    assert len(rig.snapshots) > n  # a complete cycle from TPDO1 alone


def test_the_compact_layout_fits_1_mbit_at_1_khz_with_worst_case_stuffing() -> None:
    """Four axes at 1 kHz: the budget of every frame the compact layout puts on the bus.

    Per cycle: SYNC, four RPDO1 (2 bytes) and four TPDO1 (8 bytes); every 20th SYNC four
    TPDO2 (4) and four TPDO4 (6); TPDO3 (6, event) at its inhibit-time maximum, 100/s per
    axis; the controlword refresh every 100 cycles; five heartbeats every 100 ms. Worst-case
    stuffing (CAN 2.0A: 47 + 8 DLC + floor((34 + 8 DLC - 1) / 4) bits per frame) stays under
    1 Mbit/s: 989 bits per 1 ms cycle. The old layout (13 frames a cycle) needed 1401.
    """
    from lca_sim.canbus.master_pdo import CONTROLWORD_REFRESH_CYCLES, EVENT_INHIBIT_100US
    from lca_sim.cia402 import bus_load
    from lca_sim.cia402 import objects as od

    cycle_hz = 1000.0
    every = bridge_params(cycle_hz=cycle_hz).slow_tpdo_every
    assert every == 20
    axes = len(JOINTS)

    def size(number: int) -> int:
        pdo = next(p for p in od.DEFAULT_PDOS if not p.receive and p.number == number)
        return sum(od.entry(i).data_type.bits for i in pdo.objects) // 8

    event_per_cycle = 1.0 / (EVENT_INHIBIT_100US * 1e-4 * cycle_hz)
    heartbeats_per_cycle = (axes + 1) / (0.1 * cycle_hz)

    def per_cycle(bits: Callable[[int], int]) -> float:
        return (
            bits(0)
            + axes * (bits(2) + bits(8))
            + axes * (bits(4) + bits(size(4))) / every
            + axes * bits(size(3)) * event_per_cycle
            + axes * bits(2) / CONTROLWORD_REFRESH_CYCLES
            + bits(1) * heartbeats_per_cycle
        )

    worst = bus_load.bus_load_pct(per_cycle(bus_load.frame_bits) * cycle_hz, 1e6)
    nominal = bus_load.bus_load_pct(per_cycle(bus_load.frame_bits_nominal) * cycle_hz, 1e6)
    assert worst == pytest.approx(98.925)
    assert worst < 100.0
    assert nominal == pytest.approx(82.107)


def test_csv_the_drive_closes_the_velocity_loop_on_the_target_velocity(
    rig_factory: Callable[..., Rig],
) -> None:
    """Pivot in CSV (mode 9, 0x60FF), the others in CST: the pivot holds the commanded speed.

    The drive's velocity PI (lca_control's, the paper's gains) runs at the bus cycle on the
    joint velocity; the bridge sends the joint velocity command as 0x60FF (motor increments/s).
    Against gravity at 35 deg, the pivot holds 0.02 rad/s within 5 % while the CST axes
    stay at zero current.
    """
    rig = rig_factory(modes=("cst", "csv", "cst", "cst"))
    assert rig.rack.node("pivot").sdo[0x6060].raw == 9  # type: ignore[union-attr]
    assert rig.rack.node("l_arm").sdo[0x6060].raw == 10  # type: ignore[union-attr]
    target_rad_s = 0.02
    assert rig.bridge.set_velocities([0.0, target_rad_s, 0.0, 0.0]) is None
    _enabled(rig)
    wait_until(
        lambda: abs(rig.bridge.axis_state("pivot").velocity - target_rad_s) < 2e-4,
        "the pivot at its commanded speed",
        10.0,
    )
    first = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= first + 50, "0.2 s more at 250 Hz", 5.0)
    speeds = [s.axes[1].velocity for s in rig.snapshots[first : first + 50]]
    assert max(abs(v - target_rad_s) for v in speeds) < 0.05 * target_rad_s
    assert rig.bridge.axis_state("pivot").statusword & 0x1000  # bit 12: follows the target
    assert all(abs(rig.bridge.axis_state(j).current_a) < 0.05 for j in ("l_arm", "c_arc", "lift"))
    rig.bridge.set_velocities([0.0, 0.0, 0.0, 0.0])
    wait_until(lambda: abs(rig.bridge.axis_state("pivot").velocity) < 1e-3, "stopped", 10.0)


def test_csv_refused_when_the_drive_maps_no_target_velocity(
    rig_factory: Callable[..., Rig],
) -> None:
    """With the drive's own mapping (no 0x60FF in an RPDO) a CSV axis is one clear error."""
    with pytest.raises(BridgeError, match="target 0x60FF of mode 9"):
        rig_factory(modes=("cst", "csv", "cst", "cst"), pdo_layout="drive")


def test_a_drive_that_restarts_behind_the_masters_back_stops_the_axes_until_init(
    rig_factory: Callable[..., Rig],
) -> None:
    """NMT reset node from elsewhere: the boot-up is seen, the axes stop, ~/init clears it.

    After a reset the drive is back to its boot mapping (CiA 301), which no longer matches
    what init() configured; carrying on would send it frames it does not expect.
    """
    rig = _enabled(rig_factory())
    rig.injector.send(can.Message(arbitration_id=0x000, data=[0x81, 2], is_extended_id=False))
    wait_until(lambda: "restarted (boot-up)" in rig.bridge.latched_reason(), "restart seen", 2.0)
    assert "drive pivot restarted" in rig.bridge.latched_reason()
    assert rig.bridge.counters.drive_restarts == 1
    rig.bridge.recover()
    assert "restarted" in rig.bridge.latched_reason()  # recover alone is not enough
    assert "not enabled" in rig.bridge.enable(True)
    rig.bridge.stop()
    rig.bridge.init()
    rig.bridge.start()
    rig.bridge.recover()
    wait_until(lambda: rig.bridge.latched_reason() == "", "latches cleared after init", 5.0)
    reset = (PowerState.SWITCH_ON_DISABLED, PowerState.READY_TO_SWITCH_ON)
    wait_until(lambda: all(v in reset for v in rig.states().values()), "faults reset", 5.0)
    _enabled(rig)


# --- which frames the master decodes itself, and which reach canopen ----------------------


def test_a_tpdo_moved_to_another_cob_id_before_init_again_is_decoded_there(
    rig_factory: Callable[..., Rig],
) -> None:
    """The master hands a TPDO to its decoder by the COB-ID that the last init() bound.

    The pivot's TPDO1 (after every SYNC: a cycle is complete only with it) moves from 0x182
    to 0x192 over SDO (CiA 301 7.5.2.35: disabled, then enabled with the new COB-ID); init()
    reads it there, and complete cycles go on only if its frames on 0x192 are decoded.
    """
    rig = rig_factory()
    wait_until(lambda: len(rig.snapshots) >= 10, "10 complete cycles", 5.0)
    rig.bridge.stop()
    rig.bridge.sdo_write("pivot", 0x1800, 1, 0x80000000 | 0x192)
    rig.bridge.sdo_write("pivot", 0x1800, 1, 0x192)
    rig.bridge.init()
    rig.bridge.start()
    complete = rig.bridge.counters.complete_cycles
    wait_until(lambda: rig.bridge.counters.complete_cycles >= complete + 25, "25 more cycles", 5.0)
    cob_id = rig.bridge.sdo_read("pivot", 0x1800, 1)
    assert isinstance(cob_id, int) and cob_id & 0x7FF == 0x192  # bit 30: no RTR
    assert rig.bridge.counters.bad_pdos == 0


def test_frames_on_a_tpdo_cob_id_reach_every_canopen_subscriber_and_the_rest_reach_canopen(
    rig_factory: Callable[..., Rig],
) -> None:
    """The master decodes TPDOs itself; every other frame still reaches canopen.

    A callback another user subscribed on a TPDO's COB-ID is called too; a remote frame there
    is not a TPDO (canopen ignores it); SDO answers and heartbeats reach canopen, whose node
    scanner still sees every drive.
    """
    rig = rig_factory()
    seen: list[bytes] = []
    rig.network.subscribe(0x182, lambda _id, data, _t: seen.append(bytes(data)))
    wait_until(lambda: len(seen) >= 5, "5 pivot TPDO1 frames at the other subscriber", 5.0)
    assert all(len(data) == 8 for data in seen)  # position and velocity
    received = rig.bridge.counters.frames_received
    rig.injector.send(can.Message(arbitration_id=0x182, is_remote_frame=True, dlc=8))
    wait_until(
        lambda: rig.bridge.counters.frames_received > received + 20, "more frames counted", 5.0
    )
    assert rig.bridge.counters.bad_pdos == 0  # the remote frame was not decoded as a TPDO
    assert rig.bridge.sdo_read("pivot", 0x6060, 0) == 10  # an SDO answer reached canopen
    assert set(rig.network.scanner.nodes) >= set(NODE_IDS)


def test_over_lca_remote_each_cycle_is_sent_in_one_batch() -> None:
    """The cycle's frames (RPDOs, SYNC, heartbeat) go through the relay in one write per cycle.

    The master sends past canopen's `send_message`; over lca_remote the bus's `batch()` must
    still hold every frame of a cycle (one write), as `remote.batched_sends` gives it.
    """
    server = RelayServer(port=0)
    relay = threading.Thread(target=server.serve, kwargs={"poll_s": 0.02}, daemon=True)
    relay.start()
    rack_bus = can.Bus(interface="lca_remote", channel=server.url)
    rack = VirtualDriveRack(rack_bus, load_rack_config(None))
    bus = can.Bus(interface="lca_remote", channel=server.url)
    assert isinstance(bus, RemoteTransportBus)
    network = canopen.Network(bus)
    try:
        rack.start(settle=False)
        network.connect()
        bridge = Cia402Master(network, bridge_params(), EDS)
        bridge.init()
        open_batches: list[int] = []  # batches open now (the cycle's thread is this one)
        batches = 0
        in_batch: list[bool] = []
        real_batch, real_send = bus.batch, bus.send

        @contextlib.contextmanager
        def counted_batch() -> Iterator[None]:
            nonlocal batches
            batches += 1
            with real_batch():
                open_batches.append(1)
                try:
                    yield
                finally:
                    open_batches.pop()

        def watched_send(msg: can.Message, timeout: float | None = None) -> None:
            in_batch.append(bool(open_batches))
            real_send(msg, timeout)

        bus.batch = counted_batch  # type: ignore[method-assign]
        bus.send = watched_send  # type: ignore[method-assign]
        for _ in range(10):
            bridge.cycle(time.monotonic())
        assert batches == 10
        assert len(in_batch) >= 10 * 5 and all(in_batch)  # 4 RPDOs and the SYNC at least
        assert bridge.counters.frames_sent >= len(in_batch)
    finally:
        network.disconnect()
        rack.stop()
        rack_bus.shutdown()
        server.stop()
        relay.join(5.0)


def test_init_again_decodes_each_tpdo_and_counts_each_emcy_once(
    rig_factory: Callable[..., Rig],
) -> None:
    """A second init() binds its decoders and EMCY consumers in place of the first's.

    The pivot's statuswords per complete cycle are the same before and after (the first
    init's decoders left subscribed decoded every TPDO twice, counting its statusword twice),
    and one advisory EMCY after it is counted once (not once per init).
    """
    rig = rig_factory()

    def statuswords_per_cycle(cycles: int) -> float:
        pivot = rig.bridge._axes[1]  # the pivot
        words, complete = pivot.statuswords_received, rig.bridge.counters.complete_cycles
        wait_until(
            lambda: rig.bridge.counters.complete_cycles >= complete + cycles,
            f"{cycles} more cycles",
            5.0,
        )
        done = rig.bridge.counters.complete_cycles - complete
        return (pivot.statuswords_received - words) / done

    wait_until(lambda: len(rig.snapshots) >= 10, "10 complete cycles", 5.0)
    before = statuswords_per_cycle(100)
    rig.bridge.stop()
    rig.bridge.init()
    rig.bridge.start()
    after = statuswords_per_cycle(100)
    assert before > 0.0
    assert after == pytest.approx(before, rel=0.1), (before, after)
    emcy = rig.bridge.counters.emcy_received
    advisory = can.Message(  # 0x8210 PDO not processed (length): advisory, the axes go on
        arbitration_id=0x80 + NODE_IDS[1],
        data=[0x10, 0x82, 0x11, 0, 0, 0, 0, 0],
        is_extended_id=False,
    )
    rig.injector.send(advisory)
    wait_until(lambda: rig.bridge.counters.emcy_received > emcy, "the EMCY counted", 2.0)
    n = len(rig.snapshots)
    wait_until(lambda: len(rig.snapshots) >= n + 10, "10 cycles later", 5.0)
    assert rig.bridge.counters.emcy_received == emcy + 1
