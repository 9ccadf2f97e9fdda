"""Faults injected into the running nodes: live parameters, a schedule, and what a user sees.

One lockstep loop (the `lca_hil_loop` fixture: simulator here, controller as a process) on the
Fig. 15 ramp, with the shipped schedule config/faults/pivot_encoder_freeze.yaml (the pivot's
encoder frozen 2.0-2.5 s, the pivot jammed 6-7 s) and a live jam of the pivot at 3.5-4.0 s, set
by parameter while the loop runs. Recorded into a bag; the tests read the
bag as a user would (lca-plot's reader) and assert that each fault is on when it should be, has
its physical effect, and shows in drive_chain_states and /diagnostics.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import support
from rclpy.node import Node
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from lca_control.cascade import CONTROL_PERIOD_S
from lca_control.contract import DIAGNOSTICS, DRIVE_CHAIN_STATES, JOINT_STATES
from lca_sim.cli import bag_events
from lca_sim.ros import bag_read
from lca_sim.ros.record import BagRecorder

if TYPE_CHECKING:
    from lca_sim.ros.testing import HilLoop

pytest_plugins = ["lca_sim.ros.testing"]

SCHEDULE = support.CONFIG / "faults" / "pivot_encoder_freeze.yaml"
FREEZE_S = (2.0, 2.5)  # the schedule's encoder freeze
LIVE_JAM_S = (3.5, 4.0)  # set live by the test
SCHEDULED_JAM_S = (6.0, 7.0)
RUN_S = 7.5
RECORDED = (f"/{JOINT_STATES}", f"/{DRIVE_CHAIN_STATES}", DIAGNOSTICS)


@pytest.fixture(scope="module")
def lca_hil_domain_id() -> int:
    """The loop of this module on its own domain id."""
    return 176


@pytest.fixture(scope="module")
def lca_hil_simulator_parameters() -> dict[str, Any]:
    """Lockstep with the shipped fault schedule, /diagnostics every 20 ms of wall time."""
    from lca_sim.ros.testing import SIMULATOR_DEFAULTS  # here: the module is a pytest plugin

    return {
        **SIMULATOR_DEFAULTS,
        "fault_schedule": str(SCHEDULE),
        "diagnostics_period_s": 0.02,
    }


def _periods(t_s: float) -> int:
    return round(t_s / CONTROL_PERIOD_S)


@pytest.fixture(scope="module")
def fault_bag(
    lca_hil_running_loop: HilLoop, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Path]:
    """The run, recorded: the schedule plays, and the pivot jams live at 3.5 s until 4.0 s."""
    loop = lca_hil_running_loop
    bag = tmp_path_factory.mktemp("faults") / "bag"
    node = Node("test_faults_recorder", context=loop.context)
    loop.executor.add_node(node)
    recorder = BagRecorder(node, bag, list(RECORDED))
    sim = loop.simulator
    try:
        loop.reset()  # paused at 0, as the bagplot test's bag: the recorder joins, then steps
        recorder.start()
        loop.wait_for(lambda: len(recorder.matched) == len(RECORDED), "the recorder")
        loop.step(_periods(LIVE_JAM_S[0]))
        assert loop.inject(sim, **{"faults.pivot.jam": True}) == ""
        loop.step(_periods(LIVE_JAM_S[1] - LIVE_JAM_S[0]))
        assert loop.inject(sim, **{"faults.pivot.jam": False}) == ""
        loop.step(_periods(RUN_S - LIVE_JAM_S[1]))
        loop.wait_for(
            lambda: recorder.counts[f"/{JOINT_STATES}"] >= _periods(RUN_S),
            "every state of the run in the bag",
        )
    finally:
        recorder.close()
        loop.executor.remove_node(node)
        node.destroy_node()
    yield bag


def _drive_faults(bag: Path, joint: str) -> list[tuple[float, str]]:
    """(header time, `faults` value) of `drive_chain/<joint>` in every drive_chain_states."""
    store = get_typestore(Stores.ROS2_JAZZY)
    out = []
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == f"/{DRIVE_CHAIN_STATES}"]
        for conn, _, raw in reader.messages(connections=conns):
            msg: Any = store.deserialize_cdr(raw, conn.msgtype)
            t_s = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            for status in msg.status:
                if status.name == f"drive_chain/{joint}":
                    out.append((t_s, {kv.key: kv.value for kv in status.values}["faults"]))
    return out


def _on_span(samples: list[tuple[float, str]], word: str) -> tuple[float, float]:
    times = [t for t, value in samples if word in value]
    assert times, f"{word} never on"
    return min(times), max(times)


def test_drive_chain_states_carry_each_fault_while_it_is_on(fault_bag: Path) -> None:
    """The `faults` key names each fault from its start to its end, to a control period."""
    samples = _drive_faults(fault_bag, "pivot")
    tolerance = CONTROL_PERIOD_S + 1e-9
    for word, (start, end) in (
        ("encoder_freeze", FREEZE_S),
        ("jam", (LIVE_JAM_S[0], SCHEDULED_JAM_S[1])),
    ):
        first, last = _on_span(samples, word)
        assert first == pytest.approx(start, abs=tolerance)
        assert last == pytest.approx(end, abs=tolerance)
    between = [v for t, v in samples if LIVE_JAM_S[1] + 0.01 < t < SCHEDULED_JAM_S[0] - 0.01]
    assert between and set(between) == {"none"}  # the live jam ended, the scheduled one later
    assert {v for _, v in _drive_faults(fault_bag, "l_arm")} == {"none"}


def test_frozen_encoder_reading_and_jammed_axis_in_joint_states(fault_bag: Path) -> None:
    """joint_states: the reading stands still while frozen; the jammed pivot does not move."""
    data = bag_read.read_bag(fault_bag, time_base="header")
    pivot = data.joints["pivot"]
    samples = list(zip(pivot.header_ns, pivot.values["position"], pivot.values["velocity"],
                       strict=True))  # fmt: skip
    frozen = [(q, v) for ns, q, v in samples if FREEZE_S[0] + 0.01 < ns / 1e9 < FREEZE_S[1]]
    assert len({q for q, _ in frozen}) == 1 and {v for _, v in frozen} == {0.0}
    moving = [v for ns, _, v in samples if 2.8 < ns / 1e9 < 3.4]
    assert min(moving) > math.radians(0.05)  # moving before the jam (the freeze's overspeed)
    jammed = [(q, v) for ns, q, v in samples if LIVE_JAM_S[0] + 0.05 < ns / 1e9 < LIVE_JAM_S[1]]
    assert len({q for q, _ in jammed}) == 1 and {v for _, v in jammed} == {0.0}


def test_diagnostics_warn_on_the_joint_and_lca_plot_draws_the_bands(fault_bag: Path) -> None:
    """/diagnostics: the pivot's status is WARN 'injected: ...' while a fault is on."""
    bands = [b for b in bag_events.fault_bands(bag_read.read_bag(fault_bag)) if b.joint == "pivot"]
    words = {b.message for b in bands}
    assert any("injected: encoder_freeze" in m for m in words), words
    assert any("injected: jam" in m for m in words), words
    assert all(b.level_name == "WARN" for b in bands if "injected" in b.message)


