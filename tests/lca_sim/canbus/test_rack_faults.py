"""Fault injection in the virtual drive rack (issue 16): object 0x2030 and the `faults:` schedule.

Each kind is injected at run time by an SDO write of the bridge's master (`Cia402Master`, the
CAN bridge's, on python-can's in-process `virtual` bus) and checked by what a master sees on
the bus: lost TPDOs, a silent heartbeat, an EMCY with its code (latched by the bridge), a
drive fault (statusword FAULT, 0x603F, no torque, a fault reset that works once the cause is
gone), bus-off (no frame at all from that node, then recovery). A scheduled run is driven SYNC
by SYNC from the test, so its times are exact; so is the run that shows that a rack without
faults sends the frames it sent before fault injection existed. Nothing sleeps a fixed time.
"""

from __future__ import annotations

import hashlib
import itertools
import os
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
import yaml
from support import CONFIG, RackAndMaster, bridge_params, wait_until

from lca_sim import RobotParams
from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.master_state import Snapshot
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import PowerState
from lca_sim.cli.virtual_drive import main
from lca_sim.config.rack import RackConfig, load_rack_config
from lca_sim.errors import ConfigError

JOINTS = ("l_arm", "pivot", "c_arc", "lift")
NODE_IDS = (1, 2, 3, 4)
PIVOT = 2
FAULTS = od.FAULT_INJECTION
_channels = itertools.count()


# --- a rack, the bridge's master and a frame recorder on one virtual channel ------------------


class Recorder(can.Listener):
    """Every frame on the channel, in bus order (a listener of its own bus instance)."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[tuple[int, bytes]] = []
        self._lock = threading.Lock()
        self._notifier = can.Notifier(self.bus, [self], timeout=0.05)

    def on_message_received(self, msg: can.Message) -> None:
        """Keep the frame."""
        with self._lock:
            self.frames.append((msg.arbitration_id, bytes(msg.data)))

    def mark(self) -> int:
        """Where the next frame will be."""
        with self._lock:
            return len(self.frames)

    def since(self, mark: int) -> list[tuple[int, bytes]]:
        """The frames after `mark`."""
        with self._lock:
            return self.frames[mark:]

    def count(self, cob_id: int, since: int = 0) -> int:
        """How many frames with this COB-ID came after `since`."""
        return sum(1 for c, _ in self.since(since) if c == cob_id)

    def close(self) -> None:
        """Stop recording."""
        self._notifier.stop()
        self.bus.shutdown()


@dataclass
class Rig(RackAndMaster):
    """A rack, the bridge's master (initialised and cycling), and a recorder of every frame."""

    recorder: Recorder
    currents_a: list[float] = field(default_factory=lambda: [0.0] * 4)
    complete: int = 0  # complete cycles (snapshots) the bridge handed on

    def node_frames(self, node_id: int, since: int) -> list[tuple[int, bytes]]:
        """Frames node `node_id` sent after `since` (by the CiA 301 pre-defined COB-IDs)."""
        own = {base + node_id for base in (0x80, 0x180, 0x280, 0x380, 0x480, 0x580, 0x700)}
        return [f for f in self.recorder.since(since) if f[0] in own]

    def enable(self) -> None:
        """Every drive to operation enabled, the controller's currents answering each state."""
        self.bridge.set_currents(self.currents_a)
        self.enable_all()

    def after_syncs(self, count: int) -> None:
        """Wait until the rack has processed `count` more SYNCs."""
        done = self.rack.counters.syncs + count
        wait_until(lambda: self.rack.counters.syncs >= done, f"{count} more SYNCs", 10.0)


@pytest.fixture
def rig(default_robot: RobotParams, rack_and_master: Callable[..., RackAndMaster]) -> Iterator[Rig]:
    """The shipped rack and the bridge's master, initialised and cycling at 250 Hz."""
    recorder = Recorder(f"test_rack_faults_{os.getpid()}_{next(_channels)}")
    try:
        holder: list[Rig] = []

        def on_state(snapshot: Snapshot) -> None:
            holder[0].complete += 1
            holder[0].bridge.set_currents(holder[0].currents_a)  # a controller answering

        built = rack_and_master(
            recorder.channel,
            bridge_params(default_robot),
            on_state=on_state,
            robot=default_robot,
        )
        holder.append(Rig(built.channel, built.rack, built.network, built.bridge, recorder))
        built.bridge.init()
        built.bridge.start()
        yield holder[0]
    finally:
        recorder.close()


