"""The simulator node: `ros2 run lca_hil simulator` (console script `lca-simulator`).

A thin shell around `CommandedPlant`: parameters in (`lca_sim.config.simulator_params`),
commands in, states out through the plant contract (docs/contract.md).

    lca-simulator --ros-args --params-file config/ros/simulator.yaml

Its parts: `sim_pacing.SimPacing` (realtime pacing or lockstep, pause and step, the end of a
lockstep run), `sim_snapshot.SimSnapshots` (the contract's snapshot, through the injected
sensor and link faults), `sim_axes.AxisWatch` (end stops, back-driving) and
`simulator_diagnostics.SimulatorDiagnostics` (/diagnostics, the controller peer). Services
`~/pause`, `~/resume`, `~/step`, `~/reset` (docs/simulation-control.md) and `~/enable`;
injected faults: docs/faults.md.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from std_srvs.srv import SetBool, Trigger

from lca_control.parameters import ParameterError
from lca_sim.config.loader import load_robot
from lca_sim.config.simulator_params import (
    SIMULATOR_PARAMETERS,
    SimulatorNodeParams,
    plant_config,
    validate_simulator_params,
)
from lca_sim.model.params import RobotParams
from lca_sim.model.plant import build_plant
from lca_sim.ros.fault_params import FaultParameters, is_fault_parameter
from lca_sim.ros.node_util import LiveParameters, declare_table, run_node, set_enabled_by_service
from lca_sim.ros.plant_contract import PlantPublisher
from lca_sim.ros.ros_logging import log_at
from lca_sim.ros.sim_axes import AxisWatch
from lca_sim.ros.sim_commands import SimCommands
from lca_sim.ros.sim_pacing import SimPacing
from lca_sim.ros.sim_snapshot import SimSnapshots
from lca_sim.ros.simulator_diagnostics import SimulatorDiagnostics

# Lockstep: how often the node looks whether to start, or to re-send to a silent controller, s.
LOCKSTEP_TICK_S = 0.05


class SimulatorNode(Node):
    """Publishes the simulated robot's states; takes each joint's command by its drive mode."""

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
        # Injected faults (docs/faults.md): parameters faults.<joint>.<kind>, a schedule.
        plant = build_plant(plant_config(p, robot, fault_period_s=p.control_period_s))
        self.sim, self.plant = plant.sim, plant.commanded
        # Position / velocity joints: the drive's loops in the model (docs/simulator.md).
        self.plant.use_drive_modes(
            p.joint_drive_modes,
            p.drive_loop_params(self.plant.current_limit_a),
            p.drive_loop_period_s,
        )
        assert plant.faults is not None  # fault_period_s given
        self.faults = plant.faults
        self._fault_params = FaultParameters(
            self, self.faults, lockstep=p.timing_mode == "lockstep"
        )
        self._snapshots = SimSnapshots(self.sim, self.faults)
        self._reset_pose()
        self._lockstep = p.timing_mode == "lockstep"
        self.pacing = SimPacing(lambda: self.params, self._lockstep)
        self._published = 0
        self._irreversible = robot.state_machine.irreversible_stop
        self._axes = AxisWatch(self.sim, self.plant, self.faults)
        self._plant = PlantPublisher(
            self, self.sim.axis_names, clock=self._lockstep, joint_state_topic=p.joint_state_topic
        )
        self._diagnostics = SimulatorDiagnostics(
            self,
            lambda: self.params,
            plant=self.plant,
            pacing=self.pacing,
            faults=self.faults,
            link=self._snapshots.link,
            axes=self._axes,
            publisher=self._plant,
            irreversible=self._irreversible,
        )
        active = self._create_interfaces(p, robot)
        modes = f", drive modes {list(p.drive_modes)}" if p.drive_modes else ""
        self.get_logger().info(
            f"robot {robot.name}, {p.timing_mode}, {p.command_interface} commands on "
            f"{active} for {list(p.joints)}{modes}, dt {p.dt_s:g} s"
        )

    def _create_interfaces(self, p: SimulatorNodeParams, robot: RobotParams) -> str:
        """Subscriptions, services and timers; returns the command topic taken."""
        self._commands = SimCommands(
            self, p, robot, self.sim.axis_names, self.plant, self.pacing, self._lockstep_step
        )
        for name, action in (
            ("reset", self.reset),
            ("pause", self.pause),
            ("resume", self.resume),
            ("step", self.step),
        ):
            self.create_service(Trigger, f"~/{name}", _trigger(action))
        self.create_service(SetBool, "~/enable", self._on_enable)
        if self._lockstep:
            self._kick_timer = self.create_timer(LOCKSTEP_TICK_S, self._lockstep_kick)
        else:
            self._tick_timer = self.create_timer(1.0 / p.publish_rate_hz, self._realtime_tick)
        self._diag_timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        return self._commands.topic

    @property
    def params(self) -> SimulatorNodeParams:
        """The parameters in force (a live set replaces them as a whole)."""
        return self._live.params

    @property
    def joint_command_counts(self) -> dict[str, int]:
        """JointState commands accepted and refused, and unknown joint names in them."""
        return self._commands.joint_commands.counts

    # --- time ----------------------------------------------------------------------------

    @property
    def sim_time_s(self) -> float:
        """Simulated time of the published states (the /clock value in lockstep)."""
        return self.pacing.sim_time_s

    @property
    def steps(self) -> int:
        """Model steps (of `dt_s`) since start-up, or in lockstep since the last `~/reset`."""
        return self.pacing.steps

    @property
    def paused(self) -> bool:
        """Simulated time is stopped (`~/pause`) until `~/resume`; `~/step` moves it on."""
        return self.pacing.paused

    @property
    def lockstep_started(self) -> bool:
        """Lockstep: the first state has gone out (its subscribers matched); realtime: True."""
        return self.pacing.started

    @property
    def command_pending(self) -> bool:
        """Lockstep, paused: a command has come whose period waits for `~/step` or `~/resume`."""
        return self.pacing.pending

    @property
    def ended(self) -> bool:
        """A lockstep run has reached `lockstep_end_s`: no further state goes out."""
        return self.pacing.ended

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

    def _lockstep_step(self) -> None:
        """Advance one control period (or up to the end) and publish; nothing once ended."""
        pacing = self.pacing
        if pacing.ended:
            pacing.after_end += 1
            self._report_end()  # an end set live below the time reached shows here
            return
        steps = pacing.period_steps()
        self._switch_faults()
        self.plant.advance(steps)
        pacing.advanced(steps)
        self._publish_state()
        if pacing.ended:
            self._report_end()

    def _report_end(self) -> None:
        """Say once that the run has ended: the log, and /diagnostics at once."""
        if self.pacing.end_reported:
            return
        self.pacing.end_reported = True
        self.get_logger().info(
            f"lockstep run ended at {self.sim_time_s:.6f} s of simulated time "
            f"(lockstep_end_s): {self._published} states published, no more will follow"
        )
        self._publish_diagnostics()

    # --- stepping ------------------------------------------------------------------------

    def _wake(self) -> None:
        """Every timer callback first: a freeze of this process is not the controller's silence.

        `SimPacing.check_freeze` moves the command deadline on by the freeze; the first freeze
        and the first one beyond the deadline are logged (`FreezeWatch.note`), the rest counted
        in /diagnostics.
        """
        p = self.params
        tick_s = LOCKSTEP_TICK_S if self._lockstep else 1.0 / p.publish_rate_hz
        freeze = self.pacing.check_freeze(tick_s)
        if freeze is None:
            return
        deadline_s = p.lockstep_resend_s if self._lockstep else p.command_timeout_s
        note = self.pacing.freezes.note(
            freeze, deadline_s, "the controller's silence does not count it"
        )
        if note is not None:
            log_at(self.get_logger(), *note)

    def _realtime_tick(self) -> None:
        self._wake()
        pacing = self.pacing
        pacing.tick_started()
        if pacing.paused:
            return  # simulated time stands; the plant holds its state exactly
        p = self.params
        silent_s = time.monotonic() - pacing.last_command_wall
        if silent_s > p.command_timeout_s and np.any(self.plant.target != 0.0):
            self.plant.hold_zero(timed_out=True)
            hold = (
                "the gear holds the load"
                if self._irreversible
                else "the gear is reversible: the load may drive the axes"
            )
            self.get_logger().warning(
                f"no command for {p.command_timeout_s:g} s: 0 V, {hold}",
                throttle_duration_sec=5.0,
            )
        due = pacing.steps_due()
        if due > 0:
            self._switch_faults()
            self.plant.advance(due)
            pacing.advanced(due)
        self._publish_state()

    def _lockstep_kick(self) -> None:
        self._wake()
        p = self.params
        pacing = self.pacing
        if pacing.ended:
            return
        if not pacing.started:
            if self._plant.joint_pub.get_subscription_count() >= p.lockstep_subscribers:
                pacing.started = True
                self._publish_state()
            return
        if time.monotonic() - max(pacing.last_command_wall, pacing.last_publish_wall) > (
            p.lockstep_resend_s
        ):
            self._publish_state()

    # --- publishing ----------------------------------------------------------------------

    def _switch_faults(self) -> None:
        """The scheduled faults for the time the next step starts at (logged when they switch)."""
        for change in self.faults.at(self.sim_time_s):
            self.get_logger().warning(f"fault schedule at {self.sim_time_s:.4f} s: {change}")

    def _publish_state(self) -> None:
        """Publish one instant through the contract's builder (joint_states first).

        joint_states is what a current-commanding controller waits for: its next command is
        being computed while motor_states, /clock and the drive-chain states go out. With
        faults injected, what goes out is what the faulty sensors and link deliver.
        """
        snap = self._snapshots.snapshot(self.sim_time_s)
        if self.faults.any_active:
            for delivered in self._snapshots.delivered(snap):
                self._plant.publish(delivered)
        else:
            self._plant.publish(snap)
        self._published += 1
        self._axes.track()
        self.pacing.last_publish_wall = time.monotonic()

    def _publish_diagnostics(self) -> None:
        self._wake()  # may run first after a freeze: the command age it reports is discounted
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        commands = self._commands
        array.status = self._diagnostics.statuses(
            self._published,
            commands.wrong_interface,
            commands.joint_commands.counts,
            commands.unserved(),
        )
        self._plant.publish_diagnostics(array)

    # --- services and parameters ---------------------------------------------------------

    def reset(self) -> tuple[bool, str]:
        """`~/reset`: the plant at `initial_position`, at rest, with a zero command.

        Lockstep: simulated time back to 0 as well (an ended run starts again), and the state
        at 0 is published, so a controller restarts its loops and profile (its time went back).
        A reset before the first period has run keeps the command already taken (the
        controller will not answer the same stamp twice). Realtime: simulated time goes on
        (the stamps follow the wall clock). Returns the reply's success and message.
        """
        pose = list(self.params.initial_position)
        self._axes.forget()
        if not self._lockstep:
            self._reset_pose()
            return True, f"reset to {pose} at {self.sim_time_s:.4f} s (time goes on)"
        rewind = self.pacing.steps > 0
        self._reset_pose(keep_command=not rewind)
        self.pacing.rewind()
        if self.pacing.started:
            self._publish_state()
        return True, f"reset to {pose}, simulated time 0 s" + (
            ""
            if self.pacing.paused
            else ("; running: a command in flight may take the first period (~/pause first)")
        )

    def pause(self) -> tuple[bool, str]:
        """`~/pause`: simulated time stops (docs/simulation-control.md). Success and message."""
        if not self.pacing.pause():
            return True, f"already paused at {self.sim_time_s:.6f} s"
        how = "commands wait for ~/step or ~/resume" if self._lockstep else "the plant holds"
        return True, f"paused at {self.sim_time_s:.6f} s: {how}"

    def resume(self) -> tuple[bool, str]:
        """`~/resume`: simulated time runs again, without catching up the pause."""
        if not self.pacing.paused:
            return True, f"already running at {self.sim_time_s:.6f} s"
        if self.pacing.resume():
            self._lockstep_step()  # the command that waited
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
        pacing = self.pacing
        if not pacing.paused:
            return False, "running: ~/pause first, then ~/step"
        if pacing.ended:
            return False, f"the lockstep run ended at {self.sim_time_s:g} s (lockstep_end_s)"
        if self._lockstep and not pacing.started:
            return False, "lockstep has not started: waiting for joint_states subscribers"
        period_s = n * p.control_period_s
        if self._lockstep:
            taken = 0
            if pacing.budget_steps(n):
                taken = 1
                self._lockstep_step()
            return True, (
                f"stepping {n} control periods ({period_s:g} s): {taken} run now, the next "
                f"{pacing.step_budget} commands run one each"
            )
        substeps = p.substeps_per_period
        for _ in range(n):
            self.plant.advance(substeps)
            pacing.stepped(substeps)
            self._publish_state()
        pacing.stepped_done(n * substeps)
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
            self.pacing.set_realtime_factor(new.realtime_factor)
        if new.publish_rate_hz != old.publish_rate_hz and not self._lockstep:
            self.pacing.clock.publish_rate_hz = new.publish_rate_hz  # sets the catch-up cap
            self.destroy_timer(self._tick_timer)
            self._tick_timer = self.create_timer(1.0 / new.publish_rate_hz, self._realtime_tick)
        if new.lockstep_end_s != old.lockstep_end_s:
            self.pacing.end_reported = False  # a later end is reported again when it is reached
        if new.diagnostics_period_s != old.diagnostics_period_s:
            self.destroy_timer(self._diag_timer)
            self._diag_timer = self.create_timer(
                new.diagnostics_period_s, self._publish_diagnostics
            )


def _trigger(
    action: Callable[[], tuple[bool, str]],
) -> Callable[[Trigger.Request, Trigger.Response], Trigger.Response]:
    """A std_srvs/Trigger handler that replies with the action's success and message."""

    def handler(_request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = action()
        return response

    return handler


def main(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-simulator` / `ros2 run lca_hil simulator`."""
    return run_node("lca-simulator", SimulatorNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
