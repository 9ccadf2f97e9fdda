"""Profile velocity (lca_sim.cia402.mode_pv): the ramp to 0x60FF and statusword bits 10, 12, 13.

The axis follows the velocity demand exactly unless a test says otherwise: from rest to
2000 inc/s on 0x6083 = 500 inc/s^2 takes 4 s; bit 10 once inside 0x606D for 0x606E; bit 12
(speed = 0) cleared once above 0x606F for 0x6070; bit 13 when the demand and the actual velocity
part by more than 0x60F8.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.mode_common import Loop, ModeOutput
from lca_sim.cia402.mode_common import WindowParams as Window
from lca_sim.cia402.mode_pv import (
    SW_MAX_SLIPPAGE,
    SW_SPEED_ZERO,
    SW_TARGET_REACHED,
    ProfileVelocityMode,
    PvParams,
)
from lca_sim.cia402.profile import ProfileParams

ENABLED = 0x0F
DT = 1e-3
PARAMS = PvParams(
    ProfileParams(0.0, 500.0, 250.0, 5000.0, max_velocity_inc_s=3000.0),
    velocity_window=Window(10.0, 0.005),
    velocity_threshold=Window(20.0, 0.010),
    max_slippage_inc_s=100.0,
)


class Axis:
    """A PV axis whose actual velocity is its demand (or `stuck_at`)."""

    def __init__(self, velocity: float = 0.0) -> None:
        self.mode = ProfileVelocityMode()
        self.velocity = velocity
        self.stuck_at: float | None = None
        self.mode.enter(0.0, velocity, ENABLED)

    def step(self, controlword: int, target: float) -> ModeOutput:
        """One step of the mode and of the axis."""
        out = self.mode.update(DT, controlword, target, self.velocity, PARAMS)
        self.velocity = out.velocity_inc_s if self.stuck_at is None else self.stuck_at
        return out

    def trace(self, controlword: int, target: float, seconds: float) -> list[ModeOutput]:
        """Steps for `seconds`, each output."""
        return [self.step(controlword, target) for _ in range(round(seconds / DT))]


def test_reaches_the_target_velocity_after_v_over_a() -> None:
    """0 -> 2000 inc/s at 500 inc/s^2: 4 s; bit 10 from 3.98 s + 5 ms; position v^2 / 2a."""
    axis = Axis()
    outs = axis.trace(ENABLED, 2000.0, 5.0)
    assert outs[0].loop is Loop.VELOCITY
    assert outs[3999].velocity_inc_s == pytest.approx(2000.0)  # t = 4.000 s
    assert outs[3990].velocity_inc_s == pytest.approx(1995.5)
    first = next(i for i, o in enumerate(outs) if o.status_bits & SW_TARGET_REACHED)
    # the axis reports last step's velocity: inside from 3.981 s, 5 ms more, +-1 step of rounding
    assert 3.985 <= (first + 1) * DT <= 3.988
    assert outs[3999].position_inc == pytest.approx(4000.0)


def test_speed_bit_is_zero_speed_with_its_threshold_time() -> None:
    """Bit 12 = 1 at rest; it clears 10 ms after |v| passes 20 inc/s (at 0.04 s); back at 0."""
    axis = Axis()
    outs = axis.trace(ENABLED, 1000.0, 0.1)
    speed = [bool(o.status_bits & SW_SPEED_ZERO) for o in outs]
    last_zero = max(i for i, zero in enumerate(speed) if zero)
    assert (last_zero + 1) * DT == pytest.approx(0.04 + 0.010, abs=1.5e-3)
    assert not any(speed[last_zero + 1 :])
    outs = axis.trace(ENABLED, 0.0, 1.0)  # from 50 inc/s to 0 at 250 inc/s^2: 0.2 s
    assert outs[-1].velocity_inc_s == 0.0 and outs[-1].status_bits & SW_SPEED_ZERO


def test_max_slippage_when_the_axis_lags() -> None:
    """Bit 13: |demand - actual| > 0x60F8 (100 inc/s): with the axis held, from 0.2 s on."""
    axis = Axis()
    axis.stuck_at = 0.0
    outs = axis.trace(ENABLED, 2000.0, 0.4)
    slipping = [bool(o.status_bits & SW_MAX_SLIPPAGE) for o in outs]
    assert slipping.index(True) + 1 in (200, 201)  # 500 inc/s^2 x 0.2 s = 100 inc/s


def test_halt_decelerates_and_reports_standstill() -> None:
    """Bit 8 at 2000 inc/s: 0x6084 = 250 inc/s^2 stops in 8 s; bit 10 then; release: back up."""
    axis = Axis(2000.0)
    axis.trace(ENABLED, 2000.0, 0.01)
    outs = axis.trace(ENABLED | CW_HALT, 2000.0, 8.1)
    assert outs[3999].velocity_inc_s == pytest.approx(1000.0)
    assert not outs[3999].status_bits & SW_TARGET_REACHED
    assert outs[-1].velocity_inc_s == 0.0 and outs[-1].status_bits & SW_TARGET_REACHED
    outs = axis.trace(ENABLED, 2000.0, 4.0)
    assert outs[-1].velocity_inc_s == pytest.approx(2000.0)


def test_target_clamped_to_max_profile_velocity_and_reversal() -> None:
    """0x60FF = -9000 with 0x607F = 3000: the ramp ends at -3000 (through 0 with d, then a)."""
    axis = Axis(1000.0)
    outs = axis.trace(ENABLED, -9000.0, 10.5)
    assert outs[-1].velocity_inc_s == -3000.0
    # 1000 -> 0 at 250 (4 s), 0 -> -3000 at 500 (6 s)
    assert outs[3999].velocity_inc_s == pytest.approx(0.0, abs=1e-6)
    assert outs[-1].status_bits & SW_TARGET_REACHED


def test_entry_is_bumpless() -> None:
    """Entering at 800 inc/s with 0x60FF = 800: the demand stays at 800 (no jump to 0)."""
    axis = Axis(800.0)
    outs = axis.trace(ENABLED, 800.0, 0.01)
    assert {o.velocity_inc_s for o in outs} == {800.0}


@given(
    position=st.floats(-1e7, 1e7),
    velocity=st.floats(-3000.0, 3000.0),
    target=st.floats(-1e4, 1e4),
)
def test_mode_change_is_bumpless(position: float, velocity: float, target: float) -> None:
    """Entered at any actual state: the first demand moves by at most one step of the ramp."""
    mode = ProfileVelocityMode()
    mode.enter(position, velocity, ENABLED)
    out = mode.update(DT, ENABLED, target, velocity, PARAMS)
    assert abs(out.velocity_inc_s - velocity) <= 500.0 * DT + 1e-9
    assert abs(out.position_inc - position - velocity * DT) <= 500.0 * DT * DT + 1e-6
