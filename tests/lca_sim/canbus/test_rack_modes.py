"""A third-party master in every mode: python-canopen's BaseNode402 drives the rack (rack_modes).

No lca_hil code on the master side: the test's master is canopen's `BaseNode402` on python-can's
virtual bus, with the shipped EDS. The rack runs in lockstep timing, so each SYNC the test sends
advances the plant exactly 0x1006 and the physics does not depend on the machine's speed; the
cycle is what a cyclic master does: its RPDO1 (controlword), then the SYNC. SDO reads between
SYNCs see the state after the SYNC's span. The plant is the shipped robot with its worm gears.
Objects, bits and units: docs/can-modes.md (CiA 402-2).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError
from support import wait_until

from lca_sim import RobotParams
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402 import codec
from lca_sim.config.rack import eds_path

EDS = str(eds_path())
PERIOD_US = 2000  # 0x1006: each SYNC is 2 ms of plant (20 steps of 1e-4 s)
PERIOD_S = PERIOD_US * 1e-6
NODE_IDS = {"l_arm": 1, "pivot": 2}  # the shipped rack.yaml
REV = 65536  # 0x608F: increments per motor revolution

# Controlword (CiA 402-2 0x6040): enable operation, and the bits of the profile modes.
CW_ENABLED = 0x0F
CW_NEW_SET_POINT = 1 << 4  # PP: new set-point; HM: homing operation start
CW_RELATIVE = 1 << 6
CW_HALT = 1 << 8
# Statusword (0x6041): the mode-specific bits, and the power-state mask.
SW_TARGET_REACHED = 1 << 10
SW_BIT12 = 1 << 12  # PP set-point acknowledge, PV speed, HM attained, CSP follows
SW_BIT13 = 1 << 13  # following error (PP, CSP), homing error (HM)
SW_STATE_MASK, SW_OPERATION_ENABLED, SW_FAULT = 0x6F, 0x27, 0x08
ABORT_VALUE_RANGE = 0x06090030
EMCY_FOLLOWING_ERROR = 0x8611

MODES = {
    1: "PROFILED POSITION",
    3: "PROFILED VELOCITY",
    6: "HOMING",
    8: "CYCLIC SYNCHRONOUS POSITION",
    9: "CYCLIC SYNCHRONOUS VELOCITY",
    10: "CYCLIC SYNCHRONOUS TORQUE",
}


@dataclass
class Drive402:
    """One drive of the lockstep rack, and canopen's BaseNode402 of it on the master side."""

    rack: VirtualDriveRack
    network: canopen.Network
    node: canopen.BaseNode402
    name: str

    def cycle(self, count: int = 1) -> None:
        """`count` cycles: the RPDO1 (controlword), then a SYNC, each processed by the rack."""
        for _ in range(count):
            done = self.rack.counters.syncs + 1
            self.node.rpdo[1].transmit()
            self.network.sync.transmit()
            wait_until(lambda: self.rack.counters.syncs >= done, "SYNC processed")  # noqa: B023

    def read(self, index: int) -> int:
        """An object's value by SDO (the state after the last SYNC's span)."""
        value: int = self.node.sdo[index].raw
        return value

    def write(self, index: int, value: int, subindex: int | None = None) -> None:
        """Write an object by SDO."""
        if subindex is None:
            self.node.sdo[index].raw = value
        else:
            self.node.sdo[index][subindex].raw = value

    def control(self, controlword: int) -> None:
        """The controlword the next cycles' RPDO1 carries."""
        self.node.controlword = controlword

    @property
    def status(self) -> int:
        """0x6041."""
        return self.read(0x6041)

    @property
    def joint_position(self) -> float:
        """The plant's joint position, rad (m)."""
        state = self.rack.plant_state()
        return float(state.position[self.rack.simulator.axis_names.index(self.name)])

    @property
    def increments_per_joint(self) -> float:
        """Increments per joint rad (m) of this drive: gear x 0x608F / 2 pi."""
        axis = self.rack._axis(self.name)  # the rack's own scale
        return codec.increments_per_joint_unit(axis.units, axis.gear_ratio)

    def set_mode(self, code: int) -> None:
        """0x6060 through BaseNode402's setter, which swallows errors: 0x6061 read back."""
        self.node.op_mode = MODES[code]
        assert self.read(0x6061) == code

    @contextmanager
    def free_running(self) -> Iterator[None]:
        """SYNCs and RPDO1 every 10 ms in the background, for BaseNode402's blocking calls."""
        self.node.rpdo[1].start(0.01)
        self.network.sync.start(0.01)
        try:
            yield
        finally:
            self.network.sync.stop()  # type: ignore[no-untyped-call]
            self.node.rpdo[1].stop()

    def enable(self, code: int) -> None:
        """Mode `code`, then BaseNode402 walks the drive to OPERATION ENABLED."""
        self.set_mode(code)
        with self.free_running():
            self.node.state = "OPERATION ENABLED"
        self.control(CW_ENABLED)
        self.cycle()
        assert self.status & SW_STATE_MASK == SW_OPERATION_ENABLED

    def cycle_until(self, condition: Callable[[], bool], what: str, max_s: float) -> float:
        """Cycle until `condition()` holds; the plant time it took, s (fails after `max_s`)."""
        cycles = 0
        while not condition():
            if cycles * PERIOD_S > max_s:
                pytest.fail(f"not within {max_s:g} s of plant time: {what}")
            self.cycle()
            cycles += 1
        return cycles * PERIOD_S


