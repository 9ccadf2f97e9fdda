"""Homing mode (CiA 402-2 0x6060 = 6): find the home position, then 0x6064 = 0x607C there.

A rising edge of controlword bit 4 starts the method 0x6098; dropping bit 4, or halt (bit 8),
interrupts it (the axis stops on the 0x609A ramp). At the home position the position frame
moves so that the actual position reads the home offset 0x607C (`ModeOutput.position_shift_inc`:
the caller adds it to its position from then on). Methods:

- 35 and 37: the present position is the home position (35 is 37's older number); no motion.
- 17 / 18: negative / positive limit switch without index pulse: towards the switch at 0x6099
  sub 1 until it is active, back at sub 2; home is where it goes inactive again. The opposite
  switch coming active is a homing error.
- -1 / -2 (manufacturer specific, lca_hil): the negative / positive mechanical stop. Towards it
  at sub 2 until the current has stayed at or above `stop_current_a` with the speed within
  `stop_velocity_inc_s` for `stop_time_s`: home is there (the axis rests against the stop).

Statusword bits 13, 12, 10 (CiA 402-2 homing table): 000 in progress, 001 interrupted or not
started, 010 attained but target not reached (still stopping), 011 completed, 100 error with
velocity, 101 error at standstill. Units: increments, s, A. docs/can-modes.md, "Homing".
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from lca_sim.cia402.device import CW_HALT
from lca_sim.cia402.mode_common import SW_BIT10, SW_BIT12, SW_BIT13, Dwell, Loop, ModeOutput
from lca_sim.cia402.profile import ProfileGenerator, ProfileParams
from lca_sim.errors import InvalidValueError

CW_HOMING_START = 1 << 4
SW_HOMING_TARGET_REACHED = SW_BIT10
SW_HOMING_ATTAINED = SW_BIT12
SW_HOMING_ERROR = SW_BIT13

METHOD_NEGATIVE_LIMIT_SWITCH = 17
METHOD_POSITIVE_LIMIT_SWITCH = 18
METHOD_CURRENT_POSITION_OLD = 35
METHOD_CURRENT_POSITION = 37
METHOD_NEGATIVE_HARD_STOP = -1  # lca_hil
METHOD_POSITIVE_HARD_STOP = -2  # lca_hil
HOMING_METHODS: frozenset[int] = frozenset(
    {
        METHOD_NEGATIVE_LIMIT_SWITCH,
        METHOD_POSITIVE_LIMIT_SWITCH,
        METHOD_CURRENT_POSITION_OLD,
        METHOD_CURRENT_POSITION,
        METHOD_NEGATIVE_HARD_STOP,
        METHOD_POSITIVE_HARD_STOP,
    }
)


@dataclass(frozen=True, slots=True)
class HomingParams:
    """Objects of homing, in increments, s and A.

    Attributes:
        method: 0x6098 (`HOMING_METHODS`).
        switch_speed_inc_s: 0x6099 sub 1, speed during search for switch, > 0.
        zero_speed_inc_s: 0x6099 sub 2, speed during search for zero, > 0.
        acceleration_inc_s2: 0x609A, the ramp of every homing move and stop, > 0.
        home_offset_inc: 0x607C, what 0x6064 reads at the home position.
        stop_current_a: methods -1 / -2: |current| at which the stop is pressed (0x2040).
        stop_time_s: methods -1 / -2: how long it must be pressed (0x2041).
        stop_velocity_inc_s: methods -1 / -2: |velocity| below which the axis stands
            (0x606F).
    """

    method: int
    switch_speed_inc_s: float
    zero_speed_inc_s: float
    acceleration_inc_s2: float
    home_offset_inc: float = 0.0
    stop_current_a: float = math.inf
    stop_time_s: float = 0.0
    stop_velocity_inc_s: float = 0.0

    def __post_init__(self) -> None:
        if self.method not in HOMING_METHODS:
            raise InvalidValueError(
                f"0x6098 homing method {self.method} is not one of {sorted(HOMING_METHODS)}"
            )
        for name in ("switch_speed_inc_s", "zero_speed_inc_s", "acceleration_inc_s2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise InvalidValueError(f"homing {name} must be finite and > 0, got {value!r}")

    @property
    def ramp(self) -> ProfileParams:
        """0x609A as both ramps of the generator."""
        a = self.acceleration_inc_s2
        return ProfileParams(self.switch_speed_inc_s, a, a, a)


@dataclass(frozen=True, slots=True)
class HomingInputs:
    """What the drive senses in one step.

    Attributes:
        position_inc, velocity_inc_s: 0x6064 and 0x606C.
        current_a: the motor current (0x6078 in A).
        negative_limit, positive_limit: the limit switches (the gantry's joint limits).
    """

    position_inc: float
    velocity_inc_s: float
    current_a: float = 0.0
    negative_limit: bool = False
    positive_limit: bool = False


class Phase(enum.Enum):
    """Where the homing procedure is."""

    IDLE = "not started or interrupted"
    SEARCH = "search for switch / stop"
    LEAVE = "search for zero (off the switch)"
    STOPPING = "attained, stopping"
    DONE = "completed"
    ERROR = "error"


_PHASE_BITS = {
    Phase.IDLE: SW_HOMING_TARGET_REACHED,
    Phase.SEARCH: 0,
    Phase.LEAVE: 0,
    Phase.STOPPING: SW_HOMING_ATTAINED,
    Phase.DONE: SW_HOMING_ATTAINED | SW_HOMING_TARGET_REACHED,
    Phase.ERROR: SW_HOMING_ERROR,
}


class HomingMode:
    """One axis in homing: feed `update` every step while operation is enabled."""

    def __init__(self) -> None:
        self._generator = ProfileGenerator()
        self._controlword = 0
        self._phase = Phase.IDLE
        self._pressed = Dwell()

    @property
    def phase(self) -> Phase:
        """Where the procedure is."""
        return self._phase

    def enter(
        self, position_inc: float, velocity_inc_s: float, controlword: int, params: HomingParams
    ) -> None:
        """Start the mode (bumpless): from the actual state, stopping on 0x609A; not started."""
        self._generator.reset(position_inc, velocity_inc_s)
        if velocity_inc_s != 0.0:
            self._generator.stop(params.acceleration_inc_s2)
        self._controlword = controlword
        self._phase = Phase.IDLE
        self._pressed.reset()

    def update(
        self, dt_s: float, controlword: int, inputs: HomingInputs, params: HomingParams
    ) -> ModeOutput:
        """One step of the procedure.

        Args:
            dt_s: time since the last step, s.
            controlword: 0x6040 (bit 4 start, bit 8 halt).
            inputs: position, velocity, current and switches of this step.
            params: the homing objects.
        """
        previous, self._controlword = self._controlword, controlword
        started = controlword & CW_HOMING_START and not previous & CW_HOMING_START
        running = self._phase in (Phase.SEARCH, Phase.LEAVE, Phase.STOPPING)
        gen = self._generator
        if controlword & CW_HALT or not controlword & CW_HOMING_START:
            if running and self._phase is not Phase.STOPPING:
                self._phase = Phase.IDLE  # interrupted
                self._stop_from(inputs, params)
        elif started:
            self._start(inputs, params)
        shift = self._advance(inputs, params, dt_s)
        demand = gen.step(dt_s)
        if self._phase is Phase.STOPPING and gen.done:
            self._phase = Phase.DONE
        bits = _PHASE_BITS[self._phase]
        if self._phase is Phase.ERROR and gen.done:
            bits |= SW_HOMING_TARGET_REACHED  # error, velocity 0
        loop = Loop.VELOCITY if self._phase in (Phase.SEARCH, Phase.LEAVE) else Loop.POSITION
        return ModeOutput(
            loop, demand.position_inc, demand.velocity_inc_s, bits, position_shift_inc=shift
        )

    def _start(self, inputs: HomingInputs, params: HomingParams) -> None:
        method, gen = params.method, self._generator
        gen.reset(inputs.position_inc, gen.point.velocity_inc_s)
        self._pressed.reset()
        if method in (METHOD_CURRENT_POSITION, METHOD_CURRENT_POSITION_OLD):
            self._phase = Phase.SEARCH  # home at once, in `_advance`
            return
        sign = _direction(method)
        if method in (METHOD_NEGATIVE_HARD_STOP, METHOD_POSITIVE_HARD_STOP):
            self._phase = Phase.SEARCH
            gen.run_at(sign * params.zero_speed_inc_s, params.ramp)
        elif self._switch(inputs, sign):
            self._phase = Phase.LEAVE
            gen.run_at(-sign * params.zero_speed_inc_s, params.ramp)
        else:
            self._phase = Phase.SEARCH
            gen.run_at(sign * params.switch_speed_inc_s, params.ramp)

    def _advance(self, inputs: HomingInputs, params: HomingParams, dt_s: float) -> float:
        """Take the transition of this step; the position shift if home was found now."""
        method, phase = params.method, self._phase
        if phase not in (Phase.SEARCH, Phase.LEAVE):
            return 0.0
        if method in (METHOD_CURRENT_POSITION, METHOD_CURRENT_POSITION_OLD):
            return self._home(inputs, params, stopped=True)
        sign = _direction(method)
        if method in (METHOD_NEGATIVE_HARD_STOP, METHOD_POSITIVE_HARD_STOP):
            pressed = (
                abs(inputs.current_a) >= params.stop_current_a
                and abs(inputs.velocity_inc_s) <= params.stop_velocity_inc_s
            )
            if self._pressed.update(pressed, dt_s, params.stop_time_s):
                return self._home(inputs, params, stopped=True)
            return 0.0
        if self._switch(inputs, -sign):  # the far switch: wrong way or wrong wiring
            self._phase = Phase.ERROR
            self._stop_from(inputs, params)
        elif phase is Phase.SEARCH and self._switch(inputs, sign):
            self._phase = Phase.LEAVE
            self._generator.run_at(-sign * params.zero_speed_inc_s, params.ramp)
        elif phase is Phase.LEAVE and not self._switch(inputs, sign):
            return self._home(inputs, params, stopped=False)
        return 0.0

    def _home(self, inputs: HomingInputs, params: HomingParams, *, stopped: bool) -> float:
        """Home is here: shift the frame so 0x6064 = 0x607C; stop, or hold where the axis is."""
        shift = params.home_offset_inc - inputs.position_inc
        gen = self._generator
        if stopped:
            gen.reset(params.home_offset_inc)
            self._phase = Phase.DONE
        else:
            self._stop_from(inputs, params, shift)
            self._phase = Phase.STOPPING
        return shift

    def _stop_from(self, inputs: HomingInputs, params: HomingParams, shift: float = 0.0) -> None:
        """Stop on 0x609A from the actual state, which the position loop then follows.

        The search ran the velocity loop, so its demand position may be far from the axis.
        """
        self._generator.reset(inputs.position_inc + shift, inputs.velocity_inc_s)
        self._generator.stop(params.acceleration_inc_s2)

    @staticmethod
    def _switch(inputs: HomingInputs, sign: float) -> bool:
        return inputs.negative_limit if sign < 0.0 else inputs.positive_limit


def _direction(method: int) -> float:
    """-1 for the methods that search the negative side, +1 for the positive."""
    return -1.0 if method in (METHOD_NEGATIVE_LIMIT_SWITCH, METHOD_NEGATIVE_HARD_STOP) else 1.0
