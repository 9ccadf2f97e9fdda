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
import warnings
from array import array
from dataclasses import dataclass
from pathlib import Path

import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from support import FreezeWatch, late_share, skip_if_host_too_slow

from lca_control import contract as ri
from lca_control.profiles import RampProfile
from lca_control.ros.controller_node import ControllerNode
from lca_sim.config.loader import config_dir
from lca_sim.ros.can_bridge_node import CanBridgeNode
from lca_sim.ros.node_util import from_stamp, make_executor

DOMAIN_ID = 131
LONG_FREEZE_MS = 40  # 10 periods of the 4 ms loop with stale commands
TRACKING_FROM_S = 2.0  # into the ramp: where tracking is judged (before, stick-slip is fair)


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


@dataclass
class SwapRun:
    """What one closed-loop run over CAN recorded."""

    # The pivot's joint states as plain floats: stamp (s) and velocity (rad/s). array('d') is
    # invisible to the garbage collector, so recording 2900 states adds nothing to the full
    # collections that would stall this process's CAN cycle (JointState objects did: 20-30 ms
    # a collection).
    stamp_s: array[float]
    velocity_rad_s: array[float]
    transitions: list[tuple[float, str, float]]  # (stamp s, pivot drive state, position rad)
    ramp: RampProfile
    latched_reason: str
    longest_freeze_ms: int  # the longest this process stood still while tracking
    commands_late_share: float = 0.0  # cycles that resent the previous command (the master's)


def _run_swap(tmp_path: Path, modes: tuple[str, ...] = (), until_s: float = 11.5) -> SwapRun:
    """The bridge (with its virtual rack), the shipped controller and a probe, on the ramp.

    `modes`: the bridge's per-joint CiA 402 modes (empty: all CST); `until_s`: controller time.
    """
    tmp_path.mkdir()
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
                Parameter("modes", value=list(modes), type_=Parameter.Type.STRING_ARRAY),
            ],
        )
        stamp_s, position_rad, velocity_rad_s = array("d"), array("d"), array("d")
        transitions: list[tuple[float, str, float]] = []
        last_state = {"name": ""}

        def on_joint(msg: JointState) -> None:
            stamp_s.append(from_stamp(msg.header.stamp))
            position_rad.append(msg.position[1])
            velocity_rad_s.append(msg.velocity[1])

        def on_drive(msg: DiagnosticArray) -> None:
            for status in msg.status:
                pivot = status.name == ri.DRIVE_STATUS_PREFIX + "pivot"
                if pivot and status.message != last_state["name"]:
                    t = from_stamp(msg.header.stamp)
                    position = position_rad[-1] if position_rad else math.nan
                    transitions.append((t, status.message, position))
                    last_state["name"] = status.message

        probe.create_subscription(JointState, ri.JOINT_STATES, on_joint, 100)
        probe.create_subscription(DiagnosticArray, ri.DRIVE_CHAIN_STATES, on_drive, 100)
        for node in (bridge, ctl, probe):
            executor.add_node(node)
        deadline = time.monotonic() + 60.0
        watch = FreezeWatch()
        try:
            while ctl.core.elapsed_s < until_s:
                assert time.monotonic() < deadline, f"only {ctl.core.elapsed_s:.2f} s of the ramp"
                executor.spin_once(timeout_sec=0.05)
                if not watch.is_alive() and ctl.core.elapsed_s >= TRACKING_FROM_S:
                    watch.start()  # only freezes while tracking count
        finally:
            watch.stop()
        ramp = ctl.core.params.profile
        freeze_ms = round(watch.longest_s * 1e3)
        assert isinstance(ramp, RampProfile)
        counters = bridge.bridge.counters
        return SwapRun(
            stamp_s,
            velocity_rad_s,
            transitions,
            ramp,
            bridge.bridge.latched_reason(),
            freeze_ms,
            late_share(counters.commands_late, counters.commands_in_time),
        )
    finally:
        started: tuple[Node | None, ...] = (probe, ctl, bridge)
        for leftover in started:
            if leftover is not None:
                leftover.destroy_node()
        executor.shutdown()
        rclpy.shutdown(context=ctx)


