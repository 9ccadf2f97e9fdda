"""The JointState command adapter of both plants: names, NaN, fields a joint does not take.

Pure: the message fields are handed in as lists, no rclpy context is started.
"""

from __future__ import annotations

import math

from lca_sim.config.loader import load_robot
from lca_sim.ros.joint_command import JointCommandAdapter, effort_scales, read_joint_command

JOINTS = ("l_arm", "pivot", "c_arc", "lift")


def _refused(joints: list[str]) -> str:
    return f"refused {joints}"


def _adapter(**kwargs: object) -> JointCommandAdapter:
    return JointCommandAdapter(
        JOINTS,
        (1.0, 2.0, 3.0, 4.0),
        velocity_refused=_refused,
        effort_refused=_refused,
        topic="/cmd",
        **kwargs,  # type: ignore[arg-type]
    )


def test_read_joint_command_matches_names_and_leaves_nan_out() -> None:
    """Any order, a partial set, NaN left out, unknown names listed, ragged fields refused."""
    cmd = read_joint_command(["pivot", "elbow", "l_arm"], [], [1.0, 2.0, math.nan], JOINTS)
    assert cmd.effort == {"pivot": 1.0} and cmd.velocity == {} and cmd.unknown == ("elbow",)
    assert cmd.error == ""
    ragged = read_joint_command(["pivot", "l_arm"], [0.5], [1.0, 2.0], JOINTS)
    assert "velocity has 1 entries for 2 names" in ragged.error and not ragged.effort


def test_effort_is_scaled_and_filled_into_the_commands_in_force() -> None:
    """Effort times the joint's scale; joints not named keep their command."""
    adapter = _adapter()
    cmd = adapter.read(["lift", "pivot"], [0.0, 0.0], [1.0, 0.5])
    assert cmd.accepted and cmd.effort == {"lift": 4.0, "pivot": 1.0} and not cmd.problems
    assert adapter.fill([9.0, 9.0, 9.0, 9.0], cmd.effort) == [9.0, 1.0, 9.0, 4.0]
    assert adapter.counts == {"accepted": 1, "refused": 0, "unknown_names": 0}


def test_velocity_joints_take_velocity_and_warn_about_effort() -> None:
    """A csv joint takes its velocity; a non-zero effort for it is named, a zero one is not."""
    adapter = _adapter(velocity_joints=("pivot",))
    cmd = adapter.read(["pivot", "lift"], [0.3, 0.2], [0.0, 1.0])
    assert cmd.accepted and cmd.velocity == {"pivot": 0.3} and cmd.effort == {"lift": 4.0}
    assert cmd.problems == ("refused ['lift']",)  # lift has no velocity loop
    loud = adapter.read(["pivot"], [], [2.0])
    assert not loud.accepted and loud.problems == ("refused ['pivot']",)


def test_a_plant_without_effort_refuses_every_effort_entry() -> None:
    """The simulator on voltages: a zero effort entry is refused too, and counted."""
    adapter = _adapter(takes_effort=False)
    cmd = adapter.read(["pivot", "ghost"], [], [0.0, 1.0])
    assert not cmd.accepted and not cmd.effort
    assert cmd.problems[0].startswith("unknown joints ['ghost']")
    assert cmd.problems[1] == "refused ['pivot']"
    assert adapter.counts == {"accepted": 0, "refused": 1, "unknown_names": 1}
    assert adapter.warning(cmd.problems).endswith("(1 refused, 1 unknown names so far)")


def test_torque_effort_scales_by_k_t_and_gear_ratio() -> None:
    """Joint torque to current: 1 / (k_t N) per joint; current effort passes as it is."""
    robot = load_robot("default")
    axes = {a.name: a for a in robot.axes}
    scales = effort_scales(robot, JOINTS, "torque")
    for joint, scale in zip(JOINTS, scales, strict=True):
        a = axes[joint]
        assert scale == 1.0 / (a.motor.torque_constant_nm_per_a * a.gear_ratio)
    assert effort_scales(robot, JOINTS, "current") == (1.0, 1.0, 1.0, 1.0)
