"""Typed, validated parameters of the CAN bridge node (pure: no ROS, no CAN import).

Same pattern as `lca_sim.config.simulator_params`: the node declares `CAN_BRIDGE_PARAMETERS`, and
start-up builds `CanBridgeNodeParams` here (one error line and exit code 2 on a bad value); a
live set goes through the same check, and a read-only parameter is refused while running.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from lca_control.parameters import (
    ParameterError,
    ParameterTable,
    ParamKind,
    ParamSpec,
    positive,
)
from lca_sim.config.simulator_params import (
    ROS2_CONTROL_PARAMETERS,
    SIMULATOR_PARAMETERS,
    check_topic,
)
from lca_sim.model.params import AXIS_NAMES

S, INT = ParamKind.STRING, ParamKind.INTEGER

# Declaration order. Read-only: the bus, the drives' configuration (written over SDO at init)
# and the wiring; live: the bridge's own safety timing, which takes effect at the next cycle.
CAN_BRIDGE_PARAMETERS = ParameterTable(
    (
        ParamSpec("interface", S, "virtual",
                  "python-can interface: socketcan (can0, vcan0), virtual, or lca_remote "
                  "(lca-can-server, docs/can-transport.md)", live=False),
        ParamSpec("channel", S, "lca_can",
                  "bus channel: can0 for socketcan; any name for virtual", live=False),
        ParamSpec("bitrate", INT, 1_000_000,
                  "bit rate, bit/s (bus-load figure; socketcan takes the link's)",
                  10_000, 1_000_000, live=False),
        ParamSpec("eds", S, "",
                  "EDS of the drives; empty: config/can/lca_drive.eds (the virtual drive)",
                  live=False),
        ParamSpec("rack_config", S, "",
                  "virtual only: rack YAML; empty: config/can/rack.yaml", live=False),
        ParamSpec("robot", S, "default",
                  "robot YAML path or shipped name: k_t, gear ratios, drive states", live=False),
        ParamSpec("joints", ParamKind.STRING_ARRAY, list(AXIS_NAMES),
                  "joint order of the command arrays and published states",
                  choices=AXIS_NAMES, live=False),
        ParamSpec("node_ids", ParamKind.INTEGER_ARRAY, [1, 2, 3, 4],
                  "CANopen node id of each joint's drive", 1, 127, live=False),
        ParamSpec("master_node_id", INT, 127, "the bridge's own node id (its heartbeat)",
                  1, 127, live=False),
        ParamSpec("modes", ParamKind.STRING_ARRAY, [],
                  "per joint: cst (current commands -> target torque), csv (velocity_commands "
                  "-> target velocity, the drive's velocity loop) or csp (position_commands -> "
                  "target position, the drive's position and velocity loops); empty: all cst",
                  choices=("cst", "csv", "csp"), live=False),
        ParamSpec("command_interface", S, "current",
                  "only current (A): target torque = k_t i (CiA 402 torque mode)",
                  choices=("current",), live=False),
        positive("cycle_hz", 500.0, "SYNC and RPDO rate, Hz", high=2000.0, live=False),
        replace(SIMULATOR_PARAMETERS["timing_mode"],
                description="realtime (SYNC paced by the wall clock) or lockstep (one SYNC per "
                "command, simulated time 1/cycle_hz per SYNC; the rack must run in lockstep "
                "too: interface virtual does it, lca-virtual-drive --timing-mode lockstep)"),
        SIMULATOR_PARAMETERS["lockstep_subscribers"],
        replace(SIMULATOR_PARAMETERS["lockstep_resend_s"],
                description="lockstep: re-publish the last state after this silence of the "
                "controller, or send the next SYNC after this wait for an incomplete cycle, s",
                live=False),
        positive("command_timeout_s", 0.1,
                 "controller silence: zero torque and halt after this, s", high=60.0),
        positive("quick_stop_after_s", 0.5, "then quick stop after this much more silence, s",
                 high=60.0),
        positive("stale_timeout_s", 0.1,
                 "a drive without TPDO this long is stale: every axis stops, s", high=60.0),
        ParamSpec("heartbeat_producer_ms", INT, 100, "written to each drive's 0x1017, ms",
                  1, 65535, live=False),
        ParamSpec("heartbeat_consumer_ms", INT, 300,
                  "each drive's 0x1016 watch on the bridge's heartbeat, ms", 1, 65535,
                  live=False),
        ParamSpec("pdo_layout", S, "compact",
                  "compact: init maps the drives' PDOs for a fast cycle (docs/can.md); "
                  "drive: use the drive's own mapping", choices=("compact", "drive"),
                  live=False),
        positive("slow_tpdo_rate_hz", 50.0,
                 "compact layout: rate of statusword, current and extras TPDOs, Hz",
                 high=2000.0, live=False),
        ParamSpec("rpdo_deadline_ms", INT, 100, "each drive's RPDO1 deadline (0x1400 sub 5), ms",
                  0, 65535, live=False),
        ParamSpec("max_send_failures", INT, 10,
                  "consecutive failed sends after which the axes halt", 1, 1_000_000),
        ParamSpec("autostart", ParamKind.BOOL, True,
                  "configure and activate at start-up (auto_init, auto_enable apply), as a "
                  "plain start; false: wait unconfigured for a lifecycle manager", live=False),
        ParamSpec("auto_init", ParamKind.BOOL, True,
                  "autostart: configure and start the drives at start-up (else: ~/init)",
                  live=False),
        ParamSpec("auto_enable", ParamKind.BOOL, False,
                  "autostart: enable operation after init (else: ~/enable)", live=False),
        *ROS2_CONTROL_PARAMETERS,
        positive("diagnostics_period_s", 1.0, "period of /diagnostics, s", high=60.0),
    )
)  # fmt: skip


@dataclass(frozen=True, slots=True)
class CanBridgeNodeParams:
    """Validated CAN bridge parameters; names carry their unit."""

    interface: str
    channel: str
    bitrate: int
    eds: str
    rack_config: str
    robot: str
    joints: tuple[str, ...]
    node_ids: tuple[int, ...]
    master_node_id: int
    modes: tuple[str, ...]
    cycle_hz: float
    timing_mode: str
    lockstep_subscribers: int
    lockstep_resend_s: float
    command_timeout_s: float
    quick_stop_after_s: float
    stale_timeout_s: float
    heartbeat_producer_ms: int
    heartbeat_consumer_ms: int
    pdo_layout: str
    slow_tpdo_rate_hz: float
    rpdo_deadline_ms: int
    max_send_failures: int
    autostart: bool
    auto_init: bool
    auto_enable: bool
    joint_command_topic: str
    joint_state_topic: str
    joint_command_effort: str
    diagnostics_period_s: float


def validate_can_bridge_params(values: Mapping[str, Any]) -> CanBridgeNodeParams:
    """Check every parameter (`CAN_BRIDGE_PARAMETERS`) and build the typed params.

    Raises:
        ParameterError: the parameter name, what was expected and the value.
    """
    v = CAN_BRIDGE_PARAMETERS.check_all(values)
    interface = v["interface"]
    if interface == "udp_multicast":
        raise ParameterError("interface", "not udp_multicast (it leaves this machine)", interface)
    if not interface:
        raise ParameterError("interface", "socketcan, virtual or another python-can one", "")
    joints: tuple[str, ...] = v["joints"]
    if not joints or len(set(joints)) != len(joints):
        raise ParameterError("joints", f"distinct names among {', '.join(AXIS_NAMES)}", joints)
    node_ids: tuple[int, ...] = v["node_ids"]
    master = v["master_node_id"]
    if len(node_ids) != len(joints) or len({*node_ids, master}) != len(node_ids) + 1:
        raise ParameterError(
            "node_ids",
            f"{len(joints)} distinct ids in 1..127, other than master_node_id {master}",
            node_ids,
        )
    modes: tuple[str, ...] = v["modes"]
    if modes and len(modes) != len(joints):
        raise ParameterError("modes", f"{len(joints)} modes (one per joint) or none", modes)
    for name in ("joint_command_topic", "joint_state_topic"):
        check_topic(name, v[name])
    fields = {k: v[k] for k in v if k != "command_interface"}
    return CanBridgeNodeParams(**fields)
