"""The samples eq. (10) is fitted on: a uniform record, its derivatives, each sample's state.

Each moving sample gets its (direction, state) from the motion direction and the robot's state
table (the same conditions as `kernel.classify`, evaluated on the smoothed current and on tau_l),
never from recorded eta values. Samples are left out when the axis is stopped (locked: eq. (10)
does not hold), within a guard of a state change, a stop, a gap or the record's ends (where the
differentiator smears a kink), and where the noise could flip a condition of the state table.

End stops: a sample within `end_stop_margin_rad` (default 3 deg) of a URDF joint limit of the
identified axis (`Simulator.position_limits`), and every sample within the guard of one, is left
out and counted (`n_end_stop`); docs/tools.md ("lca-hil identify", step 1) says why and how wide.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import savgol_filter

from lca_sim.analysis.identify_types import (
    AMBIGUOUS,
    BoolArray,
    FloatArray,
    IdentificationError,
    IdentifyOptions,
    IntArray,
    MotionRecord,
)
from lca_sim.model.gantry import Gantry
from lca_sim.model.params import AxisParams, RobotParams
from lca_sim.model.state_machine import (
    Dominance,
    DriveStateRule,
    LoadCondition,
    MotorCondition,
    match_rule,
)

# Relative spread of the sample period above which the record is resampled on a uniform grid.
_JITTER_TOLERANCE = 0.01
# A hole in the time stamps longer than this many periods is a gap, not jitter.
_GAP_PERIODS = 3.0
# MAD of a normal sample times this is its standard deviation.
_MAD_TO_SIGMA = 1.4826


def check_options(opts: IdentifyOptions) -> None:
    """Reject options the procedure cannot run with, one clear line each."""
    checks = (
        ("window_s", opts.window_s > 0.0, "> 0"),
        ("polyorder", opts.polyorder >= 1, ">= 1"),
        ("guard_s", opts.guard_s >= 0.0, ">= 0"),
        ("margin_sigma", opts.margin_sigma >= 0.0, ">= 0"),
        ("min_samples", opts.min_samples >= 1, ">= 1"),
        ("confidence", 0.0 < opts.confidence < 1.0, "in (0, 1)"),
        ("bootstrap_replicates", opts.bootstrap_replicates >= 10, ">= 10"),
        ("end_stop_margin_rad", opts.end_stop_margin_rad >= 0.0, ">= 0"),
        ("ci_width_relative", opts.ci_width_relative > 0.0, "> 0"),
        ("ci_width_absolute", opts.ci_width_absolute > 0.0, "> 0"),
    )
    for name, ok, expected in checks:
        if not ok:
            raise IdentificationError(f"{name}: expected {expected}, got {getattr(opts, name)!r}")


def uniform_record(
    record: MotionRecord, n_axes: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, BoolArray]:
    """Check the record and put it on a uniform time grid.

    Returns the time, position, velocity and current on the grid, and a mask that is False
    inside gaps of the original stamps (where the grid's values are interpolated, not measured).
    """
    time_s, position, velocity, current = _checked_arrays(record, n_axes)
    n = time_s.shape[0]
    steps = np.diff(time_s)
    if np.any(steps <= 0.0):
        raise IdentificationError("time_s: expected strictly increasing times")
    period = float(np.median(steps))
    if float(np.max(np.abs(steps - period))) <= _JITTER_TOLERANCE * period:
        return time_s, position, velocity, current, np.ones(n, dtype=np.bool_)
    count = math.floor((time_s[-1] - time_s[0]) / period + 1e-9) + 1
    grid = time_s[0] + period * np.arange(count, dtype=np.float64)
    right = np.clip(np.searchsorted(time_s, grid, side="right"), 1, n - 1)
    valid = (time_s[right] - time_s[right - 1]) <= _GAP_PERIODS * period
    return (
        grid,
        _resample(grid, time_s, position),
        _resample(grid, time_s, velocity),
        _resample(grid, time_s, current),
        valid,
    )


def _checked_arrays(
    record: MotionRecord, n_axes: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The record's time, position, velocity and current as float arrays of matching shapes.

    Raises:
        IdentificationError: A wrong shape, a non-finite value or fewer than 3 samples.
    """
    time_s = np.asarray(record.time_s, dtype=np.float64)
    position = np.asarray(record.position, dtype=np.float64)
    velocity = np.asarray(record.velocity, dtype=np.float64)
    current = np.asarray(record.current_a, dtype=np.float64)
    n = time_s.shape[0] if time_s.ndim == 1 else -1
    if n < 0:
        raise IdentificationError(f"time_s: expected a 1-D array, got shape {time_s.shape}")
    for name, array, shape in (
        ("position", position, (n, n_axes)),
        ("velocity", velocity, (n, n_axes)),
        ("current_a", current, (n,)),
    ):
        if array.shape != shape:
            raise IdentificationError(f"{name}: expected shape {shape}, got {array.shape}")
    for name, array in (
        ("time_s", time_s),
        ("position", position),
        ("velocity", velocity),
        ("current_a", current),
    ):
        if not np.all(np.isfinite(array)):
            raise IdentificationError(f"{name}: expected finite values only")
    if n < 3:
        raise IdentificationError(f"expected at least 3 samples, got {n}")
    return time_s, position, velocity, current


def _resample(grid: FloatArray, time_s: FloatArray, values: FloatArray) -> FloatArray:
    """`values` sampled at `time_s` (1-D, or one column per axis) interpolated onto `grid`."""
    if values.ndim == 1:
        return np.asarray(np.interp(grid, time_s, values), dtype=np.float64)
    columns = [np.interp(grid, time_s, col) for col in values.T]
    return np.asarray(np.stack(columns, axis=1), dtype=np.float64)


def window_samples(opts: IdentifyOptions, period_s: float, n: int) -> int:
    """The odd Savitzky-Golay window in samples, long enough for the polynomial order."""
    window = round(opts.window_s / period_s)
    window = max(window, opts.polyorder + 2)
    if window % 2 == 0:
        window += 1
    if window > n:
        raise IdentificationError(
            f"expected at least {window} samples for a {opts.window_s:g} s window at "
            f"{period_s:g} s, got {n}"
        )
    return window


def savgol(
    values: FloatArray, window: int, polyorder: int, deriv: int, period_s: float
) -> FloatArray:
    """Savitzky-Golay smoothing (deriv 0) or derivative (deriv 1) along time, zero phase."""
    out = savgol_filter(values, window, polyorder, deriv=deriv, delta=period_s, axis=0)
    return np.asarray(out, dtype=np.float64)


def smoothing_gain(h: FloatArray) -> float:
    """Standard deviation of smoothed white noise relative to the raw noise: sqrt(sum h^2).

    `h` holds the smoother's coefficients (`savgol_coeffs`).
    """
    return float(np.sqrt(np.sum(h * h)))


def noise_sigma(residual: FloatArray, h: FloatArray) -> float:
    """Noise standard deviation from the raw-minus-smoothed residual, robust to kinks.

    For white noise of variance s^2 the residual of a least-squares smoother has variance
    s^2 (1 - h0), h0 the centre weight of the filter's coefficients `h` (`savgol_coeffs`); the
    median absolute deviation ignores the few large residuals where the signal has a kink.
    """
    h0 = float(h[len(h) // 2])
    mad = float(np.median(np.abs(residual - np.median(residual))))
    return _MAD_TO_SIGMA * mad / math.sqrt(max(1.0 - h0, 1e-12))


def near_end_stop(
    position: FloatArray, limits: tuple[float, float], margin: float, guard: int
) -> BoolArray:
    """True where the axis is within `margin` of an end stop, or within `guard` samples of that.

    The guard covers the differentiator's smear of the impact (docs/tools.md, "lca-hil identify"
    step 1).
    """
    near = (position <= limits[0] + margin) | (position >= limits[1] - margin)
    if not np.any(near):
        return near
    # Dilate by `guard` samples on both sides: a running count over a window of 2 guard + 1.
    counts = np.convolve(near.astype(np.int64), np.ones(2 * guard + 1, dtype=np.int64), "same")
    out: BoolArray = counts > 0
    return out


def load_and_inertia(
    robot: RobotParams,
    gantry: Gantry,
    a: int,
    position: FloatArray,
    velocity: FloatArray,
    accel: FloatArray,
    moving: BoolArray,
) -> tuple[FloatArray, FloatArray]:
    """Eq. (8)-(10) terms of axis a at the moving samples (zero elsewhere), motor side.

    tau_l = N^-1 (C qdot + Q)_a and the coupled inertia torque
    (J qddot_m)_a = J_m N_a qddot_a + N_a^-1 (A(q) qddot)_a, from Pinocchio.
    """
    ratio = robot.axes[a].gear_ratio
    rotor = robot.axes[a].motor.rotor_inertia_kg_m2
    n_axes = len(robot.axes)
    tau_l = np.zeros(len(position))
    inertia = np.zeros(len(position))
    for k in np.nonzero(moving)[0]:
        mass, nle = gantry.dynamics_terms(position[k], velocity[k])
        # crba fills the upper triangle only: row a of the symmetric A.
        row = sum(float(mass[min(a, b), max(a, b)]) * float(accel[k, b]) for b in range(n_axes))
        tau_l[k] = float(nle[a]) / ratio
        inertia[k] = rotor * ratio * float(accel[k, a]) + row / ratio
    return tau_l, inertia


def velocity_friction(params: AxisParams, direction: IntArray, omega_m: FloatArray) -> FloatArray:
    """Eq. (4): Coulomb plus viscous friction per sample, N m (0 where stopped)."""
    f = params.friction
    direct = f.coulomb_direct_nm + f.viscous_direct_nm_s_per_rad * omega_m
    reverse = -f.coulomb_reverse_nm + f.viscous_reverse_nm_s_per_rad * omega_m
    out: FloatArray = np.where(direction > 0, direct, np.where(direction < 0, reverse, 0.0))
    return out


def classify_samples(
    rules: tuple[DriveStateRule, ...],
    direction: IntArray,
    tau_m: FloatArray,
    tau_l: FloatArray,
    margin_nm: float,
    load_band_nm: float = 0.0,
) -> IntArray:
    """The moving state of every sample (Fig. 8 and its mirror), -2 where it is ambiguous.

    The conditions are those of `kernel.classify`, along the motion direction d: the motor
    drives when d tau_m > 0, the load drives when -d tau_l > 0, the load dominates when
    |tau_m| < |tau_l|. A sample is ambiguous when flipping a condition that lies within
    `margin_nm` of its boundary would change the state. A model load torque within
    `load_band_nm` (`state_machine.load_torque_band_nm`) is exactly zero, as in the model's own
    step: Pinocchio's rounding residue on an axis without a gravity load (the L-arm) decides
    nothing, and such samples are not ambiguous on the load's conditions.
    """
    zero_load = np.abs(tau_l) <= load_band_nm
    tau_l = np.where(zero_load, 0.0, tau_l)
    lookup = np.zeros((2, 2, 2), dtype=np.int64)
    motor_words = (MotorCondition.DRIVES, MotorCondition.BRAKES)
    load_words = (LoadCondition.DRIVES, LoadCondition.RESISTS)
    dominant_words = (Dominance.MOTOR, Dominance.LOAD)
    for m_index, motor in enumerate(motor_words):
        for l_index, load in enumerate(load_words):
            for d_index, dominant in enumerate(dominant_words):
                # parse_state_machine guarantees every combination is covered (a rule, not None).
                rule = match_rule(rules, motor, load, dominant)
                lookup[m_index, l_index, d_index] = rules.index(rule)
    d = direction.astype(np.float64)
    motor_drives = d * tau_m > 0.0
    load_drives = -d * tau_l > 0.0
    load_dominant = np.abs(tau_m) < np.abs(tau_l)
    i = np.where(motor_drives, 0, 1)
    j = np.where(load_drives, 0, 1)
    k = np.where(load_dominant, 1, 0)
    state = lookup[i, j, k]
    near_motor = np.abs(tau_m) < margin_nm
    near_load = (np.abs(tau_l) < margin_nm) & ~zero_load
    near_dominant = (np.abs(np.abs(tau_m) - np.abs(tau_l)) < margin_nm) & ~zero_load
    ambiguous = (
        (near_motor & (lookup[1 - i, j, k] != state))
        | (near_load & (lookup[i, 1 - j, k] != state))
        | (near_dominant & (lookup[i, j, 1 - k] != state))
    )
    out: IntArray = np.where(ambiguous, AMBIGUOUS, state).astype(np.int64)
    return out


def guarded(key: IntArray, guard: int) -> BoolArray:
    """True where the label has been constant for `guard` samples on both sides.

    Samples within `guard` of a label change or of the record's ends are False.
    """
    n = len(key)
    change = np.nonzero(key[1:] != key[:-1])[0] + 1
    starts = np.concatenate(([0], change))
    stops = np.concatenate((change, [n]))
    keep = np.zeros(n, dtype=np.bool_)
    for start, stop in zip(starts, stops, strict=True):
        lo, hi = start + guard, stop - guard
        if hi > lo:
            keep[lo:hi] = True
    return keep