class TpdoCount(can.Listener):
    """What the master's network receives: TPDO frames per COB-ID."""

    def __init__(self) -> None:
        self.counts: dict[int, int] = {}

    def on_message_received(self, msg: can.Message) -> None:
        """Count the frame."""
        self.counts[msg.arbitration_id] = self.counts.get(msg.arbitration_id, 0) + 1

    def of(self, cob_id: int) -> int:
        """Frames with this COB-ID so far (python-can calls a listener itself: no __call__)."""
        return self.counts.get(cob_id, 0)


def _remote(network: canopen.Network, node_id: int) -> canopen.RemoteNode:
    """The master's view of a drive: its NMT heartbeat consumer and EMCY consumer."""
    node = network[node_id]
    assert isinstance(node, canopen.RemoteNode)
    return node


def _count_on(network: canopen.Network) -> TpdoCount:
    counter = TpdoCount()
    assert network.notifier is not None
    network.notifier.add_listener(counter)
    return counter


# --- each kind, injected by SDO at run time ---------------------------------------------------


def test_lost_tpdo_stops_that_tpdo_of_that_axis_only(rig: Rig) -> None:
    """0x2030 sub 1 = 0x01: pivot's TPDO1 stops, its TPDO2 and the other axes' TPDO1 go on.

    The bridge completes no cycle without pivot's position (the cycle's TPDO1), and with every
    TPDO lost while enabled it latches the drive as stale (its /diagnostics ERROR).
    """
    seen = _count_on(rig.network).of
    rig.after_syncs(10)
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_LOST_TPDOS, 0x01)
    pivot_tpdo1, pivot_tpdo2, l_arm = seen(0x182), seen(0x282), seen(0x181)
    complete = rig.complete
    wait_until(lambda: seen(0x181) >= l_arm + 50, "50 more l_arm TPDO1")
    assert seen(0x182) == pivot_tpdo1  # not one more
    assert seen(0x282) > pivot_tpdo2  # statusword and current still come
    assert rig.complete <= complete + 1  # a cycle in flight at the write, then none
    assert rig.rack.active_faults["pivot"] == {"lost_tpdo": 1}
    assert rig.bridge.sdo_read("pivot", FAULTS, od.FAULT_LOST_TPDOS) == 0x01
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_LOST_TPDOS, 0)
    wait_until(lambda: seen(0x182) >= pivot_tpdo1 + 20, "pivot TPDO1 again")
    wait_until(lambda: rig.complete > complete + 20, "complete cycles again")
    assert rig.rack.counters.tpdos_lost > 40

    rig.enable()
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_LOST_TPDOS, 0x0F)  # all four
    wait_until(lambda: "stale drive pivot" in rig.bridge.latched_reason(), "pivot stale")


def test_heartbeat_off_is_seen_lost_by_a_heartbeat_consumer(rig: Rig) -> None:
    """0x2030 sub 2 = 1: no heartbeat from pivot for longer than a consumer time; back at 0."""
    producer_s = rig.bridge.params.heartbeat_producer_ms * 1e-3
    consumer_s = 3.0 * producer_s  # a consumer time of three producer periods (CiA 301 0x1016)
    pivot, l_arm = _remote(rig.network, PIVOT).nmt, _remote(rig.network, 1).nmt
    wait_until(lambda: pivot.timestamp is not None, "a pivot heartbeat")
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_HEARTBEAT_OFF, 1)
    written = time.time()

    def age(nmt: Any) -> float:
        return time.time() - float(nmt.timestamp)

    wait_until(lambda: age(pivot) > consumer_s, "pivot's heartbeat lost", 5.0)
    assert pivot.timestamp is not None and pivot.timestamp <= written  # nothing since the write
    assert age(l_arm) < consumer_s  # the other nodes' heartbeats go on
    with pytest.raises(canopen.SdoAbortedError):  # a bool: 0 or 1
        rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_HEARTBEAT_OFF, 2)
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_HEARTBEAT_OFF, 0)
    wait_until(lambda: age(pivot) < producer_s, "pivot's heartbeat again", 5.0)
    assert rig.rack.power_state("pivot") is PowerState.READY_TO_SWITCH_ON  # nothing else changed


