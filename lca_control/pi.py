"""A discrete PI controller, G(s) = Kp (1 + 1 / (Ti s)) (the paper's section 6).

Pure: no clock (every update takes its own dt), no I/O, no ROS. The integral action is kept in
output units, which makes parameter changes and re-enabling bumpless.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


class ControlParamError(ValueError):
    """PI or cascade parameters that cannot work (non-finite, Ti <= 0, empty limits).

    The control core's only exception. It does not derive from `lca_sim.errors.LcaHilError`
    because lca_control sits below lca_sim and imports nothing from it; the tools and nodes
    catch both through `lca_sim.errors.USER_ERRORS`.
    """


@dataclass(frozen=True, slots=True)
class PIParams:
    """Gains and output limits of one PI loop.

    Attributes:
        kp: proportional gain, output units per error unit (V/A for the current loop, A per
            rad/s for the velocity loop).
        ti_s: integral action time Ti, s; `math.inf` gives a pure P controller.
        output_min, output_max: the output is clamped to this range, and the integral stops
            growing while the output is held at a limit (anti-windup by clamping).
    """

    kp: float
    ti_s: float
    output_min: float
    output_max: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.kp) and self.kp >= 0.0):
            raise ControlParamError(f"kp must be finite and >= 0, got {self.kp!r}")
        if not (self.ti_s > 0.0) or math.isnan(self.ti_s):
            raise ControlParamError(f"ti_s must be > 0 (inf for P only), got {self.ti_s!r}")
        if not (math.isfinite(self.output_min) and math.isfinite(self.output_max)):
            raise ControlParamError("output limits must be finite")
        if not self.output_min < self.output_max:
            raise ControlParamError(
                f"output_min {self.output_min!r} must be below output_max {self.output_max!r}"
            )


def pi_law(
    kp: float,
    ti_s: float,
    output_min: float,
    output_max: float,
    integral: float,
    error: float,
    dt_s: float,
) -> tuple[float, float]:
    """One PI sample: (output, new integral) from the old integral and the error.

    u = Kp e + I with I += Kp / Ti * e * dt (backward Euler), u clamped to the limits; while u
    is clamped and the error pushes further into the limit the integral is frozen, and it never
    exceeds the limits itself. Plain float arithmetic only, so
    `lca_sim.model.commanded_plant` compiles this very function with numba for its bank of
    in-drive current loops.
    """
    new_integral = integral + kp / ti_s * error * dt_s
    unclamped = kp * error + new_integral
    if unclamped > output_max:
        output = output_max
        if error > 0.0:  # would wind up further: keep the old integral
            new_integral = integral
    elif unclamped < output_min:
        output = output_min
        if error < 0.0:
            new_integral = integral
    else:
        output = unclamped
    return output, min(max(new_integral, output_min), output_max)


def pi_rebase(
    kp: float, output_min: float, output_max: float, output: float, last_error: float
) -> tuple[float, float]:
    """Bumpless retune: the new (integral, output), both within the new limits.

    The integral is chosen so that the last error with the new Kp gives the last output.
    """
    integral = output - kp * last_error
    return (
        min(max(integral, output_min), output_max),
        min(max(output, output_min), output_max),
    )


class PIController:
    """One discrete PI loop with an explicit dt.

    The update is u = Kp e + I with I += Kp / Ti * e * dt (backward Euler, the integral includes
    the current sample), and u clamped to the limits. While u is clamped and the error pushes
    further into the limit, I is frozen (conditional integration), so the loop leaves saturation
    as soon as the error changes sign.

    A sample whose setpoint or measurement is NaN or infinite is rejected: the output holds its
    last value, the state is untouched, and `rejected_samples` counts it.
    """

    def __init__(self, params: PIParams) -> None:
        self._params = params
        self._integral = 0.0
        self._output = 0.0
        self._last_error = 0.0
        self.rejected_samples = 0

    @property
    def params(self) -> PIParams:
        """The gains and limits in use."""
        return self._params

    @property
    def output(self) -> float:
        """The last output."""
        return self._output

    @property
    def integral(self) -> float:
        """The integral action, in output units."""
        return self._integral

    def update(self, setpoint: float, measurement: float, dt_s: float) -> float:
        """One control period: returns the new output.

        Raises:
            ControlParamError: dt_s is not a positive finite number.
        """
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ControlParamError(f"dt_s must be > 0 and finite, got {dt_s!r}")
        if not (math.isfinite(setpoint) and math.isfinite(measurement)):
            self.rejected_samples += 1
            return self._output
        p = self._params
        error = setpoint - measurement
        output, self._integral = pi_law(
            p.kp, p.ti_s, p.output_min, p.output_max, self._integral, error, dt_s
        )
        self._output = output
        self._last_error = error
        return output

    def reset(self, output: float = 0.0) -> None:
        """Start again with the integral set so that a zero error gives `output` (bumpless)."""
        p = self._params
        held = min(max(output, p.output_min), p.output_max) if math.isfinite(output) else 0.0
        self._integral = held
        self._output = held
        self._last_error = 0.0

    def set_params(self, params: PIParams) -> None:
        """Change gains or limits without a jump in the output.

        The integral is re-based so that the last error with the new Kp gives the last output.
        """
        self._params = params
        self._integral, self._output = pi_rebase(
            params.kp, params.output_min, params.output_max, self._output, self._last_error
        )
