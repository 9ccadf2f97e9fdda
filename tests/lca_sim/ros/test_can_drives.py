"""The bridge's BridgeParams come from its node parameters field by field, none forgotten.

Pure: no bus is opened and no rclpy context started.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import pytest

from lca_sim.canbus.master_params import BridgeParams
from lca_sim.config.can_bridge_params import CAN_BRIDGE_PARAMETERS, validate_can_bridge_params
from lca_sim.ros import can_drives
from lca_sim.ros.can_drives import (
    FROM_ROBOT,
    LIVE_FIELDS,
    MASTER_DEFAULTS,
    RENAMED,
    UnmappedFieldError,
    bridge_params,
    live_bridge_params,
)

# Every value other than its default, so a field taken from the wrong place shows.
NODE_VALUES: dict[str, Any] = {
    "bitrate": 500_000,
    "node_ids": [11, 12, 13, 14],
    "master_node_id": 100,
    "modes": ["cst", "csv", "cst", "cst"],
    "cycle_hz": 250.0,
    "command_timeout_s": 0.2,
    "quick_stop_after_s": 0.7,
    "stale_timeout_s": 0.3,
    "heartbeat_producer_ms": 50,
    "heartbeat_consumer_ms": 250,
    "pdo_layout": "drive",
    "slow_tpdo_rate_hz": 25.0,
    "rpdo_deadline_ms": 40,
    "max_send_failures": 3,
}
ROBOT_VALUES: dict[str, Any] = {
    "torque_constants_nm_per_a": (0.1, 0.2, 0.3, 0.4),
    "gear_ratios": (10.0, 20.0, 30.0, 40.0),
    "drive_state_names": ("a", "b"),
}


def node_params() -> Any:
    return validate_can_bridge_params({**CAN_BRIDGE_PARAMETERS.defaults(), **NODE_VALUES})


def test_every_field_comes_from_the_node_the_robot_or_a_named_default() -> None:
    """Each BridgeParams field has the node's value (or the robot's, or the master's default)."""
    p = node_params()
    built = bridge_params(p, ROBOT_VALUES)
    for f in fields(BridgeParams):
        value = getattr(built, f.name)
        if f.name in MASTER_DEFAULTS:
            assert value == f.default, f.name
        elif f.name in FROM_ROBOT:
            assert value == ROBOT_VALUES[f.name], f.name
        else:
            assert value == getattr(p, RENAMED.get(f.name, f.name)), f.name
            assert value != f.default, f"{f.name}: NODE_VALUES should set it off its default"


def test_a_field_without_source_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """A field added to BridgeParams that nothing fills fails the build (it cannot drift)."""

    @dataclass(frozen=True)
    class Wider(BridgeParams):
        brand_new_field_s: float = 1.0

    monkeypatch.setattr(can_drives, "BridgeParams", Wider)
    with pytest.raises(UnmappedFieldError, match="brand_new_field_s"):
        bridge_params(node_params(), ROBOT_VALUES)


def test_a_live_set_changes_exactly_the_live_safety_timing() -> None:
    """The master's live fields are the bridge's live parameters it has."""
    assert set(LIVE_FIELDS) == {
        "command_timeout_s",
        "quick_stop_after_s",
        "stale_timeout_s",
        "max_send_failures",
    }
    built = bridge_params(node_params(), ROBOT_VALUES)
    defaults = validate_can_bridge_params(CAN_BRIDGE_PARAMETERS.defaults())
    live = live_bridge_params(built, defaults)
    for f in fields(BridgeParams):
        expected = getattr(defaults if f.name in LIVE_FIELDS else built, f.name)
        assert getattr(live, f.name) == expected, f.name
