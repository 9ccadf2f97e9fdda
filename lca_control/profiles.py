"""Built-in velocity reference profiles (pure functions of time, no clock).

`RampProfile` replays the paper's Fig. 15: the velocity rises linearly, is held, then returns to
zero. `TrapezoidProfile` is the usual point-to-point move. Both give the velocity reference and
the displacement it integrates to (for the optional position loop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lca_control.pi import ControlParamError


def _check(name: str, value: float, *, positive: bool = False) -> None:
    if not math.isfinite(value) or value < 0.0 or (positive and value == 0.0):
        raise ControlParamError(f"{name} must be {'> 0' if positive else '>= 0'}, got {value!r}")


@dataclass(frozen=True, slots=True)
class RampProfile:
    """A velocity ramp: 0, then linear up to end_velocity over ramp_s, held hold_s, then 0.

    Units: s, and rad/s (m/s for the lift) for the velocity.
    """

    start_s: float
    ramp_s: float
    end_velocity: float
    hold_s: float = 0.0

    def __post_init__(self) -> None:
        _check("start_s", self.start_s)
        _check("ramp_s", self.ramp_s, positive=True)
        _check("hold_s", self.hold_s)
        if not math.isfinite(self.end_velocity):
            raise ControlParamError(f"end_velocity must be finite, got {self.end_velocity!r}")

    @property
    def end_s(self) -> float:
        """When the reference is back at zero."""
        return self.start_s + self.ramp_s + self.hold_s

    def velocity(self, t_s: float) -> float:
        """The velocity reference at t_s."""
        u = t_s - self.start_s
        if u <= 0.0 or t_s >= self.end_s:
            return 0.0
        if u < self.ramp_s:
            return self.end_velocity * u / self.ramp_s
        return self.end_velocity

    def displacement(self, t_s: float) -> float:
        """The integral of the velocity reference from 0 to t_s."""
        u = min(max(t_s - self.start_s, 0.0), self.ramp_s + self.hold_s)
        if u <= self.ramp_s:
            return 0.5 * self.end_velocity * u * u / self.ramp_s
        return self.end_velocity * (0.5 * self.ramp_s + (u - self.ramp_s))


@dataclass(frozen=True, slots=True)
class TrapezoidProfile:
    """Accelerate to cruise_velocity over accel_s, cruise for cruise_s, decelerate over decel_s."""

    start_s: float
    accel_s: float
    cruise_s: float
    decel_s: float
    cruise_velocity: float

    def __post_init__(self) -> None:
        _check("start_s", self.start_s)
        _check("accel_s", self.accel_s, positive=True)
        _check("cruise_s", self.cruise_s)
        _check("decel_s", self.decel_s, positive=True)
        if not math.isfinite(self.cruise_velocity):
            raise ControlParamError(f"cruise_velocity must be finite, got {self.cruise_velocity!r}")

    @property
    def end_s(self) -> float:
        """When the move is over."""
        return self.start_s + self.accel_s + self.cruise_s + self.decel_s

    def velocity(self, t_s: float) -> float:
        """The velocity reference at t_s."""
        u = t_s - self.start_s
        v = self.cruise_velocity
        if u <= 0.0 or t_s >= self.end_s:
            return 0.0
        if u < self.accel_s:
            return v * u / self.accel_s
        if u < self.accel_s + self.cruise_s:
            return v
        return v * (self.end_s - t_s) / self.decel_s

    def displacement(self, t_s: float) -> float:
        """The integral of the velocity reference from 0 to t_s."""
        v = self.cruise_velocity
        u = min(max(t_s - self.start_s, 0.0), self.end_s - self.start_s)
        if u <= self.accel_s:
            return 0.5 * v * u * u / self.accel_s
        moved = 0.5 * v * self.accel_s
        if u <= self.accel_s + self.cruise_s:
            return moved + v * (u - self.accel_s)
        moved += v * self.cruise_s
        left = self.end_s - self.start_s - u
        return moved + 0.5 * v * (self.decel_s - left * left / self.decel_s)


Profile = RampProfile | TrapezoidProfile
