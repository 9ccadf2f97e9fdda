"""The modes' parameters from the object values (lca_sim.cia402.mode_params), write checks."""

from __future__ import annotations

import pytest

from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import DriveUnits
from lca_sim.cia402.mode_common import SoftwareLimits, WindowParams
from lca_sim.cia402.mode_params import (
    csp_params,
    homing_params,
    mode_write_abort,
    pp_params,
    pv_params,
)
from lca_sim.cia402.profile import ProfileParams

REV = 65536


def _defaults(index: int, subindex: int) -> int:
    default = od.entry(index, subindex).default
    assert default is not None
    return default


def test_the_table_defaults_make_valid_parameters() -> None:
    """Every mode builds from the shipped defaults, in increments and s (docs/can-modes.md)."""
    profile = ProfileParams(10 * REV, 10 * REV, 10 * REV, 50 * REV, 100 * REV)
    pp = pp_params(_defaults)
    assert pp.profile == profile and pp.halt_option == 1
    assert pp.limits == SoftwareLimits()
    assert pp.position_window == WindowParams(REV // 8, 0.010)
    assert pp.following_error == WindowParams(10 * REV, 0.010)
    pv = pv_params(_defaults)
    assert pv.velocity_window == WindowParams(REV // 8, 0.010)
    assert pv.velocity_threshold == WindowParams(REV // 8, 0.010)
    assert pv.max_slippage_inc_s == 2**31 - 1
    homing = homing_params(_defaults, DriveUnits(1.2, 10.0, REV))
    assert (homing.method, homing.switch_speed_inc_s, homing.zero_speed_inc_s) == (
        37,
        5 * REV,
        REV,
    )
    assert homing.stop_current_a == pytest.approx(8.0)  # 800 per mille of 10 A
    assert homing.stop_time_s == pytest.approx(0.1)
    assert csp_params(_defaults).following_error == pp.following_error


@pytest.mark.parametrize(
    ("index", "subindex", "value", "abort"),
    [
        (od.HALT_OPTION, 0, 1, None),
        (od.HALT_OPTION, 0, 3, 0x06090030),  # current-limit halt: not offered
        (od.MOTION_PROFILE_TYPE, 0, 1, 0x06090030),
        (od.HOMING_METHOD, 0, -1, None),
        (od.HOMING_METHOD, 0, 1, 0x06090030),
        (od.PROFILE_ACCELERATION, 0, 0, 0x06090032),
        (od.HOMING_SPEEDS, 2, 0, 0x06090032),
        (od.HOMING_SPEEDS, 2, 1, None),
        (od.SOFTWARE_POSITION_LIMIT, 1, 2**31 - 1, None),  # min = max: allowed
        (od.PROFILE_VELOCITY, 0, 0, None),  # 0 is a velocity: no move
    ],
)
def test_write_checks(index: int, subindex: int, value: int, abort: int | None) -> None:
    """CiA 301 abort codes for the values a mode cannot run with."""
    assert mode_write_abort(index, subindex, value, _defaults) == abort


def test_software_limit_min_above_max_is_refused() -> None:
    """0x607D: min above the stored max, or max below the stored min: 0x06090036."""
    stored = {(od.SOFTWARE_POSITION_LIMIT, 1): -100, (od.SOFTWARE_POSITION_LIMIT, 2): 100}

    def values(index: int, subindex: int) -> int:
        return stored[(index, subindex)]

    assert mode_write_abort(od.SOFTWARE_POSITION_LIMIT, 1, 101, values) == 0x06090036
    assert mode_write_abort(od.SOFTWARE_POSITION_LIMIT, 2, -101, values) == 0x06090036
    assert mode_write_abort(od.SOFTWARE_POSITION_LIMIT, 2, -100, values) is None