def test_emcy_with_any_code_reaches_the_master_and_latches_in_the_bridge(rig: Rig) -> None:
    """0x2030 sub 3 = 0x4310: that EMCY with 0x1001 generic + temperature; the bridge latches.

    The drive does not fault for it (0x603F stays 0); writing 0 sends "error reset".
    """
    emcy = _remote(rig.network, PIVOT).emcy
    rig.enable()
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_RAISE_EMCY, 0x4310)
    wait_until(lambda: any(e.code == 0x4310 for e in emcy.log), "EMCY 0x4310 at the master")
    entry = next(e for e in emcy.log if e.code == 0x4310)
    assert entry.register == 0x09  # CiA 301 0x1001: generic (bit 0) + temperature (bit 3)
    wait_until(lambda: rig.bridge.emcy_codes()["pivot"] == 0x4310, "latched in the bridge")
    assert "0x4310" in rig.bridge.latched_reason()
    assert rig.bridge.sdo_read("pivot", od.ERROR_REGISTER, 0) == 0x09
    assert rig.bridge.sdo_read("pivot", od.ERROR_CODE, 0) == 0
    assert rig.rack.power_state("pivot") is not PowerState.FAULT
    logged = len(emcy.log)
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_RAISE_EMCY, 0)
    wait_until(lambda: len(emcy.log) > logged, "the error reset EMCY")
    assert (emcy.log[-1].code, emcy.log[-1].register) == (0x0000, 0x00)
    assert rig.bridge.sdo_read("pivot", od.ERROR_REGISTER, 0) == 0


def test_drive_fault_faults_the_drive_and_stops_its_torque(rig: Rig) -> None:
    """0x2030 sub 4 = 0x2310: FAULT, 0x603F = 0x2310, zero current, the self-locking axis holds.

    A fault reset is refused while the cause lasts; once it is cleared the bridge's reset
    recovers the drive, which then follows its current command again.
    """
    rig.currents_a[1] = 2.0
    rig.enable()
    wait_until(lambda: abs(rig.rack.plant_state().current_a[1] - 2.0) < 0.05, "pivot at 2 A")
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_DRIVE_FAULT, 0x2310)
    wait_until(lambda: rig.bridge.emcy_codes()["pivot"] == 0x2310, "EMCY 0x2310 latched")
    wait_until(
        lambda: rig.bridge.axis_state("pivot").power_state is PowerState.FAULT,
        "the statusword says FAULT",
    )
    assert rig.bridge.axis_state("pivot").statusword & 0x08  # CiA 402 statusword bit 3
    assert rig.bridge.sdo_read("pivot", od.ERROR_CODE, 0) == 0x2310
    assert rig.bridge.sdo_read("pivot", od.ERROR_REGISTER, 0) == 0x03  # generic + current
    wait_until(lambda: abs(rig.rack.plant_state().current_a[1]) < 1e-3, "pivot current 0")
    held = rig.rack.plant_state().position[1]
    rig.after_syncs(100)
    assert abs(rig.rack.plant_state().position[1] - held) < 1e-6  # the gear holds the load
    assert abs(rig.rack.plant_state().current_a[1]) < 1e-3

    rig.bridge.recover()  # fault resets (controlword bit 7 edges) while the cause lasts
    rig.after_syncs(60)
    assert rig.rack.power_state("pivot") is PowerState.FAULT
    assert rig.bridge.sdo_read("pivot", od.ERROR_CODE, 0) == 0x2310
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_DRIVE_FAULT, 0)  # the cause is gone
    rig.bridge.recover()
    wait_until(lambda: rig.rack.power_state("pivot") is not PowerState.FAULT, "fault reset")
    assert rig.bridge.sdo_read("pivot", od.ERROR_CODE, 0) == 0
    rig.enable()
    wait_until(lambda: abs(rig.rack.plant_state().current_a[1] - 2.0) < 0.05, "2 A again")


