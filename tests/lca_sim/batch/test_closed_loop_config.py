"""A closed-loop run's config from the nodes' parameters: lca-hil run's, and a sweep point's.

A sweep's closed-loop point must run what `lca-hil run` would run with the same files: the
nodes' parameters checked as the nodes check them, the spec's `base.faults` schedule (or the
simulator's `fault_schedule`) and the simulator's standing `faults.<joint>.<kind>` parameters.
Before the fault tests the sweep dropped all faults without a word, so a study of a jammed
pivot computed the healthy one.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from support import CONFIG

from lca_control.parameters import ParameterError
from lca_sim.analysis.closed_loop import ClosedLoop
from lca_sim.batch.closed_loop_config import closed_loop_builder, closed_loop_config, load_config
from lca_sim.batch.compute import run_point
from lca_sim.batch.plan import load_spec
from lca_sim.batch.tasks import build_tasks
from lca_sim.config.params_file import node_parameters
from lca_sim.errors import ConfigError
from lca_sim.model.fault_schedule import ScheduledFault

DURATION_S = 3.0
PIVOT = 1


def _write(tmp_path: Path, name: str, document: dict[str, Any]) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _spec(**base: Any) -> dict[str, Any]:
    return {
        "base": {"kind": "closed_loop", "duration_s": DURATION_S, "axis": "pivot", **base},
        "parameters": [],
        "metrics": [{"metric": "peak_current_a"}, {"metric": "tracking_error_max"}],
    }


def _direct_peak(faults: tuple[ScheduledFault, ...], simulator: dict[str, Any]) -> float:
    """The pivot's peak current of the composed loop run with these faults (lca-hil run's)."""
    controller = node_parameters(CONFIG / "ros" / "controller.yaml", "controller")
    config = closed_loop_config(controller, simulator, DURATION_S)
    if faults:
        config = replace(config, faults=faults)
    result = ClosedLoop(config).run()
    return float(np.max(np.abs(result.current_a[:, result.axes.index("pivot")])))


def _simulator() -> dict[str, Any]:
    return node_parameters(CONFIG / "ros" / "simulator.yaml", "simulator")


def test_the_loop_refuses_what_the_nodes_could_not_run() -> None:
    """Interfaces that differ, or an end that is no whole number of steps: the parameter named."""
    controller = node_parameters(CONFIG / "ros" / "controller.yaml", "controller")
    simulator = {**_simulator(), "lockstep_end_s": 1.0}
    with pytest.raises(ParameterError, match=r"^command_interface: expected the controller's"):
        closed_loop_config({**controller, "command_interface": "voltage"}, simulator)
    with pytest.raises(ParameterError, match=r"^duration_s: expected a time > 0 s, a whole mul"):
        closed_loop_config(controller, simulator, duration_s=1.00005)
    with pytest.raises(ParameterError, match=r"^velocity_ti_s: expected"):
        closed_loop_config({**controller, "velocity_ti_s": -1.0}, simulator)
    with pytest.raises(ParameterError, match=r"^lockstep_end_s: expected a run's end > 0"):
        closed_loop_config(controller, _simulator())  # no length, and the shipped end is 0
    # Drive modes are the simulator node's: a composed run must not silently ignore them.
    modes = {**simulator, "drive_modes": ["current", "position", "current", "current"]}
    with pytest.raises(ParameterError, match=r"^drive_modes: expected none, or current for"):
        closed_loop_config(controller, modes)
    same = {**simulator, "drive_modes": ["current"] * 4}
    assert closed_loop_config(controller, same).plant.interface == "current"


def test_a_closed_loop_point_is_lca_hil_runs_loop(tmp_path: Path) -> None:
    """A closed-loop point with a controller gain set runs the loop `lca-hil run` runs."""
    spec_doc = {
        "base": {"kind": "closed_loop", "duration_s": 1.2, "axis": "pivot"},
        "parameters": [
            {"name": "kp", "path": "controller.velocity_kp_a_per_rad_s", "values": [200.0]}
        ],
        "metrics": [{"metric": "peak_current_a"}, {"metric": "tracking_error_max"}],
    }
    spec, documents = load_spec(_write(tmp_path, "spec.yaml", spec_doc))
    (task,) = build_tasks(spec, documents, "0", closed_loop_builder)
    outcome = run_point(task)
    controller = node_parameters(CONFIG / "ros" / "controller.yaml", "controller")
    config = closed_loop_config({**controller, "velocity_kp_a_per_rad_s": 200.0}, _simulator(), 1.2)
    result = ClosedLoop(config).run()
    pivot = result.axes.index("pivot")
    assert outcome.metrics["peak_current_a"] == float(np.max(np.abs(result.current_a[:, pivot])))
    error = result.tracking_error()[:, result.joints.index("pivot")]
    assert outcome.metrics["tracking_error_max"] == float(np.max(np.abs(error)))
    bad = {
        **spec_doc,
        "parameters": [{"name": "k", "path": "controller.velocity_kp", "values": [1]}],
    }
    spec, documents = load_spec(_write(tmp_path, "spec.yaml", bad))
    with pytest.raises(ConfigError, match="velocity_kp"):
        build_tasks(spec, documents, "0", closed_loop_builder)


def test_load_config_is_closed_loop_config_of_the_files() -> None:
    """`lca-hil run`'s config from the shipped params files: the values' config, unchanged."""
    controller = node_parameters(CONFIG / "ros" / "controller.yaml", "controller")
    expected = closed_loop_config(controller, _simulator(), 2.0)
    loaded = load_config(CONFIG / "ros" / "controller.yaml", CONFIG / "ros" / "simulator.yaml", 2.0)
    assert loaded == expected


def test_a_swept_jam_start_runs_the_schedule_lca_hil_run_runs(tmp_path: Path) -> None:
    """base.faults with its jam's start swept: each point is the composed run with that jam."""
    schedule = {
        "faults": [
            {"joint": "pivot", "kind": "encoder_freeze", "value": True, "start_s": 0.5,
             "end_s": 0.7},
            {"joint": "pivot", "kind": "jam", "value": True, "start_s": 2.0, "end_s": 2.8},
        ]
    }  # fmt: skip
    _write(tmp_path, "jam.yaml", schedule)
    spec_doc = _spec(faults="jam.yaml")
    spec_doc["parameters"] = [{"name": "jam_s", "path": "faults.1.start_s", "values": [1.0, 2.0]}]
    spec, documents = load_spec(_write(tmp_path, "spec.yaml", spec_doc))
    tasks = build_tasks(spec, documents, "0", closed_loop_builder)
    peaks = [run_point(task).metrics["peak_current_a"] for task in tasks]
    for jam_s, peak in zip((1.0, 2.0), peaks, strict=True):
        faults = (
            ScheduledFault("pivot", "encoder_freeze", True, 0.5, 0.7),
            ScheduledFault("pivot", "jam", True, jam_s, 2.8),
        )
        assert peak == _direct_peak(faults, _simulator())
    healthy = _direct_peak((), _simulator())
    # A jammed pivot's velocity loop winds up towards its current limit: far above the ramp's.
    assert min(peaks) > 2.0 * healthy
    assert tasks[0].key != tasks[1].key


