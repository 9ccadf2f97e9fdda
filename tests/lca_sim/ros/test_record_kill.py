"""lca-record killed with SIGKILL: the bag is recovered and loses at most one flush period.

The ROS test runs on loopback only (conftest), on domain 77; the subprocesses get both variables
explicitly. Nothing sleeps a fixed time: every wait polls a condition with a deadline.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
import support
import yaml
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import serialize_message
from rclpy.signals import SignalHandlerOptions
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapWriter
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import JointState

from lca_control.contract import JOINT_STATE_TYPE, JOINT_STATES, STATE_QOS_DEPTH
from lca_sim.cli.bagplot import read_bag
from lca_sim.ros.bag_recover import recover_bag, scan_mcap
from lca_sim.ros.tool_args import RECORD_FLUSH_PERIOD_S

BIN = Path(sys.executable).parent
DOMAIN_ID = 77
PUBLISH_PERIOD_S = 0.005  # 200 Hz asked; the rate is measured, not trusted
RUN_BEFORE_KILL_S = 1.5  # several flush periods, and far below one 1 MiB chunk of JointStates
# Beyond the flush period: DDS delivery and the recorder's executor on a shared 2-core machine.
LOSS_MARGIN_S = 0.25
TIMEOUT_S = 30.0
TOPIC = f"/{JOINT_STATES}"


def lca_record() -> str:
    """Path of the installed lca-record console script."""
    path = BIN / "lca-record"
    if not path.exists():
        pytest.skip("lca-record is not installed (pip install -e .)")
    return str(path)


def tool_env() -> dict[str, str]:
    """The environment of the recorder subprocess: loopback-only DDS on this test's domain."""
    return {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "77"}


