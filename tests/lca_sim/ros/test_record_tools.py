"""lca-record, lca-echo and lca-plot: no lost message, clean stops, YAML output, PNG plots.

The ROS tests run on loopback only (conftest sets ROS_AUTOMATIC_DISCOVERY_RANGE), each on its
own domain id in 71..78; subprocesses get both variables explicitly. Nothing sleeps a fixed
time: every wait polls a condition with a deadline while spinning an executor.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
import support
import yaml
from diagnostic_msgs.msg import (
    DiagnosticArray,
    DiagnosticStatus,
    KeyValue,
)
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from lca_control.contract import (
    CLOCK,
    DIAGNOSTIC_ARRAY_TYPE,
    DRIVE_CHAIN_STATES,
    DRIVE_STATUS_PREFIX,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    MOTOR_STATES,
    STATE_QOS_DEPTH,
)
from lca_sim.cli import bag_events, bagplot
from lca_sim.ros import bag_read, record
from lca_sim.ros.echo import message_to_plain
from lca_sim.ros.record import BagRecorder
from lca_sim.ros.record_topics import subscription_qos

JOINTS = ("l_arm", "pivot", "c_arc", "lift")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
BIN = Path(sys.executable).parent
PUBLISH_PERIOD_S = 0.001  # up to 1 kHz per topic (the timer may run slower)
MATCH_TIMEOUT_S = 15.0
EXIT_TIMEOUT_S = 15.0
SIM_START_S = 1000


# ---------------------------------------------------------------- helpers


@contextlib.contextmanager
def ros_node(domain_id: int, name: str) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """A node and executor in a fresh context on `domain_id`, shut down afterwards."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = Node(name, context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            yield node, executor
        finally:
            executor.shutdown(timeout_sec=1.0)
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def spin_until(
    executor: SingleThreadedExecutor,
    condition: Callable[[], bool],
    what: str,
    timeout_s: float = MATCH_TIMEOUT_S,
) -> None:
    """`support.spin_until` with this module's matching deadline."""
    support.spin_until(executor, condition, what, timeout_s)


def tool_env(domain_id: int) -> dict[str, str]:
    """The environment of a tool subprocess: loopback-only DDS on the test's domain."""
    return {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": str(domain_id),
    }


def tool(name: str) -> str:
    """Path of an installed console script of lca_hil (next to the venv's python)."""
    path = BIN / name
    assert path.exists(), f"{name} is not installed next to {sys.executable} (pip install -e .)"
    return str(path)


