"""The modes' parameters from the drive's object values, and which writes of them to refuse.

One place that reads the raw objects of docs/can-modes.md into the modes' typed parameters
(increments stay increments; ms become s; 0x2040 per mille of 0x6075 becomes A), and the SDO
abort code a write of one of them gets (CiA 301), so every value a mode is built from is valid.

    values = lambda index, sub: stored[(index, sub)]
    mode_write_abort(od.PROFILE_ACCELERATION, 0, 0, values)    # 0x06090032: value too low
    pp_params(values)                                          # PpParams(...)
"""

from __future__ import annotations

from collections.abc import Callable

from lca_sim.cia402 import cia301
from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import DriveUnits
from lca_sim.cia402.homing import HOMING_METHODS, HomingParams
from lca_sim.cia402.mode_common import SoftwareLimits, WindowParams
from lca_sim.cia402.mode_csp import CspParams
from lca_sim.cia402.mode_pp import PpParams
from lca_sim.cia402.mode_pv import PvParams
from lca_sim.cia402.profile import HALT_OPTIONS, MOTION_PROFILE_TYPES, ProfileParams

# (index, sub-index) -> raw value, as the drive stores it.
ObjectValues = Callable[[int, int], int]

# Option codes: the values a write may set.
MODE_OPTION_VALUES: dict[tuple[int, int], frozenset[int]] = {
    (od.HALT_OPTION, 0): HALT_OPTIONS,
    (od.MOTION_PROFILE_TYPE, 0): MOTION_PROFILE_TYPES,
    (od.HOMING_METHOD, 0): HOMING_METHODS,
}
# Rates the generator divides by: 0 is refused (a ramp that never ends).
POSITIVE_OBJECTS: frozenset[tuple[int, int]] = frozenset(
    {
        (od.PROFILE_ACCELERATION, 0),
        (od.PROFILE_DECELERATION, 0),
        (od.QUICK_STOP_DECELERATION, 0),
        (od.HOMING_ACCELERATION, 0),
        (od.HOMING_SPEEDS, 1),
        (od.HOMING_SPEEDS, 2),
    }
)
_MS = 1e-3


def mode_write_abort(index: int, subindex: int, value: int, values: ObjectValues) -> int | None:
    """The CiA 301 abort code for writing `value` to a mode object, or None to accept it.

    0x06090030 for an option code the drive does not offer (0x605D, 0x6086, 0x6098),
    0x06090032 for a zero ramp or homing speed, 0x06090036 for a 0x607D min above its max (or a
    max below its min). Other objects: None (their data type bounds them).
    """
    allowed = MODE_OPTION_VALUES.get((index, subindex))
    if allowed is not None and value not in allowed:
        return cia301.ABORT_VALUE_RANGE
    if (index, subindex) in POSITIVE_OBJECTS and value <= 0:
        return cia301.ABORT_VALUE_TOO_LOW
    if index == od.SOFTWARE_POSITION_LIMIT and subindex in (1, 2):
        low = value if subindex == 1 else values(od.SOFTWARE_POSITION_LIMIT, 1)
        high = value if subindex == 2 else values(od.SOFTWARE_POSITION_LIMIT, 2)
        if low > high:
            return cia301.ABORT_MAX_BELOW_MIN
    return None


def _window(values: ObjectValues, window: int, time_ms: int) -> WindowParams:
    return WindowParams(float(values(window, 0)), values(time_ms, 0) * _MS)


def profile_params(values: ObjectValues) -> ProfileParams:
    """0x6081, 0x6083, 0x6084, 0x6085, 0x607F."""
    return ProfileParams(
        float(values(od.PROFILE_VELOCITY, 0)),
        float(values(od.PROFILE_ACCELERATION, 0)),
        float(values(od.PROFILE_DECELERATION, 0)),
        float(values(od.QUICK_STOP_DECELERATION, 0)),
        float(values(od.MAX_PROFILE_VELOCITY, 0)),
    )


def software_limits(values: ObjectValues) -> SoftwareLimits:
    """0x607D sub 1 and sub 2."""
    return SoftwareLimits(
        float(values(od.SOFTWARE_POSITION_LIMIT, 1)), float(values(od.SOFTWARE_POSITION_LIMIT, 2))
    )


def pp_params(values: ObjectValues) -> PpParams:
    """Profile position's objects."""
    return PpParams(
        profile_params(values),
        values(od.HALT_OPTION, 0),
        software_limits(values),
        _window(values, od.POSITION_WINDOW, od.POSITION_WINDOW_TIME),
        _window(values, od.FOLLOWING_ERROR_WINDOW, od.FOLLOWING_ERROR_TIME),
    )


def pv_params(values: ObjectValues) -> PvParams:
    """Profile velocity's objects."""
    return PvParams(
        profile_params(values),
        values(od.HALT_OPTION, 0),
        _window(values, od.VELOCITY_WINDOW, od.VELOCITY_WINDOW_TIME),
        _window(values, od.VELOCITY_THRESHOLD, od.VELOCITY_THRESHOLD_TIME),
        float(values(od.MAX_SLIPPAGE, 0)),
    )


def homing_params(values: ObjectValues, units: DriveUnits) -> HomingParams:
    """Homing's objects; 0x2040 in A by the drive's rated current 0x6075."""
    return HomingParams(
        values(od.HOMING_METHOD, 0),
        float(values(od.HOMING_SPEEDS, 1)),
        float(values(od.HOMING_SPEEDS, 2)),
        float(values(od.HOMING_ACCELERATION, 0)),
        float(values(od.HOME_OFFSET, 0)),
        values(od.HOMING_STOP_CURRENT, 0) * units.rated_current_a / 1000.0,
        values(od.HOMING_STOP_TIME, 0) * _MS,
        float(values(od.VELOCITY_THRESHOLD, 0)),
    )


def csp_params(values: ObjectValues) -> CspParams:
    """Cyclic synchronous position's objects."""
    return CspParams(
        profile_params(values),
        values(od.HALT_OPTION, 0),
        software_limits(values),
        _window(values, od.FOLLOWING_ERROR_WINDOW, od.FOLLOWING_ERROR_TIME),
    )
