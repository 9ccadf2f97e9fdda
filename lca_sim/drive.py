"""The plant as a drive sees it: command intake, the in-drive current loop, stepping (pure core).

`DrivePlant` sits between a transport (the simulator node, later the virtual CAN drive) and the
`Simulator`: it validates command arrays, holds the last good command, runs the current loop "in
the drive" at the model rate when the commands are currents, and advances the model. No ROS, no
clock: callers say how many steps to take.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from lca_control.pi import PIController, PIParams
from lca_sim.simulator import Simulator

FloatArray = npt.NDArray[np.float64]

VOLTAGE = "voltage"
CURRENT = "current"


@dataclass
class CommandCounters:
    """How many command messages were taken or refused, and why."""

    accepted: int = 0
    rejected_length: int = 0
    rejected_nonfinite: int = 0
    rejected_absurd: int = 0
    timeouts: int = 0
    saturated: int = 0

    @property
    def rejected(self) -> int:
        """All refused commands."""
        return self.rejected_length + self.rejected_nonfinite + self.rejected_absurd

    def as_dict(self) -> dict[str, int]:
        """The counters by name (for diagnostics)."""
        return {
            "commands_accepted": self.accepted,
            "commands_rejected_length": self.rejected_length,
            "commands_rejected_nonfinite": self.rejected_nonfinite,
            "commands_rejected_absurd": self.rejected_absurd,
            "command_timeouts": self.timeouts,
            "commands_saturated": self.saturated,
        }


@dataclass
class DrivePlant:
    """A simulator behind voltage or current commands.

    Args:
        sim: the model.
        joints: the order of the command arrays (a subset of the simulator's axes).
        interface: `voltage` (V) or `current` (A, the current PI runs here at the model rate).
        current_pi: gains of the in-drive current loop; its output limits are replaced by each
            axis's amplifier voltage limit.
        max_abs_command: a command beyond this magnitude is absurd and refused outright
            (commands within it but beyond the amplifier or current limit are saturated).
        current_limit_a: saturation of current setpoints (current interface).
    """

    sim: Simulator
    joints: tuple[str, ...]
    interface: str
    current_pi: PIParams
    max_abs_command: float
    current_limit_a: float = 20.0
    enabled: bool = True
    counters: CommandCounters = field(default_factory=CommandCounters)

    def __post_init__(self) -> None:
        self._index = [self.sim.axis_names.index(j) for j in self.joints]
        self._target = np.zeros(self.sim.n_axes)
        self._volts = np.zeros(self.sim.n_axes)
        self._voltage_limits = [a.motor.voltage_limit_v for a in self.sim.robot.axes]
        self._loops = [
            PIController(_with_limits(self.current_pi, -limit, limit))
            for limit in self._voltage_limits
        ]

    @property
    def target(self) -> FloatArray:
        """The command in force per simulator axis (V or A); read only."""
        view = self._target.view()
        view.flags.writeable = False
        return view

    def command(self, values: Sequence[float]) -> str | None:
        """Take a command array in `joints` order; return None, or why it was refused.

        The last good command stays in force when one is refused.
        """
        if len(values) != len(self.joints):
            self.counters.rejected_length += 1
            return (
                f"expected {len(self.joints)} values ({', '.join(self.joints)}), got {len(values)}"
            )
        if not all(math.isfinite(v) for v in values):
            self.counters.rejected_nonfinite += 1
            return f"values must be finite, got {list(values)}"
        if any(abs(v) > self.max_abs_command for v in values):
            self.counters.rejected_absurd += 1
            return f"|value| above {self.max_abs_command:g}: {list(values)}"
        for joint_index, axis in enumerate(self._index):
            value = float(values[joint_index])
            limit = (
                self._voltage_limits[axis] if self.interface == VOLTAGE else self.current_limit_a
            )
            if abs(value) > limit:
                self.counters.saturated += 1
                value = math.copysign(limit, value)
            self._target[axis] = value
        self.counters.accepted += 1
        return None

    def hold_zero(self, timed_out: bool = False) -> None:
        """Drop the command to zero (command timeout, disable): the gear holds the load."""
        if timed_out:
            self.counters.timeouts += 1
        self._target[:] = 0.0
        for loop in self._loops:
            loop.reset()

    def set_enabled(self, enabled: bool) -> None:
        """Amplifiers on or off; off means 0 V on every axis and reset current loops."""
        self.enabled = enabled
        self.hold_zero()

    def set_current_gains(self, kp_v_per_a: float, ti_s: float) -> None:
        """Retune the in-drive current loop (bumpless)."""
        self.current_pi = PIParams(kp_v_per_a, ti_s, -1.0, 1.0)
        for loop, limit in zip(self._loops, self._voltage_limits, strict=True):
            loop.set_params(_with_limits(self.current_pi, -limit, limit))

    def advance(self, n_steps: int) -> None:
        """Run the model n_steps of its dt under the command in force."""
        sim = self.sim
        volts = self._volts
        if not self.enabled:
            volts[:] = 0.0
            for _ in range(n_steps):
                sim.step(volts)
            return
        if self.interface == VOLTAGE:
            volts[:] = self._target
            for _ in range(n_steps):
                sim.step(volts)
            return
        currents = sim.state_array[2]
        dt = sim.dt_s
        loops = self._loops
        target = self._target
        for _ in range(n_steps):
            for a in self._index:
                volts[a] = loops[a].update(target[a], currents[a], dt)
            sim.step(volts)


def _with_limits(params: PIParams, low: float, high: float) -> PIParams:
    return PIParams(params.kp, params.ti_s, low, high)
