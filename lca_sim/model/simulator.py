"""The drive-chain simulator: model built once, explicit state, fixed-step stepper.

Like Drake's System / Context / Simulator split: `RobotParams` is the immutable model
description, `PlantState` an explicit state value that can be read and restored, and `Simulator`
the stepper that owns the scratch buffers (Pinocchio `Data`, kernel arrays) and advances by its
fixed `dt_s`. Nothing here reads a clock or touches a file.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from lca_sim.errors import ConfigError, LcaHilError, UnknownNameError
from lca_sim.model import kernel
from lca_sim.model.gantry import Gantry
from lca_sim.model.params import RobotParams
from lca_sim.model.state_machine import FIRST_MOVING_STATE, MotionState, load_torque_band_nm
from lca_sim.model.step_path import StepPath

FloatArray = npt.NDArray[np.float64]

# Per-axis signals a step exposes, in kernel row order, with their SI unit suffix.
SIGNAL_NAMES: tuple[str, ...] = (
    "motor_velocity_rad_s",
    "current_a",
    "voltage_v",
    "motor_torque_nm",
    "load_torque_nm",
    "friction_torque_nm",
    "eta_m",
    "eta_l",
    "motor_power_w",
    "load_power_w",
    "gear_loss_w",
    "friction_loss_w",
    "electrical_power_w",
    "copper_loss_w",
    "motor_acceleration_rad_s2",
)
assert len(SIGNAL_NAMES) == kernel.N_SIGNALS
# For `Simulator.step`'s checks: numpy's float64 dtype is one object, so `is` tests it at the
# cost of a pointer comparison (anything else takes the converting path, which tests it fully).
_FLOAT64 = np.dtype(np.float64)
_OK = kernel.OK


class InputError(LcaHilError, ValueError):
    """A command given to the simulator is not usable (wrong length, NaN or infinite)."""


@dataclass(frozen=True, slots=True)
class PlantState:
    """The full state of the plant: enough to restore a run exactly.

    With the rigid-body terms held (`Simulator` `rigid_body_update_steps` > 1) the hold's phase
    is not part of it: a restored state starts a new hold, so a run restored in the middle of
    a hold follows the exact run of that simulator to within the hold's error, not bit for bit.

    Attributes:
        time_s: simulated time.
        position: joint positions (rad, m for the lift), in axis order.
        velocity: joint velocities (rad/s, m/s).
        current_a: armature currents.
        motion: upper-level state per axis (Fig. 6).
        drive: lower-level drive-state index per axis (names in `Simulator.state_names`).

    """

    time_s: float
    position: tuple[float, ...]
    velocity: tuple[float, ...]
    current_a: tuple[float, ...]
    motion: tuple[MotionState, ...]
    drive: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class AxisSignals:
    """What one step exposes for every axis (copies; SI units, motor side for torques).

    Efficiencies are NaN while an axis is stopped: it is locked and eq. (10) does not apply.
    Powers: motor_power_w = tau_m w_m is the power the motor sends into the gear,
    load_power_w = tau_l w_m the power the gear delivers to the load (both negative when the
    flow reverses); gear_loss_w and friction_loss_w are what the efficiencies and eq. (4) burn.
    """

    motion: tuple[MotionState, ...]
    drive: tuple[str, ...]
    values: Mapping[str, FloatArray]

    def __getitem__(self, name: str) -> FloatArray:
        """One signal for all axes, by its name in `SIGNAL_NAMES`."""
        try:
            return self.values[name]
        except KeyError:
            raise UnknownNameError("signal", name, SIGNAL_NAMES) from None


class Simulator:
    """Fixed-step simulator of the four coupled drive chains (eq. 8-10).

    Args:
        robot: validated robot parameters.
        dt_s: the fixed integration step (default 0.1 ms).
        rigid_body_update_steps: Pinocchio's A(q) and C(q, qdot) qdot + Q(q) (eq. 2) are
            evaluated once every this many steps and held in between (default 1: at every
            step, the exact fixed-step scheme). With k > 1 they are evaluated at the hold's
            mean position, q + qdot (k - 1) dt / 2, so the error of A(q) and Q(q) is second
            order in the hold (the velocity in C(q, qdot) qdot is the hold's first); the motor,
            gear, state machine and current loops still run at every step. The simulator node
            holds them for 1 ms (10 steps): the results move by microradians
            (tests/lca_sim/model/test_model_physics.py) and a control period's model CPU
            drops by three quarters.

    The simulator starts at rest at q = 0 with zero current; use `reset` for other states.

    """

    def __init__(
        self, robot: RobotParams, dt_s: float = 1e-4, rigid_body_update_steps: int = 1
    ) -> None:
        if not (dt_s > 0.0 and np.isfinite(dt_s)):
            raise ConfigError(robot.source, "dt_s", f"expected a positive step, got {dt_s!r}")
        if type(rigid_body_update_steps) is not int or rigid_body_update_steps < 1:
            raise ConfigError(
                robot.source,
                "rigid_body_update_steps",
                f"expected a whole number of steps >= 1, got {rigid_body_update_steps!r}",
            )
        self.robot = robot
        self.dt_s = float(dt_s)
        self._gantry = Gantry(robot.urdf_xml, robot.gravity_m_s2, robot.source)
        if self._gantry.joint_names != robot.axis_names:
            raise ConfigError(
                robot.source,
                "axes",
                f"expected the URDF's joints {list(self._gantry.joint_names)} in that order, "
                f"got {list(robot.axis_names)}",
            )
        self.axis_names: tuple[str, ...] = robot.axis_names
        self.n_axes = len(robot.axes)
        self.state_names: tuple[str, ...] = robot.state_machine.state_names
        self.prismatic: tuple[bool, ...] = tuple(j.prismatic for j in self._gantry.joints)
        self._params = _params_array(robot, self._gantry)
        self._model = kernel.pack_model(
            self._params,
            robot.state_machine.rule_codes(),
            _eta_array(robot),
            robot.state_machine.irreversible_stop,
        )
        self._work = np.zeros((kernel.work_rows(self.n_axes), self.n_axes))
        self._signals = self._work[kernel.FIRST_SIGNAL : kernel.FIRST_SIGNAL + kernel.N_SIGNALS]
        self._command = np.zeros(self.n_axes)
        self._command_shape = (self.n_axes,)
        self._path = StepPath(
            self._gantry, self._work, self._model, self.dt_s, rigid_body_update_steps
        )
        # Bound once: `step` is the hot path of every run (bench/model_step.py).
        self._kernel_step = self._path.step
        self._time_s = 0.0
        self.reset()

    # --- state -----------------------------------------------------------------------------

    def __reduce__(self) -> Any:
        """Refused: a copy would step the original's memory (see below); build a new one.

        The exact scheme's step reaches its arrays through a frame of raw addresses
        (`lca_sim.model.step_path`), so a copy made by `copy` or `pickle` would keep pointing at
        this simulator's arrays and Pinocchio buffers, and its steps would change them.
        """
        raise TypeError(
            "a Simulator cannot be copied or pickled (its step holds raw addresses of its own "
            "arrays): build a new one from the same RobotParams, and set_state to its state"
        )

    def reset(
        self,
        position: Mapping[str, float] | Sequence[float] | None = None,
        velocity: Mapping[str, float] | Sequence[float] | None = None,
        voltage_v: Sequence[float] | FloatArray | None = None,
    ) -> None:
        """Start again at t = 0 from a pose and velocity, with zero armature current.

        A nonzero initial velocity starts the axis in DIRECT or REVERSE motion; a zero one starts
        it stopped. Positions outside the joint's end stops are an error.
        """
        q = self._per_axis(position, "position")
        v = self._per_axis(velocity, "velocity")
        lo = self._params[kernel.P_POSITION_MIN]
        hi = self._params[kernel.P_POSITION_MAX]
        for a, name in enumerate(self.axis_names):
            if not lo[a] <= q[a] <= hi[a]:
                raise InputError(
                    f"initial position of {name} = {q[a]:g} is outside [{lo[a]:g}, {hi[a]:g}]"
                )
        self._work[:] = 0.0
        self._work[kernel.X_POSITION] = q
        self._work[kernel.X_VELOCITY] = v
        self._work[kernel.X_MOTION] = np.sign(v)
        self._time_s = 0.0
        self._path.restart()
        self._evaluate(np.zeros(self.n_axes) if voltage_v is None else voltage_v)

    def set_state(self, state: PlantState) -> None:
        """Restore a state captured by `state` (for lockstep rewinds and determinism checks).

        A new hold of the rigid-body terms starts from it (`rigid_body_update_steps`).
        """
        self._work[kernel.X_POSITION] = state.position
        self._work[kernel.X_VELOCITY] = state.velocity
        self._work[kernel.X_CURRENT] = state.current_a
        self._work[kernel.X_MOTION] = [int(m) for m in state.motion]
        self._work[kernel.X_DRIVE] = state.drive
        self._time_s = state.time_s
        self._path.restart()
        self._evaluate(self._command.copy())

    @property
    def state(self) -> PlantState:
        """A snapshot of the current state."""
        return PlantState(
            time_s=self._time_s,
            position=tuple(float(x) for x in self._work[kernel.X_POSITION]),
            velocity=tuple(float(x) for x in self._work[kernel.X_VELOCITY]),
            current_a=tuple(float(x) for x in self._work[kernel.X_CURRENT]),
            motion=tuple(MotionState(int(m)) for m in self._work[kernel.X_MOTION]),
            drive=tuple(int(d) for d in self._work[kernel.X_DRIVE]),
        )

    @property
    def time_s(self) -> float:
        """Simulated time."""
        return self._time_s

    @property
    def signals(self) -> AxisSignals:
        """A snapshot of everything the last step exposed, per axis."""
        return AxisSignals(
            motion=tuple(MotionState(int(m)) for m in self._work[kernel.X_MOTION]),
            drive=tuple(self.state_names[int(d)] for d in self._work[kernel.X_DRIVE]),
            values={name: self._signals[row].copy() for row, name in enumerate(SIGNAL_NAMES)},
        )

    # Read-only views for recorders that copy every step (no allocation). They stay valid for
    # the simulator's life: its arrays are updated in place, never replaced.
    @property
    def state_array(self) -> FloatArray:
        """View of [position, velocity, current] x axes; do not write."""
        view = self._work[: kernel.X_CURRENT + 1].view()
        view.flags.writeable = False
        return view

    @property
    def mode_array(self) -> FloatArray:
        """View of [motion (0, +1, -1), drive-state index] x axes, as exact floats; read only."""
        view = self._work[kernel.X_MOTION : kernel.X_DRIVE + 1].view()
        view.flags.writeable = False
        return view

    @property
    def position_limits(self) -> tuple[tuple[float, float], ...]:
        """The joint end stops (min, max) per axis, from the URDF (rad, or m for the lift)."""
        return tuple((j.position_min, j.position_max) for j in self._gantry.joints)

    @property
    def model_array(self) -> FloatArray:
        """The packed constants the kernel runs on (`kernel.pack_model`); read only."""
        view = self._model.view()
        view.flags.writeable = False
        return view

    @property
    def signal_array(self) -> FloatArray:
        """View of the signals, rows in `SIGNAL_NAMES` order; do not write."""
        view = self._signals.view()
        view.flags.writeable = False
        return view

    # --- stepping --------------------------------------------------------------------------

    def step(self, voltage_v: Sequence[float] | FloatArray) -> None:
        """Advance one `dt_s` with the given amplifier voltage commands (V, saturated inside).

        Raises:
            InputError: wrong length, NaN or infinite command; the state is left unchanged.

        """
        command = voltage_v
        if (
            type(command) is not np.ndarray
            or command.dtype is not _FLOAT64
            or command.shape != self._command_shape
        ):
            command = np.asarray(voltage_v, dtype=np.float64)
            if command.shape != self._command_shape:
                raise InputError(f"expected {self.n_axes} voltages, got shape {command.shape}")
        if self._kernel_step(command) != _OK:
            raise InputError(f"voltage commands must be finite, got {command.tolist()}")
        self._command = command
        self._time_s += self.dt_s

    def advance(self, n_steps: int, voltage_v: FloatArray) -> None:
        """`n_steps` of `step` under one voltage command, in compiled code per hold.

        Raises:
            InputError: wrong length, NaN or infinite command; the state is left unchanged.

        """
        command = np.asarray(voltage_v, dtype=np.float64)
        if command.shape != self._command_shape:
            raise InputError(f"expected {self.n_axes} voltages, got shape {command.shape}")
        self.advance_with(n_steps, kernel.steps, command)  # refuses NaN before its first step

    def advance_with(
        self,
        n_steps: int,
        stepper: Callable[..., int],
        volts: FloatArray,
        *args: FloatArray | int,
        fused: Any = None,
    ) -> None:
        """Advance `n_steps` of `dt_s` under voltages a compiled drive computes at every step.

        `stepper(n, volts, *args, mass_matrix, nonlinear_effects, work, model, dt_s)` is a numba
        function that takes up to `n` steps on the given rigid-body terms: at each, it writes
        the voltage commands into `volts` from the state in `work` (rows `kernel.X_*`, read
        only) and calls `kernel.step` with them. It returns the number of steps taken, `n`
        unless a step refused its voltages, or -1 before any step when it was compiled against
        other code than the running (`StaleCodeError`). The in-drive current loops
        (`lca_sim.model.commanded_plant`) run this way: one compiled call per hold of the
        rigid-body terms, the same arithmetic as
        `step` with the voltages computed outside. With held terms, `fused` (the stepper's
        fused form, which evaluates the holds itself: `StepPath.advance_fused`) takes all
        `n_steps` in one compiled call instead, the same bits.

        Raises:
            InputError: the voltages were not finite; the steps before stand, the state is as
                after them.
            StaleCodeError: the stepper (or `fused`) is stale code; nothing changed.

        """
        if fused is not None and self._path.hold_steps > 1:
            done, complete = self._path.advance_fused(n_steps, fused, volts, *args)
        else:
            done, complete = self._path.advance_with(n_steps, stepper, volts, *args)
        time_s, dt_s = self._time_s, self.dt_s
        for _ in range(done):  # added step by step: the same time as `step` gives
            time_s += dt_s
        self._time_s = time_s
        if not complete:
            # The last command stays the last good one (set_state re-evaluates with it).
            raise InputError(f"voltage commands must be finite, got {volts.tolist()}")
        self._command = volts.copy()

    @property
    def rigid_body_update_steps(self) -> int:
        """Steps per evaluation of Pinocchio's terms (fixed at construction)."""
        return self._path.hold_steps

    def derivative(
        self, state: PlantState, voltage_v: Sequence[float] | FloatArray
    ) -> tuple[FloatArray, tuple[int, ...]]:
        """dx/dt of the continuous model at `state` under `voltage_v`, without stepping.

        Returns a [3, n] array: joint velocity, joint acceleration (eq. 10 solved for the moving
        axes with the drive state picked for this state, stopped axes locked at 0), and the
        armature current rate (v - R i - k_t w) / L with the voltage saturated; and the drive
        state index of every axis that this evaluation picked. This is what a numerical
        linearisation differentiates (`lca_sim.analysis.linear`). The simulator's own state, time
        and last command are left as they were.
        """
        saved_work = self._work.copy()
        saved_time, saved_command = self._time_s, self._command
        try:
            self._work[kernel.X_POSITION] = state.position
            self._work[kernel.X_VELOCITY] = state.velocity
            self._work[kernel.X_CURRENT] = state.current_a
            self._work[kernel.X_MOTION] = [int(m) for m in state.motion]
            self._work[kernel.X_DRIVE] = state.drive
            self._evaluate(voltage_v)
            model = self._model
            ratio = model[kernel.P_GEAR_RATIO]
            current = self._work[kernel.X_CURRENT]
            omega = ratio * self._work[kernel.X_VELOCITY]
            out = np.empty((3, self.n_axes))
            out[0] = self._work[kernel.X_VELOCITY]
            out[1] = self._work[kernel.S_MOTOR_ACCELERATION] / ratio
            out[2] = (
                self._work[kernel.S_VOLTAGE]
                - model[kernel.P_RESISTANCE_OHM] * current
                - model[kernel.P_TORQUE_CONSTANT] * omega
            ) / model[kernel.P_INDUCTANCE_H]
            return out, tuple(int(d) for d in self._work[kernel.X_DRIVE])
        finally:
            self._work[:] = saved_work
            self._time_s, self._command = saved_time, saved_command

    def _evaluate(self, voltage_v: Sequence[float] | FloatArray) -> None:
        """Fill the signals for the current state without advancing time (a zero-length step)."""
        command = np.asarray(voltage_v, dtype=np.float64)
        if command.shape != (self.n_axes,) or not np.all(np.isfinite(command)):
            raise InputError(f"expected {self.n_axes} finite voltages, got {command.tolist()}")
        self._path.evaluate(command)
        self._command = command

    # --- helpers ---------------------------------------------------------------------------

    @property
    def gantry(self) -> Gantry:
        """The rigid-body model (for energy checks); its scratch data is shared with the stepper."""
        return self._gantry

    def drive_state_index(self, name: str) -> int:
        """The index of a drive state, by name."""
        try:
            return self.state_names.index(name)
        except ValueError:
            raise UnknownNameError("drive state", name, self.state_names) from None

    def is_moving_state(self, index: int) -> bool:
        """True for the drive states of DIRECT / REVERSE motion (not the stop sub-states)."""
        return index >= FIRST_MOVING_STATE

    def _per_axis(
        self, values: Mapping[str, float] | Sequence[float] | None, what: str
    ) -> FloatArray:
        out = np.zeros(self.n_axes)
        if values is None:
            return out
        if isinstance(values, Mapping):
            for name, value in values.items():
                if name not in self.axis_names:
                    raise UnknownNameError("axis", name, self.axis_names)
                out[self.axis_names.index(name)] = float(value)
        else:
            if len(values) != self.n_axes:
                raise InputError(f"expected {self.n_axes} initial {what} values, got {len(values)}")
            out[:] = [float(x) for x in values]
        if not np.all(np.isfinite(out)):
            raise InputError(f"initial {what} must be finite, got {out.tolist()}")
        return out


def _params_array(robot: RobotParams, gantry: Gantry) -> FloatArray:
    params = np.zeros((kernel.N_PARAMS, len(robot.axes)))
    machine = robot.state_machine
    for a, (axis, joint) in enumerate(zip(robot.axes, gantry.joints, strict=True)):
        m, f = axis.motor, axis.friction
        params[kernel.P_GEAR_RATIO, a] = axis.gear_ratio
        params[kernel.P_RESISTANCE_OHM, a] = m.resistance_ohm
        params[kernel.P_INDUCTANCE_H, a] = m.inductance_h
        params[kernel.P_TORQUE_CONSTANT, a] = m.torque_constant_nm_per_a
        params[kernel.P_ROTOR_INERTIA, a] = m.rotor_inertia_kg_m2
        params[kernel.P_VOLTAGE_LIMIT_V, a] = m.voltage_limit_v
        params[kernel.P_STATIC_DIRECT, a] = f.static_direct_nm
        params[kernel.P_STATIC_REVERSE, a] = f.static_reverse_nm
        params[kernel.P_COULOMB_DIRECT, a] = f.coulomb_direct_nm
        params[kernel.P_COULOMB_REVERSE, a] = f.coulomb_reverse_nm
        params[kernel.P_VISCOUS_DIRECT, a] = f.viscous_direct_nm_s_per_rad
        params[kernel.P_VISCOUS_REVERSE, a] = f.viscous_reverse_nm_s_per_rad
        params[kernel.P_POSITION_MIN, a] = joint.position_min
        params[kernel.P_POSITION_MAX, a] = joint.position_max
        params[kernel.P_VELOCITY_EPS, a] = machine.velocity_eps_rad_s
        params[kernel.P_TORQUE_EPS, a] = machine.motor_torque_eps_nm
        params[kernel.P_LOAD_TORQUE_BAND, a] = load_torque_band_nm(m.stall_torque_nm)
    return params


def _eta_array(robot: RobotParams) -> FloatArray:
    rules = robot.state_machine.rules
    eta = np.ones((len(robot.axes), 2, len(rules), 2))
    for a, axis in enumerate(robot.axes):
        for k, direction in enumerate((MotionState.DIRECT, MotionState.REVERSE)):
            for r, rule in enumerate(rules):
                entry = axis.efficiency[(direction, rule.name)]
                eta[a, k, r, 0] = entry.eta_m
                eta[a, k, r, 1] = entry.eta_l
    return eta
