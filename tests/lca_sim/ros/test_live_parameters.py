"""Every node walks its whole parameter table live: each set takes effect, or is rejected.

For each parameter of a node's table the test sets a valid new value while the node runs:
a read-only one must be refused with a reason that says to restart, and the value in force
must not move; a live one must be accepted and its effect must be visible in the running node
(a probe per parameter; a live parameter without a probe fails the test). Each live parameter
is also set to a value outside its documented range, which must be refused with its name.
The simulator is walked twice, lockstep on voltages and realtime on currents: a parameter of
one timing mode or interface shows its effect on the node of that mode.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import support
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray

from lca_control.controller import JointController
from lca_control.parameters import ParamKind, ParamSpec
from lca_sim.ros.can_bridge_node import CanBridgeNode
from lca_sim.ros.controller_node import ControllerNode
from lca_sim.ros.simulator_node import SimulatorNode

Probe = tuple[Any, Callable[[Any], bool]]  # the new value, and how its effect shows


ros_context = support.domain_contexts(150, 20)


def _other_value(spec: ParamSpec) -> Any:
    """A value the spec accepts that differs from its default."""
    default = spec.default
    if spec.kind is ParamKind.BOOL:
        return not default
    if spec.kind is ParamKind.STRING:
        return next((c for c in spec.choices if c != default), default + "_other")
    if spec.kind in (ParamKind.STRING_ARRAY, ParamKind.INTEGER_ARRAY, ParamKind.DOUBLE_ARRAY):
        return list(reversed(default)) if len(set(default)) > 1 else [*default, *default]
    if spec.kind is ParamKind.INTEGER:
        return default + 1 if spec.high is None or default + 1 <= spec.high else default - 1
    return default / 2.0


def _out_of_range(spec: ParamSpec) -> Any:
    """A value the spec refuses, or None for a free string (any name is in its range)."""
    if spec.kind is ParamKind.BOOL:
        return "yes"
    if spec.kind is ParamKind.STRING:
        return "sideways" if spec.choices else None
    if spec.kind is ParamKind.DOUBLE_ARRAY:
        return [math.nan]
    if spec.low is not None:
        return spec.low - 1.0 if spec.kind is ParamKind.DOUBLE else int(spec.low) - 1
    return math.nan  # an unbounded double must still be finite


def _walk(node: Node, table: Any, probes: dict[str, Probe], current: Callable[[str], Any]) -> None:
    assert set(probes) == {s.name for s in table if s.live}, "a live parameter has no probe"
    for spec in table:
        before = current(spec.name)
        if not spec.live:
            result = node.set_parameters([Parameter(spec.name, value=_other_value(spec))])[0]
            assert not result.successful, f"{spec.name} is read-only but was accepted"
            assert spec.name in result.reason and "restart" in result.reason
            assert current(spec.name) == before
            continue
        refused = _out_of_range(spec)
        if refused is not None:
            bad = node.set_parameters([Parameter(spec.name, value=refused)])[0]
            assert not bad.successful and spec.name in bad.reason, (spec.name, bad.reason)
            assert current(spec.name) == before
        value, took_effect = probes[spec.name]
        good = node.set_parameters([Parameter(spec.name, value=value)])[0]
        assert good.successful, (spec.name, good.reason)
        assert took_effect(node), f"{spec.name} := {value!r} was accepted but had no effect"


def _lockstep_advance_s(sim: SimulatorNode) -> float:
    """Simulated time one lockstep command advances, measured on the running node."""
    t0 = sim.sim_time_s
    sim._commands.on_command(Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0]))
    return sim.sim_time_s - t0


def _lockstep_ends_at(sim: SimulatorNode, end_s: float) -> bool:
    """lockstep_end_s: commands advance to exactly end_s, then publish nothing more."""
    command = Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0])
    for _ in range(100_000):
        if sim.ended:
            break
        sim._commands.on_command(command)
    published = sim._published
    sim._commands.on_command(command)  # after the end: ignored
    return sim.ended and abs(sim.sim_time_s - end_s) < 1e-12 and sim._published == published


def _step_runs_periods(sim: SimulatorNode, periods: int) -> bool:
    """step_periods: paused, one ~/step lets exactly that many commands run a period."""
    command = Float64MultiArray(data=[0.0, 0.0, 0.0, 0.0])
    sim.reset()  # time back to 0: a run that lockstep_end_s ended starts again
    sim.pause()
    t0 = sim.sim_time_s
    stepped = sim.step()[0]
    for _ in range(periods + 2):
        sim._commands.on_command(command)
    advanced_s = sim.sim_time_s - t0
    sim.resume()  # the command left waiting runs its period
    return stepped and math.isclose(advanced_s, periods * sim.params.control_period_s)


def _timer_period_s(timer: Any) -> float:
    return float(timer.timer_period_ns) * 1e-9


def _disabled_applies_zero_volts(sim: SimulatorNode) -> bool:
    """Disabled: the next steps put 0 V on every axis whatever the command."""
    sim.plant.command([0.0, 8.0, 0.0, 0.0])
    sim.plant.advance(10)
    return not sim.plant.enabled and bool(np.all(sim.sim.signal_array[2] == 0.0))


def _stored(name: str, value: Any) -> Probe:
    """The value in force, for a parameter of the other timing mode or command interface.

    Its effect is shown by the walk of the other node (`STORED_IN_...`).
    """
    return value, lambda n: getattr(n.params, name) == value


def _resends_after(sim: SimulatorNode, resend_s: float) -> bool:
    """lockstep_resend_s: the last state is published again after that silence, not before."""
    published = sim._published
    sim.pacing.last_command_wall = sim.pacing.last_publish_wall = time.monotonic() - 0.6 * resend_s
    sim._lockstep_kick()
    quiet = sim._published == published
    sim.pacing.last_command_wall = sim.pacing.last_publish_wall = time.monotonic() - 1.1 * resend_s
    sim._lockstep_kick()
    return quiet and sim._published == published + 1


def _command(sim: SimulatorNode, pivot: float) -> None:
    """A command array that moves only the pivot (its unit is the node's interface's)."""
    sim._commands.on_command(
        Float64MultiArray(data=[pivot if j == "pivot" else 0.0 for j in sim.params.joints])
    )


def _pivot_target(sim: SimulatorNode) -> float:
    return float(sim.plant.target[sim.sim.axis_names.index("pivot")])


def _silence_drops_the_command_after(sim: SimulatorNode, executor: Any, timeout_s: float) -> bool:
    """command_timeout_s (realtime): that long without a command and the current drops to 0."""
    timeouts = sim.plant.counters.timeouts
    _command(sim, 1.0)
    commanded_s = time.monotonic()
    assert _pivot_target(sim) == 1.0
    # the node started with 30 s: without the new value nothing drops within this deadline
    support.spin_until(
        executor, lambda: not np.any(sim.plant.target), "the command dropped to 0", timeout_s=10.0
    )
    silent_s = time.monotonic() - commanded_s
    return sim.plant.counters.timeouts == timeouts + 1 and silent_s >= timeout_s


def _current_above_refused(sim: SimulatorNode, limit_a: float) -> bool:
    """max_command_current_a: a command above it is refused (counted), one below it taken."""
    counters = sim.plant.counters
    rejected = counters.rejected_absurd
    _command(sim, 1.0)
    _command(sim, limit_a + 1.0)  # within the old limit (100 A)
    refused = counters.rejected_absurd == rejected + 1 and _pivot_target(sim) == 1.0
    _command(sim, limit_a - 1.0)
    return refused and _pivot_target(sim) == limit_a - 1.0


def _common_simulator_probes() -> dict[str, Probe]:
    """Probes of the parameters that act the same in either timing mode and interface."""
    return {
        "current_kp_v_per_a": (20.0, lambda n: n.plant.current_pi.kp == 20.0),
        "current_ti_s": (2e-3, lambda n: n.plant.current_pi.ti_s == 2e-3),
        "initial_position": (
            [0.0, 0.5, 0.0, 0.0],
            lambda n: (n._reset_pose(), n.sim.state_array[0, 1])[1] == 0.5,
        ),
        "enabled": (False, _disabled_applies_zero_volts),
        "diagnostics_period_s": (0.5, lambda n: _timer_period_s(n._diag_timer) == 0.5),
        # its effect on a realtime node: test_sim_control; in lockstep it is stored
        "realtime_factor": (0.5, lambda n: n.params.realtime_factor == 0.5),
    }


# What each walk can only store (the value set): its effect shows on the other walk's node.
# Disjoint, so each live parameter's effect is probed by one of the two walks.
STORED_IN_LOCKSTEP_VOLTAGE: dict[str, Any] = {
    "publish_rate_hz": 100.0,
    "command_timeout_s": 0.05,
    "max_command_current_a": 5.0,
}
STORED_IN_REALTIME_CURRENT: dict[str, Any] = {
    "control_period_s": 0.008,
    "max_command_voltage_v": 50.0,
    "lockstep_resend_s": 2.0,
    "lockstep_end_s": 0.05,
    "step_periods": 3,
}


def test_every_simulator_parameter_has_its_effect_probed_in_one_walk() -> None:
    """No live parameter is merely stored in both walks (realtime_factor: test_sim_control)."""
    from lca_sim.config.simulator_params import SIMULATOR_PARAMETERS

    assert not STORED_IN_LOCKSTEP_VOLTAGE.keys() & STORED_IN_REALTIME_CURRENT.keys()
    assert STORED_IN_LOCKSTEP_VOLTAGE.keys() | STORED_IN_REALTIME_CURRENT.keys() <= {
        s.name for s in SIMULATOR_PARAMETERS if s.live
    }


def test_simulator_applies_or_rejects_every_parameter() -> None:
    """The simulator's whole table, on a lockstep voltage node whose loop the test drives."""
    from lca_sim.config.simulator_params import SIMULATOR_PARAMETERS

    with ros_context() as (ctx, executor):
        sim = SimulatorNode(
            context=ctx,
            parameter_overrides=[
                Parameter("timing_mode", value="lockstep"),
                Parameter("lockstep_subscribers", value=0),
            ],
        )
        executor.add_node(sim)
        sim.pacing.started = True  # lockstep without a controller: the test sends the commands
        probes: dict[str, Probe] = {
            **_common_simulator_probes(),
            **{name: _stored(name, v) for name, v in STORED_IN_LOCKSTEP_VOLTAGE.items()},
            "control_period_s": (0.008, lambda n: math.isclose(_lockstep_advance_s(n), 0.008)),
            "max_command_voltage_v": (
                50.0,
                lambda n: n.plant.command([0.0, 60.0, 0.0, 0.0]) is not None,  # refused now
            ),
            # 1.2 s of silence: past the old 1 s, before the new 2 s
            "lockstep_resend_s": (2.0, lambda n: _resends_after(n, 2.0)),
            # not a whole number of 8 ms periods: the last period is cut short at the end
            "lockstep_end_s": (0.0502, lambda n: _lockstep_ends_at(n, 0.0502)),
            "step_periods": (3, lambda n: _step_runs_periods(n, 3)),
        }
        _walk(sim, SIMULATOR_PARAMETERS, probes, lambda name: sim.get_parameter(name).value)


