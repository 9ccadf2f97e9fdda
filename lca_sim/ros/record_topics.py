"""Which topics `lca-record` subscribes, with which QoS, and how it follows the ROS graph.

`TopicSubscriber`, the subscription part of `lca_sim.ros.record.BagRecorder`:

* named topics are resolved as any topic of the node (namespace, remappings) and waited for up
  to `--wait-s` each; one whose type has not appeared by then is dropped with a warning;
* `--all` records every topic that exists or appears later, except hidden ones and `/rosout`
  and `/parameter_events` (name those to record them); a topic of several types is recorded
  with the first;
* QoS: reliable, keep-last `--depth`, best-effort when a publisher is (`/clock` before any is
  known), transient-local when every publisher offers it (`subscription_qos`); a topic
  subscribed before its publishers existed, or joined by a best-effort publisher, is
  resubscribed to match them (`TopicSubscriber._adapt_qos`).
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription
from rclpy.topic_endpoint_info import TopicEndpointInfo
from rosbags.interfaces import Connection

from lca_control.contract import CLOCK, STATE_QOS_DEPTH
from lca_sim.ros.record_bag import BagFile, RecorderError

# Recorded by --all only when named: every node publishes them, the recorder itself included.
INFRASTRUCTURE_TOPICS = frozenset({"/rosout", "/parameter_events"})


def import_message_class(msgtype: str) -> type[Any]:
    """The Python class of a ROS message type string such as `sensor_msgs/msg/JointState`.

    Raises:
        RecorderError: The string is malformed or its package is not installed.
    """
    parts = msgtype.split("/")
    if len(parts) == 2:  # the short form pkg/Type
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise RecorderError(f"malformed message type {msgtype!r}; expected pkg/msg/Type")
    package, kind, name = parts
    try:
        module = importlib.import_module(f"{package}.{kind}")
        cls = getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise RecorderError(f"message type {msgtype} is not installed: {exc}") from None
    if not isinstance(cls, type) or not hasattr(cls, "get_fields_and_field_types"):
        raise RecorderError(f"{msgtype} is not a ROS message class")
    return cls


def subscription_qos(
    topic: str, publishers: Sequence[TopicEndpointInfo], depth: int = STATE_QOS_DEPTH
) -> QoSProfile:
    """The QoS to subscribe `topic` with so that it matches all its `publishers`.

    Reliable unless a publisher is best-effort (or the topic is `/clock` and none is known yet);
    transient-local only when every publisher offers it; keep-last `depth`.
    """
    reliabilities = [p.qos_profile.reliability for p in publishers]
    best_effort = ReliabilityPolicy.BEST_EFFORT in reliabilities or (
        topic == CLOCK and not publishers
    )
    latched = bool(publishers) and all(
        p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers
    )
    return QoSProfile(  # type: ignore[no-untyped-call]  # rclpy leaves __init__ unannotated
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def is_hidden_topic(topic: str) -> bool:
    """True for a hidden topic: one of its name tokens starts with an underscore."""
    return any(token.startswith("_") for token in topic.split("/"))


@dataclass
class RecordedTopic:
    """One recorded topic: its bag connection, live subscription and message count."""

    topic: str
    msgtype: str
    msg_class: type[Any]
    connection: Connection
    qos: QoSProfile
    publishers_known: bool  # False: the QoS was chosen before any publisher was seen
    subscription: Subscription | None = None
    count: int = 0  # written to the bag (under the bag's lock)
    matched: bool = False  # the subscription has matched a publisher (noted once)


@dataclass
class _Waiting:
    """A named topic whose type has not appeared in the graph yet."""

    topic: str
    since_s: float = field(default_factory=time.monotonic)


class TopicSubscriber:
    """The topics recorded, waited for and given up, and their raw subscriptions.

    Args:
        node: the node to subscribe with; its clock stamps the messages.
        bag: where the messages go.
        named: the fully qualified topics asked for.
        record_all: also record every other non-hidden topic, including ones appearing later.
        wait_s: how long to wait for a named topic's type before dropping it (inf: forever).
        depth: keep-last depth of the subscriptions.
        log: where warnings go.
        note: where the one-line "recording <topic>" notes go.
    """

    def __init__(
        self,
        node: Node,
        bag: BagFile,
        named: Sequence[str],
        *,
        record_all: bool,
        wait_s: float,
        depth: int,
        log: Callable[[str], None],
        note: Callable[[str], None],
    ) -> None:
        self._node = node
        self._bag = bag
        self._clock = node.get_clock()
        self._named = list(named)
        self.record_all = record_all
        self._wait_s = wait_s
        self._depth = depth
        self._log = log
        self._note = note
        self.recorded: dict[str, RecordedTopic] = {}  # changed under the bag's lock
        self._skipped: set[str] = set()  # seen by --all but unrecordable (warned once)
        self.waiting: dict[str, _Waiting] = {}
        self.dropped: list[str] = []

    def start_waiting(self) -> None:
        """Start the wait for every named topic (from now)."""
        self.waiting = {name: _Waiting(name) for name in self._named}

    def poll_graph(self) -> None:
        """Subscribe to newly appeared topics, adapt QoS and give up on overdue named topics."""
        types = dict(self._node.get_topic_names_and_types())
        self._poll_waiting(types)
        if self.record_all:
            self._subscribe_appeared(types)
        for rec in self.recorded.values():
            self._adapt_qos(rec)
            self._note_if_matched(rec)

    def unsubscribe(self) -> None:
        """Destroy every subscription (recording stops)."""
        for rec in self.recorded.values():
            if rec.subscription is not None:
                self._node.destroy_subscription(rec.subscription)
                rec.subscription = None

    def _poll_waiting(self, types: dict[str, list[str]]) -> None:
        """Subscribe to the named topics whose type appeared; drop those overdue after wait_s."""
        for name in list(self.waiting):
            if types.get(name):
                del self.waiting[name]
                self._subscribe(name, types[name], named=True)
            elif time.monotonic() - self.waiting[name].since_s > self._wait_s:
                del self.waiting[name]
                self.dropped.append(name)
                self._log(f"no publisher or type for {name} after {self._wait_s:g} s; skipped")

    def _subscribe_appeared(self, types: dict[str, list[str]]) -> None:
        """For --all: subscribe to every topic with a type that is not handled already."""
        for name, type_names in types.items():
            if self._new_for_all(name) and type_names:
                self._subscribe(name, type_names, named=False)

    def _new_for_all(self, name: str) -> bool:
        """Neither recorded, skipped nor waited for, and not a topic --all leaves out."""
        return not (
            name in self.recorded
            or name in self._skipped
            or name in self.waiting
            or name in INFRASTRUCTURE_TOPICS
            or is_hidden_topic(name)
        )

    def _note_if_matched(self, rec: RecordedTopic) -> None:
        """Note a recorded topic once its subscription has matched a publisher."""
        if rec.matched or rec.subscription is None:
            return
        n_publishers = rec.subscription.get_publisher_count()
        if n_publishers > 0:
            rec.matched = True
            plural = "s" if n_publishers > 1 else ""
            self._note(f"recording {rec.topic} ({rec.msgtype}, {n_publishers} publisher{plural})")

    def _subscribe(self, topic: str, type_names: list[str], *, named: bool) -> None:
        msgtype = type_names[0]
        if len(type_names) > 1:
            self._log(f"{topic} has several types {type_names}; recording {msgtype}")
        try:
            msg_class = import_message_class(msgtype)
            if msgtype not in self._bag.typestore.types:
                raise RecorderError(f"{msgtype} is not in the ROS 2 Jazzy typestore")
        except RecorderError as exc:
            self._log(f"cannot record {topic}: {exc}")
            if named:
                self.dropped.append(topic)
            else:
                self._skipped.add(topic)
            return
        publishers = self._node.get_publishers_info_by_topic(topic)
        qos = subscription_qos(topic, publishers, self._depth)
        connection = self._bag.add_connection(topic, msgtype, [p.qos_profile for p in publishers])
        rec = RecordedTopic(
            topic=topic,
            msgtype=msgtype,
            msg_class=msg_class,
            connection=connection,
            qos=qos,
            publishers_known=bool(publishers),
        )
        rec.subscription = self._create_subscription(rec, qos)
        with self._bag.lock:  # the counts may be read from another thread
            self.recorded[topic] = rec

    def _adapt_qos(self, rec: RecordedTopic) -> None:
        """Resubscribe when the publishers need another QoS than the subscription has.

        Two cases: the QoS was a guess made before any publisher was known (settled once, when
        the first publishers appear; the durability only while nothing was recorded, since a
        transient-local subscription would get the publisher's history again), or a best-effort
        publisher joined a topic subscribed reliable (which would receive nothing from it). The
        new subscription is created before the old one is destroyed, so the switch loses
        nothing (a message in flight may be recorded twice). Settling the guess is the normal
        start (a note: `/clock` is guessed best-effort before its publisher is known); a
        best-effort publisher joining later is a warning, since its messages before the
        switch were not received.
        """
        if rec.subscription is None:
            return
        publishers = self._node.get_publishers_info_by_topic(rec.topic)
        if not publishers:
            return
        wanted = subscription_qos(rec.topic, publishers, self._depth)
        first_publishers = not rec.publishers_known
        rec.publishers_known = True
        reliability_changed = wanted.reliability != rec.qos.reliability
        if first_publishers:
            durability_changed = wanted.durability != rec.qos.durability and rec.count == 0
            if not (reliability_changed or durability_changed):
                return
        elif not (reliability_changed and wanted.reliability == ReliabilityPolicy.BEST_EFFORT):
            return
        say = self._note if first_publishers else self._log
        say(
            f"{rec.topic}: resubscribing {wanted.reliability.name.lower()}/"
            f"{wanted.durability.name.lower()} to match its publishers"
        )
        old = rec.subscription
        rec.qos = wanted
        rec.matched = False  # noted again once the new subscription has matched
        rec.subscription = self._create_subscription(rec, wanted)
        self._node.destroy_subscription(old)

    def _create_subscription(self, rec: RecordedTopic, qos: QoSProfile) -> Subscription:
        clock = self._clock
        bag = self._bag

        def on_message(data: bytes) -> None:
            stamp_ns = clock.now().nanoseconds
            with bag.lock:
                if bag.write_locked(rec.connection, stamp_ns, data):
                    rec.count += 1

        # raw=True hands the callback the serialized bytes; rclpy types it for messages.
        callback = cast("Callable[[Any], None]", on_message)
        return self._node.create_subscription(rec.msg_class, rec.topic, callback, qos, raw=True)