def test_the_simulators_fault_schedule_and_standing_faults_reach_a_point(tmp_path: Path) -> None:
    """A simulator params file's fault_schedule and faults.* values (nested YAML) are run."""
    simulator_doc = {
        "simulator": {
            "ros__parameters": {
                **_simulator(),
                "fault_schedule": "pivot_encoder_freeze",
                "faults": {"pivot": {"payload_kg": 60.0}},
            }
        }
    }
    _write(tmp_path, "simulator.yaml", simulator_doc)
    spec, documents = load_spec(_write(tmp_path, "spec.yaml", _spec(simulator="simulator.yaml")))
    assert documents.simulator["faults.pivot.payload_kg"] == 60.0
    (task,) = build_tasks(spec, documents, "0", closed_loop_builder)
    faults = task.run.faults  # type: ignore[union-attr]
    assert ScheduledFault("pivot", "payload_kg", 60.0, 0.0, float("inf")) in faults
    assert [f.kind for f in faults if f.start_s > 0.0] == ["encoder_freeze", "jam"]
    peak = run_point(task).metrics["peak_current_a"]
    assert peak == _direct_peak(faults, _simulator())
    assert peak != _direct_peak((), _simulator())


def test_a_swept_standing_fault_changes_the_run(tmp_path: Path) -> None:
    """simulator.faults.pivot.payload_kg is the simulator's parameter of that dotted name."""
    spec_doc = _spec()
    spec_doc["parameters"] = [
        {"name": "payload_kg", "path": "simulator.faults.pivot.payload_kg", "values": [0.0, 80.0]}
    ]
    spec, documents = load_spec(_write(tmp_path, "spec.yaml", spec_doc))
    unloaded, loaded = (
        run_point(t).metrics for t in build_tasks(spec, documents, "0", closed_loop_builder)
    )
    assert unloaded["peak_current_a"] == _direct_peak((), _simulator())
    payload = (ScheduledFault("pivot", "payload_kg", 80.0, 0.0, float("inf")),)
    assert loaded["peak_current_a"] == _direct_peak(payload, _simulator())
    assert loaded["peak_current_a"] != unloaded["peak_current_a"]