def test_realtime_current_simulator_applies_or_rejects_every_parameter() -> None:
    """The simulator's whole table again, on a realtime node taking currents.

    The realtime- and current-only parameters show their effect here; a command timeout of
    30 s at start makes a drop within the probe's deadline the new value's doing.
    """
    from lca_sim.config.simulator_params import SIMULATOR_PARAMETERS

    with ros_context() as (ctx, executor):
        sim = SimulatorNode(
            context=ctx,
            parameter_overrides=[
                Parameter("command_interface", value="current"),
                Parameter("command_timeout_s", value=30.0),
            ],
        )
        executor.add_node(sim)
        probes: dict[str, Probe] = {
            **_common_simulator_probes(),
            **{name: _stored(name, v) for name, v in STORED_IN_REALTIME_CURRENT.items()},
            "publish_rate_hz": (100.0, lambda n: _timer_period_s(n._tick_timer) == 0.01),
            "command_timeout_s": (
                0.2,
                lambda n: _silence_drops_the_command_after(n, executor, 0.2),
            ),
            "max_command_current_a": (5.0, lambda n: _current_above_refused(n, 5.0)),
        }
        _walk(sim, SIMULATOR_PARAMETERS, probes, lambda name: sim.get_parameter(name).value)


def test_realtime_simulator_retimes_its_publisher_live() -> None:
    """publish_rate_hz in realtime mode: the tick timer runs at the new period at once."""
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx)
        executor.add_node(sim)
        assert sim.set_parameters([Parameter("publish_rate_hz", value=100.0)])[0].successful
        assert _timer_period_s(sim._tick_timer) == 0.01


