"""The drive's loops against analytic responses on a rigid inertia, and their properties."""

from __future__ import annotations

import math
from dataclasses import replace

import control as ct
import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from lca_control.drive_loops import DriveLoopParams, DriveLoops, DriveMode, paper_drive_loops
from lca_control.pi import ControlParamError, PIParams

LIMIT_A = 20.0
PARAMS = paper_drive_loops(LIMIT_A)  # Kp 316.23 A per rad/s, Ti 10 ms, kp 15 1/s, 0.2 rad/s
KP_V, TI_S = PARAMS.velocity.kp, PARAMS.velocity.ti_s
# A rigid inertia J dw/dt = K i with K / J = 100 / Kp: the velocity loop's crossover Kp K / J is
# then the paper's 100 rad/s, its poles s^2 + 100 s + 100 / Ti: wn = 100 rad/s, zeta = 0.5.
GAIN_PER_INERTIA = 100.0 / KP_V  # K / J, rad/s^2 per A


def _rigid(
    loops: DriveLoops, dt_s: float, n: int, **targets: float
) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities of the rigid inertia under the loops, from rest at 0."""
    x = w = 0.0
    xs, ws = np.empty(n), np.empty(n)
    for k in range(n):
        i = loops.update(dt_s, position=x, velocity=w, **targets)
        x += w * dt_s
        w += GAIN_PER_INERTIA * i * dt_s
        xs[k], ws[k] = x, w
    return xs, ws


def test_position_loop_over_an_ideal_velocity_loop_decays_with_time_constant_1_over_kp() -> None:
    """x(t) = x* (1 - exp(-kp t)) when the velocity follows the setpoint exactly."""
    loops = DriveLoops(PARAMS, DriveMode.POSITION)
    dt, target = 1e-4, 0.01  # kp x* = 0.15 rad/s: below the 0.2 rad/s cap
    x = 0.0
    for k in range(1, 3001):
        loops.update(dt, position=x, velocity=0.0, position_target=target)
        x += loops.velocity_setpoint * dt
        exact = target * (1.0 - (1.0 - PARAMS.position_kp_per_s * dt) ** k)
        assert x == pytest.approx(exact, rel=1e-9)
    assert x == pytest.approx(target * (1.0 - math.exp(-15.0 * 0.3)), rel=1e-3)


def test_velocity_pi_step_on_a_rigid_inertia_matches_the_closed_loop() -> None:
    """The step follows python-control's response of Kp (1 + 1/(Ti s)) K / (J s); no error left."""
    dt, n, step = 1e-5, 20_000, 0.01  # Kp step = 3.2 A: no saturation
    _, w = _rigid(DriveLoops(PARAMS, DriveMode.VELOCITY), dt, n, velocity_target=step)
    open_loop = ct.tf([KP_V * GAIN_PER_INERTIA * TI_S, KP_V * GAIN_PER_INERTIA], [TI_S, 0.0, 0.0])
    closed = ct.feedback(open_loop, 1)
    poles = sorted(ct.poles(closed), key=lambda p: p.imag)
    assert abs(poles[1]) == pytest.approx(100.0, rel=1e-9)  # wn
    assert -poles[1].real / abs(poles[1]) == pytest.approx(0.5, rel=1e-9)  # zeta
    t = dt * np.arange(1, n + 1)
    _, expected = ct.step_response(closed, t)
    assert np.max(np.abs(w - step * expected)) < 0.01 * step
    info = ct.step_info(closed)
    overshoot = 100.0 * (w.max() - step) / step
    assert overshoot == pytest.approx(info["Overshoot"], abs=0.5)  # about 30 %: the PI's zero
    assert w[-1] == pytest.approx(step, rel=1e-4)


def test_position_cascade_on_a_rigid_inertia_matches_the_closed_loop() -> None:
    """P over the velocity PI: python-control's response within 1 %, near first order, no overshoot.

    The outer loop's pole is -14.6 1/s (the inner pair -42.7 +- 91.8j); with the PI's zero the
    response stays within 10 % of x* (1 - exp(-kp t)).
    """
    dt, n, target = 1e-4, 8000, 0.002  # Kp kp x* = 9.5 A: no saturation
    x, _ = _rigid(DriveLoops(PARAMS, DriveMode.POSITION), dt, n, position_target=target)
    t = dt * np.arange(1, n + 1)
    s = ct.tf("s")
    velocity_loop = ct.feedback(KP_V * (1 + 1 / (TI_S * s)) * GAIN_PER_INERTIA / s, 1)
    closed = ct.feedback(PARAMS.position_kp_per_s * velocity_loop / s, 1)
    assert max(p.real for p in ct.poles(closed)) == pytest.approx(-14.633, abs=1e-3)
    _, expected = ct.step_response(closed, t)
    assert np.max(np.abs(x - target * expected)) < 0.01 * target
    first_order = target * (1.0 - np.exp(-PARAMS.position_kp_per_s * t))
    assert np.max(np.abs(x - first_order)) < 0.1 * target
    assert x.max() <= target
    assert x[-1] == pytest.approx(target, rel=1e-4)


