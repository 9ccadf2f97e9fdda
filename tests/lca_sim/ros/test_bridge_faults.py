"""The CAN bridge's own peer faults on /diagnostics: a silent controller, a second plant.

The bridge with its virtual rack in this process (interface virtual), the drives enabled. A
controller that stops commanding halts the drives (zero torque) after command_timeout_s and
quick-stops them after quick_stop_after_s more; both must show on the bridge's /diagnostics,
not only in its log, and the halt must clear by itself when commands return. A second node
publishing joint_states is a second plant on the domain: ERROR, as on the simulator.
"""

from __future__ import annotations

import math
from typing import Any

import can
import support
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from support import Diagnostics, spin_until

from lca_control import contract as pc
from lca_sim.cia402.device import PowerState
from lca_sim.ros.can_bridge_node import CanBridgeNode

BRIDGE = "lca_hil/can_bridge"
PIVOT = "lca_hil/can_bridge/pivot"
OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR

ros_context = support.domain_contexts(220, 10)


def _bridge(ctx: Context, executor: SingleThreadedExecutor, **overrides: Any) -> CanBridgeNode:
    values: dict[str, Any] = {
        "interface": "virtual",
        "channel": f"test_bridge_faults_{id(ctx)}",
        "auto_enable": True,
        "cycle_hz": 250.0,
        "diagnostics_period_s": 0.1,
        **support.ROOMY_WATCHDOGS,  # room for this process's GIL (rack, bridge, test)
    }
    values.update(overrides)
    bridge = CanBridgeNode(
        context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()]
    )
    executor.add_node(bridge)
    return bridge


def _enabled(bridge: CanBridgeNode) -> bool:
    return all(
        bridge.bridge.axis_state(j).power_state is PowerState.OPERATION_ENABLED
        for j in bridge.params.joints
    )


def test_a_silent_controller_halts_then_quick_stops_and_the_bridge_says_so() -> None:
    """OK waiting, WARN "halted" after command_timeout_s, OK on commands, ERROR at quick stop."""
    with ros_context() as (ctx, executor):
        # 50 Hz: this thread's executor answers each state well within a period, so the
        # late-command WARN (LateShare) stays away and the OK of "commands again" shows.
        bridge = _bridge(
            ctx, executor, command_timeout_s=0.2, quick_stop_after_s=1.0, cycle_hz=50.0
        )
        probe = Diagnostics(ctx, executor)
        commands = probe.node.create_publisher(Float64MultiArray, pc.CURRENT_COMMANDS, 10)
        answering = [False]

        def answer(_state: JointState) -> None:  # one command per state, as a controller
            if answering[0]:
                commands.publish(Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0]))

        probe.node.create_subscription(JointState, pc.JOINT_STATES, answer, 10)
        try:
            spin_until(executor, lambda: _enabled(bridge), "drives operation enabled", 30.0)
            # waiting for its controller is no fault: OK, saying what it waits for
            probe.wait_for(BRIDGE, OK, "enabled, waiting for the first command")
            assert probe.value(BRIDGE, "command_losses") == "0"

            def commanding(until: str, level: bytes) -> None:
                # Answering every state keeps the commands in time: a test that commands
                # slower than the cycle is, rightly, a late-command WARN (LateShare).
                answering[0] = True
                support.wait_until(
                    lambda: probe.shows(BRIDGE, level, until),
                    until,
                    30.0,
                    step=lambda: executor.spin_once(timeout_sec=0.01),
                )
                answering[0] = False

            commanding("running", OK)
            # The controller stops: halt after 0.2 s, and the bridge reports it.
            probe.wait_for(BRIDGE, WARN, "halted, zero torque")
            assert probe.value(BRIDGE, "command_losses") == "1"
            # Back before the quick stop: the halt clears by itself.
            commanding("commands again", OK)
            assert _enabled(bridge)
            # Silent past 0.2 + 1.0 s: the quick stop, which holds until ~/enable.
            status = probe.wait_for(BRIDGE, ERROR, "quick stop")
            assert "~/enable" in status.message
            assert probe.value(BRIDGE, "command_losses") == "2"
        finally:
            bridge.destroy_node()
            probe.node.destroy_node()


def test_a_second_publisher_of_joint_states_is_an_error_on_the_bridge() -> None:
    """Another node publishing joint_states beside the bridge: ERROR naming it, then clear."""
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, auto_enable=False)
        probe = Diagnostics(ctx, executor)
        other = Node("second_plant", context=ctx)
        try:
            probe.wait_for(BRIDGE, OK, "running")
            publisher = other.create_publisher(JointState, pc.JOINT_STATES, 10)
            probe.wait_for(BRIDGE, ERROR, "another node publishes joint_states: /second_plant")
            assert "/second_plant" in probe.value(BRIDGE, "other_publishers")
            other.destroy_publisher(publisher)
            probe.wait_for(BRIDGE, OK, "running")
        finally:
            bridge.destroy_node()
            other.destroy_node()
            probe.node.destroy_node()


