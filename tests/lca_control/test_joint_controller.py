"""JointController on plant time: repeated stamps are skipped, time going back is a restart."""

from __future__ import annotations

import pytest

from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.controller import (
    PLANT_TIME_TOLERANCE_S,
    JointController,
    validate_controller_params,
)

DT_S = CONTROL_PERIOD_S  # the plant's state period, s
STEPS_1_S = round(1.0 / DT_S)  # one second of states
POSITIONS = [0.0, 0.6, 0.0, 0.0]


def _controller(**values: object) -> JointController:
    defaults: dict[str, object] = {
        "reference_source": "ramp",
        "command_interface": "current",
        "ramp_start_s": 0.0,
        "ramp_duration_s": 1.0,
    }
    defaults.update(values)
    return JointController(validate_controller_params(defaults))


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
