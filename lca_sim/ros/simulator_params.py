"""Typed, validated parameters of the simulator node (pure: no ROS import).

The node declares each parameter with these defaults, reads them into a dict, and builds a
`SimulatorNodeParams` here; a live change is checked by building the params again with the new
value, so start-up and `ros2 param set` follow exactly the same rules.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from lca_sim.errors import ConfigError
from lca_sim.model.params import AXIS_NAMES

TIMING_MODES = ("realtime", "lockstep")
COMMAND_INTERFACES = ("voltage", "current")

# name -> (default, description with unit). Order is the declaration order.
SIMULATOR_PARAMETERS: dict[str, tuple[Any, str]] = {
    "robot": ("default", "robot YAML path or shipped name (default, reversible); read at start"),
    "joints": (list(AXIS_NAMES), "joint order of the command arrays (ros2_control convention)"),
    "timing_mode": ("realtime", "realtime (wall-clock paced) or lockstep (one period per command)"),
    "command_interface": ("voltage", "voltage (V, both loops in the controller) or current (A)"),
    "dt_s": (1e-4, "model integration step, s; read at start"),
    "rigid_body_period_s": (
        1e-3,
        "Pinocchio's A(q), C qdot + Q evaluated every this long, s: a whole multiple of dt_s, "
        "at most 0.01 (dt_s: at every step); read at start",
    ),
    "publish_rate_hz": (250.0, "realtime: state publish rate, Hz"),
    "control_period_s": (0.004, "lockstep: simulated time advanced per command, s"),
    "command_timeout_s": (0.1, "realtime: command silence after which the voltage drops to 0, s"),
    "max_command_voltage_v": (1000.0, "commands beyond this |V| are rejected as absurd"),
    "max_command_current_a": (100.0, "commands beyond this |A| are rejected as absurd"),
    "current_kp_v_per_a": (31.62, "in-drive current PI gain (current interface), V/A"),
    "current_ti_s": (1e-3, "in-drive current PI integral time, s"),
    "initial_position": ([0.0, 0.0, 0.0, 0.0], "pose at start and on ~/reset, rad (m for lift)"),
    "enabled": (True, "amplifiers on at start; ~/enable switches them"),
    "lockstep_subscribers": (1, "lockstep: joint_states subscribers to wait for before t = 0"),
    "lockstep_resend_s": (1.0, "lockstep: re-publish the last state after this silence, s"),
    "diagnostics_period_s": (1.0, "period of /diagnostics, s"),
}

# Parameters that define the model or the wiring: changing them needs a restart.
READ_ONLY = frozenset(
    {"robot", "joints", "timing_mode", "command_interface", "dt_s", "rigid_body_period_s"}
)


@dataclass(frozen=True, slots=True)
class SimulatorNodeParams:
    """Validated simulator-node parameters; names carry their SI unit."""

    robot: str
    joints: tuple[str, ...]
    timing_mode: str
    command_interface: str
    dt_s: float
    rigid_body_period_s: float
    publish_rate_hz: float
    control_period_s: float
    command_timeout_s: float
    max_command_voltage_v: float
    max_command_current_a: float
    current_kp_v_per_a: float
    current_ti_s: float
    initial_position: tuple[float, ...]
    enabled: bool
    lockstep_subscribers: int
    lockstep_resend_s: float
    diagnostics_period_s: float

    @property
    def substeps_per_period(self) -> int:
        """Model steps per lockstep control period."""
        return round(self.control_period_s / self.dt_s)

    @property
    def rigid_body_update_steps(self) -> int:
        """Model steps per evaluation of the rigid-body terms (`Simulator`)."""
        return round(self.rigid_body_period_s / self.dt_s)


def _positive(values: Mapping[str, Any], name: str, maximum: float = math.inf) -> float:
    value = values[name]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError("parameters", name, f"expected a number, got {value!r}")
    number = float(value)
    if not (math.isfinite(number) and 0.0 < number <= maximum):
        raise ConfigError(
            "parameters", name, f"expected a number in (0, {maximum:g}], got {value!r}"
        )
    return number


def _whole_multiple(values: Mapping[str, Any], name: str, dt_s: float, maximum: float) -> float:
    period_s = _positive(values, name, maximum)
    ratio = period_s / dt_s
    if round(ratio) < 1 or abs(ratio - round(ratio)) > 1e-6 * ratio:
        raise ConfigError("parameters", name, f"expected a whole multiple of dt_s = {dt_s:g}")
    return period_s


def validate_simulator_params(values: Mapping[str, Any]) -> SimulatorNodeParams:
    """Check every parameter and build the typed params.

    Raises:
        ConfigError: with source "parameters", the parameter name and what was expected.
    """
    joints = tuple(values["joints"])
    unknown = [j for j in joints if j not in AXIS_NAMES]
    if not joints or unknown or len(set(joints)) != len(joints):
        raise ConfigError(
            "parameters",
            "joints",
            f"expected distinct names among {', '.join(AXIS_NAMES)}, got {list(joints)}",
        )
    timing_mode = str(values["timing_mode"])
    if timing_mode not in TIMING_MODES:
        raise ConfigError("parameters", "timing_mode", f"expected one of {TIMING_MODES}")
    interface = str(values["command_interface"])
    if interface not in COMMAND_INTERFACES:
        raise ConfigError(
            "parameters", "command_interface", f"expected one of {COMMAND_INTERFACES}"
        )
    dt_s = _positive(values, "dt_s", 0.01)
    control_period_s = _whole_multiple(values, "control_period_s", dt_s, 1.0)
    rigid_body_period_s = _whole_multiple(values, "rigid_body_period_s", dt_s, 0.01)
    publish_rate_hz = _positive(values, "publish_rate_hz", 10_000.0)
    if 1.0 / publish_rate_hz < dt_s:
        raise ConfigError("parameters", "publish_rate_hz", "expected a period of at least dt_s")
    initial = tuple(float(x) for x in values["initial_position"])
    if len(initial) != len(AXIS_NAMES) or not all(math.isfinite(x) for x in initial):
        raise ConfigError(
            "parameters",
            "initial_position",
            f"expected {len(AXIS_NAMES)} finite positions ({', '.join(AXIS_NAMES)})",
        )
    subscribers = values["lockstep_subscribers"]
    if isinstance(subscribers, bool) or not isinstance(subscribers, int) or subscribers < 0:
        raise ConfigError("parameters", "lockstep_subscribers", "expected an integer >= 0")
    return SimulatorNodeParams(
        robot=str(values["robot"]),
        joints=joints,
        timing_mode=timing_mode,
        command_interface=interface,
        dt_s=dt_s,
        rigid_body_period_s=rigid_body_period_s,
        publish_rate_hz=publish_rate_hz,
        control_period_s=control_period_s,
        command_timeout_s=_positive(values, "command_timeout_s", 60.0),
        max_command_voltage_v=_positive(values, "max_command_voltage_v"),
        max_command_current_a=_positive(values, "max_command_current_a"),
        current_kp_v_per_a=_positive(values, "current_kp_v_per_a"),
        current_ti_s=_positive(values, "current_ti_s", 10.0),
        initial_position=initial,
        enabled=bool(values["enabled"]),
        lockstep_subscribers=subscribers,
        lockstep_resend_s=_positive(values, "lockstep_resend_s", 60.0),
        diagnostics_period_s=_positive(values, "diagnostics_period_s", 60.0),
    )
