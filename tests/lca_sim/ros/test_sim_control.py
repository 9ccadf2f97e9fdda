"""Simulation control: pause, resume, step, reset, realtime factor; the public pytest fixture.

The realtime tests drive a simulator node directly; the lockstep ones use `lca_hil_loop` exactly
as a user's tests would, through `pytest_plugins`. Every wait has a deadline; none sleeps.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
import support
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from support import Diagnostics, spin_until, start_simulator, wait_until

from lca_control.contract import SIMULATOR_STATUS
from lca_sim.ros.simulator_node import SimulatorNode

if TYPE_CHECKING:  # imported by pytest as a plugin (below), so its asserts are rewritten
    from lca_sim.ros.testing import HilLoop

pytest_plugins = ["lca_sim.ros.testing"]

ros_context = support.domain_contexts(140, 6)
PERIOD_NS = 4_000_000  # control_period_s
REALTIME: dict[str, Any] = {
    "command_interface": "current",
    "command_timeout_s": 60.0,  # the test's one command stays in force
    "initial_position": [0.0, 0.0, 0.0, 0.0],
    "diagnostics_period_s": 0.2,
}


@pytest.fixture(scope="module")
def lca_hil_domain_id() -> int:
    """The fixture's loop on this module's own domain id (after the direct tests' 140-145)."""
    return 146


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class Services:
    """Trigger clients of the simulator's control services, called with a deadline."""

    def __init__(self, ctx: Context, executor: SingleThreadedExecutor) -> None:
        self.node = Node("test_sim_control_client", context=ctx)
        self.executor = executor
        executor.add_node(self.node)
        self.clients = {
            name: self.node.create_client(Trigger, f"/simulator/{name}")
            for name in ("pause", "resume", "step", "reset")
        }
        spin_until(executor, lambda: all(c.service_is_ready() for c in self.clients.values()))

    def call(self, name: str) -> Trigger.Response:
        """Call ~/`name` and spin until its reply."""
        future = self.clients[name].call_async(Trigger.Request())
        spin_until(self.executor, future.done, f"the reply of ~/{name}")
        return future.result()


def _spin_for_wall(executor: SingleThreadedExecutor, seconds: float) -> None:
    """Let `seconds` of wall time pass while the executor runs (a deadline, not a sleep)."""
    end = time.monotonic() + seconds
    wait_until(
        lambda: time.monotonic() >= end,
        "wall time",
        seconds + 30.0,
        step=lambda: executor.spin_once(timeout_sec=0.01),
    )


def _moving_realtime(ctx: Context, executor: SingleThreadedExecutor) -> SimulatorNode:
    sim = start_simulator(ctx, executor, REALTIME)
    sim.plant.command([0.0, 8.0, 0.0, 0.0])
    spin_until(executor, lambda: sim.sim.state_array[0, 1] > 0.001, "the pivot moving")
    return sim


def test_realtime_pause_holds_the_state_bit_for_bit() -> None:
    """Paused: state, stamps and publishing stop while wall time passes; no stall on resume."""
    with ros_context() as (ctx, executor):
        sim = _moving_realtime(ctx, executor)
        services = Services(ctx, executor)
        diagnostics = Diagnostics(ctx, executor)
        reply = services.call("pause")
        assert reply.success and "paused" in reply.message
        state = sim.sim.state_array.copy()
        signals = sim.sim.signal_array.copy()
        t_s, published = sim.sim_time_s, sim._published
        _spin_for_wall(executor, 0.6)
        np.testing.assert_array_equal(sim.sim.state_array, state)
        np.testing.assert_array_equal(sim.sim.signal_array, signals)
        assert (sim.sim_time_s, sim._published) == (t_s, published)
        diagnostics.clear()
        paused = diagnostics.wait_for(SIMULATOR_STATUS, DiagnosticStatus.OK, "paused")
        assert {kv.key: kv.value for kv in paused.values}["paused"] == "True"
        assert services.call("resume").success
        spin_until(executor, lambda: sim.sim_time_s > t_s + 0.2, "simulated time again")
        assert sim.pacing.overrun_steps * sim.params.dt_s < 0.3  # the 0.6 s pause is no backlog
        diagnostics.clear()
        diagnostics.wait_for(SIMULATOR_STATUS, DiagnosticStatus.OK, "running")
        assert float(diagnostics.value(SIMULATOR_STATUS, "paused_s")) >= 0.6


def test_realtime_step_advances_exactly_n_periods() -> None:
    """~/step while paused: N control periods at once, each state published, 4 ms apart."""
    with ros_context() as (ctx, executor):
        sim = _moving_realtime(ctx, executor)
        services = Services(ctx, executor)
        stamps: list[int] = []

        def on_state(msg: JointState) -> None:
            stamps.append(_stamp_ns(msg.header.stamp))

        services.node.create_subscription(JointState, "joint_states", on_state, 100)
        spin_until(executor, lambda: len(stamps) > 0, "joint states")
        assert services.call("pause").success
        steps, published = sim.steps, sim._published
        spin_until(executor, lambda: stamps[-1] == _stamp_ns_of(sim), "the last running state")
        seen = len(stamps)
        result = sim.set_parameters_atomically(support.parameters(step_periods=5))
        assert result.successful
        reply = services.call("step")
        assert reply.success, reply.message
        assert sim.steps - steps == 5 * sim.params.substeps_per_period
        assert sim._published - published == 5
        spin_until(executor, lambda: len(stamps) >= seen + 5, "the five stepped states")
        stepped = np.array(stamps[seen - 1 :])
        # float seconds of wall-clock epoch time resolve about 0.2 us
        assert np.all(np.abs(np.diff(stepped) - PERIOD_NS) <= 1000)
        _spin_for_wall(executor, 0.1)
        assert sim.steps - steps == 5 * sim.params.substeps_per_period  # still paused


def _stamp_ns_of(sim: SimulatorNode) -> int:
    from lca_sim.ros.node_util import to_stamp

    return _stamp_ns(to_stamp(sim.sim_time_s))


def test_refused_step_and_realtime_factor_say_why() -> None:
    """~/step while running and a realtime factor out of (0, 100] are refused with the reason."""
    with ros_context() as (ctx, executor):
        sim = start_simulator(ctx, executor, REALTIME)
        services = Services(ctx, executor)
        steps = sim.steps
        reply = services.call("step")
        assert not reply.success and "pause" in reply.message
        for bad in (0.0, -1.0, 101.0, math.nan):
            result = sim.set_parameters_atomically(support.parameters(realtime_factor=bad))
            assert not result.successful and "realtime_factor" in result.reason, bad
        assert sim.params.realtime_factor == 1.0
        assert services.call("pause").success
        assert services.call("step").success
        assert sim.steps >= steps + sim.params.substeps_per_period


def test_realtime_factor_two_runs_simulated_time_twice_as_fast() -> None:
    """realtime_factor 2: simulated time advances about twice the wall time over a window."""
    with ros_context() as (ctx, executor):
        sim = start_simulator(ctx, executor, REALTIME)
        diagnostics = Diagnostics(ctx, executor)
        assert sim.set_parameters_atomically(support.parameters(realtime_factor=2.0)).successful
        spin_until(executor, lambda: sim.sim_time_s > sim.pacing.time_base_s + 0.1, "running")
        wall0, sim0 = time.monotonic(), sim.sim_time_s
        _spin_for_wall(executor, 1.5)
        rate = (sim.sim_time_s - sim0) / (time.monotonic() - wall0)
        assert 1.6 < rate < 2.2, rate
        diagnostics.clear()
        diagnostics.wait_for(SIMULATOR_STATUS, DiagnosticStatus.OK, "running")
        assert float(diagnostics.value(SIMULATOR_STATUS, "realtime_factor_set")) == 2.0
        measured = float(diagnostics.value(SIMULATOR_STATUS, "realtime_factor"))
        assert 1.5 < measured < 2.3, measured


# --- the public fixture, as a user's test uses it ---------------------------------------------


class JointStates:
    """The joint states seen by the loop's helper node, by stamp (ns)."""

    def __init__(self, loop: HilLoop) -> None:
        self.by_stamp: dict[int, tuple[float, ...]] = {}
        loop.node.create_subscription(JointState, "joint_states", self._on_state, 1000)

    def _on_state(self, msg: JointState) -> None:
        self.by_stamp[_stamp_ns(msg.header.stamp)] = (*msg.position, *msg.velocity, *msg.effort)

    def run(self, loop: HilLoop, periods: int) -> tuple[np.ndarray, np.ndarray]:
        """Step the loop `periods` periods from t = 0; the states 1..periods and the plant."""
        self.by_stamp.clear()
        loop.step(periods)
        wanted = [k * PERIOD_NS for k in range(1, periods + 1)]
        loop.wait_for(lambda: all(t in self.by_stamp for t in wanted), "every stepped state")
        plant = np.concatenate([loop.simulator.sim.state_array, loop.simulator.sim.signal_array])
        return np.array([self.by_stamp[t] for t in wanted]), plant.copy()


def test_the_fixture_starts_paused_at_time_zero(lca_hil_loop: HilLoop) -> None:
    """Each test gets the loop at t = 0, paused, the controller's first command waiting."""
    sim = lca_hil_loop.simulator
    assert sim.paused and sim.command_pending and sim.steps == 0
    np.testing.assert_array_equal(sim.sim.state_array[0], sim.params.initial_position)
    lca_hil_loop.step(10)
    assert sim.steps == 10 * sim.params.substeps_per_period
    steps = sim.steps
    lca_hil_loop.wait_for(lambda: sim.command_pending, "the answer to the last state")
    end = time.monotonic() + 0.3
    lca_hil_loop.wait_for(lambda: time.monotonic() > end, "wall time")
    assert sim.steps == steps  # paused: the waiting command runs no period


def test_reset_then_the_same_inputs_give_the_same_trajectory(lca_hil_loop: HilLoop) -> None:
    """Step K periods, reset, step K again: the same states and plant to the last bit."""
    states = JointStates(lca_hil_loop)
    periods = 500  # 2 s: the ramp (from 1 s) moves the pivot
    first, plant = states.run(lca_hil_loop, periods)
    sim = lca_hil_loop.simulator
    assert sim.steps == periods * sim.params.substeps_per_period
    lca_hil_loop.reset()
    assert sim.sim_time_s == 0.0 and sim.steps == 0
    np.testing.assert_array_equal(sim.sim.state_array[0], sim.params.initial_position)
    np.testing.assert_array_equal(sim.sim.state_array[1:], 0.0)
    second, plant_again = states.run(lca_hil_loop, periods)
    assert np.ptp(first[:, 1]) > 1e-3  # the pivot really moved
    np.testing.assert_array_equal(first, second)
    np.testing.assert_array_equal(plant, plant_again)


def test_inject_and_set_parameters_report_refusals(lca_hil_loop: HilLoop) -> None:
    """inject: a live set on the owning node; a refusal comes back with its reason."""
    sim = lca_hil_loop.simulator
    reason = lca_hil_loop.inject(sim, initial_position=[0.0, 9.0, 0.0, 0.0])
    assert "end stops" in reason
    assert lca_hil_loop.inject(sim, enabled=False) == ""
    assert not sim.plant.enabled
    lca_hil_loop.set_parameters(sim, enabled=True)
    assert sim.plant.enabled
