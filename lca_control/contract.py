"""The plant contract: what every plant backend publishes and accepts over ROS 2.

A controller needs the same things of any plant, so this is the one definition the simulator
node and the CAN bridge (and any later backend) are held to: topic names and types
(`PLANT_PUBLISHES`, `PLANT_SUBSCRIBES`), QoS as plain values (`QosSpec`), units, the
drive-chain keys with their ranges (`DRIVE_STATE_KEYS`, `DRIVE_KEYS`), the vocabularies
(`MOTION_STATE_NAMES`, `UNKNOWN`) and the `PlantSnapshot` every backend fills.
`lca_sim.ros.plant_contract` is the one builder of the messages, and
`tests/lca_sim/ros/test_plant_contract.py` runs every backend against it. docs/contract.md is
the prose: each topic's content, the joint order, what is NaN and when.

It imports no ROS package (plain values and numpy only), so the controller, tools and tests
share it without rclpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from lca_control.pi import ControlParamError

FloatArray = npt.NDArray[np.float64]

# --- topics and types --------------------------------------------------------------------

JOINT_STATES = "joint_states"
MOTOR_STATES = "motor_states"
DRIVE_CHAIN_STATES = "drive_chain_states"
DIAGNOSTICS = "/diagnostics"
CLOCK = "/clock"
VOLTAGE_COMMANDS = "voltage_commands"
CURRENT_COMMANDS = "current_commands"
VELOCITY_REFERENCE = "velocity_reference"
VELOCITY_COMMANDS = "velocity_commands"
POSITION_COMMANDS = "position_commands"  # rad (m for the lift) per joint: the drive's loops
# ros2_control's topic-based hardware interface (joint_state_topic_hardware_interface,
# topic_based_ros2_control/TopicBasedSystem): the defaults its code uses; docs/ros2_control.md.
ROBOT_JOINT_COMMANDS = "/robot_joint_commands"
ROBOT_JOINT_STATES = "/robot_joint_states"

JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
DIAGNOSTIC_ARRAY_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
FLOAT64_MULTI_ARRAY_TYPE = "std_msgs/msg/Float64MultiArray"

# Reliable, keep-last: the lockstep loop must not drop a state or a command, and a recorder
# that falls behind for a moment must not lose samples either.
STATE_QOS_DEPTH = 100
COMMAND_QOS_DEPTH = 10
DIAGNOSTICS_QOS_DEPTH = 10
CLOCK_QOS_DEPTH = 10

RELIABLE = "reliable"
BEST_EFFORT = "best_effort"

# How the simulator's /diagnostics says a lockstep run has reached `lockstep_end_s`: its status
# SIMULATOR_STATUS carries ENDED_KEY = "True" (from then on, in every diagnostics period). A
# controller whose last state is that instant's takes the silence after it for the end.
SIMULATOR_STATUS = "lca_hil/simulator"
ENDED_KEY = "ended"


@dataclass(frozen=True, slots=True)
class QosSpec:
    """A topic's QoS as plain values: keep-last `depth`, `reliability` RELIABLE or BEST_EFFORT.

    Durability is volatile and history keep-last everywhere (the ROS defaults).
    """

    depth: int
    reliability: str = RELIABLE


STATE_QOS = QosSpec(STATE_QOS_DEPTH)
COMMAND_QOS = QosSpec(COMMAND_QOS_DEPTH)
DIAGNOSTICS_QOS = QosSpec(DIAGNOSTICS_QOS_DEPTH)
CLOCK_QOS = QosSpec(CLOCK_QOS_DEPTH)


@dataclass(frozen=True, slots=True)
class TopicSpec:
    """One topic of the contract.

    Attributes:
        name: the topic name (relative names take the node's namespace).
        type: the ROS message type, `pkg/msg/Type`.
        qos: what the plant's publisher or subscription uses.
        required: every backend has it; False: only some do (`/clock`, in lockstep).
    """

    name: str
    type: str
    qos: QosSpec
    required: bool = True


PLANT_PUBLISHES: tuple[TopicSpec, ...] = (
    TopicSpec(JOINT_STATES, JOINT_STATE_TYPE, STATE_QOS),
    TopicSpec(MOTOR_STATES, JOINT_STATE_TYPE, STATE_QOS),
    TopicSpec(DRIVE_CHAIN_STATES, DIAGNOSTIC_ARRAY_TYPE, STATE_QOS),
    TopicSpec(DIAGNOSTICS, DIAGNOSTIC_ARRAY_TYPE, DIAGNOSTICS_QOS),
    TopicSpec(CLOCK, CLOCK_TYPE, CLOCK_QOS, required=False),
    TopicSpec(ROBOT_JOINT_STATES, JOINT_STATE_TYPE, STATE_QOS, required=False),
)
PLANT_SUBSCRIBES: tuple[TopicSpec, ...] = (
    TopicSpec(CURRENT_COMMANDS, FLOAT64_MULTI_ARRAY_TYPE, COMMAND_QOS),
    TopicSpec(VOLTAGE_COMMANDS, FLOAT64_MULTI_ARRAY_TYPE, COMMAND_QOS),
    TopicSpec(VELOCITY_COMMANDS, FLOAT64_MULTI_ARRAY_TYPE, COMMAND_QOS, required=False),
    TopicSpec(POSITION_COMMANDS, FLOAT64_MULTI_ARRAY_TYPE, COMMAND_QOS, required=False),
    TopicSpec(ROBOT_JOINT_COMMANDS, JOINT_STATE_TYPE, COMMAND_QOS, required=False),
)

# Units of the JointState fields (revolute joint; a prismatic one reads m, m/s, N).
JOINT_STATE_UNITS: Mapping[str, str] = {"position": "rad", "velocity": "rad/s", "effort": "N m"}
MOTOR_STATE_UNITS: Mapping[str, str] = {"position": "rad", "velocity": "rad/s", "effort": "A"}

# --- vocabularies ------------------------------------------------------------------------

UNKNOWN = "unknown"
# The motion state (the upper level of the paper's Fig. 6): name <-> direction sign d.
MOTION_STATE_CODES: Mapping[str, int] = {"stop": 0, "direct": 1, "reverse": -1}
# Keyed by float too (an int code finds its name as well): snapshots carry the codes as floats.
MOTION_STATE_NAMES: Mapping[float, str] = {code: name for name, code in MOTION_STATE_CODES.items()}


class UnknownStateError(ControlParamError):
    """A state name that is not in the contract's vocabulary (the valid names are listed)."""

    def __init__(self, kind: str, name: str, valid: Sequence[str]) -> None:
        self.kind = kind
        self.name = name
        self.valid = tuple(valid)
        super().__init__(f"unknown {kind} {name!r}; valid: {', '.join(self.valid)}")


def motion_state_name(code: float) -> str:
    """The name of a motion-state code (-1, 0, +1, as int or exact float); UNKNOWN otherwise."""
    return MOTION_STATE_NAMES.get(code, UNKNOWN)


def motion_state_code(name: str) -> int:
    """The code of a motion-state name.

    Raises:
        UnknownStateError: `name` is not one of MOTION_STATE_NAMES.
    """
    try:
        return MOTION_STATE_CODES[name]
    except KeyError:
        raise UnknownStateError("motion state", name, tuple(MOTION_STATE_CODES)) from None


def drive_state_name(code: float, state_names: Sequence[str]) -> str:
    """The name of a drive-state code (an index into the robot's state names); UNKNOWN if none.

    NaN, a negative code (the CAN bridge's "not reported yet") or one past the names is UNKNOWN.
    """
    if 0 <= code < len(state_names):
        return state_names[int(code)]
    return UNKNOWN


# --- drive_chain/<joint> keys ------------------------------------------------------------

DRIVE_STATUS_PREFIX = "drive_chain/"
MOTION = "motion"  # DriveKey.kind of a motion-state name
DRIVE = "drive"  # DriveKey.kind of a drive-state name
NUMBER = "number"  # DriveKey.kind of a float, in repr form ('nan' for NaN)
TEXT = "text"  # DriveKey.kind of free text (never empty)
NO_FAULTS = "none"  # the `faults` value of a joint with no injected fault


@dataclass(frozen=True, slots=True)
class DriveKey:
    """One key of a `drive_chain/<joint>` status.

    Attributes:
        name: the key; for a number it is also the `PlantSnapshot` field it comes from.
        kind: MOTION, DRIVE (a name of that vocabulary, or UNKNOWN) or NUMBER.
        unit: SI unit of a number ("1": unitless), "" for a name.
        low, high: the closed range a finite number must lie in.
        nan: what NaN means for this key; "" if a backend must never send NaN.
        text: what the value is.
    """

    name: str
    kind: str
    unit: str
    text: str
    low: float = -math.inf
    high: float = math.inf
    nan: str = ""


_NOT_REPORTED = "the backend cannot know it (a real CiA 402 drive does not report it)"

DRIVE_KEYS: tuple[DriveKey, ...] = (
    DriveKey(
        "motion_state",
        MOTION,
        "",
        "upper level of the state machine (Fig. 6): stop, direct or reverse",
    ),
    DriveKey(
        "drive_state",
        DRIVE,
        "",
        "lower level: one of the robot's state names (Figs 7-8, Table 1); = the status message",
    ),
    DriveKey(
        "eta_m",
        NUMBER,
        "1",
        "eq. (10) coefficient on the motor torque in the active drive state",
        0.0,
        1.0,
        "undefined: the axis is stopped (the gear is locked), or " + _NOT_REPORTED,
    ),
    DriveKey(
        "eta_l",
        NUMBER,
        "1",
        "eq. (10) coefficient on the load torque in the active drive state",
        0.0,
        1.0,
        "undefined: the axis is stopped (the gear is locked), or " + _NOT_REPORTED,
    ),
    DriveKey("motor_torque_nm", NUMBER, "N m", "motor torque k_t * i, motor side"),
    DriveKey(
        "load_torque_nm",
        NUMBER,
        "N m",
        "torque the load demands at the motor shaft, eq. (8): N^-1 (C qdot + Q)",
        nan=_NOT_REPORTED,
    ),
    DriveKey(
        "friction_torque_nm",
        NUMBER,
        "N m",
        "gear friction torque at the motor shaft, eq. (3) stopped, eq. (4) moving",
        nan=_NOT_REPORTED,
    ),
    DriveKey("current_a", NUMBER, "A", "armature current"),
    DriveKey(
        "voltage_v",
        NUMBER,
        "V",
        "amplifier output voltage (within the axis's voltage_limit_v)",
        nan=_NOT_REPORTED,
    ),
    DriveKey(
        "faults",
        TEXT,
        "",
        "injected faults acting on the joint (docs/faults.md), `kind=value, ...`; 'none'",
    ),
)
DRIVE_KEY = {key.name: key for key in DRIVE_KEYS}
# Keys of each per-joint DiagnosticStatus on `drive_chain_states`, in message order (values are
# strings, as diagnostic_msgs/KeyValue requires; numbers in repr form, 'nan' for NaN).
DRIVE_STATE_KEYS: tuple[str, ...] = tuple(key.name for key in DRIVE_KEYS)
# The numeric keys, in message order: each is the `PlantSnapshot` field of the same name.
DRIVE_NUMBER_KEYS: tuple[str, ...] = tuple(k.name for k in DRIVE_KEYS if k.kind == NUMBER)


def drive_value_problems(
    values: Mapping[str, str], state_names: Sequence[str], *, allow_unknown: bool = True
) -> list[str]:
    """What is wrong with one `drive_chain/<joint>` status's key/values; [] if nothing.

    Checks the key set and order against DRIVE_STATE_KEYS, names against their vocabulary
    (with UNKNOWN only if `allow_unknown`), numbers against their range and NaN rule, and that
    text is not empty.
    """
    problems: list[str] = []
    if tuple(values) != DRIVE_STATE_KEYS:
        problems.append(f"keys {list(values)}, expected {list(DRIVE_STATE_KEYS)}")
    for key in DRIVE_KEYS:
        if key.name not in values:
            continue
        problem = _drive_value_problem(key, values[key.name], state_names, allow_unknown)
        if problem:
            problems.append(problem)
    return problems


def _drive_value_problem(
    key: DriveKey, text: str, state_names: Sequence[str], allow_unknown: bool
) -> str:
    """What is wrong with one value of `key`; "" if nothing."""
    if key.kind == TEXT:
        return "" if text else f"{key.name} is empty"
    if key.kind != NUMBER:
        vocabulary = tuple(MOTION_STATE_CODES) if key.kind == MOTION else tuple(state_names)
        if text not in vocabulary and not (allow_unknown and text == UNKNOWN):
            return f"{key.name} {text!r} not in {list(vocabulary)}"
        return ""
    try:
        number = float(text)
    except ValueError:
        return f"{key.name} {text!r} is not a number"
    if math.isnan(number):
        return "" if key.nan else f"{key.name} is NaN, which it must never be"
    if not key.low <= number <= key.high:
        return f"{key.name} {text} outside [{key.low:g}, {key.high:g}] {key.unit}"
    return ""


# --- the snapshot a backend fills --------------------------------------------------------


@dataclass(frozen=True, slots=True)
class PlantSnapshot:
    """One instant of a plant, everything the contract's state topics carry (no ROS types).

    Every per-joint field is a 1-D float64 array in `joints` order. A backend may hand views
    of its live state and reuse its arrays (the simulator does, to keep its publish path free
    of allocations): the snapshot is then valid until the backend advances or takes its next
    snapshot, and the builder consumes it at once. NaN marks a value the backend cannot know.

    Attributes:
        stamp_s: the instant (s; simulated time, or the wall time of the CAN SYNC).
        joints: joint names, in the robot's axis order.
        position, velocity, effort: joint side (rad, rad/s, N m; m, m/s, N for the lift);
            effort = N * tau_m.
        motor_position_rad, motor_velocity_rad_s: motor side.
        current_a: armature current (A).
        motion_state: codes -1, 0, +1 (MOTION_STATE_NAMES) as floats; NaN if unknown.
        drive_state: indices into `state_names` as floats; NaN (or negative) if unknown.
        state_names: the robot's drive-state names (`RobotParams.state_machine.state_names`).
        eta_m, eta_l: eq. (10) coefficients (1), NaN while stopped.
        motor_torque_nm, load_torque_nm, friction_torque_nm: motor side (N m).
        voltage_v: amplifier voltage (V).
        faults: injected faults per joint as text (`drive_chain/<joint>` key `faults`); empty:
            none on any joint.
    """

    stamp_s: float
    joints: tuple[str, ...]
    position: FloatArray
    velocity: FloatArray
    effort: FloatArray
    motor_position_rad: FloatArray
    motor_velocity_rad_s: FloatArray
    current_a: FloatArray
    motion_state: FloatArray
    drive_state: FloatArray
    state_names: tuple[str, ...]
    eta_m: FloatArray
    eta_l: FloatArray
    motor_torque_nm: FloatArray
    load_torque_nm: FloatArray
    friction_torque_nm: FloatArray
    voltage_v: FloatArray
    faults: tuple[str, ...] = ()  # per joint, the `faults` key; () for NO_FAULTS on every joint

    @property
    def motion_state_names(self) -> tuple[str, ...]:
        """The motion state of each joint by name (UNKNOWN where the code is unknown)."""
        return tuple(motion_state_name(c) for c in self.motion_state.tolist())

    @property
    def drive_state_names(self) -> tuple[str, ...]:
        """The drive state of each joint by name (UNKNOWN where the code is unknown)."""
        return tuple(drive_state_name(c, self.state_names) for c in self.drive_state.tolist())