def test_an_initial_position_outside_the_end_stops_is_refused_live() -> None:
    """A pose ~/reset could not take is rejected when it is set, not when reset fails."""
    with ros_context() as (ctx, executor):
        sim = SimulatorNode(context=ctx)
        executor.add_node(sim)
        result = sim.set_parameters([Parameter("initial_position", value=[0.0, 9.0, 0.0, 0.0])])
        assert not result[0].successful and "end stops" in result[0].reason
        assert sim.params.initial_position == (0.0, 0.0, 0.0, 0.0)


def _topic_reference_expires_after(ctl: ControllerNode, timeout_s: float) -> bool:
    """reference_timeout_s: a topic reference counts until it is that old, then as zero."""
    assert ctl.set_parameters([Parameter("reference_source", value="topic")])[0].successful
    core = ctl.core
    positions = [0.0] * 4
    core.set_topic_reference([0.0, 0.05, 0.0, 0.0], 10.0)  # within the velocity limit
    fresh = core.velocity_references(10.0 + 0.8 * timeout_s, positions)[1]
    # 0.3 s old: still counted under the old timeout (0.5 s)
    stale = core.velocity_references(10.0 + 1.2 * timeout_s, positions)[1]
    return math.isclose(fresh, 0.05) and stale == 0.0