def test_velocity_feedforward_removes_the_ramp_error() -> None:
    """A ramp x* = r t: error r / kp without feed-forward, none with it (ideal velocity loop)."""
    rate, dt = 0.1, 1e-3
    for gain, expected_error in ((0.0, rate / PARAMS.position_kp_per_s), (1.0, 0.0)):
        loops = DriveLoops(replace(PARAMS, velocity_feedforward_gain=gain), DriveMode.POSITION)
        x = 0.0
        for k in range(2000):
            loops.update(dt, position=x, velocity=0.0, position_target=rate * k * dt)
            x += loops.velocity_setpoint * dt
        assert rate * 2000 * dt - x == pytest.approx(expected_error, abs=1e-9)  # e at 2 s


def test_current_feedforward_adds_j_over_kt_n_times_the_acceleration() -> None:
    """Velocity mode, perfectly tracked ramp of 2 rad/s^2: the output is c * 2 A exactly."""
    c = 0.5  # A per rad/s^2
    loops = DriveLoops(replace(PARAMS, current_feedforward_a_per_rad_s2=c), DriveMode.VELOCITY)
    dt = 1e-3
    outputs = [
        loops.update(dt, position=0.0, velocity=2.0 * k * dt, velocity_target=2.0 * k * dt)
        for k in range(50)
    ]
    assert outputs[0] == 0.0  # no history yet
    assert outputs[1:] == pytest.approx([c * 2.0] * 49, rel=1e-9)


def test_current_mode_passes_the_target_through_within_the_limits() -> None:
    """Current mode: the setpoint is the target, clamped to +-20 A."""
    loops = DriveLoops(PARAMS)
    assert loops.update(4e-3, position=0.0, velocity=0.0, current_target_a=3.5) == 3.5
    assert loops.update(4e-3, position=0.0, velocity=0.0, current_target_a=-50.0) == -LIMIT_A


def test_a_large_position_step_is_capped_at_the_velocity_limit() -> None:
    """1 rad away at kp 15: the setpoint is the 0.2 rad/s cap."""
    loops = DriveLoops(PARAMS, DriveMode.POSITION)
    loops.update(4e-3, position=0.0, velocity=0.0, position_target=1.0)
    assert loops.velocity_setpoint == 0.2


def test_switch_from_velocity_to_position_at_rest_keeps_the_holding_current() -> None:
    """The integral's holding current carries over exactly: at rest the output does not move."""
    loops = DriveLoops(PARAMS, DriveMode.VELOCITY)
    for _ in range(100):  # a constant load: the integral builds up the holding current
        held = loops.update(4e-3, position=0.3, velocity=-0.001, velocity_target=0.0)
    loops.set_mode(DriveMode.POSITION, position=0.3, velocity=0.0)
    assert loops.update(4e-3, position=0.3, velocity=0.0) == held
    assert loops.position_target == 0.3


def test_reset_gives_zero_and_position_mode_then_holds_the_present_position() -> None:
    """After reset the output is 0, and a first position cycle at rest without target gives 0."""
    loops = DriveLoops(PARAMS, DriveMode.POSITION)
    for _ in range(20):
        loops.update(4e-3, position=0.0, velocity=0.05, position_target=0.5)
    loops.reset()
    assert loops.current_setpoint_a == 0.0
    assert loops.update(4e-3, position=0.7, velocity=0.0) == 0.0
    assert loops.position_target == 0.7


def test_non_finite_input_is_rejected_and_the_output_holds() -> None:
    """NaN in, the last output out, counted."""
    loops = DriveLoops(PARAMS, DriveMode.VELOCITY)
    u = loops.update(4e-3, position=0.0, velocity=0.0, velocity_target=0.01)
    assert loops.update(4e-3, position=0.0, velocity=math.nan, velocity_target=0.01) == u
    assert loops.update(4e-3, position=0.0, velocity=0.0, position_target=math.inf) == u
    assert loops.rejected_samples == 2
    with pytest.raises(ControlParamError, match="dt_s"):
        loops.update(0.0, position=0.0, velocity=0.0)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("position_kp_per_s", -1.0),
        ("position_kp_per_s", math.inf),
        ("velocity_limit", 0.0),
        ("velocity_feedforward_gain", 1.5),
        ("current_feedforward_a_per_rad_s2", -0.1),
    ],
)
def test_bad_parameters_are_refused(field: str, value: float) -> None:
    """Each bad value raises the control core's error naming the field."""
    with pytest.raises(ControlParamError, match=field):
        replace(PARAMS, **{field: value})  # type: ignore[arg-type]


