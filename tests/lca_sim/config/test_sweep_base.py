"""The files a sweep spec's base names: the nodes' params, the fault schedule, scenario, robot."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from support import CONFIG

from lca_sim.config.params_file import node_parameters
from lca_sim.config.sweep_base import (
    base_fault_schedule,
    base_node_files,
    base_robot,
    base_scenario,
)
from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import ConfigError

SIMULATOR_YAML = CONFIG / "ros" / "simulator.yaml"
FREEZE_YAML = CONFIG / "faults" / "pivot_encoder_freeze.yaml"


def _write(path: Path, document: Any) -> Path:
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _simulator_file(tmp_path: Path, **changes: Any) -> Path:
    values = {**node_parameters(SIMULATOR_YAML, "simulator"), **changes}
    return _write(tmp_path / "sim.yaml", {"simulator": {"ros__parameters": values}})


def test_the_nodes_files_default_to_the_shipped_ones(tmp_path: Path) -> None:
    """No base.controller or base.simulator: config/ros/*.yaml; a path is from the spec's folder."""
    spec = tmp_path / "spec.yaml"
    controller, simulator, simulator_path = base_node_files({}, spec)
    assert controller == node_parameters(CONFIG / "ros" / "controller.yaml", "controller")
    assert simulator == node_parameters(SIMULATOR_YAML, "simulator")
    assert simulator_path == SIMULATOR_YAML
    mine = _simulator_file(tmp_path, dt_s=2e-4)
    _, simulator, simulator_path = base_node_files({"simulator": "sim.yaml"}, spec)
    assert simulator["dt_s"] == 2e-4 and simulator_path == mine


def test_base_faults_wins_over_the_simulators_schedule(tmp_path: Path) -> None:
    """`base.faults` first, then the simulator's `fault_schedule`, else no schedule."""
    spec = tmp_path / "spec.yaml"
    entries = read_yaml(FREEZE_YAML)["faults"]
    simulator = {"fault_schedule": "pivot_encoder_freeze"}
    assert base_fault_schedule({}, simulator, spec, SIMULATOR_YAML) == (
        tuple(entries),
        str(FREEZE_YAML),
    )
    mine = _write(tmp_path / "mine.yaml", {"faults": entries[:1]})
    assert base_fault_schedule({"faults": "mine.yaml"}, simulator, spec, SIMULATOR_YAML) == (
        tuple(entries[:1]),
        str(mine),
    )
    assert base_fault_schedule({}, {"fault_schedule": ""}, spec, SIMULATOR_YAML) == ((), "")


@pytest.mark.parametrize(
    ("base", "simulator", "where", "message"),
    [
        ({}, {"fault_schedule": 3}, "sim.yaml: fault_schedule",
         "expected a schedule's name"),
        ({"faults": "none.yaml"}, {}, "spec.yaml: base.faults",
         "file not found: {home}/none.yaml"),
        ({"faults": "list.yaml"}, {}, "list.yaml", "expected a mapping with a 'faults' list"),
    ],
    ids=["not a name", "no such file", "not a schedule"],
)  # fmt: skip
def test_a_bad_schedule_names_its_file(
    tmp_path: Path, base: dict[str, Any], simulator: dict[str, Any], where: str, message: str
) -> None:
    """One ConfigError naming the file that holds the bad reference or entry."""
    _write(tmp_path / "list.yaml", [1, 2])
    with pytest.raises(ConfigError) as caught:
        base_fault_schedule(base, simulator, tmp_path / "spec.yaml", tmp_path / "sim.yaml")
    assert str(caught.value).startswith(f"{tmp_path}/{where}:"), str(caught.value)
    assert message.format(home=tmp_path) in str(caught.value)


def test_an_open_loop_base_names_its_scenario(tmp_path: Path) -> None:
    """`base.scenario`: a shipped name or a path; missing, or not a mapping, is an error."""
    spec = tmp_path / "spec.yaml"
    shipped = read_yaml(CONFIG / "scenarios" / "fig9_open_loop_pivot.yaml")
    assert base_scenario({"scenario": "fig9_open_loop_pivot"}, spec) == shipped
    with pytest.raises(ConfigError) as caught:
        base_scenario({}, spec)
    assert str(caught.value) == f"{spec}: base.scenario: missing (an open-loop scenario)"
    _write(tmp_path / "list.yaml", [1])
    with pytest.raises(ConfigError) as caught:
        base_scenario({"scenario": "list.yaml"}, spec)
    assert str(caught.value) == f"{spec}: base.scenario: expected a scenario document"


def test_the_robot_is_the_bases_else_the_simulators_else_default(tmp_path: Path) -> None:
    """The simulator params' robot is the run's robot, as for the node and lca-hil run."""
    spec = tmp_path / "spec.yaml"

    def name(base: dict[str, Any], simulator: dict[str, Any]) -> str:
        urdf_xml, document = base_robot(base, simulator, spec)
        assert "<robot" in urdf_xml
        return str(document["robot"]["name"])

    default, reversible = (
        read_yaml(CONFIG / "robots" / "default.yaml")["robot"]["name"],
        name({"robot": "reversible"}, {}),
    )
    assert default != reversible
    assert name({}, {"robot": "reversible"}) == reversible
    assert name({"robot": "default"}, {"robot": "reversible"}) == default
    assert name({}, {}) == default
