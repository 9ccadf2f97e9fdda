"""The simulator's command inputs: voltage, current, velocity, position arrays, JointState.

`SimCommands` subscribes to the command topic of `command_interface` (and counts what comes
on the other one), to `velocity_commands` / `position_commands` when a joint runs that drive
mode (`drive_modes`), and to the JointState command topic (docs/ros2_control.md); it puts each
command in force on the plant and, in lockstep, hands the controller's answer on as the
period's command. A refused command still runs its period in lockstep, so the loop goes on
with the last good command.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from lca_control import contract as pc
from lca_control.drive_loops import DriveMode
from lca_sim.config.simulator_params import SimulatorNodeParams
from lca_sim.model.commanded_plant import CommandedPlant
from lca_sim.model.drive_modes import JointDriveLoops
from lca_sim.model.params import RobotParams
from lca_sim.ros.joint_command import JointCommandAdapter, effort_scales, unserved_axes
from lca_sim.ros.plant_contract import qos_profile
from lca_sim.ros.sim_pacing import SimPacing


class SimCommands:
    """The simulator's command subscriptions and what they count.

    Args:
        node: the simulator node; the subscriptions are created on it.
        p: its parameters at start-up (the interface, joints and topics are read-only).
        robot: the robot config (k_t and gear ratios for a JointState torque).
        axis_names: the simulator's axes, in its order (the plant's `target`).
        plant: the commanded plant the commands go to.
        pacing: the node's simulated time (lockstep start, pause, step budget).
        run_period: lockstep: run the period of the command just taken.
    """

    def __init__(
        self,
        node: Node,
        p: SimulatorNodeParams,
        robot: RobotParams,
        axis_names: tuple[str, ...],
        plant: CommandedPlant,
        pacing: SimPacing,
        run_period: Callable[[], None],
    ) -> None:
        self._log = node.get_logger()  # type: ignore[no-untyped-call]  # rclpy is untyped here
        self._interface = p.command_interface
        self._plant = plant
        self._pacing = pacing
        self._run_period = run_period
        self.wrong_interface = 0
        qos = qos_profile(pc.COMMAND_QOS)
        self.topic, other = (
            (pc.VOLTAGE_COMMANDS, pc.CURRENT_COMMANDS)
            if p.command_interface == "voltage"
            else (pc.CURRENT_COMMANDS, pc.VOLTAGE_COMMANDS)
        )
        modes = p.joint_drive_modes
        velocity_joints = tuple(j for j, m in zip(p.joints, modes, strict=True) if m == "velocity")
        position_joints = tuple(j for j, m in zip(p.joints, modes, strict=True) if m == "position")
        # Lockstep: the controller's answer is the last topic it sends per state (current or
        # voltage, then velocity, then position), as on the CAN bridge; the others are put
        # in force when they come and run no period.
        self.answer_topic = self.topic
        self._axes_of = {  # the topic that serves each drive mode's joints, and those joints
            self.topic: tuple(
                j for j, m in zip(p.joints, modes, strict=True) if m == p.command_interface
            ),
            pc.VELOCITY_COMMANDS: velocity_joints,
            pc.POSITION_COMMANDS: position_joints,
        }
        self.taken = dict.fromkeys(self._axes_of, 0)  # command arrays taken, per topic
        node.create_subscription(Float64MultiArray, self.topic, self.on_command, qos)
        node.create_subscription(Float64MultiArray, other, self._on_wrong_interface, qos)
        for mode, topic in (
            (DriveMode.VELOCITY, pc.VELOCITY_COMMANDS),
            (DriveMode.POSITION, pc.POSITION_COMMANDS),
        ):
            if mode.value in modes:
                callback = partial(self._on_targets, mode, topic)
                node.create_subscription(Float64MultiArray, topic, callback, qos)
                self.answer_topic = topic
        # ros2_control's topic-based interface: A per joint, or joint torque / (k_t N); the
        # velocity entry for velocity-mode joints, the position entry for position-mode ones.
        self._joint_index = [axis_names.index(j) for j in p.joints]
        self.joint_commands = JointCommandAdapter(
            p.joints,
            effort_scales(robot, p.joints, p.joint_command_effort),
            velocity_joints=velocity_joints,
            takes_effort=p.command_interface != "voltage",
            velocity_refused=lambda j: (
                f"velocity commands for {j}: not in velocity mode (drive_modes); command "
                "effort, or run the joint in velocity mode"
            ),
            effort_refused=lambda _: (
                "effort refused: the simulator takes voltages (command_interface)"
            ),
            topic=p.joint_command_topic,
            position_joints=position_joints,
            position_refused=lambda j: (
                f"position commands for {j}: not in position mode (drive_modes); command "
                "effort or velocity, or run the joint in position mode"
            ),
        )
        if p.joint_command_topic:
            node.create_subscription(JointState, p.joint_command_topic, self._on_joint, qos)

    def on_command(self, msg: Float64MultiArray) -> None:
        """A command array on the interface's topic (joints order)."""
        self.taken[self.topic] += 1
        self._take(list(msg.data), self._plant.command, self.answer_topic == self.topic)

    def _on_targets(self, mode: DriveMode, topic: str, msg: Float64MultiArray) -> None:
        """velocity_commands or position_commands (joints order; other joints' entries ignored)."""
        apply = partial(self._plant.command_targets, mode)
        self.taken[topic] += 1
        self._take(list(msg.data), apply, self.answer_topic == topic)

    def unserved(self) -> str:
        """Joints no command topic serves while another does (`unserved_axes`).

        JointState commands serve every mode.
        """
        if self.joint_commands.counts["accepted"]:
            return ""
        return unserved_axes(self._axes_of, self.taken)

    def _on_joint(self, msg: JointState) -> None:
        """A JointState command (docs/ros2_control.md): position, velocity or effort by name.

        Effort is this node's command (A, or joint torque per `joint_command_effort`) on the
        joints named with a finite entry; velocity the target of velocity-mode joints, position
        (rad, m) that of position-mode joints; every other joint keeps its command. A non-zero
        velocity or position entry for a joint not in that mode is refused (counted, warned);
        a zero one is what the interface sends for an interface no controller claims, NaN
        what Jazzy's sends. In voltage mode effort has no meaning here and the message is
        refused. In lockstep the message is the period's command either way, as a refused
        array is.
        """
        adapter = self.joint_commands
        cmd = adapter.read(msg.name, msg.velocity, msg.effort, position=msg.position)
        if cmd.problems:
            self._log.warning(adapter.warning(cmd.problems), throttle_duration_sec=1.0)
        if not cmd.accepted:
            self._take(None, self._plant.command, answers=True)
            return
        plant = self._plant
        if cmd.position and plant.drive is not None:
            apply = partial(plant.command_targets, DriveMode.POSITION)
            answers = not (cmd.velocity or cmd.effort)
            held = self._held_positions(plant.drive)
            self._take(adapter.fill(held, cmd.position), apply, answers)
        if cmd.velocity and plant.drive is not None:
            held = list(plant.drive.velocity_targets)
            apply = partial(plant.command_targets, DriveMode.VELOCITY)
            self._take(adapter.fill(held, cmd.velocity), apply, answers=not cmd.effort)
        if cmd.effort:
            held = plant.target[self._joint_index].tolist()
            self._take(adapter.fill(held, cmd.effort), plant.command, answers=True)

    def _held_positions(self, drive: JointDriveLoops) -> list[float]:
        """Each joint's position target in force (joints order), rad (m).

        A joint without one (halted, or not in position mode) holds where it is: its present
        position, never 0, so a JointState naming some joints leaves the others in place.
        """
        present = self._plant.sim.state.position
        targets = drive.position_targets
        return [
            present[axis] if target is None else target
            for axis, target in zip(self._joint_index, targets, strict=True)
        ]

    def _take(
        self,
        values: list[float] | None,
        apply: Callable[[list[float]], str | None],
        answers: bool,
    ) -> None:
        """One command array (joints order): in force, and in lockstep the period's command.

        Only a command that `answers` the state runs the period (the last topic sent).
        None: a refused JointState command, which in lockstep still runs the period (in
        realtime it is no command: the timeout runs on).
        """
        pacing = self._pacing
        if values is None and not pacing.lockstep:
            return
        reason = None if values is None else apply(values)
        if reason is not None:
            self._log.warning(
                f"command rejected ({self._plant.counters.rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )
            if not pacing.lockstep:
                return
            # In lockstep the loop must go on: the last good command stays in force.
        if not answers:
            if reason is None:
                pacing.command_came()  # the command timeout counts from here
            return
        pacing.command_came()
        if pacing.lockstep and pacing.started:
            if pacing.paused and not pacing.admit_paused_command():
                return  # it waits for ~/step or ~/resume (`command_pending`)
            self._run_period()

    def _on_wrong_interface(self, msg: Float64MultiArray) -> None:
        self.wrong_interface += 1
        self._log.warning(
            f"ignoring commands on the inactive interface ({self.wrong_interface} so far); "
            f"command_interface is {self._interface}",
            throttle_duration_sec=5.0,
        )
