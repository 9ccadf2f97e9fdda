"""Linearised drive-chain models of one axis and its section 6 loops (Figs 12 and 14).

The full nonlinear simulator (Pinocchio dynamics, eq. 10 with the state machine's efficiencies,
the armature equation) is linearised by central differences of `Simulator.derivative` around a
joint moving at constant velocity, the other axes held still (their irreversible gears lock them):

    x = [q, qdot, i] of the axis (joint side, armature current), u = armature voltage
    dx/dt ~= A (x - x0) + B (u - u0)

The operating point is an equilibrium (i0 makes the joint acceleration zero, u0 = R i0 + k_t N
qdot0 makes di/dt zero); the drive state follows from it and its efficiencies enter A. Transfer
functions (python-control): the current plant P_i = I/U with L_i = C_i P_i (Fig. 12), and the
velocity plant P_v = qdot/I_ref with the current loop closed, L_v = C_v P_v (Fig. 14), qdot
joint side as the paper's velocity gains are. docs/paper.md ("Linearisation") has the points.

Pure: no ROS, no files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import control as ct
import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq

from lca_sim.errors import LcaHilError
from lca_sim.model import kernel
from lca_sim.model.simulator import PlantState, Simulator
from lca_sim.model.state_machine import MotionState

FloatArray = npt.NDArray[np.float64]

# Relative central-difference steps; the state machine's boundaries are checked against them.
_REL_STEP = 1e-6


class LinearisationError(LcaHilError, ValueError):
    """No usable equilibrium or linear model at the requested operating point."""


@dataclass(frozen=True, slots=True)
class OperatingPoint:
    """A joint moving at constant velocity: where a linear model is taken.

    Attributes:
        position_rad: joint position (m for the lift).
        velocity_rad_s: joint velocity, nonzero (m/s for the lift).
    """

    position_rad: float
    velocity_rad_s: float

    @property
    def label(self) -> str:
        """A short legend label in degrees."""
        return (
            f"{math.degrees(self.position_rad):.0f} deg, "
            f"{math.degrees(self.velocity_rad_s):+.0f} deg/s"
        )


@dataclass(frozen=True, slots=True)
class LinearAxisModel:
    """The linearised axis at one operating point.

    Attributes:
        point: where it was taken.
        drive_state: the drive state of the equilibrium (its efficiencies are in `a`).
        current_a, voltage_v: the equilibrium armature current and voltage.
        a, b: dx/dt = a x + b u for x = [q, qdot, i], u = voltage (deviations from x0, u0).
    """

    point: OperatingPoint
    drive_state: str
    current_a: float
    voltage_v: float
    a: FloatArray
    b: FloatArray

    def current_plant(self) -> ct.TransferFunction:
        """P_i(s) = I(s) / U(s), A per V."""
        return ct.ss2tf(ct.ss(self.a, self.b, [[0.0, 0.0, 1.0]], [[0.0]]))

    def velocity_plant(self, current_kp_v_per_a: float, current_ti_s: float) -> ct.StateSpace:
        """P_v(s) = qdot(s) / I_ref(s), rad/s per A, with the current PI loop closed.

        The PI integral z (dz/dt = i_ref - i) joins the state; u = Kp (i_ref - i) + Kp/Ti z.
        """
        kp, ki = current_kp_v_per_a, current_kp_v_per_a / current_ti_s
        c_i = np.array([[0.0, 0.0, 1.0]])
        a_cl = np.block([[self.a - kp * self.b @ c_i, ki * self.b], [-c_i, np.zeros((1, 1))]])
        b_cl = np.vstack([kp * self.b, [[1.0]]])
        return ct.ss(a_cl, b_cl, [[0.0, 1.0, 0.0, 0.0]], [[0.0]])


def pi_transfer(kp: float, ti_s: float) -> ct.TransferFunction:
    """The paper's PI, G(s) = Kp (1 + 1 / (Ti s))."""
    return ct.tf([kp * ti_s, kp], [ti_s, 0.0])


def axis_moving_state(
    sim: Simulator, axis: int, position: float, velocity: float, current: float
) -> PlantState:
    """A plant state with only `axis` moving (in the direction of `velocity`), others at rest."""
    n = sim.n_axes
    q = [0.0] * n
    v = [0.0] * n
    i = [0.0] * n
    motion = [MotionState.STOP] * n
    q[axis], v[axis], i[axis] = position, velocity, current
    motion[axis] = MotionState.DIRECT if velocity > 0.0 else MotionState.REVERSE
    return PlantState(0.0, tuple(q), tuple(v), tuple(i), tuple(motion), tuple([0] * n))


