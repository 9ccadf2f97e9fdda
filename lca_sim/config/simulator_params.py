"""Typed, validated parameters of the simulator node (pure: no ROS import).

The node declares every parameter from `SIMULATOR_PARAMETERS` (`lca_sim.ros.node_util.
declare_table`) and builds a `SimulatorNodeParams` here; a live change is checked by building
the params again with the new value, so start-up and `ros2 param set` follow exactly the same
rules, and a read-only parameter is refused while the node runs.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from lca_control.cascade import (
    CONTROL_PERIOD_S,
    PAPER_VELOCITY_KP_A_PER_RAD_S,
    PAPER_VELOCITY_TI_S,
)
from lca_control.contract import ROBOT_JOINT_COMMANDS, ROBOT_JOINT_STATES
from lca_control.drive_loops import (
    DEFAULT_POSITION_KP_PER_S,
    DEFAULT_VELOCITY_LIMIT,
    DriveLoopParams,
)
from lca_control.parameters import (
    ParameterError,
    ParameterTable,
    ParamKind,
    ParamSpec,
    non_negative,
    positive,
)
from lca_control.pi import PIParams
from lca_sim.errors import InvalidValueError
from lca_sim.model.drive_modes import DRIVE_MODE_NAMES, VOLTAGE_MODE, check_drive_modes
from lca_sim.model.params import AXIS_NAMES, RobotParams
from lca_sim.model.plant import PlantConfig

TIMING_MODES = ("realtime", "lockstep")
COMMAND_INTERFACES = ("voltage", "current")
JOINT_COMMAND_EFFORTS = ("current", "torque")

S, D_ARRAY = ParamKind.STRING, ParamKind.DOUBLE_ARRAY

# ros2_control's topic-based hardware interface (docs/ros2_control.md): the same three
# parameters on both plants (the simulator and the CAN bridge).
ROS2_CONTROL_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("joint_command_topic", S, ROBOT_JOINT_COMMANDS,
              "sensor_msgs/JointState commands by joint name (ros2_control's topic-based "
              "hardware interface, docs/ros2_control.md); empty: off", live=False),
    ParamSpec("joint_state_topic", S, ROBOT_JOINT_STATES,
              "joint_states' message again on this topic (ros2_control's "
              "joint_states_topic); empty: off", live=False),
    ParamSpec("joint_command_effort", S, "current",
              "what a JointState command's effort is: current (A) or torque (joint side, "
              "N m; N for the lift: current = effort / (k_t N))",
              choices=JOINT_COMMAND_EFFORTS, live=False),
)  # fmt: skip


# Declaration order. Read-only: the model and the wiring (a restart builds them anew).
SIMULATOR_PARAMETERS = ParameterTable(
    (
        ParamSpec("robot", S, "default",
                  "robot YAML path or shipped name (default, reversible)", live=False),
        ParamSpec("joints", ParamKind.STRING_ARRAY, list(AXIS_NAMES),
                  "joint order of the command arrays (ros2_control convention)",
                  choices=AXIS_NAMES, live=False),
        ParamSpec("timing_mode", S, "realtime",
                  "realtime (wall-clock paced) or lockstep (one period per command)",
                  choices=TIMING_MODES, live=False),
        ParamSpec("command_interface", S, "voltage",
                  "voltage (V, both loops in the controller) or current (A)",
                  choices=COMMAND_INTERFACES, live=False),
        ParamSpec("drive_modes", ParamKind.STRING_ARRAY, [],
                  "drive mode per joint, joints order: position (position_commands), velocity "
                  "(velocity_commands), current, voltage (not mixed with the others); empty: "
                  "command_interface for every joint (docs/simulator.md)",
                  choices=DRIVE_MODE_NAMES, live=False),
        positive("drive_loop_period_s", CONTROL_PERIOD_S,
                 "the drive's position and velocity loops run every this long, s (a whole "
                 "multiple of dt_s)", high=1.0, live=False),
        non_negative("drive_position_kp_per_s", DEFAULT_POSITION_KP_PER_S,
                     "drive position loop gain, velocity per position error, 1/s", high=1000.0,
                     live=False),
        non_negative("drive_velocity_kp_a_per_rad_s", PAPER_VELOCITY_KP_A_PER_RAD_S,
                     "drive velocity PI gain, A per rad/s (per m/s for the lift)", live=False),
        positive("drive_velocity_ti_s", PAPER_VELOCITY_TI_S,
                 "drive velocity PI integral time, s", high=10.0, live=False),
        positive("drive_velocity_limit", DEFAULT_VELOCITY_LIMIT,
                 "drive |velocity setpoint| cap, rad/s (m/s for the lift)", live=False),
        positive("dt_s", 1e-4, "model integration step, s", high=0.01, live=False),
        positive("rigid_body_period_s", 1e-3,
                 "Pinocchio's A(q), C qdot + Q evaluated every this long, s: a whole multiple "
                 "of dt_s (dt_s: at every step)", high=0.01, live=False),
        positive("publish_rate_hz", 250.0, "realtime: state publish rate, Hz", high=10_000.0),
        positive("control_period_s", CONTROL_PERIOD_S,
                 "lockstep: simulated time advanced per command; the period of ~/step, s (a "
                 "whole multiple of dt_s)",
                 high=1.0),
        positive("command_timeout_s", 0.1,
                 "realtime: command silence after which the voltage drops to 0, s", high=60.0),
        positive("max_command_voltage_v", 1000.0, "commands beyond this |V| are refused"),
        positive("max_command_current_a", 100.0, "commands beyond this |A| are refused"),
        positive("current_kp_v_per_a", 31.62, "in-drive current PI gain (current interface), V/A"),
        positive("current_ti_s", 1e-3, "in-drive current PI integral time, s", high=10.0),
        ParamSpec("initial_position", D_ARRAY, [0.0, 0.0, 0.0, 0.0],
                  "pose at start and on ~/reset, rad (m for the lift), one per axis"),
        ParamSpec("enabled", ParamKind.BOOL, True,
                  "amplifiers on; false puts 0 V on every axis from the next step"),
        ParamSpec("lockstep_subscribers", ParamKind.INTEGER, 1,
                  "lockstep: joint_states subscribers to wait for before t = 0", 0, 1000,
                  live=False),
        positive("lockstep_resend_s", 1.0,
                 "lockstep: re-publish the last state after this silence, s", high=60.0),
        non_negative("lockstep_end_s", 0.0,
                     "lockstep: simulated time of the run's last state, s (a whole multiple of "
                     "dt_s); no state after it (0: no end)", high=1e6),
        *ROS2_CONTROL_PARAMETERS,
        positive("diagnostics_period_s", 1.0, "period of /diagnostics, s", high=60.0),
        positive("realtime_factor", 1.0,
                 "realtime: simulated time advances this many times the wall time (lockstep: "
                 "stored, the controller sets the pace)", high=100.0),
        ParamSpec("step_periods", ParamKind.INTEGER, 1,
                  "control periods (control_period_s) one ~/step call advances while paused",
                  1, 1_000_000),
    )
)  # fmt: skip
READ_ONLY = SIMULATOR_PARAMETERS.read_only


@dataclass(frozen=True, slots=True)
class SimulatorNodeParams:
    """Validated simulator-node parameters; names carry their SI unit."""

    robot: str
    joints: tuple[str, ...]
    timing_mode: str
    command_interface: str
    drive_modes: tuple[str, ...]
    drive_loop_period_s: float
    drive_position_kp_per_s: float
    drive_velocity_kp_a_per_rad_s: float
    drive_velocity_ti_s: float
    drive_velocity_limit: float
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
    lockstep_end_s: float
    joint_command_topic: str
    joint_state_topic: str
    joint_command_effort: str
    diagnostics_period_s: float
    realtime_factor: float
    step_periods: int

    @property
    def joint_drive_modes(self) -> tuple[str, ...]:
        """Each joint's drive mode: `drive_modes`, or `command_interface` for every joint."""
        return self.drive_modes or (self.command_interface,) * len(self.joints)

    def drive_loop_params(self, current_limit_a: float) -> DriveLoopParams:
        """The drive loops' gains and limits (`lca_control.drive_loops`), +-current_limit_a."""
        return DriveLoopParams(
            PIParams(
                self.drive_velocity_kp_a_per_rad_s,
                self.drive_velocity_ti_s,
                -current_limit_a,
                current_limit_a,
            ),
            position_kp_per_s=self.drive_position_kp_per_s,
            velocity_limit=self.drive_velocity_limit,
        )

    @property
    def substeps_per_period(self) -> int:
        """Model steps per lockstep control period."""
        return round(self.control_period_s / self.dt_s)

    @property
    def lockstep_end_steps(self) -> int | None:
        """Model steps of a lockstep run (`lockstep_end_s`), None for a run without end."""
        return round(self.lockstep_end_s / self.dt_s) if self.lockstep_end_s > 0.0 else None

    @property
    def rigid_body_update_steps(self) -> int:
        """Model steps per evaluation of the rigid-body terms (`Simulator`)."""
        return round(self.rigid_body_period_s / self.dt_s)


