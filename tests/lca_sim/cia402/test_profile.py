"""The linear-ramp profile generator (lca_sim.cia402.profile): analytic trapezoids, properties.

Rest to rest over D with v, a, d: a trapezoid of duration v/a + v/d + (D - v^2/2a - v^2/2d)/v
when D is long enough to cruise, else a triangle peaking at sqrt(2adD / (a + d)). For all inputs
(hypothesis): the speed never exceeds 0x6081 (or the speed a retarget started from), it grows no
faster than 0x6083 and falls no faster than 0x6084, a positioning ends exactly on its target, and
a retarget never jumps the velocity.
"""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_sim.cia402.profile import (
    HALT_QUICK_STOP_RAMP,
    HALT_SLOW_DOWN_RAMP,
    ProfileGenerator,
    ProfileParams,
    ProfilePoint,
    plan_move,
)
from lca_sim.errors import InvalidValueError

REV = 65536.0
SLOW = ProfileParams(1000.0, 500.0, 250.0, 5000.0)

speeds = st.floats(10.0, 1e7)
ramps = st.floats(10.0, 1e8)
params_st = st.builds(ProfileParams, speeds, ramps, ramps, ramps)


def _run(gen: ProfileGenerator, dt_s: float) -> list[ProfilePoint]:
    """Step until the plan is done (and one step more); the samples."""
    points = [gen.point]
    steps = math.ceil(gen.remaining_s / dt_s) + 2
    while not gen.done:
        points.append(gen.step(dt_s))
        steps -= 1
        assert steps > 0, "the plan does not end when it said"
    points.append(gen.step(dt_s))
    return points


def _check_limits(
    points: list[ProfilePoint], params: ProfileParams, dt_s: float, v_allowed: float
) -> None:
    """Speed within `v_allowed`; |v| grows at most a dt and falls at most d dt per step."""
    a, d = params.acceleration_inc_s2, params.deceleration_inc_s2
    slack = 1e-9 * max(v_allowed, a * dt_s, d * dt_s) + 1e-9
    for before, after in itertools.pairwise(points):
        v0, v1 = before.velocity_inc_s, after.velocity_inc_s
        assert abs(v1) <= v_allowed * (1 + 1e-12) + slack
        if v0 * v1 >= 0.0:
            change = abs(v1) - abs(v0)
            assert change <= a * dt_s + slack
            assert -change <= d * dt_s + slack
        else:  # through zero within the step: slowed with d, then sped up with a
            assert abs(v1 - v0) <= max(a, d) * dt_s + slack


def test_trapezoid_duration_and_peak() -> None:
    """10000 inc at 1000 inc/s, a 500, d 250: 2 s up, 4 s down, 7 s cruise: 13 s, peak 1000."""
    gen = ProfileGenerator(0.0)
    gen.move_to(10000.0, SLOW)
    assert gen.remaining_s == pytest.approx(13.0)
    points = _run(gen, 0.01)
    assert max(p.velocity_inc_s for p in points) == pytest.approx(1000.0)
    assert points[-1] == ProfilePoint(10000.0, 0.0)
    gen.move_to(10000.0, SLOW)
    assert gen.done


def test_triangle_when_too_short_to_cruise() -> None:
    """100 inc: peak sqrt(2 a d D / (a + d)) = 182.57 inc/s, duration peak/a + peak/d."""
    peak = math.sqrt(2 * 500.0 * 250.0 * 100.0 / 750.0)
    gen = ProfileGenerator(5000.0)
    gen.move_to(4900.0, SLOW)
    assert gen.remaining_s == pytest.approx(peak / 500.0 + peak / 250.0)
    points = _run(gen, 1e-3)
    assert min(p.velocity_inc_s for p in points) == pytest.approx(-peak, rel=1e-3)
    assert points[-1].position_inc == 4900.0


def test_max_profile_velocity_clamps_the_profile_velocity() -> None:
    """0x607F below 0x6081: the cruise is at 0x607F."""
    params = ProfileParams(1000.0, 500.0, 500.0, 500.0, max_velocity_inc_s=400.0)
    gen = ProfileGenerator()
    gen.move_to(4000.0, params)
    assert max(p.velocity_inc_s for p in _run(gen, 0.01)) == pytest.approx(400.0)
    # 0.8 s up and 0.8 s down (160 inc each), 3680 inc at 400 inc/s (9.2 s): 10.8 s
    assert plan_move(ProfilePoint(0.0, 0.0), 4000.0, params).duration_s == pytest.approx(10.8)


def test_velocity_ramp_reaches_its_speed_after_v_over_a() -> None:
    """PV: from rest to 2000 inc/s at 500 inc/s^2 takes 4 s, covering v^2 / 2a = 4000 inc."""
    gen = ProfileGenerator(100.0)
    gen.run_at(2000.0, ProfileParams(0.0, 500.0, 250.0, 5000.0))
    assert gen.remaining_s == pytest.approx(4.0)
    point = gen.step(4.0)
    assert point.velocity_inc_s == pytest.approx(2000.0)
    assert point.position_inc == pytest.approx(4100.0)
    # reversing: down to 0 with d (8 s), then up to -1000 with a (2 s)
    gen.run_at(-1000.0, ProfileParams(0.0, 500.0, 250.0, 5000.0))
    assert gen.remaining_s == pytest.approx(10.0)
    assert gen.step(10.0).velocity_inc_s == pytest.approx(-1000.0)
    assert gen.step(5.0).velocity_inc_s == -1000.0


