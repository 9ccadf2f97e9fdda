"""`lca-record`: record ROS 2 topics to a rosbag2 MCAP bag, the message bytes as they arrive.

    lca-record joint_states motor_states drive_chain_states -o out/run1
    lca-record --all --max-duration-s 60 -o out/run2 --ros-args -p use_sim_time:=true

Each topic's type is read from the ROS graph and the topic is subscribed *raw*: the serialized
CDR bytes are written to the bag unchanged (no deserialization). Every message is stamped with
the recorder node's clock at reception, so `use_sim_time:=true` records simulated time. The bag
is rosbag2 version 9 with MCAP storage, written by `rosbags`, with the message definitions and
type hashes (RIHS01) of the ROS 2 Jazzy typestore, as `ros2 bag record` writes them.

Topics:

* Named topics are resolved like any topic of the node (relative names get the namespace; ros
  args remappings apply) and waited for up to `--wait-s` seconds each; a topic whose type has not
  appeared by then is dropped with a warning and the others are still recorded.
* `--all` records every topic that exists or appears later, except hidden ones and the
  infrastructure topics `/rosout` and `/parameter_events` (name those to record them).
* A topic with more than one type is recorded with the first and a warning.

QoS: reliable, keep-last `STATE_QOS_DEPTH` (the project's state QoS; `--depth` to change); if
any publisher on the topic is best-effort (as `/clock` publishers often are), the subscription
is best-effort so it matches them (a reliable subscription receives nothing from a best-effort
publisher). `/clock` with no publisher yet is subscribed best-effort, which matches either kind.
The durability is transient-local when every publisher offers it, so latched messages are kept.
A topic subscribed before any publisher existed (its type came from a subscription) gets its
QoS settled when the first publishers appear, and a best-effort publisher joining a topic
subscribed reliable makes the recorder resubscribe best-effort.

Output: one line `lca-record: recording <topic> (<type>, <n> publishers)` on stderr per topic
once its subscription has matched a publisher: from then on nothing that topic publishes is
lost. (A publisher that sees the recorder in `get_subscription_count()` is *not* enough: DDS
matching is two-sided, and messages sent before the recorder's side has matched are dropped by
its volatile subscription.) `--verbose` adds the counts every second.

Crash safety: a recorder killed with SIGKILL loses at most `--flush-period-s` (default 0.25 s)
of what it had received. The writer closes the open MCAP chunk and flushes it to the file every
`FLUSH_SHARE` (0.4) of that bound, 0.1 s by default: at the first message after that interval,
and from a steady-clock timer of the same interval when messages stop. What was received just
after a flush is thus on disk one interval later plus the delay of the callback or timer that
flushes it, and the rest of the bound (0.15 s by default) is left for that delay on a loaded
machine. (A flush every full bound would lose the bound plus that delay.) Such a bag has no
summary, footer or metadata.yaml; `lca-record --recover BAG` (`lca_sim.ros.bag_recover`, no ROS
needed) rewrites it from its complete chunks as a standard MCAP file with a fresh
metadata.yaml. Tested on a recovered bag: rosbags' reader and lca-plot's (`read_bag`); lca-echo
reads live topics, not bags, and the `mcap` package's readers are not installed here, so not
tried. Without the periodic flush rosbags closes a chunk only at 1 MiB and buffers the file,
and a killed recording lost everything after the last full chunk.

Stopping: SIGINT (Ctrl-C), SIGTERM or `--max-duration-s`. The recorder then takes the messages
already received by the middleware, closes the bag (metadata.yaml is written) and prints the
number of messages per topic. Exit codes (from `lca_sim.errors`): 0 stopped normally (also on a
signal), 2 bad arguments, an existing output folder, or none of the named topics could be
recorded (did not appear within `--wait-s`, or an unknown type); errors are one line on stderr.

Embedding (the recorder shares a node and its executor; nothing here spins)::

    from lca_sim.ros.record import BagRecorder

    recorder = BagRecorder(node, "out/run1", topics=["joint_states", "drive_chain_states"])
    recorder.start()          # opens the bag, subscribes to what the graph has, polls for more
    ...                       # spin the node's executor as usual
    counts = recorder.close() # {"/joint_states": 4000, ...}; the bag is complete after this

`BagRecorder.counts` gives the messages written so far per topic, `BagRecorder.matched` the
topics whose subscription has matched a publisher (wait for these before publishing what must
be recorded), `BagRecorder.waiting` the named topics still waited for and
`BagRecorder.dropped` those given up. Writing happens in the subscription callback under a
lock, so a multi-threaded executor is safe too.

Throughput: a write costs about 5 us per message (rosbags MCAP writer; measured with 172-byte
JointState messages) and the node-clock stamp another 5 us, small beside the executor's own cost
per callback, so the callback writes directly instead of handing the bytes to a writer thread.
The console script spins rclpy's C++ events executor when it is available (`--executor`): about
110 us of CPU per message in all against 250 us with SingleThreadedExecutor. A recorder starved
of CPU for longer than `STATE_QOS_DEPTH` messages of a topic still loses the oldest of them
(keep-last): give it a core at high rates.

Typing note: rclpy ships py.typed but leaves a few functions unannotated (QoSProfile.__init__,
Node.get_logger, Node.destroy_node), so this module needs `disallow_untyped_calls = false` (the
ROS-shell override in pyproject.toml); rclpy types subscription callbacks for messages, not the
bytes of a raw subscription, hence one cast.
"""