def test_bus_off_silences_the_node_until_it_recovers(rig: Rig) -> None:
    """0x2030 sub 5 = 300 ms: after the write's answer no frame from the node, then EMCY 0x8140.

    The rack's time (SYNCs) times it; 0x6007 faults the enabled drive and 0x1029 (0) takes it
    to PRE-OPERATIONAL; the bridge sees it stale. Its ~/recover (NMT start, fault reset)
    brings it back with its configuration (no boot-up).
    """
    rig.enable()
    mark = rig.recorder.mark()
    rig.bridge.sdo_write("pivot", FAULTS, od.FAULT_BUS_OFF, 300)  # answered: then silent
    recovery = (0x82, b"\x40\x81\x11\x00\x00\x00\x00\x00")  # EMCY 0x8140, 0x1001 = 0x11
    wait_until(lambda: recovery in rig.node_frames(PIVOT, mark), "EMCY 0x8140", 10.0)
    frames = rig.node_frames(PIVOT, mark)
    answer = frames.index((0x582, b"\x60\x30\x20\x05\x00\x00\x00\x00"))  # the write's
    assert frames[answer + 1] == recovery  # not one frame in between
    l_arm = [f for f in rig.recorder.since(mark) if f[0] == 0x181]
    assert len(l_arm) > 50  # the other nodes went on
    on, off = (e for e in rig.rack.fault_log if e.kind == "bus_off")
    assert (on.value, off.value) == (1, 0)
    assert 0.3 <= off.time_s - on.time_s < 0.3 + 0.004 + 1e-9  # 300 ms of SYNCs (4 ms cycle)
    assert rig.rack.counters.frames_dropped_bus_off > 0
    assert rig.rack.nmt_state("pivot") == "PRE-OPERATIONAL"  # CiA 301 0x1029 sub 1 = 0
    assert rig.rack.faults["pivot"] == 0x8140
    wait_until(lambda: "stale drive pivot" in rig.bridge.latched_reason(), "pivot stale")
    heartbeats = rig.recorder.count(0x702, mark)
    wait_until(lambda: rig.recorder.count(0x702, mark) > heartbeats, "a heartbeat again")
    assert rig.node_frames(PIVOT, mark)[-1] == (0x702, b"\x7f")  # PRE-OPERATIONAL, no boot-up
    rig.bridge.recover()
    wait_until(lambda: rig.rack.nmt_state("pivot") == "OPERATIONAL", "NMT start")
    wait_until(lambda: rig.rack.power_state("pivot") is not PowerState.FAULT, "fault reset")
    tpdo1 = rig.recorder.count(0x182, mark)
    wait_until(lambda: rig.recorder.count(0x182, mark) > tpdo1 + 10, "pivot TPDO1 again")


# --- the schedule, and no fault at all ---------------------------------------------------------

PERIOD_US = 2000  # 0x1006 of the scripted runs: 20 plant steps of 1e-4 s per SYNC


def _sdo_download(index: int, subindex: int, value: int, size: int) -> bytes:
    """A CiA 301 SDO expedited download request (client -> server)."""
    command = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    return struct.pack("<BHB", command, index, subindex) + value.to_bytes(4, "little")


@dataclass
class ScriptedRun:
    """A run driven SYNC by SYNC: every frame of the rack, and where each SYNC went out."""

    frames: list[tuple[int, bytes]]
    sync_marks: list[int]  # index in `frames` of the first frame after SYNC k was sent
    rack: VirtualDriveRack

    def sync_of(self, position: int) -> int:
        """The SYNC a frame at `position` in `frames` followed."""
        return max(k for k, mark in enumerate(self.sync_marks) if mark <= position)


