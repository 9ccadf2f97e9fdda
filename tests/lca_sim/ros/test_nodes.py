"""Simulator and controller nodes in-process: closed loop, determinism, timeouts, bad input.

Each test has its own rclpy Context and domain id, waits for conditions with a deadline while
spinning, and never sleeps a fixed time.
"""

from __future__ import annotations

import itertools
import math
import time
from typing import Any

import numpy as np
import pytest
import support
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool, Trigger
from support import CONFIG, spin_until

from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.contract import ENDED_KEY, SIMULATOR_STATUS
from lca_sim.ros.controller_node import ControllerNode
from lca_sim.ros.node_util import status
from lca_sim.ros.simulator_node import SimulatorNode

PIVOT_START_RAD = math.radians(35.0)
CONTROL_PERIOD_NS = round(CONTROL_PERIOD_S * 1e9)  # the simulator's default period


ros_context = support.domain_contexts(60, 40)


def _params(**values: Any) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def _lockstep_pair(
    ctx: Context, executor: SingleThreadedExecutor, robot: str = "default", **sim_params: Any
) -> tuple[SimulatorNode, ControllerNode]:
    sim = SimulatorNode(
        context=ctx,
        parameter_overrides=_params(
            **{
                "robot": robot,
                "timing_mode": "lockstep",
                "command_interface": "current",
                "initial_position": [0.0, PIVOT_START_RAD, 0.0, 0.0],
                "lockstep_subscribers": 2,  # the controller and the test's recorder
                **sim_params,
            }
        ),
    )
    ctl = ControllerNode(
        context=ctx,
        parameter_overrides=_params(
            reference_source="ramp", command_interface="current", use_sim_time=True
        ),
    )
    executor.add_node(sim)
    executor.add_node(ctl)
    return sim, ctl


class Recorder:
    """Collects joint states on a node of the test."""

    def __init__(self, ctx: Context, executor: SingleThreadedExecutor) -> None:
        self.node = Node("test_recorder", context=ctx)
        self.states: list[JointState] = []
        self.node.create_subscription(JointState, "joint_states", self.states.append, 100)
        executor.add_node(self.node)


def test_closed_loop_ramp_switches_to_load_driving_near_55_deg() -> None:
    """Fig. 15 over topics: the ramp is tracked and motor -> load driving happens at 55 deg."""
    with ros_context() as (ctx, executor):
        sim, ctl = _lockstep_pair(ctx, executor)
        recorder = Recorder(ctx, executor)
        transitions: list[tuple[float, str, float]] = []
        last = ""

        def watch() -> bool:
            nonlocal last
            state = sim.sim.state_names[int(sim.sim.mode_array[1, 1])]
            if state != last:
                transitions.append((sim.sim_time_s, state, float(sim.sim.state_array[0, 1])))
                last = state
            return sim.sim_time_s >= 11.0

        spin_until(executor, watch, timeout_s=120.0)
        names = [name for _, name, _ in transitions]
        assert "motor_driving" in names
        first_motor = names.index("motor_driving")
        switch = next(
            t for t in transitions[first_motor:] if t[1] != "motor_driving"
        )  # the first state after motor driving
        assert switch[1].startswith(("motor_and_load_driving", "load_driving"))
        assert math.degrees(switch[2]) == pytest.approx(55.0, abs=1.0)
        # Tracking: joint velocity against the ramp, once the pivot has broken away.
        ramp = ctl.core.params.profile
        assert ramp is not None
        errors = []
        for msg in recorder.states:
            t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            if 2.0 < t < 10.9:
                errors.append(abs(msg.velocity[1] - ramp.velocity(t)))
        assert len(errors) > 1000
        assert math.degrees(max(errors)) < 0.3  # deg/s


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def test_lockstep_clock_advances_one_control_period_per_state() -> None:
    """/clock in lockstep: one tick per published instant, 4 ms of simulated time apart."""
    with ros_context() as (ctx, executor):
        sim, ctl = _lockstep_pair(ctx, executor)  # the controller runs on sim time
        recorder = Recorder(ctx, executor)
        clocks: list[int] = []

        def on_clock(msg: Clock) -> None:
            clocks.append(_stamp_ns(msg.clock))

        recorder.node.create_subscription(Clock, "/clock", on_clock, 100)
        spin_until(executor, lambda: sim.sim_time_s >= 1.0, timeout_s=60.0)
        spin_until(executor, lambda: len(set(clocks)) >= 200)
        ticks = np.array(sorted(set(clocks)))
        np.testing.assert_array_equal(np.diff(ticks), CONTROL_PERIOD_NS)  # exactly one period
        joint_stamps = {_stamp_ns(m.header.stamp) for m in recorder.states}
        assert set(ticks.tolist()) <= joint_stamps  # every tick is an instant published
        assert (
            ctl.get_clock().now().nanoseconds >= ticks[-1] - 2 * CONTROL_PERIOD_NS
        )  # it follows /clock


