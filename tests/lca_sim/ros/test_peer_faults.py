"""A plant waiting for its controller, or without one: /diagnostics says so.

Simulator nodes in-process, each test on its own rclpy Context and domain id. Every wait polls
with a deadline (support.spin_until); nothing sleeps a fixed time. A peer that goes away or
restarts is in the fault matrix (tests/test_fault_matrix.py, items 3 and 5).
"""

from __future__ import annotations

import support
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray
from support import LOCKSTEP_SIMULATOR, Diagnostics, start_simulator

from lca_control.contract import SIMULATOR_STATUS

ros_context = support.domain_contexts(180, 20)


def test_a_lockstep_simulator_waiting_for_subscribers_says_so() -> None:
    """Lockstep start without enough subscribers: OK (no fault yet), naming what it waits for."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        start_simulator(ctx, executor, LOCKSTEP_SIMULATOR, lockstep_subscribers=3)
        # the simulator reports its wait for subscribers
        diagnostics.wait_for(SIMULATOR_STATUS, DiagnosticStatus.OK, "waiting for 3", 15.0)
        assert diagnostics.latest[SIMULATOR_STATUS].message.startswith("waiting for 3")


def test_a_realtime_simulator_reports_command_silence_and_recovery() -> None:
    """Realtime: OK waiting before the first command; silence after commands is WARN."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        start_simulator(
            ctx, executor, LOCKSTEP_SIMULATOR, timing_mode="realtime", command_timeout_s=0.2
        )
        # before any command the simulator waits for its controller: no fault
        diagnostics.wait_for(
            SIMULATOR_STATUS, DiagnosticStatus.OK, "waiting for the first command", 15.0
        )
        assert diagnostics.latest[SIMULATOR_STATUS].message.endswith("holding (0 V)")
        assert diagnostics.value(SIMULATOR_STATUS, "command_losses") == "0"
        driver = Node("driver", context=ctx)
        pub = driver.create_publisher(Float64MultiArray, "current_commands", 10)
        sending = driver.create_timer(0.02, lambda: pub.publish(Float64MultiArray(data=[0.0] * 4)))
        executor.add_node(driver)
        diagnostics.clear()
        # the simulator runs on the commands
        diagnostics.wait_for(SIMULATOR_STATUS, DiagnosticStatus.OK, "running", 15.0)
        driver.destroy_timer(sending)
        # the simulator reports the command silence once commands that came stop
        diagnostics.wait_for(SIMULATOR_STATUS, DiagnosticStatus.WARN, "no command for", 15.0)
        message = diagnostics.latest[SIMULATOR_STATUS].message
        assert message.startswith("no command for") and message.endswith("holding (0 V)")
        assert diagnostics.value(SIMULATOR_STATUS, "command_losses") == "1"
        driver.create_timer(0.02, lambda: pub.publish(Float64MultiArray(data=[0.0] * 4)))
        diagnostics.clear()
        # the simulator reports OK once commands return
        diagnostics.wait_for(SIMULATOR_STATUS, DiagnosticStatus.OK, "commands again", 15.0)
