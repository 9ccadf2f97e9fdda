"""The entry points of the ROS 2 node scripts: `--help` answered before ROS 2 is imported.

`lca-simulator`, `lca-controller` and `lca-can-bridge` (and their `ros2 run lca_hil` names) start
here, not in the node modules: those import rclpy at module level, so the help has to be printed
before they are imported. `-h` / `--help` among the script's own arguments (outside
`--ros-args ... --`) prints the usage, what the node does, its topics and services, and its
parameter table (`ParameterTable.describe`: type, default, range, live or read-only), and exits 0
without importing rclpy. Any other command line goes unchanged to the node module's `main`.

The topic names come from `lca_control.contract` and the parameters from the same tables the
nodes declare, so the help cannot drift from what the node does.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass

from lca_control import contract as pc
from lca_control.controller import CONTROLLER_PARAMETERS
from lca_control.parameters import ParameterTable
from lca_sim.cli.console import own_arguments, script_arguments, wants_help
from lca_sim.config.can_bridge_params import CAN_BRIDGE_PARAMETERS
from lca_sim.config.simulator_params import SIMULATOR_PARAMETERS
from lca_sim.errors import EXIT_OK
from lca_sim.ros.tool_args import echo_parser, record_parser


@dataclass(frozen=True, slots=True)
class NodeScript:
    """What the help of one node script says.

    Attributes:
        prog: the console script name (`lca-simulator`).
        executable: the `ros2 run lca_hil <executable>` name.
        summary: what the node does, in a sentence or two.
        publishes: the topics it publishes, each with a note when it depends on a parameter.
        subscribes: the topics it subscribes to, likewise.
        services: its services with their types.
        table: its parameter table.
    """

    prog: str
    executable: str
    summary: str
    publishes: tuple[str, ...]
    subscribes: tuple[str, ...]
    services: tuple[str, ...]
    table: ParameterTable

    def help_text(self) -> str:
        """The full --help text."""
        usage = "[--ros-args --params-file FILE | -p name:=value ...]"
        lines = [
            f"usage: {self.prog} {usage}",
            f"       ros2 run lca_hil {self.executable} {usage}",
            "",
            self.summary,
            "",
            "Publishes:",
            *(f"  {topic}" for topic in self.publishes),
            "Subscribes:",
            *(f"  {topic}" for topic in self.subscribes),
            "Services:",
            *(f"  {service}" for service in self.services),
            "",
            "Parameters (name (type; default; range; live or read-only): description):",
            self.table.describe(),
        ]
        return "\n".join(lines) + "\n"


_PLANT_STATES = (
    f"{pc.JOINT_STATES} ({pc.JOINT_STATE_TYPE}): joint side, SI",
    f"{pc.MOTOR_STATES} ({pc.JOINT_STATE_TYPE}): motor side, effort = current (A)",
    f"{pc.DRIVE_CHAIN_STATES} ({pc.DIAGNOSTIC_ARRAY_TYPE}): drive and motion state per joint",
    f"{pc.DIAGNOSTICS} ({pc.DIAGNOSTIC_ARRAY_TYPE}): health and counters",
)

SIMULATOR = NodeScript(
    prog="lca-simulator",
    executable="simulator",
    summary=(
        "The simulated LCA robot as a ROS 2 plant: takes voltage or current commands, steps the\n"
        "drive-chain model (realtime: paced by the wall clock; lockstep: one control period per\n"
        "command) and publishes the plant states of lca_control.contract."
    ),
    publishes=(
        *_PLANT_STATES,
        f"{pc.CLOCK} ({pc.CLOCK_TYPE}): simulated time, in lockstep only",
    ),
    subscribes=(
        f"{pc.VOLTAGE_COMMANDS} or {pc.CURRENT_COMMANDS} ({pc.FLOAT64_MULTI_ARRAY_TYPE}): "
        "per command_interface; the other one is counted and refused",
    ),
    services=(
        "~/reset (std_srvs/srv/Trigger): back to initial_position",
        "~/enable (std_srvs/srv/SetBool): sets the enabled parameter",
    ),
    table=SIMULATOR_PARAMETERS,
)

CONTROLLER = NodeScript(
    prog="lca-controller",
    executable="controller",
    summary=(
        "The paper's cascaded PI controller over topics: one command per new plant state, the\n"
        "period taken from the state stamps, so it drives the simulator and the CAN bridge alike."
    ),
    publishes=(
        f"{pc.VOLTAGE_COMMANDS} or {pc.CURRENT_COMMANDS} ({pc.FLOAT64_MULTI_ARRAY_TYPE}): "
        "per command_interface",
        f"{pc.DIAGNOSTICS} ({pc.DIAGNOSTIC_ARRAY_TYPE}): health and counters",
    ),
    subscribes=(
        f"{pc.JOINT_STATES} ({pc.JOINT_STATE_TYPE})",
        f"{pc.MOTOR_STATES} ({pc.JOINT_STATE_TYPE}): with voltage commands only (current loop)",
        f"{pc.VELOCITY_REFERENCE} ({pc.FLOAT64_MULTI_ARRAY_TYPE}): rad/s (m/s) per joint",
    ),
    services=("~/enable (std_srvs/srv/SetBool): sets the enabled parameter",),
    table=CONTROLLER_PARAMETERS,
)

CAN_BRIDGE = NodeScript(
    prog="lca-can-bridge",
    executable="can_bridge",
    summary=(
        "Replaces the simulator with CiA 402 drives on a CAN bus (the virtual drive rack with\n"
        "interface virtual): current commands become torque set-points, each SYNC cycle one set\n"
        "of plant states of lca_control.contract. A managed (lifecycle) node: with autostart\n"
        "it configures and activates itself; docs/can.md."
    ),
    publishes=_PLANT_STATES,
    subscribes=(
        f"{pc.CURRENT_COMMANDS} ({pc.FLOAT64_MULTI_ARRAY_TYPE}): A per joint",
        f"{pc.VOLTAGE_COMMANDS} ({pc.FLOAT64_MULTI_ARRAY_TYPE}): counted and refused",
    ),
    services=(
        "~/init, ~/enable, ~/disable, ~/halt, ~/recover, ~/cyclic_torque_mode "
        "(std_srvs/srv/Trigger)",
        "~/sdo_read (rcl_interfaces/srv/GetParameters): names <joint>/<index>[/<subindex>]",
        "~/sdo_write (rcl_interfaces/srv/SetParameters): the same names",
        "~/change_state, ~/get_state, ... (lifecycle_msgs/srv/...): configure, activate, "
        "deactivate, cleanup, shutdown (`ros2 lifecycle set`)",
    ),
    table=CAN_BRIDGE_PARAMETERS,
)


def answered_help(script: NodeScript, args: Sequence[str] | None) -> bool:
    """Print the script's help and return True if its arguments ask for it (None: sys.argv)."""
    if not wants_help(script_arguments(args)):
        return False
    sys.stdout.write(script.help_text())
    return True


