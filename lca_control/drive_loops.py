"""The loops a CiA 402 servo drive closes itself, for one axis (pure: no clock, no I/O).

    position target --[P + velocity feed-forward]--> velocity setpoint --[velocity PI]--> current
    setpoint (A) --> the drive's current loop (not here: the plant runs it at the model rate)

`DriveLoops` runs in one of three modes: `position` (cyclic synchronous position, CiA 402-2
mode 8), `velocity` (mode 9) or `current` (mode 10, pass-through). It is the one implementation
behind the simulator node's drive modes and the virtual drive's CSP / CSV / CST, so both plants
behave as the same drive. Joint-side units throughout: rad and rad/s (m and m/s for the lift);
the velocity PI is the paper's section 6 loop (`lca_control.cascade`), and its law and bumpless
re-base are `lca_control.pi`'s `pi_law` / `pi_rebase`.

Default position gain: 15 1/s. The velocity loop's crossover is ~100 rad/s (docs/control.md);
a P position loop over it is then nearly first order with time constant 1 / kp (67 ms), and a
crossover near 15 rad/s keeps a factor ~7 of separation, so the inner loop's phase lag costs
the outer one only a few degrees and a position step does not overshoot.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from lca_control.cascade import (
    PAPER_VELOCITY_KP_A_PER_RAD_S,
    PAPER_VELOCITY_TI_S,
    position_law,
)
from lca_control.pi import ControlParamError, PIParams, pi_law, pi_rebase

DEFAULT_POSITION_KP_PER_S = 15.0
DEFAULT_VELOCITY_LIMIT = 0.2  # rad/s (m/s for the lift): the controller's own default cap


class DriveMode(enum.Enum):
    """What the drive's command is, with its CiA 402-2 mode of operation (0x6060)."""

    POSITION = "position"  # cyclic synchronous position, 8
    VELOCITY = "velocity"  # cyclic synchronous velocity, 9
    CURRENT = "current"  # cyclic synchronous torque, 10 (a current setpoint, A)

    @classmethod
    def parse(cls, name: str) -> DriveMode:
        """The mode of this name.

        Raises:
            ControlParamError: not a mode's name (the valid ones are listed).
        """
        try:
            return cls(name)
        except ValueError:
            valid = ", ".join(m.value for m in cls)
            raise ControlParamError(f"unknown drive mode {name!r}; valid: {valid}") from None


@dataclass(frozen=True, slots=True)
class DriveLoopParams:
    """Gains and limits of one axis's drive loops.

    Attributes:
        velocity: the velocity PI (A per rad/s, Ti in s); its output limits are the drive's
            current limits, A (in current mode too).
        position_kp_per_s: position loop gain, velocity per position error, 1/s.
        velocity_limit: |velocity setpoint| cap, rad/s (m/s), in position and velocity mode.
        velocity_feedforward_gain: the position target's derivative added to the velocity
            setpoint (position mode), 0 (off) to 1 (full).
        current_feedforward_a_per_rad_s2: current per joint acceleration (A per rad/s^2, per
            m/s^2 for the lift: J / (k_t N)), applied to the feed-forward velocity's derivative;
            0 (default) is off.
    """

    velocity: PIParams
    position_kp_per_s: float = DEFAULT_POSITION_KP_PER_S
    velocity_limit: float = DEFAULT_VELOCITY_LIMIT
    velocity_feedforward_gain: float = 1.0
    current_feedforward_a_per_rad_s2: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.position_kp_per_s) and self.position_kp_per_s >= 0.0):
            raise ControlParamError(f"position_kp_per_s must be >= 0, got {self.position_kp_per_s}")
        if not (math.isfinite(self.velocity_limit) and self.velocity_limit > 0.0):
            raise ControlParamError(f"velocity_limit must be > 0, got {self.velocity_limit}")
        if not 0.0 <= self.velocity_feedforward_gain <= 1.0:
            raise ControlParamError(
                f"velocity_feedforward_gain must be in [0, 1], got {self.velocity_feedforward_gain}"
            )
        if not (
            math.isfinite(self.current_feedforward_a_per_rad_s2)
            and self.current_feedforward_a_per_rad_s2 >= 0.0
        ):
            raise ControlParamError(
                "current_feedforward_a_per_rad_s2 must be >= 0, got "
                f"{self.current_feedforward_a_per_rad_s2}"
            )