@pytest.fixture
def drive(
    lockstep_rack: Callable[..., tuple[VirtualDriveRack, canopen.Network]],
    request: pytest.FixtureRequest,
) -> Drive402:
    """l_arm (or the axis of `@pytest.mark.parametrize("drive", [...], indirect=True)`)."""
    name, initial = getattr(request, "param", ("l_arm", {}))
    return _drive402(*lockstep_rack(**initial), name)


def _drive402(rack: VirtualDriveRack, network: canopen.Network, name: str) -> Drive402:
    """A BaseNode402 of drive `name` (python-canopen): 0x1006 set, its PDOs read, OPERATIONAL."""
    node = canopen.BaseNode402(NODE_IDS[name], EDS)  # type: ignore[no-untyped-call]
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    node.TIMEOUT_CHECK_TPDO = 2.0
    node.TIMEOUT_SWITCH_OP_MODE = 2.0
    node.TIMEOUT_SWITCH_STATE_SINGLE = 3.0
    node.TIMEOUT_SWITCH_STATE_FINAL = 6.0
    node.nmt.state = "PRE-OPERATIONAL"
    node.sdo[0x1006].raw = PERIOD_US
    node.setup_402_state_machine()  # type: ignore[no-untyped-call]  # reads the PDOs over SDO
    node.nmt.state = "OPERATIONAL"
    wait_until(lambda: rack.nmt_state(name) == "OPERATIONAL", f"{name} OPERATIONAL")
    return Drive402(rack, network, node, name)


def trapezoid_time_s(distance: float, velocity: float, accel: float, decel: float) -> float:
    """A linear-ramp positioning's duration from rest to rest (docs/can-modes.md)."""
    peak = min(velocity, math.sqrt(2.0 * accel * decel * distance / (accel + decel)))
    ramps = peak * peak / (2.0 * accel) + peak * peak / (2.0 * decel)
    return peak / accel + peak / decel + (distance - ramps) / peak


# --- profile position (1) -------------------------------------------------------------------


def _profile(drive: Drive402, velocity: int, accel: int, decel: int) -> None:
    drive.write(0x6081, velocity)
    drive.write(0x6083, accel)
    drive.write(0x6084, decel)


def test_pp_reaches_the_target_in_the_trapezoids_time(drive: Drive402) -> None:
    """PP: set-point handshake, bit 10 within 0x6067 at the end, the trapezoid's duration."""
    velocity, accel, decel = 10 * REV, 20 * REV, 40 * REV
    _profile(drive, velocity, accel, decel)
    drive.enable(1)
    drive.cycle(5)  # 0x6068 = 10 ms
    start = drive.read(0x6064)
    assert drive.status & SW_TARGET_REACHED  # no set-point yet: standing on the entry position
    target = start + 12 * REV
    drive.write(0x607A, target)
    # CiA 402-2 PP handshake: bit 4 up -> the drive acknowledges with bit 12 ...
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    assert drive.status & (SW_BIT12 | SW_TARGET_REACHED) == SW_BIT12
    # ... bit 4 down -> bit 12 down, and the move runs (target not reached).
    drive.control(CW_ENABLED)
    drive.cycle()
    assert drive.status & (SW_BIT12 | SW_TARGET_REACHED) == 0
    window = drive.read(0x6067)
    took_s, lag = PERIOD_S, 0
    while not drive.status & SW_TARGET_REACHED:
        assert took_s < 5.0, "target not reached"
        drive.cycle()
        took_s += PERIOD_S
        lag = max(lag, abs(drive.read(0x60F4)))
    # The position loop feeds 0x6062's rate (over the last cycle) forward: the axis follows
    # within about one cycle's step, v dt = 1311 (fed forward twice, it ran v / kp = 43 690
    # ahead).
    assert 0 < lag <= 2000
    # 12 rev at 10 rev/s, 20 / 40 rev/s^2: 0.5 s + 0.25 s of ramps (3.75 rev), 0.825 s cruising.
    expected_s = trapezoid_time_s(12 * REV, velocity, accel, decel)
    assert expected_s == pytest.approx(1.575)
    # The loops lag the demand by a few ms, and bit 10 waits 0x6068 = 10 ms in the window.
    assert expected_s <= took_s <= expected_s + 0.05
    assert abs(drive.read(0x6064) - target) <= window
    assert drive.read(0x6062) == target  # the demand ends exactly on the target
    assert abs(drive.joint_position * drive.increments_per_joint - target) <= window
    assert drive.status & SW_BIT13 == 0


