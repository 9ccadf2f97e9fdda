"""The fault matrix of issue 14 ("No silent faults"): one case per numbered item, 1 to 12.

Each case starts the real nodes (in-process, on an rclpy Context of their own) or the installed
console tool, on its own ROS 2 domain (`FIRST_DOMAIN_ID + item - 1`, 220 to 231: no other module
uses them), causes the item's fault, and asserts the diagnostic level and message, or the tool's
output, within a deadline, and that no data was lost where the item says so. Every wait polls
with a deadline (support.wait_until / spin_until); nothing sleeps a fixed time. docs/reliability.md
points here from each row of its tables.
"""

from __future__ import annotations

import math
import time
import types
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import pytest
import support
import yaml
from diagnostic_msgs.msg import DiagnosticStatus
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from support import (
    CONTROLLER_STATUS,
    LOCKSTEP_SIMULATOR,
    SIMULATOR_STATUS,
    Diagnostics,
    kill,
    spin_until,
    start_simulator,
    strict_loads,
)

from lca_control.ros.controller_node import ControllerNode
from lca_sim.ros import simulator_node

FIRST_DOMAIN_ID = 220  # item N runs on FIRST_DOMAIN_ID + N - 1
PIVOT_STATUS = f"{SIMULATOR_STATUS}/pivot"
PIVOT = 1  # the pivot's index in the joint arrays
# A realtime simulator without a controller (no command-loss WARN), quick to report.
REALTIME_SIMULATOR: dict[str, Any] = {
    "timing_mode": "realtime",
    "command_timeout_s": 60.0,
    "diagnostics_period_s": 0.2,
}
LOADED_PIVOT = [0.0, math.radians(35.0), 0.0, 0.0]  # the pivot under gravity load
MOTOR_DOMINANT = "motor_and_load_driving_motor_dominant"


def _domain_id(item: int) -> int:
    return FIRST_DOMAIN_ID + item - 1


def ros_context(item: int) -> AbstractContextManager[tuple[Context, SingleThreadedExecutor]]:
    """A fresh rclpy Context and executor on item `item`'s own domain."""
    return support.ros_context_on(_domain_id(item))


def _controller(ctx: Context, executor: SingleThreadedExecutor, **overrides: Any) -> ControllerNode:
    """The controller on a ramp of the pivot, current commands, quick to miss its plant."""
    values: dict[str, Any] = {
        "reference_source": "ramp",
        "command_interface": "current",
        "use_sim_time": True,  # its clock stops with the simulator's /clock
        "plant_timeout_s": 0.3,
        **overrides,
    }
    ctl = ControllerNode(context=ctx, parameter_overrides=support.parameters(**values))
    executor.add_node(ctl)
    return ctl


def _set_parameter(
    executor: SingleThreadedExecutor, client_node: Node, target: str, name: str, value: Any
) -> SetParametersResult:
    """One live set through the node's set_parameters service, as `ros2 param set` does it."""
    client = client_node.create_client(SetParameters, f"/{target}/set_parameters")
    spin_until(executor, client.service_is_ready, f"/{target}/set_parameters is served", 30.0)
    # rclpy leaves Parameter and Future.result unannotated
    change = Parameter(name, value=value).to_parameter_msg()  # type: ignore[no-untyped-call]
    future = client.call_async(SetParameters.Request(parameters=[change]))
    spin_until(executor, future.done, f"the answer to {name} := {value!r}", 30.0)
    response = future.result()  # type: ignore[no-untyped-call]
    assert response is not None
    result: SetParametersResult = response.results[0]
    return result


def _scenario_result(doc: dict[str, Any], out: Path) -> Path:
    """`lca-sim run` of a scenario document; the result.csv it wrote."""
    out.mkdir(parents=True, exist_ok=True)
    scenario = out / "scenario.yaml"
    scenario.write_text(yaml.safe_dump(doc), encoding="utf-8")
    run = support.run_tool(
        "lca-sim", "run", "--scenario", str(scenario), "--out", str(out), "--no-plot"
    )
    assert run.returncode == 0, run.stdout + run.stderr
    return out / "result.csv"


