"""Per-joint drive modes of the commanded plant: the drive's loops ahead of its current loop.

A joint in `position` or `velocity` mode runs `lca_control.drive_loops.DriveLoops` once per
drive cycle (`period_steps` model steps) on the plant's joint position and velocity (rad, rad/s;
m, m/s for the lift); the output is that joint's current setpoint for the in-drive current
loop of `CommandedPlant`. A `current` joint takes current commands as before. `voltage` is the
plant's other interface: every amplifier is then driven by the command itself, so it is not
mixed with the modes that need the in-drive current loop. docs/simulator.md, "Drive modes".
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from lca_control.drive_loops import DriveLoopParams, DriveLoops, DriveMode
from lca_sim.errors import InvalidValueError

VOLTAGE_MODE = "voltage"
DRIVE_MODE_NAMES = (*(m.value for m in DriveMode), VOLTAGE_MODE)


def check_drive_modes(modes: Sequence[str], joints: Sequence[str]) -> tuple[str, ...]:
    """Drive modes per joint: one per joint, known names, voltage for all joints or none.

    Raises:
        InvalidValueError: the reason, with the joints and the valid names.
    """
    if len(modes) != len(joints):
        raise InvalidValueError(
            f"drive_modes: expected {len(joints)} modes ({', '.join(joints)}), got {list(modes)}"
        )
    unknown = [m for m in modes if m not in DRIVE_MODE_NAMES]
    if unknown:
        raise InvalidValueError(
            f"drive_modes: unknown {unknown}; valid: {', '.join(DRIVE_MODE_NAMES)}"
        )
    if VOLTAGE_MODE in modes and set(modes) != {VOLTAGE_MODE}:
        raise InvalidValueError(
            f"drive_modes: voltage mixed with other modes ({list(modes)}): a voltage joint's "
            "amplifier takes the command itself, the others need the in-drive current loop; "
            "use voltage for every joint or for none"
        )
    return tuple(modes)


class JointDriveLoops:
    """One `DriveLoops` per joint (in the plant's joint order), cycled every `period_steps`.

    Args:
        modes: each joint's mode: position, velocity or current.
        params: the loops' gains and limits (the same for every joint).
        period_steps: model steps per drive cycle.
    """

    def __init__(
        self, modes: Sequence[DriveMode], params: DriveLoopParams, period_steps: int
    ) -> None:
        if period_steps < 1:
            raise InvalidValueError(f"period_steps must be >= 1, got {period_steps}")
        self.modes = tuple(modes)
        self.period_steps = period_steps
        self._loops = [DriveLoops(params, m) for m in self.modes]
        self._position_target: list[float | None] = [None] * len(self.modes)
        self._velocity_target = [0.0] * len(self.modes)
        self.steps_to_cycle = 0  # model steps until the next cycle runs
        self.halted = True  # no command since start, a timeout or a disable: 0 A out

    def joints_in(self, mode: DriveMode) -> tuple[int, ...]:
        """Indices of the joints that run `mode`."""
        return tuple(j for j, m in enumerate(self.modes) if m is mode)

    @property
    def loops(self) -> tuple[DriveLoops, ...]:
        """The loops, joint order (read their state; command through this class)."""
        return tuple(self._loops)

    @property
    def velocity_targets(self) -> tuple[float, ...]:
        """The velocity target in force per joint (0 for the others), rad/s (m/s)."""
        return tuple(self._velocity_target)

    @property
    def position_targets(self) -> tuple[float | None, ...]:
        """The position target in force per joint, rad (m); None without one (halted, other modes).

        The target set last, else the loop's own (a position loop holds the position it
        started from until its first target).
        """
        return tuple(
            (target if target is not None else loops.position_target)
            if loops.mode is DriveMode.POSITION
            else None
            for target, loops in zip(self._position_target, self._loops, strict=True)
        )

    def set_target(self, joint: int, value: float) -> None:
        """A position (rad, m) or velocity (rad/s, m/s) target, by the joint's mode; runs again.

        Raises:
            InvalidValueError: a current-mode joint (it takes current commands) or NaN.
        """
        if not math.isfinite(value):
            raise InvalidValueError(f"target of joint {joint} must be finite, got {value}")
        mode = self.modes[joint]
        if mode is DriveMode.POSITION:
            self._position_target[joint] = value
        elif mode is DriveMode.VELOCITY:
            self._velocity_target[joint] = value
        else:
            raise InvalidValueError(f"joint {joint} runs current mode: it takes no target")
        self.halted = False

    def cycle(
        self, positions: Sequence[float], velocities: Sequence[float], dt_s: float
    ) -> list[float | None]:
        """One drive cycle: each loop joint's current setpoint (A), None for current joints.

        Halted: 0 A for the loop joints, and their loops stay reset.
        """
        currents: list[float | None] = []
        for j, loops in enumerate(self._loops):
            if loops.mode is DriveMode.CURRENT:
                currents.append(None)
            elif self.halted:
                currents.append(0.0)
            else:
                currents.append(
                    loops.update(
                        dt_s,
                        position=positions[j],
                        velocity=velocities[j],
                        position_target=self._position_target[j],
                        velocity_target=self._velocity_target[j],
                    )
                )
        return currents

    def halt(self) -> None:
        """0 A until the next target (timeout, disable, reset): loops and targets cleared.

        A position joint then holds where it is when a target comes for another joint.
        """
        self.halted = True
        for loops in self._loops:
            loops.reset()
        self._position_target = [None] * len(self.modes)
        self._velocity_target = [0.0] * len(self.modes)