def test_unknown_mode_names_the_valid_ones() -> None:
    """`torque` is not a drive mode here: the error lists position, velocity, current."""
    assert DriveMode.parse("velocity") is DriveMode.VELOCITY
    with pytest.raises(ControlParamError, match="position, velocity, current"):
        DriveMode.parse("torque")


MODES = st.sampled_from(list(DriveMode))
FINITE = st.floats(-1e3, 1e3)
SAMPLE = st.tuples(FINITE, FINITE, FINITE, FINITE, FINITE)


def _params(limit_a: float, velocity_limit: float, feedforward: float) -> DriveLoopParams:
    return DriveLoopParams(
        PIParams(KP_V, TI_S, -limit_a, limit_a),
        velocity_limit=velocity_limit,
        current_feedforward_a_per_rad_s2=feedforward,
    )


@given(
    MODES,
    st.lists(SAMPLE, min_size=1, max_size=30),
    st.floats(0.1, 50.0),
    st.floats(0.01, 5.0),
    st.floats(0.0, 10.0),
    st.floats(1e-5, 0.01),
)
def test_outputs_stay_within_the_current_and_velocity_limits(
    mode: DriveMode,
    samples: list[tuple[float, float, float, float, float]],
    limit_a: float,
    velocity_limit: float,
    feedforward: float,
    dt_s: float,
) -> None:
    """Any inputs: |current| <= the current limit, |velocity setpoint| <= velocity_limit."""
    loops = DriveLoops(_params(limit_a, velocity_limit, feedforward), mode)
    for x, w, x_ref, w_ref, i_ref in samples:
        i = loops.update(
            dt_s,
            position=x,
            velocity=w,
            position_target=x_ref,
            velocity_target=w_ref,
            current_target_a=i_ref,
        )
        assert abs(i) <= limit_a * (1.0 + 1e-12)
        assert abs(loops.velocity_setpoint) <= velocity_limit


@given(
    MODES,
    MODES,
    st.lists(SAMPLE, min_size=1, max_size=20),
    st.floats(-0.5, 0.5),
    st.floats(-0.2, 0.2),
)
def test_a_mode_switch_moves_the_output_only_by_the_pis_response(
    before: DriveMode,
    after: DriveMode,
    samples: list[tuple[float, float, float, float, float]],
    x: float,
    w: float,
) -> None:
    """Switch at any state, first cycle at that state holding it: |du| <= Kp dt / Ti |e|.

    Holding means no new position target (position mode) or the present velocity as the
    target (velocity mode); the bound grows by what the integral could not take when the
    re-based value would leave the current limits.
    """
    assume(after is not before)
    dt = 4e-3
    loops = DriveLoops(PARAMS, before)
    for x0, w0, x_ref, w_ref, i_ref in samples:
        loops.update(
            dt,
            position=x0,
            velocity=w0,
            position_target=x_ref,
            velocity_target=w_ref,
            current_target_a=i_ref,
        )
    u0 = loops.current_setpoint_a
    loops.set_mode(after, position=x, velocity=w)
    if after is DriveMode.CURRENT:
        assert loops.update(dt, position=x, velocity=w, current_target_a=u0) == u0
        return
    hold = {"velocity_target": w} if after is DriveMode.VELOCITY else {}
    u1 = loops.update(dt, position=x, velocity=w, **hold)
    error = -w if after is DriveMode.POSITION else 0.0
    rebase_loss = max(0.0, abs(u0 - KP_V * error) - LIMIT_A)
    assert abs(u1 - u0) <= KP_V * dt / TI_S * abs(error) + rebase_loss + 1e-9


@given(MODES, st.lists(SAMPLE, min_size=1, max_size=20), st.floats(-1.0, 1.0))
def test_reset_gives_zero_from_any_state(
    mode: DriveMode, samples: list[tuple[float, float, float, float, float]], x: float
) -> None:
    """After any history, reset: 0 A, and a first cycle at rest holding still gives 0 A."""
    loops = DriveLoops(PARAMS, mode)
    for x0, w0, x_ref, w_ref, i_ref in samples:
        loops.update(
            4e-3,
            position=x0,
            velocity=w0,
            position_target=x_ref,
            velocity_target=w_ref,
            current_target_a=i_ref,
        )
    loops.reset()
    assert loops.current_setpoint_a == 0.0
    assert loops.update(4e-3, position=x, velocity=0.0) == 0.0
