"""The controller's core: references, per-joint cascades, command arrays (pure, no ROS).

`JointController` is what the controller node runs on every new plant state: it picks each
joint's velocity reference (topic, built-in profile, or hold), runs the cascades and returns the
command array in joint order, in volts or in amps. With the velocity or the position interface
the loops are closed in the drive: the array is the velocity references (rad/s, m/s) or the
position set-points (rad, m), and no cascade runs (docs/control.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from lca_control.cascade import (
    CONTROL_PERIOD_S,
    PAPER_CURRENT_KP_V_PER_A,
    PAPER_CURRENT_TI_S,
    PAPER_VELOCITY_KP_A_PER_RAD_S,
    PAPER_VELOCITY_TI_S,
    AxisCascade,
    CascadeParams,
)
from lca_control.parameters import (
    ParameterError,
    ParameterTable,
    ParamKind,
    ParamSpec,
    non_negative,
    positive,
)
from lca_control.pi import PIParams
from lca_control.profiles import Profile, RampProfile, TrapezoidProfile

REFERENCE_SOURCES = ("topic", "ramp", "trapezoid", "hold")
# A stamp older than the last one by more than this is a plant that restarted (its time began
# again), not a late message: 1 us is above the float rounding of wall-clock stamps (~0.2 us).
PLANT_TIME_TOLERANCE_S = 1e-6
COMMAND_INTERFACES = ("voltage", "current", "velocity", "position")

D = ParamKind.DOUBLE

# Units in the names; joint-side velocities in rad/s (m/s). Every value is checked whether or
# not the running reference source uses it, so switching profiles live cannot fail later.
CONTROLLER_PARAMETERS = ParameterTable(
    (
        ParamSpec("joints", ParamKind.STRING_ARRAY, ["l_arm", "pivot", "c_arc", "lift"],
                  "joint order of commands and references", live=False),
        ParamSpec("command_interface", ParamKind.STRING, "voltage",
                  "voltage (both loops here), current (current loop in the drive), velocity "
                  "or position (velocity / position set-points; every loop in the drive)",
                  choices=COMMAND_INTERFACES, live=False),
        ParamSpec("reference_source", ParamKind.STRING, "topic",
                  "topic (velocity_reference), ramp, trapezoid or hold",
                  choices=REFERENCE_SOURCES),
        ParamSpec("profile_joint", ParamKind.STRING, "pivot",
                  "the joint a built-in profile moves; the others hold"),
        non_negative("ramp_start_s", 1.0, "ramp: start time after the first state, s"),
        positive("ramp_duration_s", 10.0, "ramp: time to reach the end velocity, s"),
        ParamSpec("ramp_end_velocity", D, math.radians(5.0), "ramp: final velocity, rad/s (m/s)"),
        non_negative("ramp_hold_s", 0.0, "ramp: time the end velocity is held, s"),
        non_negative("trapezoid_start_s", 1.0, "trapezoid: start time, s"),
        positive("trapezoid_accel_s", 1.0, "trapezoid: acceleration time, s"),
        non_negative("trapezoid_cruise_s", 2.0, "trapezoid: cruise time, s"),
        positive("trapezoid_decel_s", 1.0, "trapezoid: deceleration time, s"),
        ParamSpec("trapezoid_velocity", D, math.radians(5.0),
                  "trapezoid: cruise velocity, rad/s (m/s)"),
        non_negative("velocity_kp_a_per_rad_s", PAPER_VELOCITY_KP_A_PER_RAD_S,
                     "velocity PI gain, A per rad/s"),
        positive("velocity_ti_s", PAPER_VELOCITY_TI_S, "velocity PI integral time, s"),
        non_negative("current_kp_v_per_a", PAPER_CURRENT_KP_V_PER_A, "current PI gain, V/A"),
        positive("current_ti_s", PAPER_CURRENT_TI_S, "current PI integral time, s"),
        positive("current_limit_a", 20.0, "current setpoint limit, A"),
        positive("voltage_limit_v", 300.0, "voltage command limit, V"),
        non_negative("position_kp_per_s", 0.0,
                     "outer position loop gain, 1/s (0: velocity control only)"),
        positive("velocity_limit", 0.2, "position loop velocity cap, rad/s (m/s)"),
        positive("reference_timeout_s", 0.5, "topic reference older than this counts as zero, s"),
        positive("nominal_period_s", CONTROL_PERIOD_S, "dt used for the very first state, s"),
        positive("plant_timeout_s", 0.5,
                 "no plant state for this long is reported (WARN on /diagnostics), s"),
        ParamSpec("enabled", ParamKind.BOOL, True, "compute commands; disabled sends zeros"),
    )
)  # fmt: skip


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
    plant_timeout_s: float


def validate_controller_params(values: Mapping[str, Any]) -> ControllerParams:
    """Check every parameter (`CONTROLLER_PARAMETERS`) and build the typed params.

    Raises:
        ParameterError: naming the parameter and what was expected.
    """
    v = CONTROLLER_PARAMETERS.check_all(values)
    joints: tuple[str, ...] = v["joints"]
    if not joints or len(set(joints)) != len(joints):
        raise ParameterError("joints", "distinct joint names", list(joints))
    source = v["reference_source"]
    profile_joint = v["profile_joint"]
    if source in ("ramp", "trapezoid") and profile_joint not in joints:
        raise ParameterError("profile_joint", f"one of {list(joints)}", profile_joint)
    ramp = RampProfile(
        v["ramp_start_s"], v["ramp_duration_s"], v["ramp_end_velocity"], v["ramp_hold_s"]
    )
    trapezoid = TrapezoidProfile(
        v["trapezoid_start_s"],
        v["trapezoid_accel_s"],
        v["trapezoid_cruise_s"],
        v["trapezoid_decel_s"],
        v["trapezoid_velocity"],
    )
    profiles: dict[str, Profile] = {"ramp": ramp, "trapezoid": trapezoid}
    profile = profiles.get(source)
    current_limit, voltage_limit = v["current_limit_a"], v["voltage_limit_v"]
    cascade = CascadeParams(
        velocity=PIParams(
            v["velocity_kp_a_per_rad_s"], v["velocity_ti_s"], -current_limit, current_limit
        ),
        current=PIParams(v["current_kp_v_per_a"], v["current_ti_s"], -voltage_limit, voltage_limit),
        position_kp_per_s=v["position_kp_per_s"],
        velocity_limit=v["velocity_limit"],
    )
    return ControllerParams(
        joints, v["command_interface"], source, profile_joint, profile, cascade,
        v["reference_timeout_s"], v["nominal_period_s"], v["enabled"], v["plant_timeout_s"],
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
        self.plant_restarts = 0
        self.last_restart_from_s = 0.0  # the stamp before the latest restart, s
        # States with a NaN or infinite reading (a lost encoder sample): the last commands are
        # sent again and the loops are not updated, so one bad sample cannot poison an integral.
        self.bad_states = 0
        self._last_commands: list[float] | None = None
        # Position interface: the set-points sent last (rad, m), and the pose the reference
        # source moves from; None: taken again from the last set-points at the next state.
        self._setpoints: list[float] | None = None
        self._anchor: list[float] | None = None
        self.last_position_setpoint: list[float] = [0.0] * len(params.joints)

    @property
    def elapsed_s(self) -> float:
        """Time since the first state (the profiles' time base)."""
        if self._t0_s is None or self._last_t_s is None:
            return 0.0
        return self._last_t_s - self._t0_s

    def set_params(self, params: ControllerParams) -> None:
        """Apply new gains or references without a bump."""
        old = self.params
        if (old.reference_source, old.profile_joint, old.profile) != (
            params.reference_source,
            params.profile_joint,
            params.profile,
        ):
            self._anchor = None  # a new reference moves on from the set-points in force
        self.params = params
        for cascade in self.cascades:
            cascade.set_params(params.cascade)

    def reset(self) -> None:
        """Zero the integrators (on enable); position set-points move on from where they are."""
        for cascade in self.cascades:
            cascade.reset()
        self._anchor = None

    def _restart(self) -> None:
        """Begin again as on the very first state: the plant's time has restarted.

        Integrators from zero, the profile from its start and the hold pose from the new state;
        a topic reference stamped on the old time base no longer counts.
        """
        self.plant_restarts += 1
        self.last_restart_from_s = self._last_t_s if self._last_t_s is not None else 0.0
        self.reset()
        self._t0_s = None
        self._last_t_s = None
        self._hold_position = None
        self._topic_reference_t_s = -math.inf
        self.last_velocity_reference = [0.0] * len(self.params.joints)
        self._setpoints = None
        if self.params.command_interface == "position":
            self._last_commands = None  # set-points of the old plant's pose mean nothing now

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

    def position_setpoints(
        self, t_s: float, positions: Sequence[float], dt_s: float
    ) -> list[float]:
        """Each joint's position set-point at plant time t_s (rad, m): the position interface.

        A built-in profile adds its displacement (`Profile.displacement`) to the pose it
        starts from; hold keeps that pose; a topic velocity reference is integrated, one
        period of dt_s at a time (a stale one counts as zero, the set-point then stands).
        The pose is the measured one at the first state, and the set-points in force after
        a re-enable or a new reference source, so no set-point jumps. Sets
        `last_velocity_reference` to the references the set-points move with.
        """
        p = self.params
        n = len(p.joints)
        last = list(positions) if self._setpoints is None else self._setpoints
        velocity = [0.0] * n
        t_rel = t_s - (self._t0_s if self._t0_s is not None else t_s)
        if p.reference_source == "topic":
            if t_s - self._topic_reference_t_s <= p.reference_timeout_s:
                velocity = list(self._topic_reference)
            step_s = 0.0 if self._setpoints is None else dt_s
            setpoints = [s + v * step_s for s, v in zip(last, velocity, strict=True)]
            self._anchor = None
        else:
            k = p.joints.index(p.profile_joint) if p.profile is not None else -1
            if self._anchor is None:
                self._anchor = list(last)
                if p.profile is not None:
                    self._anchor[k] -= p.profile.displacement(t_rel)
            setpoints = list(self._anchor)
            if p.profile is not None:
                setpoints[k] += p.profile.displacement(t_rel)
                velocity[k] = p.profile.velocity(t_rel)
        self._setpoints = setpoints
        self.last_position_setpoint = list(setpoints)
        self.last_velocity_reference = velocity
        return list(setpoints)

    def update(
        self,
        t_s: float,
        positions: Sequence[float],
        velocities: Sequence[float],
        currents_a: Sequence[float] | None,
    ) -> list[float] | None:
        """One control step on a plant state stamped t_s; None for a stale or repeated stamp.

        A stamp earlier than the last by more than `PLANT_TIME_TOLERANCE_S` is a restarted
        plant (a simulator or bridge started again, its time from 0): the loops and the
        profiles restart from this state (`plant_restarts` counts it) instead of waiting for
        the old time, which would never come. So is a stamp later than the last by more than
        `plant_timeout_s`: a plant stamped with the wall clock (a realtime simulator, the CAN
        bridge) that was gone or restarted comes back with its time jumped forward, and one
        control step across the gap would wind the integrators up by the whole gap.

        Returns the command array in joint order: volts (voltage interface, needs the
        currents), amps (current interface), the velocity references (velocity interface,
        rad/s or m/s) or the position set-points (position interface, rad or m:
        `position_setpoints`; disabled, the measured positions, so the drive holds where the
        joint is). With the velocity and position interfaces no cascade runs.
        """
        p = self.params
        if p.command_interface == "voltage" and currents_a is None:
            return None  # the current loop needs the measured currents
        if self._stale(t_s):
            return None
        readings = [*positions, *velocities, *(currents_a or ())]
        if not all(math.isfinite(v) for v in readings):
            self.bad_states += 1
            self._last_t_s = t_s
            if self._last_commands is None and p.command_interface == "position":
                return None  # no set-point yet: a zero would send every joint to 0
            return list(self._last_commands or [0.0] * len(p.joints))
        dt_s = p.nominal_period_s if self._last_t_s is None else t_s - self._last_t_s
        if self._t0_s is None:
            self._t0_s = t_s
        self._last_t_s = t_s
        n = len(p.joints)
        if not p.enabled:
            self.last_velocity_reference = [0.0] * n  # a drive closing the loop holds still
            if p.command_interface == "position":
                return self._hold_here(positions)
            return [0.0] * n
        if p.command_interface == "position":
            commands = self.position_setpoints(t_s, positions, dt_s)
        else:
            references = self.velocity_references(t_s, positions)
            self.last_velocity_reference = references
            if p.command_interface == "velocity":
                commands = list(references)
            else:
                commands = self._cascade_commands(references, velocities, currents_a, dt_s)
        self._last_commands = commands
        return commands

    def _stale(self, t_s: float) -> bool:
        """A repeated or slightly older stamp; a restart (`update`) begins here instead."""
        last_s = self._last_t_s
        if last_s is None:
            return False
        if t_s < last_s - PLANT_TIME_TOLERANCE_S or t_s > last_s + self.params.plant_timeout_s:
            self._restart()
            return False
        return t_s <= last_s

    def _cascade_commands(
        self,
        references: Sequence[float],
        velocities: Sequence[float],
        currents_a: Sequence[float] | None,
        dt_s: float,
    ) -> list[float]:
        """The cascades' step: amps (no currents: the drive closes the current loop) or volts."""
        commands = []
        for i, cascade in enumerate(self.cascades):
            current_ref = cascade.current_command(references[i], velocities[i], dt_s)
            if currents_a is None:
                commands.append(current_ref)
            else:
                commands.append(cascade.voltage_command(current_ref, currents_a[i], dt_s))
        return commands

    def _hold_here(self, positions: Sequence[float]) -> list[float]:
        """Disabled on the position interface: the measured positions are the set-points."""
        self._setpoints = list(positions)
        self._anchor = None
        self.last_position_setpoint = list(positions)
        self._last_commands = list(positions)
        return list(positions)