def _first_step_dt_is(ctl: ControllerNode, period_s: float) -> bool:
    """nominal_period_s: the first state after a restart integrates its error over that dt.

    The node's first command (plant time gone back: a restart) must equal a fresh controller's
    second one, `period_s` after a first state without any error. The error is small enough
    that no loop saturates (a saturated output would hide the dt).
    """
    assert ctl.set_parameters([Parameter("reference_source", value="hold")])[0].successful
    still, creeping = [0.0] * 4, [1e-6] * 4  # rad/s
    core = ctl.core
    core.update(1e6, still, still, still)
    first = core.update(0.0, still, creeping, still)  # time back: a restart
    fresh = JointController(core.params)
    fresh.update(0.0, still, still, still)  # no error: nothing integrated
    second = fresh.update(period_s, still, creeping, still)
    return first is not None and first == second and 0.0 < abs(first[0]) < 1.0


def test_controller_applies_or_rejects_every_parameter() -> None:
    """The controller's whole table; effects read off the running cascades."""
    from lca_control.controller import CONTROLLER_PARAMETERS

    with ros_context() as (ctx, executor):
        ctl = ControllerNode(context=ctx)
        executor.add_node(ctl)

        def core(name: str, value: Any) -> Probe:
            return value, lambda n: getattr(n.core.params, name) == value

        def cascade(path: str, value: float) -> Probe:
            loop, field = path.split(".")
            return value, lambda n: all(
                getattr(getattr(c.params, loop), field) == value for c in n.core.cascades
            )

        def profile(field: str, value: float) -> Probe:
            # an idle profile's value is checked and kept; it shows once the profile runs
            source = "ramp" if field.startswith("ramp") else "trapezoid"
            return (
                value,
                lambda n: (
                    n.set_parameters([Parameter("reference_source", value=source)])[0].successful
                    and n._live.values[field] == value
                    and n.core.params.profile is not None
                ),
            )

        probes: dict[str, Probe] = {
            "reference_source": core("reference_source", "hold"),
            "profile_joint": core("profile_joint", "lift"),
            **{
                name: profile(name, value)
                for name, value in (
                    ("ramp_start_s", 2.0),
                    ("ramp_duration_s", 5.0),
                    ("ramp_end_velocity", 0.05),
                    ("ramp_hold_s", 1.0),
                    ("trapezoid_start_s", 2.0),
                    ("trapezoid_accel_s", 0.5),
                    ("trapezoid_cruise_s", 1.0),
                    ("trapezoid_decel_s", 0.5),
                    ("trapezoid_velocity", 0.05),
                )
            },
            "velocity_kp_a_per_rad_s": cascade("velocity.kp", 100.0),
            "velocity_ti_s": cascade("velocity.ti_s", 0.02),
            "current_kp_v_per_a": cascade("current.kp", 20.0),
            "current_ti_s": cascade("current.ti_s", 2e-3),
            "current_limit_a": cascade("velocity.output_max", 5.0),
            "voltage_limit_v": cascade("current.output_max", 100.0),
            "position_kp_per_s": (
                2.0,
                lambda n: all(c.params.position_kp_per_s == 2.0 for c in n.core.cascades),
            ),
            "velocity_limit": (0.1, lambda n: n.core.params.cascade.velocity_limit == 0.1),
            "reference_timeout_s": (0.25, lambda n: _topic_reference_expires_after(n, 0.25)),
            "nominal_period_s": (0.002, lambda n: _first_step_dt_is(n, 0.002)),
            "plant_timeout_s": core("plant_timeout_s", 0.25),
            "enabled": (
                False,
                lambda n: n.core.update(1.0, [0.0] * 4, [0.5] * 4, [1.0] * 4) == [0.0] * 4,
            ),
        }
        _walk(ctl, CONTROLLER_PARAMETERS, probes, lambda name: ctl.get_parameter(name).value)


