"""Every console script answers `--help` and `-h` with its usage, exit 0, without starting ROS 2.

The scripts are read from setup.py's entry points, so a new one is covered without editing this
file. Each runs as installed (`.venv/bin/<script>`, the wrapper pip generated) in a subprocess
whose import system refuses rclpy and the ROS message packages: a script that imports rclpy
before it looks at `--help` fails there. The node scripts must also list every parameter of
their table with its default.
"""

from __future__ import annotations

import ast
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from support import ROOT

from lca_control.controller import CONTROLLER_PARAMETERS
from lca_control.parameters import ParameterTable
from lca_sim.cli.nodes import own_arguments, wants_help
from lca_sim.cli.ros_guard import ROS_MODULES
from lca_sim.ros.can_bridge_params import CAN_BRIDGE_PARAMETERS
from lca_sim.ros.simulator_params import SIMULATOR_PARAMETERS

BIN = Path(sys.executable).parent  # the console scripts sit next to the interpreter
HELP_TIMEOUT_S = 120.0  # a cold import of a tool on a shared, loaded 2-core machine
HELP_FLAGS = ("--help", "-h")

# The node launchers and the parameter table each one's help must list (taken from the params
# modules here, not from the launcher, so a launcher showing the wrong table fails).
NODE_TABLES: dict[str, ParameterTable] = {
    "lca_sim.cli.nodes:simulator": SIMULATOR_PARAMETERS,
    "lca_sim.cli.nodes:controller": CONTROLLER_PARAMETERS,
    "lca_sim.cli.nodes:can_bridge": CAN_BRIDGE_PARAMETERS,
}
# Entry points that still import rclpy at module level, before argparse sees --help. Their help
# works where ROS 2 is installed and starts nothing (checked below), but not without rclpy.

# Prepended to the subprocess: rclpy and the message packages cannot be imported from here on.
NO_ROS = textwrap.dedent(
    f"""
    import importlib.abc, sys

    class NoRos(importlib.abc.MetaPathFinder):
        def find_spec(self, fullname, path=None, target=None):
            if fullname.partition(".")[0] in {sorted(ROS_MODULES)!r}:
                raise ModuleNotFoundError(f"No module named {{fullname!r}}", name=fullname)
            return None

    sys.meta_path.insert(0, NoRos())
    """
)


# Launchers of the rclpy tools with a plain argparse help (no parameter table).
TOOL_LAUNCHERS = frozenset({"lca_sim.cli.nodes:record", "lca_sim.cli.nodes:echo"})


def console_scripts() -> dict[str, str]:
    """setup.py's console scripts: name -> `module:function`, read without running setup.py."""
    tree = ast.parse((ROOT / "setup.py").read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "entry_points":
            entries = ast.literal_eval(node.value)["console_scripts"]
            pairs = (entry.split("=") for entry in entries)
            return {name.strip(): target.strip() for name, target in pairs}
    raise AssertionError("setup.py has no entry_points")


SCRIPTS = console_scripts()


def run_help(script: str, flag: str, guard: str) -> subprocess.CompletedProcess[str]:
    """Run the installed console script with `flag` behind `guard`; the finished process."""
    path = BIN / script
    assert path.is_file(), f"{path} missing: run `bash scripts/setup.sh` after editing setup.py"
    code = guard + textwrap.dedent(
        f"""
        import runpy
        sys.argv = [{str(path)!r}, {flag!r}]
        runpy.run_path(sys.argv[0], run_name="__main__")
        """
    )
    return subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=HELP_TIMEOUT_S,
        check=False,
    )


def _shown(value: object) -> str:
    """A default as the help shows it (YAML-like: true, 0.004, 'realtime', [a, b])."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    if isinstance(value, float):
        assert math.isfinite(value)
        return f"{value:g}"
    return repr(value) if isinstance(value, str) else str(value)


def _cases() -> list[object]:
    return [
        pytest.param(script, flag, id=f"{script} {flag}")
        for script in SCRIPTS
        for flag in HELP_FLAGS
    ]


@pytest.mark.parametrize(("script", "flag"), _cases())
def test_help_without_ros(script: str, flag: str) -> None:
    """The help: exit 0, a usage line, no ROS 2 needed; a node's lists its parameter table."""
    proc = run_help(script, flag, NO_ROS)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"exit {proc.returncode}\n{output[-3000:]}"
    assert "usage" in output.lower(), output
    assert "Traceback" not in output
    target = SCRIPTS[script]
    if target.startswith("lca_sim.cli.nodes:") and target not in TOOL_LAUNCHERS:
        assert target in NODE_TABLES, f"{script}: a node launcher this test has no table for"
    table = NODE_TABLES.get(target)
    if table is None:
        return
    lines = {line.split(" (", 1)[0].strip(): line for line in proc.stdout.splitlines()}
    for spec in table:
        assert spec.name in lines, f"{script} --help does not list {spec.name}"
        assert f"default {_shown(spec.default)}" in lines[spec.name], lines[spec.name]
        assert lines[spec.name].strip() == spec.help_line()


def test_every_exception_is_a_console_script() -> None:
    """The tables above name only entry points setup.py has (no stale entries)."""
    targets = set(SCRIPTS.values())
    assert set(NODE_TABLES) <= targets


@pytest.mark.parametrize(
    ("argv", "own", "helps"),
    [
        (["--help"], ["--help"], True),
        (["-h", "--ros-args", "-p", "a:=1"], ["-h"], True),
        (["--ros-args", "-p", "robot:=--help"], [], False),
        (["--ros-args", "-p", "a:=1", "--", "-h"], ["-h"], True),
        (["--ros-args", "--params-file", "f.yaml", "--ros-args", "-r", "x:=y"], [], False),
        ([], [], False),
    ],
)
def test_help_flag_is_read_outside_ros_arguments(
    argv: list[str], own: list[str], helps: bool
) -> None:
    """`-h`/`--help` counts only among the script's own arguments, as rcl splits them."""
    assert own_arguments(argv) == own
    assert wants_help(argv) is helps
