"""`lca-echo`: print the messages of a topic as YAML documents, like `ros2 topic echo`.

    lca-echo joint_states
    lca-echo drive_chain_states --once
    lca-echo /clock -n 10 --qos-reliability best_effort --ros-args -r __ns:=/robot1

The topic's type is read from the ROS graph (waiting up to `--wait-s` for it to appear) and each
message is printed as YAML with its fields in declaration order, arrays as lists, followed by a
`---` line. A DiagnosticStatus level prints as its number and name (`level: 1 (WARN)`, a YAML
string), a subnormal float as 0.0 (every other float at full precision).

The QoS is keep-last `STATE_QOS_DEPTH`; the reliability matches the publishers by default
(best-effort if any publisher is) or is forced with `--qos-reliability`. Exit codes: 0 after
the requested messages or on SIGINT/SIGTERM, 2 bad arguments or a topic that did not appear
within `--wait-s` (one line on stderr).
"""

from __future__ import annotations

import argparse
import array
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, cast

import yaml
from rclpy.context import Context
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy

from lca_sim.errors import EXIT_OK, fail
from lca_sim.ros.node_util import ToolStartError, first_line, tool_arguments, tool_context
from lca_sim.ros.record_bag import RecorderError
from lca_sim.ros.record_topics import import_message_class, subscription_qos
from lca_sim.ros.tool_args import echo_parser
from lca_sim.runtime import stop_signals

PROG = "lca-echo"

NODE_NAME = "lca_echo"

# YAML scalars a message field can hold; everything else is converted.
_PLAIN = (bool, int, str)

# diagnostic_msgs/DiagnosticStatus level constants, by value.
DIAGNOSTIC_LEVEL_NAMES = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
_DIAGNOSTIC_STATUS_TYPE = "diagnostic_msgs.msg._diagnostic_status.DiagnosticStatus"


def plain_float(value: float) -> float:
    """`value` without denormal noise: a subnormal (0 < |value| < `sys.float_info.min`) is 0.0.

    Normal values, however tiny (1e-300), are kept at full precision: YAML prints their `repr`,
    which reads back as the same float. Rounding normal numbers would hide real values; only the
    subnormal range, reached by underflow in float arithmetic and never a meaningful physical
    quantity here, is flushed to zero. NaN and infinities are kept.
    """
    if value != 0.0 and abs(value) < sys.float_info.min:
        return 0.0
    return float(value)  # a plain float also for numpy scalars, which safe_dump cannot write


def diagnostic_level_text(level: bytes | int) -> str:
    """A DiagnosticStatus level as its number and name, e.g. `"1 (WARN)"`.

    A string rather than a number with a YAML comment, since `yaml.safe_dump` cannot write
    comments; `1 (WARN)` is printed unquoted and still reads back (as that string). A value
    outside OK..STALE prints as e.g. `"7 (unknown)"`.
    """
    number = level[0] if isinstance(level, bytes | bytearray) else int(level)
    return f"{number} ({DIAGNOSTIC_LEVEL_NAMES.get(number, 'unknown')})"


# `rosidl_runtime_py.convert.message_to_yaml` is not part of the PyPI ROS wheels this project
# installs, so the conversion walks the message fields itself.
def message_to_plain(msg: Any) -> Any:
    """A ROS message (or field value) as plain dicts, lists and scalars, fields in order.

    Nested messages become dicts keyed by field name, sequences and arrays (Python lists,
    `array.array`, numpy arrays) become lists, `bytes` a list of ints; a single `octet`/`byte`
    field (rclpy gives a `bytes` of length 1) becomes its int, and a DiagnosticStatus `level`
    its number and name (`diagnostic_level_text`). Floats go through `plain_float`: subnormals
    print as 0.0, every other float at full precision.
    """
    if msg is None or isinstance(msg, _PLAIN):
        return msg
    if isinstance(msg, float):
        return plain_float(msg)
    if hasattr(msg, "get_fields_and_field_types"):
        return _message_fields(msg)
    if isinstance(msg, bytes | bytearray):
        return list(msg)
    if isinstance(msg, array.array | list | tuple):
        return [message_to_plain(item) for item in msg]
    if hasattr(msg, "tolist"):  # numpy arrays and scalars
        return message_to_plain(msg.tolist())
    return str(msg)


def _message_fields(msg: Any) -> dict[str, Any]:
    """The fields of a ROS message, in declaration order, as plain values."""
    is_status = f"{type(msg).__module__}.{type(msg).__name__}" == _DIAGNOSTIC_STATUS_TYPE
    plain: dict[str, Any] = {}
    for name, field_type in msg.get_fields_and_field_types().items():
        value = getattr(msg, name)
        if is_status and name == "level":
            plain[name] = diagnostic_level_text(value)
        elif field_type in ("octet", "byte") and isinstance(value, bytes) and len(value) == 1:
            plain[name] = value[0]
        else:
            plain[name] = message_to_plain(value)
    return plain


