"""Profile position (lca_sim.cia402.mode_pp): the CiA 402-2 set-point handshake, bit by bit.

The axis follows the demand exactly (actual = 0x6062) unless a test holds it, so the bit
sequences are the mode's own: bit 4 up -> bit 12 up; bit 4 down -> bit 12 down (or not while a
set-point waits in the buffer); bit 10 once the target is held for 0x6068; bit 13 and one EMCY
0x8611 when the axis lags beyond 0x6065 for longer than 0x6066.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.mode_common import EMCY_FOLLOWING_ERROR, Loop, ModeOutput, SoftwareLimits
from lca_sim.cia402.mode_common import WindowParams as Window
from lca_sim.cia402.mode_pp import (
    CW_CHANGE_SET_IMMEDIATELY,
    CW_NEW_SET_POINT,
    CW_RELATIVE,
    SW_FOLLOWING_ERROR,
    SW_SET_POINT_ACKNOWLEDGE,
    SW_TARGET_REACHED,
    PpParams,
    ProfilePositionMode,
)
from lca_sim.cia402.profile import ProfileParams

ENABLED = 0x0F  # enable operation
DT = 1e-3
# 1000 inc/s, 1000 inc/s^2 both ways: 1000 inc is a triangle (1 s up, 1 s down)
PARAMS = PpParams(
    ProfileParams(1000.0, 1000.0, 1000.0, 10000.0),
    position_window=Window(10.0, 0.005),
    following_error=Window(100.0, 0.010),
)
ACK, REACHED, FOLLOWING = SW_SET_POINT_ACKNOWLEDGE, SW_TARGET_REACHED, SW_FOLLOWING_ERROR


class Axis:
    """A PP axis whose actual position is its demand (or held where `stuck_at` says)."""

    def __init__(self, position: float = 0.0, params: PpParams = PARAMS) -> None:
        self.mode = ProfilePositionMode()
        self.params = params
        self.position = position
        self.stuck_at: float | None = None
        self.mode.enter(position, 0.0, ENABLED, params)

    def step(self, controlword: int, target: float = 0.0) -> ModeOutput:
        """One step of the mode and of the axis."""
        out = self.mode.update(DT, controlword, target, self.position, self.params)
        self.position = out.position_inc if self.stuck_at is None else self.stuck_at
        return out

    def run(self, controlword: int, seconds: float, target: float = 0.0) -> ModeOutput:
        """Steps for `seconds`, the last output."""
        out = self.step(controlword, target)
        for _ in range(round(seconds / DT) - 1):
            out = self.step(controlword, target)
        return out


def _bits(out: ModeOutput) -> int:
    return out.status_bits & (ACK | REACHED | FOLLOWING)


def test_single_set_point_handshake_and_target_reached() -> None:
    """CiA 402-2 single set-point: bit 4 up -> 12 up, bit 4 down -> 12 down; 10 at the end."""
    axis = Axis()
    assert _bits(axis.run(ENABLED, 0.01)) == REACHED  # at rest on the preceding target
    out = axis.step(ENABLED | CW_NEW_SET_POINT, 1000.0)
    assert _bits(out) == ACK
    assert out.loop is Loop.POSITION
    assert _bits(axis.step(ENABLED | CW_NEW_SET_POINT, 1000.0)) == ACK  # held until bit 4 drops
    assert _bits(axis.step(ENABLED, 1000.0)) == 0
    # triangle: 1000 inc at 1000 inc/s^2 peaks at 1000 inc/s after 1 s, ends at 2 s
    out = axis.run(ENABLED, 1.95)
    assert _bits(out) == 0
    assert 0.0 < 1000.0 - axis.position < 10.0  # inside the window, the profile not done
    out = axis.run(ENABLED, 0.06)
    assert axis.position == 1000.0 and out.velocity_inc_s == 0.0
    assert _bits(out) == REACHED
    assert out.following_error_inc == 0.0


def test_target_reached_waits_for_the_window_time() -> None:
    """Bit 10 only once the axis has been inside 0x6067 for 0x6068 (5 ms here)."""
    axis = Axis()
    axis.stuck_at = 50.0  # outside the window of 100 +- 10 until released
    axis.step(ENABLED | CW_NEW_SET_POINT, 100.0)
    out = axis.run(ENABLED, 1.0)
    assert out.position_inc == 100.0 and _bits(out) & REACHED == 0
    axis.stuck_at = axis.position = 95.0
    bits = [_bits(axis.step(ENABLED)) & REACHED for _ in range(8)]
    assert bits == [0, 0, 0, 0, 0, REACHED, REACHED, REACHED]


def test_set_of_set_points_buffers_one() -> None:
    """Bit 5 = 0 mid-move: the next set-point waits (12 stays up), a third one is refused."""
    axis = Axis()
    axis.step(ENABLED | CW_NEW_SET_POINT, 1000.0)
    axis.run(ENABLED, 0.5)
    assert _bits(axis.step(ENABLED | CW_NEW_SET_POINT, 3000.0)) == ACK
    out = axis.run(ENABLED, 0.5, 3000.0)
    assert _bits(out) == ACK  # bit 4 is down, but the buffer is full
    axis.step(ENABLED | CW_NEW_SET_POINT, -5000.0)  # a third: not taken
    assert axis.mode.target_inc == 1000.0
    out = axis.run(ENABLED, 1.1)  # the first move ends at 2 s; the second starts
    assert axis.mode.target_inc == 3000.0
    assert _bits(out) == 0  # 12 down once the buffered set-point runs; 10 not yet
    out = axis.run(ENABLED, 4.0)
    assert axis.position == 3000.0 and _bits(out) == REACHED


def test_change_set_immediately_retargets_without_a_velocity_jump() -> None:
    """Bit 5 = 1: the new target starts at once, from the present demand velocity."""
    axis = Axis()
    axis.step(ENABLED | CW_NEW_SET_POINT, 1000.0)
    before = axis.run(ENABLED, 0.8)
    out = axis.step(ENABLED | CW_NEW_SET_POINT | CW_CHANGE_SET_IMMEDIATELY, -2000.0)
    assert _bits(out) == ACK
    assert abs(out.velocity_inc_s - before.velocity_inc_s) <= 1000.0 * DT + 1e-9
    assert axis.mode.target_inc == -2000.0
    out = axis.run(ENABLED | CW_CHANGE_SET_IMMEDIATELY, 8.0)
    assert axis.position == -2000.0 and _bits(out) == REACHED


def test_relative_moves_add_to_the_preceding_target() -> None:
    """Bit 6: 0x607A adds to the preceding target (0x60F2 = 0): 5000 + 1000 + 1000 = 7000."""
    axis = Axis(5000.0)
    axis.step(ENABLED | CW_NEW_SET_POINT | CW_RELATIVE, 1000.0)
    axis.run(ENABLED | CW_RELATIVE, 3.0)
    assert axis.position == 6000.0
    axis.step(ENABLED | CW_NEW_SET_POINT | CW_RELATIVE, 1000.0)
    out = axis.run(ENABLED | CW_RELATIVE, 3.0)
    assert axis.position == 7000.0 and _bits(out) == REACHED


def test_halt_stops_on_the_deceleration_and_resumes() -> None:
    """Bit 8 at 1000 inc/s: stop in 1 s (0x6084), bit 10 = standstill; release: on to target."""
    axis = Axis()
    axis.step(ENABLED | CW_NEW_SET_POINT, 10000.0)
    out = axis.run(ENABLED, 2.0)
    assert out.velocity_inc_s == pytest.approx(1000.0)
    where = axis.position
    out = axis.run(ENABLED | CW_HALT, 0.5)
    assert _bits(out) == 0  # decelerating
    out = axis.run(ENABLED | CW_HALT, 0.6)
    assert out.velocity_inc_s == 0.0 and _bits(out) == REACHED  # "velocity of axis is 0"
    assert axis.position == pytest.approx(where + 500.0, abs=2.0)
    out = axis.run(ENABLED, 12.0)
    assert axis.position == 10000.0 and _bits(out) == REACHED


def test_following_error_sets_bit_13_and_one_emcy() -> None:
    """The axis stuck at 0: 0x60F4 grows; beyond 100 inc for 10 ms, bit 13 and EMCY 0x8611."""
    axis = Axis()
    axis.stuck_at = 0.0
    axis.step(ENABLED | CW_NEW_SET_POINT, 1000.0)
    outs = [axis.step(ENABLED) for _ in range(1000)]
    # demand = t^2 / 2 * 1000: beyond 100 inc after 0.447 s, the bit 10 ms later
    first = next(i for i, o in enumerate(outs) if o.status_bits & FOLLOWING)
    assert first * DT == pytest.approx(0.4572, abs=2e-3)
    assert [o.emcy_code for o in outs].count(EMCY_FOLLOWING_ERROR) == 1
    assert outs[first].emcy_code == EMCY_FOLLOWING_ERROR
    assert outs[-1].following_error_inc == pytest.approx(500.0, abs=1.0)


def test_targets_beyond_the_software_limits_are_limited() -> None:
    """0x607D [-500, 800]: a target of 1000 ends at 800; a relative one from there too."""
    params = PpParams(PARAMS.profile, limits=SoftwareLimits(-500.0, 800.0))
    axis = Axis(params=params)
    axis.step(ENABLED | CW_NEW_SET_POINT, 1000.0)
    axis.run(ENABLED, 3.0)
    assert axis.position == 800.0
    axis.step(ENABLED | CW_NEW_SET_POINT, -2000.0)
    axis.run(ENABLED, 4.0)
    assert axis.position == -500.0


def test_entering_while_moving_is_bumpless() -> None:
    """Entry at 500 inc/s: the demand starts at the actual state and stops on 0x6084."""
    mode = ProfilePositionMode()
    mode.enter(2000.0, 500.0, ENABLED, PARAMS)
    first = mode.update(DT, ENABLED, 0.0, 2000.0, PARAMS)
    assert first.position_inc == pytest.approx(2000.0 + 500.0 * DT, abs=1e-3)
    assert first.velocity_inc_s == pytest.approx(500.0 - 1000.0 * DT)
    for _ in range(1000):
        out = mode.update(DT, ENABLED, 0.0, first.position_inc, PARAMS)
    assert out.velocity_inc_s == 0.0
    assert out.position_inc == pytest.approx(2000.0 + 125.0)  # v^2 / 2d


@given(position=st.floats(-1e7, 1e7), velocity=st.floats(-5000.0, 5000.0))
def test_mode_change_is_bumpless(position: float, velocity: float) -> None:
    """Entered at any actual state: the demand starts there and stops on 0x6084."""
    mode = ProfilePositionMode()
    mode.enter(position, velocity, ENABLED, PARAMS)
    out = mode.update(DT, ENABLED, 0.0, position, PARAMS)
    assert abs(out.velocity_inc_s - velocity) <= 1000.0 * DT + 1e-9
    assert abs(out.position_inc - position - velocity * DT) <= 1000.0 * DT * DT + 1e-6
    stop = position + velocity * abs(velocity) / 2000.0
    for _ in range(5 + round(abs(velocity) / 1000.0 / DT)):
        out = mode.update(DT, ENABLED, 0.0, out.position_inc, PARAMS)
    assert out.velocity_inc_s == 0.0 and out.position_inc == pytest.approx(stop, abs=1e-6)
