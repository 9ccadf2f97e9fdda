"""The simulator node's drive modes: position_commands in lockstep move the pivot to its target.

The test is the controller: it answers each joint_states with a position_commands array, so
each answer runs one control period. Every wait has a deadline; none sleeps.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
import support
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from support import spin_until

from lca_control import contract as pc
from lca_control.parameters import ParameterError

WARN = DiagnosticStatus.WARN
ros_context = support.domain_contexts(122, 4)  # its own: 140-145 are test_sim_control's
TARGET_RAD = 0.7
START_RAD = math.radians(35.0)


def _t_s(msg: JointState) -> float:
    return float(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)


def _lockstep_pivot_in(ctx: Any, executor: Any, mode: str) -> Any:
    """A lockstep simulator from 35 deg with the pivot in drive mode `mode`, the others current."""
    return support.start_simulator(
        ctx,
        executor,
        {
            "timing_mode": "lockstep",
            "command_interface": "current",
            "drive_modes": ["current", mode, "current", "current"],
            "initial_position": [0.0, START_RAD, 0.0, 0.0],
            "lockstep_subscribers": 1,
        },
    )


def test_position_commands_move_the_pivot_to_the_target_and_it_stays() -> None:
    """From 35 deg to 0.7 rad in position mode: within 2e-5 rad after 1.5 s, l_arm unmoved."""
    with ros_context() as (ctx, executor):
        sim = _lockstep_pivot_in(ctx, executor, "position")
        node = Node("test_position_master", context=ctx)
        executor.add_node(node)
        publisher = node.create_publisher(Float64MultiArray, pc.POSITION_COMMANDS, 10)
        states: list[JointState] = []

        def answer(msg: JointState) -> None:
            states.append(msg)
            # NaN for the current joints: their entries are ignored (docs/simulator.md)
            publisher.publish(Float64MultiArray(data=[math.nan, TARGET_RAD, math.nan, math.nan]))

        node.create_subscription(JointState, pc.JOINT_STATES, answer, pc.STATE_QOS_DEPTH)
        spin_until(executor, lambda: sim.sim_time_s >= 2.0, "2 s of lockstep", timeout_s=120.0)
        assert sim.plant.counters.accepted == round(sim.sim_time_s / 0.004)
        assert sim.plant.counters.rejected == 0
        late = [m.position for m in states if _t_s(m) > 1.5]
        assert len(late) > 100
        assert max(abs(p[1] - TARGET_RAD) for p in late) < 2e-5
        assert all(p[0] == 0.0 for p in late)  # 0 A on l_arm: the worm gear holds it


def test_velocity_commands_answer_the_state_after_the_current_commands() -> None:
    """Current then velocity commands per state: one period per velocity array, 0.05 rad/s held.

    velocity_commands is the controller's last topic, so it runs the period; the currents of
    the current joints are in force by then (as on the CAN bridge with csv axes).
    """
    with ros_context() as (ctx, executor):
        sim = _lockstep_pivot_in(ctx, executor, "velocity")
        node = Node("test_velocity_master", context=ctx)
        executor.add_node(node)
        currents = node.create_publisher(Float64MultiArray, pc.CURRENT_COMMANDS, 10)
        velocities = node.create_publisher(Float64MultiArray, pc.VELOCITY_COMMANDS, 10)
        states: list[JointState] = []

        def answer(msg: JointState) -> None:
            states.append(msg)
            currents.publish(Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0]))  # pivot: ignored
            velocities.publish(Float64MultiArray(data=[math.nan, 0.05, math.nan, math.nan]))

        node.create_subscription(JointState, pc.JOINT_STATES, answer, pc.STATE_QOS_DEPTH)
        spin_until(executor, lambda: sim.sim_time_s >= 2.0, "2 s of lockstep", timeout_s=120.0)
        periods = round(sim.sim_time_s / 0.004)
        spin_until(executor, lambda: sim.plant.counters.accepted >= 2 * periods, "the currents")
        assert sim.plant.counters.accepted == 2 * periods  # no period ran on the currents
        late = [m.velocity[1] for m in states if _t_s(m) > 1.5]
        assert len(late) > 100
        assert max(abs(w - 0.05) for w in late) < 5e-5


def test_drive_modes_that_do_not_fit_refuse_the_start() -> None:
    """Position mode with voltage commands: the one-line ParameterError at start-up."""
    with (
        ros_context() as (ctx, executor),
        pytest.raises(
            ParameterError, match=r"^drive_modes: expected modes that fit command_interface voltage"
        ),
    ):
        support.start_simulator(
            ctx,
            executor,
            {"command_interface": "voltage", "drive_modes": ["position"] * 4},
        )


def test_position_joints_without_position_commands_warn() -> None:
    """The pivot in position mode and only current_commands coming: a WARN naming it.

    Without it the pivot would hold where it is without a word (realtime: nothing stalls).
    """
    with ros_context() as (ctx, executor):
        support.start_simulator(
            ctx,
            executor,
            {
                "timing_mode": "realtime",
                "command_interface": "current",
                "drive_modes": ["current", "position", "current", "current"],
                "initial_position": [0.0, START_RAD, 0.0, 0.0],
                "diagnostics_period_s": 0.1,
            },
        )
        probe = support.Diagnostics(ctx, executor)
        currents = probe.node.create_publisher(Float64MultiArray, pc.CURRENT_COMMANDS, 10)
        probe.node.create_timer(
            0.01, lambda: currents.publish(Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0]))
        )
        status = probe.wait_for("lca_hil/simulator", WARN, "['pivot'] get no position_commands")
        assert "command_interface" in status.message
