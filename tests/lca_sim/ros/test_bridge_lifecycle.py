"""The CAN bridge as a managed node: the standard lifecycle services drive the drives.

The bridge with its virtual rack in this process (interface virtual, python-can's in-process
bus). A client node plays the lifecycle manager: lifecycle_msgs/srv/ChangeState on
`/can_bridge/change_state` and GetState on `/can_bridge/get_state`, exactly what
`ros2 lifecycle set` and nav2's lifecycle manager call. Each transition is judged on the bus and
in the rack: what the drives' object dictionaries hold, their CiA 402 power state, the current
and the motion of an axis. Every wait has a deadline; none sleeps.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import can
import pytest
import support
from diagnostic_msgs.msg import DiagnosticStatus
from lifecycle_msgs.msg import Transition  # type: ignore[import-untyped]
from lifecycle_msgs.srv import ChangeState, GetState  # type: ignore[import-untyped]
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from support import Diagnostics, spin_until

from lca_control import contract as pc
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402 import objects as od
from lca_sim.cia402.device import MODE_CST, PowerState
from lca_sim.ros.can_bridge_node import CanBridgeNode
from lca_sim.runtime import SlowCalls

BRIDGE = "lca_hil/can_bridge"
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
CYCLE_HZ = 250.0
PIVOT_A = 4.0  # enough to turn the pivot against its gear's friction and gravity
OK, ERROR = DiagnosticStatus.OK, DiagnosticStatus.ERROR
# CiA 402 states with the power stage off (or the drive function disabled): no torque.
TORQUE_FREE = frozenset(
    {PowerState.SWITCH_ON_DISABLED, PowerState.READY_TO_SWITCH_ON, PowerState.SWITCHED_ON}
)

ros_context = support.domain_contexts(214, 4)


def _bridge(ctx: Context, executor: SingleThreadedExecutor, **overrides: Any) -> CanBridgeNode:
    values: dict[str, Any] = {
        "interface": "virtual",
        "channel": f"test_bridge_lifecycle_{id(ctx)}",
        "autostart": False,
        "auto_enable": True,
        "cycle_hz": CYCLE_HZ,
        "diagnostics_period_s": 0.1,
        "command_timeout_s": 0.5,
        **support.ROOMY_WATCHDOGS,  # room for this process's GIL (rack, bridge, test)
    }
    values.update(overrides)
    bridge = CanBridgeNode(
        context=ctx,
        parameter_overrides=[
            Parameter(k, value=v)  # type: ignore[no-untyped-call]
            for k, v in values.items()
        ],
    )
    executor.add_node(bridge)
    return bridge


class Manager:
    """A lifecycle manager's side of the bridge: the standard services, from a node of its own."""

    def __init__(self, ctx: Context, executor: SingleThreadedExecutor) -> None:
        self.node = Node("lifecycle_manager", context=ctx)
        self.executor = executor
        executor.add_node(self.node)
        self._change = self.node.create_client(ChangeState, "/can_bridge/change_state")
        self._get = self.node.create_client(GetState, "/can_bridge/get_state")
        self._enable = self.node.create_client(Trigger, "/can_bridge/enable")
        self.currents = self.node.create_publisher(Float64MultiArray, pc.CURRENT_COMMANDS, 10)
        self.joint_states: list[JointState] = []
        self.node.create_subscription(JointState, pc.JOINT_STATES, self.joint_states.append, 50)

    def _call(self, client: Any, request: Any) -> Any:
        spin_until(self.executor, client.service_is_ready, f"{client.srv_name} served", 30.0)
        future = client.call_async(request)
        spin_until(self.executor, future.done, f"{client.srv_name} answered", 30.0)
        return future.result()

    def set(self, transition_id: int) -> bool:
        """Ask for one transition (lifecycle_msgs/msg/Transition id); whether it succeeded."""
        request = ChangeState.Request()
        request.transition.id = transition_id
        return bool(self._call(self._change, request).success)

    def state(self) -> str:
        """The bridge's lifecycle state label."""
        return str(self._call(self._get, GetState.Request()).current_state.label)

    def enable(self) -> Any:
        """Call the bridge's ~/enable."""
        return self._call(self._enable, Trigger.Request())

    def command(self, pivot_a: float) -> None:
        """One current command (pivot only), then one spin."""
        self.currents.publish(Float64MultiArray(data=[0.0, pivot_a, 0.0, 0.0]))
        self.executor.spin_once(timeout_sec=0.01)


def _rack(bridge: CanBridgeNode) -> VirtualDriveRack:
    rack = bridge.rack
    assert rack is not None, "no rack: the bridge is not configured"
    return rack


def _powers(bridge: CanBridgeNode) -> dict[str, PowerState]:
    return {j: _rack(bridge).power_state(j) for j in JOINTS}


def _pivot_q(bridge: CanBridgeNode) -> float:
    rack = _rack(bridge)
    return float(rack.plant_state().position[rack.axis_names.index("pivot")])


