"""A peer that goes away or restarts: the loop picks up again and /diagnostics says so.

Simulator and controller nodes in-process, each test on its own rclpy Context and domain id;
a node is "killed" by destroying it and "restarted" by building a new one on the same context.
Every wait polls with a deadline (support.spin_until); nothing sleeps a fixed time.
"""

from __future__ import annotations

import math
from typing import Any

import support
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from support import spin_until

from lca_control.ros.controller_node import ControllerNode
from lca_sim.ros.simulator_node import SimulatorNode

SIMULATOR = "lca_hil/simulator"
CONTROLLER = "lca_hil/controller"


ros_context = support.domain_contexts(180, 20)


def _params(**values: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def _simulator(ctx: Context, executor: SingleThreadedExecutor, **overrides: Any) -> SimulatorNode:
    values: dict[str, Any] = {
        "timing_mode": "lockstep",
        "command_interface": "current",
        "initial_position": [0.0, math.radians(35.0), 0.0, 0.0],
        "lockstep_subscribers": 1,  # the controller
        "lockstep_resend_s": 0.3,
        "diagnostics_period_s": 0.2,
    }
    values.update(overrides)
    sim = SimulatorNode(context=ctx, parameter_overrides=_params(**values))
    executor.add_node(sim)
    return sim


def _controller(ctx: Context, executor: SingleThreadedExecutor) -> ControllerNode:
    ctl = ControllerNode(
        context=ctx,
        parameter_overrides=_params(
            reference_source="ramp",
            command_interface="current",
            use_sim_time=True,  # its clock stops with the simulator's /clock
            plant_timeout_s=0.3,
        ),
    )
    executor.add_node(ctl)
    return ctl


def _kill(executor: SingleThreadedExecutor, node: Node) -> None:
    executor.remove_node(node)
    node.destroy_node()


class Diagnostics:
    """The latest /diagnostics status of each name, seen from a node of the test."""

    def __init__(self, ctx: Context, executor: SingleThreadedExecutor) -> None:
        self.node = Node("test_diagnostics", context=ctx)
        self.latest: dict[str, DiagnosticStatus] = {}
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_array, 50)
        executor.add_node(self.node)

    def _on_array(self, msg: DiagnosticArray) -> None:
        for item in msg.status:
            self.latest[item.name] = item

    def clear(self) -> None:
        """Forget what was seen, so a wait sees only reports from now on."""
        self.latest.clear()

    def shows(self, name: str, level: bytes, message_start: str) -> bool:
        """Whether the latest status of `name` has this level and its message starts so."""
        item = self.latest.get(name)
        return item is not None and item.level == level and item.message.startswith(message_start)


def test_a_restarted_simulator_is_picked_up_and_counted() -> None:
    """Simulator restarted mid-run (its time from 0 again): the loop runs again, one restart."""
    with ros_context() as (ctx, executor):
        sim = _simulator(ctx, executor)
        ctl = _controller(ctx, executor)
        spin_until(executor, lambda: sim.sim_time_s >= 0.4, "the lockstep loop runs", 60.0)
        _kill(executor, sim)
        restarted = _simulator(ctx, executor)
        spin_until(
            executor,
            lambda: restarted.sim_time_s >= 0.2,
            "the loop runs again after the simulator restarted",
            30.0,
        )
        assert ctl.core.plant_restarts == 1


def test_a_lost_controller_is_reported_by_the_simulator_and_a_new_one_picks_up() -> None:
    """Controller gone: WARN 'no command for ...'; a new controller: the loop runs, OK again."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        sim = _simulator(ctx, executor)
        ctl = _controller(ctx, executor)
        spin_until(executor, lambda: sim.sim_time_s >= 0.2, "the lockstep loop runs", 60.0)
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.OK, "running"),
            "the simulator reports OK while the controller runs",
        )
        _kill(executor, ctl)
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.WARN, "no command for"),
            "the simulator reports the lost controller",
            15.0,
        )
        stopped_s = sim.sim_time_s
        ctl = _controller(ctx, executor)
        spin_until(
            executor,
            lambda: sim.sim_time_s >= stopped_s + 0.2,
            "a new controller picks up the re-sent state",
            30.0,
        )
        assert ctl.core.plant_restarts == 0  # a new controller's first state is no restart
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.OK, "commands again"),
            "the simulator reports OK once commands return",
            15.0,
        )


def test_a_lost_simulator_is_reported_by_the_controller() -> None:
    """Simulator gone: the controller reports WARN 'no plant state ...', OK again after."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        sim = _simulator(ctx, executor)
        _controller(ctx, executor)
        spin_until(executor, lambda: sim.sim_time_s >= 0.2, "the lockstep loop runs", 60.0)
        spin_until(
            executor,
            lambda: diagnostics.shows(CONTROLLER, DiagnosticStatus.OK, "running"),
            "the controller reports OK while states come",
        )
        _kill(executor, sim)
        spin_until(
            executor,
            lambda: diagnostics.shows(CONTROLLER, DiagnosticStatus.WARN, "no plant state for"),
            "the controller reports the lost simulator",
            15.0,
        )
        sim = _simulator(ctx, executor)
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(CONTROLLER, DiagnosticStatus.OK, "plant states again"),
            "the controller reports OK once states return",
            30.0,
        )


def test_a_lockstep_simulator_waiting_for_subscribers_says_so() -> None:
    """Lockstep start without enough subscribers: WARN naming what it waits for."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        _simulator(ctx, executor, lockstep_subscribers=3)
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.WARN, "waiting for 3"),
            "the simulator reports its wait for subscribers",
            15.0,
        )


def test_a_realtime_simulator_reports_command_silence_and_recovery() -> None:
    """Realtime: no command beyond command_timeout_s is WARN 'holding (0 V)'; commands: OK."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        _simulator(ctx, executor, timing_mode="realtime", command_timeout_s=0.2)
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.WARN, "no command for"),
            "the simulator reports command silence",
            15.0,
        )
        assert diagnostics.latest[SIMULATOR].message.endswith("holding (0 V)")
        driver = Node("driver", context=ctx)
        pub = driver.create_publisher(Float64MultiArray, "current_commands", 10)
        driver.create_timer(0.02, lambda: pub.publish(Float64MultiArray(data=[0.0] * 4)))
        executor.add_node(driver)
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.OK, "commands again"),
            "the simulator reports OK once commands return",
            15.0,
        )