def test_pp_profile_velocity_is_clamped_where_the_loops_are(drive: Drive402) -> None:
    """0x607F is the loops' cap (rack.yaml velocity_limit, 0.2 rad/s at l_arm's 800:1 gear).

    A 0x6081 of twice it cruises at 0x607F (CiA 402-2: the profile velocity is limited to the
    max profile velocity), not faster than the loops follow: no following error.
    """
    cap = drive.read(0x607F)
    assert cap == round(0.2 * drive.increments_per_joint)  # 1 668 861 inc/s
    _profile(drive, 2 * cap, 4 * cap, 4 * cap)  # 0.25 s ramps
    drive.enable(1)
    target = drive.read(0x6064) + cap  # 1 s at the cap: 0.5 s cruising
    drive.write(0x607A, target)
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    drive.control(CW_ENABLED)
    speeds = []
    for _ in range(int(0.6 / PERIOD_S)):
        drive.cycle()
        speeds.append(abs(drive.read(0x606C)))
    cruise = speeds[int(0.4 / PERIOD_S) :]  # 0.4-0.6 s: past the ramp and the PI's overshoot
    assert abs(sum(cruise) / len(cruise) - cap) <= 0.02 * cap
    assert max(speeds) <= 1.1 * cap  # the velocity PI's overshoot (5 %), not 2 x the cap
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "target reached", 1.0)
    assert drive.status & SW_BIT13 == 0


def test_pp_relative_move_lands_at_start_plus_distance(drive: Drive402) -> None:
    """PP with bit 6: 0x607A is relative to the preceding target (0x60F2 = 0)."""
    _profile(drive, 10 * REV, 40 * REV, 40 * REV)
    drive.enable(1)
    start = drive.read(0x6064)
    window = drive.read(0x6067)
    for distance, expected in ((5 * REV, start + 5 * REV), (-8 * REV, start - 3 * REV)):
        drive.write(0x607A, distance)
        drive.control(CW_ENABLED | CW_RELATIVE | CW_NEW_SET_POINT)
        drive.cycle()
        assert drive.status & SW_BIT12
        drive.control(CW_ENABLED | CW_RELATIVE)
        drive.cycle()
        drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "relative move", 3.0)
        assert drive.read(0x6062) == expected
        assert abs(drive.read(0x6064) - expected) <= window


def _new_set_point(drive: Drive402, target: int, extra: int = 0) -> None:
    """The PP handshake: 0x607A, bit 4 up for a cycle (bit 12 answers), bit 4 down."""
    drive.write(0x607A, target)
    drive.control(CW_ENABLED | CW_NEW_SET_POINT | extra)
    drive.cycle()
    assert drive.status & SW_BIT12
    drive.control(CW_ENABLED | extra)
    drive.cycle()


def test_pp_halt_stops_on_the_deceleration_and_resumes(drive: Drive402) -> None:
    """PP bit 8: stop on 0x6084 (0x605D = 1), bit 10 at standstill; dropping it resumes."""
    velocity, decel = 10 * REV, 40 * REV
    _profile(drive, velocity, 40 * REV, decel)
    drive.enable(1)
    start = drive.read(0x6064)
    target = start + 20 * REV
    _new_set_point(drive, target)
    drive.cycle(200)  # cruising at 10 rev/s since 0.25 s
    halted_at = drive.read(0x6062)
    drive.control(CW_ENABLED | CW_HALT)
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "halted", 1.0)
    # The demand stops v^2 / 2 d = 1.25 rev beyond where the halt came (within a cycle's step).
    stop = velocity * velocity / (2.0 * decel)
    assert abs(drive.read(0x6062) - (halted_at + stop)) <= velocity * PERIOD_S
    drive.cycle(20)
    assert drive.status & SW_TARGET_REACHED
    assert drive.read(0x6062) < target
    drive.control(CW_ENABLED)
    drive.cycle()
    assert drive.status & SW_TARGET_REACHED == 0
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "target", 3.0)
    assert abs(drive.read(0x6064) - target) <= drive.read(0x6067)


