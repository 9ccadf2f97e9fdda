"""lca-plot on a recorded closed loop: references beside the signals, drive-state changes, faults.

One bag per module: a lockstep simulator and the controller on the Fig. 15 ramp (the
`lca_hil_loop` fixture), recorded by lca-record's `BagRecorder` with the controller's
`velocity_commands`, run for 11.5 s of simulated time (the pivot passes 55 deg at about 9.9 s).
The shipped PlotJuggler and Foxglove layouts are checked against the same bag. Synthetic bags
written with rosbags test the fault bands.
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
import support
from rclpy.node import Node
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.contract import (
    CURRENT_COMMANDS,
    DIAGNOSTIC_ARRAY_TYPE,
    DIAGNOSTICS,
    DRIVE_CHAIN_STATES,
    DRIVE_STATUS_PREFIX,
    FLOAT64_MULTI_ARRAY_TYPE,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    MOTOR_STATES,
    VELOCITY_COMMANDS,
)
from lca_sim.cli import bag_events, bagplot, plotting
from lca_sim.ros import bag_read
from lca_sim.ros.record import BagRecorder

if TYPE_CHECKING:  # imported by pytest as a plugin (below), so its asserts are rewritten
    from lca_sim.ros.testing import HilLoop

pytest_plugins = ["lca_sim.ros.testing"]

LAYOUTS = support.CONFIG / "layouts"
PLOTJUGGLER_LAYOUT = LAYOUTS / "lca_hil.plotjuggler.xml"
FOXGLOVE_LAYOUT = LAYOUTS / "lca_hil.foxglove.json"
PERIOD_S = CONTROL_PERIOD_S  # the simulator's control_period_s (its default, the controller's)
RUN_S = 11.5
RECORDED = (
    JOINT_STATES,
    MOTOR_STATES,
    DRIVE_CHAIN_STATES,
    DIAGNOSTICS,
    VELOCITY_COMMANDS,
    CURRENT_COMMANDS,
)
RAMP_START_S, RAMP_END_S = 1.0, 11.0  # the controller's ramp: 0 to 5 deg/s, then 0 at once
RAMP_DEG_S2 = 0.5
TRACKING_TOLERANCE_DEG_S = 0.3  # the controller's velocity tracking on the ramp, after 2 s
TRANSITION_DEG = 55.0  # Fig. 15: motor driving -> load driving
STATE_AND_COMMANDS = (JOINT_STATES, MOTOR_STATES, VELOCITY_COMMANDS, CURRENT_COMMANDS)
JOINTS = ("l_arm", "pivot", "c_arc", "lift")


@pytest.fixture(scope="module")
def lca_hil_domain_id() -> int:
    """The loop of this module on its own domain id."""
    return 172


@pytest.fixture(scope="module")
def ramp_bag(
    lca_hil_running_loop: HilLoop, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Path]:
    """A bag of RUN_S s of the closed loop on the ramp, velocity_commands included."""
    loop = lca_hil_running_loop
    loop.reset()
    bag = tmp_path_factory.mktemp("ramp") / "bag"
    node = Node("test_bagplot_recorder", context=loop.context)
    loop.executor.add_node(node)
    recorder = BagRecorder(node, bag, [f"/{t}" if t[0] != "/" else t for t in RECORDED])
    try:
        recorder.start()
        loop.wait_for(
            lambda: len(recorder.matched) == len(RECORDED), "the recorder's subscriptions"
        )
        periods = round(RUN_S / PERIOD_S)
        loop.step(periods, timeout_s=240.0)
        loop.wait_for(
            lambda: all(recorder.counts[f"/{t}"] >= periods for t in STATE_AND_COMMANDS),
            "every state and command of the run in the bag",
        )
    finally:
        recorder.close()
        loop.executor.remove_node(node)
        node.destroy_node()
    yield bag


def test_reference_is_read_aligned_with_the_velocity(ramp_bag: Path) -> None:
    """velocity_commands, on the states' time axis, is the ramp; the pivot follows it."""
    data = bag_read.read_bag(ramp_bag)
    assert data.time_base == "header"
    pivot = data.joints["pivot"]
    reference = data.references[VELOCITY_COMMANDS]
    index = data.joint_names().index("pivot")
    assert data.joint_names() == list(JOINTS)
    commanded = dict(zip(reference.time_s, reference.column(index), strict=True))
    checked = 0
    offsets: list[float] = []
    samples = zip(pivot.time_s, pivot.header_ns, pivot.values["velocity"], strict=True)
    for t_s, header_ns, velocity in samples:
        sim_time_s = header_ns / 1e9  # the plot's time axis starts at the first state recorded
        if not 2.0 <= sim_time_s < RAMP_END_S - 0.05 or t_s not in commanded:
            continue
        ramp_deg_s = RAMP_DEG_S2 * (sim_time_s - RAMP_START_S)
        # The command answering each state is the ramp at that state's time, within the
        # controller's own one-period offset of its ramp's origin.
        offsets.append(round(math.degrees(commanded[t_s]) - ramp_deg_s, 9))
        assert abs(math.degrees(velocity - commanded[t_s])) < TRACKING_TOLERANCE_DEG_S, t_s
        checked += 1
    assert checked > 0.9 * (RAMP_END_S - 2.05) / PERIOD_S
    # Commands are placed by reception order, which may put one a period off its state (the
    # recorder's subscriptions are not ordered across topics): the offset stays within one
    # period's ramp increment.
    assert max(abs(o) for o in offsets) <= RAMP_DEG_S2 * PERIOD_S + 1e-9
    other = data.joint_names().index("l_arm")
    assert set(reference.column(other)) == {0.0}  # the other joints hold
    assert CURRENT_COMMANDS in data.references


