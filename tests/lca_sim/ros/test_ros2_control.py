"""ros2_control's topic-based hardware interface, played by a test node, drives both plants.

ros2_control is not installable here, so `FakeTopicSystem` sends and reads exactly what
joint_state_topic_hardware_interface's `write()` and `read()` do (docs/ros2_control.md): every
`controller_manager` update (250 Hz, config/ros2_control/controllers.yaml) one JointState on
`/robot_joint_commands`, QoS keep-last 1 reliable, naming every joint of the `<ros2_control>`
block in its order with one `velocity` and one `effort` entry per joint (both interfaces are
declared, an unclaimed one sends 0.0), `position` empty; it subscribes `/robot_joint_states` with
the sensor-data QoS and matches joints by name. Both plants run on the wall clock.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import rclpy
import yaml
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import JointState

from lca_control import contract as pc
from lca_sim.config.loader import config_dir
from lca_sim.ros.can_bridge_node import CanBridgeNode
from lca_sim.ros.node_util import make_executor
from lca_sim.ros.simulator_node import SimulatorNode

DOMAIN_ID = 163
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
UPDATE_RATE_HZ = 250.0  # controllers.yaml's update_rate


class FakeTopicSystem(Node):
    """The hardware interface's two topics, with its message layout, QoS and rate."""

    def __init__(self, ctx: Context) -> None:
        super().__init__("fake_topic_based_system", context=ctx)
        self.names: list[str] = list(JOINTS)
        self.velocity = [0.0] * len(JOINTS)
        self.effort = [0.0] * len(JOINTS)
        self.states: list[JointState] = []
        self._pub = self.create_publisher(JointState, pc.ROBOT_JOINT_COMMANDS, QoSProfile(depth=1))
        self.create_subscription(
            JointState, pc.ROBOT_JOINT_STATES, self.states.append, qos_profile_sensor_data
        )
        self.sent = 0
        self.create_timer(1.0 / UPDATE_RATE_HZ, self._write)

    def command(self, names: list[str], velocity: list[float], effort: list[float]) -> None:
        """What the next writes send (one entry per name in each field, as the interface)."""
        self.names, self.velocity, self.effort = names, velocity, effort

    def _write(self) -> None:
        msg = JointState(name=list(self.names), velocity=self.velocity, effort=self.effort)
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub.publish(msg)
        self.sent += 1

    def position(self, joint: str) -> float:
        """`read()`: the joint's position from the latest state, found by name."""
        last = self.states[-1]
        return float(last.position[list(last.name).index(joint)])