def _lockstep_run(seconds: float) -> np.ndarray:
    with ros_context() as (ctx, executor):
        sim, _ = _lockstep_pair(ctx, executor)
        recorder = Recorder(ctx, executor)
        spin_until(executor, lambda: sim.sim_time_s >= seconds, timeout_s=120.0)
        spin_until(executor, lambda: len(recorder.states) >= round(seconds / CONTROL_PERIOD_S))
        rows = {
            (m.header.stamp.sec, m.header.stamp.nanosec): (*m.position, *m.velocity)
            for m in recorder.states
        }
        return np.array([rows[k] for k in sorted(rows)])


def test_lockstep_is_deterministic() -> None:
    """The same lockstep run twice records identical joint states, bit for bit."""
    first = _lockstep_run(2.0)
    second = _lockstep_run(2.0)
    assert first.shape[0] >= 500
    n = min(len(first), len(second))
    np.testing.assert_array_equal(first[:n], second[:n])
    assert np.ptp(first[:, 1]) > 0.0  # the pivot really moved


def test_the_end_of_a_lockstep_run_is_no_plant_loss_for_the_controller() -> None:
    """A simulator that ended its run (lockstep_end_s) leaves the controller OK, not WARN.

    `lca-hil fig15` keeps the controller running while the recorder drains the last messages;
    on a loaded host that outlasted plant_timeout_s and the controller's log said "no plant
    state for 0.6 s" at the end of a healthy run.
    """
    with ros_context() as (ctx, executor):
        sim, ctl = _lockstep_pair(ctx, executor, lockstep_subscribers=1, lockstep_end_s=0.1)
        spin_until(executor, lambda: sim.ended and sim.pacing.after_end >= 1)  # last one answered
        answered = ctl.commands_sent
        assert answered == round(0.1 / CONTROL_PERIOD_S) + 1  # t = 0 and every period to 0.1 s
        timeout_s = ctl.core.params.plant_timeout_s
        spin_until(executor, lambda: time.monotonic() - ctl._last_state_wall > 2 * timeout_s)
        spin_until(executor, lambda: len(ctl._ends_announced_s) > 0)
        assert ctl._plant_health() == (DiagnosticStatus.OK, "plant ended its run at 0.1 s")
        assert ctl.plant_losses == 0
        assert ctl.commands_sent == answered


@pytest.mark.parametrize(
    ("ended_at_s", "level"), [(2.0, DiagnosticStatus.WARN), (1.0, DiagnosticStatus.OK)]
)
def test_only_an_end_at_the_last_state_taken_excuses_the_silence(
    ended_at_s: float, level: bytes
) -> None:
    """Another simulator's end (or this one's before a reset) is no end of this plant."""
    with ros_context() as (ctx, executor):
        ctl = ControllerNode(context=ctx, parameter_overrides=_params(plant_timeout_s=0.1))
        plant = Node("fake_plant", context=ctx)
        states = plant.create_publisher(JointState, "joint_states", 10)
        diagnostics = plant.create_publisher(DiagnosticArray, "/diagnostics", 10)
        executor.add_node(ctl)
        executor.add_node(plant)
        spin_until(executor, lambda: states.get_subscription_count() > 0)
        spin_until(executor, lambda: diagnostics.get_subscription_count() > 0)
        state = JointState(name=["l_arm", "pivot", "c_arc", "lift"], position=[0.0] * 4)
        state.velocity = [0.0] * 4
        state.header.stamp.sec = 1
        states.publish(state)
        spin_until(executor, lambda: ctl._joint is not None)
        ended = status(SIMULATOR_STATUS, DiagnosticStatus.OK, "ended", {
            ENDED_KEY: True, "sim_time_s": ended_at_s
        })  # fmt: skip
        diagnostics.publish(DiagnosticArray(status=[ended]))
        spin_until(executor, lambda: len(ctl._ends_announced_s) == 1)
        spin_until(executor, lambda: time.monotonic() - ctl._last_state_wall > 0.1)
        assert ctl._plant_health()[0] == level
        assert ctl.plant_losses == (1 if level == DiagnosticStatus.WARN else 0)


