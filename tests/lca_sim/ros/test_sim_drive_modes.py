"""The simulator node's drive modes: position_commands in lockstep move the pivot to its target.

The test is the controller: it answers each joint_states with a position_commands array, so
each answer runs one control period. Every wait has a deadline; none sleeps.
"""

from __future__ import annotations

import math

import pytest
import support
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from support import spin_until

from lca_control import contract as pc
from lca_control.parameters import ParameterError

ros_context = support.domain_contexts(141, 1)
TARGET_RAD = 0.7
START_RAD = math.radians(35.0)


def test_position_commands_move_the_pivot_to_the_target_and_it_stays() -> None:
    """From 35 deg to 0.7 rad in position mode: within 2e-5 rad after 1.5 s, l_arm unmoved."""
    with ros_context() as (ctx, executor):
        sim = support.start_simulator(
            ctx,
            executor,
            {
                "timing_mode": "lockstep",
                "command_interface": "current",
                "drive_modes": ["current", "position", "current", "current"],
                "initial_position": [0.0, START_RAD, 0.0, 0.0],
                "lockstep_subscribers": 1,
            },
        )
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
        late = [
            m.position for m in states if m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec > 1.5
        ]
        assert len(late) > 100
        assert max(abs(p[1] - TARGET_RAD) for p in late) < 2e-5
        assert all(p[0] == 0.0 for p in late)  # 0 A on l_arm: the worm gear holds it


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
