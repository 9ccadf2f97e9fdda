"""Small helpers shared by the ROS 2 node shells (parameters, stamps, diagnostics, main loop)."""

from __future__ import annotations

import math
import os
import signal
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Generic, TypeVar, cast

import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.context import Context
from rclpy.event_handler import (
    PublisherEventCallbacks,
    QoSPublisherMatchedInfo,
    QoSSubscriptionMatchedInfo,
    SubscriptionEventCallbacks,
)
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.type_support import check_is_valid_msg_type
from rclpy.utilities import ok as rclpy_ok
from rclpy.utilities import remove_ros_args

from lca_control import contract as pc
from lca_control.parameters import ParameterTable
from lca_sim.config.ros_params import (
    params_file_arguments,
    read_ros_params_file,
    sections_for_node,
)
from lca_sim.errors import EXIT_BAD_INPUT, EXIT_OK, USER_ERRORS, LcaHilError
from lca_sim.ros.contract_cdr import stamp_parts
from lca_sim.ros.dds_profile import PROFILE_ENV, use_shipped_profile
from lca_sim.ros.ros_logging import python_logging_on_ros
from lca_sim.runtime import settle_heap


def declare_table(node: Node, table: ParameterTable) -> dict[str, Any]:
    """Declare every parameter of `table`; return the values the node starts with.

    Each descriptor carries the description and the documented range, with "read-only" for
    a parameter that needs a restart, so `ros2 param describe` shows them. Refusing a live set
    of a read-only parameter is left to `LiveParameters`, which says to restart the node
    (rclpy's own read-only flag would refuse it before any callback, without saying so).
    Typing is left to the table's own check (`dynamic_typing`), which takes 500 for a double
    as well as 500.0 and names the parameter and the expected type when it refuses a value.
    """
    values: dict[str, Any] = {}
    for spec in table:
        constraints = spec.range_text()
        if not spec.live:
            constraints = f"{constraints}; read-only: restart the node to change it".lstrip("; ")
        descriptor = ParameterDescriptor(
            description=spec.description,
            additional_constraints=constraints,
            dynamic_typing=True,
        )
        values[spec.name] = node.declare_parameter(spec.name, spec.default, descriptor).value
    return values


Validated = TypeVar("Validated")


class LiveParameters(Generic[Validated]):
    """A node's on-set-parameters callback: every live set takes effect or is rejected.

    A set is checked as a whole: the proposed values go through the node's validator (the
    same one start-up used), then `apply(old, new, changed_names)` makes them take effect in
    the running node. A read-only parameter, a value the validator refuses, or an `apply` that
    raises a user error rejects the set with the reason, and the node keeps its old values.
    """

    def __init__(
        self,
        node: Node,
        table: ParameterTable,
        values: Mapping[str, Any],
        validate: Callable[[Mapping[str, Any]], Validated],
        apply: Callable[[Validated, Validated, frozenset[str]], None],
        owned_elsewhere: Callable[[str], bool] | None = None,
    ) -> None:
        self._table = table
        # Parameters another on-set callback owns (the fault injection's): not this one's.
        self._elsewhere = owned_elsewhere or (lambda _name: False)
        self._values = dict(values)
        self._validate = validate
        self._apply = apply
        self.params: Validated = validate(self._values)
        node.add_on_set_parameters_callback(self._on_set)

    @property
    def values(self) -> dict[str, Any]:
        """The raw values in force."""
        return dict(self._values)

    def _on_set(self, changes: Sequence[Parameter]) -> SetParametersResult:
        changes = [c for c in changes if not self._elsewhere(c.name)]
        if not changes:
            return accepted()
        names = frozenset(c.name for c in changes)
        fixed = sorted(n for n in names if n in self._table.read_only)
        if fixed:
            return rejected(f"{', '.join(fixed)}: read-only while running; restart the node")
        unknown = sorted(n for n in names if n not in self._table)
        if unknown:
            return rejected(f"{', '.join(unknown)}: not a parameter of this node")
        proposed = with_changes(self._values, changes)
        try:
            new = self._validate(proposed)
            self._apply(self.params, new, names)
        except USER_ERRORS as exc:
            return rejected(str(exc))
        self._values, self.params = proposed, new
        return accepted()