def _spin_until(executor: object, what: Callable[[], bool], timeout_s: float, why: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not what():
        assert time.monotonic() < deadline, why
        executor.spin_once(timeout_sec=0.02)  # type: ignore[attr-defined]


def _assert_states_fit_the_interface(states: list[JointState]) -> None:
    """Names are the robot's joints in axis order, every field filled, nothing NaN."""
    assert states
    for msg in states[-50:]:
        assert tuple(msg.name) == JOINTS
        assert len(msg.position) == len(msg.velocity) == len(msg.effort) == len(JOINTS)
        values = [*msg.position, *msg.velocity, *msg.effort]
        assert all(math.isfinite(v) for v in values), values


def test_simulator_follows_joint_state_effort_by_name() -> None:
    """3 A on l_arm moves it forward, reordered and partial commands too; the rest stays."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    executor = make_executor(ctx)
    sim = fake = None
    try:
        sim = SimulatorNode(
            context=ctx,
            parameter_overrides=[Parameter("command_interface", value="current")],
        )
        fake = FakeTopicSystem(ctx)
        executor.add_node(sim)
        executor.add_node(fake)
        _spin_until(executor, lambda: len(fake.states) > 5, 20.0, "no /robot_joint_states")
        start = {j: fake.position(j) for j in JOINTS}

        fake.command(list(JOINTS), [0.0] * 4, [3.0, 0.0, 0.0, 0.0])
        _spin_until(
            executor,
            lambda: fake.position("l_arm") - start["l_arm"] > 0.01,
            20.0,
            "3 A did not move l_arm",
        )
        # Reordered and partial: l_arm keeps 3 A from the message above only through NaN.
        fake.command(["pivot", "l_arm"], [0.0, 0.0], [math.nan, 3.0])
        moved = fake.position("l_arm")
        _spin_until(
            executor,
            lambda: fake.position("l_arm") - moved > 0.01,
            20.0,
            "a reordered partial command did not keep l_arm moving",
        )
        assert sim.plant.target[1] == 0.0 and sim.plant.target[0] == pytest.approx(3.0)
        for joint in ("pivot", "c_arc", "lift"):
            assert abs(fake.position(joint) - start[joint]) < 1e-3, joint
        _assert_states_fit_the_interface(fake.states)

        fake.command(["l_arm", "elbow"], [0.0, 0.0], [0.0, 1.0])
        _spin_until(
            executor,
            lambda: sim.joint_command_counts["unknown_names"] > 0,
            10.0,
            "an unknown joint name was not counted",
        )
        assert sim.plant.target[0] == 0.0  # the known joint of that message still applies
        assert sim.joint_command_counts["accepted"] > 0
    finally:
        for node in (sim, fake):
            if node is not None:
                executor.remove_node(node)
                node.destroy_node()
        executor.shutdown()
        rclpy.shutdown(context=ctx)


def _roomy_rack_config(tmp_path: Path) -> Path:
    """The shipped rack with a 50-period SYNC-loss watch (one process carries it all here)."""
    with (config_dir() / "can" / "rack.yaml").open() as f:
        rack = yaml.safe_load(f)
    rack["sync_loss_periods"] = 50
    path = tmp_path / "rack.yaml"
    path.write_text(yaml.safe_dump(rack))
    return path


def test_can_bridge_follows_a_velocity_command_on_a_csv_axis(tmp_path: Path) -> None:
    """The pivot in csv: the drive's own loop follows the JointState velocity of 0.05 rad/s."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID + 1)
    executor = make_executor(ctx)
    bridge = fake = None
    try:
        fake = FakeTopicSystem(ctx)
        bridge = CanBridgeNode(
            context=ctx,
            parameter_overrides=[
                Parameter("interface", value="virtual"),
                Parameter("channel", value="test_ros2_control"),
                Parameter("auto_enable", value=True),
                Parameter("cycle_hz", value=250.0),
                Parameter("rack_config", value=str(_roomy_rack_config(tmp_path))),
                Parameter("rpdo_deadline_ms", value=500),
                Parameter("heartbeat_consumer_ms", value=1000),
                Parameter("stale_timeout_s", value=0.5),
                Parameter("modes", value=["cst", "csv", "cst", "cst"]),
            ],
        )
        executor.add_node(bridge)
        executor.add_node(fake)
        _spin_until(executor, lambda: len(fake.states) > 5, 20.0, "no /robot_joint_states")
        start = fake.position("pivot")
        wanted = 0.05  # rad/s

        def following() -> bool:
            last = fake.states[-1]
            return bool(abs(last.velocity[1] - wanted) < 0.3 * wanted)

        # Reordered as a user's block may be; effort 0 on the csv pivot is the unclaimed one.
        fake.command(["lift", "pivot", "c_arc", "l_arm"], [0.0, wanted, 0.0, 0.0], [0.0] * 4)
        _spin_until(executor, following, 20.0, "the pivot did not follow 0.05 rad/s")
        assert fake.position("pivot") > start
        assert bridge.bridge.latched_reason() == ""
        _assert_states_fit_the_interface(fake.states)

        fake.command(["pivot", "wrist"], [wanted, 0.0], [0.0, 0.0])
        _spin_until(
            executor,
            lambda: bridge.joint_command_counts["unknown_names"] > 0,
            10.0,
            "an unknown joint name was not counted",
        )
        assert bridge.joint_command_counts["accepted"] > 0
    finally:
        for node in (bridge, fake):
            if node is not None:
                executor.remove_node(node)
                node.destroy_node()
        executor.shutdown()
        rclpy.shutdown(context=ctx)