def test_a_bad_fault_value_is_refused_with_its_reason(lca_hil_loop: HilLoop) -> None:
    """An out-of-range value: refused, named, and the fault stays off."""
    sim = lca_hil_loop.simulator
    reason = lca_hil_loop.inject(sim, **{"faults.pivot.supply_sag": 1.5})
    assert "faults.pivot.supply_sag" in reason and "[0, 1]" in reason
    reason = lca_hil_loop.inject(sim, **{"faults.pivot.drift_state": "melting"})
    assert "motor_driving" in reason  # the states it may name
    assert sim.faults.describe("pivot") == "none"
    assert lca_hil_loop.inject(sim, fault_schedule="") != ""  # read-only while running


def test_link_delay_is_refused_in_lockstep_and_drop_counts(lca_hil_loop: HilLoop) -> None:
    """In lockstep a late state would stop the loop: the set is refused, saying so."""
    sim = lca_hil_loop.simulator
    reason = lca_hil_loop.inject(sim, **{"faults.link.state_delay_s": 0.012})
    assert "lockstep" in reason
    assert sim.faults.describe("link") == "none"


def test_lost_encoder_samples_show_on_the_controller(lca_hil_loop: HilLoop) -> None:
    """Half the pivot's samples lost: the loop runs on, the controller WARNs with the count."""
    from diagnostic_msgs.msg import DiagnosticArray

    loop = lca_hil_loop
    sim = loop.simulator
    seen: list[tuple[int, str, dict[str, str]]] = []

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == "lca_hil/controller":
                values = {kv.key: kv.value for kv in status.values}
                seen.append((int.from_bytes(status.level, "little"), status.message, values))

    sub = loop.node.create_subscription(DiagnosticArray, DIAGNOSTICS, on_diagnostics, 50)
    try:
        assert loop.inject(sim, **{"faults.pivot.encoder_dropout": 0.5}) == ""
        loop.step(100)  # every period still runs: a lost sample gets the last command again
        loop.wait_for(
            lambda: any(int(v.get("states_not_finite", "0")) > 10 for _, _, v in seen),
            "the controller's count of lost samples",
            timeout_s=30.0,
        )
        level, message, _ = next(s for s in seen if int(s[2].get("states_not_finite", "0")) > 10)
        assert level >= 1 and "NaN or infinite readings" in message
    finally:
        assert loop.inject(sim, **{"faults.pivot.encoder_dropout": 0.0}) == ""
        loop.node.destroy_subscription(sub)