def test_controller_unchanged_over_can_tracks_the_ramp_and_switches_near_55_deg(
    tmp_path: Path,
) -> None:
    """The swap tracks the ramp and switches near 55 deg.

    Runs on the wall clock: if the rack saw this process stand still for more than ten control
    periods during the ramp (a stalled host, or a garbage collection holding the GIL; a fresh
    CI machine once stood 242 ms, and a 90 ms stall was seen to brake the axis to a reversal),
    the run says nothing about tracking. It runs once more then; a second long freeze is
    judged as it is.
    """
    run = _run_swap(tmp_path / "first")
    if run.longest_freeze_ms > LONG_FREEZE_MS:
        warnings.warn(
            f"the process stood still for {run.longest_freeze_ms} ms during the swap; once more",
            stacklevel=1,
        )
        run = _run_swap(tmp_path / "second")
    transitions = run.transitions
    assert run.latched_reason == ""
    skip_if_host_too_slow(run.commands_late_share, "CST over CAN")
    t0 = run.stamp_s[0]
    tracking_from_s = t0 + TRACKING_FROM_S  # the window the tracking error is judged over
    names = [name for _, name, _ in transitions]
    assert "motor_driving" in names, transitions
    # The load starts driving where the centre of gravity passes over the axis. Before it,
    # while the ramp is tracked, only motor driving and (during a brief brake of the velocity
    # loop) coasting can occur: both are states where the load resists. A cold-start run
    # showed such a brake at 41 deg. In the ramp's first instants the reference is a few
    # hundredths of a deg/s, and over CAN's wall-clock timing the axis may stick and slip
    # there (stop_motor_direct, even a short slip back with the load), as a worm gear does.
    load_drives = ("motor_and_load_driving", "load_driving")
    switch = next(t for t in transitions if t[0] > tracking_from_s and t[1].startswith(load_drives))
    in_force = [t[1] for t in transitions if t[0] <= tracking_from_s][-1:]
    during = [t[1] for t in transitions if tracking_from_s < t[0] < switch[0]]
    assert set(in_force + during) <= {"motor_driving", "coasting"}, transitions
    assert math.degrees(switch[2]) == pytest.approx(55.0, abs=1.0)
    ramp = run.ramp
    errors = [
        abs(v - ramp.velocity(t - t0))
        for t, v in zip(run.stamp_s, run.velocity_rad_s, strict=True)
        if tracking_from_s < t < t0 + 10.9
    ]
    assert len(errors) > 1500  # 250 Hz over 8.9 s: 2225, less any incomplete cycles
    assert math.degrees(max(errors)) < 0.5  # deg/s (0.3 over the lockstep simulator)


def test_the_same_controller_drives_a_csv_axis_through_its_velocity_commands(
    tmp_path: Path,
) -> None:
    """The pivot in CSV: the drive closes the velocity loop on the controller's setpoints.

    Nothing changes on the controller: the bridge subscribes to velocity_commands for its CSV
    axis (the controller publishes them while someone listens) and sends them as 0x60FF; the
    drive's velocity PI (the paper's gains, at the 250 Hz bus cycle) tracks the ramp as the
    controller's own loop does over CST.
    """
    run = _run_swap(tmp_path / "first", modes=("cst", "csv", "cst", "cst"), until_s=4.5)
    if run.longest_freeze_ms > LONG_FREEZE_MS:
        warnings.warn(f"stood still {run.longest_freeze_ms} ms; once more", stacklevel=1)
        run = _run_swap(tmp_path / "second", modes=("cst", "csv", "cst", "cst"), until_s=4.5)
    assert run.latched_reason == ""
    t0 = run.stamp_s[0]
    errors = [
        abs(v - run.ramp.velocity(t - t0))
        for t, v in zip(run.stamp_s, run.velocity_rad_s, strict=True)
        if t0 + TRACKING_FROM_S < t < t0 + 4.4
    ]
    assert len(errors) > 400  # 250 Hz over 2.4 s: 600, less any incomplete cycles
    assert math.degrees(max(errors)) < 0.5  # deg/s, as over CST
    assert run.ramp.velocity(4.4) > math.radians(1.5)  # the ramp did rise (deg/s)
