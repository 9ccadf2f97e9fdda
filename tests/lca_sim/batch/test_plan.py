"""A sweep read from its files: the spec's documents by kind, and the plan of every point."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from support import CONFIG

from lca_sim.batch.plan import load_spec, plan_sweep
from lca_sim.config.params_file import node_parameters
from lca_sim.config.yaml_files import read_yaml

FREEZE_YAML = CONFIG / "faults" / "pivot_encoder_freeze.yaml"


def _write(tmp_path: Path, document: dict[str, Any]) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _spec(base: dict[str, Any]) -> dict[str, Any]:
    return {"base": base, "parameters": [], "metrics": [{"metric": "peak_current_a"}]}


def test_a_closed_loop_spec_reads_the_nodes_files_and_the_schedule(tmp_path: Path) -> None:
    """Closed loop: both nodes' parameters, the schedule's entries and file; no scenario."""
    base = {"kind": "closed_loop", "axis": "pivot", "faults": "pivot_encoder_freeze"}
    spec, documents = load_spec(_write(tmp_path, _spec(base)))
    assert spec.kind == "closed_loop" and documents.base == base
    assert documents.controller == node_parameters(CONFIG / "ros" / "controller.yaml", "controller")
    assert documents.simulator == node_parameters(CONFIG / "ros" / "simulator.yaml", "simulator")
    assert documents.faults == tuple(read_yaml(FREEZE_YAML)["faults"])
    assert documents.faults_source == str(FREEZE_YAML)
    assert documents.scenario == {} and "<robot" in documents.urdf_xml


def test_an_open_loop_spec_reads_its_scenario_and_no_node(tmp_path: Path) -> None:
    """Open loop: the scenario document; no node parameters, no schedule."""
    base = {"kind": "open_loop", "axis": "pivot", "scenario": "fig9_open_loop_pivot"}
    _, documents = load_spec(_write(tmp_path, _spec(base)))
    assert documents.scenario == read_yaml(CONFIG / "scenarios" / "fig9_open_loop_pivot.yaml")
    assert documents.controller == {} and documents.simulator == {} and documents.faults == ()


def test_the_plan_holds_a_task_per_point(tmp_path: Path) -> None:
    """plan_sweep builds every point's task before anything runs, keyed by the version."""
    spec_doc = {
        "base": {"kind": "current_step", "axis": "pivot", "duration_s": 0.01},
        "parameters": [{"name": "kp", "path": "base.current_kp_v_per_a", "values": [20.0, 40.0]}],
        "metrics": [{"metric": "overshoot_pct", "signal": "current_a"}],
    }
    path = _write(tmp_path, spec_doc)
    plan = plan_sweep(path)
    assert plan.spec_path == path and len(plan.tasks) == 2
    assert len({task.key for task in plan.tasks}) == 2
