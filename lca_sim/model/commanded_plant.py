"""The plant as a drive sees it: command intake, the in-drive current loop, stepping (pure core).

`CommandedPlant` sits between a transport (the simulator node, later the virtual CAN drive) and the
`Simulator`: it validates command arrays, holds the last good command, runs the current loop "in
the drive" at the model rate when the commands are currents, and advances the model. With drive
modes (`use_drive_modes`), joints in position or velocity mode get their current setpoint from
the drive's own loops (`lca_sim.model.drive_modes`) once per drive cycle. No ROS, no clock:
callers say how many steps to take.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from numba import njit

from lca_control import pi as lca_pi
from lca_control.drive_loops import DriveLoopParams, DriveMode
from lca_control.pi import PIParams, pi_law, pi_rebase
from lca_sim.errors import InvalidValueError
from lca_sim.model import code_version, kernel, rigid_body
from lca_sim.model.drive_modes import VOLTAGE_MODE, JointDriveLoops, check_drive_modes
from lca_sim.model.faults import FaultInjector
from lca_sim.model.simulator import Simulator
from lca_sim.model.step_path import StaleCodeError

FloatArray = npt.NDArray[np.float64]
logger = logging.getLogger(__name__)

VOLTAGE = "voltage"
CURRENT = "current"

# Rows of the in-drive current loops' array (one column per simulator axis).
_L_INTEGRAL = 0
_L_OUTPUT = 1
_L_LAST_ERROR = 2
_L_LIMIT_V = 3  # amplifier voltage limit: the loop's output is clamped to +-this
_L_TARGET_A = 4
_L_ACTIVE = 5  # 1.0 for axes in `joints`, whose loop runs; the others get 0 V
_N_LOOP_ROWS = 6

# lca_control's PI law itself, compiled: the drive's loops are the controller's PI, not a copy.
_pi_law_compiled = njit(cache=True)(pi_law)

# What this module's cached functions compile in from other files: kernel's step (and
# rigid_body's terms) and lca_control's PI law. numba keys their cache on this file only, so
# after an edit of one of those they would run the old code, silently: they compare this value
# with the one they were compiled with and refuse (-1); `recompile_current_loops` compiles them
# again.
CODE_VERSION = code_version.combined(
    kernel.CODE_VERSION, code_version.fingerprint(vars(lca_pi), lca_pi.__name__)
)


@njit  # not cached: compiled into each caller as it is compiled, from the running pi.py
def _run_current_loops(loops, current_a, gains, volts):  # type: ignore[no-untyped-def]
    """One sample of every active axis's current PI: volts from targets and measured currents.

    gains is [kp_v_per_a, ti_s, dt_s]; the limits are per axis (row _L_LIMIT_V). A cached
    copy of its own would be linked, as loaded, into a caller compiled afresh (a new argument
    layout), whose `CODE_VERSION` guard then passes: an edit of pi.py would go unseen.
    """
    for a in range(volts.shape[0]):
        if loops[_L_ACTIVE, a] == 0.0:
            volts[a] = 0.0
            continue
        limit = loops[_L_LIMIT_V, a]
        error = loops[_L_TARGET_A, a] - current_a[a]
        output, integral = _pi_law_compiled(
            gains[0], gains[1], -limit, limit, loops[_L_INTEGRAL, a], error, gains[2]
        )
        loops[_L_INTEGRAL, a] = integral
        loops[_L_OUTPUT, a] = output
        loops[_L_LAST_ERROR, a] = error
        volts[a] = output


@njit(cache=True)
def _current_loops_steps(n_steps, volts, loops, gains, version, mass, nle, work, model, dt_s):  # type: ignore[no-untyped-def]
    """Model steps, each under the current loops' voltages (`Simulator.advance_with`).

    -1 and nothing touched when compiled against other code than the running (`version`, the
    module's `CODE_VERSION`: `recompile_current_loops`).
    """
    if version != CODE_VERSION:  # a global: frozen into the compiled code
        return -1
    for k in range(n_steps):
        _run_current_loops(loops, work[kernel.X_CURRENT], gains, volts)
        if kernel.step(mass, nle, volts, work, model, dt_s) != kernel.OK:
            return k
    return n_steps


@njit(cache=True)
def _current_loops_held(  # type: ignore[no-untyped-def]
    n_steps,
    age,
    hold,
    lead_s,
    hold_position,
    held_mass,
    held_nle,
    mass,
    nle,
    tree,
    body,
    volts,
    loops,
    gains,
    version,
    work,
    model,
    dt_s,
    out,
):
    """`_current_loops_steps` on eq. (2)'s held terms, the holds included: one compiled call.

    The fused form of `StepPath.advance_with` for this stepper (`StepPath.advance_fused`): at
    each new hold (`age` 0) the terms are evaluated at the hold's mean position with
    `StepPath._rigid_body_terms`'s arithmetic, so the same bits; the numpy calls and two
    dispatches per hold around the compiled code cost more than the steps themselves. Writes
    (steps done, age after) into `out`; returns 1 when all `n_steps` were taken, 0 when a step
    refused its voltages, -1 (nothing touched) when this code was compiled against other code
    than the running, here or in `_current_loops_steps` (`version`: `recompile_current_loops`).
    """
    if version != CODE_VERSION:  # a global: frozen into the compiled code
        return -1
    taken = 0
    while taken < n_steps:
        if age == 0:
            for i in range(hold_position.shape[0]):
                hold_position[i] = work[kernel.X_VELOCITY, i] * lead_s
                hold_position[i] += work[kernel.X_POSITION, i]
            rigid_body.terms(hold_position, work[kernel.X_VELOCITY], tree, body, mass, nle)
            held_mass[:, :] = mass
            held_nle[:] = nle
        chunk = min(hold - age, n_steps - taken)
        done = _current_loops_steps(
            chunk, volts, loops, gains, version, held_mass, held_nle, work, model, dt_s
        )
        if done < 0:  # its cached copy for these types is stale: nothing touched
            return -1
        taken += done
        age = (age + done) % hold
        if done < chunk:
            break
    out[0] = taken
    out[1] = age
    return 1 if taken == n_steps else 0


@njit(cache=True)
def _sensed_current_loops_steps(  # type: ignore[no-untyped-def]
    n_steps, volts, loops, gains, version, sense, noise, mass, nle, work, model, dt_s
):
    """`_current_loops_steps` with a faulty current sensor (lca_sim.model.faults).

    The loops regulate the measured current gain * i + offset + noise[k] (sense rows 0 and 1,
    noise one row per step) instead of the true one.
    """
    if version != CODE_VERSION:  # a global: frozen into the compiled code
        return -1
    measured = np.empty(volts.shape[0])
    for k in range(n_steps):
        for a in range(volts.shape[0]):
            measured[a] = sense[0, a] * work[kernel.X_CURRENT, a] + sense[1, a] + noise[k, a]
        _run_current_loops(loops, measured, gains, volts)
        if kernel.step(mass, nle, volts, work, model, dt_s) != kernel.OK:
            return k
    return n_steps


def recompile_current_loops() -> None:
    """Compile this module's cached functions again from the running code.

    Callees first: numba links a caller with its callees' code as loaded, so a caller compiled
    again over a stale callee would keep the callee's old code. One not compiled in this
    process yet gets its cache emptied (`recompile` flushes it) and is compiled afresh when
    first called. `_run_current_loops` is not cached, and `_pi_law_compiled`'s cache is keyed
    on pi.py itself: both are fresh.
    """
    logger.info("compiling the current loops again: numba's cache holds code of older files")
    for function in (_current_loops_steps, _current_loops_held, _sensed_current_loops_steps):
        function.recompile()


@dataclass
class CommandCounters:
    """How many command messages were taken or refused, and why."""

    accepted: int = 0
    rejected_length: int = 0
    rejected_nonfinite: int = 0
    rejected_absurd: int = 0
    timeouts: int = 0
    saturated: int = 0

    @property
    def rejected(self) -> int:
        """All refused commands."""
        return self.rejected_length + self.rejected_nonfinite + self.rejected_absurd

    def as_dict(self) -> dict[str, int]:
        """The counters by name (for diagnostics)."""
        return {
            "commands_accepted": self.accepted,
            "commands_rejected_length": self.rejected_length,
            "commands_rejected_nonfinite": self.rejected_nonfinite,
            "commands_rejected_absurd": self.rejected_absurd,
            "command_timeouts": self.timeouts,
            "commands_saturated": self.saturated,
        }


@dataclass
class CommandedPlant:
    """A simulator behind voltage or current commands.

    Args:
        sim: the model.
        joints: the order of the command arrays (a subset of the simulator's axes).
        interface: `voltage` (V) or `current` (A, the current PI runs here at the model rate).
        current_pi: gains of the in-drive current loop; its output limits are replaced by each
            axis's amplifier voltage limit.
        max_abs_command: a command beyond this magnitude is absurd and refused outright
            (commands within it but beyond the amplifier or current limit are saturated).
        current_limit_a: saturation of current setpoints (current interface).
    """

    sim: Simulator
    joints: tuple[str, ...]
    interface: str
    current_pi: PIParams
    max_abs_command: float
    current_limit_a: float = 20.0
    enabled: bool = True
    counters: CommandCounters = field(default_factory=CommandCounters)
    faults: FaultInjector | None = None  # injected faults (lca_sim.model.faults); None: none
    drive: JointDriveLoops | None = None  # position / velocity joints (`use_drive_modes`)

    def __post_init__(self) -> None:
        self._index = [self.sim.axis_names.index(j) for j in self.joints]
        self._target = np.zeros(self.sim.n_axes)
        self._volts = np.zeros(self.sim.n_axes)
        self._voltage_limits = [a.motor.voltage_limit_v for a in self.sim.robot.axes]
        self._loops = np.zeros((_N_LOOP_ROWS, self.sim.n_axes))
        self._loops[_L_LIMIT_V] = self._voltage_limits
        self._loops[_L_ACTIVE, self._index] = 1.0
        self._gains = np.array([self.current_pi.kp, self.current_pi.ti_s, self.sim.dt_s])
        self._warm_up()

    def _warm_up(self) -> None:
        """Run one step of each path now (the faulted one too), and rewind.

        Nothing is then compiled (or loaded from numba's cache) in the first step of a running
        loop, or when a fault is first injected: on a fresh machine that took 0.2 s, which a
        CAN drive's watchdogs see as a lost master. Code from numba's cache of older files
        refuses to run (`CODE_VERSION`): it is compiled again here, before any real step.
        """
        sim = self.sim
        snapshot = sim.state
        try:
            self._run_each_path()
        except StaleCodeError:
            recompile_current_loops()
            self._run_each_path()
        sim.set_state(snapshot)  # kernel.step itself: set_state evaluates the state with it
        self._volts[:] = 0.0

    def _run_each_path(self) -> None:
        sim, volts, gains = self.sim, self._volts, self._gains
        loops = self._loops.copy()
        sim.advance_with(1, _current_loops_steps, volts, loops, gains, CODE_VERSION)
        sim.advance_with(
            1, _current_loops_steps, volts, loops, gains, CODE_VERSION, fused=_current_loops_held
        )
        sense = np.vstack((np.ones(sim.n_axes), np.zeros(sim.n_axes)))  # a true sensor
        noise = np.zeros((1, sim.n_axes))
        sim.advance_with(
            1, _sensed_current_loops_steps, volts, loops, gains, CODE_VERSION, sense, noise
        )
        sim.advance(1, np.zeros(sim.n_axes))

    @property
    def target(self) -> FloatArray:
        """The command in force per simulator axis (V or A); read only."""
        view = self._target.view()
        view.flags.writeable = False
        return view

    def use_drive_modes(
        self, modes: Sequence[str], params: DriveLoopParams, period_s: float
    ) -> None:
        """Run each joint in its drive mode (`joints` order): position, velocity, current, voltage.

        All voltage needs the voltage interface, the others the current interface; all current
        is the plain current interface. The loops run every `period_s` (a whole multiple of
        the model's dt) and start halted (0 A) until their first target.

        Raises:
            InvalidValueError: modes that do not fit the joints or the interface, or a period
                that is not a whole multiple of dt.
        """
        checked = check_drive_modes(modes, self.joints)
        voltage = checked[0] == VOLTAGE_MODE
        if voltage != (self.interface == VOLTAGE):
            raise InvalidValueError(
                f"drive_modes {list(checked)} need the {VOLTAGE if voltage else CURRENT} "
                f"interface, the plant takes {self.interface}"
            )
        steps = round(period_s / self.sim.dt_s)
        if steps < 1 or abs(period_s - steps * self.sim.dt_s) > 1e-9 * period_s:
            raise InvalidValueError(
                f"drive loop period {period_s:g} s: expected a whole multiple of dt "
                f"{self.sim.dt_s:g} s"
            )
        drive_modes = [DriveMode.parse(m) for m in checked] if not voltage else []
        if voltage or all(m is DriveMode.CURRENT for m in drive_modes):
            self.drive = None
            return
        self.drive = JointDriveLoops(drive_modes, params, steps)

    def _takes(self, mode: DriveMode) -> tuple[int, ...]:
        """Indices (joints order) of the joints whose command arrays of `mode` count."""
        if self.drive is None:
            return tuple(range(len(self.joints))) if mode is DriveMode.CURRENT else ()
        return self.drive.joints_in(mode)

    def _check(self, values: Sequence[float], taken: Sequence[int]) -> str | None:
        """Why this array is refused (counted), or None: length, then the taken entries."""
        if len(values) != len(self.joints):
            self.counters.rejected_length += 1
            return (
                f"expected {len(self.joints)} values ({', '.join(self.joints)}), got {len(values)}"
            )
        if not all(math.isfinite(values[j]) for j in taken):
            self.counters.rejected_nonfinite += 1
            return f"values must be finite, got {list(values)}"
        if any(abs(values[j]) > self.max_abs_command for j in taken):
            self.counters.rejected_absurd += 1
            return f"|value| above {self.max_abs_command:g}: {list(values)}"
        return None

    def command(self, values: Sequence[float]) -> str | None:
        """Take a command array in `joints` order; return None, or why it was refused.

        The last good command stays in force when one is refused. With drive modes only the
        current joints' entries count; the others are ignored (any value, NaN too).
        """
        taken = self._takes(DriveMode.CURRENT)
        reason = self._check(values, taken)
        if reason is not None:
            return reason
        for joint_index in taken:
            axis = self._index[joint_index]
            value = float(values[joint_index])
            limit = (
                self._voltage_limits[axis] if self.interface == VOLTAGE else self.current_limit_a
            )
            if abs(value) > limit:
                self.counters.saturated += 1
                value = math.copysign(limit, value)
            self._target[axis] = value
        self.counters.accepted += 1
        return None

    def command_targets(self, mode: DriveMode, values: Sequence[float]) -> str | None:
        """Position (rad, m) or velocity (rad/s, m/s) targets, `joints` order; None or why not.

        Only the entries of the joints in `mode` count (the others are ignored, NaN too). A
        position beyond a joint's end stops is saturated to it (counted): the drive's software
        position limits; a velocity beyond the loops' velocity_limit is capped by them (counted
        as well). Without a joint in `mode` the array is refused.
        """
        taken = self._takes(mode) if mode is not DriveMode.CURRENT else ()
        if self.drive is None or not taken:
            self.counters.rejected_length += 1
            return f"no joint runs {mode.value} mode (drive_modes)"
        reason = self._check(values, taken)
        if reason is not None:
            return reason
        for joint_index in taken:
            value = float(values[joint_index])
            if mode is DriveMode.POSITION:
                low, high = self.sim.position_limits[self._index[joint_index]]
                if not low <= value <= high:
                    self.counters.saturated += 1
                    value = min(max(value, low), high)
            elif abs(value) > self.drive.loops[joint_index].params.velocity_limit:
                self.counters.saturated += 1  # the loop caps it
            self.drive.set_target(joint_index, value)
        self.counters.accepted += 1
        return None

    def hold_zero(self, timed_out: bool = False) -> None:
        """Drop the command to zero (command timeout, disable): the gear holds the load.

        The drive loops halt (0 A) until their next target.
        """
        if timed_out:
            self.counters.timeouts += 1
        self._target[:] = 0.0
        self._loops[[_L_INTEGRAL, _L_OUTPUT, _L_LAST_ERROR]] = 0.0
        if self.drive is not None:
            self.drive.halt()

    def set_enabled(self, enabled: bool) -> None:
        """Amplifiers on or off; off means 0 V on every axis and reset current loops."""
        self.enabled = enabled
        self.hold_zero()

    def set_current_gains(self, kp_v_per_a: float, ti_s: float) -> None:
        """Retune the in-drive current loop (bumpless)."""
        self.current_pi = PIParams(kp_v_per_a, ti_s, -1.0, 1.0)
        loops = self._loops
        for a, limit in enumerate(self._voltage_limits):
            loops[_L_INTEGRAL, a], loops[_L_OUTPUT, a] = pi_rebase(
                kp_v_per_a, -limit, limit, loops[_L_OUTPUT, a], loops[_L_LAST_ERROR, a]
            )
        self._gains[:2] = (kp_v_per_a, ti_s)

    @property
    def current_loop_outputs_v(self) -> FloatArray:
        """The last output of each axis's in-drive current loop, V (0 for inactive axes)."""
        outputs: FloatArray = self._loops[_L_OUTPUT].copy()
        return outputs

    def advance(self, n_steps: int) -> None:
        """Run the model n_steps of its dt under the command in force."""
        sim = self.sim
        volts = self._volts
        if not self.enabled:
            volts[:] = 0.0
            sim.advance(n_steps, volts)
            return
        if self.interface == VOLTAGE:
            volts[:] = self._target
            if self.faults is not None and self.faults.any_active:
                self.faults.thermal(
                    sim.state_array[kernel.X_CURRENT],
                    sim.state_array[kernel.X_CURRENT],
                    n_steps * sim.dt_s,
                )
            sim.advance(n_steps, volts)
            return
        drive = self.drive
        if drive is None:
            self._advance_current(n_steps)
            return
        while n_steps > 0:
            if drive.steps_to_cycle == 0:
                self._drive_cycle(drive)
            chunk = min(n_steps, drive.steps_to_cycle)
            self._advance_current(chunk)
            drive.steps_to_cycle -= chunk
            n_steps -= chunk

    def _drive_cycle(self, drive: JointDriveLoops) -> None:
        """The drive loops on the joints' state now: their currents become the setpoints (A)."""
        state = self.sim.state_array
        index = self._index
        currents = drive.cycle(
            state[kernel.X_POSITION, index].tolist(),
            state[kernel.X_VELOCITY, index].tolist(),
            drive.period_steps * self.sim.dt_s,
        )
        for joint_index, current_a in enumerate(currents):
            if current_a is not None:
                limit = self.current_limit_a
                self._target[index[joint_index]] = min(max(current_a, -limit), limit)
        drive.steps_to_cycle = drive.period_steps

    def _advance_current(self, n_steps: int) -> None:
        """`advance` of the current interface: the in-drive current loops, faults if any."""
        if self.faults is not None and self.faults.any_active:
            self._advance_faulted(n_steps, self.faults)
            return
        self._loops[_L_TARGET_A] = self._target
        args = (self._volts, self._loops, self._gains, CODE_VERSION)
        try:
            self.sim.advance_with(n_steps, _current_loops_steps, *args, fused=_current_loops_held)
        except StaleCodeError:  # another process rewrote numba's cache since the warm-up
            recompile_current_loops()
            self.sim.advance_with(n_steps, _current_loops_steps, *args, fused=_current_loops_held)

    def _advance_faulted(self, n_steps: int, faults: FaultInjector) -> None:
        """`advance` of the current interface with injected faults in force.

        The I2t monitors see the interval first (a trip takes effect in it); the drive's
        current limit clamps the setpoints; safe torque off holds the loops at rest (no
        wind-up while the power stage is off); a sagging supply lowers the loops' voltage
        limit as it lowers the amplifier's; the loops regulate the current sensor's reading.
        """
        sim, loops = self.sim, self._loops
        faults.thermal(sim.state_array[kernel.X_CURRENT], self._target, n_steps * sim.dt_s)
        target = np.clip(self._target, -faults.drive.current_limit, faults.drive.current_limit)
        target[faults.drive.sto] = 0.0
        loops[_L_TARGET_A] = target
        for row in (_L_INTEGRAL, _L_OUTPUT, _L_LAST_ERROR):
            loops[row, faults.drive.sto] = 0.0
        loops[_L_LIMIT_V] = sim.model_array[kernel.P_VOLTAGE_LIMIT_V]
        sense = np.vstack((faults.sensors.gain, faults.sensors.offset))
        noise = faults.sensors.current_noise(n_steps)
        args = (self._volts, loops, self._gains, CODE_VERSION, sense, noise)
        try:
            sim.advance_with(n_steps, _sensed_current_loops_steps, *args)
        except StaleCodeError:  # nothing was touched
            recompile_current_loops()
            sim.advance_with(n_steps, _sensed_current_loops_steps, *args)
        loops[_L_LIMIT_V] = self._voltage_limits
