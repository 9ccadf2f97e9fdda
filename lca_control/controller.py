"""The controller's core: references, per-joint cascades, command arrays (pure, no ROS).

`JointController` is what the controller node runs on every new plant state: it picks each
joint's velocity reference (topic, built-in profile, or hold), runs the cascades and returns the
command array in joint order, in volts or in amps.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from lca_control.cascade import (
    PAPER_CURRENT_KP_V_PER_A,
    PAPER_CURRENT_TI_S,
    PAPER_VELOCITY_KP_A_PER_RAD_S,
    PAPER_VELOCITY_TI_S,
    AxisCascade,
    CascadeParams,
)
from lca_control.pi import ControlParamError, PIParams
from lca_control.profiles import Profile, RampProfile, TrapezoidProfile

REFERENCE_SOURCES = ("topic", "ramp", "trapezoid", "hold")

# name -> (default, description). Units in the names; joint-side velocities in rad/s (m/s).
CONTROLLER_PARAMETERS: dict[str, tuple[Any, str]] = {
    "joints": (["l_arm", "pivot", "c_arc", "lift"], "joint order of commands and references"),
    "command_interface": (
        "voltage",
        "voltage (both loops here) or current (current loop in the drive)",
    ),
    "reference_source": ("topic", "topic (velocity_reference), ramp, trapezoid or hold"),
    "profile_joint": ("pivot", "the joint a built-in profile moves; the others hold"),
    "ramp_start_s": (1.0, "ramp: start time after the first state, s"),
    "ramp_duration_s": (10.0, "ramp: time to reach the end velocity, s"),
    "ramp_end_velocity": (math.radians(5.0), "ramp: final velocity, rad/s (m/s)"),
    "ramp_hold_s": (0.0, "ramp: time the end velocity is held, s"),
    "trapezoid_start_s": (1.0, "trapezoid: start time, s"),
    "trapezoid_accel_s": (1.0, "trapezoid: acceleration time, s"),
    "trapezoid_cruise_s": (2.0, "trapezoid: cruise time, s"),
    "trapezoid_decel_s": (1.0, "trapezoid: deceleration time, s"),
    "trapezoid_velocity": (math.radians(5.0), "trapezoid: cruise velocity, rad/s (m/s)"),
    "velocity_kp_a_per_rad_s": (PAPER_VELOCITY_KP_A_PER_RAD_S, "velocity PI gain, A per rad/s"),
    "velocity_ti_s": (PAPER_VELOCITY_TI_S, "velocity PI integral time, s"),
    "current_kp_v_per_a": (PAPER_CURRENT_KP_V_PER_A, "current PI gain, V/A"),
    "current_ti_s": (PAPER_CURRENT_TI_S, "current PI integral time, s"),
    "current_limit_a": (20.0, "current setpoint limit, A"),
    "voltage_limit_v": (300.0, "voltage command limit, V"),
    "position_kp_per_s": (0.0, "outer position loop gain, 1/s (0: velocity control only)"),
    "velocity_limit": (0.2, "position loop velocity cap, rad/s (m/s)"),
    "reference_timeout_s": (0.5, "topic reference older than this counts as zero, s"),
    "nominal_period_s": (0.004, "dt used for the very first state, s"),
    "enabled": (True, "compute commands; disabled sends zeros"),
}
READ_ONLY = frozenset({"joints", "command_interface"})


@dataclass(frozen=True, slots=True)
class ControllerParams:
    """Validated controller parameters."""

    joints: tuple[str, ...]
    command_interface: str
    reference_source: str
    profile_joint: str
    profile: Profile | None
    cascade: CascadeParams
    reference_timeout_s: float
    nominal_period_s: float
    enabled: bool


def _number(values: Mapping[str, Any], name: str) -> float:
    value = values[name]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ControlParamError(f"{name}: expected a finite number, got {value!r}")
    return float(value)


def validate_controller_params(values: Mapping[str, Any]) -> ControllerParams:
    """Check the parameters and build the typed params.

    Raises:
        ControlParamError: naming the parameter and what was expected.
    """
    joints = tuple(str(j) for j in values["joints"])
    if not joints or len(set(joints)) != len(joints):
        raise ControlParamError(f"joints: expected distinct joint names, got {list(joints)}")
    interface = str(values["command_interface"])
    if interface not in ("voltage", "current"):
        raise ControlParamError(
            f"command_interface: expected voltage or current, got {interface!r}"
        )
    source = str(values["reference_source"])
    if source not in REFERENCE_SOURCES:
        raise ControlParamError(f"reference_source: expected one of {REFERENCE_SOURCES}")
    profile_joint = str(values["profile_joint"])
    if source in ("ramp", "trapezoid") and profile_joint not in joints:
        raise ControlParamError(
            f"profile_joint: expected one of {list(joints)}, got {profile_joint!r}"
        )
    profile: Profile | None = None
    if source == "ramp":
        profile = RampProfile(
            _number(values, "ramp_start_s"),
            _number(values, "ramp_duration_s"),
            _number(values, "ramp_end_velocity"),
            _number(values, "ramp_hold_s"),
        )
    elif source == "trapezoid":
        profile = TrapezoidProfile(
            _number(values, "trapezoid_start_s"),
            _number(values, "trapezoid_accel_s"),
            _number(values, "trapezoid_cruise_s"),
            _number(values, "trapezoid_decel_s"),
            _number(values, "trapezoid_velocity"),
        )
    current_limit = _number(values, "current_limit_a")
    voltage_limit = _number(values, "voltage_limit_v")
    if current_limit <= 0.0 or voltage_limit <= 0.0:
        raise ControlParamError("current_limit_a and voltage_limit_v must be > 0")
    cascade = CascadeParams(
        velocity=PIParams(
            _number(values, "velocity_kp_a_per_rad_s"),
            _number(values, "velocity_ti_s"),
            -current_limit,
            current_limit,
        ),
        current=PIParams(
            _number(values, "current_kp_v_per_a"),
            _number(values, "current_ti_s"),
            -voltage_limit,
            voltage_limit,
        ),
        position_kp_per_s=_number(values, "position_kp_per_s"),
        velocity_limit=_number(values, "velocity_limit"),
    )
    timeout = _number(values, "reference_timeout_s")
    period = _number(values, "nominal_period_s")
    if timeout <= 0.0 or period <= 0.0:
        raise ControlParamError("reference_timeout_s and nominal_period_s must be > 0")
    return ControllerParams(
        joints, interface, source, profile_joint, profile, cascade, timeout, period,
        bool(values["enabled"]),
    )  # fmt: skip


class JointController:
    """The cascades of every commanded joint, driven by plant states."""

    def __init__(self, params: ControllerParams) -> None:
        self.params = params
        self.cascades = [AxisCascade(params.cascade) for _ in params.joints]
        self._t0_s: float | None = None
        self._last_t_s: float | None = None
        self._hold_position: list[float] | None = None
        self._topic_reference: list[float] = [0.0] * len(params.joints)
        self._topic_reference_t_s = -math.inf
        self.last_velocity_reference: list[float] = [0.0] * len(params.joints)
        self.rejected_references = 0

    @property
    def elapsed_s(self) -> float:
        """Time since the first state (the profiles' time base)."""
        if self._t0_s is None or self._last_t_s is None:
            return 0.0
        return self._last_t_s - self._t0_s

    def set_params(self, params: ControllerParams) -> None:
        """Apply new gains or references without a bump."""
        self.params = params
        for cascade in self.cascades:
            cascade.set_params(params.cascade)

    def reset(self) -> None:
        """Zero the integrators (on enable)."""
        for cascade in self.cascades:
            cascade.reset()

    def set_topic_reference(self, values: Sequence[float], t_s: float) -> str | None:
        """Take a velocity reference array (joint order); return why it was refused, if so."""
        if len(values) != len(self.params.joints) or not all(math.isfinite(v) for v in values):
            self.rejected_references += 1
            return f"expected {len(self.params.joints)} finite velocities, got {list(values)}"
        self._topic_reference = [float(v) for v in values]
        self._topic_reference_t_s = t_s
        return None

    def velocity_references(self, t_s: float, positions: Sequence[float]) -> list[float]:
        """Each joint's velocity reference at plant time t_s."""
        p = self.params
        if self._hold_position is None:
            self._hold_position = list(positions)
        n = len(p.joints)
        feedforward = [0.0] * n
        targets = list(self._hold_position)
        if p.reference_source == "topic":
            if t_s - self._topic_reference_t_s <= p.reference_timeout_s:
                feedforward = list(self._topic_reference)
            targets = list(positions)  # no position loop against a free velocity reference
        elif p.profile is not None:
            k = p.joints.index(p.profile_joint)
            t_rel = t_s - (self._t0_s if self._t0_s is not None else t_s)
            feedforward[k] = p.profile.velocity(t_rel)
            targets[k] = self._hold_position[k] + p.profile.displacement(t_rel)
        if p.cascade.position_kp_per_s == 0.0:
            return feedforward
        return [
            cascade.velocity_setpoint(targets[i], positions[i], feedforward[i])
            for i, cascade in enumerate(self.cascades)
        ]

    def update(
        self,
        t_s: float,
        positions: Sequence[float],
        velocities: Sequence[float],
        currents_a: Sequence[float] | None,
    ) -> list[float] | None:
        """One control step on a plant state stamped t_s; None for a stale or repeated stamp.

        Returns the command array in joint order: volts (voltage interface, needs the
        currents) or amps (current interface).
        """
        p = self.params
        if self._last_t_s is not None and t_s <= self._last_t_s:
            return None
        if p.command_interface == "voltage" and currents_a is None:
            return None  # the current loop needs the measured currents
        dt_s = p.nominal_period_s if self._last_t_s is None else t_s - self._last_t_s
        if self._t0_s is None:
            self._t0_s = t_s
        self._last_t_s = t_s
        n = len(p.joints)
        if not p.enabled:
            return [0.0] * n
        references = self.velocity_references(t_s, positions)
        self.last_velocity_reference = references
        commands = []
        for i, cascade in enumerate(self.cascades):
            current_ref = cascade.current_command(references[i], velocities[i], dt_s)
            if currents_a is None:  # current interface: the drive closes the current loop
                commands.append(current_ref)
            else:
                commands.append(cascade.voltage_command(current_ref, currents_a[i], dt_s))
        return commands
