"""A ROS 2 params file as rcl will read it, checked before a node starts (no ROS, no model).

rcl reads `--params-file` silently: a YAML file that is not node sections, or one whose
sections name other nodes, sets nothing and the node runs on its defaults. The node shells
(`lca_sim.ros.node_util.run_node`) check here first and say so.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import ConfigError

PARAMS_KEY = "ros__parameters"


def params_file_arguments(argv: Sequence[str]) -> list[Path]:
    """The files a command line gives rcl with `--params-file` (inside `--ros-args ... [--]`)."""
    files: list[Path] = []
    in_ros = False
    tokens = list(argv)
    for i, token in enumerate(tokens):
        if token == "--ros-args":
            in_ros = True
        elif in_ros and token == "--":
            in_ros = False
        elif in_ros and token == "--params-file" and i + 1 < len(tokens):
            files.append(Path(tokens[i + 1]))
    return files


def read_ros_params_file(path: Path) -> Mapping[str, Any]:
    """A params file as rcl will read it: a mapping of node names to `ros__parameters`.

    rcl reads a file that is YAML but not such a mapping without a word and sets nothing; this
    says so first.

    Raises:
        ConfigError: the file is missing, not YAML, or not a mapping of node sections.
    """
    document = read_yaml(path)
    if not isinstance(document, Mapping) or not any(
        isinstance(section, Mapping) and isinstance(section.get(PARAMS_KEY), Mapping)
        for section in document.values()
    ):
        raise ConfigError(
            str(path), "", f"expected a ROS 2 params file (<node name>: {PARAMS_KEY}: ...)"
        )
    return document


def sections_for_node(document: Mapping[str, Any], node_fqn: str) -> list[str]:
    """The sections of a params file that apply to the node `node_fqn` (e.g. `/simulator`).

    rcl's rule: a key names a node by its full name, with or without the leading slash, where
    `*` stands for one name token and `**` for any number of them (`/**` is every node).
    """
    matched = []
    for key, section in document.items():
        if not (isinstance(key, str) and isinstance(section, Mapping)):
            continue
        pattern = "".join(
            "(/[^/]+)*" if token == "**" else "/[^/]+" if token == "*" else "/" + re.escape(token)
            for token in key.strip("/").split("/")
        )
        if re.fullmatch(pattern, node_fqn):
            matched.append(key)
    return matched
