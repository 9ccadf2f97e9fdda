"""The swap: the unchanged controller node, closed-loop over CAN, replays Fig. 15.

The CAN bridge node (interface virtual: the virtual drive rack in this process, on python-can's
virtual bus) replaces the simulator node; the controller node is the same, with the same
parameters as against the simulator (config/ros/controller.yaml's ramp: pivot to 5 deg/s over
10 s from 35 deg). The test checks what the simulator test checks: the ramp is tracked, and the
drive-chain state, as the drive reports it over TPDO3, leaves motor driving near 55 deg. This
runs on the wall clock (about 12 s): CAN has no lockstep.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from lca_control.node import ControllerNode
from lca_sim import ros_interface as ri
from lca_sim.can_bridge_node import CanBridgeNode
from lca_sim.config import config_dir
from lca_sim.rosutil import make_executor

DOMAIN_ID = 131


def _controller_yaml() -> list[Parameter]:
    """The controller's parameters exactly as shipped (the same file the simulator runs with)."""
    with (config_dir() / "ros" / "controller.yaml").open() as f:
        values = yaml.safe_load(f)["controller"]["ros__parameters"]
    return [Parameter(name, value=value) for name, value in values.items()]


def _roomy_rack_config(tmp_path: Path) -> Path:
    """The shipped rack with a 50-period SYNC-loss watch instead of 10 (see the test)."""
    with (config_dir() / "can" / "rack.yaml").open() as f:
        rack = yaml.safe_load(f)
    rack["sync_loss_periods"] = 50
    path = tmp_path / "rack.yaml"
    path.write_text(yaml.safe_dump(rack))
    return path


def test_controller_unchanged_over_can_tracks_the_ramp_and_switches_near_55_deg(
    tmp_path: Path,
) -> None:
    ctx = Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    executor = make_executor(ctx)  # the executor the nodes spin in production (run_node)
    bridge = ctl = probe = None
    try:
        # The controller and the probe first: their construction (type support libraries loaded
        # on a fresh machine) then cannot stall the CAN cycle, which starts with the bridge.
        ctl = ControllerNode(context=ctx, parameter_overrides=_controller_yaml())
        probe = Node("swap_probe", context=ctx)
        bridge = CanBridgeNode(
            context=ctx,
            parameter_overrides=[
                Parameter("interface", value="virtual"),
                Parameter("channel", value="test_can_swap"),
                Parameter("auto_enable", value=True),
                # The controller's period in the lockstep test (4 ms); one process carries the
                # rack, the bridge, the controller and this probe here, on 2 cores.
                Parameter("cycle_hz", value=250.0),
                # Watchdogs with room for this process's GIL: the rack, the bridge, the
                # controller and the probe share one interpreter here, and on a fresh 2-core
                # machine the bridge's cycle thread was once starved past the 40 ms SYNC-loss
                # watch. The watchdogs have their own tests (test_virtual_drive, test_can_bridge).
                Parameter("rack_config", value=str(_roomy_rack_config(tmp_path))),
                Parameter("rpdo_deadline_ms", value=500),
                Parameter("heartbeat_consumer_ms", value=1000),
                Parameter("stale_timeout_s", value=0.5),
            ],
        )
        states: list[JointState] = []
        transitions: list[tuple[float, str, float]] = []
        last_state = {"name": ""}
        latest_position = {"pivot": math.nan}

        def on_joint(msg: JointState) -> None:
            states.append(msg)
            latest_position["pivot"] = msg.position[1]

        def on_drive(msg: DiagnosticArray) -> None:
            for status in msg.status:
                pivot = status.name == ri.DRIVE_STATUS_PREFIX + "pivot"
                if pivot and status.message != last_state["name"]:
                    t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                    transitions.append((t, status.message, latest_position["pivot"]))
                    last_state["name"] = status.message

        probe.create_subscription(JointState, ri.JOINT_STATES, on_joint, 100)
        probe.create_subscription(DiagnosticArray, ri.DRIVE_CHAIN_STATES, on_drive, 100)
        for node in (bridge, ctl, probe):
            executor.add_node(node)
        deadline = time.monotonic() + 60.0
        while ctl.core.elapsed_s < 11.5:
            assert time.monotonic() < deadline, f"only {ctl.core.elapsed_s:.2f} s of the ramp"
            executor.spin_once(timeout_sec=0.05)
        assert bridge.bridge.latched_reason() == ""
        names = [name for _, name, _ in transitions]
        assert "motor_driving" in names, transitions
        first_motor = names.index("motor_driving")
        # The load starts driving where the centre of gravity passes over the axis. Before it,
        # only motor driving and (during a brief brake of the velocity loop) coasting can occur:
        # both are states where the load resists. A cold-start run showed such a brake at 41 deg.
        load_drives = ("motor_and_load_driving", "load_driving")
        switch = next(t for t in transitions[first_motor:] if t[1].startswith(load_drives))
        before = {t[1] for t in transitions[first_motor:] if t[0] < switch[0]}
        assert before <= {"motor_driving", "coasting"}, transitions
        assert math.degrees(switch[2]) == pytest.approx(55.0, abs=1.0)
        ramp = ctl.core.params.profile
        assert ramp is not None
        t0 = states[0].header.stamp.sec + 1e-9 * states[0].header.stamp.nanosec
        errors = []
        for msg in states:
            t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec - t0
            if 2.0 < t < 10.9:
                errors.append(abs(msg.velocity[1] - ramp.velocity(t)))
        assert len(errors) > 1500  # 250 Hz over 8.9 s: 2225, less any incomplete cycles
        assert math.degrees(max(errors)) < 0.5  # deg/s (0.3 over the lockstep simulator)
    finally:
        started: tuple[Node | None, ...] = (probe, ctl, bridge)
        for leftover in started:
            if leftover is not None:
                leftover.destroy_node()
        executor.shutdown()
        rclpy.shutdown(context=ctx)
