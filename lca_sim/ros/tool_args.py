"""The command lines of lca-record and lca-echo, without ROS 2.

The two tools import rclpy at module level; their parsers live here so that `--help` is
answered (by `lca_sim.cli.nodes`) before rclpy is imported.
"""

from __future__ import annotations

import argparse
from pathlib import Path

RECORD_WAIT_S = 10.0
# The recorder's keep-last depth per topic: how far its executor may fall behind before the
# oldest messages are overwritten unseen (DDS reports no loss of that kind). 2 s of a 1 kHz
# topic: a Python recorder on a loaded 2-core host was measured 0.26 s behind at 1 kHz (158
# messages lost with the plants' own depth of 100), and no burst of a plant here lasts longer.
RECORD_DEPTH = 2000
# A SIGKILLed recorder loses at most this much: every period the open chunk is closed and flushed.
RECORD_FLUSH_PERIOD_S = 0.25
# After a stop request the recorder takes what the middleware already holds for at most this
# long: a live publisher never lets it fall quiet. A full queue (RECORD_DEPTH) of two topics
# is 4000 messages, 0.32 s at the 80 us a message measured here on the single-threaded
# executor, several times that on a loaded host.
RECORD_DRAIN_MAX_S = 2.0
EXECUTORS = ("events", "single")
ECHO_WAIT_S = 5.0
RELIABILITY_CHOICES = ("auto", "reliable", "best_effort")


def record_parser() -> argparse.ArgumentParser:
    """The argument parser of lca-record (ROS arguments are removed before it runs)."""
    parser = argparse.ArgumentParser(
        prog="lca-record",
        description="Record ROS 2 topics to a rosbag2 MCAP bag (raw CDR, node-clock stamps).",
        epilog="ROS arguments go last: --ros-args -p use_sim_time:=true -r __ns:=/robot1",
    )
    parser.add_argument("topics", nargs="*", metavar="TOPIC", help="topics to record")
    parser.add_argument(
        "--all", action="store_true", help="record every topic, also ones that appear later"
    )
    parser.add_argument(
        "-o", "--output", type=Path, default=None, help="bag folder (default lca_bag_<time>)"
    )
    parser.add_argument(
        "--wait-s",
        type=float,
        default=RECORD_WAIT_S,
        help=f"wait this long for a named topic to appear (default {RECORD_WAIT_S:g}; inf ok)",
    )
    parser.add_argument(
        "--max-duration-s", type=float, default=None, help="stop after this many seconds"
    )
    parser.add_argument(
        "--depth",
        type=int,
        default=RECORD_DEPTH,
        help=f"keep-last depth of the subscriptions (default {RECORD_DEPTH}); how many messages "
        "per topic the recorder may fall behind before the oldest are lost",
    )
    parser.add_argument(
        "--executor",
        choices=EXECUTORS,
        default=EXECUTORS[0],
        help="rclpy executor: events (C++ events executor, about half the CPU per message; "
        "the default when available) or single (SingleThreadedExecutor)",
    )
    parser.add_argument(
        "--flush-period-s",
        type=float,
        default=RECORD_FLUSH_PERIOD_S,
        help="a killed recorder loses at most this much of what it received: the open MCAP "
        "chunk is closed and flushed every 0.4 of it "
        f"(default {RECORD_FLUSH_PERIOD_S:g})",
    )
    parser.add_argument(
        "--drain-max-s",
        type=float,
        default=RECORD_DRAIN_MAX_S,
        help="on a stop request, go on taking the messages already received until none came "
        f"for 0.05 s (five waits in a row), at most this long (default {RECORD_DRAIN_MAX_S:g}); "
        "give more when the publishers have ended and the recorder may be behind (a loaded host)",
    )
    parser.add_argument(
        "--recover",
        type=Path,
        default=None,
        metavar="BAG",
        help="make the bag of a killed recording readable (keeps its complete chunks, rewrites "
        "the MCAP summary and metadata.yaml) and exit; needs no ROS",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="print progress each second")
    return parser


def echo_parser() -> argparse.ArgumentParser:
    """The argument parser of lca-echo (ROS arguments are removed before it runs)."""
    parser = argparse.ArgumentParser(
        prog="lca-echo",
        description="Print the messages of a ROS 2 topic as YAML.",
        epilog="ROS arguments go last: --ros-args -p use_sim_time:=true -r __ns:=/robot1",
    )
    parser.add_argument("topic", metavar="TOPIC", help="topic name (relative names get the ns)")
    count = parser.add_mutually_exclusive_group()
    count.add_argument("--once", action="store_true", help="print one message and exit")
    count.add_argument("-n", "--count", type=int, default=None, help="print N messages and exit")
    parser.add_argument(
        "--wait-s",
        type=float,
        default=ECHO_WAIT_S,
        help=f"wait this long for the topic to appear (default {ECHO_WAIT_S:g}; inf ok)",
    )
    parser.add_argument(
        "--qos-reliability",
        choices=RELIABILITY_CHOICES,
        default="auto",
        help="subscription reliability (default auto: match the publishers)",
    )
    return parser