def test_pp_buffers_one_set_point_and_runs_it_after_the_first(drive: Drive402) -> None:
    """PP bit 5 = 0 while moving: the next set-point waits (bit 12 stays up), then runs."""
    _profile(drive, 10 * REV, 40 * REV, 40 * REV)
    drive.enable(1)
    start = drive.read(0x6064)
    _new_set_point(drive, start + 4 * REV)
    drive.cycle(10)
    drive.write(0x607A, start + 2 * REV)
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    drive.control(CW_ENABLED)
    drive.cycle()
    assert drive.status & SW_BIT12  # buffered: the acknowledge stays until it starts
    # The first positioning ends on its own target before the second one starts back.
    reached_first = False
    while drive.status & SW_BIT12:
        drive.cycle()
        reached_first = reached_first or drive.read(0x6062) == start + 4 * REV
    assert reached_first
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "second target", 2.0)
    assert abs(drive.read(0x6064) - (start + 2 * REV)) <= drive.read(0x6067)


def test_pp_target_beyond_the_software_limit_stops_at_it(drive: Drive402) -> None:
    """0x607D: a PP target beyond the max is limited to it (CiA 402-2)."""
    _profile(drive, 10 * REV, 40 * REV, 40 * REV)
    drive.enable(1)
    start = drive.read(0x6064)
    drive.write(0x607D, start + 3 * REV, 2)
    _new_set_point(drive, start + 10 * REV)
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "limit", 2.0)
    assert drive.read(0x6062) == start + 3 * REV
    assert abs(drive.read(0x6064) - (start + 3 * REV)) <= drive.read(0x6067)


def test_pp_after_homing_moves_in_the_homed_frame(drive: Drive402) -> None:
    """HM 37 with 0x607C, then PP to 0x607C + 5 rev: the joint moves 5 motor rev."""
    home_offset = 1_000_000
    drive.write(0x607C, home_offset)
    _profile(drive, 10 * REV, 40 * REV, 40 * REV)
    drive.enable(6)
    joint_at_home = drive.joint_position
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    assert drive.status & SW_BIT12
    drive.set_mode(1)
    drive.control(CW_ENABLED)
    drive.cycle()
    _new_set_point(drive, home_offset + 5 * REV)
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "target", 2.0)
    window = drive.read(0x6067)
    assert abs(drive.read(0x6064) - (home_offset + 5 * REV)) <= window
    moved = (drive.joint_position - joint_at_home) * drive.increments_per_joint
    assert abs(moved - 5 * REV) <= window


CW_QUICK_STOP = 0x0B  # CiA 402-2: bit 2 (quick stop) low, the others enabled


@pytest.mark.parametrize("option", [2, 6])
def test_pp_quick_stop_ramps_down_on_0x6085(drive: Drive402, option: int) -> None:
    """Quick stop in PP (0x605A = 2 / 6): the demand ramps to rest on 0x6085, the axis follows.

    Option 2 then goes to SWITCH ON DISABLED at standstill; option 6 stays in QUICK STOP
    ACTIVE, holding, and enable operation (transition 16) resumes PP from there.
    """
    velocity, quick_decel = 10 * REV, drive.read(0x6085)  # 50 rev/s^2
    drive.write(0x605A, option)
    _profile(drive, velocity, 40 * REV, 40 * REV)
    drive.enable(1)
    _new_set_point(drive, drive.read(0x6064) + 30 * REV)
    drive.cycle(200)  # cruising
    at_quick_stop = drive.read(0x6064)
    drive.control(CW_QUICK_STOP)
    drive.cycle()
    assert drive.status & 0x6F == 0x07  # QUICK STOP ACTIVE
    threshold = drive.read(0x606F)
    took_s = drive.cycle_until(lambda: abs(drive.read(0x606C)) <= threshold, "standing", 1.0)
    # v / d = 0.2 s over v^2 / 2d = 1 rev; the loops' lag adds a few cycles.
    assert 0.2 - 0.01 <= took_s <= 0.2 + 0.05
    stop = velocity * velocity / (2.0 * quick_decel)
    assert abs(drive.read(0x6064) - (at_quick_stop + stop)) <= 2 * velocity * PERIOD_S
    if option == 2:
        drive.cycle_until(lambda: drive.status & 0x4F == 0x40, "SWITCH ON DISABLED", 0.5)
        return
    drive.cycle(50)
    assert drive.status & 0x6F == 0x07
    held = drive.read(0x6064)
    drive.control(CW_ENABLED)
    drive.cycle(10)
    assert drive.status & (0x6F | SW_TARGET_REACHED) == 0x27 | SW_TARGET_REACHED
    assert abs(drive.read(0x6064) - held) <= drive.read(0x6067)


CW_CHANGE_IMMEDIATELY = 1 << 5


