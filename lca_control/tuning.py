"""The section 6 tuning rule for a PI loop, G(s) = Kp (1 + 1 / (Ti s)).

The paper tunes each loop on the Bode diagrams of its linearised plant: choose the crossover
wc = 1 / Ti (from the wanted response time, t_r ~= 3 Ti for the current loop), read the plant
magnitude |P(j wc)| and set Kp for unity gain there, Kp = 1 / |P(j wc)| ("graphically, Kp =
30 dB"). With several operating points the magnitudes at wc differ a little; the rule here takes
the smallest one, so that the crossover is at wc or above at every operating point and the PI
zero (at 1/Ti) never falls above the crossover, where its phase lag would eat the margin.

Pure: numbers in, numbers out (the plants' frequency responses come from `lca_sim.analysis.linear`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from lca_control.pi import ControlParamError


@dataclass(frozen=True, slots=True)
class PiTuning:
    """A tuned PI loop.

    Attributes:
        kp: proportional gain (output units per error unit): 1 / |P(j wc)| for the smallest
            plant magnitude at wc.
        crossover_rad_s: the chosen crossover wc.
        plant_gain_spread_db: max - min of the plant magnitudes at wc over the operating points.
    """

    kp: float
    crossover_rad_s: float
    plant_gain_spread_db: float

    @property
    def ti_s(self) -> float:
        """Integral action time, 1 / wc (section 6)."""
        return 1.0 / self.crossover_rad_s

    @property
    def kp_db(self) -> float:
        """Kp in dB, as the paper quotes it."""
        return 20.0 * math.log10(self.kp)

    @property
    def plant_gain_db(self) -> float:
        """The plant magnitude the gain was read from, dB (the smallest one): -Kp in dB."""
        return -self.kp_db


def tune_pi(crossover_rad_s: float, plant_magnitudes: Sequence[float]) -> PiTuning:
    """Kp and Ti from the plant magnitudes |P(j wc)| at each operating point (section 6).

    Raises:
        ControlParamError: no magnitudes, a non-positive or non-finite one, or a bad wc.
    """
    if not (math.isfinite(crossover_rad_s) and crossover_rad_s > 0.0):
        raise ControlParamError(f"crossover must be finite and > 0, got {crossover_rad_s!r}")
    if not plant_magnitudes:
        raise ControlParamError("tuning needs the plant magnitude at one operating point at least")
    if not all(math.isfinite(m) and m > 0.0 for m in plant_magnitudes):
        raise ControlParamError(f"plant magnitudes must be finite and > 0, got {plant_magnitudes}")
    smallest = min(plant_magnitudes)
    return PiTuning(
        kp=1.0 / smallest,
        crossover_rad_s=crossover_rad_s,
        plant_gain_spread_db=20.0 * math.log10(max(plant_magnitudes) / smallest),
    )


def response_time_to_crossover(response_time_s: float) -> float:
    """The paper's t_r ~= 3 Ti, so wc = 1 / Ti = 3 / t_r (rad/s)."""
    if not (math.isfinite(response_time_s) and response_time_s > 0.0):
        raise ControlParamError(f"response time must be finite and > 0, got {response_time_s!r}")
    return 3.0 / response_time_s