def _identify(csv_path: Path, axis: str) -> tuple[str, dict[str, Any]]:
    """`lca-hil identify` of one axis: its report and its identification.json, parsed strictly."""
    run = support.run_tool(
        "lca-hil", "identify", str(csv_path), "--axis", axis, "--out", str(csv_path.parent)
    )
    assert run.returncode == 0, run.stdout + run.stderr
    doc = strict_loads((csv_path.parent / "identification.json").read_text(encoding="utf-8"))
    assert isinstance(doc, dict)
    return run.stdout, doc


def _estimate(doc: dict[str, Any], state: str, direction: str) -> dict[str, Any]:
    entry: dict[str, Any] = next(
        e for e in doc["estimates"] if (e["state"], e["direction"]) == (state, direction)
    )
    return entry


# --- 2 ----------------------------------------------------------------------------------------


def test_item_02_a_reversible_robot_without_command_reports_back_driving_and_end_stop() -> None:
    """Item 2: "reversible robot, left without command, back-drove and fell into its end stop"."""
    with ros_context(2) as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        # The pivot under gravity, 0.01 rad inside its end stop (2 rad): it runs into it at
        # about 0.01 rad/s with 0 V (the reversible baseline of docs/model.md).
        start_simulator(
            ctx,
            executor,
            REALTIME_SIMULATOR,
            robot="reversible",
            command_timeout_s=0.2,
            initial_position=[0.0, 1.99, 0.0, 0.0],
        )
        spin_until(
            executor,
            lambda: diagnostics.shows(
                PIVOT_STATUS, DiagnosticStatus.WARN, "back-driving: pivot moving at"
            ),
            "the back-driven pivot is reported",
            30.0,
        )
        assert diagnostics.latest[PIVOT_STATUS].message.endswith("rad/s with no command")
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR_STATUS, DiagnosticStatus.WARN, "no command for"),
            "the command silence is reported",
            30.0,
        )
        assert "holding" not in diagnostics.latest[SIMULATOR_STATUS].message  # not held
        spin_until(
            executor,
            lambda: diagnostics.shows(PIVOT_STATUS, DiagnosticStatus.WARN, "end stop hit at"),
            "the end-stop contact is reported with its speed",
            60.0,
        )
        assert float(diagnostics.value(PIVOT_STATUS, "end_stop_contact_speed")) > 0.0


# --- 3 ----------------------------------------------------------------------------------------


def test_item_03_a_restarted_simulator_is_picked_up_and_counted() -> None:
    """Item 3: "A simulator restarted during a lockstep run: its stamps started again at 0"."""
    with ros_context(3) as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        sim = start_simulator(ctx, executor, LOCKSTEP_SIMULATOR)
        ctl = _controller(ctx, executor)
        spin_until(executor, lambda: sim.sim_time_s >= 0.4, "the lockstep loop runs", 60.0)
        kill(executor, sim)
        restarted = start_simulator(ctx, executor, LOCKSTEP_SIMULATOR)
        spin_until(
            executor,
            lambda: restarted.sim_time_s >= 0.2,
            "the loop runs again after the simulator restarted",
            30.0,
        )
        assert ctl.core.plant_restarts == 1
        spin_until(
            executor,
            lambda: (
                CONTROLLER_STATUS in diagnostics.latest
                and diagnostics.value(CONTROLLER_STATUS, "plant_restarts") == "1"
            ),
            "the controller's /diagnostics counts the restart",
            30.0,
        )
        assert diagnostics.latest[CONTROLLER_STATUS].level == DiagnosticStatus.OK


# --- 4 ----------------------------------------------------------------------------------------