# Each node module is imported only after the help check: importing it loads rclpy.


def simulator(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-simulator` / `ros2 run lca_hil simulator`."""
    if answered_help(SIMULATOR, args):
        return EXIT_OK
    from lca_sim.ros.simulator_node import main  # noqa: PLC0415

    return main(args)


def controller(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-controller` / `ros2 run lca_hil controller`."""
    if answered_help(CONTROLLER, args):
        return EXIT_OK
    from lca_sim.ros.controller_node import main  # noqa: PLC0415

    return main(args)


def can_bridge(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-can-bridge` / `ros2 run lca_hil can_bridge`."""
    if answered_help(CAN_BRIDGE, args):
        return EXIT_OK
    from lca_sim.ros.can_bridge_node import main  # noqa: PLC0415

    return main(args)


def _tool_help(parser: argparse.ArgumentParser, args: Sequence[str] | None) -> bool:
    if not wants_help(script_arguments(args)):
        return False
    sys.stdout.write(parser.format_help())
    return True


def record(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-record` / `ros2 run lca_hil record`."""
    if _tool_help(record_parser(), args):
        return EXIT_OK
    own = own_arguments(script_arguments(args))
    if any(arg == "--recover" or arg.startswith("--recover=") for arg in own):
        # Recovery reads and writes files only: no rclpy, so it works where ROS 2 is absent.
        from lca_sim.ros.bag_recover import recover_main  # noqa: PLC0415

        return recover_main(own)
    from lca_sim.ros.record import main  # noqa: PLC0415

    return main(args)


def echo(args: Sequence[str] | None = None) -> int:
    """Entry point of `lca-echo`."""
    if _tool_help(echo_parser(), args):
        return EXIT_OK
    from lca_sim.ros.echo import main  # noqa: PLC0415

    return main(args)
