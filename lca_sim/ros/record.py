"""`lca-record`: record ROS 2 topics to a rosbag2 MCAP bag, the message bytes as they arrive.

    lca-record joint_states motor_states drive_chain_states -o out/run1
    lca-record --all --max-duration-s 60 -o out/run2 --ros-args -p use_sim_time:=true

Each topic is subscribed raw: its CDR bytes go into the bag unchanged, stamped with the node's
clock at reception. `BagRecorder` composes the topics (`lca_sim.ros.record_topics`: which, and
with which QoS) and the bag (`lca_sim.ros.record_bag`: a killed recorder loses at most
`--flush-period-s`; `lca-record --recover BAG`, `lca_sim.ros.bag_recover`, rewrites its bag).
It stops on SIGINT, SIGTERM or `--max-duration-s`, closes the bag and prints the counts per
topic. Exit codes (`lca_sim.errors`): 0 stopped normally (also on a signal); 2 bad arguments, an
existing output folder, or none of the named topics recorded. Embedding: `BagRecorder(node,
out, topics)`, `start()`, spin the node's executor, `close()` returns the counts.
docs/plotting.md ("Recording a run") has what it prints, when nothing is lost, and its limits.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.context import Context
from rclpy.executors import Executor
from rclpy.node import Node
from rclpy.timer import Timer

from lca_sim.errors import EXIT_OK, fail
from lca_sim.ros.bag_recover import recover_main
from lca_sim.ros.node_util import (
    ToolStartError,
    first_line,
    make_executor,
    tool_arguments,
    tool_context,
)
from lca_sim.ros.record_bag import BagFile, RecorderError
from lca_sim.ros.record_topics import TopicSubscriber
from lca_sim.ros.tool_args import RECORD_DEPTH, record_parser
from lca_sim.ros.tool_args import RECORD_FLUSH_PERIOD_S as DEFAULT_MAX_LOSS_S
from lca_sim.ros.tool_args import RECORD_WAIT_S as DEFAULT_WAIT_S
from lca_sim.runtime import stop_signals

PROG = "lca-record"

NODE_NAME = "lca_record"
GRAPH_POLL_PERIOD_S = 0.1
REASON_IDLE = "no topic left to record"
# After a stop request: keep taking already-received messages until none came for this long.
DRAIN_QUIET_S = 0.05
DRAIN_SPIN_S = 0.01  # one spin's wait for a message while draining
DRAIN_QUIET_SPINS = round(DRAIN_QUIET_S / DRAIN_SPIN_S)  # ... and this many of them in a row
PROGRESS_PERIOD_S = 1.0


class BagRecorder:
    """Records topics of a node's ROS graph into a new rosbag2 MCAP bag (see the module doc).

    Composes the bag (`record_bag.BagFile`: the writer and its flushes) and the topics
    (`record_topics.TopicSubscriber`: subscriptions and QoS), with the node's timers that
    drive them, and reports what is recorded.

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
        depth: int = RECORD_DEPTH,
        graph_poll_period_s: float = GRAPH_POLL_PERIOD_S,
        max_loss_s: float = DEFAULT_MAX_LOSS_S,
        log: Callable[[str], None] | None = None,
        note: Callable[[str], None] | None = None,
    ) -> None:
        self._node = node
        self.bag = BagFile(Path(output), max_loss_s)
        self._poll_period_s = graph_poll_period_s
        self._poll_timer: Timer | None = None
        self._flush_timer: Timer | None = None
        self._started = self._closed = False
        try:
            named = [node.resolve_topic_name(name) for name in topics]
        except Exception as exc:  # rclpy raises its own validation errors
            raise RecorderError(f"bad topic name: {first_line(exc)}") from None
        self.topics = TopicSubscriber(
            node,
            self.bag,
            named,
            record_all=record_all,
            wait_s=wait_s,
            depth=depth,
            log=log or node.get_logger().warning,
            note=note or node.get_logger().info,
        )

    @property
    def output(self) -> Path:
        """The bag folder."""
        return self.bag.output

    @property
    def counts(self) -> dict[str, int]:
        """Messages written so far per recorded topic (fully qualified names)."""
        with self.bag.lock:
            return {name: rec.count for name, rec in self.topics.recorded.items()}

    @property
    def total(self) -> int:
        """Messages written so far over all topics."""
        with self.bag.lock:
            return sum(rec.count for rec in self.topics.recorded.values())

    @property
    def waiting(self) -> list[str]:
        """Named topics whose type has not appeared yet."""
        return sorted(self.topics.waiting)

    @property
    def dropped(self) -> list[str]:
        """Named topics given up after `wait_s` (or with a type that cannot be recorded)."""
        return list(self.topics.dropped)

    @property
    def matched(self) -> list[str]:
        """Recorded topics whose subscription has matched at least one publisher.

        Matching is only complete when *both* sides have seen each other: a publisher whose
        `get_subscription_count()` already counts this recorder can still lose its first
        messages to it (a volatile reader drops data from a writer it has not matched yet).
        Wait for a topic to be listed here (checked every graph poll) before publishing
        anything that must be recorded.
        """
        with self.bag.lock:
            return [name for name, rec in self.topics.recorded.items() if rec.matched]

    @property
    def idle(self) -> bool:
        """True when nothing is or can be recorded any more: no topic, none waited for."""
        t = self.topics
        return not t.record_all and not t.recorded and not t.waiting

    def start(self) -> None:
        """Create the bag, subscribe to the topics already in the graph and start polling.

        Raises:
            RecorderError: The output folder exists or cannot be created.
        """
        if self._started or self._closed:
            raise RecorderError("BagRecorder.start() called twice")
        self.bag.open()
        self._started = True
        self.topics.start_waiting()
        self.poll_graph()
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        node = self._node
        self._poll_timer = node.create_timer(self._poll_period_s, self.poll_graph, clock=steady)
        self._flush_timer = node.create_timer(
            self.bag.flush_interval_s, self.bag.flush, clock=steady
        )

    def flush(self) -> None:
        """Close the open MCAP chunk and flush the file (`BagFile.flush`)."""
        self.bag.flush()

    def poll_graph(self) -> None:
        """Subscribe to newly appeared topics, adapt QoS and give up on overdue named topics."""
        if self.bag.is_open:
            self.topics.poll_graph()

    def stop_discovery(self) -> None:
        """Stop looking for new topics (recording of subscribed topics goes on)."""
        if self._poll_timer is not None:
            self._node.destroy_timer(self._poll_timer)
            self._poll_timer = None
        self.topics.waiting.clear()

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
        self.topics.unsubscribe()
        self._closed = True
        self.bag.close()
        return self.counts