def equilibrium_current(sim: Simulator, axis: int, point: OperatingPoint) -> float:
    """The armature current that holds `point`'s velocity (zero joint acceleration), A.

    Raises:
        LinearisationError: no current within the amplifier's range holds it (for instance
            where the drive state switches exactly at the equilibrium).
    """
    if point.velocity_rad_s == 0.0:
        raise LinearisationError(
            "an operating point needs a nonzero velocity (a stopped irreversible axis is "
            "locked and has no linear model)"
        )
    model = sim.model_array
    i_max = model[kernel.P_VOLTAGE_LIMIT_V, axis] / model[kernel.P_RESISTANCE_OHM, axis]
    zero = np.zeros(sim.n_axes)

    def acceleration(current: float) -> float:
        state = axis_moving_state(sim, axis, point.position_rad, point.velocity_rad_s, current)
        return float(sim.derivative(state, zero)[0][1, axis])

    lo, hi = acceleration(-i_max), acceleration(i_max)
    if not lo < 0.0 < hi:
        raise LinearisationError(
            f"{sim.axis_names[axis]} at {point.label}: no current within +-{i_max:g} A holds "
            "this velocity"
        )
    current = float(brentq(acceleration, -i_max, i_max, xtol=1e-12, rtol=1e-12))
    if abs(acceleration(current)) > 1e-6 * max(abs(lo), abs(hi)):
        raise LinearisationError(
            f"{sim.axis_names[axis]} at {point.label}: the acceleration jumps across zero "
            f"at {current:.4g} A (a drive-state boundary); pick another operating point"
        )
    return current


def linearise(sim: Simulator, axis: str, point: OperatingPoint) -> LinearAxisModel:
    """Linearise the full nonlinear model of `axis` around `point` by central differences.

    Raises:
        LinearisationError: no equilibrium, or the drive state changes inside the difference
            steps (the point sits on a state-machine boundary).
    """
    a_index = sim.axis_names.index(axis)
    current0 = equilibrium_current(sim, a_index, point)
    model = sim.model_array
    ratio = model[kernel.P_GEAR_RATIO, a_index]
    voltage0 = (
        model[kernel.P_RESISTANCE_OHM, a_index] * current0
        + model[kernel.P_TORQUE_CONSTANT, a_index] * ratio * point.velocity_rad_s
    )
    x0 = np.array([point.position_rad, point.velocity_rad_s, current0])
    scale = np.array([1.0, abs(point.velocity_rad_s), max(abs(current0), 1e-3)])
    steps = _REL_STEP * np.maximum(np.abs(x0), scale)

    def f(x: FloatArray, u: float) -> tuple[FloatArray, int]:
        state = axis_moving_state(sim, a_index, float(x[0]), float(x[1]), float(x[2]))
        volts = np.zeros(sim.n_axes)
        volts[a_index] = u
        dx, drive = sim.derivative(state, volts)
        return dx[:, a_index], drive[a_index]

    _, drive0 = f(x0, voltage0)
    a = np.empty((3, 3))
    for j in range(3):
        dx = np.zeros(3)
        dx[j] = steps[j]
        plus, d_plus = f(x0 + dx, voltage0)
        minus, d_minus = f(x0 - dx, voltage0)
        if d_plus != drive0 or d_minus != drive0:
            raise LinearisationError(
                f"{axis} at {point.label}: the drive state changes within the difference "
                "step (a state-machine boundary); pick another operating point"
            )
        a[:, j] = (plus - minus) / (2.0 * steps[j])
    du = _REL_STEP * max(abs(voltage0), 1.0)
    b = ((f(x0, voltage0 + du)[0] - f(x0, voltage0 - du)[0]) / (2.0 * du)).reshape(3, 1)
    return LinearAxisModel(
        point=point,
        drive_state=sim.state_names[drive0],
        current_a=current0,
        voltage_v=float(voltage0),
        a=a,
        b=b,
    )


def independence_frequency(
    omega_rad_s: FloatArray,
    responses: Sequence[npt.NDArray[np.complex128]],
    tolerance_db: float = 1.0,
    tolerance_deg: float = 5.0,
) -> float:
    """The lowest frequency above which all responses agree (Figs 12 and 14).

    Returns the smallest grid frequency from which on the spread of the magnitudes stays
    within `tolerance_db` and that of the phases within `tolerance_deg`; NaN if they never do.
    """
    stacked = np.vstack([np.asarray(r) for r in responses])
    mag_db = 20.0 * np.log10(np.abs(stacked))
    phase_deg = np.degrees(np.unwrap(np.angle(stacked), axis=1))
    # Phases may differ by whole turns from the unwrapping; compare modulo 360.
    phase_deg -= 360.0 * np.round((phase_deg - phase_deg[:1]) / 360.0)
    spread_ok = (np.ptp(mag_db, axis=0) <= tolerance_db) & (
        np.ptp(phase_deg, axis=0) <= tolerance_deg
    )
    bad = np.nonzero(~spread_ok)[0]
    if len(bad) == 0:
        return float(omega_rad_s[0])
    if bad[-1] == len(omega_rad_s) - 1:
        return math.nan
    return float(omega_rad_s[bad[-1] + 1])


# The operating points of Figs 12 and 14 here: the pivot at +-7 deg/s (the speed of Figs 4-5)
# across its range, on both sides of the motor-driving -> load-driving switch near 55 deg.
DEFAULT_POSITIONS_DEG: tuple[float, ...] = (10.0, 30.0, 45.0, 65.0, 80.0, 100.0)
DEFAULT_SPEED_DEG_S = 7.0


