"""The identification's values: a recorded motion, its options, each state's estimate, the result.

`lca_sim.analysis.identify` has the procedure (section 4.1, eq. 10-11).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from lca_sim.errors import LcaHilError, UnknownNameError
from lca_sim.model.state_machine import (
    Efficiency,
    MotionState,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
DIRECTIONS: tuple[MotionState, MotionState] = (MotionState.DIRECT, MotionState.REVERSE)
# Labels of samples that are not in a moving state.
STOPPED = -1
AMBIGUOUS = -2
INVALID = -3
END_STOP = -4


class Criterion(enum.Enum):
    """How the width of a confidence interval is judged (module docstring, Identifiability)."""

    RELATIVE = "relative"  # width <= ci_width_relative * estimate
    ABSOLUTE = "absolute"  # width <= ci_width_absolute (small efficiencies)


class IdentificationError(LcaHilError, ValueError):
    """The samples given to `identify` cannot be used (shape, non-finite, too short...)."""


class EstimateStatus(enum.Enum):
    """What became of one (direction, state) of the identification."""

    IDENTIFIED = "identified"
    NOT_VISITED = "not_visited"  # no usable sample in this state
    TOO_FEW_SAMPLES = "too_few_samples"  # fewer than `min_samples` usable samples
    WEAK_EXCITATION = "weak_excitation"  # the emitter's torque is lost in the current noise
    NOT_IDENTIFIABLE = "not_identifiable"  # the interval is wider than the bound (module doc)
    FIXED = "fixed"  # no emitter coefficient (coasting): both are 1 by eq. (11)

    @property
    def keeps_prior(self) -> bool:
        """True when the written config keeps the prior value of this state."""
        return self is not EstimateStatus.IDENTIFIED


@dataclass(frozen=True, slots=True)
class MotionRecord:
    """Uniformly or nearly uniformly sampled motion of the robot while one axis is identified.

    Attributes:
        time_s: [n] sample times, strictly increasing, s.
        position: [n, n_axes] joint positions (rad; m for the lift), in the robot's axis order.
        velocity: [n, n_axes] joint velocities (rad/s; m/s).
        current_a: [n] armature current of the identified axis, A.

    """

    time_s: FloatArray
    position: FloatArray
    velocity: FloatArray
    current_a: FloatArray


@dataclass(frozen=True, slots=True)
class IdentifyOptions:
    """Tuning of the identification; the defaults suit records at 0.25-10 kHz.

    Attributes:
        window_s: length of the Savitzky-Golay window (smoothing and differentiation), s.
        polyorder: its polynomial order.
        guard_s: samples this close to a state change, a stop, a gap or the record's ends are
            left out (at least half the window, where the differentiator sees the kink).
        margin_sigma: a sample is ambiguous, and left out, when a condition of the state table
            (sign of tau_m, sign of tau_l, |tau_m| vs |tau_l|) is within this many standard
            deviations of the smoothed motor-torque noise of its boundary.
        min_samples: fewer usable samples than this in a state: not identified.
        confidence: level of the confidence intervals.
        bootstrap_replicates: moving-block bootstrap replicates per state.
        seed: of the bootstrap's random generator (results are reproducible).
        end_stop_margin_rad: samples this close to a joint limit of the identified axis (rad; m
            for a prismatic axis), and those within the guard of one, are left out.
        ci_width_relative: widest interval accepted, relative to the estimate clipped to [0, 1].
        ci_width_absolute: widest interval accepted, absolute (the floor for small estimates).

    """

    window_s: float = 0.03
    polyorder: int = 3
    guard_s: float = 0.02
    margin_sigma: float = 4.0
    min_samples: int = 100
    confidence: float = 0.95
    bootstrap_replicates: int = 2000
    seed: int = 0
    end_stop_margin_rad: float = math.radians(3.0)
    ci_width_relative: float = 0.2
    ci_width_absolute: float = 0.1


@dataclass(frozen=True, slots=True)
class StateEstimate:
    """The identification of one drive state in one direction.

    Attributes:
        state: drive-state name (the robot's state table).
        direction: DIRECT or REVERSE.
        coefficient: "eta_m" or "eta_l", the one estimated; None when the state has no emitter
            coefficient (both fixed at 1).
        status: identified, or why not.
        estimate: the estimated coefficient (NaN when nothing could be estimated).
        ci_low, ci_high: its confidence interval (NaN when not estimated).
        n_samples: usable samples of this state (after every exclusion).
        n_effective: samples corrected for serial correlation, n / integrated correlation time.
        block_length: the bootstrap's block length in samples (0 when no interval was drawn).
        prior: the coefficients of the robot config the identification started from.
        identified: what the identified config gets: the estimate (clipped to the range the
            config loader accepts) with the other coefficient at 1, or the prior when the status
            keeps it.
        clipped: the estimate was outside (0, 1] (eta_m) or [0, 1] (eta_l) and was clipped.
        residual_mean_nm: mean eq. (10) residual with the identified coefficients, N m.
        residual_rms_nm: its RMS, N m.
        regressor_rms_nm: RMS of the emitter's torque over the samples, N m (the excitation).
        criterion: how the interval's width was judged, None when no interval was drawn.
        ci_width_bound: the widest interval accepted under `criterion` (NaN when None).

    """

    state: str
    direction: MotionState
    coefficient: str | None
    status: EstimateStatus
    estimate: float
    ci_low: float
    ci_high: float
    n_samples: int
    n_effective: float
    block_length: int
    prior: Efficiency
    identified: Efficiency
    clipped: bool
    residual_mean_nm: float
    residual_rms_nm: float
    regressor_rms_nm: float
    criterion: Criterion | None = None
    ci_width_bound: float = math.nan

    @property
    def ci_width(self) -> float:
        """Width of the confidence interval, high - low (NaN when not estimated)."""
        return self.ci_high - self.ci_low


@dataclass(frozen=True, slots=True)
class IdentificationResult:
    """Everything `identify` found, with the per-sample classification for inspection.

    Attributes:
        axis: the identified axis.
        estimates: one per (state, direction), states in table order, direct first.
        sample_period_s: period of the (possibly resampled) record, s.
        time_s: [n] the sample times used (a uniform grid).
        direction: [n] motion direction per sample (+1, -1, 0 when stopped).
        state_index: [n] moving-state index per sample into `state_names`, or -1 stopped,
            -2 ambiguous (a condition within the noise margin), -3 invalid (gap, record end),
            -4 at or near an end stop (`IdentifyOptions.end_stop_margin_rad`, and its guard).
        used: [n] True where the sample entered a fit.
        state_names: the robot's moving-state names.
        current_noise_a: estimated standard deviation of the current noise, A.
        velocity_noise_rad_s: estimated standard deviation of the motor velocity noise, rad/s.
        moving_threshold_rad_s: motor speed below which a sample counts as stopped.
        position_limits: (min, max) of the identified axis from the URDF (rad; m).
        options: the options used.

    """

    axis: str
    estimates: tuple[StateEstimate, ...]
    sample_period_s: float
    time_s: FloatArray
    direction: IntArray
    state_index: IntArray
    used: BoolArray
    state_names: tuple[str, ...]
    current_noise_a: float
    velocity_noise_rad_s: float
    moving_threshold_rad_s: float
    position_limits: tuple[float, float]
    options: IdentifyOptions

    @property
    def n_samples(self) -> int:
        """Samples of the (resampled) record."""
        return len(self.time_s)

    @property
    def n_moving(self) -> int:
        """Samples where the identified axis moves."""
        return int(np.count_nonzero(self.direction))

    @property
    def n_end_stop(self) -> int:
        """Samples left out at or near an end stop (within the margin or its guard)."""
        return int(np.count_nonzero(self.state_index == END_STOP))

    @property
    def n_used(self) -> int:
        """Samples that entered a fit."""
        return int(np.count_nonzero(self.used))

    def estimate(self, state: str, direction: MotionState) -> StateEstimate:
        """The estimate of one state in one direction.

        Raises:
            UnknownNameError: `state` is not a moving state of the robot.
        """
        for item in self.estimates:
            if item.state == state and item.direction == direction:
                return item
        raise UnknownNameError("drive state", state, self.state_names)

    @property
    def not_identified(self) -> tuple[StateEstimate, ...]:
        """The (state, direction) pairs whose prior value is kept, with the reason."""
        return tuple(e for e in self.estimates if e.status.keeps_prior)

    def efficiency_table(self) -> dict[tuple[MotionState, str], Efficiency]:
        """The identified efficiency table (priors where nothing was identified)."""
        return {(e.direction, e.state): e.identified for e in self.estimates}