def _scripted_run(config: RackConfig, syncs: int = 160, linked: bool = False) -> ScriptedRun:
    """The rack without heartbeats, 0x1006 = 2 ms, driven by RPDOs and SYNCs paced by 0x1006.

    Configured over SDO, started, enabled by RPDO1 and given torques that change sign after
    100 SYNCs. Each SYNC waits for the previous one's synchronous TPDOs, so the rack's frames
    and the SYNC each follows are the same on every run. `linked`: the rack on the bridge's
    linked bus (its TPDOs after a SYNC in one call, as over lca_remote), else on a plain
    virtual one (frame by frame, as on socketcan).
    """
    config = replace(config, heartbeat_producer_ms=0, sync_loss_periods=1e6)
    channel = f"test_rack_faults_scripted_{os.getpid()}_{next(_channels)}"
    recorder = Recorder(channel)
    rack_bus = (
        LinkedVirtualBus(channel=channel)
        if linked
        else can.Bus(interface="virtual", channel=channel)
    )
    rack = VirtualDriveRack(rack_bus, config)
    marks: list[int] = []

    def send(cob_id: int, data: bytes = b"") -> None:
        recorder.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    try:
        rack.start(settle=False)
        wait_until(lambda: all(recorder.count(0x700 + n) for n in NODE_IDS), "boot-ups")
        for n in NODE_IDS:
            for index, sub, value, size in ((0x1006, 0, PERIOD_US, 4), (0x1802, 5, 0, 2)):
                answers = recorder.count(0x580 + n)
                send(0x600 + n, _sdo_download(index, sub, value, size))
                wait_until(_more(recorder, 0x580 + n, answers), "SDO answer")
        send(0x000, bytes([0x01, 0]))
        # event-driven TPDO3 goes at the first monitor tick in OPERATIONAL, before any SYNC
        wait_until(lambda: all(recorder.count(0x380 + n) for n in NODE_IDS), "TPDO3s")
        torques = {1: 200, 2: 300, 3: -150, 4: 400}
        last_s = -1.0
        for k in range(syncs):
            if k == 100:
                torques = {1: -250, 2: -100, 3: 300, 4: -50}
            for n in NODE_IDS:
                controlword = 0x06 if k == 0 else 0x0F
                send(0x200 + n, struct.pack("<Hh", controlword, torques[n] if k > 2 else 0))
            # pacing, not a wait for a condition: SYNCs no faster than 0x1006 admits
            while time.monotonic() - last_s < PERIOD_US * 1.05e-6:
                time.sleep(0.0002)
            last_s = time.monotonic()
            marks.append(recorder.mark())
            send(0x080)
            wait_until(_more(recorder, 0x284, k), f"SYNC {k}'s TPDOs")
        assert rack.counters.syncs_too_fast == 0
        return ScriptedRun(recorder.since(0), marks, rack)
    finally:
        rack.stop()
        recorder.close()
        rack_bus.shutdown()


def _more(recorder: Recorder, cob_id: int, than: int) -> Callable[[], bool]:
    """A condition: more than `than` frames with this COB-ID recorded."""
    return lambda: recorder.count(cob_id) > than


def _digest(frames: list[tuple[int, bytes]]) -> tuple[int, str]:
    """Count and SHA-256 of a frame sequence, without EMCY 0xFF02 (a stall of this machine)."""
    kept = [(c, d) for c, d in frames if not (0x81 <= c <= 0xFF and d[:2] == b"\x02\xff")]
    digest = hashlib.sha256()
    for cob_id, data in kept:
        digest.update(struct.pack("<HB", cob_id, len(data)) + data)
    return len(kept), digest.hexdigest()


# The frames of `_scripted_run` on the shipped rack and robot before fault injection existed
# (commit 2102d08). A change of the model or of the drive logic changes them on purpose: then
# run this test's `_scripted_run` on that commit's successor without 0x2030 and update.
FRAMES_BEFORE_FAULT_INJECTION = (
    1373,
    "d67835edca549d250df6a443ecda94e3ddaa88f680838d3036aa06f81cdcc38e",
)


@pytest.mark.parametrize("linked", [False, True], ids=["frame_by_frame", "one_call_per_sync"])
def test_without_faults_the_rack_sends_the_frames_it_sent_before(linked: bool) -> None:
    """No fault configured: every frame of a scripted run is the one of the rack before 0x2030.

    With eq. (2)'s terms evaluated at every step, as the rack did then (it holds them for
    `rigid_body_period_s`, 1 ms, since; that moves the plant by microradians). On either send
    path of the TPDOs: frame by frame, or a SYNC's in one call of the bus.
    """
    run = _scripted_run(replace(load_rack_config(None), rigid_body_period_s=1e-4), linked=linked)
    assert _digest(run.frames) == FRAMES_BEFORE_FAULT_INJECTION
    assert run.rack.fault_log == ()


