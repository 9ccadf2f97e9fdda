"""Typed, validated parameters of the CAN bridge node (pure: no ROS, no CAN import).

Same pattern as `lca_sim.ros.simulator_params`: the node declares these, and start-up builds
`CanBridgeNodeParams` here (one error line and exit code 2 on a bad value).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from lca_sim.errors import ConfigError
from lca_sim.model.params import AXIS_NAMES

# name -> (default, description with unit). Order is the declaration order.
CAN_BRIDGE_PARAMETERS: dict[str, tuple[Any, str]] = {
    "interface": ("virtual", "python-can interface: socketcan (can0, vcan0) or virtual"),
    "channel": ("lca_can", "bus channel: can0 for socketcan; any name for virtual"),
    "bitrate": (1_000_000, "bit rate, bit/s (bus-load figure; socketcan takes the link's)"),
    "eds": ("", "EDS of the drives; empty: config/can/lca_drive.eds (the virtual drive)"),
    "rack_config": ("", "virtual only: rack YAML; empty: config/can/rack.yaml"),
    "robot": ("default", "robot YAML path or shipped name: k_t, gear ratios, drive states"),
    "joints": (list(AXIS_NAMES), "joint order of the command arrays and published states"),
    "node_ids": ([1, 2, 3, 4], "CANopen node id of each joint's drive"),
    "master_node_id": (127, "the bridge's own node id (its heartbeat)"),
    "command_interface": ("current", "only current (A): target torque = k_t i"),
    "cycle_hz": (500.0, "SYNC and RPDO rate, Hz"),
    "command_timeout_s": (0.1, "controller silence: zero torque and halt after this, s"),
    "quick_stop_after_s": (0.5, "then quick stop after this much more silence, s"),
    "stale_timeout_s": (0.1, "a drive without TPDO this long is stale: every axis stops, s"),
    "heartbeat_producer_ms": (100, "written to each drive's 0x1017, ms"),
    "heartbeat_consumer_ms": (300, "each drive's 0x1016 watch on the bridge's heartbeat, ms"),
    "rpdo_deadline_ms": (100, "each drive's RPDO1 deadline (0x1400 sub 5), ms"),
    "max_send_failures": (10, "consecutive failed sends after which the axes halt"),
    "auto_init": (True, "configure and start the drives at start-up (else: ~/init)"),
    "auto_enable": (False, "enable operation after init (else: ~/enable)"),
    "diagnostics_period_s": (1.0, "period of /diagnostics, s"),
}


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
    cycle_hz: float
    command_timeout_s: float
    quick_stop_after_s: float
    stale_timeout_s: float
    heartbeat_producer_ms: int
    heartbeat_consumer_ms: int
    rpdo_deadline_ms: int
    max_send_failures: int
    auto_init: bool
    auto_enable: bool
    diagnostics_period_s: float


def _number(values: Mapping[str, Any], name: str, low: float, high: float) -> float:
    value = values[name]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError("parameters", name, f"expected a number, got {value!r}")
    if not (math.isfinite(value) and low < value <= high):
        raise ConfigError("parameters", name, f"expected a number in ({low:g}, {high:g}]")
    return float(value)


def _integer(values: Mapping[str, Any], name: str, low: int, high: int) -> int:
    value = values[name]
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ConfigError("parameters", name, f"expected an integer in [{low}, {high}]")
    return value


def validate_can_bridge_params(values: Mapping[str, Any]) -> CanBridgeNodeParams:
    """Check every parameter and build the typed params.

    Raises:
        ConfigError: with source "parameters", the parameter name and what was expected.
    """
    interface = str(values["interface"])
    if interface == "udp_multicast":
        raise ConfigError("parameters", "interface", "udp_multicast leaves this machine: refused")
    if not interface:
        raise ConfigError("parameters", "interface", "expected socketcan, virtual or another")
    joints = tuple(str(j) for j in values["joints"])
    if not joints or any(j not in AXIS_NAMES for j in joints) or len(set(joints)) != len(joints):
        raise ConfigError(
            "parameters", "joints", f"expected distinct names among {', '.join(AXIS_NAMES)}"
        )
    node_ids = tuple(values["node_ids"])
    master = _integer(values, "master_node_id", 1, 127)
    if (
        len(node_ids) != len(joints)
        or any(isinstance(i, bool) or not isinstance(i, int) or not 1 <= i <= 127 for i in node_ids)
        or len({*node_ids, master}) != len(node_ids) + 1
    ):
        raise ConfigError(
            "parameters",
            "node_ids",
            f"expected {len(joints)} distinct ids in 1..127, other than master_node_id {master}",
        )
    if str(values["command_interface"]) != "current":
        raise ConfigError(
            "parameters",
            "command_interface",
            "the bridge takes current commands only (CiA 402 torque mode: the current loop "
            "runs in the drive); run the controller with command_interface: current",
        )
    return CanBridgeNodeParams(
        interface=interface,
        channel=str(values["channel"]),
        bitrate=_integer(values, "bitrate", 10_000, 1_000_000),
        eds=str(values["eds"]),
        rack_config=str(values["rack_config"]),
        robot=str(values["robot"]),
        joints=joints,
        node_ids=tuple(int(i) for i in node_ids),
        master_node_id=master,
        cycle_hz=_number(values, "cycle_hz", 0.0, 2000.0),
        command_timeout_s=_number(values, "command_timeout_s", 0.0, 60.0),
        quick_stop_after_s=_number(values, "quick_stop_after_s", 0.0, 60.0),
        stale_timeout_s=_number(values, "stale_timeout_s", 0.0, 60.0),
        heartbeat_producer_ms=_integer(values, "heartbeat_producer_ms", 1, 65535),
        heartbeat_consumer_ms=_integer(values, "heartbeat_consumer_ms", 1, 65535),
        rpdo_deadline_ms=_integer(values, "rpdo_deadline_ms", 0, 65535),
        max_send_failures=_integer(values, "max_send_failures", 1, 1_000_000),
        auto_init=bool(values["auto_init"]),
        auto_enable=bool(values["auto_enable"]),
        diagnostics_period_s=_number(values, "diagnostics_period_s", 0.0, 60.0),
    )
