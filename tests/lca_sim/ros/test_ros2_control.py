"""ros2_control's topic-based hardware interface, played by a test node, drives both plants.

ros2_control is not installable here, so `FakeTopicSystem` sends and reads exactly what
joint_state_topic_hardware_interface's `write()` and `read()` do (docs/ros2_control.md): every
`controller_manager` update (250 Hz, config/ros2_control/controllers.yaml) one JointState on
`/robot_joint_commands`, QoS keep-last 1 reliable, naming every joint of the `<ros2_control>`
block in its order with one `position`, one `velocity` and one `effort` entry per joint (the
shipped block declares all three interfaces); an interface no controller claims sends 0.0 in
PickNik's package and NaN in Jazzy's, and both plants must ignore either for a joint whose
drive does not take that field. It subscribes `/robot_joint_states` with the sensor-data QoS and
matches joints by name. The effort and CSV tests run on the wall clock; the position and
velocity interface tests run both plants in lockstep, the fake writing once per state as the
controller_manager's read -> update -> write does.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import rclpy
import support
import yaml
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import JointState

from lca_control import contract as pc
from lca_sim.config.paths import config_dir
from lca_sim.ros.can_bridge_node import CanBridgeNode
from lca_sim.ros.node_util import make_executor
from lca_sim.ros.simulator_node import SimulatorNode

DOMAIN_ID = 176  # and 177: its own (150-169 are test_live_parameters')
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
UPDATE_RATE_HZ = 250.0  # controllers.yaml's update_rate


class FakeTopicSystem(Node):
    """The hardware interface's two topics, with its message layout, QoS and rate.

    Args:
        ctx: the test's context.
        unclaimed: what an interface no controller claims sends: 0.0 (PickNik's package) or
            NaN (Jazzy's).
        lockstep: write once per state read (the plant in lockstep) instead of at 250 Hz.
    """

    def __init__(self, ctx: Context, unclaimed: float = 0.0, lockstep: bool = False) -> None:
        super().__init__("fake_topic_based_system", context=ctx)
        self.unclaimed = unclaimed
        self.names: list[str] = list(JOINTS)
        self.position_cmd = [unclaimed] * len(JOINTS)
        self.velocity = [0.0] * len(JOINTS)
        self.effort = [0.0] * len(JOINTS)
        self.states: list[JointState] = []
        self._pub = self.create_publisher(JointState, pc.ROBOT_JOINT_COMMANDS, QoSProfile(depth=1))
        self.create_subscription(
            JointState, pc.ROBOT_JOINT_STATES, self._read, qos_profile_sensor_data
        )
        self.sent = 0
        self._lockstep = lockstep
        if not lockstep:
            self.create_timer(1.0 / UPDATE_RATE_HZ, self._write)

    def command(
        self,
        names: list[str],
        velocity: list[float],
        effort: list[float],
        position: list[float] | None = None,
    ) -> None:
        """What the next writes send (one entry per name in each field, as the interface).

        `position` None: every entry `unclaimed` (no joint's position interface claimed).
        """
        self.names, self.velocity, self.effort = names, velocity, effort
        self.position_cmd = [self.unclaimed] * len(names) if position is None else position

    def _read(self, msg: JointState) -> None:
        self.states.append(msg)
        if self._lockstep:
            self._write()

    def _write(self) -> None:
        msg = JointState(
            name=list(self.names), position=self.position_cmd, velocity=self.velocity,
            effort=self.effort,
        )  # fmt: skip
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
        fake = FakeTopicSystem(ctx, unclaimed=0.0)  # PickNik's package
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
        fake = FakeTopicSystem(ctx, unclaimed=math.nan)  # Jazzy's package
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


# ------------------------------------------- position and velocity interfaces, both plants

lockstep_context = support.domain_contexts(173, 3)
# l_arm on a velocity interface, pivot and c_arc on position interfaces, lift on effort.
SIM_MODES = ["velocity", "position", "position", "current"]
BRIDGE_MODES = ["csv", "csp", "csp", "cst"]
PERIOD_S = 0.004  # the simulator's control_period_s; the bridge's 1 / cycle_hz
PIVOT_START_RAD = 0.6109  # both shipped plants start the pivot at 35 deg
# Until SWITCH_S every joint is named; then only l_arm and pivot: c_arc must keep its target.
SWITCH_S, END_S = 1.5, 3.0
L_ARM_RAD_S = (0.05, 0.08)
PIVOT_RAD = (0.7, 0.65)
C_ARC_RAD = 0.05


def _lockstep_plant(ctx: Context, plant: str, channel: str) -> SimulatorNode | CanBridgeNode:
    """The shipped simulator or bridge in lockstep at 4 ms, in the modes above."""
    if plant == "simulator":
        return SimulatorNode(
            context=ctx,
            parameter_overrides=support.parameters(
                timing_mode="lockstep",
                command_interface="current",
                control_period_s=PERIOD_S,
                drive_modes=SIM_MODES,
                initial_position=[0.0, PIVOT_START_RAD, 0.0, 0.0],
                lockstep_subscribers=1,
            ),
        )
    with (config_dir() / "ros" / "can_bridge.yaml").open() as f:
        values = yaml.safe_load(f)["can_bridge"]["ros__parameters"]
    values.update(
        timing_mode="lockstep",
        cycle_hz=1.0 / PERIOD_S,
        modes=BRIDGE_MODES,
        lockstep_subscribers=1,
        channel=channel,
    )
    return CanBridgeNode(context=ctx, parameter_overrides=support.parameters(**values))


def _stamp_s(msg: JointState) -> float:
    return float(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)


@pytest.mark.parametrize("unclaimed", [0.0, math.nan], ids=["picknik", "jazzy"])
@pytest.mark.parametrize("plant", ["simulator", "can"])
def test_position_and_velocity_interfaces_on_both_plants(
    plant: str, unclaimed: float, tmp_path: Path
) -> None:
    """Position and velocity command interfaces by name, in lockstep, on both plants.

    l_arm follows its velocity entry, pivot and c_arc their position entries; the unclaimed
    entries (0.0 or NaN) are ignored. After SWITCH_S the messages name only l_arm and pivot:
    c_arc keeps its target (never sent to 0) and the lift, on effort, never moves.
    """
    u = unclaimed
    with lockstep_context() as (ctx, executor):
        fake = FakeTopicSystem(ctx, unclaimed=u, lockstep=True)
        # lockstep_subscribers counts joint_states: the fake reads /robot_joint_states, so a
        # node of the test starts the run.
        starter = Node("lockstep_starter", context=ctx)
        starter.create_subscription(JointState, pc.JOINT_STATES, lambda _: None, 10)
        node = _lockstep_plant(ctx, plant, f"ros2_control_{tmp_path.name}")
        for n in (fake, starter, node):
            executor.add_node(n)
        fake.command(
            list(JOINTS),
            velocity=[L_ARM_RAD_S[0], u, u, u],
            effort=[u, u, u, 0.0],
            position=[u, PIVOT_RAD[0], C_ARC_RAD, u],
        )
        try:
            support.spin_until(
                executor,
                lambda: bool(fake.states) and _stamp_s(fake.states[-1]) >= SWITCH_S,
                f"{SWITCH_S} s of lockstep on {plant}",
                timeout_s=120.0,
            )
            fake.command(
                ["pivot", "l_arm"],
                velocity=[u, L_ARM_RAD_S[1]],
                effort=[u, u],
                position=[PIVOT_RAD[1], u],
            )
            support.spin_until(
                executor,
                lambda: _stamp_s(fake.states[-1]) >= END_S,
                f"{END_S} s of lockstep on {plant}",
                timeout_s=120.0,
            )
            support.assert_lockstep_plant_clean(node)
            counts = node.joint_command_counts
            assert counts["refused"] == 0 and counts["accepted"] > 500
        finally:
            for n in (node, starter, fake):
                support.kill(executor, n)
    _assert_states_fit_the_interface(fake.states)
    rows = [(_stamp_s(m), list(m.position), list(m.velocity)) for m in fake.states]
    before = [r for r in rows if SWITCH_S - 0.3 < r[0] <= SWITCH_S]
    after = [r for r in rows if END_S - 0.3 < r[0] <= END_S]
    assert len(before) > 50 and len(after) > 50
    for (_, q, v), wanted_rad_s, pivot_rad in (
        *((row, L_ARM_RAD_S[0], PIVOT_RAD[0]) for row in before),
        *((row, L_ARM_RAD_S[1], PIVOT_RAD[1]) for row in after),
    ):
        assert v[0] == pytest.approx(wanted_rad_s, rel=0.02)  # l_arm: its velocity entry
        assert q[1] == pytest.approx(pivot_rad, abs=1e-4)  # pivot: its position entry
        assert q[2] == pytest.approx(C_ARC_RAD, abs=1e-4)  # c_arc: held after SWITCH_S
        assert q[3] == rows[0][1][3]  # lift: 0 A, the worm gear holds it