def plant_config(
    params: SimulatorNodeParams, robot: RobotParams, fault_period_s: float | None = None
) -> PlantConfig:
    """The plant the simulator node runs with these parameters (`lca_sim.model.plant`).

    The node, `lca-hil run` and the closed-loop sweeps build their plant from this one reading
    of the parameters: the command limit is `max_command_voltage_v` or `max_command_current_a`
    by the interface.
    """
    voltage = params.command_interface == "voltage"
    return PlantConfig(
        robot=robot,
        dt_s=params.dt_s,
        rigid_body_update_steps=params.rigid_body_update_steps,
        joints=params.joints,
        interface=params.command_interface,
        current_kp_v_per_a=params.current_kp_v_per_a,
        current_ti_s=params.current_ti_s,
        max_abs_command=params.max_command_voltage_v if voltage else params.max_command_current_a,
        enabled=params.enabled,
        fault_period_s=fault_period_s,
    )


def _whole_multiple(name: str, period_s: float, dt_s: float) -> float:
    ratio = period_s / dt_s
    if round(ratio) < 1 or abs(ratio - round(ratio)) > 1e-6 * ratio:
        raise ParameterError(name, f"a whole multiple of dt_s = {dt_s:g}", period_s)
    return period_s


def validate_simulator_params(values: Mapping[str, Any]) -> SimulatorNodeParams:
    """Check every parameter (`SIMULATOR_PARAMETERS`) and build the typed params.

    Raises:
        ParameterError: the parameter name, what was expected and the value.
    """
    v = SIMULATOR_PARAMETERS.check_all(values)
    joints: tuple[str, ...] = v["joints"]
    if not joints or len(set(joints)) != len(joints):
        raise ParameterError("joints", f"distinct names among {', '.join(AXIS_NAMES)}", joints)
    dt_s = v["dt_s"]
    if 1.0 / v["publish_rate_hz"] < dt_s:
        raise ParameterError("publish_rate_hz", "a period of at least dt_s", v["publish_rate_hz"])
    initial: tuple[float, ...] = v["initial_position"]
    if len(initial) != len(AXIS_NAMES):
        raise ParameterError(
            "initial_position", f"{len(AXIS_NAMES)} positions ({', '.join(AXIS_NAMES)})", initial
        )
    for name in ("control_period_s", "rigid_body_period_s", "drive_loop_period_s"):
        _whole_multiple(name, v[name], dt_s)
    if v["drive_modes"]:
        _check_drive_modes(v["drive_modes"], joints, v["command_interface"])
    if v["lockstep_end_s"] > 0.0:
        _whole_multiple("lockstep_end_s", v["lockstep_end_s"], dt_s)
    for name in ("joint_command_topic", "joint_state_topic"):
        check_topic(name, v[name])
    return SimulatorNodeParams(**v)


def _check_drive_modes(modes: tuple[str, ...], joints: tuple[str, ...], interface: str) -> None:
    """One mode per joint, voltage for all or none, and the interface the modes run on.

    Raises:
        ParameterError: drive_modes, with the reason.
    """
    try:
        check_drive_modes(modes, joints)
    except InvalidValueError as exc:
        raise ParameterError("drive_modes", str(exc).removeprefix("drive_modes: "), modes) from None
    voltage = modes[0] == VOLTAGE_MODE
    if voltage != (interface == "voltage"):
        need = "voltage" if voltage else "current (the in-drive current loop runs them)"
        raise ParameterError(
            "drive_modes", f"modes that fit command_interface {interface}: it must be {need}", modes
        )


def check_topic(name: str, topic: str) -> str:
    """A topic parameter: empty (off) or a ROS name (letters, digits, `_`, `/`, `~`).

    Raises:
        ParameterError: anything else.
    """
    if (topic and not re.fullmatch(r"[~/]?[A-Za-z_][A-Za-z0-9_/]*", topic)) or "//" in topic:
        raise ParameterError(name, "empty or a ROS topic name such as /robot_joint_states", topic)
    return topic
