"""Faults of the simulated plant itself that /diagnostics must not report as OK.

A reversible robot back-driven into its end stop, a realtime simulator that stalled, a second
publisher of the plant's states on the domain. Nodes in-process, each test on its own rclpy
Context and domain id; every wait polls with a deadline (support.spin_until).
"""

from __future__ import annotations

import math
import time
import types
from typing import Any

import pytest
import support
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from support import spin_until

from lca_sim.ros import simulator_node
from lca_sim.ros.simulator_node import SimulatorNode

SIMULATOR = "lca_hil/simulator"
PIVOT = "lca_hil/simulator/pivot"

ros_context = support.domain_contexts(200, 20)


def _simulator(
    ctx: Context, executor: SingleThreadedExecutor, name: str = "simulator", **overrides: Any
) -> SimulatorNode:
    values: dict[str, Any] = {
        "timing_mode": "realtime",
        "command_timeout_s": 60.0,  # no controller in these tests: no command-loss WARN
        "diagnostics_period_s": 0.2,
    }
    values.update(overrides)
    sim = SimulatorNode(
        name,
        context=ctx,
        parameter_overrides=[Parameter(k, value=v) for k, v in values.items()],
    )
    executor.add_node(sim)
    return sim


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

    def shows(self, name: str, level: bytes, text: str) -> bool:
        """Whether the latest status of `name` has this level and its message contains `text`."""
        item = self.latest.get(name)
        return item is not None and item.level == level and text in item.message

    def value(self, name: str, key: str) -> str:
        """A value of the latest status of `name`."""
        values: dict[str, str] = {kv.key: kv.value for kv in self.latest[name].values}
        return values[key]


def test_a_reversible_robot_without_command_reports_back_driving_and_its_end_stop_hit() -> None:
    """Reversible gear, no command: WARN back-driving, then 'end stop hit at X rad/s'."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        # The pivot under gravity, 0.01 rad inside its end stop (2 rad): it runs into it at
        # about 0.01 rad/s with 0 V (the reversible baseline of docs/model.md).
        _simulator(
            ctx,
            executor,
            robot="reversible",
            command_timeout_s=0.2,
            initial_position=[0.0, 1.99, 0.0, 0.0],
        )
        spin_until(
            executor,
            lambda: diagnostics.shows(
                PIVOT, DiagnosticStatus.WARN, "back-driving: pivot moving at"
            ),
            "the back-driven pivot is reported",
            30.0,
        )
        assert diagnostics.latest[PIVOT].message.endswith("rad/s with no command")
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.WARN, "no command for"),
            "the command silence is reported",
            30.0,
        )
        assert "holding" not in diagnostics.latest[SIMULATOR].message  # the load is not held
        spin_until(
            executor,
            lambda: diagnostics.shows(PIVOT, DiagnosticStatus.WARN, "end stop hit at"),
            "the end-stop contact is reported with its speed",
            60.0,
        )
        assert float(diagnostics.value(PIVOT, "end_stop_contact_speed")) > 0.0


def test_a_stalled_realtime_simulator_reports_the_time_it_skipped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 0.5 s stall of the node's clock: WARN 'stalled', windowed factor < 1, lag reported."""
    stall = {"s": 0.0}
    clock = types.SimpleNamespace(monotonic=lambda: time.monotonic() + stall["s"], time=time.time)
    monkeypatch.setattr(simulator_node, "time", clock)
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        # The default (irreversible) robot under load, no command: held, no back-driving.
        _simulator(ctx, executor, initial_position=[0.0, math.radians(35.0), 0.0, 0.0])
        spin_until(
            executor,
            lambda: (
                diagnostics.shows(SIMULATOR, DiagnosticStatus.OK, "running")
                and PIVOT in diagnostics.latest
            ),
            "the simulator runs",
            30.0,
        )
        assert diagnostics.latest[PIVOT].level == DiagnosticStatus.OK
        stall["s"] = 0.5  # wall time went on half a second without a tick
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(
                SIMULATOR,
                DiagnosticStatus.WARN,
                "stalled: simulated time fell",
            ),
            "the stall is reported",
            30.0,
        )
        assert diagnostics.latest[SIMULATOR].message.endswith("behind the wall clock (skipped)")
        assert float(diagnostics.value(SIMULATOR, "realtime_factor")) < 0.8
        assert float(diagnostics.value(SIMULATOR, "skipped_s")) > 0.4
        assert float(diagnostics.value(SIMULATOR, "stamp_lag_s")) > 0.4
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.OK, "running"),
            "OK again in the periods after the stall",
            30.0,
        )
        assert float(diagnostics.value(SIMULATOR, "stamp_lag_s")) > 0.4  # the lag stays


def test_a_second_publisher_of_the_plant_states_is_an_error() -> None:
    """Two simulators on one domain: ERROR naming the other; the other gone: no ERROR."""
    with ros_context() as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        _simulator(ctx, executor)
        other = _simulator(ctx, executor, "simulator_b")
        spin_until(
            executor,
            lambda: diagnostics.shows(
                SIMULATOR,
                DiagnosticStatus.ERROR,
                "another node publishes joint_states: /simulator_b",
            ),
            "the first simulator reports the second publisher",
            30.0,
        )
        executor.remove_node(other)
        other.destroy_node()
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR, DiagnosticStatus.OK, "running"),
            "no ERROR once the second simulator is gone",
            30.0,
        )