def test_item_04_a_stalled_realtime_simulator_reports_the_time_it_skipped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Item 4: "its stamps lagged wall time for good while `realtime_factor` still read about 1"."""
    stall = {"s": 0.0}
    clock = types.SimpleNamespace(monotonic=lambda: time.monotonic() + stall["s"], time=time.time)
    monkeypatch.setattr(simulator_node, "time", clock)
    with ros_context(4) as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        # The default (irreversible) robot under load, no command: held, no back-driving.
        start_simulator(ctx, executor, REALTIME_SIMULATOR, initial_position=LOADED_PIVOT)
        spin_until(
            executor,
            lambda: (
                diagnostics.shows(SIMULATOR_STATUS, DiagnosticStatus.OK, "running")
                and PIVOT_STATUS in diagnostics.latest
            ),
            "the simulator runs",
            30.0,
        )
        assert diagnostics.latest[PIVOT_STATUS].level == DiagnosticStatus.OK
        stall["s"] = 0.5  # wall time went on half a second without a tick
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(
                SIMULATOR_STATUS, DiagnosticStatus.WARN, "stalled: simulated time fell"
            ),
            "the stall is reported",
            30.0,
        )
        message = diagnostics.latest[SIMULATOR_STATUS].message
        assert message.endswith("behind the wall clock (skipped)")
        assert float(diagnostics.value(SIMULATOR_STATUS, "realtime_factor")) < 0.8
        assert float(diagnostics.value(SIMULATOR_STATUS, "skipped_s")) > 0.4
        assert float(diagnostics.value(SIMULATOR_STATUS, "stamp_lag_s")) > 0.4
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR_STATUS, DiagnosticStatus.OK, "running"),
            "OK again in the periods after the stall",
            30.0,
        )
        assert float(diagnostics.value(SIMULATOR_STATUS, "stamp_lag_s")) > 0.4  # the lag stays


# --- 5 ----------------------------------------------------------------------------------------


def test_item_05_a_lost_peer_is_reported_by_the_node_left_behind() -> None:
    """Item 5: "A controller whose simulator went away kept reporting OK; so did a simulator"."""
    with ros_context(5) as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        sim = start_simulator(ctx, executor, LOCKSTEP_SIMULATOR)
        ctl = _controller(ctx, executor)
        spin_until(executor, lambda: sim.sim_time_s >= 0.2, "the lockstep loop runs", 60.0)
        spin_until(
            executor,
            lambda: (
                diagnostics.shows(CONTROLLER_STATUS, DiagnosticStatus.OK, "running")
                and diagnostics.shows(SIMULATOR_STATUS, DiagnosticStatus.OK, "running")
            ),
            "both report OK while the loop runs",
        )
        # The simulator goes away: the controller says so, and OK again once states return.
        kill(executor, sim)
        spin_until(
            executor,
            lambda: diagnostics.shows(
                CONTROLLER_STATUS, DiagnosticStatus.WARN, "no plant state for"
            ),
            "the controller reports the lost simulator",
            15.0,
        )
        assert diagnostics.value(CONTROLLER_STATUS, "plant_losses") == "1"
        sim = start_simulator(ctx, executor, LOCKSTEP_SIMULATOR)
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(CONTROLLER_STATUS, DiagnosticStatus.OK, "plant states again"),
            "the controller reports OK once states return",
            30.0,
        )
        # The controller goes away: the simulator says so; a new controller picks up the loop.
        kill(executor, ctl)
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR_STATUS, DiagnosticStatus.WARN, "no command for"),
            "the simulator reports the lost controller",
            15.0,
        )
        message = diagnostics.latest[SIMULATOR_STATUS].message
        assert message.endswith("simulated time paused, the last state is re-sent"), message
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
            lambda: diagnostics.shows(SIMULATOR_STATUS, DiagnosticStatus.OK, "commands again"),
            "the simulator reports OK once commands return",
            15.0,
        )


# --- 6 ----------------------------------------------------------------------------------------


def test_item_06_a_second_publisher_of_the_plant_states_is_an_error() -> None:
    """Item 6: "Two simulators started on one ROS domain both published `joint_states`"."""
    with ros_context(6) as (ctx, executor):
        diagnostics = Diagnostics(ctx, executor)
        start_simulator(ctx, executor, REALTIME_SIMULATOR)
        other = start_simulator(ctx, executor, REALTIME_SIMULATOR, "simulator_b")
        spin_until(
            executor,
            lambda: diagnostics.shows(
                SIMULATOR_STATUS,
                DiagnosticStatus.ERROR,
                "another node publishes joint_states: /simulator_b",
            ),
            "the first simulator reports the second publisher",
            30.0,
        )
        kill(executor, other)
        diagnostics.clear()
        spin_until(
            executor,
            lambda: diagnostics.shows(SIMULATOR_STATUS, DiagnosticStatus.OK, "running"),
            "no ERROR once the second simulator is gone",
            30.0,
        )
