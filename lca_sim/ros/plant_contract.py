"""The one builder of the plant contract's messages: every backend publishes through it.

A backend (the simulator node, the CAN bridge) fills a `lca_control.contract.PlantSnapshot` and
hands it to `PlantPublisher.publish` (the CAN bridge hands the same values as plain lists to
`publish_values`, without building arrays on its cycle thread); this module alone turns them
into `joint_states`, `motor_states`, `drive_chain_states` (and `/clock` for a lockstep plant),
with the contract's topic names, types and QoS, so the backends cannot drift apart. The per-joint
`drive_chain/<joint>` statuses carry exactly `DRIVE_STATE_KEYS`, names from the contract's
vocabularies (`UNKNOWN` for a code the backend has no report of) and numbers in repr form
('nan' for NaN).

Cost: the messages go out serialized (`contract_cdr.ContractCdr`: the bytes rclpy's serializer
would make, laid out once per joint set), not as rclpy messages converted field by field on
every publish; a message nobody subscribes to is not built at all (a subscriber that joins later
gets it from its first match on: the optional topics' subscribers are counted from rmw's
matched events, not asked of the graph on every cycle). joint_states always goes out: it is
what a controller waits for, so it goes first, then motor_states, /clock and the drive chain.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from lca_control import contract as pc
from lca_control.contract import PlantSnapshot
from lca_sim.errors import LcaHilError
from lca_sim.ros.contract_cdr import ContractCdr, DriveChainRows, drive_chain_rows, stamp_parts
from lca_sim.ros.node_util import MatchedCount, other_publishers

# (position, velocity, effort) of one JointState, each in joint order.
JointValues = tuple[Sequence[float], Sequence[float], Sequence[float]]

_RELIABILITY = {
    pc.RELIABLE: ReliabilityPolicy.RELIABLE,
    pc.BEST_EFFORT: ReliabilityPolicy.BEST_EFFORT,
}


# The topics only the plant publishes: a second publisher of any of them is a second plant.
STATE_TOPICS = (pc.JOINT_STATES, pc.MOTOR_STATES, pc.DRIVE_CHAIN_STATES)


class SnapshotError(LcaHilError):
    """A snapshot that does not fit the publisher (other joints, or in another order)."""


def qos_profile(spec: pc.QosSpec) -> QoSProfile:
    """The rclpy QoS profile of a contract QoS (keep-last depth, reliability, volatile)."""
    return QoSProfile(depth=spec.depth, reliability=_RELIABILITY[spec.reliability])  # type: ignore[no-untyped-call]


class PlantPublisher:
    """A plant's state publishers, with the contract's names, types and QoS.

    Args:
        node: the backend's node; the publishers are created on it.
        joints: the joint names every snapshot carries, in the robot's axis order.
        clock: also publish /clock with each snapshot's stamp (a lockstep plant).
        joint_state_topic: also publish joint_states' message on this topic (ros2_control's
            `/robot_joint_states`); empty: not at all.
    """

    def __init__(
        self,
        node: Node,
        joints: Sequence[str],
        *,
        clock: bool = False,
        joint_state_topic: str = "",
    ) -> None:
        self.joints = tuple(joints)
        self._node = node
        self._log = node.get_logger()  # type: ignore[no-untyped-call]  # rclpy is untyped here
        self._other_publishers: tuple[str, ...] = ()
        state_qos = qos_profile(pc.STATE_QOS)
        self._motor_subs, self._drive_subs = MatchedCount(), MatchedCount()
        self._clock_subs, self._extra_subs = MatchedCount(), MatchedCount()
        self.joint_pub: Publisher = node.create_publisher(JointState, pc.JOINT_STATES, state_qos)
        self.motor_pub: Publisher = node.create_publisher(
            JointState,
            pc.MOTOR_STATES,
            state_qos,
            event_callbacks=self._motor_subs.publisher_callbacks(),
        )
        self.drive_pub: Publisher = node.create_publisher(
            DiagnosticArray,
            pc.DRIVE_CHAIN_STATES,
            state_qos,
            event_callbacks=self._drive_subs.publisher_callbacks(),
        )
        self.diagnostics_pub: Publisher = node.create_publisher(
            DiagnosticArray, pc.DIAGNOSTICS, qos_profile(pc.DIAGNOSTICS_QOS)
        )
        self.clock_pub: Publisher | None = (
            node.create_publisher(
                Clock,
                pc.CLOCK,
                qos_profile(pc.CLOCK_QOS),
                event_callbacks=self._clock_subs.publisher_callbacks(),
            )
            if clock
            else None
        )
        self.extra_joint_pub: Publisher | None = (
            node.create_publisher(
                JointState,
                joint_state_topic,
                state_qos,
                event_callbacks=self._extra_subs.publisher_callbacks(),
            )
            if joint_state_topic
            else None
        )
        self._cdr = ContractCdr(self.joints)
        self.published = 0

    def publish(self, snap: PlantSnapshot) -> None:
        """Publish one instant: joint_states always, the others if anyone subscribes.

        Raises:
            SnapshotError: the snapshot's joints are not this publisher's (a backend bug).
        """
        if snap.joints is not self.joints and snap.joints != self.joints:
            raise SnapshotError(
                f"snapshot joints {list(snap.joints)}, the publisher's {list(self.joints)}"
            )
        self.publish_values(
            snap.stamp_s,
            (snap.position.tolist(), snap.velocity.tolist(), snap.effort.tolist()),
            (
                snap.motor_position_rad.tolist(),
                snap.motor_velocity_rad_s.tolist(),
                snap.current_a.tolist(),
            ),
            lambda: drive_chain_rows(snap),
        )

    def publish_values(
        self,
        stamp_s: float,
        joint: JointValues,
        motor: JointValues,
        drive_chain: Callable[[], DriveChainRows],
    ) -> None:
        """Publish one instant from plain values in this publisher's joint order.

        `joint` and `motor` are (position, velocity, effort) of joint_states and motor_states
        (motor side: rad, rad/s, A); `drive_chain` is called only when drive_chain_states has a
        subscriber. The CAN bridge fills these from its drives' states directly, without a
        snapshot's arrays (`publish` is the same for a `PlantSnapshot`).
        """
        sec, nanosec = stamp_parts(stamp_s)
        cdr = self._cdr
        joint_cdr = cdr.joint_state(sec, nanosec, *joint)
        self.joint_pub.publish(joint_cdr)
        extra = self.extra_joint_pub
        if extra is not None and self._extra_subs.count:  # ros2_control listens
            extra.publish(joint_cdr)
        if self._motor_subs.count:
            self.motor_pub.publish(cdr.joint_state(sec, nanosec, *motor))
        if self.clock_pub is not None and self._clock_subs.count:
            self.clock_pub.publish(cdr.clock(sec, nanosec))
        if self._drive_subs.count:
            self.drive_pub.publish(cdr.drive_chain(sec, nanosec, drive_chain()))
        self.published += 1

    def publish_diagnostics(self, array: DiagnosticArray) -> None:
        """Publish the node's own /diagnostics (its content is the node's)."""
        self.diagnostics_pub.publish(array)

    def graph_health(self, values: dict[str, object]) -> tuple[bytes, str] | None:
        """ERROR while another node publishes one of the plant's state topics, else None.

        Read from the ROS graph (`get_publishers_info_by_topic`) each call; both backends call
        it every diagnostics period. Another node of the same name shows as a second publisher
        under this node's name. Its start and its end are logged once each, and the publishers
        found go to `values["other_publishers"]`.
        """
        found = other_publishers(self._node, STATE_TOPICS)
        if tuple(found) != self._other_publishers:
            if found:
                self._log.error(f"another node publishes {'; '.join(found)}")
            elif self._other_publishers:
                self._log.info("no other publisher of the plant's states any more")
            self._other_publishers = tuple(found)
        values["other_publishers"] = "; ".join(found) or "none"
        return (DiagnosticStatus.ERROR, f"another node publishes {found[0]}") if found else None


def worst_first(found: Sequence[tuple[bytes, str]]) -> tuple[bytes, str]:
    """The worst level and the messages at or above WARN, the worst first (OK: the first one)."""
    level = max(item[0] for item in found)
    if level == DiagnosticStatus.OK:
        return found[0]
    ranked = sorted(
        (item for item in found if item[0] != DiagnosticStatus.OK), key=lambda i: -i[0][0]
    )
    return level, "; ".join(message for _, message in ranked)
