"""Per-joint drive modes on the real plant model: the drive's loops ahead of its current loop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lca_control.drive_loops import DriveMode, paper_drive_loops
from lca_sim.config.loader import load_robot
from lca_sim.errors import InvalidValueError
from lca_sim.model import kernel
from lca_sim.model.commanded_plant import CommandedPlant
from lca_sim.model.drive_modes import JointDriveLoops, check_drive_modes
from lca_sim.model.plant import Plant, PlantConfig, build_plant

JOINTS = ("l_arm", "pivot", "c_arc", "lift")
PIVOT = 1
PERIOD_S = 0.004  # lca_control.cascade.CONTROL_PERIOD_S
PERIOD_STEPS = 40  # of the 0.1 ms model step
LOOPS = paper_drive_loops(20.0)  # 316.23 A per rad/s, Ti 10 ms, kp 15 1/s, 0.2 rad/s
START_RAD = 0.6109  # the pivot at 35 deg (config/ros/simulator.yaml)


def _plant(modes: tuple[str, ...], interface: str = "current") -> Plant:
    plant = build_plant(
        PlantConfig(
            robot=load_robot("default"),
            dt_s=1e-4,
            rigid_body_update_steps=10,
            joints=JOINTS,
            interface=interface,
            current_kp_v_per_a=31.62,
            current_ti_s=1e-3,
            max_abs_command=50.0,
        )
    )
    plant.sim.reset({"pivot": START_RAD})
    plant.commanded.use_drive_modes(modes, LOOPS, PERIOD_S)
    return plant


def _pivot_run(commanded: CommandedPlant, periods: int) -> tuple[np.ndarray, np.ndarray]:
    """The pivot's position and velocity after each of `periods` drive cycles."""
    xs, ws = np.empty(periods), np.empty(periods)
    for k in range(periods):
        commanded.advance(PERIOD_STEPS)
        xs[k] = commanded.sim.state_array[kernel.X_POSITION, PIVOT]
        ws[k] = commanded.sim.state_array[kernel.X_VELOCITY, PIVOT]
    return xs, ws


def test_a_velocity_joint_reaches_and_holds_the_commanded_velocity() -> None:
    """0.05 rad/s asked of the pivot: from 1.5 s to 2 s it runs at it within 0.1 %."""
    plant = _plant(("current", "velocity", "current", "current"))
    assert plant.commanded.command_targets(DriveMode.VELOCITY, [0.0, 0.05, 0.0, 0.0]) is None
    _, w = _pivot_run(plant.commanded, 500)
    assert np.max(np.abs(w[375:] - 0.05)) < 5e-5
    assert w.max() < 0.05 * 1.3  # the PI's overshoot on the geared inertia: about 15 %
    held = plant.sim.state_array[kernel.X_POSITION, [0, 2, 3]]
    assert held == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)  # 0 A: the worm gears hold


def test_a_position_joint_moves_to_its_target_and_the_worm_gear_holds_it() -> None:
    """The pivot from 35 deg to 0.7 rad: there within 2e-5 rad after 1.5 s, held at 0 A after."""
    plant = _plant(("current", "position", "current", "current"))
    commanded = plant.commanded
    assert commanded.command_targets(DriveMode.POSITION, [math.nan, 0.7, 0.0, 0.0]) is None
    x, w = _pivot_run(commanded, 375)
    assert np.max(np.abs(x[-50:] - 0.7)) < 2e-5
    assert np.max(np.abs(w)) <= LOOPS.velocity_limit * 1.1  # the cap + 5 % PI overshoot
    commanded.hold_zero()  # e.g. a command timeout: 0 A, the loops halt
    x_held, _ = _pivot_run(commanded, 250)
    assert np.all(x_held == x[-1])  # self-locking: not a nanoradian of back-driving
    assert plant.sim.state_array[kernel.X_CURRENT, PIVOT] == pytest.approx(0.0, abs=1e-6)


def test_the_loops_start_halted_and_current_joints_keep_their_current_commands() -> None:
    """Before any target the loop joints get 0 A; current joints take current_commands."""
    plant = _plant(("current", "position", "current", "velocity"))
    commanded = plant.commanded
    assert commanded.command([0.0, math.nan, 2.0, 7.0]) is None  # pivot, lift: ignored
    commanded.advance(PERIOD_STEPS)
    assert list(commanded.target) == [0.0, 0.0, 2.0, 0.0]