def message_to_yaml(msg: Any) -> str:
    """A ROS message as a block-style YAML document (no trailing `---`)."""
    return yaml.safe_dump(
        message_to_plain(msg), sort_keys=False, default_flow_style=False, allow_unicode=True
    )


class _Printer:
    """Subscription callback: print each message, count, and signal when enough were printed."""

    def __init__(self, limit: int | None, done: threading.Event) -> None:
        self.limit = limit
        self.printed = 0
        self.broken_pipe = False
        self._done = done

    def __call__(self, msg: Any) -> None:
        if self._done.is_set():
            return
        try:
            sys.stdout.write(message_to_yaml(msg) + "---\n")
            sys.stdout.flush()
        except BrokenPipeError:  # e.g. piped into `head`
            # Later writes (and the interpreter's final flush) go nowhere instead of failing.
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
            self.broken_pipe = True
            self._done.set()
            return
        self.printed += 1
        if self.limit is not None and self.printed >= self.limit:
            self._done.set()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the lca-echo console script."""
    try:
        all_args, own_args = tool_arguments(PROG, argv)
    except ToolStartError as exc:
        return fail(PROG, str(exc))
    args, limit = _parse_args(own_args)
    done = threading.Event()
    try:
        with stop_signals(lambda _name: done.set()), tool_context(all_args) as context:
            return _run_node(context, args, limit, done)
    except ToolStartError as exc:
        return fail(PROG, str(exc))


def _parse_args(own_args: list[str]) -> tuple[argparse.Namespace, int | None]:
    """The parsed arguments and the number of messages to print (None: no limit).

    Bad arguments exit through `parser.error` (status 2).
    """
    parser = echo_parser()
    args = parser.parse_args(own_args)
    limit: int | None = 1 if args.once else args.count
    if limit is not None and limit < 1:
        parser.error("--count must be >= 1")
    if math.isnan(args.wait_s) or args.wait_s < 0:
        parser.error("--wait-s must be >= 0")
    return args, limit


def _run_node(
    context: Context, args: argparse.Namespace, limit: int | None, done: threading.Event
) -> int:
    """Create the node and its executor, echo, and take both down again; the exit code."""
    node = Node(NODE_NAME, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        return _echo(node, executor, args, limit, done)
    except RecorderError as exc:
        return fail(PROG, str(exc))
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()


# --qos-reliability choices that override what the publishers offer ("auto" keeps that).
_FORCED_RELIABILITY = {
    "reliable": ReliabilityPolicy.RELIABLE,
    "best_effort": ReliabilityPolicy.BEST_EFFORT,
}


def _echo(
    node: Node,
    executor: Executor,
    args: argparse.Namespace,
    limit: int | None,
    done: threading.Event,
) -> int:
    """Wait for the topic's type, subscribe and print until `limit` messages or a signal.

    Raises:
        RecorderError: The topic's message type cannot be imported.
    """
    try:
        topic = node.resolve_topic_name(args.topic)
    except Exception as exc:  # rclpy's name validation errors
        return fail(PROG, f"bad topic name {args.topic!r}: {first_line(exc)}")
    msgtype = _wait_for_type(node, executor, topic, args.wait_s, done)
    if msgtype is None:
        if done.is_set():  # interrupted while waiting
            return EXIT_OK
        return fail(PROG, f"topic {topic} did not appear within {args.wait_s:g} s")
    msg_class = import_message_class(msgtype)
    qos = subscription_qos(topic, node.get_publishers_info_by_topic(topic))
    if args.qos_reliability in _FORCED_RELIABILITY:
        qos.reliability = _FORCED_RELIABILITY[args.qos_reliability]
    printer = _Printer(limit, done)
    node.create_subscription(msg_class, topic, cast("Callable[[Any], None]", printer), qos)
    while not done.is_set():
        executor.spin_once(timeout_sec=0.05)
    return EXIT_OK


def _wait_for_type(
    node: Node, executor: Executor, topic: str, wait_s: float, done: threading.Event
) -> str | None:
    """The first type of `topic` once it is in the graph; None after `wait_s` or a signal."""
    deadline_s = time.monotonic() + wait_s
    while not done.is_set():
        types = dict(node.get_topic_names_and_types())
        if types.get(topic):
            type_names: list[str] = types[topic]
            if len(type_names) > 1:
                print(
                    f"lca-echo: warning: {topic} has several types {type_names}; "
                    f"echoing {type_names[0]}",
                    file=sys.stderr,
                )
            return type_names[0]
        if time.monotonic() >= deadline_s:
            return None
        executor.spin_once(timeout_sec=0.05)
    return None