def set_enabled_by_service(node: Node, enabled: bool, disabled_message: str) -> tuple[bool, str]:
    """A `~/enable` (SetBool) service as a set of the node's `enabled` parameter.

    One path for the service and the parameter, so they never disagree. Returns the service
    response's success and message (the rejection reason if the set was refused).
    """
    result = node.set_parameters([Parameter("enabled", value=enabled)])[0]
    if not result.successful:
        return False, result.reason
    return True, "enabled" if enabled else disabled_message


def with_changes(base: Mapping[str, Any], changes: Sequence[Parameter]) -> dict[str, Any]:
    """A copy of `base` with the proposed parameter changes applied (for validation)."""
    merged = dict(base)
    for param in changes:
        merged[param.name] = param.value
    return merged


def rejected(reason: str) -> SetParametersResult:
    """A refused parameter change with its reason."""
    return SetParametersResult(successful=False, reason=reason)


def accepted() -> SetParametersResult:
    """An accepted parameter change."""
    return SetParametersResult(successful=True)


def to_stamp(t_s: float) -> Time:
    """Seconds (float) to builtin_interfaces/Time (`contract_cdr.stamp_parts`' split)."""
    sec, nanosec = stamp_parts(t_s)
    return Time(sec=sec, nanosec=nanosec)


def simulator_end_s(found: DiagnosticStatus) -> float | None:
    """The simulated time at which the simulator's lockstep run ended, if `found` says it did.

    `found` is one status of a /diagnostics array: the simulator's (`SIMULATOR_STATUS`) with
    `ENDED_KEY` = "True" gives its `sim_time_s` (NaN when that is missing or unreadable); any
    other status gives None.
    """
    if found.name != pc.SIMULATOR_STATUS:
        return None
    values = {kv.key: kv.value for kv in found.values}
    if values.get(pc.ENDED_KEY) != "True":
        return None
    try:
        return float(values["sim_time_s"])
    except (KeyError, ValueError):
        return math.nan