def test_can_bridge_applies_or_rejects_every_parameter() -> None:
    """The bridge's whole table, with its virtual rack; safety timing reaches the master."""
    from lca_sim.config.can_bridge_params import CAN_BRIDGE_PARAMETERS

    with ros_context() as (ctx, executor):
        bridge = CanBridgeNode(
            context=ctx,
            parameter_overrides=[Parameter("channel", value="test_live_parameters")],
        )
        executor.add_node(bridge)
        try:

            def master(name: str, value: Any) -> Probe:
                return value, lambda n: getattr(n.bridge.params, name) == value

            probes: dict[str, Probe] = {
                "command_timeout_s": master("command_timeout_s", 0.2),
                "quick_stop_after_s": master("quick_stop_after_s", 1.0),
                "stale_timeout_s": master("stale_timeout_s", 0.3),
                "max_send_failures": master("max_send_failures", 20),
                "diagnostics_period_s": (
                    0.5,
                    lambda n: _timer_period_s(n._diag_timer) == 0.5,
                ),
            }
            _walk(
                bridge, CAN_BRIDGE_PARAMETERS, probes, lambda name: bridge.get_parameter(name).value
            )
        finally:
            bridge.destroy_node()


@pytest.mark.parametrize("value", [True, False])
def test_enable_service_and_parameter_agree(value: bool) -> None:
    """~/enable is the enabled parameter by another door: both read the same afterwards."""
    from std_srvs.srv import SetBool

    with ros_context() as (ctx, _):
        sim = SimulatorNode(context=ctx)
        response = sim._on_enable(SetBool.Request(data=value), SetBool.Response())
        assert response.success
        assert sim.get_parameter("enabled").value is value
        assert sim.plant.enabled is value
