"""The motion profile generator of the CiA 402-2 profile modes (pure: time is passed in).

0x6086 motion profile type 0, linear ramp: a trapezoidal velocity, accelerating with 0x6083
while the speed grows and decelerating with 0x6084 while it falls, cruising at 0x6081 clamped
to 0x607F. A plan is a few constant-acceleration segments from the present demand (position and
velocity), so a new target mid-move (change set immediately) or a halt never jumps the velocity;
a positioning ends exactly at its target. docs/can-modes.md, "The profile generator".

Units: motor-side encoder increments (0x608F), increments/s and increments/s^2, as floats; the
caller rounds to the objects' integers at the object boundary (0x6062 is the rounded demand).

    gen = ProfileGenerator(position_inc=0.0)
    gen.move_to(65536.0, ProfileParams(6553.6, 13107.2, 13107.2, 65536.0))
    gen.step(0.001)    # ProfilePoint(position_inc=..., velocity_inc_s=13.1...)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lca_sim.errors import InvalidValueError

# 0x6086 motion profile type: 0 linear ramp (trapezoidal). sin^2 (-1 in old drafts, 1 in
# CiA 402-2) and the jerk-limited types are not offered.
MOTION_PROFILE_LINEAR = 0
MOTION_PROFILE_TYPES: frozenset[int] = frozenset({MOTION_PROFILE_LINEAR})

# 0x605D halt option code (CiA 402-2): 1 slow down on the slow-down ramp (0x6084, in homing
# 0x609A), 2 on the quick-stop ramp (0x6085). 3 (current limit) and 4 (voltage limit) need a
# drive that stops by its limits; the virtual drive does not offer them (refused on write).
HALT_SLOW_DOWN_RAMP = 1
HALT_QUICK_STOP_RAMP = 2
HALT_OPTIONS: frozenset[int] = frozenset({HALT_SLOW_DOWN_RAMP, HALT_QUICK_STOP_RAMP})

_LANDING_TOLERANCE = 1e-9  # relative: a stop that overshoots the target by less still lands


@dataclass(frozen=True, slots=True)
class ProfileParams:
    """The ramp of the profile modes (CiA 402-2 factor-free: increments, s).

    Attributes:
        velocity_inc_s: profile velocity 0x6081, >= 0.
        acceleration_inc_s2: profile acceleration 0x6083, > 0.
        deceleration_inc_s2: profile deceleration 0x6084, > 0.
        quick_stop_deceleration_inc_s2: quick stop deceleration 0x6085, > 0.
        max_velocity_inc_s: max profile velocity 0x607F, >= 0 (clamps 0x6081 and 0x60FF).
    """

    velocity_inc_s: float
    acceleration_inc_s2: float
    deceleration_inc_s2: float
    quick_stop_deceleration_inc_s2: float
    max_velocity_inc_s: float = math.inf

    def __post_init__(self) -> None:
        for name in ("velocity_inc_s", "max_velocity_inc_s"):
            value = getattr(self, name)
            if math.isnan(value) or value < 0.0:
                raise InvalidValueError(f"profile {name} must be >= 0, got {value!r}")
        for name in (
            "acceleration_inc_s2",
            "deceleration_inc_s2",
            "quick_stop_deceleration_inc_s2",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise InvalidValueError(f"profile {name} must be finite and > 0, got {value!r}")

    @property
    def cruise_velocity_inc_s(self) -> float:
        """0x6081 clamped to 0x607F."""
        return min(self.velocity_inc_s, self.max_velocity_inc_s)

    def halt_deceleration_inc_s2(self, halt_option: int) -> float:
        """The deceleration a halt uses for a 0x605D option code (`HALT_OPTIONS`).

        Raises:
            InvalidValueError: an option code the drive does not offer.
        """
        if halt_option == HALT_SLOW_DOWN_RAMP:
            return self.deceleration_inc_s2
        if halt_option == HALT_QUICK_STOP_RAMP:
            return self.quick_stop_deceleration_inc_s2
        raise InvalidValueError(f"0x605D halt option {halt_option} is not one of 1, 2")


@dataclass(frozen=True, slots=True)
class ProfilePoint:
    """The demand of the moment: position (0x6062) and velocity, increments and increments/s."""

    position_inc: float
    velocity_inc_s: float


@dataclass(frozen=True, slots=True)
class Segment:
    """Constant acceleration from `start_s` for `duration_s` (inf: for ever)."""

    start_s: float
    duration_s: float
    position_inc: float
    velocity_inc_s: float
    acceleration_inc_s2: float

    @property
    def end_s(self) -> float:
        """When the segment ends."""
        return self.start_s + self.duration_s

    def at(self, t_s: float) -> ProfilePoint:
        """The point at plan time `t_s` (within or past the segment: extrapolated)."""
        tau = t_s - self.start_s
        a = self.acceleration_inc_s2
        return ProfilePoint(
            self.position_inc + self.velocity_inc_s * tau + 0.5 * a * tau * tau,
            self.velocity_inc_s + a * tau,
        )


@dataclass(frozen=True, slots=True)
class Plan:
    """Segments in time order, then `end` held for ever (None: the last segment goes on)."""

    segments: tuple[Segment, ...]
    end: ProfilePoint | None

    @property
    def duration_s(self) -> float:
        """When the plan reaches its end point or its final velocity."""
        finite = [s.end_s for s in self.segments if math.isfinite(s.duration_s)]
        return max(finite, default=0.0)

    def at(self, t_s: float) -> ProfilePoint:
        """The demand at plan time `t_s` >= 0."""
        for segment in self.segments:
            if t_s < segment.end_s:
                return segment.at(t_s)
        if self.end is not None:
            return self.end
        return self.segments[-1].at(t_s)


class _Builder:
    """Appends segments, keeping the running time, position and velocity."""

    def __init__(self, position_inc: float, velocity_inc_s: float) -> None:
        self.t_s = 0.0
        self.position_inc = position_inc
        self.velocity_inc_s = velocity_inc_s
        self.segments: list[Segment] = []

    def ramp(self, to_velocity_inc_s: float, acceleration_inc_s2: float) -> None:
        """To `to_velocity_inc_s` at the magnitude `acceleration_inc_s2`."""
        dv = to_velocity_inc_s - self.velocity_inc_s
        if dv == 0.0:
            return
        self.hold(abs(dv) / acceleration_inc_s2, math.copysign(acceleration_inc_s2, dv))
        self.velocity_inc_s = to_velocity_inc_s  # exact, not the sum's rounding

    def hold(self, duration_s: float, acceleration_inc_s2: float = 0.0) -> None:
        """Constant acceleration for `duration_s`."""
        if duration_s <= 0.0:
            return
        seg = Segment(
            self.t_s, duration_s, self.position_inc, self.velocity_inc_s, acceleration_inc_s2
        )
        self.segments.append(seg)
        end = seg.at(seg.end_s)
        self.t_s, self.position_inc, self.velocity_inc_s = seg.end_s, *_astuple(end)

    def stop(self, deceleration_inc_s2: float) -> None:
        """To standstill, landing exactly where v^2 / 2d says."""
        v = self.velocity_inc_s
        stop_at = self.position_inc + v * abs(v) / (2.0 * deceleration_inc_s2)
        self.ramp(0.0, deceleration_inc_s2)
        self.position_inc = stop_at


def _astuple(point: ProfilePoint) -> tuple[float, float]:
    return point.position_inc, point.velocity_inc_s


def plan_move(start: ProfilePoint, target_inc: float, params: ProfileParams) -> Plan:
    """A positioning from `start` to rest at `target_inc` (linear ramp).

    From rest: accelerate with a to v_p, cruise, decelerate with d, where
    v_p = min(v_max, sqrt((2 a d D + d u^2) / (a + d))) for the distance D and the initial
    speed u towards the target (a triangle when v_p < v_max). Moving away from the target, or
    too fast to stop before it, the plan first stops with d and then moves back. Faster than
    v_max towards it, it decelerates to v_max with d first.
    """
    a, d = params.acceleration_inc_s2, params.deceleration_inc_s2
    v_max = params.cruise_velocity_inc_s
    build = _Builder(*_astuple(start))
    u0 = build.velocity_inc_s
    distance = target_inc - build.position_inc
    direction = math.copysign(1.0, distance if distance != 0.0 else u0)
    u = u0 * direction
    reach = abs(distance) * (1.0 + _LANDING_TOLERANCE) + _LANDING_TOLERANCE
    if u < 0.0 or u * u / (2.0 * d) > reach:
        build.stop(d)
        distance = target_inc - build.position_inc
        direction = math.copysign(1.0, distance)
        u = 0.0
    if distance == 0.0:
        return Plan(tuple(build.segments), ProfilePoint(target_inc, 0.0))
    if v_max <= 0.0:  # 0x6081 or 0x607F is 0: no move, only a stop
        build.stop(d)
        return Plan(tuple(build.segments), ProfilePoint(build.position_inc, 0.0))
    span = abs(distance)
    if u <= v_max:
        peak = min(v_max, max(u, math.sqrt((2.0 * a * d * span + d * u * u) / (a + d))))
        build.ramp(direction * peak, a)
    else:
        peak = v_max
        build.ramp(direction * peak, d)
    travelled = abs(build.position_inc - (target_inc - distance))
    build.hold((span - travelled - peak * peak / (2.0 * d)) / peak)
    build.stop(d)
    return Plan(tuple(build.segments), ProfilePoint(target_inc, 0.0))


def plan_velocity(start: ProfilePoint, target_inc_s: float, params: ProfileParams) -> Plan:
    """A ramp from `start` to `target_inc_s` (clamped to +-0x607F), then that speed for ever.

    The speed falls with d (0x6084) and grows with a (0x6083); through zero it does both.
    """
    a, d = params.acceleration_inc_s2, params.deceleration_inc_s2
    limit = params.max_velocity_inc_s
    target = max(-limit, min(limit, target_inc_s))
    build = _Builder(*_astuple(start))
    v = build.velocity_inc_s
    if v * target < 0.0:
        build.ramp(0.0, d)
        v = 0.0
    build.ramp(target, a if abs(target) > abs(v) else d)
    tail = Segment(build.t_s, math.inf, build.position_inc, target, 0.0)
    return Plan((*build.segments, tail), None)


def plan_stop(start: ProfilePoint, deceleration_inc_s2: float) -> Plan:
    """To standstill from `start` with `deceleration_inc_s2` (a halt or a quick stop)."""
    build = _Builder(*_astuple(start))
    build.stop(deceleration_inc_s2)
    return Plan(tuple(build.segments), ProfilePoint(build.position_inc, 0.0))


class ProfileGenerator:
    """Steps a plan; a new plan starts from the demand of the moment (no velocity jump).

    Args:
        position_inc: the demand to start from (the actual position: bumpless).
        velocity_inc_s: the demand velocity to start from.
    """

    def __init__(self, position_inc: float = 0.0, velocity_inc_s: float = 0.0) -> None:
        self._plan: Plan
        self._t_s: float
        self._point: ProfilePoint
        self.reset(position_inc, velocity_inc_s)

    @property
    def point(self) -> ProfilePoint:
        """The present demand."""
        return self._point

    @property
    def done(self) -> bool:
        """The plan has reached its end point (positioning, stop) or its final velocity."""
        return self._t_s >= self._plan.duration_s

    @property
    def remaining_s(self) -> float:
        """Plan time left until `done`."""
        return max(0.0, self._plan.duration_s - self._t_s)

    def reset(self, position_inc: float, velocity_inc_s: float = 0.0) -> None:
        """Start over at this demand, holding its velocity (a mode's generator on entry)."""
        point = ProfilePoint(position_inc, velocity_inc_s)
        if velocity_inc_s == 0.0:
            self._plan = Plan((), point)
        else:
            self._plan = Plan((Segment(0.0, math.inf, position_inc, velocity_inc_s, 0.0),), None)
        self._t_s = 0.0
        self._point = point

    def shift(self, offset_inc: float) -> None:
        """Move the whole plan by `offset_inc` (the position frame moved: homing)."""
        plan = self._plan
        segments = tuple(
            Segment(s.start_s, s.duration_s, s.position_inc + offset_inc, s.velocity_inc_s,
                    s.acceleration_inc_s2)
            for s in plan.segments
        )  # fmt: skip
        end = plan.end
        if end is not None:
            end = ProfilePoint(end.position_inc + offset_inc, end.velocity_inc_s)
        self._plan = Plan(segments, end)
        self._point = ProfilePoint(
            self._point.position_inc + offset_inc, self._point.velocity_inc_s
        )

    def move_to(self, target_inc: float, params: ProfileParams) -> None:
        """Position to `target_inc` from the present demand."""
        self._start(plan_move(self._point, target_inc, params))

    def run_at(self, velocity_inc_s: float, params: ProfileParams) -> None:
        """Ramp to `velocity_inc_s` from the present demand and keep it."""
        self._start(plan_velocity(self._point, velocity_inc_s, params))

    def stop(self, deceleration_inc_s2: float) -> None:
        """Decelerate to standstill from the present demand."""
        self._start(plan_stop(self._point, deceleration_inc_s2))

    def step(self, dt_s: float) -> ProfilePoint:
        """Advance by `dt_s` >= 0 and return the demand.

        Raises:
            InvalidValueError: a negative or non-finite time step.
        """
        if not (math.isfinite(dt_s) and dt_s >= 0.0):
            raise InvalidValueError(f"dt_s must be finite and >= 0, got {dt_s!r}")
        self._t_s += dt_s
        self._point = self._plan.at(self._t_s)
        return self._point

    def _start(self, plan: Plan) -> None:
        self._plan = plan
        self._t_s = 0.0
