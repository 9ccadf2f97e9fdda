"""Identification of the drive-state efficiencies from a recorded motion (section 4.1, eq. 10-11).

The paper identifies one efficiency coefficient per drive state and direction experimentally
(Table 1) and announces an automatic procedure for it (section 7). This module is that procedure,
as a pure function of sampled arrays: no ROS, no files, no clock. Eq. (10), per sample of a
moving axis, motor side:

    eta_m tau_m = (J qddot_m)_axis + eta_l tau_l + tau_fv(qdot_m)

with tau_m = k_t i, tau_l from Pinocchio (eq. 8), the coupled inertia row (eq. 9-10) times
Savitzky-Golay accelerations, and the eq. (4) friction taken as known. By eq. (11) the free
coefficient is the emitter's: eta_l where the load drives, eta_m where the motor drives, none
when coasting (the mean residual is reported as a check). docs/tools.md ("lca-hil identify")
has the procedure and why friction is not fitted; `lca_sim.analysis.identify_samples` picks
the samples, `lca_sim.analysis.identify_estimate` makes each estimate and its verdict.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import savgol_coeffs

from lca_sim.analysis.identify_estimate import estimate_state
from lca_sim.analysis.identify_samples import (
    check_options,
    classify_samples,
    guarded,
    load_and_inertia,
    near_end_stop,
    noise_sigma,
    savgol,
    smoothing_gain,
    uniform_record,
    velocity_friction,
    window_samples,
)
from lca_sim.analysis.identify_types import (
    DIRECTIONS,
    END_STOP,
    INVALID,
    STOPPED,
    IdentificationResult,
    IdentifyOptions,
    MotionRecord,
)
from lca_sim.errors import UnknownNameError
from lca_sim.model.gantry import Gantry
from lca_sim.model.params import RobotParams
from lca_sim.model.state_machine import (
    load_torque_band_nm,
)


def identify(
    robot: RobotParams,
    axis: str,
    record: MotionRecord,
    options: IdentifyOptions | None = None,
) -> IdentificationResult:
    """Identify the efficiencies of every drive state of one axis from a recorded motion.

    Eq. (10) per usable moving sample, with everything but the state's free coefficient known
    (module docstring): eta_m tau_m - eta_l tau_l = (J qddot_m)_axis + tau_fv.

    Args:
        robot: the robot parameters (state table, motor, gear, friction; prior efficiencies).
        axis: the axis to identify, by name.
        record: the samples.
        options: tuning; the defaults when None.

    Returns:
        One estimate per (state, direction), with the reason when one was not identified.

    Raises:
        UnknownNameError: `axis` is not an axis of the robot.
        IdentificationError: the record's arrays are inconsistent, non-finite or too short.
    """
    opts = options if options is not None else IdentifyOptions()
    check_options(opts)
    if axis not in robot.axis_names:
        raise UnknownNameError("axis", axis, robot.axis_names)
    a = robot.axis_names.index(axis)
    params = robot.axes[a]
    time_s, position, velocity, current_a, valid = uniform_record(record, len(robot.axes))
    period_s = float(time_s[1] - time_s[0])
    window = window_samples(opts, period_s, len(time_s))
    guard = max(math.ceil(opts.guard_s / period_s - 1e-9), window // 2 + 1)

    # Zero-phase smoothing and differentiation: offline, so the filter may look ahead.
    smooth_v = savgol(velocity, window, opts.polyorder, 0, period_s)
    accel = savgol(velocity, window, opts.polyorder, 1, period_s)
    smooth_i = savgol(current_a, window, opts.polyorder, 0, period_s)
    coeffs = np.asarray(savgol_coeffs(window, opts.polyorder), dtype=np.float64)
    gain = smoothing_gain(coeffs)
    current_noise_a = noise_sigma(current_a - smooth_i, coeffs)
    velocity_noise = params.gear_ratio * noise_sigma(velocity[:, a] - smooth_v[:, a], coeffs)

    k_t = params.motor.torque_constant_nm_per_a
    tau_m = k_t * smooth_i
    tau_margin_nm = max(opts.margin_sigma * k_t * current_noise_a * gain, 1e-12)
    omega_m = params.gear_ratio * smooth_v[:, a]
    threshold = max(
        robot.state_machine.velocity_eps_rad_s,
        opts.margin_sigma * velocity_noise * gain,
    )
    direction = np.where(omega_m > threshold, 1, np.where(omega_m < -threshold, -1, 0))
    direction = direction.astype(np.int64)
    moving = (direction != 0) & valid

    gantry = Gantry(robot.urdf_xml, robot.gravity_m_s2, robot.source)
    joint = gantry.joints[a]
    limits = (joint.position_min, joint.position_max)
    end_stop = near_end_stop(position[:, a], limits, opts.end_stop_margin_rad, guard)
    tau_l, inertia_nm = load_and_inertia(robot, gantry, a, position, smooth_v, accel, moving)
    tau_fv = velocity_friction(params, direction, omega_m)
    # Eq. (10) with the unknowns on the left: eta_m tau_m - eta_l tau_l = y.
    y = inertia_nm + tau_fv

    rules = robot.state_machine.rules
    band_nm = load_torque_band_nm(params.motor.stall_torque_nm)
    state = classify_samples(rules, direction, tau_m, tau_l, tau_margin_nm, band_nm)
    labels = np.where(moving, state, np.where(valid, STOPPED, INVALID))
    labels = np.where(end_stop, END_STOP, labels).astype(np.int64)
    key = np.where(labels >= 0, (direction > 0) * len(rules) + labels, labels)
    used = guarded(key, guard) & (labels >= 0)

    rng = np.random.default_rng(opts.seed)
    estimates = []
    for rule_index, rule in enumerate(rules):
        for d in DIRECTIONS:
            select = used & (labels == rule_index) & (direction == int(d))
            estimate = estimate_state(
                rule,
                d,
                params,
                tau_m[select],
                tau_l[select],
                y[select],
                np.nonzero(select)[0],
                window,
                tau_margin_nm,
                opts,
                rng,
            )
            estimates.append(estimate)
    return IdentificationResult(
        axis=axis,
        estimates=tuple(estimates),
        sample_period_s=period_s,
        time_s=time_s,
        direction=np.where(moving, direction, 0).astype(np.int64),
        state_index=labels,
        used=used,
        state_names=tuple(r.name for r in rules),
        current_noise_a=current_noise_a,
        velocity_noise_rad_s=velocity_noise,
        moving_threshold_rad_s=threshold,
        position_limits=limits,
        options=opts,
    )