def test_pp_change_set_immediately_replans_without_a_velocity_jump(drive: Drive402) -> None:
    """PP bit 5: a new target mid-move takes over at once, from the present demand."""
    velocity, decel = 10 * REV, 40 * REV
    _profile(drive, velocity, 40 * REV, decel)
    drive.enable(1)
    start = drive.read(0x6064)
    _new_set_point(drive, start + 20 * REV)
    drive.cycle(200)  # cruising at 10 rev/s, ~3 rev travelled
    new_target = drive.read(0x6062) + REV  # closer than the 1.25 rev it takes to stop
    speed_before = drive.read(0x606C)
    _new_set_point(drive, new_target, CW_CHANGE_IMMEDIATELY)
    # The speed ramps down at once on 0x6084 (no jump), overshoots by 0.25 rev and comes back.
    assert speed_before - drive.read(0x606C) <= 2 * decel * PERIOD_S * 1.5
    peak = drive.read(0x6062)
    while not drive.status & SW_TARGET_REACHED:
        drive.cycle()
        peak = max(peak, drive.read(0x6062))
        assert drive.read(0x6062) <= new_target + velocity * velocity / (2.0 * decel)
    assert peak > new_target  # it went beyond and came back
    assert abs(drive.read(0x6064) - new_target) <= drive.read(0x6067)


# --- profile velocity (3) -------------------------------------------------------------------


def test_pv_holds_the_commanded_speed_and_reports_standstill(drive: Drive402) -> None:
    """PV: the ramp on 0x6083, then the speed held within 0x606D with bit 10; bit 12 stopped."""
    accel = 20 * REV
    drive.write(0x6083, accel)
    drive.write(0x6084, accel)
    drive.enable(3)
    assert drive.status & SW_BIT12  # speed = 0
    speed = 5 * REV  # 5 rev/s motor, 0.039 rad/s of l_arm
    window = drive.read(0x606D)  # 8192 inc/s: 2.5 % of the speed
    drive.write(0x60FF, speed)
    drive.cycle(20)
    # 0x606F = 1/8 rev/s is passed after ~10 ms (the ramp's 6 ms and the loop's lag), then
    # bit 12 drops once it has stayed above for 0x6070 = 10 ms.
    assert drive.status & SW_BIT12 == 0
    # The ramp takes speed / 0x6083 = 0.25 s; the velocity PI then rings on the worm gear's
    # friction (~7 Hz), its first overshoot 5 % of the speed, settled into the window by 0.6 s.
    for cycle in range(20, 300):
        drive.cycle()
        velocity = drive.read(0x606C)
        assert velocity <= speed * 1.06
        if cycle * PERIOD_S >= 0.25:
            assert velocity >= speed * 0.94
    for _ in range(100):  # 0.2 s held
        drive.cycle()
        assert abs(drive.read(0x606C) - speed) <= window
        assert drive.status & SW_TARGET_REACHED
    drive.write(0x60FF, 0)
    drive.cycle_until(lambda: bool(drive.status & SW_BIT12), "speed 0", 1.0)
    assert abs(drive.read(0x606C)) <= drive.read(0x606F)
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "stopped", 1.0)


def test_pv_halt_ramps_down_and_back(drive: Drive402) -> None:
    """PV bit 8: stop on 0x6084 (bit 10 once stopped), dropping it ramps back to 0x60FF."""
    accel = 40 * REV
    drive.write(0x6083, accel)
    drive.write(0x6084, accel)
    drive.enable(3)
    speed = 5 * REV
    drive.write(0x60FF, speed)
    drive.cycle(300)
    drive.control(CW_ENABLED | CW_HALT)
    threshold = drive.read(0x606F)
    took_s = drive.cycle_until(lambda: abs(drive.read(0x606C)) <= threshold, "halted", 1.0)
    assert took_s <= speed / accel + 0.05  # 0.125 s on the ramp
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "halt: bit 10", 0.5)
    drive.control(CW_ENABLED)
    drive.cycle(150)
    assert abs(drive.read(0x606C) - speed) <= drive.read(0x606D)


# --- homing (6) -----------------------------------------------------------------------------


@pytest.mark.parametrize("method", [35, 37])
def test_homing_on_the_present_position_reads_the_home_offset(drive: Drive402, method: int) -> None:
    """HM 35 / 37: no motion, and at once 0x6064 = 0x607C, bits 12 and 10 (completed)."""
    home_offset = 123_456
    drive.write(0x6098, method)
    drive.write(0x607C, home_offset)
    drive.enable(6)
    # CiA 402-2 homing table: 13 12 10 = 0 0 1, not started.
    assert drive.status & (SW_BIT13 | SW_BIT12 | SW_TARGET_REACHED) == SW_TARGET_REACHED
    before = drive.joint_position
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    assert drive.status & (SW_BIT13 | SW_BIT12 | SW_TARGET_REACHED) == (
        SW_BIT12 | SW_TARGET_REACHED
    )
    assert abs(drive.read(0x6064) - home_offset) <= 2  # the worm gear holds: no drift
    drive.cycle(50)
    assert abs(drive.joint_position - before) * drive.increments_per_joint <= 2
    assert abs(drive.read(0x6064) - home_offset) <= 2


