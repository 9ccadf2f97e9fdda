"""PlantPublisher: the optional state topics follow their subscribers without asking the graph.

A subscriber of motor_states, drive_chain_states or /clock that joins gets every snapshot
published after its match is known, one that leaves costs nothing any more, and `publish`
itself never calls into rmw for subscriber counts (three such calls per cycle were 4 % of a
500 Hz CAN cycle).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from support import ros_context_on, spin_until

from lca_control import contract as pc
from lca_control.contract import PlantSnapshot
from lca_sim.ros.plant_contract import PlantPublisher

DOMAIN_ID = 121
JOINTS = ("l_arm", "pivot", "c_arc", "lift")


def snapshot(stamp_s: float) -> PlantSnapshot:
    """A plausible snapshot: positions carry the stamp, so each message is identifiable."""
    n = len(JOINTS)
    ones = np.ones(n)
    return PlantSnapshot(
        stamp_s=stamp_s,
        joints=JOINTS,
        position=ones * stamp_s,
        velocity=ones * 0.1,
        effort=ones * 2.0,
        motor_position_rad=ones * 3.0,
        motor_velocity_rad_s=ones * 4.0,
        current_a=ones * 0.5,
        motion_state=np.zeros(n),
        drive_state=np.zeros(n),
        state_names=("stopped",),
        eta_m=ones * 0.9,
        eta_l=ones * 0.4,
        motor_torque_nm=ones * 0.02,
        load_torque_nm=ones * 0.01,
        friction_torque_nm=ones * 0.001,
        voltage_v=ones * 12.0,
    )


def count_graph_queries(pubs: list[Any]) -> dict[str, int]:
    """Count every `get_subscription_count` call on these publishers from now on."""
    queries = {"n": 0}
    for pub in pubs:
        original = pub.get_subscription_count

        def counted(original: Any = original) -> int:
            queries["n"] += 1
            return int(original())

        pub.get_subscription_count = counted
    return queries


def count_publishes(pubs: dict[str, Any]) -> dict[str, int]:
    """Count the messages actually handed to these publishers from now on."""
    built = dict.fromkeys(pubs, 0)
    for key, pub in pubs.items():
        send = pub.publish

        def counted(msg: Any, key: str = key, send: Any = send) -> None:
            built[key] += 1
            send(msg)

        pub.publish = counted
    return built


class Reader:
    """A node reading the state topics and ros2_control's copy: each message's stamp (s)."""

    def __init__(self, node: Node) -> None:
        self.got: dict[str, list[float]] = {
            "joint": [],
            "motor": [],
            "drive": [],
            "clock": [],
            "robot_joint": [],
        }
        self.values: set[tuple[str, ...]] = set()  # motor effort, the pivot's keys, as text
        qos = 100
        node.create_subscription(JointState, pc.JOINT_STATES, self._on_joint, qos)
        self.motor = node.create_subscription(JointState, pc.MOTOR_STATES, self._on_motor, qos)
        self.drive = node.create_subscription(
            DiagnosticArray, pc.DRIVE_CHAIN_STATES, self._on_drive, qos
        )
        node.create_subscription(Clock, pc.CLOCK, self._on_clock, qos)
        node.create_subscription(
            JointState, pc.ROBOT_JOINT_STATES, self._on_robot_joint, qos
        )  # ros2_control's copy of joint_states

    def _on_joint(self, m: JointState) -> None:
        self.got["joint"].append(m.position[1])

    def _on_robot_joint(self, m: JointState) -> None:
        self.got["robot_joint"].append(m.position[1])

    def _on_motor(self, m: JointState) -> None:
        self.got["motor"].append(m.header.stamp.sec)
        self.values.add(("motor", *m.name, *map(repr, m.effort)))

    def _on_drive(self, m: DiagnosticArray) -> None:
        self.got["drive"].append(m.header.stamp.sec)
        pivot = m.status[1]
        self.values.add((pivot.name, pivot.message, *(f"{v.key}={v.value}" for v in pivot.values)))

    def _on_clock(self, m: Clock) -> None:
        self.got["clock"].append(m.clock.sec)


def test_optional_topics_follow_their_subscribers_without_graph_queries() -> None:
    with ros_context_on(DOMAIN_ID) as (ctx, executor):
        plant_node = Node("plant", context=ctx)
        reader_node = Node("reader", context=ctx)
        executor.add_node(plant_node)
        executor.add_node(reader_node)
        publisher = PlantPublisher(
            plant_node, JOINTS, clock=True, joint_state_topic=pc.ROBOT_JOINT_STATES
        )
        queries = count_graph_queries(
            [publisher.motor_pub, publisher.drive_pub, publisher.clock_pub]
        )
        built = count_publishes({"motor": publisher.motor_pub, "drive": publisher.drive_pub})
        reader = Reader(reader_node)
        got = reader.got
        spin_until(
            executor,
            lambda: (
                publisher.joint_pub.get_subscription_count() == 1
                and publisher._motor_subs.count == 1
                and publisher._drive_subs.count == 1
                and publisher._clock_subs.count == 1
                and publisher._extra_subs.count == 1
            ),
            "the reader's five subscriptions matched and their events taken",
        )
        for k in range(1, 21):  # one at a time: keep-last queues hold no backlog
            publisher.publish(snapshot(float(k)))
            spin_until(
                executor,
                lambda k=k: all(len(v) == k for v in got.values()),  # type: ignore[misc]
                f"message {k} on each topic",
            )
        assert got["motor"] == list(range(1, 21))
        assert got["drive"] == list(range(1, 21))
        assert got["clock"] == list(range(1, 21))
        assert got["robot_joint"] == got["joint"] == list(range(1, 21))
        assert built == {"motor": 20, "drive": 20}
        assert reader.values == {
            ("motor", *JOINTS, "0.5", "0.5", "0.5", "0.5"),
            (
                "drive_chain/pivot",
                "stopped",
                "motion_state=stop",
                "drive_state=stopped",
                "eta_m=0.9",
                "eta_l=0.4",
                "motor_torque_nm=0.02",
                "load_torque_nm=0.01",
                "friction_torque_nm=0.001",
                "current_a=0.5",
                "voltage_v=12.0",
                "faults=none",
            ),
        }

        reader_node.destroy_subscription(reader.motor)
        reader_node.destroy_subscription(reader.drive)
        spin_until(
            executor,
            lambda: publisher._motor_subs.count == 0 and publisher._drive_subs.count == 0,
            "the unmatch events of motor_states and drive_chain_states",
        )
        for k in range(21, 31):
            publisher.publish(snapshot(float(k)))
            spin_until(
                executor,
                lambda k=k: len(got["joint"]) == len(got["clock"]) == k,  # type: ignore[misc]
                f"joint_states and /clock {k}",
            )
        assert built == {"motor": 20, "drive": 20}  # nobody listens: not built, not sent
        assert queries["n"] == 0, "publish asked the graph for subscriber counts"
        reader_node.destroy_node()
        plant_node.destroy_node()