from __future__ import annotations

import argparse
import importlib
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from types import FrameType
from typing import Any, cast

import rclpy
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.context import Context
from rclpy.executors import Executor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from rclpy.topic_endpoint_info import TopicEndpointInfo
from rclpy.utilities import remove_ros_args
from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.rosbag2.storage_mcap import McapWriter
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from lca_control.contract import CLOCK, STATE_QOS_DEPTH
from lca_sim.errors import EXIT_BAD_INPUT, EXIT_OK, LcaHilError
from lca_sim.ros.bag_recover import recover_main
from lca_sim.ros.node_util import make_executor
from lca_sim.ros.tool_args import RECORD_FLUSH_PERIOD_S as DEFAULT_MAX_LOSS_S
from lca_sim.ros.tool_args import RECORD_WAIT_S as DEFAULT_WAIT_S
from lca_sim.ros.tool_args import record_parser

NODE_NAME = "lca_record"
# Recorded by --all only when named: every node publishes them, the recorder itself included.
INFRASTRUCTURE_TOPICS = frozenset({"/rosout", "/parameter_events"})
GRAPH_POLL_PERIOD_S = 0.1
REASON_IDLE = "no topic left to record"
# After a stop request: keep taking already-received messages until none came for this long.
DRAIN_QUIET_S = 0.05
DRAIN_MAX_S = 0.5
PROGRESS_PERIOD_S = 1.0
NS_PER_S = 1_000_000_000
# The open chunk is flushed every FLUSH_SHARE of the loss bound; the rest of the bound is left
# for the callback or timer that does it to come late (module doc, "Crash safety").
FLUSH_SHARE = 0.4


class RecorderError(LcaHilError):
    """The recorder cannot start: bad output folder, bad topic name or message type."""


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
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def _qos_time(duration_ns: int) -> QosTime:
    sec, nsec = divmod(duration_ns, NS_PER_S)
    return QosTime(sec=sec, nsec=nsec)