def linearise_points(
    sim: Simulator, axis: str = "pivot", points: Sequence[OperatingPoint] | None = None
) -> list[LinearAxisModel]:
    """The axis linearised at `points` (the default operating points if None)."""
    return [linearise(sim, axis, p) for p in (points or default_operating_points())]


def default_operating_points() -> tuple[OperatingPoint, ...]:
    """Constant-velocity points in both directions across the pivot's range."""
    return tuple(
        OperatingPoint(math.radians(p), math.radians(sign * DEFAULT_SPEED_DEG_S))
        for sign in (1.0, -1.0)
        for p in DEFAULT_POSITIONS_DEG
    )


@dataclass(frozen=True, slots=True)
class LoopMargins:
    """Stability margins of one open loop.

    Attributes:
        crossover_rad_s: gain crossover (|L| = 1).
        phase_margin_deg: phase margin at the crossover (continuous loop).
        gain_margin_db: the gain increase that destabilises (inf if the phase does not cross
            -180 deg above the crossover).
        sampled_phase_margin_deg: the phase margin left once the loop's delay is accounted
            for: `delay_s` (by default a sample period T's zero-order hold, T/2); equal to the
            continuous one when there is no delay.
        delay_s: that delay, s.
    """

    crossover_rad_s: float
    phase_margin_deg: float
    gain_margin_db: float
    sampled_phase_margin_deg: float
    delay_s: float = 0.0

    def phase_margin_with_delay_deg(self, delay_s: float) -> float:
        """The phase margin with a pure delay of `delay_s` in the loop, deg.

        A delay e^(-s tau) leaves |L| and so the crossover as they are and takes wc tau rad of
        phase there (the gain margin does move: not computed here).
        """
        return self.phase_margin_deg - math.degrees(self.crossover_rad_s * delay_s)


def loop_margins(
    loop: ct.LTI, sample_period_s: float = 0.0, delay_periods: float = 0.5
) -> LoopMargins:
    """Margins of an open loop (python-control), with its delay in sample periods.

    `delay_periods` x `sample_period_s` is the time from a sample to the command's effect,
    hold included: 0.5 for a zero-order hold; 1.5 over a synchronous CAN drive (a torque sent
    before SYNC k acts after it, then is held a period).
    """
    gm, pm, _, wpc, wgc, _ = ct.stability_margins(loop, returnall=True)
    gm, pm, wpc, wgc = (np.atleast_1d(np.asarray(x, dtype=float)) for x in (gm, pm, wpc, wgc))
    if len(wgc) == 0:
        return LoopMargins(math.nan, math.nan, math.inf, math.nan)
    k = int(np.argmax(wgc))  # the highest crossover is the one that sets the bandwidth
    crossover, phase_margin = float(wgc[k]), float(pm[k])
    above = [g for g, w in zip(gm, wpc, strict=True) if w > crossover and g > 1.0]
    gain_margin_db = 20.0 * math.log10(min(above)) if above else math.inf
    delay_s = delay_periods * sample_period_s
    delay_deg = math.degrees(crossover * delay_s)
    return LoopMargins(crossover, phase_margin, gain_margin_db, phase_margin - delay_deg, delay_s)


@dataclass(frozen=True, slots=True)
class PointLoops:
    """The cascade's two open loops at one operating point, with their margins.

    Attributes:
        model: the linearised axis there.
        current_loop: C_i(s) P_i(s), the current loop open.
        velocity_loop: C_v(s) P_v(s), the velocity loop open around the closed current loop.
        current, velocity: their margins, with the sample-and-hold of the rate each runs at.
    """

    model: LinearAxisModel
    current_loop: ct.LTI
    velocity_loop: ct.LTI
    current: LoopMargins
    velocity: LoopMargins


def cascade_loops(
    models: Sequence[LinearAxisModel],
    current_gains: tuple[float, float],
    velocity_gains: tuple[float, float],
    current_period_s: float,
    velocity_period_s: float,
    velocity_delay_periods: float = 0.5,
) -> tuple[PointLoops, ...]:
    """Both open loops of the cascade at every model, for (Kp, Ti) gains of each PI (section 6).

    `current_period_s` and `velocity_period_s` are the rates the loops run at (the drive's model
    step, the controller's period), for the sampled phase margins; `velocity_delay_periods` is
    the velocity loop's delay in its periods (`loop_margins`; the current loop's is a hold).
    """
    c_i = pi_transfer(*current_gains)
    c_v = pi_transfer(*velocity_gains)
    loops = []
    for m in models:
        current_loop = c_i * m.current_plant()
        velocity_loop = c_v * m.velocity_plant(*current_gains)
        loops.append(
            PointLoops(
                model=m,
                current_loop=current_loop,
                velocity_loop=velocity_loop,
                current=loop_margins(current_loop, current_period_s),
                velocity=loop_margins(velocity_loop, velocity_period_s, velocity_delay_periods),
            )
        )
    return tuple(loops)