@pytest.mark.parametrize("linked", [False, True], ids=["frame_by_frame", "one_call_per_sync"])
def test_a_scheduled_fault_goes_on_and_off_at_its_times(tmp_path: Path, linked: bool) -> None:
    """rack.yaml `faults:`: pivot's TPDO1 lost from 0.1 s to 0.15 s, c_arc's EMCY at 0.2 s.

    The rack's time is the plant's: at 2 ms per SYNC, SYNC k runs at k x 2 ms, so the TPDO1s
    of SYNCs 50-74 are missing, exactly, and the EMCY comes right after SYNC 100.
    """
    shipped = yaml.safe_load((CONFIG / "can" / "rack.yaml").read_text(encoding="utf-8"))
    shipped["robot"] = "default"
    shipped["faults"] = [
        {"joint": "pivot", "kind": "lost_tpdo", "value": 1, "start_s": 0.1, "end_s": 0.15},
        {"joint": "c_arc", "kind": "emcy", "value": 0x5530, "start_s": 0.2},
    ]
    path = tmp_path / "rack.yaml"
    path.write_text(yaml.safe_dump(shipped), encoding="utf-8")
    run = _scripted_run(load_rack_config(path), syncs=110, linked=linked)
    missing = set(range(110)) - {
        run.sync_of(i) for i, (cob_id, _) in enumerate(run.frames) if cob_id == 0x182
    }
    assert missing == set(range(50, 75))
    log = [(e.joint, e.kind, e.value, e.source) for e in run.rack.fault_log]
    assert log == [
        ("pivot", "lost_tpdo", 1, "schedule"),
        ("pivot", "lost_tpdo", 0, "schedule"),
        ("c_arc", "emcy", 0x5530, "schedule"),
    ]
    times = [e.time_s for e in run.rack.fault_log]
    assert times == pytest.approx([0.1, 0.15, 0.2], abs=1e-12)
    emcy = [i for i, (cob_id, data) in enumerate(run.frames) if cob_id == 0x83]
    assert [run.frames[i][1][:3] for i in emcy] == [b"\x30\x55\x01"]  # code, 0x1001 generic
    assert run.sync_of(emcy[0]) == 100
    assert run.rack.counters.tpdos_lost == 25  # lost as if sent: counted, not sent
    assert run.rack.counters.send_errors == 0


@pytest.mark.parametrize(
    ("entry", "key", "expected"),
    [
        ({"joint": "wrist", "kind": "emcy", "value": 1, "start_s": 0}, "faults[0].joint", ""),
        ({"joint": "pivot", "kind": "jam", "start_s": 0}, "faults[0].kind", "lost_tpdo"),
        ({"joint": "pivot", "kind": "emcy", "start_s": 0}, "faults[0].value", "missing"),
        ({"joint": "pivot", "kind": "heartbeat_off", "start_s": 1, "end_s": 1},
         "faults[0].end_s", ""),
        ({"joint": "pivot", "kind": "bus_off", "start_s": 0, "until": 1}, "faults[0].until",
         "unknown key"),
    ],
)  # fmt: skip
def test_a_bad_fault_entry_is_one_error_naming_its_key(
    tmp_path: Path, entry: dict[str, Any], key: str, expected: str
) -> None:
    """A fault schedule is validated where it is read: the file, the bad key, what was wanted."""
    shipped = yaml.safe_load((CONFIG / "can" / "rack.yaml").read_text(encoding="utf-8"))
    shipped["robot"] = "default"
    shipped["faults"] = [entry]
    path = tmp_path / "rack.yaml"
    path.write_text(yaml.safe_dump(shipped), encoding="utf-8")
    with pytest.raises(ConfigError) as error:
        load_rack_config(path)
    assert key in str(error.value) and expected in str(error.value)


def test_overlapping_entries_and_a_bad_faults_file_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two overlapping faults of one kind on one joint; lca-virtual-drive --faults: exit 2."""
    faults = tmp_path / "faults.yaml"
    faults.write_text(
        "faults:\n"
        "  - {joint: pivot, kind: bus_off, start_s: 1.0, end_s: 2.0}\n"
        "  - {joint: pivot, kind: bus_off, start_s: 1.5}\n",
        encoding="utf-8",
    )
    assert main(["--interface", "virtual", "--channel", "unused", "--faults", str(faults)]) == 2
    err = capsys.readouterr().err
    assert "faults[1]" in err and "overlaps" in err