def paper_drive_loops(
    current_limit_a: float,
    position_kp_per_s: float = DEFAULT_POSITION_KP_PER_S,
    velocity_limit: float = DEFAULT_VELOCITY_LIMIT,
) -> DriveLoopParams:
    """The section 6 velocity PI (316.23 A per rad/s, Ti 10 ms) within +-current_limit_a."""
    return DriveLoopParams(
        velocity=PIParams(
            PAPER_VELOCITY_KP_A_PER_RAD_S, PAPER_VELOCITY_TI_S, -current_limit_a, current_limit_a
        ),
        position_kp_per_s=position_kp_per_s,
        velocity_limit=velocity_limit,
    )


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


class DriveLoops:
    """One axis's drive loops in one mode; each update takes its own dt.

    Position mode: v = clamp(g dx*/dt + v_off + kp (x* - x), +-velocity_limit), the velocity PI
    gives the current. Velocity mode: v = clamp(v*, ...), same PI. Current mode: the target
    clamped to the current limits. In position and velocity mode `current_target_a` is an
    additive current offset (CiA 402-2 0x60B2 torque offset), and in position mode
    `velocity_target` a velocity offset (0x60B1); the total stays within the current limits.

    A sample with a non-finite input is rejected: the output holds, `rejected_samples` counts.
    """

    def __init__(self, params: DriveLoopParams, mode: DriveMode = DriveMode.CURRENT) -> None:
        self._params = params
        self._mode = mode
        self._integral = 0.0  # the velocity PI's integral action, A
        self._output_a = 0.0
        self._last_error = 0.0  # the velocity PI's last error, rad/s
        self._position_target: float | None = None  # in force (position mode)
        self._last_position_target: float | None = None  # for the velocity feed-forward
        self._last_feedforward: float | None = None  # for the current feed-forward
        self.velocity_setpoint = 0.0  # the last velocity setpoint, rad/s (m/s)
        self.rejected_samples = 0

    @property
    def params(self) -> DriveLoopParams:
        """The gains and limits in use."""
        return self._params

    @property
    def mode(self) -> DriveMode:
        """The mode in force."""
        return self._mode

    @property
    def current_setpoint_a(self) -> float:
        """The last output, A."""
        return self._output_a

    @property
    def position_target(self) -> float | None:
        """The position target in force (position mode), rad (m); None before one."""
        return self._position_target

    def update(
        self,
        dt_s: float,
        *,
        position: float,
        velocity: float,
        position_target: float | None = None,
        velocity_target: float = 0.0,
        current_target_a: float = 0.0,
    ) -> float:
        """One drive cycle: the current setpoint, A.

        Args:
            dt_s: the cycle's length, s.
            position, velocity: the measured joint position (rad, m) and velocity (rad/s, m/s).
            position_target: position mode's target; None keeps the one in force (at first the
                position the mode started from).
            velocity_target: velocity mode's target; position mode's velocity offset.
            current_target_a: current mode's target; the others' current offset.

        Raises:
            ControlParamError: dt_s is not a positive finite number.
        """
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ControlParamError(f"dt_s must be > 0 and finite, got {dt_s!r}")
        inputs = (position, velocity, velocity_target, current_target_a)
        if not all(math.isfinite(v) for v in inputs) or (
            position_target is not None and not math.isfinite(position_target)
        ):
            self.rejected_samples += 1
            return self._output_a
        p = self._params
        low, high = p.velocity.output_min, p.velocity.output_max
        if self._mode is DriveMode.CURRENT:
            self._output_a = _clamp(current_target_a, low, high)
            return self._output_a
        if self._mode is DriveMode.POSITION:
            target, rate = self._position_step(position_target, position, dt_s)
            feedforward = velocity_target + rate
            self.velocity_setpoint = position_law(
                p.position_kp_per_s, p.velocity_limit, target, position, feedforward
            )
        else:
            feedforward = velocity_target
            self.velocity_setpoint = _clamp(velocity_target, -p.velocity_limit, p.velocity_limit)
        offset_a = current_target_a
        if p.current_feedforward_a_per_rad_s2 > 0.0 and self._last_feedforward is not None:
            acceleration = (feedforward - self._last_feedforward) / dt_s
            offset_a += p.current_feedforward_a_per_rad_s2 * acceleration
        self._last_feedforward = feedforward
        offset_a = _clamp(offset_a, low, high)
        # The PI's own limits are shifted by the offset: its anti-windup then holds the total.
        error = self.velocity_setpoint - velocity
        pi_output, self._integral = pi_law(
            p.velocity.kp,
            p.velocity.ti_s,
            low - offset_a,
            high - offset_a,
            self._integral,
            error,
            dt_s,
        )
        self._last_error = error
        self._output_a = pi_output + offset_a
        return self._output_a

    def _position_step(
        self, position_target: float | None, position: float, dt_s: float
    ) -> tuple[float, float]:
        """The target in force (rad, m) and its feed-forward rate, gain * dx*/dt (rad/s, m/s).

        Without a target yet (after `reset`) the present position is held.
        """
        if position_target is not None:
            self._position_target = position_target
        elif self._position_target is None:
            self._position_target = position
        target = self._position_target
        last, self._last_position_target = self._last_position_target, target
        if last is None:
            return target, 0.0
        return target, self._params.velocity_feedforward_gain * (target - last) / dt_s

    def set_mode(
        self,
        mode: DriveMode,
        *,
        position: float,
        velocity: float,
        velocity_setpoint: float = 0.0,
        restart: bool = False,
    ) -> None:
        """Switch mode without a jump in the current setpoint (CiA 402-2 0x6060 while enabled).

        The new loop starts from the present state: position mode holds the present position
        until a target comes, velocity mode takes the present velocity as its reference, and
        the velocity PI's integral is re-based so that the new loop's error at this state
        gives the present output (`pi_rebase`). The first update then differs from the output
        before the switch only by the PI's response to the change of its error.

        Args:
            velocity_setpoint: position mode: the velocity its demand starts with (rad/s, m/s;
                a profile that ramps down from the actual velocity), so the PI is re-based on
                the error the first update sees; 0 for a demand that starts at rest.
            restart: start the loop afresh even in the mode it is in (a new CiA 402 mode on
                the same loop: its last target and error are the old mode's).
        """
        if mode is self._mode and not restart:
            return
        self._mode = mode
        self._last_feedforward = None
        if mode is DriveMode.CURRENT:
            return
        if mode is DriveMode.POSITION:
            self._position_target = self._last_position_target = position
            error = velocity_setpoint - velocity
        else:
            error = 0.0
        p = self._params.velocity
        self._integral, self._output_a = pi_rebase(
            p.kp, p.output_min, p.output_max, self._output_a, error
        )
        self._last_error = error

    def reset(self) -> None:
        """A disabled power stage: zero output, integral and feed-forward history."""
        self._integral = self._output_a = self._last_error = 0.0
        self._position_target = self._last_position_target = self._last_feedforward = None
        self.velocity_setpoint = 0.0

    def set_params(self, params: DriveLoopParams) -> None:
        """Retune without a jump in the output (`pi_rebase` with the last error)."""
        self._params = params
        v = params.velocity
        self._integral, self._output_a = pi_rebase(
            v.kp, v.output_min, v.output_max, self._output_a, self._last_error
        )
