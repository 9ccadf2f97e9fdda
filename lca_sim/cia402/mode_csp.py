"""Cyclic synchronous position mode (CiA 402-2 0x6060 = 8): the master's 0x607A every cycle.

The position loop follows the target 0x607A (limited to 0x607D) as it comes, with 0x60B1 the
velocity offset as its velocity feed-forward and 0x60B2 the torque offset added to the current
demand; the drive does not interpolate between cycles. Halt (bit 8) stops on the 0x605D ramp
and holds, ignoring 0x607A. Statusword bit 10 is reserved (0), bit 12 "drive follows the command
value" (0 while halted), bit 13 following error (0x6065 / 0x6066): when it rises the output
carries EMCY 0x8611 and the caller takes the fault reaction. Units: increments, increments/s,
per mille of 0x6076. docs/can-modes.md, "Cyclic synchronous position".
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.mode_common import (
    EMCY_FOLLOWING_ERROR,
    SW_BIT12,
    SW_BIT13,
    WINDOW_DISABLED,
    FollowingErrorWatch,
    Loop,
    ModeOutput,
    SoftwareLimits,
    WindowParams,
    rising,
)
from lca_sim.cia402.profile import HALT_SLOW_DOWN_RAMP, ProfileGenerator, ProfileParams

SW_FOLLOWS_COMMAND = SW_BIT12
SW_FOLLOWING_ERROR = SW_BIT13


@dataclass(frozen=True, slots=True)
class CspParams:
    """Objects of cyclic synchronous position, in increments and s.

    Attributes:
        profile: the ramps a halt uses (0x6084, 0x6085).
        halt_option: 0x605D.
        limits: 0x607D.
        following_error: 0x6065 / 0x6066.
    """

    profile: ProfileParams
    halt_option: int = HALT_SLOW_DOWN_RAMP
    limits: SoftwareLimits = field(default_factory=SoftwareLimits)
    following_error: WindowParams = WINDOW_DISABLED


class CyclicPositionMode:
    """One axis in CSP: feed `update` every step while operation is enabled."""

    def __init__(self) -> None:
        self._halt = ProfileGenerator()
        self._controlword = 0
        self._following = FollowingErrorWatch()
        self._last_demand: float | None = None  # the last cycle's demand, for its rate

    def enter(self, position_inc: float, velocity_inc_s: float, controlword: int) -> None:
        """Start the mode: a master sets 0x607A to 0x6064 before it switches (bumpless)."""
        self._halt.reset(position_inc, velocity_inc_s)
        self._controlword = controlword & ~CW_HALT  # a halt already on stops from here
        self._following.reset()
        self._last_demand = None

    def update(
        self,
        dt_s: float,
        controlword: int,
        target_inc: float,
        position_inc: float,
        params: CspParams,
        *,
        velocity_offset_inc_s: float = 0.0,
        torque_offset_permille: int = 0,
    ) -> ModeOutput:
        """One step.

        Args:
            dt_s: time since the last step, s.
            controlword: 0x6040.
            target_inc: target position 0x607A, increments.
            position_inc: position actual 0x6064, increments.
            params: the mode's objects.
            velocity_offset_inc_s: 0x60B1, increments/s.
            torque_offset_permille: 0x60B2, per mille of 0x6076.
        """
        previous, self._controlword = self._controlword, controlword
        halted = bool(controlword & CW_HALT)
        if halted:
            if rising(controlword, previous, CW_HALT):
                self._halt.stop(params.profile.halt_deceleration_inc_s2(params.halt_option))
            point = self._halt.step(dt_s)
            demand, velocity = point.position_inc, point.velocity_inc_s
        else:
            demand, velocity = params.limits.clamp(target_inc), velocity_offset_inc_s
            # A halt ramps down from the speed the targets moved at (their last step's rate,
            # plus 0x60B1), not from the offset alone: else the demand stopped at once.
            last, self._last_demand = self._last_demand, demand
            rate = 0.0 if last is None or dt_s <= 0.0 else (demand - last) / dt_s
            self._halt.reset(demand, velocity + rate)
        following, rose = self._following.update(demand, position_inc, dt_s, params.following_error)
        bits = 0 if halted else SW_FOLLOWS_COMMAND
        if following:
            bits |= SW_FOLLOWING_ERROR
        return ModeOutput(
            Loop.POSITION,
            demand,
            velocity,
            bits,
            torque_offset_permille=0 if halted else torque_offset_permille,
            following_error_inc=demand - position_inc,
            emcy_code=EMCY_FOLLOWING_ERROR if rose else None,
        )