def test_a_state_is_answered_once_a_reader_of_the_commands_matches() -> None:
    """No reader of current_commands yet: the state is held, not answered into the void.

    A stamp is answered once only, so an answer nobody received would leave a lockstep plant
    re-publishing the same state for ever (a fresh-clone CI run waited 60 s for the first
    command this way: the controller's writer had not yet matched the simulator's reader).
    """
    with ros_context() as (ctx, executor):
        ctl = ControllerNode(
            context=ctx,
            parameter_overrides=_params(reference_source="ramp", command_interface="current"),
        )
        plant = Node("fake_plant", context=ctx)
        states = plant.create_publisher(JointState, "joint_states", 10)
        executor.add_node(ctl)
        executor.add_node(plant)
        spin_until(executor, lambda: states.get_subscription_count() > 0)
        state = JointState(name=["l_arm", "pivot", "c_arc", "lift"], position=[0.0] * 4)
        state.velocity = [0.0] * 4
        states.publish(state)
        spin_until(executor, lambda: ctl._joint is not None)
        spin_until(executor, lambda: math.isfinite(ctl._last_wake_wall))  # its first wake
        wake_s = ctl._last_wake_wall
        spin_until(executor, lambda: ctl._last_wake_wall > wake_s + 0.12)  # 2 more 20 Hz wakes
        assert ctl.states_held == 1  # one state, however often it was tried
        received: list[Float64MultiArray] = []
        reader = plant.create_subscription(
            Float64MultiArray, "current_commands", received.append, 10
        )
        spin_until(executor, lambda: reader.get_publisher_count() > 0)
        states.publish(state)  # re-published, as a lockstep plant does after its resend time
        spin_until(executor, lambda: len(received) == 1)  # the held state, answered
        assert ctl.commands_sent == 1  # once: the re-published stamp is not answered again
        assert len(received[0].data) == 4


def _realtime_sim(ctx: Context, executor: SingleThreadedExecutor, robot: str) -> SimulatorNode:
    sim = SimulatorNode(
        context=ctx,
        parameter_overrides=_params(
            robot=robot,
            command_interface="current",
            command_timeout_s=0.2,
            initial_position=[0.0, 0.0, 0.0, 0.0],
        ),
    )
    executor.add_node(sim)
    return sim


@pytest.mark.parametrize(("robot", "holds"), [("default", True), ("reversible", False)])
def test_command_silence_drops_to_zero_and_the_worm_holds(robot: str, holds: bool) -> None:
    """Command silence: 0 V; the irreversible pivot holds, the reversible one sinks.

    The axes are judged by their drive state, not by the current: at 0 V the current crosses
    zero on its way down while the pivot still coasts (it brakes on its back-EMF), so a batch of
    realtime steps that happened to end at that crossing read as "stopped" and the pivot then
    coasted on another 1.6 mrad (CI, a slow host).
    """
    with ros_context() as (ctx, executor):
        sim = _realtime_sim(ctx, executor, robot)
        driver = Node("driver", context=ctx)
        pub = driver.create_publisher(Float64MultiArray, "current_commands", 10)
        executor.add_node(driver)
        spin_until(executor, lambda: pub.get_subscription_count() > 0)
        pub.publish(Float64MultiArray(data=[0.0, 6.0, 0.0, 0.0]))
        spin_until(executor, lambda: sim.plant.target[1] == 6.0)
        spin_until(executor, lambda: sim.plant.counters.timeouts == 1)
        assert sim.plant.target[1] == 0.0
        arrays = sim.sim

        def pivot_state() -> str:
            return arrays.state_names[int(arrays.mode_array[1, 1])]

        settled = "stop_hold" if holds else "load_driving"  # the worm locked / the load sinks
        spin_until(executor, lambda: pivot_state() == settled)
        q0 = float(arrays.state_array[0, 1])
        t0 = sim.sim_time_s
        spin_until(executor, lambda: sim.sim_time_s > t0 + 1.0)
        moved = float(arrays.state_array[0, 1]) - q0
        if holds:
            assert moved == 0.0
            assert pivot_state() == "stop_hold"
            assert abs(float(arrays.state_array[2, 1])) < 1e-3  # no current holds it: the worm
        else:
            assert moved < -math.radians(0.5)  # it sinks