@contextlib.contextmanager
def ros_node(name: str) -> Iterator[tuple[Node, SingleThreadedExecutor]]:
    """A node and executor in a fresh context on DOMAIN_ID, shut down afterwards."""
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = Node(name, context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            yield node, executor
        finally:
            executor.shutdown(timeout_sec=1.0)
            node.destroy_node()  # type: ignore[no-untyped-call]  # rclpy leaves it unannotated
    finally:
        rclpy.shutdown(context=context)


def joint_state(seq: int) -> Any:
    """A JointState whose stamp carries the sequence number."""
    msg = JointState()
    msg.header.stamp.nanosec = seq
    msg.name = ["l_arm", "pivot", "c_arc", "lift"]
    msg.position = [float(seq), 0.5, -0.25, 0.1]
    msg.velocity = [0.0, 1.0, 0.0, 0.0]
    msg.effort = [0.0, 2.0, 0.0, 0.0]
    return msg


def sequences(bag: Path) -> list[int]:
    """The /joint_states sequence numbers in the bag, read with rosbags."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == TOPIC]
        assert [c.msgtype for c in conns] == [JOINT_STATE_TYPE]
        msgs: list[Any] = [
            typestore.deserialize_cdr(raw, JOINT_STATE_TYPE)
            for _, _, raw in reader.messages(connections=conns)
        ]
    return [int(msg.header.stamp.nanosec) for msg in msgs]


@pytest.mark.slow
def test_sigkilled_recording_is_recovered_losing_at_most_a_flush_period(tmp_path: Path) -> None:
    """SIGKILL mid-run; --recover; the bag opens and holds all but the last flush period."""
    bag = tmp_path / "killed"
    args = [lca_record(), TOPIC, "-o", str(bag), "--wait-s", "30"]
    stderr_lines: list[str] = []
    proc = subprocess.Popen(args, env=tool_env(), stderr=subprocess.PIPE, text=True)
    pump = threading.Thread(
        target=lambda: stderr_lines.extend(proc.stderr or ()),
        daemon=True,
    )
    pump.start()
    publish_s: list[float] = []  # publish_s[seq]: when message seq was published (monotonic)
    try:
        with ros_node("test_kill_publisher") as (node, executor):
            pub = node.create_publisher(JointState, JOINT_STATES, STATE_QOS_DEPTH)
            support.spin_until(
                executor,
                lambda: (
                    pub.get_subscription_count() >= 1
                    and any(f"recording {TOPIC} (" in line for line in list(stderr_lines))
                ),
                "the recorder to subscribe",
                TIMEOUT_S,
            )
            kill_s: list[float] = []

            def tick() -> None:
                if kill_s:
                    return
                now_s = time.monotonic()
                if publish_s and now_s - publish_s[0] >= RUN_BEFORE_KILL_S:
                    proc.kill()  # SIGKILL: no handler, no close, no metadata.yaml
                    kill_s.append(now_s)
                    return
                pub.publish(joint_state(len(publish_s)))
                publish_s.append(time.monotonic())

            timer = node.create_timer(PUBLISH_PERIOD_S, tick)
            support.spin_until(executor, lambda: bool(kill_s), "the kill", TIMEOUT_S)
            node.destroy_timer(timer)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=TIMEOUT_S)
    assert proc.returncode == -9
    assert not (bag / "metadata.yaml").exists()  # the recorder did not close the bag

    recovered = subprocess.run(
        [lca_record(), "--recover", str(bag)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    assert recovered.returncode == 0, recovered.stderr
    assert "lca-record: recovered" in recovered.stderr

    seqs = sequences(bag)
    assert seqs, "nothing recovered"
    assert seqs == list(range(len(seqs)))  # a prefix of what was published, nothing skipped
    data = read_bag(bag)  # lca-plot's reader
    assert data.topics == [TOPIC]
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text(encoding="utf-8"))
    assert metadata["rosbag2_bagfile_information"]["message_count"] == len(seqs)

    n_published = len(publish_s)
    rate_hz = (n_published - 1) / (publish_s[-1] - publish_s[0])
    lost = n_published - len(seqs)
    lost_s = kill_s[0] - publish_s[len(seqs) - 1]  # since the last recovered one was published
    print(f"published {n_published} at {rate_hz:.0f} Hz; lost {lost} ({lost_s:.3f} s)")
    budget_s = RECORD_FLUSH_PERIOD_S + LOSS_MARGIN_S
    assert lost <= budget_s * rate_hz + 1, f"lost {lost} of {n_published} ({lost_s:.3f} s)"
    assert lost_s <= budget_s, f"lost {lost} of {n_published} ({lost_s:.3f} s)"

    again = subprocess.run(
        [lca_record(), "--recover", str(bag)],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    assert again.returncode == 0
    assert "nothing to recover" in again.stderr


def write_chunked_bag(bag: Path, n_messages: int, per_chunk: int) -> Path:
    """A closed bag of JointStates whose MCAP has a chunk every `per_chunk` messages."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(TOPIC, JOINT_STATE_TYPE, typestore=typestore)
        storage = writer.storage
        assert isinstance(storage, McapWriter)
        for seq in range(n_messages):
            writer.write(conn, seq + 1, serialize_message(joint_state(seq)))
            if (seq + 1) % per_chunk == 0:
                storage.close_chunk()
    return bag / f"{bag.name}.mcap"


@pytest.mark.parametrize("cut_fraction", [0.3, 0.55, 0.8, 0.97])
def test_recover_keeps_the_complete_chunks_of_a_cut_file(
    tmp_path: Path, cut_fraction: float
) -> None:
    """A file cut anywhere recovers to a prefix made of whole chunks, readable by rosbags."""
    bag = tmp_path / "cut"
    mcap = write_chunked_bag(bag, n_messages=100, per_chunk=10)
    data = mcap.read_bytes()
    cut = int(len(data) * cut_fraction)
    mcap.write_bytes(data[:cut])
    (bag / "metadata.yaml").unlink()
    expected = len(scan_mcap(data[:cut]).messages)
    assert expected % 10 == 0

    result = recover_bag(bag)

    assert not result.was_complete
    assert result.counts == {TOPIC: expected}
    assert sequences(bag) == list(range(expected))
    assert read_bag(bag).topics == [TOPIC]


def test_recover_leaves_a_complete_bag_alone(tmp_path: Path) -> None:
    bag = tmp_path / "whole"
    mcap = write_chunked_bag(bag, n_messages=20, per_chunk=10)
    before = mcap.read_bytes()
    assert recover_bag(bag).was_complete
    assert mcap.read_bytes() == before
    assert sequences(bag) == list(range(20))
