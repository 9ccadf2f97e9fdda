"""Profile velocity mode (CiA 402-2 0x6060 = 3): 0x60FF through the ramp, the velocity loop.

The target velocity 0x60FF (clamped to +-0x607F) is reached on the linear ramp of 0x6083 /
0x6084 from the present demand; a new 0x60FF replans at once. Bit 8 halt stops on the 0x605D
ramp; dropping it ramps back to 0x60FF. Statusword bit 10 target reached: |actual - target|
within 0x606D for 0x606E (with halt: the axis stands still); bit 12 speed: 1 while the speed
is 0, i.e. cleared once |actual| has stayed above the threshold 0x606F for 0x6070; bit 13 max
slippage: |demand - actual| velocity above 0x60F8 (the virtual drive's motor has no slip: this
is the velocity loop's lag). Units: increments/s, s. docs/can-modes.md, "Profile velocity".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.mode_common import (
    SW_BIT10,
    SW_BIT12,
    SW_BIT13,
    Dwell,
    Loop,
    ModeOutput,
    WindowParams,
    falling,
    rising,
)
from lca_sim.cia402.profile import HALT_SLOW_DOWN_RAMP, ProfileGenerator, ProfileParams

SW_TARGET_REACHED = SW_BIT10
SW_SPEED_ZERO = SW_BIT12
SW_MAX_SLIPPAGE = SW_BIT13

_NONE = WindowParams(0.0, 0.0)


@dataclass(frozen=True, slots=True)
class PvParams:
    """Objects of profile velocity, in increments/s and s.

    Attributes:
        profile: 0x6083, 0x6084, 0x6085, 0x607F (0x6081 is not used).
        halt_option: 0x605D.
        velocity_window: 0x606D / 0x606E (target reached).
        velocity_threshold: 0x606F / 0x6070 (speed = 0).
        max_slippage_inc_s: 0x60F8; inf: off.
    """

    profile: ProfileParams
    halt_option: int = HALT_SLOW_DOWN_RAMP
    velocity_window: WindowParams = _NONE
    velocity_threshold: WindowParams = _NONE
    max_slippage_inc_s: float = math.inf


class ProfileVelocityMode:
    """One axis in profile velocity: feed `update` every step while operation is enabled."""

    def __init__(self) -> None:
        self._generator = ProfileGenerator()
        self._controlword = 0
        self._target: float | None = None
        self._halted = False
        self._reached = Dwell()
        self._moving = Dwell()

    def enter(self, position_inc: float, velocity_inc_s: float, controlword: int) -> None:
        """Start the mode (bumpless): the ramp starts at the actual position and velocity."""
        self._generator.reset(position_inc, velocity_inc_s)
        self._controlword = controlword
        self._target = None
        self._halted = bool(controlword & CW_HALT)
        self._reached.reset()
        self._moving.reset()

    def update(
        self,
        dt_s: float,
        controlword: int,
        target_inc_s: float,
        velocity_inc_s: float,
        params: PvParams,
    ) -> ModeOutput:
        """One step.

        Args:
            dt_s: time since the last step, s.
            controlword: 0x6040.
            target_inc_s: target velocity 0x60FF, increments/s.
            velocity_inc_s: velocity actual 0x606C, increments/s.
            params: the mode's objects.
        """
        previous, self._controlword = self._controlword, controlword
        profile = params.profile
        limit = profile.max_velocity_inc_s
        target = max(-limit, min(limit, target_inc_s))
        if rising(controlword, previous, CW_HALT) or (self._halted and self._target is None):
            self._halted = True
            self._generator.stop(profile.halt_deceleration_inc_s2(params.halt_option))
            self._target = target
        elif falling(controlword, previous, CW_HALT):
            self._halted = False
            self._target = None  # replanned below
        if not self._halted and target != self._target:
            self._target = target
            self._reached.reset()
            self._generator.run_at(target, profile)
        demand = self._generator.step(dt_s)
        bits = 0
        if self._halted:
            if self._generator.done and abs(velocity_inc_s) <= params.velocity_threshold.window:
                bits |= SW_TARGET_REACHED
        else:
            inside = abs(velocity_inc_s - target) <= params.velocity_window.window
            if self._reached.update(inside, dt_s, params.velocity_window.time_s):
                bits |= SW_TARGET_REACHED
        threshold = params.velocity_threshold
        if not self._moving.update(abs(velocity_inc_s) > threshold.window, dt_s, threshold.time_s):
            bits |= SW_SPEED_ZERO
        if abs(demand.velocity_inc_s - velocity_inc_s) > params.max_slippage_inc_s:
            bits |= SW_MAX_SLIPPAGE
        return ModeOutput(Loop.VELOCITY, demand.position_inc, demand.velocity_inc_s, bits)