def from_stamp(stamp: Time) -> float:
    """builtin_interfaces/Time to seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def status(
    name: str, level: bytes, message: str, values: Mapping[str, object], hardware_id: str = ""
) -> DiagnosticStatus:
    """A DiagnosticStatus with string key/values (floats in repr form)."""
    return DiagnosticStatus(
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[KeyValue(key=k, value=_text(v)) for k, v in values.items()],
    )


def _text(value: object) -> str:
    if isinstance(value, float):
        return repr(value)
    return str(value)


def check_loopback_environment() -> None:
    """Warn (once, on stderr) when DDS discovery is not limited to this machine."""
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") != "LOCALHOST":
        print(
            "warning: ROS_AUTOMATIC_DISCOVERY_RANGE is not LOCALHOST: DDS may reach other "
            "machines (source scripts/env.sh)",
            file=sys.stderr,
        )


def make_executor(context: Context | None = None, kind: str = "events") -> Executor:
    """Rclpy's events executor (C++, rclpy.experimental) if available, else single-threaded.

    Measured on the 2-core machine: the events executor costs about 110 us of CPU per message
    taken against about 250 us for SingleThreadedExecutor. That halves the recorder's load
    (a recorder falling more than `STATE_QOS_DEPTH` messages behind on a topic loses the
    oldest) and the per-step overhead of the nodes in a lockstep loop.
    """
    if kind == "events":
        try:
            from rclpy.experimental.events_executor import EventsExecutor  # noqa: PLC0415
        except ImportError:
            pass
        else:
            return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


class MatchedCount:
    """The endpoints matched to a publisher or a subscription, from its matched events.

    Kept by the executor's thread (the node's event handlers), read on any thread: asking the
    graph instead (`get_subscription_count`, a call into rmw, about 6 us) on every cycle cost
    the CAN bridge 4 % of a 500 Hz cycle for three optional topics.
    """

    def __init__(self) -> None:
        self.count = 0

    def on_matched(self, info: QoSPublisherMatchedInfo | QoSSubscriptionMatchedInfo) -> None:
        """A matched event: the count it reports now."""
        self.count = info.current_count

    def publisher_callbacks(self) -> PublisherEventCallbacks:
        """For `create_publisher`: count its subscribers."""
        return PublisherEventCallbacks(matched=self.on_matched)

    def subscription_callbacks(self) -> SubscriptionEventCallbacks:
        """For a subscription (`unspun_subscription`): count its publishers."""
        return SubscriptionEventCallbacks(matched=self.on_matched)


def unspun_subscription(
    node: Node,
    msg_type: Any,
    topic: str,
    qos: QoSProfile,
    *,
    raw: bool,
    event_callbacks: SubscriptionEventCallbacks | None = None,
) -> Subscription:
    """A subscription of `node` that no executor takes from: its owner takes, when it chooses.

    Built as `Node.create_subscription` builds one (the node's remappings and namespace apply,
    and the graph shows the node as the topic's subscriber), but not registered with the node,
    so an executor spinning the node never takes its messages: the owner calls
    `sub.handle.take_message`. Its QoS-event handlers (`event_callbacks`) are the node's, as
    usual: the executor calls them. The owner destroys it (`destroy_unspun`) before the node.
    """
    check_is_valid_msg_type(msg_type)
    with node.handle:
        impl = _rclpy.Subscription(node.handle, msg_type, topic, qos.get_c_qos_profile())
    sub = Subscription(
        impl,
        msg_type,
        topic,
        lambda _msg: None,
        node.default_callback_group,
        qos,
        raw,
        event_callbacks or SubscriptionEventCallbacks(),
    )
    for handler in _event_handlers(sub):
        node.add_waitable(handler)
    return sub


def destroy_unspun(node: Node, sub: Subscription) -> None:
    """Destroy an `unspun_subscription` of `node` and its event handlers."""
    for handler in _event_handlers(sub):
        node.remove_waitable(handler)
    sub.destroy()


def _event_handlers(sub: Subscription) -> list[Any]:
    """A subscription's QoS-event handlers (a list; rclpy annotates it as one handler)."""
    return list(cast(Any, sub.event_handlers))


def run_node(prog: str, build: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Init rclpy, build the node, spin until SIGINT or SIGTERM, shut down cleanly.

    A configuration error while building the node is one line on stderr and exit code 2.
    """
    check_loopback_environment()
    own_profile = use_shipped_profile()  # before the first participant: Fast DDS reads it then
    stop = {"requested": False}

    def _on_signal(signum: int, _frame: object) -> None:
        stop["requested"] = True

    argv = list(args) if args is not None else list(sys.argv)
    try:
        params_files = [(path, read_ros_params_file(path)) for path in params_file_arguments(argv)]
    except USER_ERRORS as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    # Our handlers go in before rclpy.init, and rclpy installs none: a signal during start-up
    # then only asks for a clean stop instead of invalidating the context under the build.
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # rcl refused the ROS arguments (RCLError and kin)
        print(f"{prog}: error: cannot start ROS: {first_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    node: Node | None = None
    with python_logging_on_ros(prog) as ros_log:
        try:
            try:
                node = build()
            except USER_ERRORS as exc:
                print(f"{prog}: error: {exc}", file=sys.stderr)
                return EXIT_BAD_INPUT
            ros_log.ros_logger = node.get_logger()  # from now on on /rosout too
            _say_own_profile(node, own_profile)
            unused = _params_files_for_others(node, params_files)
            if unused:
                print(f"{prog}: error: {unused}", file=sys.stderr)
                return EXIT_BAD_INPUT
            executor = make_executor()
            executor.add_node(node)
            settle_heap()  # start-up objects out of the collector's sight: no 100 ms stalls later
            while not stop["requested"] and rclpy_ok():
                executor.spin_once(timeout_sec=0.1)
            return EXIT_OK
        except (KeyboardInterrupt, ExternalShutdownException):
            return EXIT_OK
        finally:
            if node is not None:
                node.destroy_node()  # what its parts log on the way down still goes to the log
            if rclpy_ok():
                rclpy.shutdown()


def _say_own_profile(node: Node, own_profile: str | None) -> None:
    """Log once that the user's Fast DDS profile is in force instead of the shipped one."""
    if own_profile:
        node.get_logger().info(
            f"Fast DDS profile {own_profile} ({PROFILE_ENV}); the shipped "
            "config/dds/fastdds.xml is not used (docs/can-transport.md)"
        )


def _params_files_for_others(
    node: Node, params_files: Sequence[tuple[Path, Mapping[str, Any]]]
) -> str:
    """Why a `--params-file` would set nothing on this node ("" when every one applies).

    rcl applies only the sections that name the node; a file of another node's (the
    controller's file given to the simulator) would leave every parameter at its default.
    """
    name = node.get_fully_qualified_name()
    for path, document in params_files:
        if not sections_for_node(document, name):
            others = ", ".join(str(key) for key in document)
            return (
                f"{path}: no parameters for node {name} (the file has {others}); "
                "nothing in it would be set"
            )
    return ""


def other_publishers(node: Node, topics: Sequence[str]) -> list[str]:
    """`topic: node, ...` for each topic another node (or a second node of this name) publishes.

    Read from the ROS graph (`get_publishers_info_by_topic`); the plants check their state
    topics with it, the controller its command topics.
    """
    me = node.get_fully_qualified_name()
    found: list[str] = []
    for topic in topics:
        names = [
            f"{info.node_namespace.rstrip('/')}/{info.node_name}"
            for info in node.get_publishers_info_by_topic(topic)
        ]
        others = sorted({name for name in names if name != me})
        if names.count(me) > 1:
            others.append(f"{me} (another node of this name)")
        if others:
            found.append(f"{topic}: {', '.join(others)}")
    return found


class ToolStartError(LcaHilError):
    """A ROS 2 console tool could not start: bad ROS arguments, or rclpy refused to init."""


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its class name if it has none).

    rcl's source locations (`, at /project/src/rcl/...`) are cut off.
    """
    text = str(exc).strip()
    line = text.splitlines()[0] if text else type(exc).__name__
    return line.split(", at /", 1)[0]


def tool_arguments(prog: str, argv: Sequence[str] | None) -> tuple[list[str], list[str]]:
    """A ROS tool's arguments with `prog` first, and its own ones (the ROS arguments removed).

    Raises:
        ToolStartError: ROS arguments rcl cannot read.
    """
    all_args = [prog, *(sys.argv[1:] if argv is None else argv)]
    try:
        return all_args, remove_ros_args(all_args)[1:]
    except Exception as exc:  # rclpy's RCLInvalidROSArgsError
        raise ToolStartError(f"bad ROS arguments: {first_line(exc)}") from None


@contextmanager
def tool_context(all_args: Sequence[str]) -> Iterator[Context]:
    """A ROS tool's own rclpy context (no rclpy signal handlers), shut down when the block ends.

    Raises:
        ToolStartError: rclpy refused the arguments or could not start.
    """
    use_shipped_profile()
    context = Context()
    try:
        try:
            rclpy.init(
                args=list(all_args), context=context, signal_handler_options=SignalHandlerOptions.NO
            )
        except Exception as exc:  # rclpy reports bad ROS arguments with its own exceptions
            raise ToolStartError(f"cannot start ROS: {first_line(exc)}") from None
        yield context
    finally:
        if context.ok():
            rclpy.shutdown(context=context)
