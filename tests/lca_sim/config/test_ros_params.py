"""config.ros_params: a params file as rcl will read it, checked before a node starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from lca_sim.config.ros_params import (
    params_file_arguments,
    read_ros_params_file,
    sections_for_node,
)
from lca_sim.errors import ConfigError


@pytest.mark.parametrize(
    ("key", "node", "applies"),
    [
        ("simulator", "/simulator", True),
        ("/simulator", "/simulator", True),
        ("/**", "/simulator", True),
        ("/**", "/ns/deep/simulator", True),
        ("/**/simulator", "/ns/simulator", True),
        ("/*/simulator", "/ns/simulator", True),
        ("/*/simulator", "/simulator", False),
        ("controller", "/simulator", False),
        ("/ns/simulator", "/simulator", False),
        ("sim*", "/simulator", False),  # `*` stands for a whole token, as in rcl
    ],
)
def test_a_section_applies_to_a_node_by_rcls_name_rules(key: str, node: str, applies: bool) -> None:
    document = {key: {"ros__parameters": {"x": 1}}}
    assert sections_for_node(document, node) == ([key] if applies else [])


def test_the_params_files_of_a_command_line_are_those_inside_ros_args() -> None:
    argv = [
        "prog",
        "--params-file",
        "not_ros.yaml",
        "--ros-args",
        "--params-file",
        "a.yaml",
        "-p",
        "x:=1",
        "--params-file",
        "b.yaml",
        "--",
        "--params-file",
        "own.yaml",
    ]
    assert params_file_arguments(argv) == [Path("a.yaml"), Path("b.yaml")]


def test_a_file_rcl_would_read_without_a_word_is_refused(tmp_path: Path) -> None:
    """Rcl sets nothing from a YAML file that is not node sections, and says nothing."""
    for text in ("just-a-hostname\n", "a: 1\n", "controller: {x: 1}\n"):
        path = tmp_path / "p.yaml"
        path.write_text(text)
        with pytest.raises(ConfigError, match="expected a ROS 2 params file"):
            read_ros_params_file(path)
    path.write_text("controller:\n  ros__parameters: {x: 1}\n")
    assert read_ros_params_file(path) == {"controller": {"ros__parameters": {"x": 1}}}