@pytest.mark.parametrize(
    ("data", "counter"),
    [
        ([0.0, math.nan, 0.0, 0.0], "rejected_nonfinite"),
        ([0.0, math.inf, 0.0, 0.0], "rejected_nonfinite"),
        ([1.0, 2.0], "rejected_length"),
        ([0.0, 5e4, 0.0, 0.0], "rejected_absurd"),
    ],
)
def test_bad_commands_are_counted_and_change_nothing(data: list[float], counter: str) -> None:
    """NaN, wrong length, absurd: refused, counted, the last good command stays in force."""
    with ros_context() as (ctx, executor):
        sim = _realtime_sim(ctx, executor, "default")
        driver = Node("driver", context=ctx)
        pub = driver.create_publisher(Float64MultiArray, "current_commands", 10)
        executor.add_node(driver)
        spin_until(executor, lambda: pub.get_subscription_count() > 0)
        pub.publish(Float64MultiArray(data=[0.0, 2.0, 0.0, 0.0]))
        spin_until(executor, lambda: sim.plant.counters.accepted == 1)
        pub.publish(Float64MultiArray(data=data))
        spin_until(executor, lambda: sim.plant.counters.rejected == 1)
        assert getattr(sim.plant.counters, counter) == 1
        assert list(sim.plant.target) == [0.0, 2.0, 0.0, 0.0]
        assert np.all(np.isfinite(sim.sim.state_array))


def test_voltage_beyond_the_amplifier_is_saturated() -> None:
    """A command above the amplifier limit (but not absurd) is clamped and counted."""
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx, parameter_overrides=_params(command_interface="voltage"))
        executor.add_node(sim)
        assert sim.plant.command([0.0, 0.0, 0.0, 60.0]) is None
        assert sim.plant.target[3] == 48.0
        assert sim.plant.counters.saturated == 1


def test_parameters_are_validated_live() -> None:
    """Bad values and read-only parameters are refused with a reason; good ones apply."""
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx)
        executor.add_node(sim)
        bad = sim.set_parameters([Parameter("command_timeout_s", value=-1.0)])[0]
        assert not bad.successful and "command_timeout_s" in bad.reason
        for name, value in (("dt_s", 2e-4), ("rigid_body_period_s", 2e-3)):
            fixed = sim.set_parameters([Parameter(name, value=value)])[0]
            assert not fixed.successful and "restart" in fixed.reason and name in fixed.reason
        assert sim.sim.rigid_body_update_steps == 10  # the 1 ms default, unchanged
        good = sim.set_parameters([Parameter("current_kp_v_per_a", value=20.0)])[0]
        assert good.successful
        assert sim.params.current_kp_v_per_a == 20.0
        ctl = ControllerNode(context=ctx)
        executor.add_node(ctl)
        bad = ctl.set_parameters([Parameter("velocity_ti_s", value=0.0)])[0]
        assert not bad.successful and "ti_s" in bad.reason
        good = ctl.set_parameters([Parameter("velocity_kp_a_per_rad_s", value=100.0)])[0]
        assert good.successful
        assert ctl.core.cascades[1].params.velocity.kp == 100.0


