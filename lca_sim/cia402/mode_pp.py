"""Profile position mode (CiA 402-2 0x6060 = 1): the set-point handshake and the positioning.

The master writes 0x607A and raises controlword bit 4 (new set-point); the drive takes it and
raises statusword bit 12 (set-point acknowledge); the master drops bit 4; the drive drops bit
12 once it can take the next set-point. Bit 5 (change set immediately) = 1 starts the new
set-point at once from the present demand; = 0 lets the running positioning finish first (a set
of set-points, buffer depth 1: one running and one waiting; a new set-point while one waits is
ignored, bit 12 stays 1 until the waiting one starts). Bit 6 = 1: 0x607A is relative to the
preceding target (0x60F2 = 0, CiA 402-2's default). Bit 8 halt stops on the 0x605D ramp and
holds; dropping it resumes towards the target. Bit 10 target reached: within 0x6067 of the
target for 0x6068 (with halt: the axis stands still); bit 13 following error (0x6065 / 0x6066).
Units: increments, s. docs/can-modes.md, "Profile position".
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.mode_common import (
    EMCY_FOLLOWING_ERROR,
    SW_BIT10,
    SW_BIT12,
    SW_BIT13,
    WINDOW_DISABLED,
    Dwell,
    FollowingErrorWatch,
    Loop,
    ModeOutput,
    SoftwareLimits,
    WindowParams,
    falling,
    rising,
)
from lca_sim.cia402.profile import HALT_SLOW_DOWN_RAMP, ProfileGenerator, ProfileParams

# Controlword bits of profile position (CiA 402-2 0x6040).
CW_NEW_SET_POINT = 1 << 4
CW_CHANGE_SET_IMMEDIATELY = 1 << 5
CW_RELATIVE = 1 << 6
# Statusword bits of profile position (CiA 402-2 0x6041).
SW_TARGET_REACHED = SW_BIT10
SW_SET_POINT_ACKNOWLEDGE = SW_BIT12
SW_FOLLOWING_ERROR = SW_BIT13


@dataclass(frozen=True, slots=True)
class PpParams:
    """Objects of profile position, in increments and s.

    Attributes:
        profile: 0x6081, 0x6083, 0x6084, 0x6085, 0x607F.
        halt_option: 0x605D (`profile.HALT_OPTIONS`).
        limits: 0x607D.
        position_window: 0x6067 / 0x6068 (target reached).
        following_error: 0x6065 / 0x6066.
    """

    profile: ProfileParams
    halt_option: int = HALT_SLOW_DOWN_RAMP
    limits: SoftwareLimits = field(default_factory=SoftwareLimits)
    position_window: WindowParams = WINDOW_DISABLED
    following_error: WindowParams = WINDOW_DISABLED


class ProfilePositionMode:
    """One axis in profile position: feed `update` every step while operation is enabled."""

    def __init__(self) -> None:
        self._generator = ProfileGenerator()
        self._controlword = 0
        self._target: float | None = None  # the set-point being run (absolute, limited)
        self._waiting: float | None = None  # the buffered one
        self._last_target = 0.0  # what a relative set-point adds to
        self._acknowledge = False
        self._halted = False
        self._reached = Dwell()
        self._following = FollowingErrorWatch()

    def enter(
        self, position_inc: float, velocity_inc_s: float, controlword: int, params: PpParams
    ) -> None:
        """Start the mode (bumpless): from the actual position and velocity, stopping if moving.

        No set-point is pending; a relative set-point then adds to the actual position.
        """
        self._generator.reset(position_inc, velocity_inc_s)
        if velocity_inc_s != 0.0:
            self._generator.stop(params.profile.deceleration_inc_s2)
        self._controlword = controlword
        self._target = self._waiting = None
        self._last_target = position_inc
        self._acknowledge = False
        self._halted = bool(controlword & CW_HALT)
        self._reached.reset()
        self._following.reset()

    @property
    def target_inc(self) -> float | None:
        """The set-point being run (absolute, after 0x607D), None before the first."""
        return self._target

    def update(
        self,
        dt_s: float,
        controlword: int,
        target_inc: float,
        position_inc: float,
        params: PpParams,
    ) -> ModeOutput:
        """One step: the handshake, the halt, the profile, the status bits.

        Args:
            dt_s: time since the last step, s.
            controlword: 0x6040 of this step.
            target_inc: 0x607A (absolute, or relative with bit 6), increments.
            position_inc: position actual 0x6064, increments.
            params: the mode's objects.
        """
        previous, self._controlword = self._controlword, controlword
        profile = params.profile
        if rising(controlword, previous, CW_NEW_SET_POINT):
            self._new_set_point(controlword, target_inc, params)
        if rising(controlword, previous, CW_HALT):
            self._halted = True
            self._generator.stop(profile.halt_deceleration_inc_s2(params.halt_option))
        elif falling(controlword, previous, CW_HALT):
            self._halted = False
            if self._target is not None:
                self._generator.move_to(self._target, profile)
        if not self._halted and self._generator.done and self._waiting is not None:
            self._start(self._waiting, profile)
            self._waiting = None
        demand = self._generator.step(dt_s)
        if not controlword & CW_NEW_SET_POINT and self._waiting is None:
            self._acknowledge = False
        following, rose = self._following.update(
            demand.position_inc, position_inc, dt_s, params.following_error
        )
        bits = SW_SET_POINT_ACKNOWLEDGE if self._acknowledge else 0
        if self._reached_now(position_inc, dt_s, params.position_window):
            bits |= SW_TARGET_REACHED
        if following:
            bits |= SW_FOLLOWING_ERROR
        return ModeOutput(
            Loop.POSITION,
            demand.position_inc,
            demand.velocity_inc_s,
            bits,
            following_error_inc=demand.position_inc - position_inc,
            emcy_code=EMCY_FOLLOWING_ERROR if rose else None,
        )

    def _new_set_point(self, controlword: int, target_inc: float, params: PpParams) -> None:
        """A rising edge of bit 4: take the set-point if the buffer has room."""
        immediate = bool(controlword & CW_CHANGE_SET_IMMEDIATELY)
        busy = not self._generator.done or (self._halted and self._target is not None)
        if not immediate and busy and self._waiting is not None:
            return  # buffer full: not acknowledged (CiA 402-2 set of set-points)
        absolute = self._last_target + target_inc if controlword & CW_RELATIVE else target_inc
        absolute = params.limits.clamp(absolute)
        self._last_target = absolute
        self._acknowledge = True
        if immediate or not busy:
            self._waiting = None
            if self._halted:
                self._target = absolute  # runs when the halt is dropped
                self._reached.reset()
            else:
                self._start(absolute, params.profile)
        else:
            self._waiting = absolute

    def _start(self, target_inc: float, profile: ProfileParams) -> None:
        self._target = target_inc
        self._reached.reset()
        self._generator.move_to(target_inc, profile)

    def _reached_now(self, position_inc: float, dt_s: float, window: WindowParams) -> bool:
        """Statusword bit 10 (CiA 402-2 profile position table)."""
        gen = self._generator
        if self._halted:  # "velocity of axis is 0"
            return gen.done and gen.point.velocity_inc_s == 0.0
        if not gen.done or self._waiting is not None:
            self._reached.reset()
            return False
        goal = self._target if self._target is not None else self._last_target
        inside = window.off or abs(position_inc - goal) <= window.window
        return self._reached.update(inside, dt_s, window.time_s)
