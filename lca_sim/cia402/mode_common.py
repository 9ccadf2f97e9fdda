"""What the CiA 402-2 modes share: their output, the software limits, the window timers.

Each mode (`mode_pp`, `mode_pv`, `homing`, `mode_csp`) returns a `ModeOutput` per step: which
drive loop to close, its demand (0x6062 and a velocity), the mode-specific statusword bits
10, 12 and 13, the following error 0x60F4 and an event (EMCY 0x8611) for the caller to report.
Positions in increments, velocities in increments/s (motor side, 0x608F); docs/can-modes.md.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from lca_sim.errors import InvalidValueError

# CiA 402-2 0x6065 / 0x6067: this window value switches the watch off.
WINDOW_OFF = 0xFFFFFFFF
# CiA 301 table 21 / CiA 402-2: "following error" (device specific, drive, position control).
EMCY_FOLLOWING_ERROR = 0x8611

# Statusword bits 10, 12 and 13 (CiA 402-2 0x6041): their meaning depends on the mode.
SW_BIT10 = 1 << 10  # target reached (PP, PV, HM)
SW_BIT12 = 1 << 12  # set-point acknowledge (PP), speed (PV), homing attained, follows (CSP)
SW_BIT13 = 1 << 13  # following error (PP, CSP), max slippage (PV), homing error (HM)
MODE_BITS_MASK = SW_BIT10 | SW_BIT12 | SW_BIT13


class Loop(enum.Enum):
    """The drive loop a mode closes (the names of lca_control's DriveLoops modes)."""

    POSITION = "position"
    VELOCITY = "velocity"
    CURRENT = "current"


@dataclass(frozen=True, slots=True)
class ModeOutput:
    """What a mode asks of the drive for one step.

    Attributes:
        loop: the loop to close.
        position_inc: position demand 0x6062 (the position loop's set-point).
        velocity_inc_s: velocity demand (the velocity loop's set-point, or feed-forward).
        torque_offset_permille: 0x60B2 added to the current loop's demand (CSP), per mille
            of 0x6076.
        status_bits: statusword bits 10, 12, 13 (`MODE_BITS_MASK`), the rest 0.
        following_error_inc: 0x60F4, demand - actual position.
        emcy_code: an EMCY to send and a fault reaction to take (0x8611), or None.
        position_shift_inc: homing moved the position frame by this much: the caller adds it
            to its actual position from now on (0x6064 at home = 0x607C).
    """

    loop: Loop
    position_inc: float
    velocity_inc_s: float
    status_bits: int = 0
    torque_offset_permille: int = 0
    following_error_inc: float = 0.0
    emcy_code: int | None = None
    position_shift_inc: float = 0.0


@dataclass(frozen=True, slots=True)
class SoftwareLimits:
    """0x607D software position limits, increments (sub 1 min, sub 2 max).

    CiA 402-2: targets beyond are limited to them. The full INTEGER32 range (the default)
    limits nothing.
    """

    min_inc: float = -(2.0**31)
    max_inc: float = 2.0**31 - 1.0

    def __post_init__(self) -> None:
        if not self.min_inc <= self.max_inc:
            raise InvalidValueError(
                f"0x607D: min position limit {self.min_inc} above max {self.max_inc}"
            )

    def clamp(self, position_inc: float) -> float:
        """`position_inc` limited to [min, max]."""
        return min(self.max_inc, max(self.min_inc, position_inc))


@dataclass(frozen=True, slots=True)
class WindowParams:
    """A window and the time a value must stay in (or out of) it, increments and s.

    Attributes:
        window: 0x6065 / 0x6067 / 0x606D ... in increments (/s); `WINDOW_OFF` switches it off.
        time_s: 0x6066 / 0x6068 / 0x606E ... (ms on the bus), >= 0.
    """

    window: float
    time_s: float

    def __post_init__(self) -> None:
        if math.isnan(self.window) or self.window < 0.0:
            raise InvalidValueError(f"a window must be >= 0, got {self.window!r}")
        if not (math.isfinite(self.time_s) and self.time_s >= 0.0):
            raise InvalidValueError(f"a window time must be finite and >= 0, got {self.time_s!r}")

    @property
    def off(self) -> bool:
        """The window is 0xFFFFFFFF: the watch is switched off."""
        return self.window >= WINDOW_OFF


# A window switched off (0x6065 / 0x6067 = 0xFFFFFFFF): the modes' default.
WINDOW_DISABLED = WindowParams(WINDOW_OFF, 0.0)


class Dwell:
    """True once a condition has held continuously for a time (a window time, CiA 402-2)."""

    def __init__(self) -> None:
        self._held_s: float | None = None

    def update(self, condition: bool, dt_s: float, time_s: float) -> bool:
        """Feed one step; the result is the condition held for at least `time_s`."""
        if not condition:
            self._held_s = None
            return False
        self._held_s = 0.0 if self._held_s is None else self._held_s + dt_s
        return self._held_s >= time_s - 1e-12

    def reset(self) -> None:
        """Forget the time held."""
        self._held_s = None


class FollowingErrorWatch:
    """0x6065 / 0x6066: the following error beyond its window for longer than its time.

    The event (EMCY 0x8611) comes once, on the rising edge of statusword bit 13.
    """

    def __init__(self) -> None:
        self._dwell = Dwell()
        self._active = False

    @property
    def active(self) -> bool:
        """Statusword bit 13."""
        return self._active

    def update(
        self, demand_inc: float, actual_inc: float, dt_s: float, params: WindowParams
    ) -> tuple[bool, bool]:
        """Feed one step: (bit 13, whether it rose now)."""
        outside = not params.off and abs(demand_inc - actual_inc) > params.window
        active = self._dwell.update(outside, dt_s, params.time_s)
        rose = active and not self._active
        self._active = active
        return active, rose

    def reset(self) -> None:
        """No following error (a mode's entry: demand = actual)."""
        self._dwell.reset()
        self._active = False


def rising(controlword: int, previous: int, bit: int) -> bool:
    """Controlword `bit` (a mask) went from 0 to 1."""
    return bool(controlword & bit) and not previous & bit


def falling(controlword: int, previous: int, bit: int) -> bool:
    """Controlword `bit` (a mask) went from 1 to 0."""
    return not controlword & bit and bool(previous & bit)