def _cycles_pass(bridge: CanBridgeNode, manager: Manager, n: int, pivot_a: float) -> None:
    """Command (and spin) until the bridge has run `n` more bus cycles."""
    master = bridge.bridge
    until = master.counters.cycles + n
    support.wait_until(
        lambda: master.counters.cycles >= until,
        f"{n} bus cycles",
        30.0,
        step=lambda: manager.command(pivot_a),
    )


def test_configure_activate_deactivate_cleanup_through_the_lifecycle_services() -> None:
    """Each transition does what it says to the drives on the bus, and nothing more."""
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor)
        manager = Manager(ctx, executor)
        probe = Diagnostics(ctx, executor)
        try:
            # Unconfigured: no bus, no rack, and /diagnostics says why.
            assert manager.state() == "unconfigured"
            assert bridge.master is None and bridge.rack is None
            probe.wait_for(BRIDGE, OK, "unconfigured")

            # configure: the drives are configured over SDO and OPERATIONAL, not enabled.
            assert manager.set(Transition.TRANSITION_CONFIGURE)
            assert manager.state() == "inactive"
            rack = _rack(bridge)
            master = bridge.master
            assert master is not None
            for joint in JOINTS:  # each drive's own answer, over SDO
                assert master.sdo_read(joint, od.MODES_OF_OPERATION, 0) == MODE_CST
                assert master.sdo_read(joint, od.CYCLE_PERIOD, 0) == round(1e6 / CYCLE_HZ)
                assert rack.nmt_state(joint) == "OPERATIONAL"
            _cycles_pass(bridge, manager, 50, PIVOT_A)  # commands sent: to be ignored
            assert set(_powers(bridge).values()) <= TORQUE_FREE, _powers(bridge)
            assert manager.joint_states == []  # an inactive node publishes no states
            assert not manager.enable().success  # nor enables on request
            status = probe.wait_for(BRIDGE, OK, "inactive")
            assert int(probe.value(BRIDGE, "commands_ignored_inactive")) > 0
            assert status.message.startswith("inactive")

            # activate: enabled, states published, and a current command moves the pivot.
            assert manager.set(Transition.TRANSITION_ACTIVATE)
            assert manager.state() == "active"
            support.wait_until(
                lambda: all(p is PowerState.OPERATION_ENABLED for p in _powers(bridge).values()),
                "every drive operation enabled",
                30.0,
                step=lambda: manager.command(PIVOT_A),
            )
            start_q = _pivot_q(bridge)
            support.wait_until(
                lambda: abs(_pivot_q(bridge) - start_q) > 0.01,
                f"the pivot turned by {PIVOT_A} A",
                30.0,
                step=lambda: manager.command(PIVOT_A),
            )
            assert manager.joint_states, "no joint_states while active"

            # deactivate: out of operation, no torque, the pivot stops; commands ignored.
            assert manager.set(Transition.TRANSITION_DEACTIVATE)
            assert manager.state() == "inactive"
            support.wait_until(
                lambda: set(_powers(bridge).values()) <= TORQUE_FREE,
                "every drive out of operation",
                30.0,
                step=lambda: manager.command(PIVOT_A),
            )
            _cycles_pass(bridge, manager, 50, PIVOT_A)
            assert abs(bridge.bridge.axis_state("pivot").current_a) < 0.05
            assert abs(rack.plant_state().velocity[rack.axis_names.index("pivot")]) < 1e-3
            assert bridge.bridge.latched_reason() == ""  # no silence watch fired meanwhile

            # cleanup: the master's bus is closed, the rack stopped, the bus quiet.
            network = bridge.network
            assert network is not None and network.bus is not None
            bus = network.bus
            assert manager.set(Transition.TRANSITION_CLEANUP)
            assert manager.state() == "unconfigured"
            assert bridge.master is None and bridge.rack is None
            try:
                bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
            except can.CanOperationError:
                pass
            else:
                raise AssertionError("the bridge's bus still sends after cleanup")
            probe.wait_for(BRIDGE, OK, "unconfigured")
        finally:
            bridge.destroy_node()
            manager.node.destroy_node()  # type: ignore[no-untyped-call]
            probe.node.destroy_node()  # type: ignore[no-untyped-call]


def test_shutdown_leaves_the_drives_torque_free_before_the_bus_closes() -> None:
    """Active -> shutdown: every drive out of operation, no watchdog fault, finalized."""
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor)
        manager = Manager(ctx, executor)
        try:
            assert manager.set(Transition.TRANSITION_CONFIGURE)
            assert manager.set(Transition.TRANSITION_ACTIVATE)
            support.wait_until(
                lambda: all(p is PowerState.OPERATION_ENABLED for p in _powers(bridge).values()),
                "every drive operation enabled",
                30.0,
                step=lambda: manager.command(PIVOT_A),
            )
            rack = _rack(bridge)
            assert manager.set(Transition.TRANSITION_ACTIVE_SHUTDOWN)
            assert manager.state() == "finalized"
            assert bridge.master is None
            powers = {j: rack.power_state(j) for j in JOINTS}
            assert set(powers.values()) <= TORQUE_FREE, powers
            assert rack.faults == dict.fromkeys(JOINTS, 0)
        finally:
            bridge.destroy_node()
            manager.node.destroy_node()  # type: ignore[no-untyped-call]


