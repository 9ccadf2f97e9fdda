"""lca-plot's panel marks from hand-made bag data: drive-state changes, fault bands, moved axes."""

from __future__ import annotations

import pytest

from lca_sim.cli.bag_events import (
    MOVE_THRESHOLD,
    drive_state_changes,
    fault_bands,
    moved_joints,
    plot_spec,
    state_order,
)
from lca_sim.ros.bag_read import BagData, DriveSeries, JointSeries, StatusSeries


def _data() -> BagData:
    """Pivot moves through two states and has one WARN; l_arm holds still."""
    data = BagData(time_base="header")
    time_s = [0.0, 0.1, 0.2, 0.3]
    for joint, positions in (("l_arm", [0.0] * 4), ("pivot", [0.0, 0.1, 0.2, 0.3])):
        series = JointSeries(time_s=list(time_s))
        series.values["position"] = positions
        data.joints[joint] = series
        drive = DriveSeries(time_s=list(time_s))
        drive.state = (
            ["stop_hold"] * 4 if joint == "l_arm" else ["stop_hold"] + ["motor_driving"] * 3
        )
        data.drives[joint] = drive
    data.statuses["lca_hil/simulator/pivot"] = StatusSeries(
        level=[0, 1, 1, 0],
        message=["ok", "back-driving 0.1", "back-driving 0.2", "ok"],
        kind=["ok", "back-driving", "back-driving", "ok"],
        time_s=list(time_s),
    )
    data.statuses["lca_hil/simulator"] = StatusSeries(
        level=[2], message=["behind"], kind=["behind"], time_s=[0.2]
    )
    return data


def test_a_state_change_is_found_with_the_position_at_its_time() -> None:
    """One change of the pivot, at its first sample in the new state; none of l_arm."""
    changes = drive_state_changes(_data())
    assert changes["l_arm"] == []
    (change,) = changes["pivot"]
    assert (change.time_s, change.before, change.after) == (0.1, "stop_hold", "motor_driving")
    assert change.position == pytest.approx(0.1)


def test_a_fault_band_lasts_while_level_and_fault_stay() -> None:
    """A changing message does not split the band; a node's own status belongs to no joint."""
    bands = fault_bands(_data())
    pivot = [b for b in bands if b.joint == "pivot"]
    assert [(b.level_name, b.start_s, b.end_s) for b in pivot] == [("WARN", 0.1, 0.3)]
    (own,) = [b for b in bands if not b.joint]
    assert own.level_name == "ERROR" and own.start_s == own.end_s == 0.2


def test_only_the_moved_axes_get_panels_unless_all_are_asked() -> None:
    """l_arm did not move more than MOVE_THRESHOLD: left out with a note, kept by all_axes."""
    data = _data()
    assert moved_joints(data) == ["pivot"]
    spec = plot_spec(data)
    assert spec.joints == ["pivot"] and spec.left_out == ["l_arm"]
    assert any(f"{MOVE_THRESHOLD:g}" in note for note in spec.notes)
    assert any(note.startswith("ERROR lca_hil/simulator") for note in spec.notes)
    assert plot_spec(data, all_axes=True).joints == ["l_arm", "pivot"]


def test_state_order_puts_the_stop_states_first() -> None:
    """The y ticks: every stop state, then the others as first seen."""
    order = state_order(["motor_driving", "stop_hold", "load_driving"])
    assert order.index("stop_hold") < order.index("motor_driving") < order.index("load_driving")
