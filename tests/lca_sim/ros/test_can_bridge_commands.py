"""The bridge's polled command intake: taken by the cycle, with the time rmw received each.

In real time `BridgeCommands` subscribes without registering with the bridge node, so no
executor takes from it, and the master's cycle thread takes what came before each SYNC
(`poll`). These tests run it against a recording master on a real rclpy context: the executor
never takes a command, `poll` takes every one in order with a receipt time between its
publication and the poll, and a poll after the subscriptions are destroyed takes nothing (the
cycle thread may still be running then).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import pytest
import support
from std_msgs.msg import Float64MultiArray

from lca_control import contract as pc
from lca_sim.config.can_bridge_params import CAN_BRIDGE_PARAMETERS, validate_can_bridge_params
from lca_sim.config.loader import load_robot
from lca_sim.ros.can_bridge_commands import BridgeCommands
from lca_sim.ros.node_util import make_executor
from lca_sim.ros.plant_contract import qos_profile

ros_context = support.domain_contexts(110, 3)
COMMANDS = 5


@dataclass
class RecordingMaster:
    """Takes current commands as `Cia402Master.set_currents` does, and keeps them."""

    taken: list[tuple[list[float], float | None]] = field(default_factory=list)

    def set_currents(self, currents_a: list[float], at: float | None = None) -> str | None:
        """Keep the command and its receipt time; refuse nothing."""
        self.taken.append((list(currents_a), at))
        return None


@contextmanager
def _polled_bridge(
    ctx: Any, *, active: bool = True
) -> Iterator[tuple[Any, RecordingMaster, BridgeCommands]]:
    """A node named can_bridge with polled `BridgeCommands` on a recording master, torn down."""
    import rclpy

    bridge = rclpy.create_node("can_bridge", context=ctx)
    master = RecordingMaster()
    p = validate_can_bridge_params(CAN_BRIDGE_PARAMETERS.defaults())
    drives: Any = SimpleNamespace(master=master, loop=None)
    commands = BridgeCommands(
        bridge,
        p,
        load_robot(p.robot),
        drives,
        lambda: active,
        lambda: "active" if active else "inactive",
        polled=True,
    )
    try:
        yield bridge, master, commands
    finally:
        commands.destroy()
        bridge.destroy_node()  # type: ignore[no-untyped-call]


def _publish_and_wait(
    ctx: Any, executor: Any, count: int
) -> tuple[float, list[list[float]], Any, Any]:
    """Publish `count` commands once matched; return when a spy in the test has them all."""
    import rclpy

    talker = rclpy.create_node("talker", context=ctx)
    seen: list[list[float]] = []

    def spy(msg: Float64MultiArray) -> None:
        seen.append(list(msg.data))

    talker.create_subscription(
        Float64MultiArray, pc.CURRENT_COMMANDS, spy, qos_profile(pc.COMMAND_QOS)
    )
    executor.add_node(talker)
    pub = talker.create_publisher(
        Float64MultiArray, pc.CURRENT_COMMANDS, qos_profile(pc.COMMAND_QOS)
    )
    # The bridge's polled reader and the spy: two readers matched before the first message.
    support.spin_until(executor, lambda: pub.get_subscription_count() >= 2, "both readers")
    published_s = time.monotonic()
    for k in range(count):
        pub.publish(Float64MultiArray(data=[float(k), 0.5, -0.25, 0.0]))
    support.spin_until(executor, lambda: len(seen) == count, "the spy has every command")
    return published_s, seen, talker, pub


@pytest.mark.parametrize("kind", ["events", "single"])
def test_the_executor_never_takes_a_polled_command_and_poll_takes_each_with_its_receipt(
    kind: str,
) -> None:
    """Spinning the bridge's executor hands nothing on; one poll hands on all, in order.

    The subscription is the bridge node's in the graph. Each command carries the monotonic
    time rmw received it: not before it was published, not after the poll (the master judges
    in time or late by it).
    """
    with ros_context() as (ctx, executor), _polled_bridge(ctx) as (bridge, master, commands):
        bridge_executor = make_executor(ctx, kind)
        bridge_executor.add_node(bridge)
        published_s, seen, talker, _pub = _publish_and_wait(ctx, executor, COMMANDS)
        subscribed = talker.get_subscriptions_info_by_topic(pc.CURRENT_COMMANDS)
        assert "can_bridge" in {info.node_name for info in subscribed}
        for _ in range(20):  # the executor runs: it must not take the polled commands
            bridge_executor.spin_once(timeout_sec=0.01)
        assert master.taken == []
        support.wait_until(lambda: len(master.taken) == COMMANDS, "poll", step=commands.poll)
        polled_s = time.monotonic()
        assert [values for values, _ in master.taken] == seen
        for _, at in master.taken:
            assert at is not None
            assert published_s - 1e-3 <= at <= polled_s, (published_s, at, polled_s)
        assert commands.taken[pc.CURRENT_COMMANDS] == COMMANDS
        commands.poll()  # nothing new: nothing handed on again
        assert len(master.taken) == COMMANDS
        bridge_executor.shutdown()


def test_commands_while_inactive_are_counted_when_polled() -> None:
    """Inactive: a poll counts each command as ignored, none reaches the master."""
    with (
        ros_context() as (ctx, executor),
        _polled_bridge(ctx, active=False) as (_bridge, master, commands),
    ):
        _publish_and_wait(ctx, executor, COMMANDS)
        support.wait_until(
            lambda: commands.ignored_inactive == COMMANDS,
            "every command counted as ignored",
            step=commands.poll,
        )
        assert master.taken == []


def test_a_poll_after_destroy_hands_on_nothing_and_raises_nothing() -> None:
    """The cycle thread may poll once more while the node is torn down.

    Commands are waiting when the subscriptions go: the poll after must not take them.
    """
    with ros_context() as (ctx, executor), _polled_bridge(ctx) as (_bridge, master, commands):
        _publish_and_wait(ctx, executor, COMMANDS)
        commands.destroy()
        commands.poll()
        assert master.taken == []
        assert commands.taken[pc.CURRENT_COMMANDS] == 0


def test_a_topic_nobody_publishes_is_not_asked_and_is_drained_when_its_publisher_goes() -> None:
    """voltage_commands: asked only while it has a publisher, then once more after the last.

    A take costs about 20 us of the 500 Hz cycle on the 2-core host; nothing publishes
    voltage_commands to a CAN bridge unless a controller is misconfigured, and then each of its
    commands is still counted and warned about, including the ones it sent just before it
    went (drained at the first poll after its publisher left).
    """
    import rclpy

    with ros_context() as (ctx, executor), _polled_bridge(ctx) as (bridge, _master, commands):
        bridge_executor = make_executor(ctx, "single")  # handles the matched events
        bridge_executor.add_node(bridge)
        for _ in range(5):
            commands.poll()
        # the first poll drained each topic once; no topic has a publisher: none asked since
        topics = 3  # current_commands, voltage_commands, the JointState command topic (cst)
        assert commands.unpublished_skips == 4 * topics
        talker = rclpy.create_node("voltage_talker", context=ctx)
        spied: list[Float64MultiArray] = []
        spy = rclpy.create_node("voltage_spy", context=ctx)  # its readers see what the bridge's do
        spy.create_subscription(
            Float64MultiArray, pc.VOLTAGE_COMMANDS, spied.append, qos_profile(pc.COMMAND_QOS)
        )
        executor.add_node(talker)
        executor.add_node(spy)
        pub = talker.create_publisher(
            Float64MultiArray, pc.VOLTAGE_COMMANDS, qos_profile(pc.COMMAND_QOS)
        )
        support.spin_until(executor, lambda: pub.get_subscription_count() >= 2, "both readers")

        def skipped_in_one_poll() -> int:
            before = commands.unpublished_skips
            commands.poll()
            return commands.unpublished_skips - before

        support.spin_until(
            bridge_executor,
            lambda: skipped_in_one_poll() == topics - 1,
            "the bridge sees the publisher (its matched event); the other topics still skipped",
        )
        for k in range(3):
            pub.publish(Float64MultiArray(data=[float(k)] * 4))

        def voltage_commands_after_a_poll() -> int:
            commands.poll()
            return commands.wrong_interface

        support.spin_until(
            bridge_executor,
            lambda: voltage_commands_after_a_poll() == 3,
            "each voltage command counted",
        )
        for k in range(2):  # sent, then the publisher goes before the bridge polls
            pub.publish(Float64MultiArray(data=[float(k)] * 4))
        support.spin_until(executor, lambda: len(spied) == 5, "the spy has all five")
        talker.destroy_publisher(pub)
        support.spin_until(
            bridge_executor,
            lambda: commands.publisher_counts()["/" + pc.VOLTAGE_COMMANDS] == 0,
            "the bridge sees the publisher gone (no poll meanwhile)",
        )
        assert commands.wrong_interface == 3
        assert skipped_in_one_poll() == topics - 1  # the one drain after the last publisher
        assert commands.wrong_interface == 5  # the two sent before it went
        assert skipped_in_one_poll() == topics  # and not asked again
        talker.destroy_node()  # type: ignore[no-untyped-call]
        spy.destroy_node()  # type: ignore[no-untyped-call]
        bridge_executor.shutdown()


@dataclass
class RecordingLog:
    """The logger calls `BridgeCommands` makes: (level, message)."""

    lines: list[tuple[str, str]] = field(default_factory=list)

    def info(self, message: str, **_kwargs: Any) -> None:
        """Keep an INFO line (rclpy's `once` and throttling are not applied)."""
        self.lines.append(("info", message))

    def warning(self, message: str, **_kwargs: Any) -> None:
        """Keep a WARN line."""
        self.lines.append(("warning", message))


def test_a_command_while_the_active_node_shuts_down_is_no_warning() -> None:
    """The master gone under an active node (its shutdown): counted, said once at INFO.

    It used to warn "ignoring commands while active ...: activate the node" on Ctrl-C.
    """
    with ros_context() as (ctx, _executor), _polled_bridge(ctx) as (_bridge, _master, commands):
        log = RecordingLog()
        commands._log = log
        commands._drives.master = None  # torn down, the lifecycle still says active
        for _ in range(3):
            commands._on_current([0.0] * 4, None)
        assert commands.ignored_inactive == 3
        assert [level for level, _ in log.lines] == ["info"] * 3, log.lines  # rclpy's once=True
        assert "shutting down" in log.lines[0][1]
