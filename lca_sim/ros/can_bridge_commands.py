"""The CAN bridge's command inputs: current, velocity, position and JointState commands.

`BridgeCommands` subscribes to `current_commands`, `velocity_commands` (csv axes only),
`position_commands` (csp axes only),
`voltage_commands` (refused: CiA 402 drives take torque) and the JointState command topic
(docs/ros2_control.md), hands the values to the master while the node is active, and in
lockstep lets the controller's answer release the next SYNC. docs/can.md has the whole story.

In real time the subscriptions are polled, not spun: the master's cycle thread takes what came
since the last SYNC (`poll`, just before it builds the RPDOs), each command with the time rmw
received it, so in time and late are judged as before. Spinning them woke the executor's
thread for every command, a second thread taking the GIL in each 2 ms cycle (about 100 us of
CPU per command; docs/can-transport.md). A polled subscription is the bridge node's, as the
graph shows, but not registered with it, so no executor takes from it
(`node_util.unspun_subscription`).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.subscription import Subscription
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from lca_control import contract as pc
from lca_sim.canbus.master import Cia402Master
from lca_sim.config.can_bridge_params import CanBridgeNodeParams
from lca_sim.model.params import RobotParams
from lca_sim.ros.can_drives import CanDrives
from lca_sim.ros.contract_cdr import CdrError, float64_multi_array_data
from lca_sim.ros.joint_command import JointCommandAdapter, effort_scales, unserved_axes
from lca_sim.ros.node_util import MatchedCount, destroy_unspun, unspun_subscription
from lca_sim.ros.plant_contract import qos_profile


class BridgeCommands:
    """The bridge's command subscriptions and what they count.

    Args:
        node: the bridge node; the subscriptions are created on it.
        p: its parameters at start-up (the joints, modes and topics are read-only).
        robot: the robot config (k_t and gear ratios for a JointState torque).
        drives: the node's drives (the master, the lockstep loop).
        active: the node is lifecycle ACTIVE (commands are passed on only then).
        lifecycle_state: the lifecycle state's label, for the warning while inactive.
        polled: take the commands in `poll` (real time) instead of from the executor.
    """

    def __init__(
        self,
        node: Node,
        p: CanBridgeNodeParams,
        robot: RobotParams,
        drives: CanDrives,
        active: Callable[[], bool],
        lifecycle_state: Callable[[], str],
        *,
        polled: bool = False,
    ) -> None:
        self._log = node.get_logger()  # type: ignore[no-untyped-call]  # rclpy is untyped here
        self._drives = drives
        self._active = active
        self._lifecycle_state = lifecycle_state
        self.velocity_axes = tuple(j for j, m in zip(p.joints, p.modes, strict=False) if m == "csv")
        self.position_axes = tuple(j for j, m in zip(p.joints, p.modes, strict=False) if m == "csp")
        modes = p.modes or ("cst",) * len(p.joints)
        self._axes_of = {  # the topic that serves each mode's axes, and those axes
            pc.CURRENT_COMMANDS: tuple(
                j for j, m in zip(p.joints, modes, strict=True) if m == "cst"
            ),
            pc.VELOCITY_COMMANDS: self.velocity_axes,
            pc.POSITION_COMMANDS: self.position_axes,
        }
        self.taken = dict.fromkeys(self._axes_of, 0)  # command arrays taken, per topic
        self.wrong_interface = 0
        self.undecodable = 0  # polled command bytes that were no Float64MultiArray
        self.unpublished_skips = 0  # polls that did not ask a topic nobody publishes
        self.ignored_inactive = 0  # commands that came while not active
        # ros2_control's topic-based interface: the commands in force, joint order, so a
        # JointState naming some joints leaves the others as they are.
        self._held_current_a = [0.0] * len(p.joints)
        self._held_velocity = [0.0] * len(p.joints)
        # NaN: no position command, a csp drive holds where it is (a JointState naming some
        # joints must not send the others to 0).
        self._held_position = [math.nan] * len(p.joints)
        self.joint_commands = JointCommandAdapter(
            p.joints,
            effort_scales(robot, p.joints, p.joint_command_effort),
            velocity_joints=self.velocity_axes,
            velocity_refused=lambda j: (
                f"velocity for {j}: their drives run cst (modes), send effort"
            ),
            effort_refused=lambda j: (
                f"effort for {j}: their drives run csv or csp (modes), send velocity or position"
            ),
            topic=p.joint_command_topic,
            position_joints=self.position_axes,
            position_refused=lambda j: f"position for {j}: their drives do not run csp (modes)",
        )
        self._node = node
        self._polls = polled
        self._polled: list[_Polled] = []
        self._poll_lock = threading.Lock()  # the cycle thread and the diagnostics timer
        self._subscribe(Float64MultiArray, pc.CURRENT_COMMANDS, self._on_current)
        self._subscribe(Float64MultiArray, pc.VOLTAGE_COMMANDS, self._on_voltage)
        if self.velocity_axes:  # CSV axes close their velocity loop in the drive
            self._subscribe(Float64MultiArray, pc.VELOCITY_COMMANDS, self._on_velocity)
        if self.position_axes:  # CSP axes close position and velocity loops in the drive
            self._subscribe(Float64MultiArray, pc.POSITION_COMMANDS, self._on_position)
        if p.joint_command_topic:
            self._subscribe(JointState, p.joint_command_topic, self._on_joint)

    def _subscribe(
        self, msg_type: Any, topic: str, handler: Callable[[Any, float | None], None]
    ) -> None:
        """Subscribe `handler(values or message, receipt time or None)` to `topic`.

        A Float64MultiArray handler gets its data as a list; polled, it is read from the
        serialized bytes (`float64_multi_array_data`), without building the message.
        """
        node, qos = self._node, qos_profile(pc.COMMAND_QOS)
        arrays = msg_type is Float64MultiArray
        if not self._polls:
            if arrays:

                def on_array(msg: Float64MultiArray) -> None:
                    handler(list(msg.data), None)

                node.create_subscription(msg_type, topic, on_array, qos)
            else:
                node.create_subscription(msg_type, topic, lambda msg: handler(msg, None), qos)
            return
        publishers = MatchedCount()
        sub = unspun_subscription(
            node,
            msg_type,
            topic,
            qos,
            raw=arrays,
            event_callbacks=publishers.subscription_callbacks(),
        )
        self._polled.append(_Polled(sub, handler, publishers))

    def poll(self) -> None:
        """Take every command that came since the last poll, with its receive time (real time).

        Called by the master's cycle thread before each SYNC's RPDOs, and by the diagnostics
        timer, which counts the commands that come while no cycle runs (unconfigured). A topic
        nobody publishes is not asked (a take costs about 20 us at 500 Hz on the 2-core host,
        voltage_commands' every cycle): it is drained once after its last publisher left.
        """
        if not self._polled:
            return
        with self._poll_lock:
            offset_ns = time.time_ns() - time.monotonic_ns()
            now_s = time.monotonic()
            for polled in self._polled:
                if polled.publishers.count:
                    polled.drained = False
                elif polled.drained:
                    self.unpublished_skips += 1
                    continue
                else:
                    polled.drained = True  # what came before the last publisher left
                sub, handler = polled.sub, polled.handler
                while True:
                    try:
                        with sub.handle:
                            taken = sub.handle.take_message(sub.msg_type, sub.raw)
                    except InvalidHandle:  # destroyed: the node is shutting down
                        return
                    if taken is None:
                        break
                    msg, info = taken
                    received_ns = int(info.get("received_timestamp") or 0)
                    # rmw stamps the receipt on the system clock; the master judges on the
                    # monotonic one. No receipt time (an rmw without it): now.
                    at_s = min(now_s, (received_ns - offset_ns) * 1e-9) if received_ns else now_s
                    if not sub.raw:
                        handler(msg, at_s)
                        continue
                    try:
                        handler(float64_multi_array_data(msg), at_s)
                    except CdrError as exc:
                        self.undecodable += 1
                        self._log.warning(
                            f"{sub.topic_name}: cannot read a command ({self.undecodable} so "
                            f"far): {exc}",
                            throttle_duration_sec=1.0,
                        )

    def publisher_counts(self) -> dict[str, int]:
        """Each polled topic's publishers, as its matched events last said."""
        return {polled.sub.topic_name: polled.publishers.count for polled in self._polled}

    def destroy(self) -> None:
        """Destroy the polled subscriptions (before the bridge node)."""
        with self._poll_lock:
            polled, self._polled = self._polled, []
        for each in polled:
            destroy_unspun(self._node, each.sub)

    def unserved(self) -> str:
        """Axes no command topic serves while another does (`unserved_axes`).

        JointState commands serve every mode.
        """
        if self.joint_commands.counts["accepted"]:
            return ""
        return unserved_axes(self._axes_of, self.taken)

    def _commanding(self) -> Cia402Master | None:
        """The master, when the node is active; else None, the command counted and warned."""
        master = self._drives.master
        active = self._active()
        if active and master is not None:
            return master
        self.ignored_inactive += 1
        if active:  # the master is gone under an active node: it is shutting down
            self._log.info(
                "ignoring commands: the node is shutting down (its drives are released)",
                once=True,
            )
            return None
        self._log.warning(
            f"ignoring commands while {self._lifecycle_state()} ({self.ignored_inactive} so "
            "far): activate the node",
            throttle_duration_sec=5.0,
        )
        return None

    def _on_current(self, values: list[float], at: float | None) -> None:
        master = self._commanding()
        if master is not None:
            self._set_currents(master, values, at)
            self.taken[pc.CURRENT_COMMANDS] += 1
            if not (self.velocity_axes or self.position_axes):
                self._answered()

    def _answered(self) -> None:
        """Lockstep: the controller's answer (taken or refused) releases the next SYNC.

        The answer is the last message the controller sends per state: current_commands, or
        with CSV axes the velocity_commands it publishes after them (the currents are then in
        force already), with CSP axes the position_commands of a controller whose
        command_interface is position (its only message per state), or one JointState command.
        """
        loop = self._drives.loop
        if loop is not None:
            loop.on_command(time.monotonic())

    def _set_currents(
        self, master: Cia402Master, currents_a: list[float], at: float | None
    ) -> None:
        reason = master.set_currents(currents_a, at)
        if reason is None:
            self._held_current_a[:] = currents_a
        else:
            self._log.warning(
                f"command rejected ({master.counters.commands_rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )

    def _on_velocity(self, values: list[float], at: float | None) -> None:
        master = self._commanding()
        if master is not None:
            self._set_velocities(master, values, at)
            self.taken[pc.VELOCITY_COMMANDS] += 1
            if not self.position_axes:
                self._answered()

    def _on_position(self, values: list[float], at: float | None) -> None:
        master = self._commanding()
        if master is not None:
            self._set_positions(master, values, at)
            self.taken[pc.POSITION_COMMANDS] += 1
            self._answered()

    def _set_positions(
        self, master: Cia402Master, positions: list[float], at: float | None
    ) -> None:
        reason = master.set_positions(positions, at)
        if reason is None:
            self._held_position[:] = positions
        else:
            self._log.warning(
                f"position command rejected ({master.counters.commands_rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )

    def _set_velocities(
        self, master: Cia402Master, velocities: list[float], at: float | None
    ) -> None:
        reason = master.set_velocities(velocities, at)
        if reason is None:
            self._held_velocity[:] = velocities
        else:
            self._log.warning(
                f"velocity command rejected ({master.counters.commands_rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )

    def _on_joint(self, msg: JointState, at: float | None) -> None:
        """A JointState command (docs/ros2_control.md), each joint by its drive's mode.

        A cst joint takes its effort entry (A, or joint torque per `joint_command_effort`),
        a csv joint its velocity entry, a csp joint its position entry (rad or m; the drive
        closes the loops); joints not named, or with
        NaN, keep their command. The entry of the other field is ignored when zero (what the
        interface sends for an interface no controller claims) and refused when not.
        """
        master = self._commanding()
        if master is None:
            return
        adapter = self.joint_commands
        cmd = adapter.read(msg.name, msg.velocity, msg.effort, position=msg.position)
        if cmd.accepted and cmd.effort:
            self._set_currents(master, adapter.fill(self._held_current_a, cmd.effort), at)
        if cmd.accepted and cmd.velocity:
            self._set_velocities(master, adapter.fill(self._held_velocity, cmd.velocity), at)
        if cmd.accepted and cmd.position:
            self._set_positions(master, adapter.fill(self._held_position, cmd.position), at)
        if cmd.problems:
            self._log.warning(adapter.warning(cmd.problems), throttle_duration_sec=1.0)
        self._answered()

    def _on_voltage(self, _values: list[float], _at: float | None) -> None:
        self.wrong_interface += 1
        self._log.warning(
            f"ignoring voltage commands ({self.wrong_interface} so far): CiA 402 drives take "
            "torque; run the controller with command_interface: current",
            throttle_duration_sec=5.0,
        )


@dataclass(slots=True)
class _Polled:
    """A polled subscription, its handler, its publishers, and whether it was drained at 0."""

    sub: Subscription
    handler: Callable[[Any, float | None], None]
    publishers: MatchedCount
    drained: bool = False