def test_a_plain_start_comes_up_active_with_the_drives_enabled() -> None:
    """With autostart (the default): configure and activate at start-up, as before the lifecycle."""
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, autostart=True)
        manager = Manager(ctx, executor)
        try:
            assert manager.state() == "active"
            support.wait_until(
                lambda: all(p is PowerState.OPERATION_ENABLED for p in _powers(bridge).values()),
                "every drive operation enabled",
                30.0,
                step=lambda: manager.command(0.0),
            )
            spin_until(executor, lambda: bool(manager.joint_states), "joint_states", 30.0)
        finally:
            bridge.destroy_node()
            manager.node.destroy_node()  # type: ignore[no-untyped-call]


def test_a_failed_configure_shows_on_diagnostics_and_leaves_no_bus_open() -> None:
    """A drive that does not answer (node 5): configure fails, unconfigured, ERROR with why."""
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, node_ids=[1, 2, 3, 5])
        manager = Manager(ctx, executor)
        probe = Diagnostics(ctx, executor)
        try:
            assert not manager.set(Transition.TRANSITION_CONFIGURE)
            assert manager.state() == "unconfigured"
            assert bridge.master is None and bridge.rack is None
            status = probe.wait_for(BRIDGE, ERROR, "configure failed: init failed: drive lift")
            assert "node 5" in status.message
        finally:
            bridge.destroy_node()
            manager.node.destroy_node()  # type: ignore[no-untyped-call]
            probe.node.destroy_node()  # type: ignore[no-untyped-call]


def test_a_publish_that_waits_in_dds_is_counted_and_said_with_its_length(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A state publish that takes 150 ms shows on /diagnostics with its length.

    Fast DDS's write waits so while a newly joined peer's shared-memory port is checked
    (docs/can-transport.md, "The 331 ms stall"). The stand-in for the waiting write holds the
    cycle thread once for 150 ms, as the real one did (with the GIL): beyond the 100 ms RPDO
    deadline of the shipped parameters. The drives of `virtual` run in the bridge's process
    and stand still with it, so the stall is said at INFO, not as a WARN that a deadline of
    theirs was passed (a CI run's healthy-run test failed on that WARN after a 102 ms stall).
    """
    caplog.set_level(logging.INFO, logger="lca_sim.canbus.master_watch")
    with ros_context() as (ctx, executor):
        bridge = _bridge(ctx, executor, autostart=True, rpdo_deadline_ms=100)
        diagnostics = Diagnostics(ctx, executor)
        publish = bridge._plant.publish_values
        held = {"calls": 0}

        def waiting_publish(*args: Any) -> None:
            held["calls"] += 1
            if held["calls"] == 50:  # the cycle thread waits in the write, as in Fast DDS
                until_s = time.monotonic() + 0.15
                while time.monotonic() < until_s:
                    pass
            publish(*args)

        bridge._plant.publish_values = waiting_publish  # type: ignore[method-assign,assignment]
        try:
            spin_until(executor, lambda: held["calls"] > 50, "the held publish", 30.0)
            diagnostics.clear()
            spin_until(executor, lambda: BRIDGE in diagnostics.latest, "a report after it", 30.0)
            slow = int(diagnostics.value(BRIDGE, "slow_publishes"))
            longest_ms = int(diagnostics.value(BRIDGE, "longest_publish_ms"))
            publish_deadline_s = bridge._slow_publishes.deadline_s  # INFO at any length
        finally:
            bridge.destroy_node()
            diagnostics.node.destroy_node()  # type: ignore[no-untyped-call]
    assert slow >= 1
    assert 150 <= longest_ms < 1000, longest_ms
    said = [(r.levelno, r.getMessage()) for r in caplog.records if "stood still" in r.getMessage()]
    assert any("the drives run in this process and stood still with it" in m for _, m in said)
    assert {level for level, _ in said} == {logging.INFO}, said
    assert publish_deadline_s == math.inf


def test_slow_calls_say_the_first_and_the_first_beyond_the_deadline() -> None:
    """The log policy of slow publishes: fast ones nothing, then INFO, WARNING, then counted."""
    slow = SlowCalls("publishing", 0.1, "why")
    assert slow.took(0.002) is None  # under FREEZE_THRESHOLD_S: not slow
    assert slow.took(0.03) == (
        logging.INFO,
        "publishing took 30 ms: why (further slow ones are only counted)",
    )
    assert slow.took(0.05) is None  # counted only
    said = slow.took(0.33)
    assert said is not None and said[0] == logging.WARNING
    assert "330 ms, longer than the deadline (0.1 s)" in said[1]
    assert slow.took(0.4) is None
    assert (slow.count, slow.longest_s) == (4, 0.4)