def test_reset_node_forgets_the_home(drive: Drive402) -> None:
    """NMT reset node (CiA 301 7.2.8.3.2.1, 0x81): 0x607C back to 0, 0x6064 the encoder's again."""
    drive.write(0x6098, 37)
    drive.write(0x607C, 1_000_000)
    drive.enable(6)
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    assert abs(drive.read(0x6064) - 1_000_000) <= 2
    drive.node.nmt.send_command(0x81)
    wait_until(lambda: drive.read(0x607C) == 0, "the reset's defaults")
    encoder = drive.joint_position * drive.increments_per_joint
    assert abs(drive.read(0x6064) - encoder) <= 2


def test_basenode402_homing_returns_true(drive: Drive402) -> None:
    """BaseNode402's own homing(): it does not write 0x6098 (37 is the default) and gets True."""
    drive.write(0x607C, -5000)
    drive.set_mode(6)
    with drive.free_running():
        drive.node.state = "OPERATION ENABLED"
        assert drive.node.homing(timeout=10) is True  # type: ignore[no-untyped-call]
    assert abs(drive.read(0x6064) + 5000) <= 2


def test_homing_interrupted_by_dropping_bit_4(drive: Drive402) -> None:
    """HM 17 from mid-range, bit 4 dropped on the way: 13 12 10 = 0 0 1, stopped on 0x609A."""
    drive.write(0x6098, 17)
    drive.enable(6)
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle(300)  # 0x6099 sub 1 = 5 rev/s towards the negative switch after 0.5 s
    assert drive.status & (SW_BIT13 | SW_BIT12 | SW_TARGET_REACHED) == 0  # in progress
    assert drive.read(0x606C) < -4 * REV
    drive.control(CW_ENABLED)
    drive.cycle()
    accel = drive.read(0x609A)
    threshold = drive.read(0x606F)
    took_s = drive.cycle_until(lambda: abs(drive.read(0x606C)) <= threshold, "stopped", 2.0)
    assert took_s <= 5 * REV / accel + 0.05  # 0.5 s on 0x609A
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "interrupted", 0.5)
    assert drive.status & (SW_BIT13 | SW_BIT12) == 0


L_ARM_NEAR_LOW_STOP = ("l_arm", {"l_arm": -1.70})  # 0.045 rad (5.7 motor rev) above its stop


@pytest.mark.parametrize("drive", [L_ARM_NEAR_LOW_STOP], indirect=True)
def test_homing_on_the_mechanical_stop_reads_the_home_offset_there(drive: Drive402) -> None:
    """HM -1 (lca_hil): towards the negative stop until the current presses it; 0x607C there."""
    home_offset = -14_000_000
    drive.write(0x6098, -1)
    drive.write(0x6099, 5 * REV, 2)  # search for zero at 5 rev/s
    drive.write(0x607C, home_offset)
    drive.enable(6)
    low = drive.rack.simulator.position_limits[0][0]
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    assert drive.status & (SW_BIT13 | SW_BIT12 | SW_TARGET_REACHED) == 0  # in progress
    drive.cycle_until(lambda: bool(drive.status & SW_BIT12), "homing attained", 5.0)
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "homing completed", 1.0)
    assert drive.status & SW_BIT13 == 0
    # On the stop (within 1 mrad of the URDF limit) and 0x6064 reads the home offset there.
    assert drive.joint_position == pytest.approx(low, abs=1e-3)
    assert abs(drive.read(0x6064) - home_offset) <= drive.read(0x6067)


@pytest.mark.parametrize("drive", [L_ARM_NEAR_LOW_STOP], indirect=True)
def test_homing_on_the_negative_limit_switch(drive: Drive402) -> None:
    """HM 17: the switch is 0.5 % of the range before the stop; home where it goes off."""
    home_offset = 1000
    drive.write(0x6098, 17)
    drive.write(0x607C, home_offset)
    drive.enable(6)
    low, high = drive.rack.simulator.position_limits[0]
    switch = low + 0.005 * (high - low)
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    drive.cycle_until(lambda: bool(drive.status & SW_TARGET_REACHED), "homing completed", 5.0)
    assert drive.status & (SW_BIT13 | SW_BIT12) == SW_BIT12
    # Home is the switch's edge; the axis stops on 0x609A beyond it: v^2 / 2a at 0x6099 sub 2.
    speed = drive.node.sdo[0x6099][2].raw
    accel = drive.read(0x609A)
    stop_inc = speed * speed / (2.0 * accel)
    window = drive.read(0x6067)
    assert abs(drive.read(0x6064) - (home_offset + stop_inc)) <= window
    assert drive.joint_position == pytest.approx(
        switch + stop_inc / drive.increments_per_joint, abs=window / drive.increments_per_joint
    )


