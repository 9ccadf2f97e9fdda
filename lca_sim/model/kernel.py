"""The compiled drive-chain step: electrics, state machine, eq. (10) solve, stick/slip integration.

The simulator's hot path, compiled with numba; plain Python over floats and small arrays, so
`NUMBA_DISABLE_JIT=1` runs it unchanged. Every argument and allocation costs in numba, so the
step takes two packed arrays built once per simulator: `model[row, axis]` (read only, from
`pack_model`: rows `P_*`, the rule table `rule_code`, the eq. (10) coefficients `eta_row`) and
`work[row, axis]` (`X_*` the state, `S_*` what a step exposes, then scratch rows).
Sign conventions, the load-sign band `P_LOAD_TORQUE_BAND` and the call path: docs/model.md,
sections 1, 4 and 5.

Over the size budget: the row layout of `model` and `work` and the compiled functions that index
them are one unit; numba compiles each entry point with every function it calls, and split
modules would share the row constants across imports without making any part readable alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt
from numba import config as numba_config
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic
from numba.np.numpy_support import carray, farray

from lca_sim.errors import InvalidValueError
from lca_sim.model import code_version, rigid_body

FloatArray = npt.NDArray[np.float64]

# Rows of `model`: per-axis constants.
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
P_LOAD_TORQUE_BAND = 16  # |tau_l| up to this counts as zero in Fig. 8 (load_torque_band_nm)
N_PARAMS = 17
# Rows of `model` after the constants.
P_IRREVERSIBLE = 17
P_N_RULES = 18
P_RULES = 19  # 3 rows per rule (motor, load, dominant codes), then 4 rows per rule of eta

# Rows of `work`: the state.
X_POSITION = 0
X_VELOCITY = 1
X_CURRENT = 2
X_MOTION = 3
X_DRIVE = 4
N_STATE = 5
# Rows of `work`: the signals a step exposes.
S_MOTOR_VELOCITY = 5
S_CURRENT = 6
S_VOLTAGE = 7
S_MOTOR_TORQUE = 8
S_LOAD_TORQUE = 9
S_FRICTION_TORQUE = 10
S_ETA_M = 11
S_ETA_L = 12
S_MOTOR_POWER = 13
S_LOAD_POWER = 14
S_GEAR_LOSS = 15
S_FRICTION_LOSS = 16
S_ELECTRICAL_POWER = 17
S_COPPER_LOSS = 18
S_MOTOR_ACCELERATION = 19
FIRST_SIGNAL = 5
N_SIGNALS = 15
# Rows of `work`: scratch.
W_OMEGA = 20
W_TAU_L = 21
W_TAU_M = 22
W_RHS = 23
W_TAU_FV = 24
W_ACC = 25
W_MOVING = 26
W_INDEX = 27
W_SOLVE = 28
W_TAU_L_STATE = 29  # tau_l as the state machine reads it: 0.0 inside the sign band
W_INERTIA = 30  # n rows: the motor-side inertia J = J_m + N^-1 A N^-1


def work_rows(n_axes: int) -> int:
    """Rows of the `work` array for n axes (state, signals, scratch, two n x n blocks)."""
    return W_INERTIA + 2 * n_axes


# Drive-state indices inside STOP (state_machine.StopState); moving states start at 4.
STOP_HOLD = 0
STOP_MOTOR_DIRECT = 1
STOP_MOTOR_REVERSE = 2
STOP_END_STOP = 3
FIRST_MOVING = 4

# Return codes.
OK = 0
BAD_INPUT = 1
# `step_in_frame` was loaded from numba's cache compiled against another `rigid_body` than the
# one running (its cache is keyed on kernel.py alone): nothing was touched; recompile it.
STALE_CODE = 2


@njit(cache=True)
def rule_code(model: FloatArray, rule: int, condition: int) -> int:
    """Condition code (0 any, 1 drives/motor, 2 brakes/resists/load) of one rule."""
    return int(model[P_RULES + 3 * rule + condition, 0])


@njit(cache=True)
def eta_row(n_rules: int, direction: int, rule: int, which: int) -> int:
    """Row of `model` holding eta_m (which = 0) or eta_l (1) of a rule in a direction (+1/-1)."""
    k = 0 if direction > 0 else 1
    return P_RULES + 3 * n_rules + 4 * rule + 2 * k + which


def pack_model(
    params: FloatArray,
    rules: npt.NDArray[np.int64],
    eta: FloatArray,
    irreversible: bool,
) -> FloatArray:
    """Pack per-axis constants, the rule table and the efficiencies into one `model` array.

    Args:
        params: [N_PARAMS, n] constants, rows `P_*`.
        rules: [n_rules, 3] condition codes (motor, load, dominant), shared by all axes.
        eta: [n, 2, n_rules, 2] coefficients: axis, direction (0 direct, 1 reverse), rule,
            (eta_m, eta_l).
        irreversible: the STOP state is irreversible (Fig. 7).
    """
    n_axes = params.shape[1]
    n_rules = rules.shape[0]
    model = np.zeros((P_RULES + 7 * n_rules, n_axes))
    model[:N_PARAMS] = params
    model[P_IRREVERSIBLE] = 1.0 if irreversible else 0.0
    model[P_N_RULES] = n_rules
    for r in range(n_rules):
        for c in range(3):
            model[P_RULES + 3 * r + c] = rules[r, c]
        for k, direction in enumerate((1, -1)):
            for which in range(2):
                model[eta_row(n_rules, direction, r, which)] = eta[:, k, r, which]
    return model


@njit(cache=True)
def classify(direction: int, tau_m: float, tau_l: float, model: FloatArray) -> int:
    """Lower-level state of a moving axis (Fig. 8 and its mirror): the first matching rule.

    Args:
        direction: +1 in DIRECT, -1 in REVERSE motion.
        tau_m: motor torque, N m.
        tau_l: load torque demanded at the motor shaft, N m (eq. 8); the step passes 0.0 for a
            load inside the axis's sign band (`_select_state`), this function reads exact signs.
        model: the packed model (its rule table).

    Returns:
        The index of the matching rule (the config guarantees one matches).
    """
    motor = 1 if direction * tau_m > 0.0 else 2
    load = 1 if -direction * tau_l > 0.0 else 2
    dominant = 2 if abs(tau_m) < abs(tau_l) else 1
    for r in range(int(model[P_N_RULES, 0])):
        m_code = rule_code(model, r, 0)
        l_code = rule_code(model, r, 1)
        d_code = rule_code(model, r, 2)
        if (
            (m_code == 0 or m_code == motor)
            and (l_code == 0 or l_code == load)
            and (d_code == 0 or d_code == dominant)
        ):
            return r
    return -1


@njit(cache=True)
def velocity_friction(direction: int, w_m: float, model: FloatArray, a: int) -> float:
    """Eq. (4): Coulomb plus viscous friction of a moving axis, N m, motor side.

    The branch follows the motion state rather than the sign of w_m, so an axis that has just
    broken away (w_m still 0) already feels its sliding friction.
    """
    if direction > 0:
        return float(model[P_COULOMB_DIRECT, a] + model[P_VISCOUS_DIRECT, a] * w_m)
    return float(-model[P_COULOMB_REVERSE, a] + model[P_VISCOUS_REVERSE, a] * w_m)


@njit(cache=True)
def static_friction(tau_m: float, model: FloatArray, a: int) -> float:
    """Eq. (3): the static friction torque of a stopped axis, N m, motor side."""
    if tau_m > 0.0:
        return min(tau_m, float(model[P_STATIC_DIRECT, a]))
    if tau_m < 0.0:
        return max(tau_m, -float(model[P_STATIC_REVERSE, a]))
    return 0.0


# The two compiled functions below stay above ruff's complexity limit (C901) on purpose: they
# are the hot path of every run (bench/model_step.py: a full 4-axis step, the rigid-body terms
# included, is about 1.05 us here), and the step's branches follow eq. (3)-(10) and Figs 6-8 in
# the order the docstrings cite them; a split would trade that reading order and re-measured
# speed for a lower count.
@njit(cache=True)
def _solve_moving(work: FloatArray, n: int) -> None:  # noqa: C901
    """Solve J[M, M] acc[M] = rhs[M] for the moving axes M by Cholesky; acc = 0 elsewhere.

    J is the inertia block of `work`; the factor goes to the n rows after it.
    """
    acc = work[W_ACC]
    rhs = work[W_RHS]
    idx = work[W_INDEX]
    y = work[W_SOLVE]
    low = work[W_INERTIA + n : W_INERTIA + 2 * n]
    k = 0
    for a in range(n):
        acc[a] = 0.0
        if work[W_MOVING, a] != 0.0:
            idx[k] = a
            k += 1
    for r in range(k):
        ir = int(idx[r])
        for c in range(r + 1):
            s = work[W_INERTIA + ir, int(idx[c])]
            for j in range(c):
                s -= low[r, j] * low[c, j]
            if r == c:
                low[r, r] = math.sqrt(s)
            else:
                low[r, c] = s / low[c, c]
    for r in range(k):
        s = rhs[int(idx[r])]
        for j in range(r):
            s -= low[r, j] * y[j]
        y[r] = s / low[r, r]
    for r in range(k - 1, -1, -1):
        s = y[r]
        for j in range(r + 1, k):
            s -= low[j, r] * acc[int(idx[j])]
        acc[int(idx[r])] = s / low[r, r]


@njit(cache=True)
def _select_state(work: FloatArray, model: FloatArray, a: int, direction: int) -> int:
    """Pick the moving state of axis a for a direction and set its eta_m, eta_l signals.

    The load torque it classifies is `W_TAU_L_STATE`: tau_l, or exactly 0.0 inside the axis's
    sign band (|tau_l| <= P_LOAD_TORQUE_BAND), where tau_l is a rounding residue on an axis
    without a gravity load and Fig. 8's states, which do not meet at tau_l = 0, would follow
    its random sign (state_machine.load_torque_band_nm). Only the choice of state sees the band:
    eq. (10) keeps the real tau_l (`W_TAU_L`), and the state a zero load picks has eta_l = 1
    (eq. 11, checked on load), so the band neither creates nor burns energy.
    """
    tau_m = work[W_TAU_M, a]
    tau_l = work[W_TAU_L_STATE, a]
    n_rules = int(model[P_N_RULES, 0])
    rule = classify(direction, tau_m, tau_l, model)
    eta_m = model[eta_row(n_rules, direction, rule, 0), a]
    eta_l = model[eta_row(n_rules, direction, rule, 1), a]
    work[S_ETA_M, a] = eta_m
    work[S_ETA_L, a] = eta_l
    return rule


@njit(cache=True)
def step(  # noqa: C901  (the compiled step; see the note above _solve_moving)
    mass_matrix: FloatArray,
    nonlinear_effects: FloatArray,
    voltage_cmd_v: FloatArray,
    work: FloatArray,
    model: FloatArray,
    dt_s: float,
) -> int:
    """Advance all axes by one fixed step dt_s, in place in `work`.

    Args:
        mass_matrix: A(q), joint side; only the upper triangle is read (`rigid_body.terms`,
            or Pinocchio's crba, which fills no more).
        nonlinear_effects: C(q, qdot) qdot + Q(q), joint side.
        voltage_cmd_v: amplifier voltage commands, saturated here at the voltage limit.
        work: state, signals and scratch (module docstring); updated in place.
        model: packed constants (`pack_model`).
        dt_s: the step, s. Zero evaluates the signals of the current state without moving.

    Returns:
        OK, or BAD_INPUT (nothing changed) when a command is NaN or infinite.
    """
    n = work.shape[1]
    for a in range(n):
        if not math.isfinite(voltage_cmd_v[a]):
            return BAD_INPUT
    irreversible = model[P_IRREVERSIBLE, 0] != 0.0

    # Motor side quantities (eq. 8): w_m = N qdot, tau_l = N^-1 (C qdot + Q),
    # J = J_m + N^-1 A(q) N^-1 (the coupled inertia of eq. 9-10, off-diagonal terms kept).
    # The state machine reads tau_l through the sign band, set aside here once per step: in
    # _select_state, called for every moving axis, the same test cost a tenth of the kernel.
    for a in range(n):
        ratio = model[P_GEAR_RATIO, a]
        work[W_OMEGA, a] = ratio * work[X_VELOCITY, a]
        tau_l = nonlinear_effects[a] / ratio
        work[W_TAU_L, a] = tau_l
        work[W_TAU_L_STATE, a] = tau_l if abs(tau_l) > model[P_LOAD_TORQUE_BAND, a] else 0.0
        for b in range(n):
            m_ab = mass_matrix[a, b] if a <= b else mass_matrix[b, a]
            work[W_INERTIA + a, b] = m_ab / (ratio * model[P_GEAR_RATIO, b])
        work[W_INERTIA + a, a] += model[P_ROTOR_INERTIA, a]

    # Electrics: L di/dt = v - R i - k w, integrated exactly over the step with w held, so the
    # electrical time constant (about 1 ms) never limits dt.
    for a in range(n):
        limit = model[P_VOLTAGE_LIMIT_V, a]
        v_sat = min(max(voltage_cmd_v[a], -limit), limit)
        work[S_VOLTAGE, a] = v_sat
        k_t = model[P_TORQUE_CONSTANT, a]
        r_ohm = model[P_RESISTANCE_OHM, a]
        i_ss = (v_sat - k_t * work[W_OMEGA, a]) / r_ohm
        decay = math.exp(-r_ohm * dt_s / model[P_INDUCTANCE_H, a])
        work[X_CURRENT, a] = i_ss + (work[X_CURRENT, a] - i_ss) * decay
        work[W_TAU_M, a] = k_t * work[X_CURRENT, a]

    # Lower level of moving axes and the right-hand side of eq. (10):
    # J qddot_m = eta_m tau_m - eta_l tau_l - tau_fv.
    for a in range(n):
        d = int(work[X_MOTION, a])
        work[W_MOVING, a] = 0.0
        work[W_RHS, a] = 0.0
        work[W_TAU_FV, a] = 0.0
        work[S_ETA_M, a] = np.nan
        work[S_ETA_L, a] = np.nan
        if d != 0:
            work[W_MOVING, a] = 1.0
            rule = _select_state(work, model, a, d)
            work[X_DRIVE, a] = FIRST_MOVING + rule
            work[W_TAU_FV, a] = velocity_friction(d, work[W_OMEGA, a], model, a)
            work[W_RHS, a] = (
                work[S_ETA_M, a] * work[W_TAU_M, a]
                - work[S_ETA_L, a] * work[W_TAU_L, a]
                - work[W_TAU_FV, a]
            )

    # Solve the moving axes with the stopped ones locked, then test each stopped axis for
    # breakaway against the reaction of the moving ones; repeat while any axis starts.
    for _ in range(n + 1):
        _solve_moving(work, n)
        started = False
        for a in range(n):
            if work[W_MOVING, a] != 0.0:
                continue
            tau_m = work[W_TAU_M, a]
            tau_l = work[W_TAU_L, a]
            coupling = 0.0
            for b in range(n):
                coupling += work[W_INERTIA + a, b] * work[W_ACC, b]
            if irreversible:
                # Fig. 7: only the motor can start the motion.
                if abs(tau_m) <= model[P_TORQUE_EPS, a]:
                    continue
                d = 1 if tau_m > 0.0 else -1
            else:
                net_free = tau_m - tau_l - coupling
                if net_free == 0.0:
                    continue
                d = 1 if net_free > 0.0 else -1
            q = work[X_POSITION, a]
            if (d > 0 and q >= model[P_POSITION_MAX, a]) or (
                d < 0 and q <= model[P_POSITION_MIN, a]
            ):
                continue
            rule = _select_state(work, model, a, d)
            net = work[S_ETA_M, a] * tau_m - work[S_ETA_L, a] * tau_l - coupling
            breakaway = model[P_STATIC_DIRECT, a] if d > 0 else model[P_STATIC_REVERSE, a]
            if d * net > breakaway:
                started = True
                work[W_MOVING, a] = 1.0
                work[X_MOTION, a] = d
                work[X_DRIVE, a] = FIRST_MOVING + rule
                work[W_TAU_FV, a] = velocity_friction(d, 0.0, model, a)
                work[W_RHS, a] = net + coupling - work[W_TAU_FV, a]
            else:
                work[S_ETA_M, a] = np.nan
                work[S_ETA_L, a] = np.nan
        if not started:
            break

    # Integrate (semi-implicit Euler). A moving axis whose velocity would cross zero, or that
    # decelerates inside the V_eps band, stops exactly: it is then locked (no drift) until a
    # breakaway, and breakaway needs static >= Coulomb friction, so it cannot chatter.
    for a in range(n):
        ratio = model[P_GEAR_RATIO, a]
        d = int(work[X_MOTION, a])
        w_old = work[W_OMEGA, a]
        acc = work[W_ACC, a]
        w_new = 0.0
        if d != 0:
            w_new = w_old + acc * dt_s
            if d * w_new <= 0.0 or (abs(w_new) < model[P_VELOCITY_EPS, a] and d * acc < 0.0):
                t_stop = dt_s
                if d * w_new <= 0.0 and acc != 0.0:
                    t_stop = min(dt_s, max(0.0, -w_old / acc))
                work[X_POSITION, a] += 0.5 * w_old * t_stop / ratio
                w_new = 0.0
                work[X_MOTION, a] = 0.0
            else:
                work[X_POSITION, a] += w_new * dt_s / ratio
        q = work[X_POSITION, a]
        q_min = model[P_POSITION_MIN, a]
        q_max = model[P_POSITION_MAX, a]
        if q > q_max or q < q_min:
            work[X_POSITION, a] = min(max(q, q_min), q_max)
            w_new = 0.0
            work[X_MOTION, a] = 0.0
        work[X_VELOCITY, a] = w_new / ratio

        tau_m = work[W_TAU_M, a]
        tau_l = work[W_TAU_L, a]
        friction = work[W_TAU_FV, a]
        if work[X_MOTION, a] == 0.0:
            q = work[X_POSITION, a]
            eps = model[P_TORQUE_EPS, a]
            if (q >= q_max and tau_m > eps) or (q <= q_min and tau_m < -eps):
                work[X_DRIVE, a] = STOP_END_STOP
            elif abs(tau_m) <= eps:
                work[X_DRIVE, a] = STOP_HOLD
            elif tau_m > 0.0:
                work[X_DRIVE, a] = STOP_MOTOR_DIRECT
            else:
                work[X_DRIVE, a] = STOP_MOTOR_REVERSE
            work[S_ETA_M, a] = np.nan
            work[S_ETA_L, a] = np.nan
            friction = static_friction(tau_m, model, a)

        i_a = work[X_CURRENT, a]
        work[S_MOTOR_VELOCITY, a] = w_new
        work[S_CURRENT, a] = i_a
        work[S_MOTOR_TORQUE, a] = tau_m
        work[S_LOAD_TORQUE, a] = tau_l
        work[S_FRICTION_TORQUE, a] = friction
        work[S_MOTOR_POWER, a] = tau_m * w_new
        work[S_LOAD_POWER, a] = tau_l * w_new
        if w_new != 0.0:
            work[S_GEAR_LOSS, a] = (1.0 - work[S_ETA_M, a]) * tau_m * w_new + (
                work[S_ETA_L, a] - 1.0
            ) * tau_l * w_new
            work[S_FRICTION_LOSS, a] = work[W_TAU_FV, a] * w_new
        else:
            work[S_GEAR_LOSS, a] = 0.0
            work[S_FRICTION_LOSS, a] = 0.0
        work[S_ELECTRICAL_POWER, a] = work[S_VOLTAGE, a] * i_a
        work[S_COPPER_LOSS, a] = model[P_RESISTANCE_OHM, a] * i_a * i_a
        work[S_MOTOR_ACCELERATION, a] = acc
    return OK


@njit(cache=True)
def steps(
    n_steps: int,
    voltage_cmd_v: FloatArray,
    mass_matrix: FloatArray,
    nonlinear_effects: FloatArray,
    work: FloatArray,
    model: FloatArray,
    dt_s: float,
) -> int:
    """`n_steps` of `step` under one voltage command and one set of rigid-body terms.

    Returns the number of steps taken: `n_steps`, or 0 when the command is not finite.
    """
    for k in range(n_steps):
        if step(mass_matrix, nonlinear_effects, voltage_cmd_v, work, model, dt_s) != OK:
            return k
    return n_steps


# --- the step at a fixed frame of memory ------------------------------------------------------
#
# numba unboxes every array argument at every call (about 0.1-0.15 us each), which at 4 axes
# costs more than the step's arithmetic. A simulator's arrays never move: `work` and `model` are
# its own, and its `Gantry` owns the packed tree, the scratch and the two buffers the compiled
# rigid-body terms (`rigid_body.terms`) write A(q) and the nonlinear effects into. So
# `step_in_frame` takes their addresses once, in a small integer array (`frame`), views them in
# place, evaluates eq. (2)'s terms at the state in `work` and steps; only the voltage array, new
# at every call, is unboxed. Nothing checks the addresses: the caller keeps every array alive
# and in place while it uses the frame. The arithmetic is `rigid_body.terms` then `step`, called
# on views of the same memory, so the bits are those of the two called in turn.

F_MASS = 0  # address of A(q): n x n float64, column major
F_NLE = 1  # address of C(q, qdot) qdot + Q(q): n float64
F_WORK = 2  # address of `work`: work_rows(n) x n float64, row major
F_MODEL = 3  # address of `model`: F_MODEL_ROWS x n float64, row major
F_N = 4  # number of axes
F_MODEL_ROWS = 5
F_TREE = 6  # address of the packed rigid-body tree: (n + 1) x rigid_body.TREE_COLS
F_BODY = 7  # address of its scratch: (n + 1) x rigid_body.BODY_COLS
F_CODE = 8  # rigid_body.CODE_VERSION of the running Python (see STALE_CODE)
N_FRAME = 9


@intrinsic
def _void_pointer(typingctx, address):  # type: ignore[no-untyped-def]
    """The integer `address` as a void pointer (numba's recipe for carray on given memory)."""

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        return builder.inttoptr(args[0], cgutils.voidptr_t)

    return types.voidptr(types.int64), codegen


# Raw addresses mean nothing to plain Python: with NUMBA_DISABLE_JIT=1 the simulator passes arrays.
FRAME_AVAILABLE = not getattr(numba_config, "DISABLE_JIT", False)


def make_frame(
    mass_matrix: FloatArray,
    nonlinear_effects: FloatArray,
    work: FloatArray,
    model: FloatArray,
    tree: FloatArray,
    body: FloatArray,
) -> npt.NDArray[np.int64]:
    """The `frame` of `step_in_frame`: the addresses and shapes of the six arrays.

    `tree` and `body` are the packed model and scratch of `rigid_body.terms`, whose outputs
    are `mass_matrix` and `nonlinear_effects`. The caller keeps the six arrays alive and in
    place for as long as it uses the frame.

    Raises:
        ValueError: an array has the wrong dtype, shape or memory layout.

    """
    n = work.shape[1]
    layouts = (
        (mass_matrix, (n, n), mass_matrix.flags.f_contiguous, "column-major"),
        (nonlinear_effects, (n,), nonlinear_effects.flags.c_contiguous, "contiguous"),
        (work, (work_rows(n), n), work.flags.c_contiguous, "row-major"),
        (model, (model.shape[0], n), model.flags.c_contiguous, "row-major"),
        (tree, (n + 1, rigid_body.TREE_COLS), tree.flags.c_contiguous, "row-major"),
        (body, (n + 1, rigid_body.BODY_COLS), body.flags.c_contiguous, "row-major"),
    )
    for array, shape, in_layout, layout in layouts:
        if array.dtype != np.float64 or array.shape != shape or not in_layout:
            raise InvalidValueError(
                f"expected a {layout} float64 array of shape {shape}, "
                f"got {array.dtype} {array.shape}"
            )
    frame = np.zeros(N_FRAME, dtype=np.int64)
    frame[F_MASS] = mass_matrix.ctypes.data
    frame[F_NLE] = nonlinear_effects.ctypes.data
    frame[F_WORK] = work.ctypes.data
    frame[F_MODEL] = model.ctypes.data
    frame[F_N] = n
    frame[F_MODEL_ROWS] = model.shape[0]
    frame[F_TREE] = tree.ctypes.data
    frame[F_BODY] = body.ctypes.data
    frame[F_CODE] = rigid_body.CODE_VERSION
    return frame


# One signature, compiled when this module is first imported (then loaded from numba's cache):
# any 1-D float64 voltage array (strided views too), the frame's address, the step.
@njit("int64(float64[:], int64, float64)", cache=True)
def step_in_frame(voltage_cmd_v: FloatArray, frame_address: int, dt_s: float) -> int:
    """Eq. (2)'s terms at the state, then `step`, on the arrays a frame points to (`make_frame`).

    Even the frame is passed by address: an integer costs numba next to nothing to unbox, an
    array about 0.1 us. Same returns as `step`. Call it through `step_in_frame_entry` on the
    hot path.
    """
    frame = carray(_void_pointer(frame_address), (N_FRAME,), np.int64)  # type: ignore[call-arg]
    if frame[F_CODE] != rigid_body.CODE_VERSION:  # a global: frozen into the compiled code
        return STALE_CODE
    n = frame[F_N]
    mass_matrix = farray(_void_pointer(frame[F_MASS]), (n, n), np.float64)
    nonlinear_effects = carray(_void_pointer(frame[F_NLE]), (n,), np.float64)
    work = carray(_void_pointer(frame[F_WORK]), (W_INERTIA + 2 * n, n), np.float64)
    model = carray(_void_pointer(frame[F_MODEL]), (frame[F_MODEL_ROWS], n), np.float64)
    tree = carray(_void_pointer(frame[F_TREE]), (n + 1, rigid_body.TREE_COLS), np.float64)
    body = carray(_void_pointer(frame[F_BODY]), (n + 1, rigid_body.BODY_COLS), np.float64)
    rigid_body.terms(work[X_POSITION], work[X_VELOCITY], tree, body, mass_matrix, nonlinear_effects)
    return step(mass_matrix, nonlinear_effects, voltage_cmd_v, work, model, dt_s)


def recompile_step_in_frame() -> None:
    """Compile `step_in_frame` again from the running code (and rewrite numba's cache)."""
    step_in_frame.recompile()


def step_in_frame_entry() -> Callable[[FloatArray, int, float], int]:
    """`step_in_frame`'s compiled entry point, without numba's dispatcher in front of it.

    The dispatcher works out the numba types of the arguments at every call to pick a compiled
    version, which costs about half the call. `step_in_frame` has one version, so this returns
    it (`Dispatcher.overloads`); its arguments are then unboxed as that version's types without
    being checked: the voltages MUST be a 1-D float64 array of the frame's axis count (any
    strides), the address that of a live frame (`make_frame`, `frame.ctypes.data`), and dt_s a
    float. Falls back to the dispatcher when numba's JIT is off or it has no single compiled
    version.
    """
    overloads = getattr(step_in_frame, "overloads", None)
    if not overloads or len(overloads) != 1:
        return step_in_frame
    entry: Callable[[FloatArray, int, float], int] = next(iter(overloads.values())).entry_point
    return entry


# What a cached function of another file runs when it calls `step` (its cache is keyed on its
# own file): this module's compiled code and constants, and rigid_body's (`code_version`).
CODE_VERSION = code_version.combined(
    rigid_body.CODE_VERSION, code_version.fingerprint(globals(), __name__)
)
