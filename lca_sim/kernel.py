"""The compiled drive-chain step: electrics, state machine, eq. (10) solve, stick/slip integration.

This is the hot path of the simulator, compiled with numba so that one 4-axis step (with the two
Pinocchio calls that feed it) costs about as much as a MuJoCo step of the same gantry. The code is
plain Python over floats and small arrays: `NUMBA_DISABLE_JIT=1` runs it uncompiled, unchanged.

Arrays are laid out by named rows so the kernel takes few arguments (numba's call overhead grows
with each one):

* `params[P_*, axis]`: per-axis constants, motor side, SI.
* `state[X_*, axis]`: joint position (rad or m), joint velocity, armature current (A).
* `modes[Z_*, axis]`: motion state (0 stop, +1 direct, -1 reverse) and drive-state index.
* `signals[S_*, axis]`: what the step exposes (torques, efficiencies, powers).
* `eta[axis, direction, rule, k]`: eq. (10) coefficients, direction 0 = DIRECT, 1 = REVERSE,
  k 0 = eta_m, 1 = eta_l.
* `rules[rule, c]`: the moving-state table (motor, load, dominant condition codes).

Sign conventions (docs/model.md): tau_m is the motor torque, tau_l = N^-1 (C qdot + Q) the torque
the load demands at the motor shaft (eq. 8), both positive in the direct direction.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Rows of `params`.
P_GEAR_RATIO = 0
P_RESISTANCE_OHM = 1
P_INDUCTANCE_H = 2
P_TORQUE_CONSTANT = 3
P_ROTOR_INERTIA = 4
P_VOLTAGE_LIMIT_V = 5
P_STATIC_DIRECT = 6
P_STATIC_REVERSE = 7
P_COULOMB_DIRECT = 8
P_COULOMB_REVERSE = 9
P_VISCOUS_DIRECT = 10
P_VISCOUS_REVERSE = 11
P_POSITION_MIN = 12
P_POSITION_MAX = 13
P_VELOCITY_EPS = 14
P_TORQUE_EPS = 15
N_PARAMS = 16

# Rows of `state`.
X_POSITION = 0
X_VELOCITY = 1
X_CURRENT = 2
N_STATE = 3

# Rows of `modes`.
Z_MOTION = 0
Z_DRIVE = 1
N_MODES = 2

# Rows of `signals`.
S_MOTOR_VELOCITY = 0
S_CURRENT = 1
S_VOLTAGE = 2
S_MOTOR_TORQUE = 3
S_LOAD_TORQUE = 4
S_FRICTION_TORQUE = 5
S_ETA_M = 6
S_ETA_L = 7
S_MOTOR_POWER = 8
S_LOAD_POWER = 9
S_GEAR_LOSS = 10
S_FRICTION_LOSS = 11
S_ELECTRICAL_POWER = 12
S_COPPER_LOSS = 13
S_MOTOR_ACCELERATION = 14
N_SIGNALS = 15

# Drive-state indices inside STOP (state_machine.StopState); moving states start at 4.
STOP_HOLD = 0
STOP_MOTOR_DIRECT = 1
STOP_MOTOR_REVERSE = 2
STOP_END_STOP = 3
FIRST_MOVING = 4

# Return codes.
OK = 0
BAD_INPUT = 1


@njit(cache=True)
def classify(direction: int, tau_m: float, tau_l: float, rules: np.ndarray) -> int:
    """Lower-level state of a moving axis (Fig. 8 and its mirror): the first matching rule.

    Args:
        direction: +1 in DIRECT, -1 in REVERSE motion.
        tau_m: motor torque, N m.
        tau_l: load torque demanded at the motor shaft, N m (eq. 8).
        rules: int array [n_rules, 3] of (motor, load, dominant) condition codes.

    Returns:
        The index of the matching rule (the config guarantees one matches).

    """
    motor = 1 if direction * tau_m > 0.0 else 2
    load = 1 if -direction * tau_l > 0.0 else 2
    dominant = 2 if abs(tau_m) < abs(tau_l) else 1
    for r in range(rules.shape[0]):
        if (
            (rules[r, 0] == 0 or rules[r, 0] == motor)
            and (rules[r, 1] == 0 or rules[r, 1] == load)
            and (rules[r, 2] == 0 or rules[r, 2] == dominant)
        ):
            return r
    return -1


@njit(cache=True)
def velocity_friction(direction: int, w_m: float, params: np.ndarray, a: int) -> float:
    """Eq. (4): Coulomb plus viscous friction of a moving axis, N m, motor side.

    The branch follows the motion state rather than the sign of w_m, so an axis that has just
    broken away (w_m still 0) already feels its sliding friction.
    """
    if direction > 0:
        return float(params[P_COULOMB_DIRECT, a] + params[P_VISCOUS_DIRECT, a] * w_m)
    return float(-params[P_COULOMB_REVERSE, a] + params[P_VISCOUS_REVERSE, a] * w_m)


@njit(cache=True)
def static_friction(tau_m: float, params: np.ndarray, a: int) -> float:
    """Eq. (3): the static friction torque of a stopped axis, N m, motor side."""
    if tau_m > 0.0:
        return min(tau_m, float(params[P_STATIC_DIRECT, a]))
    if tau_m < 0.0:
        return max(tau_m, -float(params[P_STATIC_REVERSE, a]))
    return 0.0


@njit(cache=True)
def _solve_moving(
    inertia: np.ndarray, moving: np.ndarray, rhs: np.ndarray, acc: np.ndarray
) -> None:
    """Solve inertia[M, M] acc[M] = rhs[M] for the moving axes M by Cholesky; acc = 0 elsewhere."""
    n = inertia.shape[0]
    idx = np.empty(n, dtype=np.int64)
    k = 0
    for a in range(n):
        acc[a] = 0.0
        if moving[a]:
            idx[k] = a
            k += 1
    if k == 0:
        return
    low = np.zeros((k, k))
    for r in range(k):
        for c in range(r + 1):
            s = inertia[idx[r], idx[c]]
            for j in range(c):
                s -= low[r, j] * low[c, j]
            if r == c:
                low[r, r] = math.sqrt(s)
            else:
                low[r, c] = s / low[c, c]
    y = np.empty(k)
    for r in range(k):
        s = rhs[idx[r]]
        for j in range(r):
            s -= low[r, j] * y[j]
        y[r] = s / low[r, r]
    for r in range(k - 1, -1, -1):
        s = y[r]
        for j in range(r + 1, k):
            s -= low[j, r] * acc[idx[j]]
        acc[idx[r]] = s / low[r, r]


@njit(cache=True)
def step(
    mass_matrix: np.ndarray,
    nonlinear_effects: np.ndarray,
    voltage_cmd_v: np.ndarray,
    state: np.ndarray,
    modes: np.ndarray,
    params: np.ndarray,
    rules: np.ndarray,
    eta: np.ndarray,
    irreversible: bool,
    dt_s: float,
    signals: np.ndarray,
) -> int:
    """Advance all axes by one fixed step dt_s, in place.

    Args:
        mass_matrix: A(q), joint side; only the upper triangle is read (Pinocchio's crba).
        nonlinear_effects: C(q, qdot) qdot + Q(q), joint side (Pinocchio's nonLinearEffects).
        voltage_cmd_v: amplifier voltage commands, saturated here at the voltage limit.
        state, modes, signals: see the module docstring; updated in place.
        params, rules, eta: see the module docstring.
        irreversible: the STOP state is irreversible (the load alone cannot start motion).
        dt_s: the step, s.

    Returns:
        OK, or BAD_INPUT (nothing changed) when a command is NaN or infinite.

    """
    n = state.shape[1]
    for a in range(n):
        if not math.isfinite(voltage_cmd_v[a]):
            return BAD_INPUT

    # Motor side quantities (eq. 8): w_m = N qdot, tau_l = N^-1 (C qdot + Q),
    # J = J_m + N^-1 A(q) N^-1 (the coupled inertia of eq. 9-10, off-diagonal terms kept).
    w = np.empty(n)
    tau_l = np.empty(n)
    tau_m = np.empty(n)
    volt = np.empty(n)
    inertia = np.empty((n, n))
    for a in range(n):
        ratio = params[P_GEAR_RATIO, a]
        w[a] = ratio * state[X_VELOCITY, a]
        tau_l[a] = nonlinear_effects[a] / ratio
        for b in range(n):
            m_ab = mass_matrix[a, b] if a <= b else mass_matrix[b, a]
            inertia[a, b] = m_ab / (ratio * params[P_GEAR_RATIO, b])
        inertia[a, a] += params[P_ROTOR_INERTIA, a]

    # Electrics: L di/dt = v - R i - k w, integrated exactly over the step with w held, so the
    # electrical time constant (about 1 ms) never limits dt.
    for a in range(n):
        limit = params[P_VOLTAGE_LIMIT_V, a]
        v_sat = min(max(voltage_cmd_v[a], -limit), limit)
        volt[a] = v_sat
        k_t = params[P_TORQUE_CONSTANT, a]
        r_ohm = params[P_RESISTANCE_OHM, a]
        i_ss = (v_sat - k_t * w[a]) / r_ohm
        decay = math.exp(-r_ohm * dt_s / params[P_INDUCTANCE_H, a])
        state[X_CURRENT, a] = i_ss + (state[X_CURRENT, a] - i_ss) * decay
        tau_m[a] = k_t * state[X_CURRENT, a]

    # Lower level of moving axes and the right-hand side of eq. (10):
    # J qddot_m = eta_m tau_m - eta_l tau_l - tau_fv.
    moving = np.zeros(n, dtype=np.bool_)
    rhs = np.zeros(n)
    eta_m = np.full(n, np.nan)
    eta_l = np.full(n, np.nan)
    tau_fv = np.zeros(n)
    for a in range(n):
        d = modes[Z_MOTION, a]
        if d != 0:
            moving[a] = True
            rule = classify(d, tau_m[a], tau_l[a], rules)
            k = 0 if d > 0 else 1
            eta_m[a] = eta[a, k, rule, 0]
            eta_l[a] = eta[a, k, rule, 1]
            modes[Z_DRIVE, a] = FIRST_MOVING + rule
            tau_fv[a] = velocity_friction(d, w[a], params, a)
            rhs[a] = eta_m[a] * tau_m[a] - eta_l[a] * tau_l[a] - tau_fv[a]

    # Solve the moving axes with the stopped ones locked, then test each stopped axis for
    # breakaway against the reaction of the moving ones; repeat while any axis starts.
    acc = np.zeros(n)
    for _ in range(n + 1):
        _solve_moving(inertia, moving, rhs, acc)
        started = False
        for a in range(n):
            if moving[a]:
                continue
            coupling = 0.0
            for b in range(n):
                coupling += inertia[a, b] * acc[b]
            if irreversible:
                # Fig. 7: only the motor can start the motion.
                if abs(tau_m[a]) <= params[P_TORQUE_EPS, a]:
                    continue
                d = 1 if tau_m[a] > 0.0 else -1
            else:
                net_free = tau_m[a] - tau_l[a] - coupling
                if net_free == 0.0:
                    continue
                d = 1 if net_free > 0.0 else -1
            q = state[X_POSITION, a]
            if (d > 0 and q >= params[P_POSITION_MAX, a]) or (
                d < 0 and q <= params[P_POSITION_MIN, a]
            ):
                continue
            rule = classify(d, tau_m[a], tau_l[a], rules)
            k = 0 if d > 0 else 1
            e_m = eta[a, k, rule, 0]
            e_l = eta[a, k, rule, 1]
            net = e_m * tau_m[a] - e_l * tau_l[a] - coupling
            breakaway = params[P_STATIC_DIRECT, a] if d > 0 else params[P_STATIC_REVERSE, a]
            if d * net > breakaway:
                moving[a] = True
                started = True
                modes[Z_MOTION, a] = d
                modes[Z_DRIVE, a] = FIRST_MOVING + rule
                eta_m[a] = e_m
                eta_l[a] = e_l
                tau_fv[a] = velocity_friction(d, 0.0, params, a)
                rhs[a] = e_m * tau_m[a] - e_l * tau_l[a] - tau_fv[a]
        if not started:
            break

    # Integrate (semi-implicit Euler). A moving axis whose velocity would cross zero, or that
    # decelerates inside the V_eps band, stops exactly: it is then locked (no drift) until a
    # breakaway, and breakaway needs static >= Coulomb friction, so it cannot chatter.
    for a in range(n):
        ratio = params[P_GEAR_RATIO, a]
        d = modes[Z_MOTION, a]
        w_new = 0.0
        if d != 0:
            w_new = w[a] + acc[a] * dt_s
            if d * w_new <= 0.0 or (abs(w_new) < params[P_VELOCITY_EPS, a] and d * acc[a] < 0.0):
                t_stop = dt_s
                if d * w_new <= 0.0 and acc[a] != 0.0:
                    t_stop = min(dt_s, max(0.0, -w[a] / acc[a]))
                state[X_POSITION, a] += 0.5 * w[a] * t_stop / ratio
                w_new = 0.0
                modes[Z_MOTION, a] = 0
            else:
                state[X_POSITION, a] += w_new * dt_s / ratio
        q = state[X_POSITION, a]
        if q > params[P_POSITION_MAX, a] or q < params[P_POSITION_MIN, a]:
            state[X_POSITION, a] = min(max(q, params[P_POSITION_MIN, a]), params[P_POSITION_MAX, a])
            w_new = 0.0
            modes[Z_MOTION, a] = 0
        state[X_VELOCITY, a] = w_new / ratio

        friction = tau_fv[a]
        if modes[Z_MOTION, a] == 0:
            q = state[X_POSITION, a]
            eps = params[P_TORQUE_EPS, a]
            if (q >= params[P_POSITION_MAX, a] and tau_m[a] > eps) or (
                q <= params[P_POSITION_MIN, a] and tau_m[a] < -eps
            ):
                modes[Z_DRIVE, a] = STOP_END_STOP
            elif abs(tau_m[a]) <= eps:
                modes[Z_DRIVE, a] = STOP_HOLD
            elif tau_m[a] > 0.0:
                modes[Z_DRIVE, a] = STOP_MOTOR_DIRECT
            else:
                modes[Z_DRIVE, a] = STOP_MOTOR_REVERSE
            eta_m[a] = np.nan
            eta_l[a] = np.nan
            friction = static_friction(tau_m[a], params, a)

        i_a = state[X_CURRENT, a]
        signals[S_MOTOR_VELOCITY, a] = w_new
        signals[S_CURRENT, a] = i_a
        signals[S_VOLTAGE, a] = volt[a]
        signals[S_MOTOR_TORQUE, a] = tau_m[a]
        signals[S_LOAD_TORQUE, a] = tau_l[a]
        signals[S_FRICTION_TORQUE, a] = friction
        signals[S_ETA_M, a] = eta_m[a]
        signals[S_ETA_L, a] = eta_l[a]
        signals[S_MOTOR_POWER, a] = tau_m[a] * w_new
        signals[S_LOAD_POWER, a] = tau_l[a] * w_new
        if w_new != 0.0:
            signals[S_GEAR_LOSS, a] = (1.0 - eta_m[a]) * tau_m[a] * w_new + (
                eta_l[a] - 1.0
            ) * tau_l[a] * w_new
            signals[S_FRICTION_LOSS, a] = tau_fv[a] * w_new
        else:
            signals[S_GEAR_LOSS, a] = 0.0
            signals[S_FRICTION_LOSS, a] = 0.0
        signals[S_ELECTRICAL_POWER, a] = volt[a] * i_a
        signals[S_COPPER_LOSS, a] = params[P_RESISTANCE_OHM, a] * i_a * i_a
        signals[S_MOTOR_ACCELERATION, a] = acc[a]
    return OK
