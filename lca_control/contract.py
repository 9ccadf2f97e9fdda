"""The ROS 2 topic interface of lca_hil: names, types and QoS shared by every node and tool.

The simulator node and the CAN bridge publish the same topics and take the same commands, so
the controller (and any user's controller) works against either unchanged.

Topics (type, publisher, content):

* `joint_states` (sensor_msgs/JointState, plant): joint side, SI (rad, rad/s; m, m/s for the
  lift); effort = N * tau_m, the joint torque (force) the motor applies through the gear before
  losses (N m, N).
* `motor_states` (sensor_msgs/JointState, plant): motor side, position (rad), velocity (rad/s),
  effort = armature current (A).
* `drive_chain_states` (diagnostic_msgs/DiagnosticArray, plant): one status per axis, named
  `drive_chain/<joint>`, message = drive state, key/values `DRIVE_STATE_KEYS`.
* `/diagnostics` (diagnostic_msgs/DiagnosticArray, every node): 1 Hz health, counters, faults.
* `/clock` (rosgraph_msgs/Clock, simulator): simulated time, in lockstep.
* `voltage_commands` (std_msgs/Float64MultiArray, controller): V per joint, in the order of the
  `joints` parameter (the ros2_control forward-command convention).
* `current_commands` (std_msgs/Float64MultiArray, controller): A per joint; the current loop
  runs in the drive.
* `velocity_reference` (std_msgs/Float64MultiArray, user): rad/s (m/s) per joint.

This module imports no ROS package: names and keys only, so tools and tests can share them.
"""

from __future__ import annotations

JOINT_STATES = "joint_states"
MOTOR_STATES = "motor_states"
DRIVE_CHAIN_STATES = "drive_chain_states"
DIAGNOSTICS = "/diagnostics"
CLOCK = "/clock"
VOLTAGE_COMMANDS = "voltage_commands"
CURRENT_COMMANDS = "current_commands"
VELOCITY_REFERENCE = "velocity_reference"

JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
DIAGNOSTIC_ARRAY_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
FLOAT64_MULTI_ARRAY_TYPE = "std_msgs/msg/Float64MultiArray"

# Keys of each per-axis DiagnosticStatus on `drive_chain_states` (values are strings, as
# diagnostic_msgs/KeyValue requires; numbers in repr form, SI units in the key names). The
# status `name` is `drive_chain/<joint>`, its `message` the drive-state name.
DRIVE_STATE_KEYS: tuple[str, ...] = (
    "motion_state",
    "drive_state",
    "eta_m",
    "eta_l",
    "motor_torque_nm",
    "load_torque_nm",
    "friction_torque_nm",
    "current_a",
    "voltage_v",
)
DRIVE_STATUS_PREFIX = "drive_chain/"

# Reliable, keep-last: the lockstep loop must not drop a state or a command, and a recorder
# that falls behind for a moment must not lose samples either.
STATE_QOS_DEPTH = 100
COMMAND_QOS_DEPTH = 10
