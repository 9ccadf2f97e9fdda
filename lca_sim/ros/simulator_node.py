"""The simulator node: `ros2 run lca_hil simulator` (console script `lca-simulator`).

A thin shell around `CommandedPlant`: parameters in, commands in, states out. See
`lca_control.contract` for the topics and `lca_sim.config.simulator_params` for the parameters:

    lca-simulator --ros-args --params-file config/ros/simulator.yaml

Timing modes:

* realtime: a wall-clock timer at `publish_rate_hz`; each tick runs as many fixed model steps as
  wall time has passed (at most four periods' worth) and publishes. Stamps are the simulated
  time, which starts at the wall time of start-up.

  After a stall (a CPU hog, SIGSTOP, a long garbage collection) the backlog beyond those four
  periods is skipped, not simulated: simulated time stays continuous (no jump in the stamps or in
  the model's dt), so it lags the wall clock from then on by the time skipped. /diagnostics
  shows it: `skipped_s` (the total, also as `overrun_steps`), `stamp_lag_s` (wall time minus
  simulated time since start), a `realtime_factor` measured over the last diagnostics period
  (simulated over wall time, so a stall reads well below 1 for that period), and WARN "stalled:
  simulated time fell X s behind the wall clock (skipped)" for a period in which time was skipped.
* lockstep: every accepted command advances exactly `control_period_s` of simulated time, then
  the state is published with /clock. Simulated time starts at 0. The first state goes out once
  `lockstep_subscribers` subscribers of joint_states have matched; if no command comes for
  `lockstep_resend_s`, the last state is sent again (a controller ignores stamps it has seen).

Faults of the plant itself, on /diagnostics every period:

* per axis, WARN "back-driving: <joint> moving at X rad/s with no command" while an axis moves
  (its motor faster than the state machine's V_eps) with a zero, timed-out or disabled command:
  a reversible chain (`irreversible_stop: false`) under load; WARN "end stop hit at X rad/s"
  while an axis rests at an end stop it arrived at with speed, X the joint speed of the last
  published state before the contact (m/s for the lift); and WARN "<joint> pushing into its
  lower (upper) end stop" while its motor pushes into one (the drive state `stop_end_stop`).
  An axis that rests on a stop it never moved into (the lift parked at 0 m, its lower stop, at
  start or after ~/reset) is OK: "resting on its lower end stop".
* the controller peer: WARN while commands that came have stopped (below); before the first
  command (and in lockstep before the subscribers match) the simulator is waiting, not
  faulty: OK "waiting for the first command: ...".
* ERROR "another node publishes joint_states: /other_node" while another node (or a second node
  of the same name) publishes one of the plant's state topics: two simulators, or a simulator
  and a bridge, on one ROS domain. Checked in the ROS graph every diagnostics period.

The end of a lockstep run: with `lockstep_end_s` > 0 the simulator ends the run itself at that
simulated time. The command that reaches it advances only up to it (a shorter last period if
the end is not a whole number of control periods), so the last state published is stamped
exactly `lockstep_end_s`; after it no state, /clock or re-send goes out and commands are
ignored (counted as `commands_after_end`). The simulator says so once in its log, publishes
/diagnostics at once, and from then on its `lca_hil/simulator` status (`SIMULATOR_STATUS`) has
the message "ended at <t> s" and the value `ended` (`ENDED_KEY`) = "True" in every
diagnostics period, so an orchestrator that subscribes late still sees it. The process keeps
running (parameters and services stay available) until it is stopped; raising
`lockstep_end_s` live resumes the run, and 0 means no end.

Simulation control (std_srvs/Trigger services; docs/simulation-control.md has the whole story):
`~/pause` stops simulated time, `~/resume` continues it, `~/step` (only while paused) advances
`step_periods` control periods (`control_period_s` each), `~/reset` puts the plant back to
`initial_position` (in lockstep also simulated time back to 0). In realtime mode a pause holds
the plant and the stamps exactly, a resume does not catch up the paused wall time (it is counted
as `paused_s`, never as a stall), and `realtime_factor` sets how fast simulated time runs against
the wall clock. In lockstep mode a paused simulator takes commands but runs no period for them:
the latest one waits (`command_pending`) for `~/resume` or `~/step`, which lets that one and
then the next N - 1 commands through, one period each.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger

from lca_control import contract as ri
from lca_control.contract import PlantSnapshot
from lca_control.parameters import ParameterError
from lca_control.pi import PIParams
from lca_sim.config.loader import load_robot
from lca_sim.config.simulator_params import (
    ENDED_KEY,
    SIMULATOR_PARAMETERS,
    SIMULATOR_STATUS,
    SimulatorNodeParams,
    validate_simulator_params,
)
from lca_sim.model.commanded_plant import CommandedPlant
from lca_sim.model.faults import LINK, FaultInjector, StateLink
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator
from lca_sim.ros.fault_params import FaultParameters, is_fault_parameter
from lca_sim.ros.joint_command import JointCommandAdapter, effort_scales
from lca_sim.ros.node_util import (
    LiveParameters,
    declare_table,
    run_node,
    set_enabled_by_service,
    status,
)
from lca_sim.ros.plant_contract import PlantPublisher, qos_profile, worst_first

MAX_CATCH_UP_PERIODS = 4
# Time skipped within one diagnostics period above which it is reported as a stall (WARN):
# five control periods. A few ms skipped on a loaded host is counted in skipped_s only.
STALL_WARN_S = 0.02
_ROW = {name: row for row, name in enumerate(SIGNAL_NAMES)}
# The plant's state topics: a second publisher of any of them on the domain is an ERROR.
_END_STOP = "stop_end_stop"


class SimulatorNode(Node):
    """Publishes the simulated robot's states and takes voltage or current commands."""

    def __init__(self, node_name: str = "simulator", **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self._live = LiveParameters(
            self,
            SIMULATOR_PARAMETERS,
            declare_table(self, SIMULATOR_PARAMETERS),
            validate_simulator_params,
            self._apply_params,
            owned_elsewhere=is_fault_parameter,
        )
        p = self.params
        robot = load_robot(p.robot)
        self.sim = Simulator(robot, dt_s=p.dt_s, rigid_body_update_steps=p.rigid_body_update_steps)
        # Injected faults (docs/faults.md): parameters faults.<joint>.<kind>, a schedule.
        self.faults = FaultInjector(self.sim, period_s=p.control_period_s)
        self._fault_params = FaultParameters(
            self, self.faults, lockstep=p.timing_mode == "lockstep"
        )
        self._link = StateLink(self.faults)
        self._measured = tuple(np.zeros(self.sim.n_axes) for _ in range(3))
        self.plant = CommandedPlant(
            sim=self.sim,
            joints=p.joints,
            interface=p.command_interface,
            current_pi=PIParams(p.current_kp_v_per_a, p.current_ti_s, -1.0, 1.0),
            max_abs_command=(
                p.max_command_voltage_v
                if p.command_interface == "voltage"
                else p.max_command_current_a
            ),
            enabled=p.enabled,
            faults=self.faults,
        )
        self._reset_pose()
        self._lockstep = p.timing_mode == "lockstep"
        self._time_base_s = 0.0 if self._lockstep else time.time()
        self._started = not self._lockstep
        self._last_command_wall = time.monotonic()
        self._commanded = False  # a command came since start (before it: waiting, no loss)
        self._last_publish_wall = time.monotonic()
        self._wall_start = time.monotonic()  # moved on by the time skipped after a stall
        self._wall_clock_started = self._lockstep  # realtime: at the first tick
        self._wall_origin = self._wall_start
        self._window_wall = self._wall_start  # the last diagnostics period: wall, steps, skipped
        self._window_steps = 0
        self._window_overrun = 0
        self._steps_done = 0
        self._overrun_steps = 0
        self._published = 0
        self._wrong_interface = 0
        self._after_end = 0
        self._end_reported = False
        self._commands_lost = False  # the controller peer, as /diagnostics reports it
        self._paused = False
        self._pending = False  # lockstep, paused: a command came, its period has not run
        self._step_budget = 0  # lockstep, paused: commands ~/step still lets through
        self._pause_began = 0.0  # monotonic, s
        self._paused_s = 0.0  # realtime: wall time spent paused (ended pauses), s
        self._window_paused_s = 0.0
        self._manual_steps = 0  # realtime: model steps taken by ~/step (not wall-paced)
        self._window_manual = 0
        self._command_losses = 0
        self._gear_ratio = np.array([a.gear_ratio for a in self.sim.robot.axes])
        self._irreversible = robot.state_machine.irreversible_stop
        self._velocity_eps_rad_s = robot.state_machine.velocity_eps_rad_s  # V_eps, motor side
        self._end_stop_code = self.sim.state_names.index(_END_STOP)
        self._position_min = np.array([low for low, _ in self.sim.position_limits])
        self._position_max = np.array([high for _, high in self.sim.position_limits])
        n_axes = len(self.sim.axis_names)
        self._moving_speed = np.zeros(n_axes)  # |joint velocity| when last published moving
        self._contact_speed = np.zeros(n_axes)  # that speed when the end stop was reached
        self._at_end_stop = np.zeros(n_axes, dtype=bool)
        self._plant = PlantPublisher(
            self, self.sim.axis_names, clock=self._lockstep, joint_state_topic=p.joint_state_topic
        )
        self._bind_snapshot_rows()
        command_qos = qos_profile(ri.COMMAND_QOS)
        active, other = (
            (ri.VOLTAGE_COMMANDS, ri.CURRENT_COMMANDS)
            if p.command_interface == "voltage"
            else (ri.CURRENT_COMMANDS, ri.VOLTAGE_COMMANDS)
        )
        self.create_subscription(Float64MultiArray, active, self._on_command, command_qos)
        self.create_subscription(Float64MultiArray, other, self._on_wrong_interface, command_qos)
        # ros2_control's topic-based interface: A per joint, or joint torque / (k_t N).
        self._joint_index = [self.sim.axis_names.index(j) for j in p.joints]
        self._joint_commands = JointCommandAdapter(
            p.joints,
            effort_scales(robot, p.joints, p.joint_command_effort),
            takes_effort=p.command_interface != "voltage",
            velocity_refused=lambda j: (
                f"velocity commands for {j}: the simulator has no velocity loop (command "
                "effort, or use the CAN bridge with the axis in csv mode)"
            ),
            effort_refused=lambda _: (
                "effort refused: the simulator takes voltages (command_interface)"
            ),
            topic=p.joint_command_topic,
        )
        if p.joint_command_topic:
            self.create_subscription(
                JointState, p.joint_command_topic, self._on_joint_command, command_qos
            )
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/pause", self._on_pause)
        self.create_service(Trigger, "~/resume", self._on_resume)
        self.create_service(Trigger, "~/step", self._on_step)
        self.create_service(SetBool, "~/enable", self._on_enable)

        if self._lockstep:
            self._kick_timer = self.create_timer(0.05, self._lockstep_kick)
        else:
            self._tick_timer = self.create_timer(1.0 / p.publish_rate_hz, self._realtime_tick)
        self._diag_timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        self.get_logger().info(
            f"robot {robot.name}, {p.timing_mode}, {p.command_interface} commands on "
            f"{active} for {list(p.joints)}, dt {p.dt_s:g} s"
        )

    @property
    def params(self) -> SimulatorNodeParams:
        """The parameters in force (a live set replaces them as a whole)."""
        return self._live.params

    @property
    def joint_command_counts(self) -> dict[str, int]:
        """JointState commands accepted and refused, and unknown joint names in them."""
        return self._joint_commands.counts

    # --- time ----------------------------------------------------------------------------

    @property
    def sim_time_s(self) -> float:
        """Simulated time of the published states (the /clock value in lockstep)."""
        return self._time_base_s + self._steps_done * self.params.dt_s

    @property
    def steps(self) -> int:
        """Model steps (of `dt_s`) since start-up, or in lockstep since the last `~/reset`."""
        return self._steps_done

    @property
    def paused(self) -> bool:
        """Simulated time is stopped (`~/pause`) until `~/resume`; `~/step` moves it on."""
        return self._paused

    @property
    def lockstep_started(self) -> bool:
        """Lockstep: the first state has gone out (its subscribers matched); realtime: True."""
        return self._started

    @property
    def command_pending(self) -> bool:
        """Lockstep, paused: a command has come whose period waits for `~/step` or `~/resume`."""
        return self._pending

    @property
    def ended(self) -> bool:
        """A lockstep run has reached `lockstep_end_s`: no further state goes out."""
        end = self.params.lockstep_end_steps
        return self._lockstep and end is not None and self._steps_done >= end

    def _reset_pose(self, keep_command: bool = False) -> None:
        """The plant at `initial_position`, at rest; its command zeroed unless `keep_command`."""
        position = dict(zip(self.sim.axis_names, self.params.initial_position, strict=True))
        try:
            self.sim.reset(position=position)
        except ValueError as exc:
            raise ParameterError(
                "initial_position",
                f"a pose within the end stops ({exc})",
                self.params.initial_position,
            ) from exc
        if not keep_command:
            self.plant.hold_zero()
        self.faults.restart()

    # --- commands ------------------------------------------------------------------------

    def _on_command(self, msg: Float64MultiArray) -> None:
        self._take_command(list(msg.data))

    def _on_joint_command(self, msg: JointState) -> None:
        """A JointState command (docs/ros2_control.md): effort per joint, by name.

        Effort is this node's command (A, or joint torque per `joint_command_effort`) on the
        joints named with a finite entry; every other joint keeps its command. The simulator
        has no velocity loop, so a non-zero velocity entry is refused (counted, warned); a
        zero one is what the interface sends for a velocity interface no controller claims.
        In voltage mode effort has no meaning here and the message is refused. In lockstep
        the message is the period's command either way, as a refused array is.
        """
        adapter = self._joint_commands
        cmd = adapter.read(msg.name, msg.velocity, msg.effort)
        values = None
        if cmd.accepted:
            values = adapter.fill(self.plant.target[self._joint_index].tolist(), cmd.effort)
        if cmd.problems:
            self.get_logger().warning(adapter.warning(cmd.problems), throttle_duration_sec=1.0)
        self._take_command(values)

    def _take_command(self, values: list[float] | None) -> None:
        """One command array (joints order): in force, and in lockstep the period's command.

        None: a refused JointState command, which in lockstep still runs the period (in
        realtime it is no command: the timeout runs on).
        """
        if values is None and not self._lockstep:
            return
        reason = None if values is None else self.plant.command(values)
        if reason is not None:
            self.get_logger().warning(
                f"command rejected ({self.plant.counters.rejected} so far): {reason}",
                throttle_duration_sec=1.0,
            )
            if not self._lockstep:
                return
            # In lockstep the loop must go on: the last good command stays in force.
        self._last_command_wall = time.monotonic()
        self._commanded = True
        if self._lockstep and self._started:
            if self._paused:
                self._paused_command()
                return
            self._lockstep_step()

    def _paused_command(self) -> None:
        """Lockstep, paused: a period for a command `~/step` lets through, else it waits."""
        if self._step_budget > 0:
            self._step_budget -= 1
            self._lockstep_step()
        else:
            self._pending = True

    def _lockstep_step(self) -> None:
        """Advance one control period (or up to the end) and publish; nothing once ended."""
        if self.ended:
            self._after_end += 1
            self._report_end()  # an end set live below the time reached shows here
            return
        steps = self.params.substeps_per_period
        end = self.params.lockstep_end_steps
        if end is not None:
            steps = min(steps, end - self._steps_done)
        self._switch_faults()
        self.plant.advance(steps)
        self._steps_done += steps
        self._publish_state()
        if self.ended:
            self._report_end()

    def _report_end(self) -> None:
        """Say once that the run has ended: the log, and /diagnostics at once."""
        if self._end_reported:
            return
        self._end_reported = True
        self.get_logger().info(
            f"lockstep run ended at {self.sim_time_s:.6f} s of simulated time "
            f"(lockstep_end_s): {self._published} states published, no more will follow"
        )
        self._publish_diagnostics()

    def _on_wrong_interface(self, msg: Float64MultiArray) -> None:
        self._wrong_interface += 1
        self.get_logger().warning(
            f"ignoring commands on the inactive interface ({self._wrong_interface} so far); "
            f"command_interface is {self.params.command_interface}",
            throttle_duration_sec=5.0,
        )

    # --- stepping ------------------------------------------------------------------------

    def _start_wall_clock(self) -> None:
        """Realtime: simulated time starts now, at the first tick of the running node.

        Not at construction: between it and the first tick the process settles its heap (a
        full collection, 0.1-0.6 s on a 2-core host still starting its peers) and the executor
        comes up, and that time counted as a stall of the first diagnostics period (a WARN
        on every healthy start).
        """
        now = time.monotonic()
        self._time_base_s = time.time() - self._steps_done * self.params.dt_s
        self._wall_start = self._wall_origin = self._window_wall = now
        self._last_command_wall = self._last_publish_wall = now
        self._wall_clock_started = True

    def _realtime_tick(self) -> None:
        if not self._wall_clock_started:
            self._start_wall_clock()
        if self._paused:
            return  # simulated time stands; the plant holds its state exactly
        p = self.params
        silent_s = time.monotonic() - self._last_command_wall
        if silent_s > p.command_timeout_s and np.any(self.plant.target != 0.0):
            self.plant.hold_zero(timed_out=True)
            self.get_logger().warning(
                f"no command for {p.command_timeout_s:g} s: 0 V, {self._hold_words}",
                throttle_duration_sec=5.0,
            )
        due = self._steps_due()
        if due > 0:
            self._switch_faults()
            self.plant.advance(due)
            self._steps_done += due
        self._publish_state()

    def _steps_due(self) -> int:
        """Realtime: the model steps due now, at most the catch-up cap; the rest is skipped.

        A backlog beyond MAX_CATCH_UP_PERIODS (a stall) is dropped: simulated time slips and
        the dropped steps are counted (`overrun_steps`). Also called by the diagnostics before
        they report, so a stall shows in the period it happened, even when the diagnostics
        timer runs before the next tick after it.
        """
        if not self._wall_clock_started:
            return 0  # simulated time starts at the first tick
        p = self.params
        factor = p.realtime_factor
        due = round((time.monotonic() - self._wall_start) * factor / p.dt_s) - self._steps_done
        cap = MAX_CATCH_UP_PERIODS * max(1, round(factor / (p.publish_rate_hz * p.dt_s)))
        if due > cap:
            self._overrun_steps += due - cap
            self._wall_start += (due - cap) * p.dt_s / factor  # drop the backlog
            due = cap
        return due

    @property
    def _hold_words(self) -> str:
        """What 0 V does to a loaded axis of this robot (its stopped state, Fig. 7)."""
        if self._irreversible:
            return "the gear holds the load"
        return "the gear is reversible: the load may drive the axes"

    def _lockstep_kick(self) -> None:
        p = self.params
        if self.ended:
            return
        if not self._started:
            if self._plant.joint_pub.get_subscription_count() >= p.lockstep_subscribers:
                self._started = True
                self._publish_state()
            return
        if time.monotonic() - max(self._last_command_wall, self._last_publish_wall) > (
            p.lockstep_resend_s
        ):
            self._publish_state()

    # --- publishing ----------------------------------------------------------------------

    def _bind_snapshot_rows(self) -> None:
        """The simulator's rows a snapshot is made of, taken once.

        `Simulator` updates its arrays in place, so these views stay current and a publish
        only fills the two products below and the snapshot itself: no per-axis objects.
        """
        sim = self.sim
        state = sim.state_array
        modes = sim.mode_array
        signals = sim.signal_array
        self._q = state[0]
        self._qdot = state[1]
        self._current = state[2]
        self._motion = modes[0]
        self._drive = modes[1]
        self._signal_rows = {name: signals[row] for row, name in enumerate(SIGNAL_NAMES)}
        self._effort = np.zeros(len(sim.axis_names))  # N * tau_m, joint side
        self._motor_position = np.zeros(len(sim.axis_names))  # N * q

    def _snapshot(self) -> PlantSnapshot:
        """The plant now, as the contract's snapshot (views of the live state; see above)."""
        rows = self._signal_rows
        np.multiply(rows["motor_torque_nm"], self._gear_ratio, out=self._effort)
        np.multiply(self._q, self._gear_ratio, out=self._motor_position)
        return PlantSnapshot(
            stamp_s=self.sim_time_s,
            joints=self.sim.axis_names,
            position=self._q,
            velocity=self._qdot,
            effort=self._effort,
            motor_position_rad=self._motor_position,
            motor_velocity_rad_s=rows["motor_velocity_rad_s"],
            current_a=self._current,
            motion_state=self._motion,
            drive_state=self._drive,
            state_names=self.sim.state_names,
            eta_m=rows["eta_m"],
            eta_l=rows["eta_l"],
            motor_torque_nm=rows["motor_torque_nm"],
            load_torque_nm=rows["load_torque_nm"],
            friction_torque_nm=rows["friction_torque_nm"],
            voltage_v=rows["voltage_v"],
        )

    def _switch_faults(self) -> None:
        """The scheduled faults for the time the next step starts at (logged when they switch)."""
        for change in self.faults.at(self.sim_time_s):
            self.get_logger().warning(f"fault schedule at {self.sim_time_s:.4f} s: {change}")

    def _faulted(self, snap: PlantSnapshot) -> list[PlantSnapshot]:
        """The snapshot as the faulty sensors report it, routed through the faulty link."""
        q, v, i = self._measured
        self.faults.measure(snap.position, snap.velocity, snap.current_a, (q, v, i))
        measured = dataclasses.replace(
            snap,
            position=q.copy(),
            velocity=v.copy(),
            current_a=i.copy(),
            motor_position_rad=q * self._gear_ratio,
            faults=tuple(self.faults.describe(j) for j in snap.joints),
            motor_velocity_rad_s=snap.motor_velocity_rad_s.copy(),
            effort=snap.effort.copy(),
            motion_state=snap.motion_state.copy(),
            drive_state=snap.drive_state.copy(),
            eta_m=snap.eta_m.copy(),
            eta_l=snap.eta_l.copy(),
            motor_torque_nm=snap.motor_torque_nm.copy(),
            load_torque_nm=snap.load_torque_nm.copy(),
            friction_torque_nm=snap.friction_torque_nm.copy(),
            voltage_v=snap.voltage_v.copy(),
        )
        return self._link.route(snap.stamp_s, measured)

    def _publish_state(self) -> None:
        """Publish one instant through the contract's builder (joint_states first).

        joint_states is what a current-commanding controller waits for: its next command is
        being computed while motor_states, /clock and the drive-chain states go out. With
        faults injected, what goes out is what the faulty sensors and link deliver.
        """
        snap = self._snapshot()
        if self.faults.any_active:
            for delivered in self._faulted(snap):
                self._plant.publish(delivered)
        else:
            self._plant.publish(snap)
        self._published += 1
        self._track_end_stops()
        self._last_publish_wall = time.monotonic()

    def _track_end_stops(self) -> None:
        """Keep each axis's last moving speed, and take it as the contact speed at an end stop.

        An axis is at its end stop when the model clamped it there: a load that drove it in
        leaves the drive state at `stop_hold` (`stop_end_stop` only while the motor pushes).
        """
        at_stop = self._at_limit()
        contact = at_stop & ~self._at_end_stop
        self._contact_speed[contact] = self._moving_speed[contact]
        self._at_end_stop[:] = at_stop
        moving = ~at_stop & (
            np.abs(self._signal_rows["motor_velocity_rad_s"]) > self._velocity_eps_rad_s
        )
        self._moving_speed[moving] = np.abs(self._qdot[moving])

    def _at_limit(self) -> np.ndarray:
        """Per axis: at an end stop (clamped to a position limit, or the motor pushing into it)."""
        return (
            (self._drive == self._end_stop_code)
            | (self._q <= self._position_min)
            | (self._q >= self._position_max)
        )

    def _command_health(self, command_age_s: float) -> tuple[bytes, str] | None:
        """The controller peer: a WARN while commands that came are missing, else OK or None.

        Realtime: silence beyond command_timeout_s (the plant is at 0 V then). Lockstep: no
        command for lockstep_resend_s (simulated time stands still). Before the first command,
        and in lockstep while the start waits for its subscribers, nothing is lost yet: OK,
        saying what the simulator waits for. A loss is logged once when it begins and once
        when it ends.
        """
        p = self.params
        if self._lockstep and not self._started:
            matched = self._plant.joint_pub.get_subscription_count()
            return DiagnosticStatus.OK, (
                f"waiting for {p.lockstep_subscribers} joint_states subscribers "
                f"({matched} so far): simulated time has not started"
            )
        limit_s = p.lockstep_resend_s if self._lockstep else p.command_timeout_s
        if command_age_s <= limit_s:
            if self._commands_lost:
                self._commands_lost = False
                self.get_logger().info(f"commands again; simulated time {self.sim_time_s:.3f} s")
            return None
        if self._lockstep:
            what = "simulated time paused, the last state is re-sent"
        else:
            what = "holding (0 V)" if self._irreversible else "0 V, reversible gear (not held)"
        if not self._commanded:
            return DiagnosticStatus.OK, f"waiting for the first command: {what}"
        message = f"no command for {command_age_s:.1f} s: {what}"
        if not self._commands_lost:
            self._commands_lost = True
            self._command_losses += 1
            self.get_logger().warning(f"{message}; is the controller running?")
        return DiagnosticStatus.WARN, message

    def _timing_health(self, values: dict[str, object]) -> tuple[bytes, str] | None:
        """Realtime: the stamp lag and the time skipped; a WARN for a period with a stall.

        The realtime factor is that of the last diagnostics period (simulated over wall time),
        so a stall shows in the period it happened instead of vanishing in a run's average.
        """
        if self._lockstep:
            return None
        if not self._paused:
            self._steps_due()  # a stall not yet seen by a tick is counted in this period
        dt_s = self.params.dt_s
        now = time.monotonic()
        paused_s = self._paused_s + (now - self._pause_began if self._paused else 0.0)
        # Wall time paused and steps taken by ~/step are neither running nor a stall.
        wall_s = now - self._window_wall - (paused_s - self._window_paused_s)
        paced = (self._steps_done - self._window_steps) - (self._manual_steps - self._window_manual)
        skipped = self._overrun_steps - self._window_overrun
        values["stamp_lag_s"] = (now - self._wall_origin) - self._steps_done * dt_s
        values["skipped_s"] = self._overrun_steps * dt_s
        values["paused_s"] = paused_s
        if wall_s > 1e-3:
            values["realtime_factor"] = paced * dt_s / wall_s
        self._window_wall, self._window_steps = now, self._steps_done
        self._window_overrun = self._overrun_steps
        self._window_paused_s, self._window_manual = paused_s, self._manual_steps
        if skipped * dt_s <= STALL_WARN_S:
            return None  # a scheduling hiccup of a few ms: counted (skipped_s), not a stall
        return DiagnosticStatus.WARN, (
            f"stalled: simulated time fell {skipped * dt_s:.3f} s behind the wall clock (skipped)"
        )

    def _publish_diagnostics(self) -> None:
        p = self.params
        level = DiagnosticStatus.OK
        message = "running" if self.plant.enabled else "disabled"
        if self._command_losses:
            message = "commands again" if self.plant.enabled else "disabled; commands again"
        counters = self.plant.counters
        if counters.rejected or self._wrong_interface or self.joint_command_counts["refused"]:
            level, message = DiagnosticStatus.WARN, "commands rejected"
        command_age_s = time.monotonic() - self._last_command_wall
        ended = self.ended  # no commands are wanted any more: not a peer problem
        # Paused, no command is due: silence then is no peer problem either.
        peer = None if ended or self._paused else self._command_health(command_age_s)
        if peer is not None and (peer[0] != DiagnosticStatus.OK or level == DiagnosticStatus.OK):
            level, message = peer
        if self._paused:
            message = f"paused at {self.sim_time_s:g} s"
        if ended:
            message = f"ended at {self.sim_time_s:g} s"
        values: dict[str, object] = {
            "timing_mode": p.timing_mode,
            "command_interface": p.command_interface,
            "enabled": self.plant.enabled,
            "sim_time_s": self.sim_time_s,
            "steps": self._steps_done,
            "states_published": self._published,
            "overrun_steps": self._overrun_steps,
            "command_age_s": command_age_s,
            "commands_wrong_interface": self._wrong_interface,
            "joint_commands_accepted": self.joint_command_counts["accepted"],
            "joint_commands_refused": self.joint_command_counts["refused"],
            "joint_command_unknown_names": self.joint_command_counts["unknown_names"],
            "command_losses": self._command_losses,
            "lockstep_end_s": p.lockstep_end_s,
            ENDED_KEY: ended,
            "commands_after_end": self._after_end,
            "paused": self._paused,
            "command_pending": self._pending,
            "step_periods_left": self._step_budget,
            "realtime_factor_set": p.realtime_factor,
            "link_faults": self.faults.describe(LINK),
            "states_dropped": self._link.dropped,
            "states_stale": self._link.stale_sent,
            **counters.as_dict(),
        }
        if self.faults.active(LINK):
            found_link = (
                DiagnosticStatus.WARN,
                f"injected link faults: {self.faults.describe(LINK)}",
            )
        else:
            found_link = None
        found = [(level, message)]
        for health in (
            self._timing_health(values),
            self._plant.graph_health(values),
            found_link,
        ):
            if health is not None:
                found.append(health)
        level, message = worst_first(found)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status.append(status(SIMULATOR_STATUS, level, message, values))
        for a, name in enumerate(self.sim.axis_names):
            array.status.append(self._axis_status(a, name))
        self._plant.publish_diagnostics(array)

    def _axis_status(self, a: int, name: str) -> DiagnosticStatus:
        """One axis: its drive state, or WARN at an end stop or back-driven without command.

        At an end stop: WARN while the motor pushes into it or after an arrival with speed (a
        hit); OK while it rests there having never moved into it (a pose at start or reset).
        """
        signals = self.sim.signal_array
        drive_state = self.sim.state_names[int(self.sim.mode_array[1, a])]
        velocity = float(self.sim.state_array[1, a])
        unit = "m/s" if self.sim.prismatic[a] else "rad/s"
        uncommanded = not self.plant.enabled or self.plant.target[a] == 0.0
        moving = abs(float(signals[_ROW["motor_velocity_rad_s"], a])) > self._velocity_eps_rad_s
        level, message, fault = DiagnosticStatus.OK, drive_state, "none"
        injected = self.faults.active(name) if self.faults.any_active else []
        if injected:
            tripped = "i2t_trip" in injected
            level = DiagnosticStatus.ERROR if tripped else DiagnosticStatus.WARN
            fault = f"injected: {self.faults.describe(name)}"
            message = fault + (" (I2t trip: torque off, latched)" if tripped else "")
        elif self._at_limit()[a]:
            side = "upper" if self._q[a] >= self._position_max[a] else "lower"
            hit = f"end stop hit at {self._contact_speed[a]:.3g} {unit}"
            if self._drive[a] == self._end_stop_code:
                level, fault = DiagnosticStatus.WARN, "pushing into end stop"
                message = f"{name} pushing into its {side} end stop"
                if self._contact_speed[a] > 0.0:
                    message += f" ({hit})"
            elif self._contact_speed[a] > 0.0:
                level, fault = DiagnosticStatus.WARN, "at end stop"
                message = hit
            else:  # parked there, never driven into it: no fault
                message = f"{drive_state}: resting on its {side} end stop"
        elif moving and uncommanded:
            level, fault = DiagnosticStatus.WARN, "back-driving"
            message = f"back-driving: {name} moving at {abs(velocity):.3g} {unit} with no command"
        return status(
            f"lca_hil/simulator/{name}",
            level,
            message,
            {
                "drive_state": drive_state,
                "position": float(self.sim.state_array[0, a]),
                "velocity": velocity,
                "command": float(self.plant.target[a]),
                "voltage_v": float(signals[_ROW["voltage_v"], a]),
                "current_a": float(self.sim.state_array[2, a]),
                "end_stop_contact_speed": float(self._contact_speed[a]),
                "fault": fault,
                "faults": self.faults.describe(name),
            },
        )

    # --- services and parameters ---------------------------------------------------------

    def _on_reset(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.reset()
        return response

    def _on_pause(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.pause()
        return response

    def _on_resume(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.resume()
        return response

    def _on_step(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.step()
        return response

    def reset(self) -> tuple[bool, str]:
        """`~/reset`: the plant at `initial_position`, at rest, with a zero command.

        Lockstep: simulated time back to 0 as well (an ended run starts again), and the state
        at 0 is published, so a controller restarts its loops and profile (its time went back).
        A reset before the first period has run keeps the command already taken (the
        controller will not answer the same stamp twice). Realtime: simulated time goes on
        (the stamps follow the wall clock). Returns the reply's success and message.
        """
        pose = list(self.params.initial_position)
        # A pose at a stop after the reset is parked there, not a hit.
        self._moving_speed[:] = 0.0
        self._contact_speed[:] = 0.0
        self._at_end_stop[:] = False
        if not self._lockstep:
            self._reset_pose()
            return True, f"reset to {pose} at {self.sim_time_s:.4f} s (time goes on)"
        rewind = self._steps_done > 0
        self._reset_pose(keep_command=not rewind)
        if rewind:
            self._steps_done = 0
            self._pending = False
            self._step_budget = 0
        self._end_reported = False
        if self._started:
            self._publish_state()
        return True, f"reset to {pose}, simulated time 0 s" + (
            ""
            if self._paused
            else ("; running: a command in flight may take the first period (~/pause first)")
        )

    def pause(self) -> tuple[bool, str]:
        """`~/pause`: simulated time stops (see the module docstring). Success and message."""
        if self._paused:
            return True, f"already paused at {self.sim_time_s:.6f} s"
        self._paused = True
        self._pause_began = time.monotonic()
        how = "commands wait for ~/step or ~/resume" if self._lockstep else "the plant holds"
        return True, f"paused at {self.sim_time_s:.6f} s: {how}"

    def resume(self) -> tuple[bool, str]:
        """`~/resume`: simulated time runs again, without catching up the pause."""
        if not self._paused:
            return True, f"already running at {self.sim_time_s:.6f} s"
        self._paused = False
        self._step_budget = 0
        if self._lockstep:
            if self._pending:
                self._pending = False
                self._lockstep_step()
        else:
            paused_s = time.monotonic() - self._pause_began
            self._paused_s += paused_s
            self._wall_start += paused_s  # no catch-up: the pause is not a backlog
            self._last_command_wall += paused_s  # nor is it command silence
        return True, f"resumed at {self.sim_time_s:.6f} s"

    def step(self) -> tuple[bool, str]:
        """`~/step`, while paused: `step_periods` control periods.

        Realtime: all at once under the command in force, each state published. Lockstep: the
        command waiting (if any) and then the next ones, one period each, up to N; the call
        returns at once, `steps` shows the progress. Success false with the reason when the
        simulator runs, has not started, or has ended.
        """
        p = self.params
        n = p.step_periods
        if not self._paused:
            return False, "running: ~/pause first, then ~/step"
        if self.ended:
            return False, f"the lockstep run ended at {self.sim_time_s:g} s (lockstep_end_s)"
        if self._lockstep and not self._started:
            return False, "lockstep has not started: waiting for joint_states subscribers"
        period_s = n * p.control_period_s
        if self._lockstep:
            self._step_budget = n
            taken = 0
            if self._pending:
                self._pending = False
                self._step_budget -= 1
                taken = 1
                self._lockstep_step()
            return True, (
                f"stepping {n} control periods ({period_s:g} s): {taken} run now, the next "
                f"{self._step_budget} commands run one each"
            )
        substeps = p.substeps_per_period
        for _ in range(n):
            self.plant.advance(substeps)
            self._steps_done += substeps
            self._manual_steps += substeps
            self._publish_state()
        self._wall_start -= n * substeps * p.dt_s / p.realtime_factor  # resume goes on from here
        return True, f"stepped {n} control periods ({period_s:g} s) to {self.sim_time_s:.6f} s"

    def _on_enable(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        """The `enabled` parameter by service (`set_enabled_by_service`)."""
        response.success, response.message = set_enabled_by_service(
            self, bool(request.data), "disabled: 0 V on every axis"
        )
        return response

    def _apply_params(
        self, old: SimulatorNodeParams, new: SimulatorNodeParams, _changed: frozenset[str]
    ) -> None:
        """A live set takes effect from the next model step (read-only ones never get here).

        Raises:
            ParameterError: a value the running model refuses (an initial position outside
                its end stops); nothing has changed then.
        """
        for a, ((low, high), q) in enumerate(
            zip(self.sim.position_limits, new.initial_position, strict=True)
        ):
            if not low <= q <= high:
                raise ParameterError(
                    "initial_position",
                    f"{self.sim.axis_names[a]} within its end stops [{low:g}, {high:g}]",
                    list(new.initial_position),
                )
        if (new.current_kp_v_per_a, new.current_ti_s) != (old.current_kp_v_per_a, old.current_ti_s):
            self.plant.set_current_gains(new.current_kp_v_per_a, new.current_ti_s)
        self.plant.max_abs_command = (
            new.max_command_voltage_v
            if new.command_interface == "voltage"
            else new.max_command_current_a
        )
        if new.enabled != old.enabled:
            self.plant.set_enabled(new.enabled)
        if new.realtime_factor != old.realtime_factor and not self._lockstep:
            # Simulated time goes on from where it is, at the new pace.
            now = self._pause_began if self._paused else time.monotonic()
            self._wall_start = now - (now - self._wall_start) * (
                old.realtime_factor / new.realtime_factor
            )
        if new.publish_rate_hz != old.publish_rate_hz and not self._lockstep:
            self.destroy_timer(self._tick_timer)
            self._tick_timer = self.create_timer(1.0 / new.publish_rate_hz, self._realtime_tick)
        if new.lockstep_end_s != old.lockstep_end_s:
            self._end_reported = False  # a later end is reported again when it is reached
        if new.diagnostics_period_s != old.diagnostics_period_s:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(
                new.diagnostics_period_s, self._publish_diagnostics
            )


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-simulator` / `ros2 run lca_hil simulator`."""
    return run_node("lca-simulator", SimulatorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