# --- cyclic synchronous position (8) --------------------------------------------------------


def test_csp_follows_a_cyclic_trajectory_within_the_window(drive: Drive402) -> None:
    """CSP: 0x607A by SDO before each SYNC, a 1 Hz cosine of 2 rev; bit 12, |0x60F4| < 0x6065."""
    window = 4000  # 0.06 rev
    drive.write(0x6065, window)
    drive.enable(8)
    start = drive.read(0x6064)
    worst = 0
    for n in range(1, 751):  # 1.5 s of 2 rev x (1 - cos), 12.6 rev/s at most
        target = start + round(2 * REV * (1.0 - math.cos(2.0 * math.pi * n * PERIOD_S)))
        drive.write(0x607A, target)
        drive.cycle()
        status = drive.status
        assert status & (SW_BIT12 | SW_BIT13) == SW_BIT12
        error = drive.read(0x60F4)
        assert abs(error) <= window
        worst = max(worst, abs(error))
    assert worst > 0  # the trajectory moved the axis
    assert abs(drive.read(0x6064) - target) <= window


def test_csp_target_in_an_rpdo_every_sync(drive: Drive402) -> None:
    """CSP with 0x607A mapped into RPDO2 by the master (python-canopen's PDO API)."""
    drive.node.nmt.state = "PRE-OPERATIONAL"
    wait_until(lambda: drive.rack.nmt_state("l_arm") == "PRE-OPERATIONAL", "PRE-OPERATIONAL")
    rpdo2 = drive.node.rpdo[2]
    rpdo2.clear()
    rpdo2.add_variable(0x607A)
    rpdo2.trans_type = 1
    rpdo2.enabled = True
    rpdo2.save()
    drive.node.nmt.state = "OPERATIONAL"
    wait_until(lambda: drive.rack.nmt_state("l_arm") == "OPERATIONAL", "OPERATIONAL")
    window = 4000
    drive.write(0x6065, window)
    drive.enable(8)
    start = drive.read(0x6064)
    for n in range(1, 601):  # 1 s of 2 rev x (1 - cos), then holding 0.2 s
        phase = 2.0 * math.pi * min(n, 500) * PERIOD_S
        target = start + round(2 * REV * (1.0 - math.cos(phase)))
        rpdo2[0x607A].raw = target
        rpdo2.transmit()
        drive.cycle()
        assert drive.read(0x6062) == target  # taken at this SYNC
        assert abs(drive.read(0x60F4)) <= window
        assert drive.status & (SW_BIT12 | SW_BIT13) == SW_BIT12
    assert abs(drive.read(0x6064) - target) <= drive.read(0x6067)


def test_csp_following_error_faults_with_emcy_8611(drive: Drive402) -> None:
    """CSP: a jump beyond a small 0x6065 -> bit 13, EMCY 0x8611, FAULT (CiA 402-2)."""
    drive.write(0x6065, 1000)
    drive.write(0x6066, 0)
    drive.enable(8)
    start = drive.read(0x6064)
    drive.write(0x607A, start + 10 * REV)
    drive.cycle()
    status = drive.status
    assert status & 0x4F == SW_FAULT
    assert status & SW_BIT13
    assert drive.read(0x603F) == EMCY_FOLLOWING_ERROR
    wait_until(
        lambda: any(e.code == EMCY_FOLLOWING_ERROR for e in drive.node.emcy.log), "EMCY 0x8611"
    )


# --- mode changes while enabled -------------------------------------------------------------


