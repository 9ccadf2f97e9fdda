"""Cyclic synchronous position (lca_sim.cia402.mode_csp): follow 0x607A, bits 12 / 13, EMCY.

The demand is the target as it comes, limited to 0x607D, with 0x60B1 as velocity and 0x60B2 as
torque offset; bit 12 while it follows (not halted); bit 13 and one EMCY 0x8611 once the axis
lags beyond 0x6065 for longer than 0x6066 (0xFFFFFFFF: never).
"""

from __future__ import annotations

import pytest

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.mode_common import (
    EMCY_FOLLOWING_ERROR,
    SW_BIT10,
    WINDOW_OFF,
    Loop,
    SoftwareLimits,
)
from lca_sim.cia402.mode_common import WindowParams as Window
from lca_sim.cia402.mode_csp import (
    SW_FOLLOWING_ERROR,
    SW_FOLLOWS_COMMAND,
    CspParams,
    CyclicPositionMode,
)
from lca_sim.cia402.profile import ProfileParams

ENABLED = 0x0F
DT = 2e-3  # a 500 Hz SYNC
PARAMS = CspParams(
    ProfileParams(1000.0, 1000.0, 1000.0, 10000.0),
    limits=SoftwareLimits(-1e5, 1e5),
    following_error=Window(100.0, 0.010),
)


def _mode(position: float = 0.0) -> CyclicPositionMode:
    mode = CyclicPositionMode()
    mode.enter(position, 0.0, ENABLED)
    return mode


def test_follows_the_target_with_its_offsets() -> None:
    """Demand = 0x607A, velocity = 0x60B1, torque offset 0x60B2; bit 12, never bit 10."""
    mode = _mode()
    for k in range(1, 50):
        target = 40.0 * k  # 20000 inc/s, the axis right behind it
        out = mode.update(
            DT,
            ENABLED,
            target,
            target - 40.0,
            PARAMS,
            velocity_offset_inc_s=20000.0,
            torque_offset_permille=-30,
        )
        assert out.loop is Loop.POSITION
        assert (out.position_inc, out.velocity_inc_s) == (target, 20000.0)
        assert out.torque_offset_permille == -30
        assert out.following_error_inc == 40.0
        assert out.status_bits == SW_FOLLOWS_COMMAND  # bit 10 is reserved in CSP
        assert not out.status_bits & SW_BIT10


def test_software_limits_limit_the_target() -> None:
    """0x607D: a target of 2e5 is followed as 1e5."""
    out = _mode(9e4).update(DT, ENABLED, 2e5, 9e4, PARAMS)
    assert out.position_inc == 1e5


def test_following_error_bit_13_and_one_emcy() -> None:
    """Axis stuck at 0, target 150 (beyond 100): bit 13 after 10 ms (5 cycles), EMCY once."""
    mode = _mode()
    outs = [mode.update(DT, ENABLED, 150.0, 0.0, PARAMS) for _ in range(10)]
    bits = [bool(o.status_bits & SW_FOLLOWING_ERROR) for o in outs]
    assert bits == [False] * 5 + [True] * 5
    assert [o.emcy_code for o in outs] == [None] * 5 + [EMCY_FOLLOWING_ERROR] + [None] * 4
    back = mode.update(DT, ENABLED, 150.0, 100.0, PARAMS)  # within the window again
    assert not back.status_bits & SW_FOLLOWING_ERROR and back.emcy_code is None


def test_following_error_window_off() -> None:
    """0x6065 = 0xFFFFFFFF switches the watch off."""
    params = CspParams(PARAMS.profile, following_error=Window(WINDOW_OFF, 0.0))
    mode = _mode()
    outs = [mode.update(DT, ENABLED, 1e6, 0.0, params) for _ in range(10)]
    assert not any(o.status_bits & SW_FOLLOWING_ERROR for o in outs)


def test_halt_stops_on_the_ramp_and_ignores_the_target() -> None:
    """Bit 8 at 500 inc/s feed-forward: to rest on 0x6084 (0.5 s, 125 inc); bit 12 off."""
    mode = _mode()
    mode.update(DT, ENABLED, 1000.0, 1000.0, PARAMS, velocity_offset_inc_s=500.0)
    outs = [
        mode.update(DT, ENABLED | CW_HALT, 5000.0, 1000.0, PARAMS, torque_offset_permille=50)
        for _ in range(300)
    ]
    assert outs[0].velocity_inc_s == pytest.approx(500.0 - 1000.0 * DT)
    assert outs[-1].position_inc == pytest.approx(1125.0) and outs[-1].velocity_inc_s == 0.0
    assert all(o.status_bits & SW_FOLLOWS_COMMAND == 0 for o in outs)
    assert all(o.torque_offset_permille == 0 for o in outs)
    out = mode.update(DT, ENABLED, 1130.0, 1125.0, PARAMS)
    assert out.position_inc == 1130.0 and out.status_bits == SW_FOLLOWS_COMMAND


def test_halt_ramps_down_from_the_speed_the_targets_moved_at() -> None:
    """Targets at 500 inc/s, no 0x60B1: the halt stops on 0x6084 from 500 inc/s, 125 inc on."""
    mode = _mode()
    for k in range(1, 51):  # 1 increment per 2 ms cycle: 500 inc/s, up to 50
        mode.update(DT, ENABLED, float(k), float(k), PARAMS)
    outs = [mode.update(DT, ENABLED | CW_HALT, 5000.0, 50.0, PARAMS) for _ in range(300)]
    assert outs[0].velocity_inc_s == pytest.approx(500.0 - 1000.0 * DT)
    assert outs[-1].position_inc == pytest.approx(50.0 + 125.0)
    assert outs[-1].velocity_inc_s == 0.0