def test_every_emcy_shows_on_the_drive_status_decoded_to_text() -> None:
    """An advisory EMCY is a WARN with its text and count; a drive fault's is an ERROR."""
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, auto_enable=False)
        probe = Diagnostics(ctx, executor)
        injector = can.Bus(interface="virtual", channel=bridge.params.channel)
        try:
            probe.wait_for(PIVOT, OK, "")

            def emcy(code: int) -> None:
                data = [code & 0xFF, code >> 8, 0x10, 0, 0, 0, 0, 0]
                injector.send(can.Message(arbitration_id=0x82, data=data, is_extended_id=False))

            emcy(0x8220)
            status = probe.wait_for(PIVOT, WARN, "EMCY 0x8220 PDO length exceeded")
            assert "(1 received)" in status.message
            emcy(0x2310)
            probe.wait_for(PIVOT, ERROR, "EMCY 0x2310 continuous over-current")
        finally:
            injector.shutdown()
            bridge.destroy_node()
            probe.node.destroy_node()


def test_a_lost_tpdo_of_a_disabled_drive_warns_on_the_bridge() -> None:
    """Pivot TPDO1 lost (0x2030 sub 1), drives disabled: WARN naming it, OK when it returns.

    Without complete cycles no joint_states go out, so the stall must show on /diagnostics.
    """
    from lca_sim.cia402 import objects as od

    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, auto_enable=False)
        probe = Diagnostics(ctx, executor)
        try:
            spin_until(
                executor, lambda: bridge.bridge.counters.complete_cycles > 10, "cycles", 30.0
            )
            probe.wait_for(BRIDGE, OK, "")
            bridge.bridge.sdo_write("pivot", od.FAULT_INJECTION, od.FAULT_LOST_TPDOS, 0x01)
            probe.wait_for(BRIDGE, WARN, "pivot TPDO1 missing")
            bridge.bridge.sdo_write("pivot", od.FAULT_INJECTION, od.FAULT_LOST_TPDOS, 0)
            probe.wait_for(BRIDGE, OK, "")
        finally:
            bridge.destroy_node()
            probe.node.destroy_node()


def test_commands_late_for_their_cycle_warn_on_the_bridge() -> None:
    """A controller answering at 25 Hz a 250 Hz cycle: most cycles resend an old command.

    The loop then has two periods of delay or more, which a loop tuned for one does not
    stand; the bridge counts it (commands_late) and WARNs with the share.
    """
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, command_timeout_s=0.5)
        probe = Diagnostics(ctx, executor)
        commands = probe.node.create_publisher(Float64MultiArray, pc.CURRENT_COMMANDS, 10)
        probe.node.create_timer(
            0.04, lambda: commands.publish(Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0]))
        )
        try:
            spin_until(executor, lambda: _enabled(bridge), "drives operation enabled", 30.0)
            status = probe.wait_for(BRIDGE, WARN, "cycles sent the previous command")
            values = {kv.key: kv.value for kv in status.values}
            late, in_time = int(values["commands_late"]), int(values["commands_in_time"])
            assert late > 0.5 * (late + in_time)
        finally:
            bridge.destroy_node()
            probe.node.destroy_node()


def test_csp_axes_without_position_commands_warn_on_the_bridge() -> None:
    """A pivot in csp and only current_commands coming: the bridge WARNs naming it.

    Without the WARN the pivot would hold where it is without a word; it ends once
    position_commands come.
    """
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, modes=["cst", "csp", "cst", "cst"])
        probe = Diagnostics(ctx, executor)
        currents = probe.node.create_publisher(Float64MultiArray, pc.CURRENT_COMMANDS, 10)
        positions = probe.node.create_publisher(Float64MultiArray, pc.POSITION_COMMANDS, 10)
        probe.node.create_timer(
            0.01, lambda: currents.publish(Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0]))
        )
        try:
            spin_until(executor, lambda: _enabled(bridge), "drives operation enabled", 30.0)
            status = probe.wait_for(BRIDGE, WARN, "['pivot'] get no position_commands")
            assert "command_interface" in status.message
            probe.node.create_timer(
                0.01,
                lambda: positions.publish(
                    Float64MultiArray(data=[math.nan, math.nan, math.nan, math.nan])
                ),
            )
            probe.wait_for(BRIDGE, OK, "")
        finally:
            bridge.destroy_node()
            probe.node.destroy_node()
