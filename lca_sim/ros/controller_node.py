"""The controller node: `ros2 run lca_hil controller` (console script `lca-controller`).

Runs the paper's cascaded PI loops over topics only, so it drives the simulator node and the CAN
bridge alike. Every new plant state (joint_states; with voltage commands also motor_states of the
same stamp, for the currents) yields one command, on the topic of `command_interface`
(`COMMAND_TOPICS`). With current or voltage it is followed by the velocity references on
velocity_commands when a plant subscribes them (CSV axes), and that is the last message per
state, the one that releases a lockstep plant; with velocity (velocity_commands) or position
(position_commands: the profile's position set-points, every loop in the drive) the one
command array is the only message per state. The period is the difference of the state
stamps, never the node clock, so the loop runs on simulated time exactly in lockstep without
`use_sim_time` (which then only changes the stamps of the controller's diagnostics).

Its plant peer on /diagnostics: before the first state it is waiting (OK "waiting for the
first plant state", said once in the log at INFO when the wait exceeds `plant_timeout_s`: a
simulator compiling its model at first start takes seconds); states that came and stop for
`plant_timeout_s` are a loss (WARN "no plant state for X s", logged as a warning), unless the
plant said it ended its run with that state: a lockstep simulator's status on /diagnostics says
`ended` at the time of its last state (`lockstep_end_s`), and silence after it is the end, not a
loss (OK "plant ended its run at T s", one INFO line).

    lca-controller --ros-args --params-file config/ros/controller.yaml
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool

from lca_control import contract as pc
from lca_control.controller import (
    CONTROLLER_PARAMETERS,
    ControllerParams,
    JointController,
    validate_controller_params,
)
from lca_sim.ros.node_util import (
    LiveParameters,
    declare_table,
    from_stamp,
    other_publishers,
    run_node,
    set_enabled_by_service,
    simulator_end_s,
    status,
)
from lca_sim.ros.ros_logging import log_at
from lca_sim.runtime import FreezeWatch, discounted

# A steady timer this often watches for freezes of this process (a paused host, a debugger):
# the plant's silence during one is not the plant's fault (`_wake`).
FREEZE_WATCH_PERIOD_S = 0.05
ENDS_KEPT = 8  # plant ends remembered: more simulators than this ending at once is no setup
# An end and a state stamp name the same instant: the stamp's nanoseconds against the status's
# float; far below any control period.
END_MATCH_S = 1e-6

# The topic of each command interface: the plant contract's command topics (docs/contract.md).
COMMAND_TOPICS = {
    "voltage": pc.VOLTAGE_COMMANDS,
    "current": pc.CURRENT_COMMANDS,
    "velocity": pc.VELOCITY_COMMANDS,
    "position": pc.POSITION_COMMANDS,
}


class ControllerNode(Node):
    """Cascaded PI control of the LCA axes over topics."""

    def __init__(self, node_name: str = "controller", **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self._live = LiveParameters(
            self,
            CONTROLLER_PARAMETERS,
            declare_table(self, CONTROLLER_PARAMETERS),
            validate_controller_params,
            self._apply_params,
        )
        params = self._live.params
        self.core = JointController(params)
        self._motor: JointState | None = None
        self._joint: JointState | None = None
        self._index: list[int] | None = None
        self._plant_t_s = 0.0
        self.commands_sent = 0
        self.states_skipped = 0
        self.states_held = 0  # states not answered while no reader of the commands matched
        self._held_state: JointState | None = None  # answered once a reader of commands matches
        self.bad_states = 0
        # Peer watch on the wall clock: /clock (use_sim_time) stops with a lost simulator.
        self._last_state_wall = time.monotonic()
        self._plant_lost = False  # silent beyond plant_timeout_s (before the first state too)
        self.plant_losses = 0
        self._freezes = FreezeWatch()  # the plant deadline forgives every freeze in full
        self._last_wake_wall = math.nan  # the first call sets it: start-up is no freeze
        # Simulated times at which a plant said on /diagnostics that its run ended (the last few).
        self._ends_announced_s: deque[float] = deque(maxlen=ENDS_KEPT)
        self._restarts_logged = 0
        state_qos = QoSProfile(depth=pc.STATE_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        command_qos = QoSProfile(depth=pc.COMMAND_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        topic = COMMAND_TOPICS[params.command_interface]
        self._command_pub = self.create_publisher(Float64MultiArray, topic, command_qos)
        # The topics no other node may publish: a second controller would fight this one.
        self._own_topics: tuple[str, ...] = (topic,)
        self._other_publishers: tuple[str, ...] = ()
        self._velocity_pub = None
        if topic in (pc.VOLTAGE_COMMANDS, pc.CURRENT_COMMANDS):  # the velocity loop runs here
            self._own_topics += (pc.VELOCITY_COMMANDS,)
            self._velocity_pub = self.create_publisher(
                Float64MultiArray, pc.VELOCITY_COMMANDS, command_qos
            )
        self._diag_pub = self.create_publisher(DiagnosticArray, pc.DIAGNOSTICS, 10)
        self.create_subscription(JointState, pc.JOINT_STATES, self._on_joint_states, state_qos)
        if params.command_interface == "voltage":
            # Only the current loop needs the motor currents; with current commands the drive
            # runs that loop, and every message not taken is executor time saved per step.
            self.create_subscription(JointState, pc.MOTOR_STATES, self._on_motor_states, state_qos)
        self.create_subscription(
            Float64MultiArray, pc.VELOCITY_REFERENCE, self._on_reference, command_qos
        )
        self.create_subscription(DiagnosticArray, pc.DIAGNOSTICS, self._on_diagnostics, 10)
        self.create_service(SetBool, "~/enable", self._on_enable)
        # A steady clock: on sim time these timers would stop with /clock, i.e. exactly when a
        # lost simulator has to be reported.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0, self._publish_diagnostics, clock=steady)
        self.create_timer(FREEZE_WATCH_PERIOD_S, self._wake, clock=steady)
        self.get_logger().info(
            f"{params.reference_source} reference, {params.command_interface} commands on "
            f"{topic} for {list(params.joints)}"
        )

    # --- plant states --------------------------------------------------------------------

    def _on_motor_states(self, msg: JointState) -> None:
        self._motor = msg
        self._try_step()

    def _on_joint_states(self, msg: JointState) -> None:
        now = time.monotonic()
        if self._plant_lost:
            self._plant_lost = False
            waited_s = now - self._last_state_wall
            again = "plant states again" if self._joint is not None else "first plant state"
            self.get_logger().info(f"{again} after {waited_s:.1f} s")
        self._joint = msg
        self._last_state_wall = now
        self._try_step()

    def _try_step(self) -> None:
        joint = self._joint
        if joint is None:
            return
        voltage = self.core.params.command_interface == "voltage"
        motor = self._motor
        if voltage and (motor is None or motor.header.stamp != joint.header.stamp):
            return  # wait for the currents of the same instant
        index = self._joint_index(list(joint.name))
        if index is None:
            return
        t_s = from_stamp(joint.header.stamp)
        try:
            positions = [joint.position[i] for i in index]
            velocities = [joint.velocity[i] for i in index]
            currents = [motor.effort[i] for i in index] if voltage and motor is not None else None
        except IndexError:
            self.bad_states += 1
            self.get_logger().warning("malformed joint or motor state", throttle_duration_sec=5.0)
            return
        if not self._command_pub.get_subscription_count():
            # Nobody reads the commands (the plant's reader not matched yet, or gone): an
            # answer now is lost, and a stamp is answered once only, so a lockstep plant that
            # re-publishes it (lockstep_resend_s) would wait for ever. The state is kept and
            # answered when a reader matches (`_wake`, 20 Hz) or the next state comes. Any
            # reader counts (a recorder too): which one is the plant, DDS does not say.
            if self._joint is not self._held_state:
                self.states_held += 1  # each state once, not each retry
                self._held_state = self._joint
            self.get_logger().info(
                f"no reader of {self._command_pub.topic_name} yet: the plant's state is answered "
                "once one matches",
                once=True,
            )
            return
        self._held_state = None
        commands = self.core.update(t_s, positions, velocities, currents)
        if self.core.plant_restarts != self._restarts_logged:
            self._restarts_logged = self.core.plant_restarts
            before_s = self.core.last_restart_from_s
            how = "went back" if t_s < before_s else "jumped forward"
            self.get_logger().warning(
                f"plant time {how} from {before_s:.4f} s to {t_s:.4f} s: a restarted or "
                "returning simulator or bridge; loops and reference restart from this state "
                f"(restart {self.core.plant_restarts})"
            )
        if commands is None:
            self.states_skipped += 1
            return
        self._plant_t_s = t_s
        self._command_pub.publish(Float64MultiArray(data=commands))
        velocity_pub = self._velocity_pub
        if velocity_pub is not None and velocity_pub.get_subscription_count():  # CSV axes
            velocity_pub.publish(Float64MultiArray(data=self.core.last_velocity_reference))
        self.commands_sent += 1

    def _joint_index(self, names: list[str]) -> list[int] | None:
        if self._index is None or len(names) != len(self._index):
            try:
                self._index = [names.index(j) for j in self.core.params.joints]
            except ValueError:
                self.bad_states += 1
                self.get_logger().warning(
                    f"joint_states lacks some of {list(self.core.params.joints)}: {names}",
                    throttle_duration_sec=5.0,
                )
                return None
        return self._index

    def _on_reference(self, msg: Float64MultiArray) -> None:
        reason = self.core.set_topic_reference(list(msg.data), self._plant_t_s)
        if reason is not None:
            self.get_logger().warning(
                f"velocity reference rejected ({self.core.rejected_references}): {reason}",
                throttle_duration_sec=1.0,
            )

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        """Keep the times at which a simulator said its run ended (`simulator_end_s`)."""
        for found in msg.status:
            end_s = simulator_end_s(found)
            if end_s is not None and math.isfinite(end_s):
                self._ends_announced_s.append(end_s)

    def _ended_with_last_state(self) -> float | None:
        """The time of the last state taken if its plant said its run ended there, else None.

        Matched by time, not by name: a simulator that ended elsewhere (another robot's, or
        this one before a reset) does not excuse this plant's silence.
        """
        if self._joint is None:
            return None
        last_s = from_stamp(self._joint.header.stamp)
        for end_s in self._ends_announced_s:
            if abs(end_s - last_s) <= END_MATCH_S:
                return last_s
        return None

    # --- services, parameters, diagnostics -----------------------------------------------

    def _on_enable(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        """The `enabled` parameter by service (`set_enabled_by_service`)."""
        response.success, response.message = set_enabled_by_service(
            self, bool(request.data), "disabled: zero commands"
        )
        return response

    def _apply_params(
        self, old: ControllerParams, new: ControllerParams, _changed: frozenset[str]
    ) -> None:
        """A live set: new gains, limits and references at the next state, bumpless."""
        self.core.set_params(new)
        if new.enabled and not old.enabled:
            self.core.reset()  # re-enabling starts the integrators from zero

    def _wake(self) -> None:
        """The freeze watch (and the diagnostics first): a freeze is not the plant's silence.

        A steady timer later than its period plus `FREEZE_THRESHOLD_S` after the last call
        means this process stood still: the states the plant sent meanwhile wait unread (or,
        on a paused host, the plant stood still too), so the plant deadline moves on by the
        freeze, never past now. The simulator and the CAN bridge do the same for commands.
        """
        if self._held_state is not None:
            self._try_step()  # the state held while no reader of the commands matched
        now = time.monotonic()
        freeze = self._freezes.check(now - self._last_wake_wall - FREEZE_WATCH_PERIOD_S)
        self._last_wake_wall = now
        if freeze is None:
            return
        self._last_state_wall = discounted(self._last_state_wall, freeze.discount_s, now)
        note = self._freezes.note(
            freeze, self.core.params.plant_timeout_s, "the plant's silence does not count it"
        )
        if note is not None:
            log_at(self.get_logger(), *note)

    def _plant_health(self) -> tuple[bytes, str]:
        """The plant peer for /diagnostics: WARN while states that came stop for plant_timeout_s.

        Before the first state the controller is waiting, which is no fault: OK, said once in
        the log at INFO once the wait exceeds plant_timeout_s. A loss is logged once when it
        begins; its end (or the first state after a long wait) when states come.
        """
        silent_s = time.monotonic() - self._last_state_wall
        late = silent_s > self.core.params.plant_timeout_s
        first = late and not self._plant_lost
        self._plant_lost = self._plant_lost or late
        if self._joint is None:
            what = f"waiting for the first plant state ({silent_s:.1f} s since start)"
            if first:
                self.get_logger().info(f"{what}: is the simulator or CAN bridge running?")
            return DiagnosticStatus.OK, what
        ended_s = self._ended_with_last_state() if late else None
        if ended_s is not None:
            what = f"plant ended its run at {ended_s:g} s"
            if first:
                self.get_logger().info(f"{what}: its last state is answered; none will follow")
            return DiagnosticStatus.OK, what
        if late:
            what = f"no plant state for {silent_s:.1f} s"
            if first:
                self.plant_losses += 1
                self.get_logger().warning(
                    f"{what}: no commands are sent; is the simulator or CAN bridge running?"
                )
            return DiagnosticStatus.WARN, what
        if self.plant_losses:
            return DiagnosticStatus.OK, "plant states again"
        return DiagnosticStatus.OK, "running"

    def _graph_health(self, values: dict[str, object]) -> str | None:
        """The ERROR message while another node publishes this one's commands, else None.

        Read from the ROS graph (`get_publishers_info_by_topic`) every diagnostics period, as
        the plants check their state topics (`PlantPublisher.graph_health`): a second
        controller, or a node of this name started twice, would send the plant two commands
        per state. Its start and its end are logged once each; the publishers found go to
        `values["other_publishers"]`.
        """
        found = other_publishers(self, self._own_topics)
        if tuple(found) != self._other_publishers:
            if found:
                self.get_logger().error(
                    f"another node publishes {'; '.join(found)}: the plant gets two commands "
                    "per state; stop the other controller"
                )
            elif self._other_publishers:
                self.get_logger().info("no other publisher of the commands any more")
            self._other_publishers = tuple(found)
        values["other_publishers"] = "; ".join(found) or "none"
        return f"another node publishes {found[0]}" if found else None

    def _publish_diagnostics(self) -> None:
        self._wake()  # may run first after a freeze: the plant's silence it judges is discounted
        core = self.core
        level, message = self._plant_health()
        if level == DiagnosticStatus.OK and (core.rejected_references or self.bad_states):
            level, message = DiagnosticStatus.WARN, "bad states or references (see counters)"
        if core.bad_states:  # said beside any other warning, never hidden behind it
            lost = (
                f"{core.bad_states} plant states with NaN or infinite readings (a lost sensor "
                "sample): the last command was sent again for each"
            )
            message = lost if level == DiagnosticStatus.OK else f"{message}; {lost}"
            level = max(level, DiagnosticStatus.WARN)
        values: dict[str, object] = {}
        conflict = self._graph_health(values)
        if conflict is not None:  # the worst first, then what else is wrong
            message = conflict if level == DiagnosticStatus.OK else f"{conflict}; {message}"
            level = DiagnosticStatus.ERROR
        values |= {
            "enabled": core.params.enabled,
            "reference_source": core.params.reference_source,
            "elapsed_s": core.elapsed_s,
            "commands_sent": self.commands_sent,
            "states_skipped": self.states_skipped,
            "states_held_for_a_reader": self.states_held,
            "bad_states": self.bad_states,
            "states_not_finite": core.bad_states,
            "references_rejected": core.rejected_references,
            "plant_state_age_s": time.monotonic() - self._last_state_wall,
            "plant_losses": self.plant_losses,
            "process_freezes": self._freezes.count,
            "longest_freeze_s": self._freezes.longest_s,
            "plant_restarts": core.plant_restarts,
        }
        for joint, reference in zip(core.params.joints, core.last_velocity_reference, strict=True):
            values[f"{joint}_velocity_reference"] = reference
        if core.params.command_interface == "position":
            for joint, setpoint in zip(
                core.params.joints, core.last_position_setpoint, strict=True
            ):
                values[f"{joint}_position_setpoint"] = setpoint
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(status("lca_hil/controller", level, message, values))
        self._diag_pub.publish(array)


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-controller` / `ros2 run lca_hil controller`."""
    return run_node("lca-controller", ControllerNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