def test_stop_lands_at_v_squared_over_2d() -> None:
    """A halt at 1000 inc/s on 0x6084 = 250: 4 s, 2000 inc; on 0x6085 = 5000: 0.2 s, 100 inc."""
    for option, stop_s, distance in ((HALT_SLOW_DOWN_RAMP, 4.0, 2000.0),
                                     (HALT_QUICK_STOP_RAMP, 0.2, 100.0)):  # fmt: skip
        gen = ProfileGenerator(0.0, 1000.0)
        gen.stop(SLOW.halt_deceleration_inc_s2(option))
        assert gen.remaining_s == pytest.approx(stop_s)
        assert gen.step(stop_s + 1.0) == ProfilePoint(distance, 0.0)
    with pytest.raises(InvalidValueError, match="0x605D"):
        SLOW.halt_deceleration_inc_s2(3)


def test_moving_away_from_the_target_stops_first() -> None:
    """At -1000 inc/s with the target ahead: stop (4 s, to -2000), then move back to +100."""
    gen = ProfileGenerator(0.0, -1000.0)
    gen.move_to(100.0, SLOW)
    points = _run(gen, 1e-3)
    assert min(p.position_inc for p in points) == pytest.approx(-2000.0, abs=1e-6)
    assert points[-1] == ProfilePoint(100.0, 0.0)
    _check_limits(points, SLOW, 1e-3, 1000.0)


def test_zero_profile_velocity_only_stops() -> None:
    """0x6081 = 0: no positioning; a moving demand stops and stays there."""
    params = ProfileParams(0.0, 500.0, 250.0, 5000.0)
    gen = ProfileGenerator(0.0)
    gen.move_to(1000.0, params)
    assert gen.done and gen.step(1.0) == ProfilePoint(0.0, 0.0)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"velocity_inc_s": -1.0},
        {"acceleration_inc_s2": 0.0},
        {"deceleration_inc_s2": math.inf},
        {"quick_stop_deceleration_inc_s2": math.nan},
        {"max_velocity_inc_s": math.nan},
    ],
)
def test_bad_profile_parameters_raise(kwargs: dict[str, float]) -> None:
    """A ramp must be finite and > 0, a velocity >= 0: InvalidValueError names the field."""
    values = {
        "velocity_inc_s": 1.0,
        "acceleration_inc_s2": 1.0,
        "deceleration_inc_s2": 1.0,
        "quick_stop_deceleration_inc_s2": 1.0,
    }
    with pytest.raises(InvalidValueError, match=next(iter(kwargs))):
        ProfileParams(**{**values, **kwargs})
    with pytest.raises(InvalidValueError, match="dt_s"):
        ProfileGenerator().step(-1e-3)


@given(
    params=params_st,
    start=st.floats(-1e7, 1e7),
    distance=st.floats(-1e7, 1e7),
    steps=st.integers(50, 400),
)
def test_positioning_keeps_its_limits_and_ends_on_target(
    params: ProfileParams, start: float, distance: float, steps: int
) -> None:
    """Rest to rest: within v / a / d at every step, exactly on the target at the end."""
    gen = ProfileGenerator(start)
    gen.move_to(start + distance, params)
    dt = max(gen.remaining_s, 1e-6) / steps
    points = _run(gen, dt)
    _check_limits(points, params, dt, params.cruise_velocity_inc_s)
    assert points[-1] == ProfilePoint(start + distance, 0.0)


@given(
    params=params_st,
    retarget=params_st,
    distance=st.floats(-1e6, 1e6),
    new_target=st.floats(-1e6, 1e6),
    fraction=st.floats(0.0, 1.0),
)
def test_retarget_never_jumps_the_velocity(
    params: ProfileParams,
    retarget: ProfileParams,
    distance: float,
    new_target: float,
    fraction: float,
) -> None:
    """Change set immediately mid-move, with new ramps: continuous velocity, lands on target."""
    gen = ProfileGenerator(0.0)
    gen.move_to(distance, params)
    dt = max(gen.remaining_s, 1e-6) / 200
    for _ in range(int(fraction * 200)):
        gen.step(dt)
    before = gen.point
    gen.move_to(new_target, retarget)
    assert gen.point == before  # the new plan starts at the present demand
    dt2 = max(gen.remaining_s, 1e-6) / 300
    points = _run(gen, dt2)
    allowed = max(retarget.cruise_velocity_inc_s, abs(before.velocity_inc_s))
    _check_limits(points, retarget, dt2, allowed)
    assert points[-1] == ProfilePoint(new_target, 0.0)
