"""The PI core and the cascade against analytic and python-control responses (section 6)."""

from __future__ import annotations

import math

import control as ct
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_control.cascade import (
    PAPER_CURRENT_KP_V_PER_A,
    PAPER_CURRENT_TI_S,
)
from lca_control.pi import ControlParamError, PIController, PIParams
from lca_control.profiles import RampProfile, TrapezoidProfile
from lca_sim import RobotParams, Simulator
from lca_sim.analysis.paper import current_step

WIDE = PIParams(kp=2.0, ti_s=0.5, output_min=-1e9, output_max=1e9)


def test_constant_error_gives_the_analytic_pi_ramp() -> None:
    """u(t) = Kp e (1 + t / Ti) for a constant error, sample by sample."""
    pi = PIController(WIDE)
    dt = 1e-3
    for k in range(1, 1001):
        u = pi.update(1.5, 0.5, dt)
        assert u == pytest.approx(2.0 * 1.0 * (1.0 + k * dt / 0.5), rel=1e-12)


def test_negative_setpoint_mirrors_positive() -> None:
    """The PI is linear: a negated error gives the negated output."""
    up, down = PIController(WIDE), PIController(WIDE)
    for k in range(200):
        e = math.sin(0.05 * k)
        assert down.update(-e, 0.0, 1e-3) == -up.update(e, 0.0, 1e-3)


def test_first_order_plant_matches_python_control() -> None:
    """PI around 1/(tau s + 1), discretised finely, tracks python-control's step response."""
    tau_s, kp, ti_s, dt = 0.05, 3.0, 0.02, 1e-5
    s = ct.tf("s")
    closed = ct.feedback(kp * (1 + 1 / (ti_s * s)) / (tau_s * s + 1), 1)
    t = np.arange(0, 0.3, 1e-3)
    _, expected = ct.step_response(closed, t)
    pi = PIController(PIParams(kp, ti_s, -1e6, 1e6))
    y = 0.0
    got = []
    steps_per_sample = round(1e-3 / dt)
    for _ in t:
        got.append(y)
        for _ in range(steps_per_sample):
            u = pi.update(1.0, y, dt)
            y += dt * (u - y) / tau_s
    np.testing.assert_allclose(got, np.ravel(expected), atol=2e-3)


def test_output_stays_within_limits_and_does_not_wind_up() -> None:
    """Saturated for 1 s, the PI leaves the limit as soon as the error changes sign."""
    limited = PIParams(kp=1.0, ti_s=0.01, output_min=-2.0, output_max=2.0)
    pi = PIController(limited)
    for _ in range(1000):
        assert pi.update(10.0, 0.0, 1e-3) == 2.0
    assert pi.integral <= 2.0
    # Without clamping the integral would be about 1000; with it one step of negative error
    # already pulls the output below the limit.
    assert pi.update(-1.0, 0.0, 1e-3) < 2.0 - 0.9


@given(
    errors=st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=50),
    kp=st.floats(0.0, 100.0),
    ti_s=st.floats(1e-4, 10.0),
)
def test_output_always_within_limits(errors: list[float], kp: float, ti_s: float) -> None:
    """Whatever the errors and gains, the output never leaves [min, max]."""
    pi = PIController(PIParams(kp, ti_s, -3.0, 5.0))
    for e in errors:
        assert -3.0 <= pi.update(e, 0.0, 1e-3) <= 5.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_or_inf_sample_is_rejected(bad: float) -> None:
    """A non-finite sample holds the last output, leaves the state alone, and is counted."""
    pi = PIController(WIDE)
    before = pi.update(1.0, 0.0, 1e-3)
    integral = pi.integral
    assert pi.update(bad, 0.0, 1e-3) == before
    assert pi.update(1.0, bad, 1e-3) == before
    assert (pi.integral, pi.rejected_samples) == (integral, 2)


