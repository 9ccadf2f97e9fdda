"""The JointState command adapter of both plants: names, NaN, fields a joint does not take.

Pure: the message fields are handed in as lists, no rclpy context is started.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_sim.config.loader import load_robot
from lca_sim.errors import InvalidValueError
from lca_sim.ros.joint_command import (
    JointCommandAdapter,
    effort_scales,
    read_joint_command,
    unserved_axes,
)

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


def _named(tag: str) -> Callable[[list[str]], str]:
    return lambda joints: f"{tag} {joints}"


def test_position_joints_take_position_and_nan_or_absent_keeps_the_command() -> None:
    """A csp joint takes its position (rad, m); NaN and joints not named keep theirs."""
    adapter = _adapter(position_joints=("pivot", "lift"), velocity_joints=("c_arc",))
    cmd = adapter.read(
        ["lift", "pivot", "c_arc"], [0.0, 0.0, 0.1], [0.0, 0.0, 0.0], [0.25, math.nan, 0.0]
    )
    assert cmd.accepted and not cmd.problems
    assert cmd.position == {"lift": 0.25} and cmd.velocity == {"c_arc": 0.1} and not cmd.effort
    assert adapter.fill([0.1, 0.6, 0.0, 0.3], cmd.position) == [0.1, 0.6, 0.0, 0.25]


def test_a_nonzero_entry_in_another_modes_field_is_refused_and_named() -> None:
    """Position for a cst/csv joint, velocity or effort for a csp joint: warned; zeros are not."""
    adapter = JointCommandAdapter(
        JOINTS,
        (1.0, 1.0, 1.0, 1.0),
        velocity_joints=("c_arc",),
        position_joints=("pivot",),
        velocity_refused=_named("v"),
        effort_refused=_named("e"),
        position_refused=_named("p"),
        topic="/cmd",
    )
    quiet = adapter.read(JOINTS, [0.0, 0.0, 0.2, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.5, 0.0, 0.0])
    assert quiet.accepted and not quiet.problems
    loud = adapter.read(JOINTS, [0.0, 0.3, 0.2, 0.0], [1.0, 2.0, 0.0, 0.0], [0.4, 0.5, 0.0, 0.0])
    assert loud.accepted  # the fields the joints take still count
    assert loud.problems == ("v ['pivot']", "e ['pivot']", "p ['l_arm']")
    assert loud.position == {"pivot": 0.5} and loud.effort == {"l_arm": 1.0, "lift": 0.0}
    only_foreign = adapter.read(["l_arm"], [], [], [0.4])
    assert not only_foreign.accepted and only_foreign.problems == ("p ['l_arm']",)
    assert adapter.counts == {"accepted": 2, "refused": 1, "unknown_names": 0}


def test_position_is_refused_by_default_with_a_reason_and_a_ragged_field_refuses_all() -> None:
    """Without position joints a position entry is refused; a wrong length refuses the message."""
    adapter = _adapter()
    cmd = adapter.read(["pivot"], [], [], [0.7])
    assert not cmd.accepted
    assert cmd.problems == ("position for ['pivot']: their drives close no position loop",)
    ragged = read_joint_command(["pivot", "lift"], [], [], JOINTS, [0.1])
    assert "position has 1 entries for 2 names" in ragged.error and not ragged.position


def test_a_joint_cannot_take_both_velocity_and_position() -> None:
    """One drive runs one mode: a joint in both sets is refused at construction."""
    with pytest.raises(InvalidValueError, match="pivot"):
        _adapter(velocity_joints=("pivot",), position_joints=("pivot", "lift"))


_ENTRY = st.sampled_from([0.0, math.nan, -0.3, 0.7])


@given(
    modes=st.lists(st.sampled_from("pve"), min_size=4, max_size=4),
    named=st.lists(st.sampled_from(JOINTS), unique=True),
    takes_effort=st.booleans(),
    data=st.data(),
)
def test_each_joint_takes_exactly_its_own_field(
    modes: list[str], named: list[str], takes_effort: bool, data: st.DataObject
) -> None:
    """For any modes and message: each joint takes exactly its own field's finite entry.

    Effort is scaled; a joint is warned about iff another field holds a non-zero entry for it,
    or (a plant without effort) its own effort field any finite entry.
    """
    mode = dict(zip(JOINTS, modes, strict=True))
    adapter = JointCommandAdapter(
        JOINTS,
        (1.0, 2.0, 3.0, 4.0),
        velocity_joints=[j for j in JOINTS if mode[j] == "v"],
        position_joints=[j for j in JOINTS if mode[j] == "p"],
        velocity_refused=_named("v"),
        effort_refused=_named("e"),
        position_refused=_named("p"),
        topic="/cmd",
        takes_effort=takes_effort,
    )
    n = len(named)
    fields = {k: data.draw(st.lists(_ENTRY, min_size=n, max_size=n)) for k in "pve"}
    cmd = adapter.read(named, fields["v"], fields["e"], fields["p"])
    scale = dict(zip(JOINTS, (1.0, 2.0, 3.0, 4.0), strict=True))
    taken: dict[str, dict[str, float]] = {"p": {}, "v": {}, "e": {}}
    warned: dict[str, list[str]] = {"p": [], "v": [], "e": []}
    for i, joint in enumerate(named):
        for kind, values in fields.items():
            value = values[i]
            if not math.isfinite(value):
                continue
            if kind == mode[joint] == "e" and not takes_effort:
                warned[kind].append(joint)
            elif kind == mode[joint]:
                taken[kind][joint] = value * (scale[joint] if kind == "e" else 1.0)
            elif value != 0.0:
                warned[kind].append(joint)
    assert (cmd.position, cmd.velocity, cmd.effort) == (taken["p"], taken["v"], taken["e"])
    expected = tuple(f"{k} {sorted(warned[k])}" for k in "vep" if warned[k])
    assert cmd.problems == expected
    assert cmd.accepted == any(taken.values())


def test_unserved_axes_names_the_joints_their_topic_leaves_idle() -> None:
    """Only current_commands coming: csp / position joints are named; none at all: silence."""
    axes_of = {
        "current_commands": ("l_arm", "c_arc", "lift"),
        "velocity_commands": (),
        "position_commands": ("pivot",),
    }
    idle = {"current_commands": 0, "velocity_commands": 0, "position_commands": 0}
    assert unserved_axes(axes_of, idle) == ""  # no command yet: the peer watch's business
    currents = {**idle, "current_commands": 7}
    assert unserved_axes(axes_of, currents).startswith("['pivot'] get no position_commands")
    both = {**currents, "position_commands": 1}
    assert unserved_axes(axes_of, both) == ""
    positions = {**idle, "position_commands": 3}
    assert unserved_axes(axes_of, positions).startswith(
        "['l_arm', 'c_arc', 'lift'] get no current_commands"
    )
