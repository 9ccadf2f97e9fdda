"""JointController on plant time and on the interfaces whose loops run in the drive.

Repeated stamps are skipped, time going back is a restart; the velocity and position interfaces
send set-points and run no cascade.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.controller import (
    PLANT_TIME_TOLERANCE_S,
    JointController,
    validate_controller_params,
)
from lca_control.profiles import RampProfile, TrapezoidProfile

DT_S = CONTROL_PERIOD_S  # the plant's state period, s
STEPS_1_S = round(1.0 / DT_S)  # one second of states
POSITIONS = [0.0, 0.6, 0.0, 0.0]


def _values(**values: object) -> dict[str, object]:
    defaults: dict[str, object] = {
        "reference_source": "ramp",
        "command_interface": "current",
        "ramp_start_s": 0.0,
        "ramp_duration_s": 1.0,
    }
    return defaults | values


def _controller(**values: object) -> JointController:
    return JointController(validate_controller_params(_values(**values)))


def _run(ctl: JointController, t0_s: float, steps: int) -> list[list[float] | None]:
    """Steps on a plant standing still (the velocity error grows the integrators)."""
    return [ctl.update(t0_s + k * DT_S, POSITIONS, [0.0] * 4, None) for k in range(steps)]


def test_a_repeated_or_slightly_older_stamp_is_skipped_and_no_restart() -> None:
    """The same stamp again (a re-sent state) gives no command and counts no restart."""
    ctl = _controller()
    _run(ctl, 0.0, 10)
    last_s = 9 * DT_S
    assert ctl.update(last_s, POSITIONS, [0.0] * 4, None) is None
    assert ctl.update(last_s - PLANT_TIME_TOLERANCE_S / 2, POSITIONS, [0.0] * 4, None) is None
    assert ctl.plant_restarts == 0
    assert ctl.elapsed_s == pytest.approx(last_s)


@pytest.mark.parametrize("restart_at_s", [0.0, 0.5, 1e9])
def test_time_going_back_restarts_loops_and_profile_like_a_new_controller(
    restart_at_s: float,
) -> None:
    """Plant time back (a restarted plant): counted once, then exactly a fresh controller."""
    ctl = _controller()
    _run(ctl, restart_at_s + 2.0, STEPS_1_S)  # 1 s at t0 + 2 s: integrators and profile wound up
    assert ctl.elapsed_s > 0.9
    after = _run(ctl, restart_at_s, 100)
    fresh = _run(_controller(), restart_at_s, 100)
    assert after == fresh  # the first command and every one after it
    assert all(command is not None for command in after)
    assert ctl.plant_restarts == 1
    assert ctl.last_restart_from_s == pytest.approx(restart_at_s + 2.0 + (STEPS_1_S - 1) * DT_S)
    assert ctl.elapsed_s == pytest.approx(99 * DT_S)


def test_a_topic_reference_from_before_the_restart_no_longer_counts() -> None:
    """A velocity reference stamped on the old time base is dropped at a restart."""
    ctl = _controller(reference_source="topic")
    _run(ctl, 5.0, 5)
    assert ctl.set_topic_reference([0.0, 0.1, 0.0, 0.0], 5.0 + 4 * DT_S) is None
    assert ctl.velocity_references(5.0 + 5 * DT_S, POSITIONS)[1] == 0.1
    ctl.update(0.0, POSITIONS, [0.0] * 4, None)
    assert ctl.plant_restarts == 1
    assert ctl.last_velocity_reference == [0.0] * 4


def test_a_state_without_currents_on_the_voltage_interface_is_no_restart() -> None:
    """Voltage commands need the currents: an older state without them changes nothing."""
    ctl = _controller(command_interface="voltage")
    for k in range(5):
        ctl.update(1.0 + k * DT_S, POSITIONS, [0.0] * 4, [0.0] * 4)
    assert ctl.update(0.0, POSITIONS, [0.0] * 4, None) is None
    assert ctl.plant_restarts == 0
    assert ctl.update(0.0, POSITIONS, [0.0] * 4, [0.0] * 4) is not None
    assert ctl.plant_restarts == 1


@pytest.mark.parametrize("gap_s", [0.6, 30.0])
def test_a_forward_jump_beyond_the_plant_timeout_restarts_like_a_new_controller(
    gap_s: float,
) -> None:
    """A wall-clock plant back after a gap: counted once, then exactly a fresh controller.

    Without it, the first step after the gap would integrate the velocity error over the
    whole gap (dt = gap_s), winding the integrators far past anything a period can.
    """
    ctl = _controller()
    _run(ctl, 100.0, STEPS_1_S)
    last_s = 100.0 + (STEPS_1_S - 1) * DT_S
    after = _run(ctl, last_s + gap_s, 100)
    fresh = _run(_controller(), last_s + gap_s, 100)
    assert after == fresh
    assert ctl.plant_restarts == 1
    assert ctl.last_restart_from_s == pytest.approx(last_s)


def test_a_gap_within_the_plant_timeout_is_one_long_period_not_a_restart() -> None:
    """A late state (a gap under plant_timeout_s, 0.5 s by default) is no restart."""
    ctl = _controller()
    _run(ctl, 100.0, STEPS_1_S)
    last_s = 100.0 + (STEPS_1_S - 1) * DT_S
    assert ctl.update(last_s + 0.4, POSITIONS, [0.0] * 4, None) is not None
    assert ctl.plant_restarts == 0
    assert ctl.elapsed_s == pytest.approx((STEPS_1_S - 1) * DT_S + 0.4)


# --- velocity and position interfaces: the loops are closed in the drive ------------------


def _no_loop_ran(ctl: JointController) -> bool:
    """No cascade has been stepped: every integrator and output is still zero."""
    return all(
        c.velocity_loop.integral == 0.0
        and c.velocity_loop.output == 0.0
        and c.current_loop.integral == 0.0
        and c.current_setpoint_a == 0.0
        for c in ctl.cascades
    )


@settings(max_examples=40, deadline=None)
@given(
    start_s=st.floats(0.0, 0.5),
    duration_s=st.floats(0.05, 1.0),
    end_velocity=st.floats(-0.5, 0.5),
    hold_s=st.floats(0.0, 0.5),
    drift=st.lists(st.floats(-0.2, 0.2), min_size=4, max_size=4),
)
def test_position_setpoints_are_the_ramps_positions_at_the_sampled_times(
    start_s: float, duration_s: float, end_velocity: float, hold_s: float, drift: list[float]
) -> None:
    """Set-point(t_k) = first measured position + displacement(t_k); no current is computed.

    What the plant reads after the first state (here drifting away) changes nothing.
    """
    ctl = _controller(
        command_interface="position",
        ramp_start_s=start_s,
        ramp_duration_s=duration_s,
        ramp_end_velocity=end_velocity,
        ramp_hold_s=hold_s,
    )
    ramp = RampProfile(start_s, duration_s, end_velocity, hold_s)
    t0_s = 3.0
    for k in range(round((ramp.end_s + 0.1) / DT_S)):
        measured = POSITIONS if k == 0 else [p + d for p, d in zip(POSITIONS, drift, strict=True)]
        t_rel = k * DT_S
        commands = ctl.update(t0_s + t_rel, measured, [0.0] * 4, None)
        assert commands is not None
        expected = [0.0, 0.6 + ramp.displacement(t_rel), 0.0, 0.0]
        assert commands == pytest.approx(expected, abs=1e-12)
        assert ctl.last_velocity_reference[1] == pytest.approx(ramp.velocity(t_rel), abs=1e-12)
    assert commands is not None
    assert commands[1] == pytest.approx(0.6 + end_velocity * (duration_s / 2 + hold_s), abs=1e-9)
    assert _no_loop_ran(ctl)


def test_position_setpoints_of_a_trapezoid_end_at_its_distance() -> None:
    """0.1 rad/s, 1 s up, 2 s cruise, 1 s down: 0.3 rad moved, the other joints held."""
    ctl = _controller(
        command_interface="position",
        reference_source="trapezoid",
        trapezoid_start_s=0.0,
        trapezoid_accel_s=1.0,
        trapezoid_cruise_s=2.0,
        trapezoid_decel_s=1.0,
        trapezoid_velocity=0.1,
    )
    profile = TrapezoidProfile(0.0, 1.0, 2.0, 1.0, 0.1)
    commands = _run(ctl, 0.0, 5 * STEPS_1_S)
    assert commands[STEPS_1_S] == pytest.approx([0.0, 0.6 + profile.displacement(1.0), 0.0, 0.0])
    assert commands[-1] == pytest.approx([0.0, 0.9, 0.0, 0.0], abs=1e-12)


def test_position_setpoints_integrate_a_topic_velocity_until_it_is_stale() -> None:
    """0.1 rad/s for 100 periods of 4 ms moves the set-point 40 mrad; stale, it stands."""
    ctl = _controller(command_interface="position", reference_source="topic")
    assert ctl.update(0.0, POSITIONS, [0.0] * 4, None) == POSITIONS  # the first state's pose
    ctl.set_topic_reference([0.0, 0.1, 0.0, -0.05], 0.0)
    for k in range(1, 101):
        commands = ctl.update(k * DT_S, POSITIONS, [0.0] * 4, None)
    assert commands == pytest.approx([0.0, 0.64, 0.0, -0.02])
    later = [ctl.update(0.6 + k * DT_S, POSITIONS, [0.0] * 4, None) for k in range(3)]
    assert later == [commands] * 3  # 0.6 s after the reference: older than 0.5 s
    assert _no_loop_ran(ctl)


def test_position_disabled_holds_the_measured_pose_and_reenabling_is_bumpless() -> None:
    """Disabled: the measured positions; enabled again the set-points move on from there."""
    values = _values(command_interface="position", ramp_end_velocity=0.1)
    ctl = JointController(validate_controller_params(values))
    _run(ctl, 0.0, 100)
    ctl.set_params(validate_controller_params(values | {"enabled": False}))
    here = [0.1, 0.7, -0.1, 0.2]
    assert ctl.update(100 * DT_S, here, [0.0] * 4, None) == here
    ctl.set_params(validate_controller_params(values))
    ctl.reset()  # what the node does on enable
    ramp = RampProfile(0.0, 1.0, 0.1)
    first = ctl.update(101 * DT_S, POSITIONS, [0.0] * 4, None)
    second = ctl.update(102 * DT_S, POSITIONS, [0.0] * 4, None)
    assert first == here
    assert second is not None
    moved = ramp.displacement(102 * DT_S) - ramp.displacement(101 * DT_S)
    assert second == pytest.approx([0.1, 0.7 + moved, -0.1, 0.2], abs=1e-12)


@given(switch_step=st.integers(1, 400))
@settings(max_examples=20, deadline=None)
def test_a_new_reference_source_moves_on_from_the_setpoints_in_force(switch_step: int) -> None:
    """Ramp to hold at any instant: the set-point stays where it was (bumpless)."""
    ctl = _controller(command_interface="position", ramp_end_velocity=0.2)
    before = _run(ctl, 0.0, switch_step)[-1]
    hold = _values(command_interface="position", reference_source="hold")
    ctl.set_params(validate_controller_params(hold))
    after = _run(ctl, switch_step * DT_S, 50)
    assert after == [before] * 50


def test_position_interface_without_a_setpoint_sends_nothing_for_a_bad_state() -> None:
    """A NaN first state has no safe set-point (0 would move every joint); later the last one."""
    ctl = _controller(command_interface="position")
    assert ctl.update(0.0, [math.nan, 0.6, 0.0, 0.0], [0.0] * 4, None) is None
    good = ctl.update(DT_S, POSITIONS, [0.0] * 4, None)
    assert ctl.update(2 * DT_S, [math.nan, 0.6, 0.0, 0.0], [0.0] * 4, None) == good
    assert ctl.bad_states == 2


def test_position_interface_restarts_like_a_new_controller() -> None:
    """Plant time back: the set-points start again from the new first state."""
    ctl = _controller(command_interface="position")
    _run(ctl, 2.0, STEPS_1_S)
    after = _run(ctl, 0.0, 100)
    assert after == _run(_controller(command_interface="position"), 0.0, 100)
    assert ctl.plant_restarts == 1
    assert ctl.update(-5.0, [math.nan, 0.6, 0.0, 0.0], [0.0] * 4, None) is None  # none yet


@pytest.mark.parametrize("kp_per_s", [0.0, 2.0])
def test_velocity_interface_sends_the_velocity_references_and_runs_no_loop(
    kp_per_s: float,
) -> None:
    """Velocity commands = the reference (with the optional position P law); no current."""
    ctl = _controller(command_interface="velocity", position_kp_per_s=kp_per_s)
    ramp = RampProfile(0.0, 1.0, math.radians(5.0))
    lagging = [0.0, 0.55, 0.0, 0.0]  # the pivot 50 mrad behind its start pose
    ctl.update(0.0, POSITIONS, [0.0] * 4, None)
    t_s = 0.5
    commands = ctl.update(t_s, lagging, [0.0] * 4, None)
    error = 0.6 + ramp.displacement(t_s) - 0.55
    expected = min(ramp.velocity(t_s) + kp_per_s * error, 0.2)
    assert commands == pytest.approx([0.0, expected, 0.0, 0.0])
    assert ctl.last_velocity_reference == commands
    assert _no_loop_ran(ctl)
