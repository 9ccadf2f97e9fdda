"""The composed closed loop: the controller core against the commanded plant, in one process.

`ClosedLoop` runs what the lockstep ROS loop runs (the simulator node with `timing_mode:
lockstep`, the controller node) without ROS: the same objects, the same numbers, in the same
order. Per control period the plant's state at model step `k`, stamped `k * dt_s` rounded to
whole nanoseconds as `builtin_interfaces/Time` holds it (`stamp_time_s`), goes to
`lca_control.controller.JointController.update`; its command array goes through
`CommandedPlant.command` (a refused one leaves the last good command in force), and the plant
advances one control period (`substeps_per_period`), or fewer up to `lockstep_end_s`. The
command on the last state is computed and recorded but never applied. A run equals a lockstep
run recorded through the nodes to the last bit (`tests/lca_sim/analysis/test_closed_loop.py`);
docs/control.md ("The composed closed loop") has the start, the order and the rounding.

Pure: no ROS, no clock, no files. `lca_sim.batch.closed_loop_config` builds the config from the
nodes' parameter files; `lca-hil run` (`lca_sim.cli.run`) writes the result.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from lca_control.controller import ControllerParams, JointController
from lca_control.parameters import ParameterError
from lca_sim.analysis.metrics import VelocityTracking, tracking_window_s, velocity_tracking
from lca_sim.errors import UnknownNameError
from lca_sim.model.commanded_plant import VOLTAGE
from lca_sim.model.fault_schedule import ScheduledFault
from lca_sim.model.faults import LINK
from lca_sim.model.params import RobotParams
from lca_sim.model.plant import PlantConfig, build_plant
from lca_sim.model.simulator import SIGNAL_NAMES

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_NS_PER_S = 1_000_000_000


def stamp_time_s(t_s: float) -> float:
    """Seconds as a `builtin_interfaces/Time` stamp holds them and the controller reads them.

    The arithmetic of `lca_sim.ros.node_util.to_stamp` then `from_stamp` (whole seconds and
    nanoseconds, then sec + 1e-9 * nanosec), without the message type.
    """
    sec = math.floor(t_s)
    nanosec = round((t_s - sec) * 1e9)
    if nanosec >= _NS_PER_S:
        sec, nanosec = sec + 1, nanosec - _NS_PER_S
    return float(int(sec)) + 1e-9 * float(int(nanosec))


def check_time_s(name: str, value: float, dt_s: float | None = None) -> None:
    """A time of a run (its duration, its control period): > 0 s, a whole number of dt_s.

    Raises:
        ParameterError: `NAME: expected a time > 0 s, a whole multiple of dt_s = 0.0001 s,
            got VALUE` (without the multiple when `dt_s` is None), the whole range in one line.
    """
    expected = "a time > 0 s" + ("" if dt_s is None else f", a whole multiple of dt_s = {dt_s:g} s")
    if not (math.isfinite(value) and value > 0.0):
        raise ParameterError(name, expected, value)
    if dt_s is not None:
        steps = value / dt_s
        if not (round(steps) >= 1 and abs(steps - round(steps)) <= 1e-6 * steps):
            raise ParameterError(name, expected, value)


@dataclass(frozen=True, slots=True)
class ClosedLoopConfig:
    """One composed run: the plant, the controller's parameters and the simulator node's pacing.

    Attributes:
        plant: the plant as the simulator node builds it from its parameters
            (`lca_sim.config.simulator_params.plant_config`): robot, model step, command
            interface, in-drive current PI, command limits.
        controller: the controller node's validated parameters.
        duration_s: simulated time of the run's last state (`lockstep_end_s`), s: a whole
            number of model steps; the last period is shorter when it is not a whole number of
            control periods.
        control_period_s: simulated time per command, s: a whole number of model steps.
        initial_position: the pose at t = 0, one value per robot axis (rad, m for the lift).
        faults: a fault schedule (lca_sim.model.fault_schedule; the simulator node's
            `fault_schedule`): switched at each period's start as the node does, the sensor
            faults on what the controller reads. The link faults (dropped, delayed, stale
            messages) need the node: a schedule naming them is refused here.

    Raises:
        ParameterError: a value the lockstep loop could not run with (named as the node's
            parameter).
    """

    plant: PlantConfig
    controller: ControllerParams
    duration_s: float
    control_period_s: float
    initial_position: tuple[float, ...]
    faults: tuple[ScheduledFault, ...] = ()

    def __post_init__(self) -> None:
        if self.controller.command_interface != self.command_interface:
            raise ParameterError(
                "command_interface",
                f"the controller's ({self.controller.command_interface})",
                self.command_interface,
            )
        if not (math.isfinite(self.dt_s) and self.dt_s > 0.0):
            raise ParameterError("dt_s", "a positive step", self.dt_s)
        for name in ("control_period_s", "duration_s"):
            check_time_s(name, getattr(self, name), self.dt_s)
        link = sorted({f.kind for f in self.faults if f.owner == LINK})
        if link:
            raise ParameterError("fault_schedule", "no link faults in a composed run", link)
        robot = self.plant.robot
        if len(self.initial_position) != len(robot.axes):
            raise ParameterError(
                "initial_position",
                f"{len(robot.axes)} positions ({', '.join(robot.axis_names)})",
                self.initial_position,
            )

    @property
    def robot(self) -> RobotParams:
        """The robot of the plant."""
        return self.plant.robot

    @property
    def command_interface(self) -> str:
        """`current` (the current PI runs in the plant) or `voltage` (both in the controller)."""
        return self.plant.interface

    @property
    def dt_s(self) -> float:
        """The model step, s."""
        return self.plant.dt_s

    @property
    def substeps_per_period(self) -> int:
        """Model steps per control period (as the simulator node rounds it)."""
        return round(self.control_period_s / self.dt_s)

    @property
    def end_steps(self) -> int:
        """Model steps of the whole run (as the node rounds `lockstep_end_s`)."""
        return round(self.duration_s / self.dt_s)

    @property
    def n_states(self) -> int:
        """States of a run: t = 0 and one at the end of every control period."""
        return 1 + -(-self.end_steps // self.substeps_per_period)


@dataclass(frozen=True, slots=True)
class ClosedLoopResult:
    """A composed run, one row per state the controller saw (t = 0 and every period's end).

    Per-axis arrays have a column per robot axis (`axes`), per-joint ones a column per
    controller joint (`joints`).

    Attributes:
        axes: the robot's axis names (the order of joint_states).
        joints: the controller's joints (the order of its commands and references).
        state_names: drive-state names by index (`drive_state`).
        time_s: the states' stamps as the controller reads them, s (`stamp_time_s`).
        steps: model steps done at each state.
        position: joint positions, rad (m for the lift).
        velocity: joint velocities, rad/s (m/s).
        current_a: armature currents, A.
        voltage_v: amplifier voltages of the last model step, V.
        drive_state: drive-state index per axis.
        velocity_reference: the controller's velocity reference at each state, rad/s (m/s).
        command: the controller's command on each state, A or V by `command_interface`; the
            last row's was not applied (the run had ended).
        command_interface: `current` or `voltage`.
        commands_rejected: commands the plant refused (the last good one stayed in force).
    """

    axes: tuple[str, ...]
    joints: tuple[str, ...]
    state_names: tuple[str, ...]
    time_s: FloatArray
    steps: IntArray
    position: FloatArray
    velocity: FloatArray
    current_a: FloatArray
    voltage_v: FloatArray
    drive_state: IntArray
    velocity_reference: FloatArray
    command: FloatArray
    command_interface: str
    commands_rejected: int
    prismatic: tuple[bool, ...] = ()

    def tracking_error(self) -> FloatArray:
        """Velocity reference minus joint velocity, per state and controller joint."""
        index = [self.axes.index(j) for j in self.joints]
        error: FloatArray = self.velocity_reference - self.velocity[:, index]
        return error

    def velocity_tracking(self, controller: ControllerParams, joint: str) -> VelocityTracking:
        """The velocity tracking error of `joint` over the controller's profile span.

        Raises:
            UnknownNameError: not a joint of the controller.
        """
        if joint not in self.joints:
            raise UnknownNameError("controller joint", joint, self.joints)
        j, a = self.joints.index(joint), self.axes.index(joint)
        return velocity_tracking(
            joint,
            self.prismatic[a] if self.prismatic else False,
            tracking_window(controller, float(self.time_s[-1])),
            self.time_s,
            self.velocity_reference[:, j],
            self.velocity[:, a],
        )


def tracking_window(controller: ControllerParams, duration_s: float) -> tuple[float, float]:
    """The velocity tracking window of a run: the built-in profile's span, else the whole run.

    The profile's times count from the first state, which is t = 0 in lockstep
    (`metrics.tracking_window_s` says why the end is left out).
    """
    profile = controller.profile
    if profile is None:
        return 0.0, duration_s
    return tracking_window_s(profile.start_s, profile.end_s)


def replay_references(
    controller: ControllerParams,
    time_s: Sequence[float],
    position: Sequence[Sequence[float]],
    velocity: Sequence[Sequence[float]],
    current_a: Sequence[Sequence[float]] | None = None,
) -> FloatArray:
    """The velocity references a controller core computes on these states, one row per state.

    What the controller node followed on a recorded run: the same core on the same float64
    values gives the same references to the bit.

    Args:
        controller: the controller's parameters (reference source `topic`: references of 0).
        time_s: the states' stamps, s.
        position, velocity: per state, the controller's joints in its order, rad (m) and
            rad/s (m/s).
        current_a: per state, their armature currents, A (the voltage interface only).
    """
    core = JointController(controller)
    rows = np.empty((len(time_s), len(controller.joints)))
    for k, t_s in enumerate(time_s):
        amps = None if current_a is None else list(current_a[k])
        core.update(t_s, list(position[k]), list(velocity[k]), amps)
        rows[k] = core.last_velocity_reference
    return rows


class ClosedLoop:
    """The controller core and the commanded plant of one config, built once, run on demand.

    Construction builds the model (Pinocchio, the compiled kernel) and the plant as the
    simulator node does; `run` then costs only the loop, so a caller can time it apart.

    Raises:
        UnknownNameError: a controller or plant joint the robot does not have.
    """

    def __init__(self, config: ClosedLoopConfig) -> None:
        self.config = config
        c = config
        fault_period_s = c.control_period_s if c.faults else None
        plant = build_plant(dataclasses.replace(c.plant, fault_period_s=fault_period_s))
        self.sim, self.plant, self.faults = plant.sim, plant.commanded, plant.faults
        if self.faults is not None:
            self.faults.set_schedule(c.faults)
        axes = self.sim.axis_names
        for joint in (*c.plant.joints, *c.controller.joints):
            if joint not in axes:
                raise UnknownNameError("joint", joint, axes)
        self._index = [axes.index(j) for j in c.controller.joints]

    def run(self) -> ClosedLoopResult:
        """Run from the initial pose to `duration_s`: the lockstep loop, without ROS.

        Every run starts as the node starts (reset pose, zero commands, a new controller), so
        two runs of one `ClosedLoop` are equal.
        """
        c = self.config
        sim, plant = self.sim, self.plant
        axes = sim.axis_names
        sim.reset(position=dict(zip(axes, c.initial_position, strict=True)))
        plant.hold_zero()
        faults = self.faults
        sensed = None
        if faults is not None:
            faults.restart()
            sensed = (np.zeros(sim.n_axes), np.zeros(sim.n_axes), np.zeros(sim.n_axes))
        rejected_before = plant.counters.rejected
        controller = JointController(c.controller)
        n, n_axes, n_joints = c.n_states, sim.n_axes, len(c.controller.joints)
        time_s = np.empty(n)
        steps_done = np.empty(n, dtype=np.int64)
        position = np.empty((n, n_axes))
        velocity = np.empty((n, n_axes))
        current = np.empty((n, n_axes))
        voltage = np.empty((n, n_axes))
        drive = np.empty((n, n_axes))
        reference = np.empty((n, n_joints))
        command = np.empty((n, n_joints))

        state = sim.state_array  # views, updated in place by every step
        q_row, v_row, i_row = state[0], state[1], state[2]
        drive_row = sim.mode_array[1]
        voltage_row = sim.signal_array[SIGNAL_NAMES.index("voltage_v")]
        index = self._index
        voltage_interface = c.command_interface == VOLTAGE
        update = controller.update
        advance = plant.advance
        take = plant.command
        period = c.substeps_per_period
        end = c.end_steps
        dt_s = c.dt_s
        done = 0
        for k in range(n):
            t_s = stamp_time_s(0.0 + done * dt_s)  # the node's time base is 0 in lockstep
            q, v = q_row.tolist(), v_row.tolist()  # what JointState carries: Python floats
            amps_row = i_row
            if sensed is not None and faults is not None and faults.any_active:
                faults.measure(q_row, v_row, i_row, sensed)  # what the faulty sensors report
                q, v = sensed[0].tolist(), sensed[1].tolist()
                amps_row = sensed[2]
            positions = [q[i] for i in index]
            velocities = [v[i] for i in index]
            currents = None
            if voltage_interface:
                amps = amps_row.tolist()
                currents = [amps[i] for i in index]
            out = update(t_s, positions, velocities, currents)
            if out is None:  # never: the stamps rise by a control period every time
                raise RuntimeError(f"the controller skipped the state at {t_s!r} s")
            time_s[k] = t_s
            steps_done[k] = done
            position[k] = q_row
            velocity[k] = v_row
            current[k] = i_row
            voltage[k] = voltage_row
            drive[k] = drive_row
            reference[k] = controller.last_velocity_reference
            command[k] = out
            if done >= end:
                break
            take(out)  # refused: the last good command stays in force, as in lockstep
            if faults is not None:
                faults.at(done * dt_s)  # the node's _switch_faults: at the period's start
            steps = min(period, end - done)
            advance(steps)
            done += steps
        return ClosedLoopResult(
            axes=axes,
            joints=c.controller.joints,
            state_names=sim.state_names,
            time_s=time_s,
            steps=steps_done,
            position=position,
            velocity=velocity,
            current_a=current,
            voltage_v=voltage,
            drive_state=drive.astype(np.int64),
            velocity_reference=reference,
            command=command,
            command_interface=c.command_interface,
            commands_rejected=plant.counters.rejected - rejected_before,
            prismatic=sim.prismatic,
        )