def test_odd_advances_run_the_same_drive_cycles_as_whole_periods() -> None:
    """Realtime advances of 7 steps at a time give, step for step, the lockstep run's state."""
    whole, odd = (_plant(("current", "position", "current", "current")) for _ in range(2))
    for plant in (whole, odd):
        plant.commanded.command_targets(DriveMode.POSITION, [0.0, 0.65, 0.0, 0.0])
    whole.commanded.advance(7 * PERIOD_STEPS)
    for _ in range(PERIOD_STEPS):
        odd.commanded.advance(7)
    assert np.array_equal(whole.sim.state_array, odd.sim.state_array)


def test_a_position_beyond_the_end_stop_is_saturated_to_it() -> None:
    """3 rad asked of the pivot (end stop 2 rad): the target is 2 rad, counted as saturated."""
    plant = _plant(("current", "position", "current", "current"))
    commanded = plant.commanded
    assert commanded.command_targets(DriveMode.POSITION, [0.0, 3.0, 0.0, 0.0]) is None
    assert commanded.counters.saturated == 1
    assert commanded.drive is not None
    commanded.advance(PERIOD_STEPS)
    assert commanded.drive.loops[PIVOT].position_target == 2.0


def test_targets_for_a_mode_no_joint_runs_are_refused() -> None:
    """Velocity targets with only position joints: refused with the reason, counted."""
    plant = _plant(("current", "position", "current", "current"))
    reason = plant.commanded.command_targets(DriveMode.VELOCITY, [0.0, 0.1, 0.0, 0.0])
    assert reason == "no joint runs velocity mode (drive_modes)"
    wrong_length = plant.commanded.command_targets(DriveMode.POSITION, [0.7])
    assert wrong_length is not None and "expected 4 values" in wrong_length
    assert plant.commanded.counters.rejected_length == 2


def test_all_current_modes_are_the_plain_current_interface() -> None:
    """drive_modes all current: no loops, the plant as without drive modes."""
    assert _plant(("current",) * 4).commanded.drive is None
    assert _plant(("voltage",) * 4, interface="voltage").commanded.drive is None


@pytest.mark.parametrize(
    ("modes", "message"),
    [
        (("position", "velocity"), "expected 4 modes"),
        (("position", "torque", "current", "current"), "unknown \\['torque'\\]"),
        (("voltage", "position", "current", "current"), "voltage mixed with other modes"),
    ],
)
def test_invalid_drive_modes_are_refused_with_the_reason(
    modes: tuple[str, ...], message: str
) -> None:
    """Wrong length, an unknown name, voltage mixed with the loop modes."""
    with pytest.raises(InvalidValueError, match=message):
        check_drive_modes(modes, JOINTS)


def test_modes_that_do_not_fit_the_interface_or_dt_are_refused() -> None:
    """Loop modes need the current interface; the period is a whole multiple of dt."""
    with pytest.raises(InvalidValueError, match="need the current interface"):
        _plant(("position",) * 4, interface="voltage")
    plant = _plant(("current",) * 4)
    with pytest.raises(InvalidValueError, match="whole multiple of dt"):
        plant.commanded.use_drive_modes(("velocity",) * 4, LOOPS, 0.00415)
    with pytest.raises(InvalidValueError, match="need the voltage interface"):
        plant.commanded.use_drive_modes(("voltage",) * 4, LOOPS, PERIOD_S)


def test_a_target_for_a_current_joint_or_nan_is_refused() -> None:
    """JointDriveLoops: a current joint takes no target; a NaN target is no target."""
    loops = JointDriveLoops([DriveMode.CURRENT, DriveMode.VELOCITY], LOOPS, PERIOD_STEPS)
    with pytest.raises(InvalidValueError, match="runs current mode"):
        loops.set_target(0, 0.1)
    with pytest.raises(InvalidValueError, match="must be finite"):
        loops.set_target(1, math.nan)
    assert loops.halted
    loops.set_target(1, 0.1)
    assert not loops.halted
    assert loops.velocity_targets == (0.0, 0.1)