def bag_qos(profile: QoSProfile) -> Qos:
    """A publisher's rclpy QoS profile as the rosbags metadata record (offered_qos_profiles)."""

    def pick(enum_type: Any, name: str) -> Any:
        return enum_type[name] if name in enum_type.__members__ else enum_type.UNKNOWN

    return Qos(
        history=pick(QosHistory, profile.history.name),
        depth=int(profile.depth),
        reliability=pick(QosReliability, profile.reliability.name),
        durability=pick(QosDurability, profile.durability.name),
        deadline=_qos_time(profile.deadline.nanoseconds),
        lifespan=_qos_time(profile.lifespan.nanoseconds),
        liveliness=pick(QosLiveliness, profile.liveliness.name),
        liveliness_lease_duration=_qos_time(profile.liveliness_lease_duration.nanoseconds),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def is_hidden_topic(topic: str) -> bool:
    """True for a hidden topic: one of its name tokens starts with an underscore."""
    return any(token.startswith("_") for token in topic.split("/"))


@dataclass
class _Recorded:
    """One recorded topic: its bag connection, live subscription and message count."""

    topic: str
    msgtype: str
    msg_class: type[Any]
    connection: Connection
    qos: QoSProfile
    publishers_known: bool  # False: the QoS was chosen before any publisher was seen
    subscription: Subscription | None = None
    count: int = 0
    matched: bool = False  # the subscription has matched a publisher (noted once)


@dataclass
class _Waiting:
    """A named topic whose type has not appeared in the graph yet."""

    topic: str
    since_s: float = field(default_factory=time.monotonic)


class BagRecorder:
    """Records topics of a node's ROS graph into a new rosbag2 MCAP bag (see the module doc).

    Args:
        node: The node to subscribe with. Its clock stamps the messages; it must be spun by the
            caller's executor between `start()` and `close()`.
        output: The bag folder to create; it must not exist.
        topics: Topic names to record (relative names are resolved by the node).
        record_all: Also record every other non-hidden topic, including ones appearing later.
        wait_s: How long to wait for a named topic's type before dropping it (inf: forever).
        depth: Keep-last depth of the subscriptions.
        graph_poll_period_s: Period of the graph check for new topics and publishers (steady
            clock, so it runs even while simulated time stands still).
        max_loss_s: The most a killed recorder may lose of what it received, s: the open
            MCAP chunk is closed and flushed every `FLUSH_SHARE` of it (steady clock).
        log: Where warnings go (default: the node's logger at warning level).
        note: Where the one-line "recording <topic>" notes go (default: the node's logger at
            info level). A topic is noted once its subscription has matched a publisher.
    """

    def __init__(
        self,
        node: Node,
        output: Path | str,
        topics: Sequence[str] = (),
        *,
        record_all: bool = False,
        wait_s: float = DEFAULT_WAIT_S,
        depth: int = STATE_QOS_DEPTH,
        graph_poll_period_s: float = GRAPH_POLL_PERIOD_S,
        max_loss_s: float = DEFAULT_MAX_LOSS_S,
        log: Callable[[str], None] | None = None,
        note: Callable[[str], None] | None = None,
    ) -> None:
        self._node = node
        self.output = Path(output)
        self._record_all = record_all
        self._wait_s = wait_s
        self._depth = depth
        self._poll_period_s = graph_poll_period_s
        if not max_loss_s > 0 or math.isinf(max_loss_s):
            raise RecorderError(f"the loss bound must be > 0 and finite, not {max_loss_s}")
        self.max_loss_s = max_loss_s
        self.flush_interval_s = FLUSH_SHARE * max_loss_s
        self._next_flush_s = math.inf
        self._flush_timer: Timer | None = None
        self._log: Callable[[str], None] = log or node.get_logger().warning
        self._note: Callable[[str], None] = note or node.get_logger().info
        self._clock = node.get_clock()
        self._lock = threading.Lock()
        self._typestore: Typestore = get_typestore(Stores.ROS2_JAZZY)
        self._writer: Writer | None = None
        self._timer: Timer | None = None
        self._recorded: dict[str, _Recorded] = {}
        self._skipped: set[str] = set()  # seen by --all but unrecordable (warned once)
        self._waiting: dict[str, _Waiting] = {}
        self._dropped: list[str] = []
        self._closed = False
        try:
            self._named = [node.resolve_topic_name(name) for name in topics]
        except Exception as exc:  # rclpy raises its own validation errors
            raise RecorderError(f"bad topic name: {first_line(exc)}") from None

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far per recorded topic (fully qualified names)."""
        with self._lock:
            return {name: rec.count for name, rec in self._recorded.items()}

    @property
    def total(self) -> int:
        """Messages written so far over all topics."""
        with self._lock:
            return sum(rec.count for rec in self._recorded.values())

    @property
    def waiting(self) -> list[str]:
        """Named topics whose type has not appeared yet."""
        return sorted(self._waiting)

    @property
    def dropped(self) -> list[str]:
        """Named topics given up after `wait_s` (or with a type that cannot be recorded)."""
        return list(self._dropped)

    @property
    def matched(self) -> list[str]:
        """Recorded topics whose subscription has matched at least one publisher.

        Matching is only complete when *both* sides have seen each other: a publisher whose
        `get_subscription_count()` already counts this recorder can still lose its first
        messages to it (a volatile reader drops data from a writer it has not matched yet).
        Wait for a topic to be listed here (checked every graph poll) before publishing
        anything that must be recorded.
        """
        with self._lock:
            return [name for name, rec in self._recorded.items() if rec.matched]

    @property
    def idle(self) -> bool:
        """True when nothing is or can be recorded any more: no topic, none waited for."""
        return not self._record_all and not self._recorded and not self._waiting

    def start(self) -> None:
        """Create the bag, subscribe to the topics already in the graph and start polling.

        Raises:
            RecorderError: The output folder exists or cannot be created.
        """
        if self._writer is not None or self._closed:
            raise RecorderError("BagRecorder.start() called twice")
        try:
            writer = Writer(self.output, version=9, storage_plugin=StoragePlugin.MCAP)
            writer.open()
        except (WriterError, OSError) as exc:
            raise RecorderError(f"cannot create bag {self.output}: {exc}") from None
        if not isinstance(writer.storage, McapWriter):  # the flush uses its chunk interface
            writer.abort()
            raise RecorderError("rosbags' MCAP writer has changed; cannot flush chunks")
        self._writer = writer
        self._next_flush_s = time.monotonic() + self.flush_interval_s
        self._waiting = {name: _Waiting(name) for name in self._named}
        self.poll_graph()
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self._node.create_timer(self._poll_period_s, self.poll_graph, clock=steady)
        self._flush_timer = self._node.create_timer(self.flush_interval_s, self.flush, clock=steady)

    def flush(self) -> None:
        """Close the open MCAP chunk (if it holds anything) and flush the file to the OS.

        What is flushed survives a SIGKILL of the recorder (`lca-record --recover` reads it).
        """
        with self._lock:
            self._flush_locked()

    def _flush_locked(self) -> None:
        writer = self._writer
        if writer is None:
            return
        storage = cast("McapWriter", writer.storage)
        if storage.chunk.bio.tell():
            storage.close_chunk()
        storage.bio.flush()
        self._next_flush_s = time.monotonic() + self.flush_interval_s

    def stop_discovery(self) -> None:
        """Stop looking for new topics (recording of subscribed topics goes on)."""
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
            self._timer = None
        self._waiting.clear()

    def close(self) -> dict[str, int]:
        """Unsubscribe, close the bag (writes metadata.yaml) and return the counts per topic.

        Idempotent. Messages the executor has not yet taken from the middleware are lost: spin
        until they are in (the console script drains for a moment) before closing.
        """
        if self._closed:
            return self.counts
        self.stop_discovery()
        if self._flush_timer is not None:
            self._node.destroy_timer(self._flush_timer)
            self._flush_timer = None
        for rec in self._recorded.values():
            if rec.subscription is not None:
                self._node.destroy_subscription(rec.subscription)
                rec.subscription = None
        with self._lock:
            writer, self._writer = self._writer, None
            self._closed = True
            if writer is not None:
                writer.close()
        return self.counts

    def poll_graph(self) -> None:
        """Subscribe to newly appeared topics, adapt QoS and give up on overdue named topics."""
        if self._writer is None:
            return
        types = dict(self._node.get_topic_names_and_types())
        self._poll_waiting(types)
        if self._record_all:
            self._subscribe_appeared(types)
        for rec in self._recorded.values():
            self._adapt_qos(rec)
            self._note_if_matched(rec)

    def _poll_waiting(self, types: dict[str, list[str]]) -> None:
        """Subscribe to the named topics whose type appeared; drop those overdue after wait_s."""
        for name in list(self._waiting):
            if types.get(name):
                del self._waiting[name]
                self._subscribe(name, types[name], named=True)
            elif time.monotonic() - self._waiting[name].since_s > self._wait_s:
                del self._waiting[name]
                self._dropped.append(name)
                self._log(f"no publisher or type for {name} after {self._wait_s:g} s; skipped")

    def _subscribe_appeared(self, types: dict[str, list[str]]) -> None:
        """For --all: subscribe to every topic with a type that is not handled already."""
        for name, type_names in types.items():
            if self._new_for_all(name) and type_names:
                self._subscribe(name, type_names, named=False)

    def _new_for_all(self, name: str) -> bool:
        """Neither recorded, skipped nor waited for, and not a topic --all leaves out."""
        return not (
            name in self._recorded
            or name in self._skipped
            or name in self._waiting
            or name in INFRASTRUCTURE_TOPICS
            or is_hidden_topic(name)
        )

    def _note_if_matched(self, rec: _Recorded) -> None:
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
            if msgtype not in self._typestore.types:
                raise RecorderError(f"{msgtype} is not in the ROS 2 Jazzy typestore")
        except RecorderError as exc:
            self._log(f"cannot record {topic}: {exc}")
            if named:
                self._dropped.append(topic)
            else:
                self._skipped.add(topic)
            return
        publishers = self._node.get_publishers_info_by_topic(topic)
        qos = subscription_qos(topic, publishers, self._depth)
        assert self._writer is not None
        with self._lock:
            connection = self._writer.add_connection(
                topic,
                msgtype,
                typestore=self._typestore,
                offered_qos_profiles=[bag_qos(p.qos_profile) for p in publishers],
            )
        rec = _Recorded(
            topic=topic,
            msgtype=msgtype,
            msg_class=msg_class,
            connection=connection,
            qos=qos,
            publishers_known=bool(publishers),
        )
        rec.subscription = self._create_subscription(rec, qos)
        with self._lock:  # `counts` may be read from another thread
            self._recorded[topic] = rec

    def _adapt_qos(self, rec: _Recorded) -> None:
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

    def _create_subscription(self, rec: _Recorded, qos: QoSProfile) -> Subscription:
        clock = self._clock
        lock = self._lock

        def on_message(data: bytes) -> None:
            stamp_ns = clock.now().nanoseconds
            with lock:
                writer = self._writer
                if writer is None:
                    return
                writer.write(rec.connection, stamp_ns, data)
                rec.count += 1
                if time.monotonic() >= self._next_flush_s:
                    self._flush_locked()

        # raw=True hands the callback the serialized bytes; rclpy types it for messages.
        callback = cast("Callable[[Any], None]", on_message)
        return self._node.create_subscription(rec.msg_class, rec.topic, callback, qos, raw=True)


def default_output(now: datetime | None = None) -> Path:
    """The default bag folder name, `lca_bag_<YYYYmmdd_HHMMSS>` in the working directory."""
    return Path(f"lca_bag_{(now or datetime.now()).strftime('%Y%m%d_%H%M%S')}")


class _StopFlag:
    """Set by SIGINT/SIGTERM; the spin loop checks it between short waits."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal_name = ""

    def __call__(self, signum: int, _frame: FrameType | None) -> None:
        self.signal_name = signal.Signals(signum).name
        self.event.set()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the lca-record console script."""
    all_args = ["lca-record", *(sys.argv[1:] if argv is None else argv)]
    try:
        own_args = remove_ros_args(all_args)[1:]
    except Exception as exc:  # rclpy's RCLInvalidROSArgsError
        return _fail(f"bad ROS arguments: {first_line(exc)}")
    args = _parse_args(own_args)
    if args.recover is not None:
        return recover_main(own_args)
    output: Path = args.output if args.output is not None else default_output()
    if output.exists():
        return _fail(f"output {output} exists already; not overwriting (choose another -o)")

    stop = _StopFlag()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    context = Context()
    try:
        try:
            rclpy.init(
                args=all_args, context=context, signal_handler_options=SignalHandlerOptions.NO
            )
        except Exception as exc:  # rclpy reports bad ROS arguments with its own exceptions
            return _fail(f"cannot start ROS: {first_line(exc)}")
        run = _record(context, args, output, stop)
    except RecorderError as exc:
        return _fail(str(exc))
    finally:
        if context.ok():
            rclpy.shutdown(context=context)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return _finish(output, run)


def _parse_args(own_args: list[str]) -> argparse.Namespace:
    """The parsed arguments; bad ones exit through `parser.error` (status 2)."""
    parser = record_parser()
    args = parser.parse_args(own_args)
    if args.recover is not None:
        return args  # checked by recover_main
    if not args.topics and not args.all:
        parser.error("name at least one TOPIC or use --all")
    if args.max_duration_s is not None and not args.max_duration_s > 0:
        parser.error("--max-duration-s must be > 0")
    if math.isnan(args.wait_s) or args.wait_s < 0:
        parser.error("--wait-s must be >= 0")
    if args.depth < 1:
        parser.error("--depth must be >= 1")
    if not args.flush_period_s > 0 or math.isinf(args.flush_period_s):
        parser.error("--flush-period-s must be > 0 and finite")
    return args


@dataclass(frozen=True, slots=True)
class _Run:
    """How a recording ended: why, the messages per topic, and the named topics not recorded."""

    reason: str
    counts: dict[str, int]
    never_seen: list[str]  # still waited for when it stopped
    dropped: list[str]  # given up (not appeared within --wait-s, or an unknown type)


def _record(context: Context, args: argparse.Namespace, output: Path, stop: _StopFlag) -> _Run:
    """Record on a node of its own until stopped, then close the bag.

    Raises:
        RecorderError: The bag cannot be created or a topic name is bad.
    """
    node = Node(NODE_NAME, context=context)
    recorder: BagRecorder | None = None
    try:
        recorder = BagRecorder(
            node,
            output,
            args.topics,
            record_all=args.all,
            wait_s=args.wait_s,
            depth=args.depth,
            max_loss_s=args.flush_period_s,
            log=_warn,
            note=_note,
        )
        recorder.start()
        executor = make_executor(context, args.executor)
        executor.add_node(node)
        reason = _spin(executor, recorder, stop, args.max_duration_s, verbose=args.verbose)
        never_seen = recorder.waiting
        recorder.stop_discovery()
        _drain(executor, recorder)
        counts = recorder.close()
        executor.shutdown(timeout_sec=1.0)
    finally:
        if recorder is not None:
            recorder.close()  # idempotent; after an unexpected error it still writes metadata
        node.destroy_node()
    return _Run(reason, counts, never_seen, recorder.dropped)


def _finish(output: Path, run: _Run) -> int:
    """Print the summary and warnings of a finished recording; the exit code."""
    _print_summary(output, run.counts, run.reason)
    if run.never_seen:
        _warn(f"stopped while still waiting for {', '.join(run.never_seen)}")
    if run.reason == REASON_IDLE:
        dropped = ", ".join(run.dropped)
        return _fail(f"could not record {dropped}; {output} is empty")
    return EXIT_OK


def _spin(
    executor: Executor,
    recorder: BagRecorder,
    stop: _StopFlag,
    max_duration_s: float | None,
    *,
    verbose: bool,
) -> str:
    """Spin until a signal, the duration limit, or nothing left to record; the reason why."""
    start_s = time.monotonic()
    next_progress_s = start_s + PROGRESS_PERIOD_S
    while True:
        # Short waits: a Python signal handler only runs once the wait returns.
        executor.spin_once(timeout_sec=0.05)
        now_s = time.monotonic()
        if stop.event.is_set():
            return stop.signal_name
        if max_duration_s is not None and now_s - start_s >= max_duration_s:
            return f"--max-duration-s {max_duration_s:g}"
        if recorder.idle:
            return REASON_IDLE
        if verbose and now_s >= next_progress_s:
            next_progress_s += PROGRESS_PERIOD_S
            counts = ", ".join(f"{t} {n}" for t, n in recorder.counts.items()) or "nothing yet"
            print(f"lca-record: {now_s - start_s:6.1f} s: {counts}", file=sys.stderr, flush=True)


def _drain(executor: Executor, recorder: BagRecorder) -> None:
    """Take the messages the middleware already holds: until none came for DRAIN_QUIET_S.

    A live publisher keeps it going, so it stops after DRAIN_MAX_S in any case (far longer than
    taking `STATE_QOS_DEPTH` queued messages per topic needs).
    """
    start_s = last_s = time.monotonic()
    total = recorder.total
    while (now_s := time.monotonic()) - last_s < DRAIN_QUIET_S and now_s - start_s < DRAIN_MAX_S:
        executor.spin_once(timeout_sec=0.01)
        if recorder.total != total:
            total = recorder.total
            last_s = time.monotonic()


def _print_summary(output: Path, counts: dict[str, int], reason: str) -> None:
    width = max((len(t) for t in counts), default=0)
    lines = [f"lca-record: stopped ({reason}); {sum(counts.values())} messages in {output}"]
    lines += [f"  {topic:<{width}}  {n}" for topic, n in counts.items()]
    print("\n".join(lines), file=sys.stderr, flush=True)


def _note(text: str) -> None:
    print(f"lca-record: {text}", file=sys.stderr, flush=True)


def _warn(text: str) -> None:
    print(f"lca-record: warning: {text}", file=sys.stderr, flush=True)


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its class name if it has none).

    rcl's source locations (`, at /project/src/rcl/...`) are cut off.
    """
    text = str(exc).strip()
    line = text.splitlines()[0] if text else type(exc).__name__
    return line.split(", at /", 1)[0]


def _fail(text: str) -> int:
    print(f"lca-record: error: {text}", file=sys.stderr, flush=True)
    return EXIT_BAD_INPUT
