"""YAML files read strictly: a key given twice is an error, a syntax error names its line.

Light on purpose (PyYAML only): the nodes check their params files with it before ROS starts,
and the controller node must not load the model to do so.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from lca_sim.errors import ConfigError, file_problem


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader, where a key given twice in one mapping is an error.

    A robot file with two `gear_ratio:` lines must not quietly use the second.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} is given twice", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: Path) -> Any:
    """Parse one YAML file; syntax errors become a one-line ConfigError with the line number."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), "", file_problem(exc)) from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), "", f"expected UTF-8 text ({exc.reason})") from exc
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        context = getattr(exc, "context_mark", None)
        if context is not None and mark is not None and context.line != mark.line:
            problem += f", in what starts at line {context.line + 1}"
        raise ConfigError(str(path), where, f"expected valid YAML ({problem})") from exc
