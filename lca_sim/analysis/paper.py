"""The paper's figures as data: what `lca-hil paper` plots, computed without plotting.

Each function reproduces one experiment of the paper on the simulator (pure: no ROS, no files,
no matplotlib; `lca_sim.cli.paper` draws and writes them):

* Figs 4-5 (`constant_velocity_torques`): the pivot at +-7 deg/s. At constant velocity eq. (10)
  reduces to eta_m tau_m = eta_l tau_l + tau_fv (eq. 5 with the efficiencies); the motor torque
  of each model is the equilibrium current times k_t, found on the full model by
  `lca_sim.analysis.linear.equilibrium_current` (the reversible model is the same robot with every
  efficiency 1, config/robots/reversible.yaml).
* Figs 9-10 (`open_loop_phases`): the four phases of the open-loop voltage run, from the
  recorded drive states.
* Figs 12 and 14 (`bode_study`): the open loops of the linearised pivot at several operating
  points, python-control's frequency responses and margins, and where they stop depending on
  the operating point.
* Fig. 13 (`current_step`): the 5 A current step with the paper's gains, rotor locked.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import control as ct
import numpy as np
import numpy.typing as npt

from lca_control.cascade import (
    CONTROL_PERIOD_S,
    PAPER_CURRENT_KP_V_PER_A,
    PAPER_CURRENT_TI_S,
    PAPER_VELOCITY_KP_A_PER_RAD_S,
    PAPER_VELOCITY_TI_S,
)
from lca_control.pi import PIController, PIParams
from lca_sim.analysis.linear import (
    LinearAxisModel,
    LinearisationError,
    LoopMargins,
    OperatingPoint,
    axis_moving_state,
    cascade_loops,
    equilibrium_current,
    independence_frequency,
)
from lca_sim.model.params import RobotParams
from lca_sim.model.scenario import ScenarioResult
from lca_sim.model.simulator import Simulator
from lca_sim.model.state_machine import (
    FIRST_MOVING_STATE,
    LoadCondition,
    MotorCondition,
    StopState,
)

FloatArray = npt.NDArray[np.float64]

PIVOT = "pivot"


# --- Figs 4 and 5 ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ConstantVelocityTorques:
    """Motor-side torques along a constant-velocity sweep of one axis (Figs 4-5).

    Attributes:
        velocity_rad_s: the joint velocity of the sweep.
        position_rad: joint positions, in the order the motion visits them.
        load_torque_nm: tau_l = N^-1 Q(q) (eq. 5, eq. 8), motor side.
        reversible_motor_torque_nm: what a velocity-only friction model expects,
            tau_l + tau_fv (eq. 5).
        state_machine_motor_torque_nm: the state-machine model's k_t i at constant velocity;
            NaN where no constant velocity exists (a state boundary).
        drive_state: the drive state of the state-machine model at each position.
        load_driving_from_rad: the first position along the motion where the load drives
            (gravity pushes along the motion); NaN if it never does.
    """

    velocity_rad_s: float
    position_rad: FloatArray
    load_torque_nm: FloatArray
    reversible_motor_torque_nm: FloatArray
    state_machine_motor_torque_nm: FloatArray
    drive_state: tuple[str, ...]
    load_driving_from_rad: float


def _steady_motor_torque(sim: Simulator, axis: int, point: OperatingPoint) -> tuple[float, str]:
    """k_t i at constant velocity, and the drive state it runs in."""
    current = equilibrium_current(sim, axis, point)
    k_t = sim.robot.axes[axis].motor.torque_constant_nm_per_a
    state = axis_moving_state(sim, axis, point.position_rad, point.velocity_rad_s, current)
    _, drive = sim.derivative(state, np.zeros(sim.n_axes))
    return k_t * current, sim.state_names[drive[axis]]


def constant_velocity_torques(
    sim: Simulator,
    sim_rev: Simulator,
    velocity_rad_s: float,
    positions_rad: Sequence[float],
    axis: str = PIVOT,
) -> ConstantVelocityTorques:
    """Figs 4-5: load torque and the two models' motor torques at constant velocity.

    `sim` runs the robot, `sim_rev` the same robot with every efficiency 1 (eq. 5).
    """
    robot = sim.robot
    a = sim.axis_names.index(axis)
    order = sorted(positions_rad, reverse=velocity_rad_s < 0.0)
    ratio = robot.axes[a].gear_ratio
    load, rev, sm, states = [], [], [], []
    for q in order:
        point = OperatingPoint(float(q), velocity_rad_s)
        q_all = np.zeros(sim.n_axes)
        q_all[a] = q
        load.append(float(sim.gantry.gravity(q_all)[a]) / ratio)
        rev.append(_steady_motor_torque(sim_rev, a, point)[0])
        try:
            torque, state = _steady_motor_torque(sim, a, point)
        except LinearisationError:
            torque, state = math.nan, "boundary"
        sm.append(torque)
        states.append(state)
    load_driving = _states_where(robot, load=LoadCondition.DRIVES)
    load_drives = [i for i, s in enumerate(states) if s in load_driving]
    return ConstantVelocityTorques(
        velocity_rad_s=velocity_rad_s,
        position_rad=np.asarray(order, dtype=float),
        load_torque_nm=np.asarray(load),
        reversible_motor_torque_nm=np.asarray(rev),
        state_machine_motor_torque_nm=np.asarray(sm),
        drive_state=tuple(states),
        load_driving_from_rad=float(order[load_drives[0]]) if load_drives else math.nan,
    )


def _states_where(
    robot: RobotParams,
    motor: MotorCondition | None = None,
    load: LoadCondition | None = None,
) -> frozenset[str]:
    """Names of the moving states whose rule has these motor / load conditions."""
    return frozenset(
        rule.name
        for rule in robot.state_machine.rules
        if (motor is None or rule.motor == motor) and (load is None or rule.load == load)
    )


# --- Figs 9 and 10 -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Phase:
    """One phase of the open-loop run: [start_s, end_s) and where it began."""

    name: str
    start_s: float
    end_s: float
    start_position_rad: float


def _phase_states(robot: RobotParams) -> tuple[tuple[str, frozenset[str]], ...]:
    """The moving phases of Figs 9-10 and the drive states that belong to each, in test order."""
    return (
        ("motor driving", _states_where(robot, MotorCondition.DRIVES, LoadCondition.RESISTS)),
        ("load driving", _states_where(robot, MotorCondition.DRIVES, LoadCondition.DRIVES)),
        ("braking", _states_where(robot, MotorCondition.BRAKES)),
    )


def _phase_name(
    state: str,
    named_states: tuple[tuple[str, frozenset[str]], ...],
    hold: str,
    *,
    moved: bool,
    current: str | None,
) -> str | None:
    """The phase a drive state belongs to; None while held, `current` for a stop sub-state."""
    for name, states in named_states:
        if state in states:
            return name
    if state == hold:
        return None
    if not moved:
        return "starting"
    return current  # a stop sub-state after motion: the phase runs on to the hold


def open_loop_phases(result: ScenarioResult, robot: RobotParams, axis: str = PIVOT) -> list[Phase]:
    """The four phases of Figs 9-10, from the drive-state transitions of a run.

    * starting: the motor torque builds up while the gear is still locked (the stop sub-states
      with the motor pushing, before the first motion);
    * motor driving: the states where the motor drives and the load resists;
    * load driving: the states where the load drives along the motion with the motor (the
      centre of gravity has passed over the axis);
    * braking: the motor brakes (its torque opposes the motion) until the axis is held again.
    """
    named_states = _phase_states(robot)
    hold = result.state_names[StopState.STOP_HOLD]
    moving = set(result.state_names[FIRST_MOVING_STATE:])
    phases: list[Phase] = []
    moved = False
    current: str | None = None
    for t in result.phases(axis):
        if t.state in moving:
            moved = True
        name = _phase_name(t.state, named_states, hold, moved=moved, current=current)
        if name != current:
            if phases:
                phases[-1] = replace(phases[-1], end_s=t.time_s)
            if name is not None:
                phases.append(Phase(name, t.time_s, math.nan, t.position))
            current = name
    if phases and math.isnan(phases[-1].end_s):
        phases[-1] = replace(phases[-1], end_s=float(result.time_s[-1]))
    return phases


# --- Figs 12 and 14 ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BodeStudy:
    """Open loops of the linearised axis at several operating points (Figs 12 and 14).

    Attributes:
        omega_rad_s: the frequency grid.
        labels, drive_states: per operating point.
        current_loop, velocity_loop: [points, omega] complex responses of C_i P_i and C_v P_v.
        current_margins, velocity_margins: per operating point.
        current_independent_from_rad_s, velocity_independent_from_rad_s: where the responses
            stop depending on the operating point (within `tolerance_db` / `tolerance_deg`).
    """

    omega_rad_s: FloatArray
    labels: tuple[str, ...]
    drive_states: tuple[str, ...]
    current_loop: npt.NDArray[np.complex128]
    velocity_loop: npt.NDArray[np.complex128]
    current_margins: tuple[LoopMargins, ...]
    velocity_margins: tuple[LoopMargins, ...]
    current_independent_from_rad_s: float
    velocity_independent_from_rad_s: float
    tolerance_db: float
    tolerance_deg: float


def bode_study(
    sim: Simulator,
    models: Sequence[LinearAxisModel],
    omega_rad_s: FloatArray | None = None,
    tolerance_db: float = 1.0,
    tolerance_deg: float = 5.0,
) -> BodeStudy:
    """Figs 12 and 14 with the paper's gains: python-control responses, margins, independence.

    `models`: the axis linearised at the operating points (`linearise_points`).
    """
    omega = np.logspace(-1, 5, 601) if omega_rad_s is None else np.asarray(omega_rad_s)
    loops = cascade_loops(
        models,
        (PAPER_CURRENT_KP_V_PER_A, PAPER_CURRENT_TI_S),
        (PAPER_VELOCITY_KP_A_PER_RAD_S, PAPER_VELOCITY_TI_S),
        sim.dt_s,
        CONTROL_PERIOD_S,
    )

    def responses(transfer: list[ct.LTI]) -> npt.NDArray[np.complex128]:
        return np.vstack([np.ravel(ct.frequency_response(lp, omega).complex) for lp in transfer])

    li = responses([p.current_loop for p in loops])
    lv = responses([p.velocity_loop for p in loops])
    return BodeStudy(
        omega_rad_s=omega,
        labels=tuple(m.point.label for m in models),
        drive_states=tuple(m.drive_state for m in models),
        current_loop=li,
        velocity_loop=lv,
        current_margins=tuple(p.current for p in loops),
        velocity_margins=tuple(p.velocity for p in loops),
        current_independent_from_rad_s=independence_frequency(
            omega, list(li), tolerance_db, tolerance_deg
        ),
        velocity_independent_from_rad_s=independence_frequency(
            omega, list(lv), tolerance_db, tolerance_deg
        ),
        tolerance_db=tolerance_db,
        tolerance_deg=tolerance_deg,
    )


# --- Fig. 13 -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class StepResponse:
    """A sampled step response and its figures.

    Attributes:
        time_s, current_a: the samples (after each model step).
        setpoint_a: the step.
        overshoot_pct: peak above the final value, % of it.
        response_time_s: the 5 % response time (the paper's t_r, docs/control.md).
        rise_time_s: 10 -> 90 % rise time.
    """

    time_s: FloatArray
    current_a: FloatArray
    setpoint_a: float
    overshoot_pct: float
    response_time_s: float
    rise_time_s: float


def current_step(
    robot: RobotParams, setpoint_a: float = 5.0, seconds: float = 0.05, axis: str = PIVOT
) -> StepResponse:
    """Fig. 13: the current PI of the paper at the model rate (0.1 ms), rotor locked.

    Locked as on a bench: the axis sits on its upper end stop and the positive current pushes
    it into the stop, so the response is the electrical loop alone.
    """
    sim = Simulator(robot, dt_s=1e-4)
    a = sim.axis_names.index(axis)
    sim.reset(position={axis: sim.position_limits[a][1]})
    limit_v = robot.axes[a].motor.voltage_limit_v
    current_loop = PIController(
        PIParams(PAPER_CURRENT_KP_V_PER_A, PAPER_CURRENT_TI_S, -limit_v, limit_v)
    )
    volts = np.zeros(sim.n_axes)
    samples = np.empty(round(seconds / sim.dt_s))
    for k in range(len(samples)):
        volts[a] = current_loop.update(setpoint_a, float(sim.state_array[2, a]), sim.dt_s)
        sim.step(volts)
        samples[k] = sim.state_array[2, a]
    t: FloatArray = np.arange(1, len(samples) + 1, dtype=np.float64) * sim.dt_s
    final = float(samples[-1])
    outside = np.nonzero(np.abs(samples - final) > 0.05 * abs(final))[0]
    response = float(t[outside[-1] + 1]) if len(outside) else float(t[0])
    t10 = float(t[np.argmax(samples >= 0.1 * final)])
    t90 = float(t[np.argmax(samples >= 0.9 * final)])
    return StepResponse(
        time_s=t,
        current_a=samples,
        setpoint_a=setpoint_a,
        overshoot_pct=(float(samples.max()) - final) / final * 100.0,
        response_time_s=response,
        rise_time_s=t90 - t10,
    )
