"""Homing (lca_sim.cia402.homing): methods 37 / 35, 17 / 18 and the mechanical stop -1 / -2.

A test axis follows the demand exactly (the velocity in the search, the position after it), with
limit switches and a wall at physical positions; the drive's frame is physical + the shifts
homing returns. After homing at the home position, 0x6064 reads 0x607C. Statusword bits 13, 12,
10 follow the CiA 402-2 homing table: 001 not started / interrupted, 000 in progress, 010
attained, 011 completed, 10x error.
"""

from __future__ import annotations

import pytest

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.homing import (
    CW_HOMING_START,
    HomingInputs,
    HomingMode,
    HomingParams,
    Phase,
)
from lca_sim.cia402.mode_common import SW_BIT10, SW_BIT12, SW_BIT13, Loop, ModeOutput
from lca_sim.errors import InvalidValueError

ENABLED = 0x0F
START = ENABLED | CW_HOMING_START
DT = 1e-3
IN_PROGRESS, NOT_STARTED, ATTAINED, COMPLETED = 0, SW_BIT10, SW_BIT12, SW_BIT12 | SW_BIT10
ERROR_MOVING, ERROR_STOPPED = SW_BIT13, SW_BIT13 | SW_BIT10


def _params(method: int, **kwargs: float) -> HomingParams:
    values = {
        "switch_speed_inc_s": 2000.0,
        "zero_speed_inc_s": 200.0,
        "acceleration_inc_s2": 10000.0,
        "home_offset_inc": 12345.0,
        "stop_current_a": 8.0,
        "stop_time_s": 0.05,
        "stop_velocity_inc_s": 1.0,
    }
    return HomingParams(method, **{**values, **kwargs})


class Rig:
    """A perfect axis at a physical position, with switches and a wall; reports the drive frame.

    Args:
        position: physical start position, increments.
        negative_below: the negative switch is active at or below this physical position.
        positive_above: the positive switch is active at or above this one.
        wall: a mechanical stop at this physical position (approached from above).
    """

    def __init__(
        self,
        position: float,
        *,
        negative_below: float | None = None,
        positive_above: float | None = None,
        wall: float | None = None,
    ) -> None:
        self.physical = position
        self.velocity = 0.0
        self.offset = 0.0  # drive frame - physical
        self.negative_below, self.positive_above, self.wall = negative_below, positive_above, wall
        self.mode = HomingMode()
        self.mode.enter(position, 0.0, ENABLED, _params(37))

    @property
    def actual(self) -> float:
        """0x6064: the physical position in the drive's (homed) frame."""
        return self.physical + self.offset

    def step(self, controlword: int, params: HomingParams) -> ModeOutput:
        """One step of the mode and of the axis."""
        pressing = self.wall is not None and self.physical <= self.wall and self.velocity == 0.0
        inputs = HomingInputs(
            self.actual,
            self.velocity,
            current_a=9.0 if pressing else 0.5,
            negative_limit=self.negative_below is not None and self.physical <= self.negative_below,
            positive_limit=self.positive_above is not None and self.physical >= self.positive_above,
        )
        out = self.mode.update(DT, controlword, inputs, params)
        self.offset += out.position_shift_inc
        if out.loop is Loop.VELOCITY:
            self.velocity = out.velocity_inc_s
            self.physical += self.velocity * DT
        else:
            self.velocity = out.velocity_inc_s
            self.physical = out.position_inc - self.offset
        if self.wall is not None and self.physical <= self.wall:
            self.physical, self.velocity = self.wall, 0.0
        return out

    def run(self, controlword: int, params: HomingParams, seconds: float) -> list[ModeOutput]:
        """Steps for `seconds`, each output."""
        return [self.step(controlword, params) for _ in range(round(seconds / DT))]


@pytest.mark.parametrize("method", [37, 35])
def test_present_position_is_home(method: int) -> None:
    """37 / 35: on the start edge 0x6064 becomes 0x607C at once; no motion; 011."""
    rig = Rig(5000.0)
    params = _params(method)
    assert rig.step(ENABLED, params).status_bits == NOT_STARTED
    out = rig.step(START, params)
    assert out.position_shift_inc == 12345.0 - 5000.0
    assert out.status_bits == COMPLETED and out.position_inc == 12345.0
    rig.run(START, params, 0.1)
    assert rig.actual == 12345.0 and rig.physical == 5000.0
    assert rig.step(ENABLED, params).status_bits == COMPLETED  # stays after bit 4 drops


