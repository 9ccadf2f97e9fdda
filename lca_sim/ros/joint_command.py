"""The JointState command adapter of both plants (docs/ros2_control.md).

ros2_control's topic-based hardware interface commands by joint name with a
sensor_msgs/JointState. `read_joint_command` reads one message; `JointCommandAdapter` turns it
into a plant's command values, each joint by what its drive takes (position, velocity or
effort), counts what it accepts and refuses, and says what to warn about. The simulator and the
CAN bridge both use it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field

from lca_sim.errors import InvalidValueError
from lca_sim.model.params import RobotParams


@dataclass(frozen=True, slots=True)
class JointCommand:
    """What one sensor_msgs/JointState command says, per joint of the receiving node.

    Attributes:
        effort: joint -> the effort entry (finite only; NaN entries are left out).
        velocity: joint -> the velocity entry (finite only).
        unknown: names the node has no joint of, in message order.
        error: why the whole message was refused ("" when it was not).
        position: joint -> the position entry (finite only), rad (m for the lift).
    """

    effort: dict[str, float]
    velocity: dict[str, float]
    unknown: tuple[str, ...] = ()
    error: str = ""
    position: dict[str, float] = field(default_factory=dict)


def read_joint_command(
    names: Sequence[str],
    velocity: Sequence[float],
    effort: Sequence[float],
    joints: Sequence[str],
    position: Sequence[float] = (),
) -> JointCommand:
    """Read a JointState command as ros2_control's topic-based hardware interface sends it.

    The interface names every joint of its `<ros2_control>` block and appends one entry per
    joint to `position` / `velocity` / `effort` for each command interface that joint
    declares, so a field is either empty (no joint commands it) or exactly as long as `name`.
    Any other length cannot be mapped to names and refuses the message. Joints match by name
    (any order, any subset); a NaN entry leaves that joint's command as it is.
    """
    n = len(names)
    fields = {"position": position, "velocity": velocity, "effort": effort}
    for kind, values in fields.items():
        if len(values) not in (0, n):
            return JointCommand(
                {},
                {},
                error=(
                    f"{kind} has {len(values)} entries for {n} names: declare the same "
                    "command interfaces on every joint of the <ros2_control> block"
                ),
            )
    wanted = set(joints)
    unknown = tuple(name for name in names if name not in wanted)
    taken: dict[str, dict[str, float]] = {kind: {} for kind in fields}
    for kind, values in fields.items():
        for name, value in zip(names, values, strict=False):
            if name in wanted and math.isfinite(value):
                taken[kind][name] = float(value)
    return JointCommand(taken["effort"], taken["velocity"], unknown, position=taken["position"])


def effort_scales(robot: RobotParams, joints: Sequence[str], effort: str) -> tuple[float, ...]:
    """Per joint, the plant's command per unit of a JointState effort entry.

    `effort` "current": the entry is the current, A (1); "torque": joint-side torque, N m (N
    for the lift), so the current is effort / (k_t N).
    """
    axes = {a.name: a for a in robot.axes}
    if effort == "current":
        return tuple(1.0 for _ in joints)
    return tuple(
        1.0 / (axes[j].motor.torque_constant_nm_per_a * axes[j].gear_ratio) for j in joints
    )


@dataclass(frozen=True, slots=True)
class AdaptedCommand:
    """A JointState command as a plant takes it.

    Attributes:
        effort: joint -> the command (effort scaled to the plant's unit), effort joints only.
        velocity: joint -> the velocity command, velocity joints only.
        accepted: the message commands at least one joint and is not refused as a whole.
        problems: what to warn about (empty: nothing).
        position: joint -> the position command (rad; m for the lift), position joints only.
    """

    effort: dict[str, float]
    velocity: dict[str, float]
    accepted: bool
    problems: tuple[str, ...]
    position: dict[str, float] = field(default_factory=dict)


def _no_position_loop(joints: list[str]) -> str:
    return f"position for {joints}: their drives close no position loop"


class JointCommandAdapter:
    """Reads JointState commands for one plant and counts them (`counts`).

    Each joint takes one field, the one of its drive's mode: position (position_joints),
    velocity (velocity_joints) or effort (the others). Its entries in the other two fields are
    ignored when zero (what the interface sends for a command interface no controller claims)
    and refused, counted and warned about, when not.

    Args:
        joints: the plant's joints, in its command order.
        effort_scales: per joint, the command per unit of effort (`effort_scales`).
        velocity_joints: the joints that take a velocity command (CAN: csv drives).
        takes_effort: False when the plant takes no effort at all (the simulator on voltages):
            every effort entry of an effort joint is refused, a zero one too.
        velocity_refused, effort_refused: the warning for entries of joints that do not take
            them, given those joints.
        topic: the command topic, named in the warning.
        position_joints: the joints that take a position command, rad or m (CAN: csp drives;
            the simulator: drive mode position).
        position_refused: the warning for position entries of joints that do not take them.

    Raises:
        InvalidValueError: a joint is both a velocity and a position joint.
    """

    def __init__(
        self,
        joints: Sequence[str],
        effort_scales: Sequence[float],
        *,
        velocity_joints: Collection[str] = (),
        takes_effort: bool = True,
        velocity_refused: Callable[[list[str]], str],
        effort_refused: Callable[[list[str]], str],
        topic: str,
        position_joints: Collection[str] = (),
        position_refused: Callable[[list[str]], str] = _no_position_loop,
    ) -> None:
        self.joints = tuple(joints)
        self._scale = dict(zip(self.joints, effort_scales, strict=True))
        self._velocity_joints = frozenset(velocity_joints)
        self._position_joints = frozenset(position_joints)
        both = sorted(self._velocity_joints & self._position_joints)
        if both:
            raise InvalidValueError(f"joints {both} cannot take both velocity and position")
        self._effort_joints = frozenset(self.joints) - self._velocity_joints - self._position_joints
        self._takes_effort = takes_effort
        self._velocity_refused = velocity_refused
        self._effort_refused = effort_refused
        self._position_refused = position_refused
        self._topic = topic
        self.counts = {"accepted": 0, "refused": 0, "unknown_names": 0}

    def read(
        self,
        names: Sequence[str],
        velocity: Sequence[float],
        effort: Sequence[float],
        position: Sequence[float] = (),
    ) -> AdaptedCommand:
        """One message's command, counted as accepted or refused."""
        cmd = read_joint_command(names, velocity, effort, self.joints, position)
        self.counts["unknown_names"] += len(cmd.unknown)
        efforts = {
            j: cmd.effort[j] * self._scale[j]
            for j in self.joints
            if j in cmd.effort and self._takes_effort and j in self._effort_joints
        }
        velocities = {
            j: cmd.velocity[j]
            for j in self.joints
            if j in cmd.velocity and j in self._velocity_joints
        }
        positions = {
            j: cmd.position[j]
            for j in self.joints
            if j in cmd.position and j in self._position_joints
        }
        accepted = not cmd.error and bool(efforts or velocities or positions)
        self.counts["accepted" if accepted else "refused"] += 1
        return AdaptedCommand(efforts, velocities, accepted, self._problems(cmd), positions)

    def _problems(self, cmd: JointCommand) -> tuple[str, ...]:
        problems: list[str] = []
        if cmd.unknown:
            problems.append(
                f"unknown joints {list(cmd.unknown)} (this node's: {list(self.joints)})"
            )
        if cmd.error:
            problems.append(cmd.error)
        # A zero entry is what the interface sends for an interface no controller claims.
        no_loop = sorted(
            j for j, v in cmd.velocity.items() if v != 0.0 and j not in self._velocity_joints
        )
        if no_loop:
            problems.append(self._velocity_refused(no_loop))
        no_effort = sorted(
            j
            for j, v in cmd.effort.items()
            if (v != 0.0 and j not in self._effort_joints)
            or (not self._takes_effort and j in self._effort_joints)
        )
        if no_effort:
            problems.append(self._effort_refused(no_effort))
        no_position = sorted(
            j for j, v in cmd.position.items() if v != 0.0 and j not in self._position_joints
        )
        if no_position:
            problems.append(self._position_refused(no_position))
        return tuple(problems)

    def fill(self, held: Sequence[float], values: Mapping[str, float]) -> list[float]:
        """The commands in force (joints order) with the joints in `values` replaced."""
        return [values.get(j, float(h)) for j, h in zip(self.joints, held, strict=True)]

    def warning(self, problems: Sequence[str]) -> str:
        """The throttled warning for a command's problems, with the counts so far."""
        c = self.counts
        return (
            f"{self._topic}: {'; '.join(problems)} ({c['refused']} refused, "
            f"{c['unknown_names']} unknown names so far)"
        )


def unserved_axes(axes_of: Mapping[str, Sequence[str]], taken: Mapping[str, int]) -> str:
    """Axes whose mode's command topic brings nothing while another topic does ('' if none).

    A controller commands one interface (current_commands, velocity_commands or
    position_commands): the joints of the other modes would then hold where they are without
    a word. `axes_of`: each topic and the joints it serves; `taken`: arrays taken per topic.
    """
    if not any(taken.values()):
        return ""
    idle = [
        f"{list(axes)} get no {topic}"
        for topic, axes in axes_of.items()
        if axes and not taken[topic]
    ]
    if not idle:
        return ""
    return "; ".join(idle) + " (their modes' topic; the controller's command_interface?)"