@pytest.mark.parametrize(("moving_in", "switch_to"), [(3, 8), (1, 8), (3, 1), (3, 6)])
def test_moving_to_a_position_mode_is_bumpless(
    drive: Drive402, moving_in: int, switch_to: int
) -> None:
    """PV (or PP) at 5 rev/s, then CSP holding 0x6064, or PP / HM stopping on their ramps.

    CSP holding at speed asks the velocity PI for a step of its error from 0 to -v; PP and HM
    without a set-point stop from the actual velocity on 0x6084 / 0x609A, so the error stays
    near 0. Re-based at the switch (`DriveLoops.set_mode`), the current changes in each cycle
    by about the integral action, kp dt / Ti |v| (2.5 A here), never by the proportional
    step kp |v| (12 A).
    """
    _profile(drive, 5 * REV, 40 * REV, 40 * REV)
    drive.write(0x60FF, 5 * REV)
    drive.enable(moving_in)
    if moving_in == 1:
        drive.write(0x607A, drive.read(0x6064) + 30 * REV)
        drive.control(CW_ENABLED | CW_NEW_SET_POINT)
        drive.cycle()
        drive.control(CW_ENABLED)
    drive.cycle(300)  # 0.6 s: at speed, settled
    current_before, velocity_before = drive.read(0x6078), drive.read(0x606C)
    drive.write(0x607A, drive.read(0x6064))  # CiA 402-2: the master sets 0x607A first
    drive.set_mode(switch_to)
    config = drive.rack.config
    v_joint = velocity_before / drive.increments_per_joint  # rad/s
    kp, ti_s = config.velocity_kp_a_per_rad_s, config.velocity_ti_s
    integral_step = kp * PERIOD_S / ti_s * abs(v_joint) * 100.0  # per mille of 10 A
    proportional_step = kp * abs(v_joint) * 100.0
    assert proportional_step > 4.0 * integral_step  # the bound tells the two apart
    # Each of the first cycles changes the current by about the integral action (and the
    # position loop's growing correction): no step of kp |v| in any of them.
    current, velocity = current_before, velocity_before
    for _ in range(5):
        drive.cycle()
        current, last_current = drive.read(0x6078), current
        velocity, last_velocity = drive.read(0x606C), velocity
        assert abs(current - last_current) <= 1.5 * integral_step
        # The speed changes by what that current decelerates in one cycle: < 10 % of it.
        assert abs(velocity - last_velocity) <= 0.1 * velocity_before
    drive.cycle_until(lambda: abs(drive.read(0x606C)) < drive.read(0x606F), "stopped", 1.0)
    assert drive.status & SW_BIT13 == 0


def test_pp_moving_to_pv_is_bumpless(drive: Drive402) -> None:
    """PP cruising at 10 rev/s, then PV at the same 0x60FF: the speed carries on."""
    _profile(drive, 10 * REV, 40 * REV, 40 * REV)
    drive.write(0x60FF, 10 * REV)
    drive.enable(1)
    drive.write(0x607A, drive.read(0x6064) + 30 * REV)
    drive.control(CW_ENABLED | CW_NEW_SET_POINT)
    drive.cycle()
    drive.control(CW_ENABLED)
    drive.cycle(300)  # 0.6 s: cruising since 0.25 s
    current_before, velocity_before = drive.read(0x6078), drive.read(0x606C)
    drive.set_mode(3)
    for _ in range(50):
        drive.cycle()
        assert abs(drive.read(0x606C) - velocity_before) <= drive.read(0x606D)
        assert abs(drive.read(0x6078) - current_before) <= 50
    assert drive.status & SW_TARGET_REACHED


# --- every mode ---------------------------------------------------------------------------


PIVOT: tuple[str, dict[str, float]] = ("pivot", {})


@pytest.mark.parametrize("drive", [PIVOT], indirect=True)
@pytest.mark.parametrize("code", sorted(MODES))
def test_the_worm_gear_holds_the_pivot_with_the_power_stage_off(drive: Drive402, code: int) -> None:
    """Zero command, then the power stage disabled: the pivot under gravity does not move."""
    drive.enable(code)
    if code == 8:
        drive.write(0x607A, drive.read(0x6064))
    drive.cycle(50)
    drive.control(0x06)  # shutdown: READY TO SWITCH ON, no current
    drive.cycle()
    assert drive.status & 0x6F == 0x21
    before = drive.joint_position
    drive.cycle(250)  # 0.5 s
    assert drive.read(0x6078) == 0
    assert abs(drive.joint_position - before) < 1e-6


def test_without_the_worm_gears_self_locking_the_pivot_falls(
    lockstep_rack: Callable[..., tuple[VirtualDriveRack, canopen.Network]],
    reversible_robot: RobotParams,
) -> None:
    """The check above can fail: on reversible gears the unpowered pivot runs down."""
    drive = _drive402(*lockstep_rack(robot=reversible_robot), "pivot")
    drive.enable(10)
    drive.control(0x06)
    drive.cycle()
    before = drive.joint_position
    drive.cycle(250)
    assert drive.joint_position < before - 1e-3


@pytest.mark.parametrize("code", sorted(MODES))
def test_0x6061_reports_each_mode(drive: Drive402, code: int) -> None:
    """0x6061 reads back each supported 0x6060 (BaseNode402's op_mode too)."""
    drive.set_mode(code)
    assert drive.node.op_mode == MODES[code]


@pytest.mark.parametrize("code", [2, 7])
def test_unsupported_modes_abort(drive: Drive402, code: int) -> None:
    """0x6060 = 2 (velocity) or 7 (interpolated position): SDO abort 0x06090030."""
    drive.set_mode(10)
    with pytest.raises(SdoAbortedError) as aborted:
        drive.write(0x6060, code)
    assert aborted.value.code == ABORT_VALUE_RANGE
    assert drive.read(0x6061) == 10