@pytest.mark.parametrize(
    ("kwargs", "word"),
    [
        ({"kp": -1.0}, "kp"),
        ({"kp": math.nan}, "kp"),
        ({"ti_s": 0.0}, "ti_s"),
        ({"ti_s": math.nan}, "ti_s"),
        ({"output_min": 1.0, "output_max": 1.0}, "output_min"),
        ({"output_max": math.inf}, "limits"),
    ],
)
def test_bad_params_are_refused(kwargs: dict[str, float], word: str) -> None:
    """Gains that cannot work raise a ControlParamError naming the field."""
    args = {"kp": 1.0, "ti_s": 1.0, "output_min": -1.0, "output_max": 1.0, **kwargs}
    with pytest.raises(ControlParamError, match=word):
        PIParams(**args)


def test_bad_dt_is_refused() -> None:
    """The core never guesses a period: dt <= 0 raises."""
    with pytest.raises(ControlParamError, match="dt_s"):
        PIController(WIDE).update(1.0, 0.0, 0.0)


def test_parameter_change_is_bumpless() -> None:
    """Retuning Kp and Ti mid-run leaves the output where it was."""
    pi = PIController(WIDE)
    for _ in range(100):
        before = pi.update(0.7, 0.2, 1e-3)
    pi.set_params(PIParams(kp=8.0, ti_s=0.05, output_min=-1e9, output_max=1e9))
    after = pi.update(0.7, 0.2, 1e-9)  # same error, a vanishing step
    assert after == pytest.approx(before, rel=1e-6)


def test_reset_is_bumpless_to_a_given_output() -> None:
    """reset(output) makes the next zero-error update return that output."""
    pi = PIController(WIDE)
    pi.update(3.0, 0.0, 1e-3)
    pi.reset(1.25)
    assert pi.update(0.0, 0.0, 1e-3) == 1.25


def test_ti_infinite_is_pure_p() -> None:
    """Ti = inf removes the integral action."""
    pi = PIController(PIParams(2.0, math.inf, -10.0, 10.0))
    assert [pi.update(1.0, 0.0, 1e-3) for _ in range(3)] == [2.0, 2.0, 2.0]


def test_profiles_integrate_to_their_displacement() -> None:
    """The displacement of each profile is the integral of its velocity."""
    ramp = RampProfile(start_s=1.0, ramp_s=10.0, end_velocity=math.radians(5.0), hold_s=0.5)
    trap = TrapezoidProfile(
        start_s=0.5, accel_s=1.0, cruise_s=2.0, decel_s=1.5, cruise_velocity=-0.1
    )
    for profile in (ramp, trap):
        t = np.linspace(0.0, profile.end_s + 1.0, 200_001)
        v = np.array([profile.velocity(x) for x in t])
        integral = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
        for k in range(0, len(t), 20_000):
            # a jump of v costs the trapezoid rule v dt / 2 (< 1e-5 here)
            assert profile.displacement(float(t[k])) == pytest.approx(integral[k], abs=1e-5)
    # Fig. 15: 5 deg/s after 10 s of ramp, 25 deg of travel
    assert math.degrees(ramp.displacement(11.0)) == pytest.approx(25.0)