class Tool:
    """A console-script subprocess whose stderr is collected line by line as it runs."""

    def __init__(self, args: list[str], domain_id: int, cwd: Path) -> None:
        self.proc = subprocess.Popen(
            args,
            cwd=cwd,
            env=tool_env(domain_id),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.stderr_lines: list[str] = []
        self._pump = threading.Thread(target=self._read_stderr, daemon=True)
        self._pump.start()

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr_lines.append(line)

    def said(self, text: str) -> bool:
        """True once a stderr line contains `text`."""
        return any(text in line for line in list(self.stderr_lines))

    def finish(self, signum: int | None = None) -> tuple[int, str, str]:
        """Send `signum` (if any), wait for the exit; the exit code, stdout and stderr."""
        if signum is not None:
            self.proc.send_signal(signum)
        code = self.proc.wait(timeout=EXIT_TIMEOUT_S)
        assert self.proc.stdout is not None
        out = self.proc.stdout.read()
        self._pump.join(timeout=EXIT_TIMEOUT_S)
        return code, out, "".join(self.stderr_lines)


@contextlib.contextmanager
def running(args: list[str], domain_id: int, cwd: Path) -> Iterator[Tool]:
    """Start a tool subprocess; kill it on the way out if the test left it running."""
    started = Tool(args, domain_id, cwd)
    try:
        yield started
    finally:
        if started.proc.poll() is None:
            started.proc.kill()
            started.proc.communicate()


def recording(topic: str) -> str:
    """lca-record's stderr note once its subscription to `topic` has matched a publisher."""
    return f"lca-record: recording {topic} ("


def joint_state(seq: int) -> Any:
    """A JointState whose stamp and first position carry the sequence number."""
    msg = JointState()
    msg.header.stamp.nanosec = seq
    msg.name = list(JOINTS)
    msg.position = [float(seq), 0.5, -0.25, 0.1]
    msg.velocity = [0.0, 1.0, 0.0, 0.0]
    msg.effort = [0.0, 2.0, 0.0, 0.0]
    return msg


def drive_array(seq: int) -> Any:
    """A drive_chain_states DiagnosticArray whose stamp carries the sequence number."""
    msg = DiagnosticArray()
    msg.header.stamp.nanosec = seq
    msg.status = [
        DiagnosticStatus(
            name=f"{DRIVE_STATUS_PREFIX}{joint}",
            message="motor_driving",
            values=[
                KeyValue(key="drive_state", value="motor_driving"),
                KeyValue(key="eta_m", value="0.4"),
                KeyValue(key="eta_l", value="nan"),
            ],
        )
        for joint in JOINTS
    ]
    return msg


def publish_paced(
    executor: SingleThreadedExecutor,
    node: Node,
    jobs: list[tuple[Publisher, Callable[[int], Any]]],
    n: int,
) -> None:
    """Publish messages 0..n-1 on every publisher from a timer, spinning until done."""
    published = [0]

    def tick() -> None:
        seq = published[0]
        if seq >= n:
            return
        for publisher, make in jobs:
            publisher.publish(make(seq))
        published[0] = seq + 1

    timer = node.create_timer(PUBLISH_PERIOD_S, tick)
    try:
        spin_until(executor, lambda: published[0] >= n, f"{n} messages published", 60.0)
    finally:
        node.destroy_timer(timer)
    for publisher, _ in jobs:
        assert publisher.wait_for_all_acked(Duration(seconds=10)), "not all messages acked"


def decode(typestore: Typestore, raw: bytes | memoryview, msgtype: str) -> Any:
    """A bag message deserialized with the typestore (Any: its fields are generated)."""
    return typestore.deserialize_cdr(raw, msgtype)


def read_sequences(bag: Path, topics: tuple[str, ...]) -> dict[str, list[int]]:
    """Per topic, the header.stamp.nanosec sequence numbers in the bag, in bag order."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    out: dict[str, list[int]] = {}
    with Reader(bag) as reader:
        for conn in reader.connections:
            if conn.topic in topics:
                out[conn.topic] = [
                    decode(typestore, raw, conn.msgtype).header.stamp.nanosec
                    for _, _, raw in reader.messages(connections=[conn])
                ]
    return out


# ---------------------------------------------------------------- lca-record


@pytest.mark.slow
def test_record_loses_no_message_and_closes_on_sigint_and_sigterm(tmp_path: Path) -> None:
    """Two recorders take the same 2 x 2000 messages; one stops on SIGINT, one on SIGTERM.

    Both run at once so the file pays DDS discovery (up to the 3 s announcement period) once.
    """
    domain_id = 71
    n_messages = 2000
    stops = {"sigint": signal.SIGINT, "sigterm": signal.SIGTERM}
    bags = {name: tmp_path / name for name in stops}
    topics = (f"/{JOINT_STATES}", f"/{DRIVE_CHAIN_STATES}")
    lca_record = tool("lca-record")
    args = {
        name: [lca_record, *topics, "-o", str(bag), "--wait-s", "30"] for name, bag in bags.items()
    }
    with ros_node(domain_id, "test_publisher") as (node, executor):
        js_pub = node.create_publisher(JointState, JOINT_STATES, STATE_QOS_DEPTH)
        dc_pub = node.create_publisher(DiagnosticArray, DRIVE_CHAIN_STATES, STATE_QOS_DEPTH)
        with contextlib.ExitStack() as stack:
            procs = {
                name: stack.enter_context(
                    running(
                        args[name],
                        domain_id,
                        tmp_path,
                    )
                )
                for name in bags
            }
            # Both sides of every match: the publishers count the recorders, and each
            # recorder reports its subscriptions matched (see BagRecorder.matched).
            spin_until(
                executor,
                lambda: (
                    js_pub.get_subscription_count() >= len(procs)
                    and dc_pub.get_subscription_count() >= len(procs)
                    and all(p.said(recording(t)) for p in procs.values() for t in topics)
                ),
                "both recorders to subscribe",
            )
            publish_paced(
                executor, node, [(js_pub, joint_state), (dc_pub, drive_array)], n_messages
            )
            results = {name: proc.finish(stops[name]) for name, proc in procs.items()}
    expected = list(range(n_messages))
    for name, bag in bags.items():
        code, _, err = results[name]
        assert code == 0, f"{name}: {err}"
        assert f"{2 * n_messages} messages" in err, f"{name}: {err}"  # the summary
        metadata = yaml.safe_load((bag / "metadata.yaml").read_text(encoding="utf-8"))
        assert metadata["rosbag2_bagfile_information"]["storage_identifier"] == "mcap"
        sequences = read_sequences(bag, topics)
        assert sequences[topics[0]] == expected, name
        assert sequences[topics[1]] == expected, name
        with Reader(bag) as reader:
            types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {topics[0]: JOINT_STATE_TYPE, topics[1]: DIAGNOSTIC_ARRAY_TYPE}, name


@pytest.mark.slow
def test_record_all_picks_up_a_topic_that_appears_later(tmp_path: Path) -> None:
    domain_id = 73
    bag = tmp_path / "bag"
    n_messages = 20
    # use_sim_time without a /clock publisher: the node clock reads 0, so every bag timestamp
    # must be 0 (a wall-clock stamp would be ~1.7e18 ns): ROS args reach the node.
    # -v: the recorder prints its counts each second, so the test can wait for all 20 to be in
    # (wait_for_all_acked would wait for Fast DDS's 3 s heartbeat after so short a burst).
    args = [tool("lca-record"), "--all", "-v", "-o", str(bag)]
    args += ["--ros-args", "-p", "use_sim_time:=true"]
    with (
        ros_node(domain_id, "test_late_publisher") as (node, executor),
        running(args, domain_id, tmp_path) as proc,
    ):
        spin_until(
            executor,
            lambda: "lca_record" in node.get_node_names() and bag.is_dir(),
            "the recorder to start",
        )
        late = node.create_publisher(Float64MultiArray, "late_topic", STATE_QOS_DEPTH)
        spin_until(
            executor,
            lambda: late.get_subscription_count() >= 1 and proc.said(recording("/late_topic")),
            "a late subscription",
        )
        for seq in range(n_messages):
            late.publish(Float64MultiArray(data=[float(seq)]))
        spin_until(executor, lambda: proc.said(f"/late_topic {n_messages}"), "all in the bag")
        code, _, err = proc.finish(signal.SIGINT)
    assert code == 0, err
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        topics = {c.topic for c in reader.connections}
        conn = next(c for c in reader.connections if c.topic == "/late_topic")
        rows = list(reader.messages(connections=[conn]))
    values = [decode(typestore, raw, conn.msgtype).data[0] for _, _, raw in rows]
    assert values == [float(seq) for seq in range(n_messages)]
    assert {stamp for _, stamp, _ in rows} == {0}
    assert "/rosout" not in topics
    assert "/parameter_events" not in topics


def test_record_refuses_an_existing_output(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    # Checked before ROS starts, so main() runs in-process without a node.
    assert record.main(["--all", "-o", str(bag)]) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [
        f"lca-record: error: output {bag} exists already; not overwriting (choose another -o)"
    ]
    assert list(bag.iterdir()) == []


def test_recorder_switches_to_best_effort_for_a_best_effort_publisher(tmp_path: Path) -> None:
    """Subscribed (reliable) before any publisher; then a best-effort publisher appears."""
    domain_id = 76
    topic = "qos_probe"
    with ros_node(domain_id, "test_qos") as (node, executor):
        # A subscription puts the topic and its type into the graph without a publisher.
        node.create_subscription(Float64MultiArray, topic, lambda _msg: None, 10)
        recorder_node = Node("qos_recorder", context=node.context)
        executor.add_node(recorder_node)
        recorder = BagRecorder(recorder_node, tmp_path / "bag", [topic], wait_s=30.0)
        try:
            recorder.start()
            spin_until(
                executor, lambda: f"/{topic}" in recorder.counts, "the recorder to subscribe"
            )
            best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
            pub = node.create_publisher(Float64MultiArray, topic, best_effort)

            def recorded() -> bool:
                pub.publish(Float64MultiArray(data=[1.0]))  # best-effort: repeat until through
                return recorder.counts[f"/{topic}"] >= 1

            spin_until(executor, recorded, "a best-effort message in the bag")
        finally:
            recorder.close()
            executor.remove_node(recorder_node)
            recorder_node.destroy_node()


def test_bag_recorder_in_process_with_sim_time_and_best_effort_clock(tmp_path: Path) -> None:
    """Embedded use: BagRecorder on a sim-time node; /clock published best-effort."""
    domain_id = 75
    bag = tmp_path / "bag"
    n_messages = 200
    with ros_node(domain_id, "test_pub") as (node, executor):
        recorder_node = Node(
            "embedded_recorder",
            context=node.context,
            parameter_overrides=[Parameter("use_sim_time", value=True)],
        )
        executor.add_node(recorder_node)
        best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        clock_pub = node.create_publisher(ClockMsg, CLOCK, best_effort)
        js_pub = node.create_publisher(JointState, JOINT_STATES, STATE_QOS_DEPTH)
        recorder = BagRecorder(recorder_node, bag, [JOINT_STATES, CLOCK], wait_s=30.0)
        try:
            recorder.start()
            # /clock: the recorder's time source and its best-effort recording subscription.
            spin_until(
                executor,
                lambda: (
                    clock_pub.get_subscription_count() >= 2
                    and js_pub.get_subscription_count() >= 1
                    and f"/{JOINT_STATES}" in recorder.matched
                ),
                "the recorder's subscriptions",
            )
            clock_msg = ClockMsg()
            clock_msg.clock.sec = SIM_START_S

            def sim_time_s() -> float:
                return float(recorder_node.get_clock().now().nanoseconds) / 1e9

            def clock_arrived() -> bool:
                clock_pub.publish(clock_msg)  # best-effort: repeat until it is through
                return sim_time_s() >= SIM_START_S

            spin_until(executor, clock_arrived, "sim time to arrive")
            publish_paced(executor, node, [(js_pub, joint_state)], n_messages)
            spin_until(
                executor,
                lambda: recorder.counts.get(f"/{JOINT_STATES}", 0) >= n_messages,
                "the recorder to take every message",
            )
            counts = recorder.close()
        finally:
            recorder.close()
            executor.remove_node(recorder_node)
            recorder_node.destroy_node()
    assert counts[f"/{JOINT_STATES}"] == n_messages
    assert counts[CLOCK] >= 1
    sequences = read_sequences(bag, (f"/{JOINT_STATES}",))
    assert sequences[f"/{JOINT_STATES}"] == list(range(n_messages))
    with Reader(bag) as reader:
        conn = next(c for c in reader.connections if c.topic == f"/{JOINT_STATES}")
        stamps_ns = [stamp for _, stamp, _ in reader.messages(connections=[conn])]
    assert min(stamps_ns) >= SIM_START_S * 1_000_000_000  # stamped with the sim clock


def test_a_recorder_held_up_for_a_1khz_second_loses_nothing(tmp_path: Path) -> None:
    """1000 states arrive while the recorder's executor does not run; all are recorded.

    The fresh-clone CI lost 158 of 2000 messages at 1 kHz when the recorder subscribed with
    the plants' depth of 100: 0.26 s behind was enough. The middleware keeps what arrives
    (its threads run while the executor is held up), up to the subscription's depth.
    """
    domain_id = 72
    n_messages = 1000
    with ros_node(domain_id, "test_burst") as (node, executor):
        recorder_node = Node("held_up_recorder", context=node.context)
        recorder_executor = SingleThreadedExecutor(context=node.context)
        recorder_executor.add_node(recorder_node)
        publisher = node.create_publisher(JointState, JOINT_STATES, STATE_QOS_DEPTH)
        recorder = BagRecorder(recorder_node, tmp_path / "bag", [JOINT_STATES], wait_s=30.0)
        try:
            recorder.start()
            spin_until(
                recorder_executor,
                lambda: f"/{JOINT_STATES}" in recorder.matched,
                "the recorder's subscription",
            )
            spin_until(executor, lambda: publisher.get_subscription_count() >= 1, "a match")
            for seq in range(n_messages):  # the recorder's executor is not spun meanwhile
                publisher.publish(joint_state(seq))
            assert publisher.wait_for_all_acked(Duration(seconds=10)), "not all acked"
            spin_until(
                recorder_executor,
                lambda: recorder.counts.get(f"/{JOINT_STATES}", 0) >= n_messages,
                f"all {n_messages} recorded",
            )
            counts = recorder.close()
        finally:
            recorder.close()
            recorder_executor.shutdown(timeout_sec=1.0)
            recorder_node.destroy_node()
    assert counts[f"/{JOINT_STATES}"] == n_messages
    sequences = read_sequences(tmp_path / "bag", (f"/{JOINT_STATES}",))
    assert sequences[f"/{JOINT_STATES}"] == list(range(n_messages))


def test_subscription_qos_matches_best_effort_publishers() -> None:
    assert subscription_qos("/joint_states", []).reliability == ReliabilityPolicy.RELIABLE
    assert subscription_qos(CLOCK, []).reliability == ReliabilityPolicy.BEST_EFFORT
    assert subscription_qos("/x", []).depth == STATE_QOS_DEPTH


# ---------------------------------------------------------------- lca-echo


@pytest.mark.slow
def test_echo_prints_yaml_documents(tmp_path: Path) -> None:
    domain_id = 74
    with ros_node(domain_id, "test_echo_publisher") as (node, executor):
        pub = node.create_publisher(JointState, JOINT_STATES, STATE_QOS_DEPTH)
        args = [tool("lca-echo"), JOINT_STATES, "-n", "3", "--wait-s", "30"]
        with running(args, domain_id, tmp_path) as echo:
            spin_until(executor, lambda: pub.get_subscription_count() >= 1, "lca-echo")
            # lca-echo's side of the match may lag this one, so keep publishing numbered
            # messages until it has printed three and exits.
            sent = [0]

            def tick() -> None:
                pub.publish(joint_state(sent[0]))
                sent[0] += 1

            node.create_timer(0.02, tick)
            spin_until(executor, lambda: echo.proc.poll() is not None, "lca-echo to exit")
            code, out, err = echo.finish()
    assert code == 0, err
    assert out.count("\n---\n") == 3
    docs = [doc for doc in yaml.safe_load_all(out) if doc is not None]
    assert len(docs) == 3
    first = docs[0]["header"]["stamp"]["nanosec"]
    for seq, doc in enumerate(docs, start=first):  # reliable: consecutive once matched
        assert list(doc) == ["header", "name", "position", "velocity", "effort"]
        assert doc["header"]["stamp"]["nanosec"] == seq
        assert doc["name"] == list(JOINTS)
        assert doc["position"] == pytest.approx(list(joint_state(seq).position))


def test_echo_unknown_topic_is_one_line_exit_2(tmp_path: Path) -> None:
    proc = subprocess.run(
        [tool("lca-echo"), "no_such_topic", "--wait-s", "0.2"],
        cwd=tmp_path,
        env=tool_env(78),
        capture_output=True,
        text=True,
        timeout=EXIT_TIMEOUT_S,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "lca-echo: error: topic /no_such_topic did not appear within 0.2 s"
    ]


def test_message_to_plain_nested_and_arrays() -> None:
    plain = message_to_plain(drive_array(7))
    assert plain["header"]["stamp"] == {"sec": 0, "nanosec": 7}
    assert plain["status"][1]["name"] == f"{DRIVE_STATUS_PREFIX}pivot"
    assert plain["status"][0]["values"][0] == {"key": "drive_state", "value": "motor_driving"}
    assert message_to_plain(joint_state(3))["position"] == [3.0, 0.5, -0.25, 0.1]


# ---------------------------------------------------------------- lca-plot


def write_test_bag(
    path: Path,
    topics: tuple[str, ...],
    n_messages: int = 50,
    *,
    header_stamps: bool = True,
    header_start_ns: int = 2_000_000_000,
) -> None:
    """A small MCAP bag: joint/motor JointStates and drive-chain DiagnosticArrays.

    Bag stamps are 10 ms apart, header stamps 20 ms apart from `header_start_ns` (or all zero
    without header_stamps).
    """
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = ts.types
    stamp = types["builtin_interfaces/msg/Time"]
    header = types["std_msgs/msg/Header"]
    js_cls = types[JOINT_STATE_TYPE]
    array_cls = types[DIAGNOSTIC_ARRAY_TYPE]
    status_cls = types["diagnostic_msgs/msg/DiagnosticStatus"]
    kv_cls = types["diagnostic_msgs/msg/KeyValue"]
    states = ("stop_hold", "stop_motor_direct", "motor_driving")

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            t: writer.add_connection(
                f"/{t}",
                DIAGNOSTIC_ARRAY_TYPE if t == DRIVE_CHAIN_STATES else JOINT_STATE_TYPE,
                typestore=ts,
            )
            for t in topics
        }
        for i in range(n_messages):
            t_ns = 1_000_000_000 + i * 10_000_000
            head_ns = (header_start_ns + i * 20_000_000) if header_stamps else 0
            head = header(stamp=stamp(sec=head_ns // 10**9, nanosec=head_ns % 10**9), frame_id="")
            value = np.array([0.01 * i, 0.02 * i, -0.01 * i, 0.001 * i])
            msgs = {
                JOINT_STATES: js_cls(
                    header=head, name=list(JOINTS), position=value, velocity=value, effort=value
                ),
                MOTOR_STATES: js_cls(
                    header=head,
                    name=list(JOINTS),
                    position=100 * value,
                    velocity=100 * value,
                    effort=value,
                ),
                DRIVE_CHAIN_STATES: array_cls(
                    header=head,
                    status=[
                        status_cls(
                            level=0,
                            name=f"{DRIVE_STATUS_PREFIX}{joint}",
                            message=states[i * len(states) // n_messages],
                            hardware_id="",
                            values=[
                                kv_cls(key="drive_state", value=states[i * 3 // n_messages]),
                                kv_cls(key="eta_m", value=repr(0.5 + 0.001 * i)),
                                kv_cls(key="eta_l", value="nan" if i < 10 else "0.3"),
                            ],
                        )
                        for joint in JOINTS
                    ],
                ),
            }
            for topic, conn in conns.items():
                writer.write(conn, t_ns, ts.serialize_cdr(msgs[topic], conn.msgtype))


def test_plot_writes_png_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "bag"
    write_test_bag(bag, (JOINT_STATES, MOTOR_STATES, DRIVE_CHAIN_STATES))
    out = tmp_path / "plots"
    assert bagplot.main([str(bag), "--out", str(out)]) == 0  # what the lca-plot script runs
    stdout = capsys.readouterr().out
    names = ("positions", "velocities", "currents", "drive_states", "efficiencies")
    for name in names:
        png = out / f"{name}.png"
        assert png.read_bytes().startswith(PNG_SIGNATURE), png
        assert f"wrote {png}" in stdout
    assert not list(out.glob("*.part"))


def test_plot_skips_missing_topics(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / "bag"
    write_test_bag(bag, (JOINT_STATES,), n_messages=5)
    assert bagplot.main([str(bag)]) == 0
    captured = capsys.readouterr()
    assert sorted(p.name for p in bag.glob("*.png")) == ["positions.png", "velocities.png"]
    assert f"no {MOTOR_STATES}" in captured.err
    assert f"no {DRIVE_CHAIN_STATES}" in captured.err


def test_plot_reads_drive_states_and_units(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    write_test_bag(bag, (JOINT_STATES, DRIVE_CHAIN_STATES), n_messages=30)
    data = bag_read.read_bag(bag)
    assert list(data.joints) == list(JOINTS)
    assert data.drives["pivot"].state[0] == "stop_hold"
    assert data.drives["pivot"].state[-1] == "motor_driving"
    assert math.isnan(data.drives["pivot"].eta["eta_l"][0])
    assert data.time_base == "header"  # auto: every message has a header stamp
    assert data.joints["pivot"].time_s[:2] == pytest.approx([0.0, 0.02])
    assert data.drives["lift"].time_s[-1] == pytest.approx(29 * 0.02)
    by_bag = bag_read.read_bag(bag, time_base="bag")
    assert by_bag.joints["pivot"].time_s[:2] == pytest.approx([0.0, 0.01])
    unstamped = tmp_path / "unstamped"
    write_test_bag(unstamped, (JOINT_STATES,), n_messages=3, header_stamps=False)
    fallback = bag_read.read_bag(unstamped)
    assert fallback.time_base == "bag"
    assert fallback.joints["lift"].time_s == pytest.approx([0.0, 0.01, 0.02])
    # Simulated time starts at exactly 0 (lockstep): that first zero stamp is a stamp.
    from_zero = tmp_path / "from_zero"
    write_test_bag(from_zero, (JOINT_STATES, DRIVE_CHAIN_STATES), n_messages=4, header_start_ns=0)
    sim_time = bag_read.read_bag(from_zero)
    assert sim_time.time_base == "header"
    assert sim_time.joints["pivot"].time_s == pytest.approx([0.0, 0.02, 0.04, 0.06])
    order = bag_events.state_order(["motor_driving", "stop_hold"])
    assert order[0] == "stop_hold"
    assert order[-1] == "motor_driving"


@pytest.mark.parametrize("bad", ["missing", "file.txt", "empty_dir"])
def test_plot_bad_bag_path_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], bad: str
) -> None:
    (tmp_path / "file.txt").write_text("not a bag", encoding="utf-8")
    (tmp_path / "empty_dir").mkdir()
    assert bagplot.main([str(tmp_path / bad)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert err.startswith("lca-plot: error: ")


def test_plot_script_bad_path(tmp_path: Path) -> None:
    proc = subprocess.run(
        [tool("lca-plot"), str(tmp_path / "no_bag")],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"lca-plot: error: bag {tmp_path / 'no_bag'}: folder not found"
    ]
    assert proc.stdout == ""


class _Backlog:
    """An executor and recorder stand-in on a clock of its own: one message taken per spin.

    `left` messages wait in the middleware, each taking `take_s` to record; after them the
    spin waits its timeout for nothing (`live`: a publisher that never ends instead).
    """

    def __init__(self, left: int, take_s: float, *, live: bool = False, stall_at: int = -1) -> None:
        self.left, self.take_s, self.live = left, take_s, live
        self.stall_at = stall_at  # after this many messages, one spin gets no CPU for 0.2 s
        self.total = 0
        self.now_s = 0.0

    def monotonic(self) -> float:
        return self.now_s

    def spin_once(self, timeout_sec: float) -> None:
        if self.total == self.stall_at:
            self.stall_at = -1
            self.now_s += 0.2  # starved: the spin returns late, having taken nothing
            return
        if self.left or self.live:
            self.left = max(self.left - 1, 0)
            self.total += 1
            self.now_s += self.take_s
        else:
            self.now_s += timeout_sec


def test_a_stopped_recorder_drains_a_backlog_for_as_long_as_it_is_given(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Recorders 3,500 and 10,000 messages behind, at 0.4 ms each (a loaded host).

    3,500: fig15's CI run; 10,000: five topics at their full default depth. The default two
    seconds of draining take the first, not the second; lca-hil fig15, whose publishers have
    ended when it stops the recorder, gives it RECORDER_DRAIN_MAX_S and every one is taken.
    A live publisher still ends the drain at the limit.
    """
    from lca_sim.cli import fig15
    from lca_sim.ros import record
    from lca_sim.ros.tool_args import RECORD_DRAIN_MAX_S, record_parser

    def drained(backlog: _Backlog, max_s: float) -> _Backlog:
        monkeypatch.setattr(record, "time", backlog)
        record._drain(backlog, backlog, max_s)  # type: ignore[arg-type]
        return backlog

    assert drained(_Backlog(3500, 4e-4), RECORD_DRAIN_MAX_S).left == 0
    assert drained(_Backlog(10000, 4e-4), RECORD_DRAIN_MAX_S).left > 4000
    assert drained(_Backlog(10000, 4e-4), fig15.RECORDER_DRAIN_MAX_S).left == 0
    done = drained(_Backlog(3500, 4e-4), fig15.RECORDER_DRAIN_MAX_S)
    assert (done.left, done.total) == (0, 3500)
    live = drained(_Backlog(0, 4e-4, live=True), 2.0)
    assert 2.0 <= live.now_s < 2.0 + 1e-3
    # A spin that got no CPU for longer than the quiet time is no end of the backlog.
    starved = drained(_Backlog(3500, 4e-4, stall_at=1000), fig15.RECORDER_DRAIN_MAX_S)
    assert (starved.left, starved.total) == (0, 3500)
    idle = drained(_Backlog(10, 4e-4), fig15.RECORDER_DRAIN_MAX_S)  # an idle host: 0.05 s
    assert idle.total == 10 and idle.now_s < 0.1
    argv = fig15._argvs(Path("bag"), 13.0, fig15.fig15_run(13.0))["recorder"]
    args = record_parser().parse_args(argv[1 : argv.index("--ros-args")])
    assert args.drain_max_s == fig15.RECORDER_DRAIN_MAX_S