def test_drive_state_changes_include_the_switch_to_load_driving(ramp_bag: Path) -> None:
    """The pivot leaves motor driving for a state in which the load drives, near 55 deg."""
    changes = bag_events.drive_state_changes(bag_read.read_bag(ramp_bag))
    assert changes["l_arm"] == []  # a held, self-locking axis stays in its stop state
    switch = next(
        c for c in changes["pivot"] if c.before == "motor_driving" and "load_driving" in c.after
    )
    assert math.degrees(switch.position) == pytest.approx(TRANSITION_DEG, abs=1.0)
    assert RAMP_START_S < switch.time_s < RAMP_END_S


def test_unmoved_axes_are_left_out_unless_asked(
    ramp_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Only the pivot moves on the ramp: one panel per figure, four with --all-axes."""
    data = bag_read.read_bag(ramp_bag)
    assert bag_events.moved_joints(data) == ["pivot"]
    plots = bagplot.write_plots(data, tmp_path / "moved", "ramp")
    assert len(plots.written) == 5
    assert all(panels == ["pivot"] for panels in plots.panels.values())
    assert any("l_arm, c_arc, lift" in note for note in plots.notes)
    every = bagplot.write_plots(data, tmp_path / "all", "ramp", all_axes=True)
    assert all(p == list(JOINTS) for p in every.panels.values())
    assert bagplot.main([str(ramp_bag), "--out", str(tmp_path / "cli"), "--all-axes"]) == 0
    assert "left out" not in capsys.readouterr().err


def test_a_healthy_run_has_no_fault_band(ramp_bag: Path) -> None:
    """The lift parked on its lower end stop is no fault: the healthy ramp shows no band."""
    data = bag_read.read_bag(ramp_bag)
    assert bag_events.fault_bands(data) == []


def write_warn_bag(path: Path, n: int = 100) -> None:
    """States every 10 ms (the pivot moving), /diagnostics: the pivot WARN from 0.3 to 0.6 s.

    The WARN's message changes (the speed in it), its `fault` value does not; the simulator's
    own status is ERROR from 0.8 s to the end. No velocity_commands or current_commands.
    """
    store = get_typestore(Stores.ROS2_JAZZY)
    t = store.types
    status_cls = t["diagnostic_msgs/msg/DiagnosticStatus"]
    kv = t["diagnostic_msgs/msg/KeyValue"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        joint_conn = writer.add_connection(f"/{JOINT_STATES}", JOINT_STATE_TYPE, typestore=store)
        drive_conn = writer.add_connection(
            f"/{DRIVE_CHAIN_STATES}", DIAGNOSTIC_ARRAY_TYPE, typestore=store
        )
        diag_conn = writer.add_connection(DIAGNOSTICS, DIAGNOSTIC_ARRAY_TYPE, typestore=store)
        for k in range(n):
            stamp_ns = k * 10_000_000
            header = t["std_msgs/msg/Header"](
                stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=stamp_ns), frame_id=""
            )
            positions = [0.0, 0.01 * k, 0.0, 0.0]
            state = t[JOINT_STATE_TYPE](
                header=header,
                name=list(JOINTS),
                position=np.array(positions),
                velocity=np.array([0.0, 1.0, 0.0, 0.0]),
                effort=np.zeros(4),
            )
            drive = "stop_hold" if k < 20 else "motor_driving"
            drives = t[DIAGNOSTIC_ARRAY_TYPE](
                header=header,
                status=[
                    status_cls(
                        level=0,
                        name=f"{DRIVE_STATUS_PREFIX}{joint}",
                        message=drive if joint == "pivot" else "stop_hold",
                        hardware_id="",
                        values=[
                            kv(key="drive_state", value=drive if joint == "pivot" else "stop_hold")
                        ],
                    )
                    for joint in JOINTS
                ],
            )
            warn = 30 <= k < 60
            pivot = status_cls(
                level=1 if warn else 0,
                name="lca_hil/simulator/pivot",
                message=f"back-driving: pivot moving at {0.1 * k:.3g} rad/s with no command"
                if warn
                else drive,
                hardware_id="",
                values=[kv(key="fault", value="back-driving" if warn else "none")],
            )
            node = status_cls(
                level=2 if k >= 80 else 0,
                name="lca_hil/simulator",
                message="stalled" if k >= 80 else "running",
                hardware_id="",
                values=[],
            )
            diagnostics = t[DIAGNOSTIC_ARRAY_TYPE](header=header, status=[node, pivot])
            bag_ns = 1_000_000_000 + stamp_ns
            for conn, msg in ((joint_conn, state), (drive_conn, drives), (diag_conn, diagnostics)):
                writer.write(conn, bag_ns + 1, store.serialize_cdr(msg, conn.msgtype))


def test_warn_status_is_a_band_and_a_missing_reference_is_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A synthetic /diagnostics WARN of the pivot is one band; no velocity_commands is noted."""
    bag = tmp_path / "bag"
    write_warn_bag(bag)
    data = bag_read.read_bag(bag)
    bands = bag_events.fault_bands(data)
    pivot = [b for b in bands if b.joint == "pivot"]
    assert len(pivot) == 1
    assert pivot[0].level_name == "WARN"
    assert pivot[0].message.startswith("back-driving: pivot moving at")
    assert (pivot[0].start_s, pivot[0].end_s) == pytest.approx((0.30, 0.60))
    node = [b for b in bands if not b.joint]
    assert [(b.status, b.level_name) for b in node] == [("lca_hil/simulator", "ERROR")]
    assert (node[0].start_s, node[0].end_s) == pytest.approx((0.80, 0.99))  # to the end
    changes = bag_events.drive_state_changes(data)["pivot"]
    assert [(c.before, c.after) for c in changes] == [("stop_hold", "motor_driving")]
    assert changes[0].time_s == pytest.approx(0.20)
    assert changes[0].position == pytest.approx(0.20)
    assert bagplot.main([str(bag), "--out", str(tmp_path / "plots")]) == 0
    err = capsys.readouterr().err
    assert f"no {VELOCITY_COMMANDS} in the bag" in err
    assert "ERROR lca_hil/simulator: stalled" in err
    assert (tmp_path / "plots" / "velocities.png").is_file()
    by_bag = bag_read.read_bag(bag, time_base="bag")
    assert bag_events.fault_bands(by_bag)[0].start_s == pytest.approx(0.30, abs=1e-6)


# --- the shipped PlotJuggler and Foxglove layouts, checked against the recorded bag ------------


@dataclass(frozen=True)
class BagSample:
    """What a layout can name in a bag: each topic's type and some of its messages.

    Attributes:
        types: topic -> message type (`pkg/msg/Type`).
        messages: topic -> deserialized messages: the first and the last of each state and
            command topic, every /diagnostics message (each node publishes its own array).
        joints: `joint_states`' names; element i of a command array belongs to joints[i].
    """

    types: Mapping[str, str]
    messages: Mapping[str, list[Any]]
    joints: tuple[str, ...]


def sample_bag(bag: Path) -> BagSample:
    """Read a bag's topics and a sample of its messages (see BagSample)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    raw: dict[str, list[tuple[bytes, str]]] = {}
    with Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, _, data in reader.messages():
            kept = raw.setdefault(conn.topic, [])
            if conn.topic == DIAGNOSTICS or len(kept) < 2:
                kept.append((bytes(data), conn.msgtype))
            else:
                kept[-1] = (bytes(data), conn.msgtype)
    messages: dict[str, list[Any]] = {
        topic: [store.deserialize_cdr(data, msgtype) for data, msgtype in kept]
        for topic, kept in raw.items()
    }
    joints = tuple(messages[f"/{JOINT_STATES}"][0].name)
    return BagSample(types, messages, joints)


@pytest.fixture(scope="module")
def bag_sample(ramp_bag: Path) -> BagSample:
    """The recorded ramp bag, sampled for the layout checks."""
    return sample_bag(ramp_bag)


@dataclass(frozen=True)
class Series:
    """What one layout path found in the bag: the values and the joint they belong to ('')."""

    values: list[Any]
    joint: str = ""


JOINT_STATE_FIELDS = ("position", "velocity", "effort")


def _is_number(value: Any) -> bool:
    """A value a plot can draw: a number, or a string that parses as one ('nan' included)."""
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return False
        return True
    return isinstance(value, (int, float, np.integer, np.floating))


# PlotJuggler's ROS 2 parser (plotjuggler_plugins/ParserROS, ros_parser.cpp) names series:
#   JointState:        <topic>/<name[i]>/position|velocity|effort
#   DiagnosticArray:   <topic>/<status.name>/<key>, <topic>/<hardware_id>/<status.name>/<key>
#                      when hardware_id is set; a value that does not parse as a number becomes
#                      a string series, which a curve cannot show
#   other messages:    the field path joined by '/', array elements as field[i]
_PJ_ARRAY_ELEMENT = re.compile(r"data\[(\d+)\]")


def _pj_joint_state(msg: Any, rest: str) -> Series:
    joint, _, field = rest.rpartition("/")
    if field not in JOINT_STATE_FIELDS or joint not in list(msg.name):
        return Series([])
    values = getattr(msg, field)
    if len(values) != len(msg.name):
        return Series([])
    return Series([float(values[list(msg.name).index(joint)])], joint)


def _pj_diagnostics(msg: Any, rest: str, joints: tuple[str, ...]) -> Series:
    for status in msg.status:
        prefix = f"{status.hardware_id}/{status.name}" if status.hardware_id else status.name
        for kv in status.values:
            if rest == f"{prefix}/{kv.key}" and _is_number(kv.value):
                last = status.name.rpartition("/")[2]
                return Series([kv.value], last if last in joints else "")
    return Series([])


def _pj_array(msg: Any, rest: str, joints: tuple[str, ...]) -> Series:
    match = _PJ_ARRAY_ELEMENT.fullmatch(rest)
    if match is None or int(match[1]) >= len(msg.data):
        return Series([])
    index = int(match[1])
    return Series([float(msg.data[index])], joints[index] if index < len(joints) else "")


def plotjuggler_series(curve: str, bag: BagSample) -> Series | str:
    """The values a PlotJuggler curve name finds in the sampled bag, or what is wrong with it."""
    topics = [t for t in bag.types if curve.startswith(t + "/")]
    if not topics:
        return f"{curve}: no topic of the bag"
    topic = max(topics, key=len)
    rest = curve[len(topic) + 1 :]
    msgtype = bag.types[topic]
    found = Series([])
    for msg in bag.messages[topic]:
        if msgtype == JOINT_STATE_TYPE:
            series = _pj_joint_state(msg, rest)
        elif msgtype == DIAGNOSTIC_ARRAY_TYPE:
            series = _pj_diagnostics(msg, rest, bag.joints)
        elif msgtype == FLOAT64_MULTI_ARRAY_TYPE:
            series = _pj_array(msg, rest, bag.joints)
        else:
            return f"{curve}: {msgtype} is not a type this check knows"
        if series.joint and found.joint and series.joint != found.joint:
            return f"{curve}: joint {series.joint} in one message, {found.joint} in another"
        found = Series(found.values + series.values, series.joint or found.joint)
    if not found.values:
        return f"{curve}: no numeric series of that name in {topic} ({msgtype})"
    return found


_PJ_NODES = ("DockSplitter", "DockArea")


def _splitter_problems(splitter: ET.Element) -> list[str]:
    """PlotJuggler's PlotDocker::restoreSplitter reads count children and count sizes."""
    children = list(splitter)
    sizes = splitter.get("sizes", "").split(";")
    problems = []
    if splitter.get("orientation") not in ("|", "-"):
        problems.append(f"splitter orientation {splitter.get('orientation')!r}")
    if not int(splitter.get("count", "0")) == len(children) == len(sizes):
        problems.append(f"splitter count {splitter.get('count')}, {len(children)} children")
    elif abs(sum(float(s) for s in sizes) - 1.0) > 1e-3:
        problems.append(f"splitter sizes {sizes} do not add up to 1")
    problems += [f"<{c.tag}> in a splitter" for c in children if c.tag not in _PJ_NODES]
    return problems


def _area_problems(area: ET.Element, bag: BagSample) -> list[str]:
    """One plot of time series, each curve in the bag and of the joint the area is named for."""
    name = area.get("name", "")
    plots = area.findall("plot")
    if len(plots) != 1 or plots[0].get("mode") != "TimeSeries":
        return [f"area {name!r}: not one TimeSeries plot"]
    curves = [c.get("name", "") for c in plots[0].findall("curve")]
    if not curves:
        return [f"area {name!r}: no curve"]
    problems = []
    for curve in curves:
        series = plotjuggler_series(curve, bag)
        if isinstance(series, str):
            problems.append(series)
        elif series.joint and series.joint != name.split()[0]:
            problems.append(f"area {name!r}: {curve} is the {series.joint}'s")
    return problems


def plotjuggler_problems(root: ET.Element, bag: BagSample) -> list[str]:
    """Everything in a PlotJuggler layout that does not fit the bag or the layout format."""
    if root.tag != "root":
        return [f"root element <{root.tag}>"]
    problems = [
        f"tabbed_widget {w.get('name')!r} has no main_window parent"
        for w in root.iter("tabbed_widget")
        if w.get("parent") != "main_window"
    ]
    for tab in root.iter("Tab"):
        containers = tab.findall("Container")
        if int(tab.get("containers", "0")) != len(containers):
            problems.append(f"tab {tab.get('tab_name')!r}: containers attribute")
        problems += [
            f"tab {tab.get('tab_name')!r}: a container without one splitter"
            for c in containers
            if [e.tag for e in c] != ["DockSplitter"]
        ]
    for splitter in root.iter("DockSplitter"):
        problems += _splitter_problems(splitter)
    for area in root.iter("DockArea"):
        problems += _area_problems(area, bag)
    return problems


# Foxglove message paths (the Plot and State Transitions panels): /topic.field[i].field,
# [:] for every element, {field==value} to keep the elements whose field has that value,
# $name for a global variable.
_FG_PATH = re.compile(r"(?P<topic>(?:/\w+)+)(?P<rest>(?:\.\w+(?:\[[^\]]*\])?(?:\{[^}]*\})?)+)")
_FG_ELEMENT = re.compile(r"\.(?P<name>\w+)(?:\[(?P<slice>[^\]]*)\])?(?:\{(?P<filter>[^}]*)\})?")
_FG_FILTER = re.compile(r"(?P<field>\w+(?:\.\w+)*)==(?P<value>\"[^\"]*\"|'[^']*'|-?\d+|\$\w+)")


def _fg_literal(text: str, variables: Mapping[str, Any]) -> Any:
    if text.startswith("$"):
        return variables[text[1:]]
    if text[0] in "\"'":
        return text[1:-1]
    return int(text)


def _fg_index_joint(parent: Any, field: str, index: int, joints: tuple[str, ...]) -> str:
    """The joint an element index selects: JointState arrays by name, command arrays by order."""
    msgtype = getattr(parent, "__msgtype__", "")
    if msgtype == JOINT_STATE_TYPE and field in JOINT_STATE_FIELDS:
        return str(parent.name[index])
    if msgtype == FLOAT64_MULTI_ARRAY_TYPE and field == "data" and index < len(joints):
        return joints[index]
    return ""


def _fg_slice(
    items: list[tuple[Any, str]],
    parent: list[Any],
    field: str,
    text: str,
    variables: Mapping[str, Any],
    joints: tuple[str, ...],
) -> list[tuple[Any, str]]:
    if text == ":":
        return [(element, joint) for value, joint in items for element in value]
    index = int(_fg_literal(text, variables))
    return [
        (value[index], _fg_index_joint(owner, field, index, joints) or joint)
        for (value, joint), owner in zip(items, parent, strict=True)
        if 0 <= index < len(value)
    ]


def _fg_filter(
    items: list[tuple[Any, str]], text: str, variables: Mapping[str, Any], joints: tuple[str, ...]
) -> list[tuple[Any, str]]:
    match = _FG_FILTER.fullmatch(text)
    assert match is not None, f"filter {{{text}}}"
    wanted = _fg_literal(match["value"], variables)
    kept = []
    for value, joint in items:
        field = value
        for name in match["field"].split("."):
            field = getattr(field, name)
        if field == wanted:
            last = str(wanted).rpartition("/")[2] if isinstance(wanted, str) else ""
            kept.append((value, last if last in joints else joint))
    return kept


def foxglove_series(path: str, bag: BagSample, variables: Mapping[str, Any]) -> Series | str:
    """The values a Foxglove message path finds in the sampled bag, or what is wrong with it."""
    match = _FG_PATH.fullmatch(path)
    if match is None:
        return f"{path}: not a message path this check reads"
    topic = match["topic"]
    if topic not in bag.types:
        return f"{path}: no topic {topic} in the bag"
    items: list[tuple[Any, str]] = [(msg, "") for msg in bag.messages[topic]]
    for element in _FG_ELEMENT.finditer(match["rest"]):
        name = element["name"]
        if not all(hasattr(value, name) for value, _ in items):
            return f"{path}: no field {name} ({bag.types[topic]})"
        parents = [value for value, _ in items]
        items = [(getattr(value, name), joint) for value, joint in items]
        if element["slice"] is not None:
            items = _fg_slice(items, parents, name, element["slice"], variables, bag.joints)
        if element["filter"] is not None:
            items = _fg_filter(items, element["filter"], variables, bag.joints)
    joints = {joint for _, joint in items}
    if not items:
        return f"{path}: finds nothing in {topic}"
    if len(joints) > 1:
        return f"{path}: finds values of {sorted(joints)}"
    return Series([value for value, _ in items], joints.pop())


def _fg_panels(node: Any, config: Mapping[str, Any]) -> Iterator[str]:
    """Every panel id of a layout tree, Tab panels' own layouts included."""
    if isinstance(node, str):
        yield node
        for tab in config.get(node, {}).get("tabs", []) if node.startswith("Tab!") else []:
            yield from _fg_panels(tab["layout"], config)
    elif node is not None:
        assert node["direction"] in ("row", "column"), node
        assert 0 < node["splitPercentage"] < 100, node
        yield from _fg_panels(node["first"], config)
        yield from _fg_panels(node["second"], config)


_FG_PATH_PANELS = ("Plot", "StateTransitions")
_FG_TOPIC_PANELS = ("DiagnosticSummary", "DiagnosticStatusPanel")


def _fg_path_problems(
    path: Mapping[str, Any], kind: str, bag: BagSample, variables: Any
) -> list[str]:
    series = foxglove_series(path["value"], bag, variables)
    if isinstance(series, str):
        return [series]
    problems = []
    # Command arrays carry no header: every curve on the recorder's reception time, so the
    # references line up with the states they answer.
    if path.get("timestampMethod") != "receiveTime":
        problems.append(f"{path['value']}: timestampMethod {path.get('timestampMethod')}")
    label = path.get("label", "")
    if series.joint and label.split()[:1] != [series.joint]:
        problems.append(f"{path['value']}: the {series.joint}'s, labelled {label!r}")
    if kind == "Plot" and not all(_is_number(v) for v in series.values):
        problems.append(f"{path['value']}: not numbers ({series.values[:3]})")
    return problems


def foxglove_problems(doc: Mapping[str, Any], bag: BagSample) -> list[str]:
    """Everything in a Foxglove layout that does not fit the bag or the layout format."""
    config = doc["configById"]
    variables = doc.get("globalVariables", {})
    panels = list(_fg_panels(doc["layout"], config))
    problems = [f"panel {p} twice in the layout" for p in set(panels) if panels.count(p) > 1]
    if set(panels) != set(config):
        problems.append(f"layout panels {sorted(set(panels) ^ set(config))} vs configById")
    for panel_id, panel in config.items():
        kind = panel_id.partition("!")[0]
        if kind in _FG_PATH_PANELS:
            for path in panel["paths"]:
                problems += _fg_path_problems(path, kind, bag, variables)
        elif kind in _FG_TOPIC_PANELS:
            if bag.types.get(panel["topicToRender"]) != DIAGNOSTIC_ARRAY_TYPE:
                problems.append(f"{panel_id}: {panel['topicToRender']} is no DiagnosticArray")
        elif kind != "Tab":
            problems.append(f"{panel_id}: a panel this check does not know")
    return problems


def test_plotjuggler_layout_names_only_what_the_bag_has(bag_sample: BagSample) -> None:
    """Every curve of the PlotJuggler layout is a numeric series of the bag, on its own joint."""
    root = ET.parse(PLOTJUGGLER_LAYOUT).getroot()
    assert plotjuggler_problems(root, bag_sample) == []
    tabs = {tab.get("tab_name"): tab for tab in root.iter("Tab")}
    assert list(tabs) == ["pivot", "all joints"]
    areas = [a.get("name", "").split()[0] for a in tabs["all joints"].iter("DockArea")]
    assert set(areas) == set(bag_sample.joints)
    # The references beside their signals: each velocity with its velocity_commands element,
    # each motor current with its current_commands element, of the same joint.
    for area in root.iter("DockArea"):
        curves = [c.get("name", "") for c in area.iter("curve")]
        for joint in bag_sample.joints:
            i = bag_sample.joints.index(joint)
            if f"/{JOINT_STATES}/{joint}/velocity" in curves:
                assert f"/{VELOCITY_COMMANDS}/data[{i}]" in curves, area.get("name")
            if f"/{MOTOR_STATES}/{joint}/effort" in curves:
                assert f"/{CURRENT_COMMANDS}/data[{i}]" in curves, area.get("name")


def test_foxglove_layout_names_only_what_the_bag_has(bag_sample: BagSample) -> None:
    """Every Foxglove path resolves in the bag to its labelled joint; the panels tile the tabs."""
    doc = json.loads(FOXGLOVE_LAYOUT.read_text())
    assert foxglove_problems(doc, bag_sample) == []
    tabs = doc["configById"][doc["layout"]]["tabs"]
    assert [t["title"] for t in tabs] == ["pivot", "all joints"]
    paths = [p["value"] for panel in doc["configById"].values() for p in panel.get("paths", [])]
    for i, joint in enumerate(bag_sample.joints):
        assert f"/{JOINT_STATES}.velocity[{i}]" in paths, joint
        assert f"/{VELOCITY_COMMANDS}.data[{i}]" in paths, joint
        assert f"/{CURRENT_COMMANDS}.data[{i}]" in paths, joint
    # The pivot's drive state goes from motor driving to load driving on the ramp: the State
    # Transitions path sees both.
    drive = foxglove_series(
        f'/{DRIVE_CHAIN_STATES}.status[:]{{name=="{DRIVE_STATUS_PREFIX}pivot"}}'
        '.values[:]{key=="drive_state"}.value',
        bag_sample,
        {},
    )
    assert isinstance(drive, Series)
    assert drive.joint == "pivot"
    assert drive.values[0] != drive.values[-1]
    assert drive.values[-1] != "motor_driving"


def test_layout_checks_catch_a_joint_or_topic_the_bag_lacks(bag_sample: BagSample) -> None:
    """A wrong joint, index, topic or field in either layout is reported, not passed."""
    xml_text = PLOTJUGGLER_LAYOUT.read_text()
    eta = "/drive_chain_states/drive_chain/pivot/eta_m"
    for wrong, changed in (
        ("/joint_states/pivot/velocity", "/joint_states/wrist/velocity"),
        ("/velocity_commands/data[1]", "/velocity_commands/data[7]"),
        ("/velocity_commands/data[1]", "/velocity_commands/data[0]"),  # the l_arm's
        (eta, eta.replace("eta_m", "eta")),
        (eta, eta.replace("drive_chain_states", "drive_states")),
    ):
        assert wrong in xml_text, wrong
        root = ET.fromstring(xml_text.replace(wrong, changed, 1))
        problems = plotjuggler_problems(root, bag_sample)
        assert any(changed in p for p in problems), (changed, problems)
    json_text = FOXGLOVE_LAYOUT.read_text()
    for wrong, changed, said in (
        ("/joint_states.velocity[1]", "/joint_states.velocity[4]", "finds nothing"),
        ("/current_commands.data[1]", "/current_commands.data[2]", "the c_arc's"),
        ("chain/pivot", "chain/wrist", "finds nothing"),
        ("/motor_states.effort[1]", "/motor_state.effort[1]", "no topic /motor_state "),
        ('key==\\"eta_m', 'key==\\"eta', "finds nothing"),
    ):
        assert wrong in json_text, wrong
        problems = foxglove_problems(json.loads(json_text.replace(wrong, changed, 1)), bag_sample)
        assert any(said in p for p in problems), (changed, problems)


# --- the figures of the ramp, read back from matplotlib's artists ------------------------------


def _rendered(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Keep every figure lca-plot saves (drawn, by file name), its renderer as `_test_renderer`."""
    figures: dict[str, Any] = {}

    def keep(fig: Any, path: Path) -> None:
        fig.tight_layout()  # as save_png lays it out
        fig.canvas.draw()
        fig._test_renderer = fig.canvas.get_renderer()  # pyplot's close drops the Agg canvas
        figures[path.name] = fig

    monkeypatch.setattr(bagplot, "save_png", keep)
    return figures


def test_ramp_figures_draw_the_reference_and_labels_that_do_not_overlap(
    ramp_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The main job's figures: the reference beside the velocity, one label per readable gap."""
    figures = _rendered(monkeypatch)
    data = bag_read.read_bag(ramp_bag)
    bagplot.write_plots(data, tmp_path, "ramp")
    assert set(figures) == {
        "positions.png", "velocities.png", "currents.png", "drive_states.png", "efficiencies.png"
    }  # fmt: skip
    (velocity,) = figures["velocities.png"].axes
    reference = next(
        line for line in velocity.lines if line.get_label() == f"{VELOCITY_COMMANDS} (reference)"
    )
    ramp = np.asarray(reference.get_ydata(), dtype=float)
    assert max(ramp) == pytest.approx(5.0, abs=RAMP_DEG_S2 * PERIOD_S + 1e-9)  # deg/s
    assert velocity.get_ylabel() == "pivot velocity (deg/s)"
    changes = bag_events.drive_state_changes(data)["pivot"]
    fast = [c for c in changes if RAMP_END_S <= c.time_s < RAMP_END_S + 0.1]
    assert len(fast) >= 3  # the stop at 11 s: several changes within 0.1 s
    for name, fig in figures.items():
        renderer = fig._test_renderer
        for panel in fig.axes:
            labels = [t for t in panel.texts if t.get_gid() == bagplot.STATE_LABEL_GID]
            boxes = [t.get_window_extent(renderer) for t in labels]
            assert 2 <= len(boxes) < len(changes), name
            for i, a in enumerate(boxes):
                for b in boxes[i + 1 :]:
                    assert not a.overlaps(b), (name, a, b)
            legend = panel.get_legend()
            assert legend is not None, name
            assert not any(box.overlaps(legend.get_window_extent(renderer)) for box in boxes)
            assert panel.get_xlim() == figures["positions.png"].axes[0].get_xlim(), name
    texts = [t.get_text() for t in figures["drive_states.png"].axes[0].texts]
    assert any("changes in" in t and "ms ->" in t for t in texts), texts


def test_the_braking_spike_is_clipped_and_marked(
    ramp_bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """currents.png: the y range holds the ramp's 0-2.5 A; the stop's -20 A peak is marked."""
    figures = _rendered(monkeypatch)
    data = bag_read.read_bag(ramp_bag)
    plots = bagplot.write_plots(data, tmp_path, "ramp")
    current = np.asarray(data.motors["pivot"].values["effort"])
    assert current.min() < -15.0  # the velocity loop brakes at its limit at 11 s
    (panel,) = figures["currents.png"].axes
    low, high = panel.get_ylim()
    ramp = current[(np.asarray(data.motors["pivot"].time_s) > 2.0) & (current > 0.0)]
    assert low > -5.0 and high < 5.0 and high > ramp.max()
    (marker,) = [line for line in panel.lines if line.get_gid() == plotting.CLIPPED_GID]
    assert set(np.asarray(marker.get_ydata(), dtype=float)) == {low}
    assert f"min {current.min():.3g} A" in str(marker.get_label())
    (side,) = plots.clipped["currents.png:pivot"]
    assert side.extreme == pytest.approx(current.min())
    assert RAMP_END_S <= side.time < RAMP_END_S + 0.1
    assert any(f"{current.min():.3g} A at" in t.get_text() for t in panel.texts)
    assert "currents.png:pivot" in plots.clipped and "velocities.png:pivot" not in plots.clipped
