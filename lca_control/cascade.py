"""The paper's cascaded PI control of one axis (section 6, Fig. 11), plus an outer position loop.

    position ref --[P, optional]--> velocity ref --[velocity PI]--> current ref --[current PI]--> V

Units: the velocity loop works on the joint-side velocity (rad/s, m/s for the lift) and outputs
a current setpoint (A); the current loop works on the armature current (A) and outputs the
amplifier voltage (V). The paper's gains are in these units: velocity Kp = 316.23 A per rad/s,
Ti = 10 ms; current Kp = 31.62 V/A, Ti = 1 ms (docs/control.md shows why the joint-side
velocity is the one that makes the paper's 100 rad/s crossover come out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from lca_control.pi import ControlParamError, PIController, PIParams

# Section 6 of the paper.
PAPER_CURRENT_KP_V_PER_A = 31.62
PAPER_CURRENT_TI_S = 1e-3
PAPER_VELOCITY_KP_A_PER_RAD_S = 316.23
PAPER_VELOCITY_TI_S = 10e-3

# The controller's period: the velocity loop's sample time, and in lockstep the simulated time
# the plant advances per command. The one place this number is written.
CONTROL_PERIOD_S = 0.004


@dataclass(frozen=True, slots=True)
class CascadeParams:
    """Gains and limits of one axis's cascade.

    Attributes:
        velocity: the velocity PI (joint velocity -> current setpoint, A per rad/s).
        current: the current PI (current -> voltage, V/A).
        position_kp_per_s: gain of the optional outer position loop (velocity per position
            error, 1/s); 0 disables it.
        velocity_limit: |velocity setpoint| cap of the position loop (rad/s or m/s).
    """

    velocity: PIParams
    current: PIParams
    position_kp_per_s: float = 0.0
    velocity_limit: float = 0.2

    def __post_init__(self) -> None:
        if not (math.isfinite(self.position_kp_per_s) and self.position_kp_per_s >= 0.0):
            raise ControlParamError(f"position_kp_per_s must be >= 0, got {self.position_kp_per_s}")
        if not (math.isfinite(self.velocity_limit) and self.velocity_limit > 0.0):
            raise ControlParamError(f"velocity_limit must be > 0, got {self.velocity_limit}")


def position_law(
    kp_per_s: float, velocity_limit: float, target: float, position: float, feedforward: float
) -> float:
    """The P position loop: velocity setpoint = feedforward + kp (target - position), capped.

    One law for the controller's outer loop and the drive's (`lca_control.drive_loops`).
    """
    command = feedforward + kp_per_s * (target - position)
    return min(max(command, -velocity_limit), velocity_limit)


def paper_cascade(current_limit_a: float, voltage_limit_v: float) -> CascadeParams:
    """The section 6 gains with the given output limits."""
    return CascadeParams(
        velocity=PIParams(
            PAPER_VELOCITY_KP_A_PER_RAD_S, PAPER_VELOCITY_TI_S, -current_limit_a, current_limit_a
        ),
        current=PIParams(
            PAPER_CURRENT_KP_V_PER_A, PAPER_CURRENT_TI_S, -voltage_limit_v, voltage_limit_v
        ),
    )


class AxisCascade:
    """The cascade of one axis; every update takes its own dt (no clock)."""

    def __init__(self, params: CascadeParams) -> None:
        self._params = params
        self.velocity_loop = PIController(params.velocity)
        self.current_loop = PIController(params.current)
        self.current_setpoint_a = 0.0

    @property
    def params(self) -> CascadeParams:
        """The parameters in use."""
        return self._params

    def set_params(self, params: CascadeParams) -> None:
        """Retune without a bump in either loop's output."""
        self._params = params
        self.velocity_loop.set_params(params.velocity)
        self.current_loop.set_params(params.current)

    def reset(self) -> None:
        """Zero both integrators and the current setpoint."""
        self.velocity_loop.reset()
        self.current_loop.reset()
        self.current_setpoint_a = 0.0

    def velocity_setpoint(
        self, position_ref: float, position: float, velocity_feedforward: float = 0.0
    ) -> float:
        """Outer position loop: a P law with velocity feed-forward, capped at velocity_limit."""
        p = self._params
        return position_law(
            p.position_kp_per_s, p.velocity_limit, position_ref, position, velocity_feedforward
        )

    def current_command(self, velocity_ref: float, velocity: float, dt_s: float) -> float:
        """Velocity loop: the current setpoint (A) for the drive's own current loop."""
        self.current_setpoint_a = self.velocity_loop.update(velocity_ref, velocity, dt_s)
        return self.current_setpoint_a

    def voltage_command(self, current_ref_a: float, current_a: float, dt_s: float) -> float:
        """Current loop: the amplifier voltage (V)."""
        return self.current_loop.update(current_ref_a, current_a, dt_s)

    def update(self, velocity_ref: float, velocity: float, current_a: float, dt_s: float) -> float:
        """Both loops at one rate: velocity -> current setpoint -> voltage."""
        current_ref = self.current_command(velocity_ref, velocity, dt_s)
        return self.voltage_command(current_ref, current_a, dt_s)

    def with_gains(
        self,
        velocity_kp: float | None = None,
        velocity_ti_s: float | None = None,
        current_kp: float | None = None,
        current_ti_s: float | None = None,
    ) -> CascadeParams:
        """These parameters with some gains replaced (validated), for a live retune."""
        p = self._params
        velocity = replace(
            p.velocity,
            kp=p.velocity.kp if velocity_kp is None else velocity_kp,
            ti_s=p.velocity.ti_s if velocity_ti_s is None else velocity_ti_s,
        )
        current = replace(
            p.current,
            kp=p.current.kp if current_kp is None else current_kp,
            ti_s=p.current.ti_s if current_ti_s is None else current_ti_s,
        )
        return replace(p, velocity=velocity, current=current)
