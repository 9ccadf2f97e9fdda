"""lca-plot on a recorded closed loop: references beside the signals, drive-state changes, faults.

One bag per module: a lockstep simulator and the controller on the Fig. 15 ramp (the
`lca_hil_loop` fixture), recorded by lca-record's `BagRecorder` with the controller's
`velocity_commands`, run for 11.5 s of simulated time (the pivot passes 55 deg at about 9.9 s).
The shipped PlotJuggler and Foxglove layouts are checked against the same bag. Synthetic bags
written with rosbags test the fault bands.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest
import support
from rclpy.node import Node
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from lca_control.contract import (
    CURRENT_COMMANDS,
    DIAGNOSTIC_ARRAY_TYPE,
    DIAGNOSTICS,
    DRIVE_CHAIN_STATES,
    DRIVE_STATUS_PREFIX,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    MOTOR_STATES,
    VELOCITY_COMMANDS,
)
from lca_sim.cli import bagplot
from lca_sim.ros.record import BagRecorder

if TYPE_CHECKING:  # imported by pytest as a plugin (below), so its asserts are rewritten
    from lca_sim.ros.testing import HilLoop

pytest_plugins = ["lca_sim.ros.testing"]

LAYOUTS = support.CONFIG / "layouts"
PLOTJUGGLER_LAYOUT = LAYOUTS / "lca_hil.plotjuggler.xml"
FOXGLOVE_LAYOUT = LAYOUTS / "lca_hil.foxglove.json"
PERIOD_S = 0.004  # the simulator's control_period_s
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
    data = bagplot.read_bag(ramp_bag)
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
    changes = bagplot.drive_state_changes(bagplot.read_bag(ramp_bag))
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
    data = bagplot.read_bag(ramp_bag)
    assert bagplot.moved_joints(data) == ["pivot"]
    plots = bagplot.write_plots(data, tmp_path / "moved", "ramp")
    assert len(plots.written) == 5
    assert all(panels == ["pivot"] for panels in plots.panels.values())
    assert any("l_arm, c_arc, lift" in note for note in plots.notes)
    every = bagplot.write_plots(data, tmp_path / "all", "ramp", all_axes=True)
    assert all(p == list(JOINTS) for p in every.panels.values())
    assert bagplot.main([str(ramp_bag), "--out", str(tmp_path / "cli"), "--all-axes"]) == 0
    assert "left out" not in capsys.readouterr().err


def test_end_stop_warn_of_the_run_is_a_band_on_its_joint(ramp_bag: Path) -> None:
    """The lift rests on its lower end stop: the simulator's WARN is a band on the lift."""
    bands = bagplot.fault_bands(bagplot.read_bag(ramp_bag))
    lift = [b for b in bands if b.joint == "lift"]
    assert lift, bands
    assert lift[0].status == "lca_hil/simulator/lift"
    assert lift[0].level_name == "WARN"
    assert lift[0].message.startswith("end stop hit")


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
    data = bagplot.read_bag(bag)
    bands = bagplot.fault_bands(data)
    pivot = [b for b in bands if b.joint == "pivot"]
    assert len(pivot) == 1
    assert pivot[0].level_name == "WARN"
    assert pivot[0].message.startswith("back-driving: pivot moving at")
    assert (pivot[0].start_s, pivot[0].end_s) == pytest.approx((0.30, 0.60))
    node = [b for b in bands if not b.joint]
    assert [(b.status, b.level_name) for b in node] == [("lca_hil/simulator", "ERROR")]
    assert (node[0].start_s, node[0].end_s) == pytest.approx((0.80, 0.99))  # to the end
    changes = bagplot.drive_state_changes(data)["pivot"]
    assert [(c.before, c.after) for c in changes] == [("stop_hold", "motor_driving")]
    assert changes[0].time_s == pytest.approx(0.20)
    assert changes[0].position == pytest.approx(0.20)
    assert bagplot.main([str(bag), "--out", str(tmp_path / "plots")]) == 0
    err = capsys.readouterr().err
    assert f"no {VELOCITY_COMMANDS} in the bag" in err
    assert "ERROR lca_hil/simulator: stalled" in err
    assert (tmp_path / "plots" / "velocities.png").is_file()
    by_bag = bagplot.read_bag(bag, time_base="bag")
    assert bagplot.fault_bands(by_bag)[0].start_s == pytest.approx(0.30, abs=1e-6)