def test_bad_start_parameter_is_a_parameter_error() -> None:
    """A bad parameter at start raises the one-line ParameterError the entry point prints."""
    from lca_control.parameters import ParameterError

    with ros_context() as (ctx, _), pytest.raises(ParameterError, match=r"^timing_mode: expected"):
        SimulatorNode(context=ctx, parameter_overrides=_params(timing_mode="sideways"))


@pytest.mark.parametrize(
    ("params_file", "said"),
    [
        # rcl itself: a traceback for a missing file, silence for a file that sets nothing.
        ("missing.yaml", "file not found"),
        ("ros/controller.yaml", "no parameters for node /simulator (the file has controller)"),
    ],
)
def test_a_params_file_that_would_set_nothing_stops_the_node_with_the_reason(
    params_file: str, said: str
) -> None:
    """The simulator given another node's params file (or none at all): exit 2, one line."""
    result = support.run_tool(
        "lca-simulator",
        "--ros-args",
        "--params-file",
        str(CONFIG / params_file),
        domain_id=97,
        timeout_s=60.0,
    )
    errors = [line for line in result.stderr.splitlines() if "error" in line.lower()]
    assert result.returncode == 2, result.stderr
    assert len(errors) == 1 and said in errors[0], result.stderr
    assert errors[0].startswith("lca-simulator: error:") and "Traceback" not in result.stderr


def test_reset_and_enable_services() -> None:
    """~/reset returns to the initial pose; ~/enable false puts 0 V on every axis."""
    with ros_context() as (ctx, executor):
        sim = _realtime_sim(ctx, executor, "default")
        client = Node("client", context=ctx)
        executor.add_node(client)
        reset = client.create_client(Trigger, "/simulator/reset")
        enable = client.create_client(SetBool, "/simulator/enable")
        spin_until(executor, lambda: reset.service_is_ready() and enable.service_is_ready())
        sim.plant.command([0.0, 8.0, 0.0, 0.0])
        spin_until(executor, lambda: sim.sim.state_array[0, 1] > 0.001)
        future = reset.call_async(Trigger.Request())
        spin_until(executor, future.done)
        assert future.result().success
        assert sim.sim.state_array[0, 1] == 0.0
        future = enable.call_async(SetBool.Request(data=False))
        spin_until(executor, future.done)
        sim.plant.command([0.0, 8.0, 0.0, 0.0])
        t0 = sim.sim_time_s
        spin_until(executor, lambda: sim.sim_time_s > t0 + 0.2)
        assert np.all(sim.sim.signal_array[2] == 0.0)  # voltage row: 0 V everywhere


def test_velocity_commands_follow_the_ramp_for_a_drive_that_closes_the_loop() -> None:
    """velocity_commands carries the setpoint the controller's velocity loop follows.

    A CSV drive takes it instead of the current: over the ramp the pivot's entry rises with the
    ramp's velocity (no position loop in the shipped parameters), the other joints' stay 0, and
    every state answered after the subscription matched has its array.
    """
    with ros_context() as (ctx, executor):
        sim, ctl = _lockstep_pair(ctx, executor)
        Recorder(ctx, executor)  # the simulator waits for two joint_states subscribers
        listener = Node("test_velocity_listener", context=ctx)
        received: list[list[float]] = []

        def on_velocities(msg: Float64MultiArray) -> None:
            received.append(list(msg.data))

        listener.create_subscription(Float64MultiArray, "velocity_commands", on_velocities, 100)
        executor.add_node(listener)
        spin_until(executor, lambda: sim.sim_time_s >= 3.0, timeout_s=120.0)
        spin_until(
            executor,
            lambda: received[-1] == ctl.core.last_velocity_reference,
            "the last setpoint delivered",
        )
        ramp = ctl.core.params.profile
        assert ramp is not None
        assert len(received) > 500
        assert ctl.commands_sent - len(received) < 100  # only those before the match are missing
        assert all(len(v) == 4 and v[0] == v[2] == v[3] == 0.0 for v in received)
        pivot = [v[1] for v in received]
        assert all(b >= a for a, b in itertools.pairwise(pivot))  # the ramp rises
        assert pivot[-1] == pytest.approx(ramp.velocity(3.0), abs=1e-3)
        assert pivot[-1] > 0.0