def default_output(now: datetime | None = None) -> Path:
    """The default bag folder name, `lca_bag_<YYYYmmdd_HHMMSS>` in the working directory."""
    return Path(f"lca_bag_{(now or datetime.now()).strftime('%Y%m%d_%H%M%S')}")


class _StopFlag:
    """Set by SIGINT/SIGTERM (`stop_signals`); the spin loop checks it between short waits."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal_name = ""

    def set(self, signal_name: str) -> None:
        self.signal_name = signal_name
        self.event.set()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the lca-record console script."""
    try:
        all_args, own_args = tool_arguments(PROG, argv)
    except ToolStartError as exc:
        return fail(PROG, str(exc))
    args = _parse_args(own_args)
    if args.recover is not None:
        return recover_main(own_args)
    output: Path = args.output if args.output is not None else default_output()
    if output.exists():
        return fail(PROG, f"output {output} exists already; not overwriting (choose another -o)")
    stop = _StopFlag()
    try:
        with stop_signals(stop.set), tool_context(all_args) as context:
            run = _record(context, args, output, stop)
    except (ToolStartError, RecorderError) as exc:
        return fail(PROG, str(exc))
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
    if not args.drain_max_s >= 0 or math.isinf(args.drain_max_s):
        parser.error("--drain-max-s must be >= 0 and finite")
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
        _drain(executor, recorder, args.drain_max_s)
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
        return fail(PROG, f"could not record {dropped}; {output} is empty")
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


def _drain(executor: Executor, recorder: BagRecorder, max_s: float) -> None:
    """Take the messages the middleware already holds, until none came for a while.

    A while: DRAIN_QUIET_S and DRAIN_QUIET_SPINS spins in a row that took nothing, so a
    recorder starved of the CPU (a loaded host), whose one spin can outlast the quiet time, does
    not take its own stall for the end. A live publisher keeps it going, so it stops after
    `max_s` (`--drain-max-s`) in any case. The default is far longer than taking
    a few hundred queued messages per topic needs on an idle host; a recorder seconds
    behind on a loaded one (a lockstep run that ended) needs more, and `lca-hil fig15` gives it.
    """
    start_s = last_s = time.monotonic()
    total = recorder.total
    empty_spins = 0
    while (now_s := time.monotonic()) - start_s < max_s:
        if now_s - last_s >= DRAIN_QUIET_S and empty_spins >= DRAIN_QUIET_SPINS:
            return
        executor.spin_once(timeout_sec=DRAIN_SPIN_S)
        if recorder.total != total:
            total = recorder.total
            last_s = time.monotonic()
            empty_spins = 0
        else:
            empty_spins += 1


def _print_summary(output: Path, counts: dict[str, int], reason: str) -> None:
    width = max((len(t) for t in counts), default=0)
    lines = [f"lca-record: stopped ({reason}); {sum(counts.values())} messages in {output}"]
    lines += [f"  {topic:<{width}}  {n}" for topic, n in counts.items()]
    print("\n".join(lines), file=sys.stderr, flush=True)


def _note(text: str) -> None:
    print(f"lca-record: {text}", file=sys.stderr, flush=True)


def _warn(text: str) -> None:
    print(f"lca-record: warning: {text}", file=sys.stderr, flush=True)