@pytest.mark.parametrize(
    ("parameter", "schedule", "message"),
    [
        (
            {"name": "k", "path": "simulator.faults.pivot.wobble", "values": [1.0]},
            None,
            "faults.pivot.wobble",
        ),
        (
            {"name": "k", "path": "faults.0.value", "values": [True]},
            {"faults": [{"joint": "elbow", "kind": "jam", "value": False, "start_s": 1.0}]},
            "faults[0].joint",
        ),
        (
            {"name": "k", "path": "faults.3.start_s", "values": [1.0]},
            {"faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": 1.0}]},
            "faults: no item '3'",
        ),
        (
            {"name": "k", "path": "faults.0.start_s", "values": [1.0]},
            {
                "faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": 1.0}],
                "fault": [],
            },
            "fault: unknown key; a fault schedule has only 'faults'",
        ),
    ],
    ids=[
        "unknown fault parameter",
        "unknown joint in the schedule",
        "no such entry",
        "unknown schedule key",
    ],
)
def test_a_bad_fault_is_one_error_before_anything_runs(
    tmp_path: Path, parameter: dict[str, Any], schedule: dict[str, Any] | None, message: str
) -> None:
    """A fault the plant would refuse names its key when the points are built."""
    spec_doc = _spec()
    if schedule is not None:
        _write(tmp_path, "faults.yaml", schedule)
        spec_doc["base"]["faults"] = "faults.yaml"
    spec_doc["parameters"] = [parameter]
    with pytest.raises(ConfigError, match=re.escape(message)):
        spec, documents = load_spec(_write(tmp_path, "spec.yaml", spec_doc))
        build_tasks(spec, documents, "0", closed_loop_builder)


def test_faults_are_refused_outside_a_closed_loop(tmp_path: Path) -> None:
    """An open-loop base has no fault schedule: base.faults is an unknown key there."""
    spec_doc = {
        "base": {"kind": "open_loop", "scenario": "fig9_open_loop_pivot", "faults": "x.yaml"},
        "parameters": [],
        "metrics": [{"metric": "peak_current_a", "axis": "pivot"}],
    }
    with pytest.raises(ConfigError, match=r"base\.faults: unknown key"):
        load_spec(_write(tmp_path, "spec.yaml", spec_doc))
