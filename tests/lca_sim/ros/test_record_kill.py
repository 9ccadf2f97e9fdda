"""lca-record --recover: a bag cut anywhere keeps its complete chunks; a whole one is left alone.

The end-to-end case (lca-record killed with SIGKILL mid-run, recovered, what survived counted
against what was published) is item 8 of the fault matrix, tests/test_fault_matrix.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapWriter
from rosbags.typesys import Stores, get_typestore
from support import RECORDED_TOPIC, numbered_joint_state, recorded_sequences

from lca_control.contract import JOINT_STATE_TYPE
from lca_sim.ros.bag_read import read_bag
from lca_sim.ros.bag_recover import recover_bag, scan_mcap


def write_chunked_bag(bag: Path, n_messages: int, per_chunk: int) -> Path:
    """A closed bag of JointStates whose MCAP has a chunk every `per_chunk` messages."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(RECORDED_TOPIC, JOINT_STATE_TYPE, typestore=typestore)
        storage = writer.storage
        assert isinstance(storage, McapWriter)
        for seq in range(n_messages):
            writer.write(conn, seq + 1, serialize_message(numbered_joint_state(seq)))
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
    assert result.counts == {RECORDED_TOPIC: expected}
    assert recorded_sequences(bag) == list(range(expected))
    assert read_bag(bag).topics == [RECORDED_TOPIC]


def test_recover_leaves_a_complete_bag_alone(tmp_path: Path) -> None:
    bag = tmp_path / "whole"
    mcap = write_chunked_bag(bag, n_messages=20, per_chunk=10)
    before = mcap.read_bytes()
    assert recover_bag(bag).was_complete
    assert mcap.read_bytes() == before
    assert recorded_sequences(bag) == list(range(20))