def test_paper_current_step_fig13(default_robot: RobotParams) -> None:
    """Fig. 13: a 5 A step, response time about 3 ms and overshoot about 24 %.

    The paper's t_r is the 5 % response time (temps de reponse a 5 %), see docs/control.md.
    """
    step = current_step(default_robot, 5.0, 0.05)
    i = step.current_a
    final = i[-1]
    assert final == pytest.approx(5.0, abs=0.01)
    assert step.overshoot_pct == pytest.approx(24.0, abs=5.0)
    assert step.response_time_s == pytest.approx(3e-3, abs=1e-3)
    # The figures are python-control's step_info of the same samples (5 % settling band).
    info = ct.step_info(i, T=step.time_s, SettlingTimeThreshold=0.05)
    assert step.response_time_s == pytest.approx(info["SettlingTime"], abs=1e-4)  # one sample
    assert step.overshoot_pct == pytest.approx(info["Overshoot"])
    assert step.rise_time_s == pytest.approx(info["RiseTime"], abs=1e-4)
    # And it is exactly the sampled RL loop python-control predicts, which has no back-EMF: the
    # rotor is locked.
    # ZOH plant at the model step, PI with the backward-Euler integral of lca_control.
    motor = default_robot.axes[1].motor
    dt = 1e-4
    plant = ct.sample_system(
        ct.tf([1.0], [motor.inductance_h, motor.resistance_ohm]), dt, method="zoh"
    )
    z = ct.tf([1.0, 0.0], [1.0], dt)
    pi = PAPER_CURRENT_KP_V_PER_A * (1 + dt / PAPER_CURRENT_TI_S * z / (z - 1))
    closed = ct.feedback(pi * plant, 1)
    _, expected = ct.step_response(5.0 * closed, np.arange(len(i) + 1) * dt)
    np.testing.assert_allclose(i, np.ravel(expected)[1:], atol=1e-6)


@pytest.mark.parametrize("hold_steps", [1, 7])
def test_in_drive_current_loops_are_the_lca_control_pi(
    default_robot: RobotParams, hold_steps: int
) -> None:
    """CommandedPlant's compiled current loops give, sample for sample, PIController's voltages.

    A 30 A command saturates (the amplifier limit clamps the pivot's PI and freezes its
    integral), then a live retune and a reversal exercise the bumpless re-base. With the
    rigid-body terms held for 7 steps, a hold straddles the 40-step call: the step-by-step and
    the whole-period paths must still agree bit for bit.
    """
    from lca_sim.model.commanded_plant import CommandedPlant

    sim_drive = Simulator(default_robot, dt_s=1e-4, rigid_body_update_steps=hold_steps)
    sim_ref = Simulator(default_robot, dt_s=1e-4, rigid_body_update_steps=hold_steps)
    gains = PIParams(PAPER_CURRENT_KP_V_PER_A, PAPER_CURRENT_TI_S, -1.0, 1.0)
    plant = CommandedPlant(
        sim=sim_drive,
        joints=("pivot", "lift"),
        interface="current",
        current_pi=gains,
        max_abs_command=100.0,
    )
    limits = [a.motor.voltage_limit_v for a in default_robot.axes]
    loops = {a: PIController(PIParams(gains.kp, gains.ti_s, -limits[a], limits[a])) for a in (1, 3)}
    volts = np.zeros(4)
    saturated = 0
    for phase, command in enumerate(([3.0, 30.0], [3.0, -2.0])):
        if phase == 1:
            plant.set_current_gains(10.0, 5e-3)
            for a, loop in loops.items():
                loop.set_params(PIParams(10.0, 5e-3, -limits[a], limits[a]))
        assert plant.command(command) is None
        targets = {1: min(command[0], plant.current_limit_a), 3: min(command[1], 20.0)}
        for _ in range(300):
            for a, loop in loops.items():
                volts[a] = loop.update(targets[a], float(sim_ref.state_array[2, a]), 1e-4)
            saturated += int(abs(volts[3]) == limits[3])
            sim_ref.step(volts)
            plant.advance(1)
            np.testing.assert_array_equal(plant.current_loop_outputs_v, volts)
            np.testing.assert_array_equal(sim_drive.state_array, sim_ref.state_array)
    assert saturated > 10  # the limit and the frozen integral were really exercised
    assert volts[0] == volts[2] == 0.0  # axes outside `joints` get no voltage
    # A whole control period in one call (as the simulator node and the CAN rack advance).
    for _ in range(40):
        for a, loop in loops.items():
            volts[a] = loop.update(-2.0 if a == 3 else 3.0, float(sim_ref.state_array[2, a]), 1e-4)
        sim_ref.step(volts)
    plant.advance(40)
    np.testing.assert_array_equal(sim_drive.state_array, sim_ref.state_array)
    assert sim_drive.time_s == sim_ref.time_s