def test_negative_limit_switch_method_17() -> None:
    """17: search down at sub 1, back up at sub 2; home where the switch goes off (1000)."""
    rig = Rig(5000.0, negative_below=1000.0)
    params = _params(17)
    outs = rig.run(START, params, 4.0)
    assert outs[0].status_bits == IN_PROGRESS and outs[0].loop is Loop.VELOCITY
    assert min(o.velocity_inc_s for o in outs) == pytest.approx(-2000.0)
    shifts = [o.position_shift_inc for o in outs if o.position_shift_inc]
    assert len(shifts) == 1
    # the edge is seen the step after the axis crosses 1000 upwards at 200 inc/s (0.2 inc)
    assert 12345.0 - shifts[0] == pytest.approx(1000.0, abs=0.5)
    bits = [o.status_bits for o in outs]
    assert ATTAINED in bits
    assert bits[-1] == COMPLETED
    # stopped from 200 inc/s on 0x609A = 10000: 2 inc past the home position
    assert rig.actual == pytest.approx(12345.0 + 2.0, abs=0.5)


def test_positive_limit_switch_method_18_starting_on_the_switch() -> None:
    """18 with the positive switch already on: straight to leaving it downwards at sub 2."""
    rig = Rig(9000.0, positive_above=8000.0)
    params = _params(18, home_offset_inc=0.0)
    outs = rig.run(START, params, 7.0)
    assert min(o.velocity_inc_s for o in outs) == pytest.approx(-200.0)
    assert max(o.velocity_inc_s for o in outs) <= 0.0
    assert outs[-1].status_bits == COMPLETED
    assert rig.actual == pytest.approx(-2.0, abs=0.5)


def test_the_far_switch_is_a_homing_error() -> None:
    """17 searching down but the positive switch comes on: error, moving (100) then still (101)."""
    rig = Rig(5000.0, positive_above=-1e9)  # mis-wired: the positive switch is always on
    outs = rig.run(START, _params(17), 0.5)
    assert outs[0].status_bits == ERROR_STOPPED  # it never moved
    rig = Rig(5000.0, positive_above=-1e9)
    rig.mode.enter(5000.0, -1000.0, ENABLED, _params(17))  # entered while moving
    rig.velocity = -1000.0
    outs = rig.run(START, _params(17), 0.5)
    assert outs[0].status_bits == ERROR_MOVING and outs[-1].status_bits == ERROR_STOPPED


def test_mechanical_stop_method_minus_1() -> None:
    """-1: down at sub 2 to the wall; current >= 0x2040 at standstill for 0x2041: home there."""
    rig = Rig(300.0, wall=0.0)
    params = _params(-1, home_offset_inc=-500.0)
    outs = rig.run(START, params, 2.5)
    # at 200 inc/s the wall is hit after ~1.55 s; home 50 ms of pressing later
    first = next(i for i, o in enumerate(outs) if o.position_shift_inc)
    assert first * DT == pytest.approx(1.5 + 0.01 + 0.05, abs=0.01)
    assert outs[first].position_shift_inc == -500.0
    assert outs[-1].status_bits == COMPLETED and outs[-1].loop is Loop.POSITION
    assert rig.actual == -500.0 and rig.physical == 0.0
    assert rig.mode.phase is Phase.DONE


def test_interrupt_by_bit_4_or_halt() -> None:
    """Dropping bit 4 (or halt) mid-search stops the axis: 001, and a new edge starts again."""
    for interrupt in (ENABLED, START | CW_HALT):
        rig = Rig(5000.0, negative_below=1000.0)
        params = _params(17)
        rig.run(START, params, 0.5)
        outs = rig.run(interrupt, params, 0.5)
        assert outs[0].status_bits == NOT_STARTED
        assert outs[-1].velocity_inc_s == 0.0
        rig.run(ENABLED, params, 0.01)
        outs = rig.run(START, params, 4.0)
        assert outs[-1].status_bits == COMPLETED


def test_entry_while_moving_stops_on_the_homing_ramp() -> None:
    """Entered at -1000 inc/s: 0x609A = 10000 stops it in 0.1 s (50 inc); then 001, at rest."""
    rig = Rig(5000.0)
    rig.mode.enter(5000.0, -1000.0, ENABLED, _params(37))
    outs = rig.run(ENABLED, _params(37), 0.2)
    assert outs[0].velocity_inc_s == pytest.approx(-1000.0 + 10000.0 * DT)
    assert outs[-1].velocity_inc_s == 0.0 and outs[-1].position_inc == pytest.approx(4950.0)
    assert {o.status_bits for o in outs} == {NOT_STARTED}


def test_unknown_method_and_bad_speed_are_refused() -> None:
    """0x6098 outside the offered methods, a zero speed: InvalidValueError."""
    with pytest.raises(InvalidValueError, match="0x6098"):
        _params(1)
    with pytest.raises(InvalidValueError, match="zero_speed_inc_s"):
        _params(37, zero_speed_inc_s=0.0)
