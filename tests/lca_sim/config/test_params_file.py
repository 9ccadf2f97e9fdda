"""A ROS 2 params file read by dotted name, and checked by the nodes' own validation."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from support import CONFIG

from lca_control.parameters import ParameterError
from lca_sim.config.params_file import (
    in_file,
    node_parameters,
    plant_params,
    read_node_files,
    with_parameters,
)
from lca_sim.errors import ConfigError

CONTROLLER_YAML = CONFIG / "ros" / "controller.yaml"
SIMULATOR_YAML = CONFIG / "ros" / "simulator.yaml"


def _write(tmp_path: Path, name: str, document: Any) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def test_a_nested_group_is_a_dotted_name(tmp_path: Path) -> None:
    """`faults: {pivot: {jam: true}}` is the parameter `faults.pivot.jam`, as rcl reads it."""
    params = {"dt_s": 1e-4, "faults": {"pivot": {"jam": True, "payload_kg": 2.0}}}
    path = _write(tmp_path, "sim.yaml", {"simulator": {"ros__parameters": params}})
    assert node_parameters(path, "simulator") == {
        "dt_s": 1e-4,
        "faults.pivot.jam": True,
        "faults.pivot.payload_kg": 2.0,
    }


@pytest.mark.parametrize("key", ["simulator", "/simulator", "/**"])
def test_the_node_is_found_by_name_slash_name_or_wildcard(tmp_path: Path, key: str) -> None:
    """The node's section is `NODE`, `/NODE` or `/**`."""
    path = _write(tmp_path, "sim.yaml", {key: {"ros__parameters": {"dt_s": 2e-4}}})
    assert node_parameters(path, "simulator") == {"dt_s": 2e-4}


@pytest.mark.parametrize(
    ("document", "key", "message"),
    [
        ([1, 2], "", "expected a ROS 2 params file (a mapping)"),
        ({"controller": {"ros__parameters": {}}}, "simulator",
         "expected simulator: ros__parameters: (the node's parameters)"),
        ({"simulator": {"parameters": {}}}, "simulator",
         "expected simulator: ros__parameters: (the node's parameters)"),
    ],
    ids=["not a mapping", "another node", "no ros__parameters"],
)  # fmt: skip
def test_a_file_without_the_node_names_the_file(
    tmp_path: Path, document: Any, key: str, message: str
) -> None:
    """One ConfigError: the file, where, what was expected."""
    path = _write(tmp_path, "sim.yaml", document)
    with pytest.raises(ConfigError) as caught:
        node_parameters(path, "simulator")
    assert str(caught.value) == f"{path}: {key or '<top level>'}: {message}"


def test_the_plant_params_leave_the_faults_to_the_injector() -> None:
    """`faults.*` values are not the plant's parameters: plant_params takes the rest."""
    values = {**node_parameters(SIMULATOR_YAML, "simulator"), "faults.pivot.jam": "yes"}
    assert plant_params(values).dt_s == 1e-4
    with pytest.raises(ParameterError, match=r"^dt_s: "):
        plant_params({**values, "dt_s": -1.0})


def test_the_shipped_files_are_read_and_checked() -> None:
    """config/ros/controller.yaml and simulator.yaml pass their nodes' validation."""
    controller, simulator = read_node_files(CONTROLLER_YAML, SIMULATOR_YAML)
    assert controller == node_parameters(CONTROLLER_YAML, "controller")
    assert simulator == node_parameters(SIMULATOR_YAML, "simulator")


@pytest.mark.parametrize(
    ("node", "name", "value", "message"),
    [
        ("controller", "velocity_ti_s", -1.0,
         "controller.ros__parameters.velocity_ti_s: expected a number in (0, inf), got -1.0"),
        ("simulator", "dt_s", -1.0,
         "simulator.ros__parameters.dt_s: expected a number in (0, 0.01], got -1.0"),
    ],
)  # fmt: skip
def test_a_value_the_node_refuses_names_its_file(
    tmp_path: Path, node: str, name: str, value: float, message: str
) -> None:
    """The node's own words, prefixed by the params file and the parameter's key path."""
    shipped = {"controller": CONTROLLER_YAML, "simulator": SIMULATOR_YAML}
    values = {**node_parameters(shipped[node], node), name: value}
    bad = _write(tmp_path, f"{node}.yaml", {node: {"ros__parameters": values}})
    paths = {**shipped, node: bad}
    with pytest.raises(ConfigError) as caught:
        read_node_files(paths["controller"], paths["simulator"])
    assert str(caught.value) == f"{bad}: {message}"


def test_in_file_keeps_the_nodes_words() -> None:
    """A ParameterError becomes the file, `NODE.ros__parameters.NAME`, and its expectation."""
    error = ParameterError("dt_s", "a number > 0", -1.0)
    converted = in_file(Path("sim.yaml"), "simulator", error)
    assert str(converted) == f"sim.yaml: simulator.ros__parameters.{error!s}"


def test_with_parameters_sets_values_and_keeps_the_rest_of_the_file() -> None:
    """The first node's values replaced in place, its other values, order and nodes kept."""
    document: dict[str, Any] = {
        "/controller": {"ros__parameters": {"joints": ["pivot"], "velocity_ti_s": 0.01}},
        "other": {"ros__parameters": {"x": 1}},
    }
    rewritten = with_parameters(document, {"velocity_ti_s": 0.02, "current_ti_s": 0.001}, "c")
    params = rewritten["/controller"]["ros__parameters"]
    assert list(params) == ["joints", "velocity_ti_s", "current_ti_s"]
    assert params["velocity_ti_s"] == 0.02 and params["joints"] == ["pivot"]
    assert rewritten["other"] == document["other"]
    assert document["/controller"]["ros__parameters"]["velocity_ti_s"] == 0.01  # not mutated
    assert with_parameters({}, {"a": 1}, "controller") == {
        "controller": {"ros__parameters": {"a": 1}}
    }
