"""The package layering, read from the import graph, and the tools that must run without ROS 2.

The import graph is read with `ast` from every module of lca_sim and lca_control, nothing is
imported to read it. Every import counts: module level ("eager"), inside a function or lambda
("lazy": it runs when the function does, so it is a dependency all the same), inside
`if TYPE_CHECKING:` ("typing"), `importlib.import_module("...")` with a literal name, relative
imports resolved. `from pkg import name` points at `pkg.name` when that is a module, else at `pkg`.

How the kinds count:

* purity and layering (which package may import which): every kind. A `TYPE_CHECKING` import
  does not run, but it still names what a module depends on, so it must not point upward or
  into ROS, CAN or matplotlib from the pure core either.
* the module cycle check: eager and lazy imports. A `TYPE_CHECKING` import never runs, so it
  cannot take part in an import-time cycle; since the layering forbids it to point upward, it
  can only close a cycle inside one package, which is what it is for (type hints between two
  modules of one layer that must not import each other).
* cheap imports: measured, not read: a fresh interpreter imports the module and `sys.modules`
  shows what came with it (the import machinery decides, `TYPE_CHECKING` is False there).

A package is a directory: `lca_sim` itself holds the base modules (errors, runtime). A package's
`__init__.py` is its face and is set aside from the package graph, except for its eager imports,
which run whenever any module of the package is imported (`lca_sim/__init__.py` names the model's
classes lazily, through PEP 562 and `TYPE_CHECKING`, for users of the top-level package).

The tools part runs each console script's entry point in a subprocess whose import system refuses
rclpy and the ROS message packages, as on a machine without ROS 2.
"""

from __future__ import annotations

import ast
import builtins
import graphlib
import json
import os
import re
import subprocess
import sys
import textwrap
from collections import defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import yaml
from support import ROOT

from lca_control import contract

PROJECT_ROOTS = ("lca_control", "lca_sim")

# Layer order, lowest first: a package may import from its own package and from packages of a
# strictly lower rank. Two packages of one rank are independent: neither imports the other.
#   0 lca_control      the control core (PI, cascade, profiles, tuning, parameter tables and the
#                      plant contract); owns what a plant must provide, so it needs nothing above
#   1 lca_sim          the base: errors (ControlParamError comes from lca_control.pi), runtime
#   2 lca_sim.model    the pure physics core
#   2 lca_sim.cia402   the pure CiA 402 object table, codec and state logic
#   3 lca_sim.config   YAML files -> the model's typed params (just above the model it fills)
#   3 lca_sim.analysis linearisation, identification, the paper's figures as data (on the model)
#   4 lca_sim.canbus   the virtual drive rack (model + config + cia402) and the CANopen master
#   4 lca_sim.batch    sweeps: spec, points, tasks, Parquet store, Dask runner (model + analysis
#                      + config); dask and pyarrow stay out of the pure core
#   5 lca_sim.ros      the node shells of the plant side and the node helpers
#   7 lca_sim.cli      the console scripts: every tool, Fig. 15 over ROS 2 included
LAYER_RANK: dict[str, int] = {
    "lca_control": 0,
    "lca_sim": 1,
    "lca_sim.model": 2,
    "lca_sim.cia402": 2,
    "lca_sim.config": 3,
    "lca_sim.analysis": 3,
    "lca_sim.canbus": 4,
    "lca_sim.batch": 4,
    "lca_sim.ros": 5,
    "lca_sim.cli": 7,
}

# The pure core: numbers in, numbers out (architecture.md, house-style.md section 1).
PURE_PACKAGES = ("lca_control", "lca_sim.model", "lca_sim.analysis", "lca_sim.cia402")
ROS_MESSAGE_PACKAGES = frozenset(
    {
        "sensor_msgs",
        "std_msgs",
        "diagnostic_msgs",
        "rosgraph_msgs",
        "builtin_interfaces",
        "rcl_interfaces",
        "std_srvs",
    }
)
ROS_PACKAGES = frozenset({"rclpy", *ROS_MESSAGE_PACKAGES})
PURE_FORBIDDEN: dict[str, str] = {
    **dict.fromkeys(sorted(ROS_PACKAGES), "ROS 2: only the shells in lca_sim.ros talk to it"),
    "can": "CAN bus I/O: lca_sim.canbus",
    "canopen": "CAN bus I/O: lca_sim.canbus",
    "matplotlib": "plotting: lca_sim.cli",
    "yaml": "config files: lca_sim.config parses them, the core gets typed params",
    "rosbags": "bag files: lca_sim.ros and lca_sim.cli",
    "dask": "sweeps on a cluster: lca_sim.batch",
    "distributed": "sweeps on a cluster: lca_sim.batch",
    "pyarrow": "the sweep's Parquet store: lca_sim.batch",
    "time": "a clock: the core gets time as an explicit dt_s",
    "datetime": "a clock: the core gets time as an explicit dt_s",
}
# Calls that read or write files, by the called name (Path.read_text, open(...), np.loadtxt, ...).
FILE_IO_CALLS = frozenset(
    {
        "open",
        "read_text",
        "write_text",
        "read_bytes",
        "write_bytes",
        "loadtxt",
        "savetxt",
        "genfromtxt",
        "fromfile",
        "tofile",
        "savez",
        "savez_compressed",
    }
)
# (module, called name) -> why this file I/O in a pure module is right. None today.
FILE_IO_EXCEPTIONS: dict[tuple[str, str], str] = {}

# What must not come with a cheap import: the JIT, the rigid-body library, SciPy and
# python-control (which brings SciPy), plotting, ROS 2, the CAN stack.
HEAVY = ("numba", "pinocchio", "scipy", "control", "matplotlib", "rclpy", "can", "canopen")
TOOL_TIMEOUT_S = 300.0  # a tool subprocess on a shared, loaded 2-core machine


# --------------------------------------------------------------------------- reading the graph

EAGER, LAZY, TYPING = "eager", "lazy", "typing"


@dataclass(frozen=True)
class Module:
    """One source file of the project."""

    name: str
    path: Path
    is_face: bool  # an __init__.py

    @property
    def package(self) -> str:
        """The directory the module lives in, dotted (`lca_sim` for errors and runtime)."""
        return self.name if self.is_face else self.name.rpartition(".")[0]

    @property
    def where(self) -> str:
        """The file, relative to the repository."""
        return str(self.path.relative_to(ROOT))


@dataclass(frozen=True)
class Import:
    """One imported name: who imports what, where, and when it runs."""

    source: Module
    target: str  # a project module, or an outside module as written
    line: int
    kind: str  # EAGER, LAZY or TYPING

    @property
    def root(self) -> str:
        """The top-level package imported (`rclpy` for `rclpy.qos`)."""
        return self.target.partition(".")[0]

    @property
    def is_project(self) -> bool:
        """An import of lca_sim or lca_control."""
        return self.root in PROJECT_ROOTS

    def __str__(self) -> str:
        return f"{self.source.where}:{self.line} imports {self.target} ({self.kind})"


def discover(root: Path = ROOT) -> dict[str, Module]:
    """Every module of the project packages, by dotted name."""
    modules: dict[str, Module] = {}
    for top in PROJECT_ROOTS:
        for path in sorted((root / top).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            is_face = parts[-1] == "__init__"
            name = ".".join(parts[:-1] if is_face else parts)
            modules[name] = Module(name, path, is_face)
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    """`TYPE_CHECKING` or `typing.TYPE_CHECKING`."""
    if isinstance(test, ast.Name):
        return test.id == "TYPE_CHECKING"
    return isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"


def _import_module_name(call: ast.Call) -> str | None:
    """The literal name of `importlib.import_module("x")` / `__import__("x")`, if this is one."""
    func = call.func
    name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
    if name not in {"import_module", "__import__"} or not call.args:
        return None
    first = call.args[0]
    if isinstance(first, ast.Constant) and isinstance(first.value, str):
        return None if first.value.startswith(".") else first.value
    return None


def _resolve_target(name: str, modules: Mapping[str, Module]) -> str:
    """An outside module as written; a project one as its nearest existing module.

    `lca_sim.data` (a data-only namespace) is `lca_sim`.
    """
    if name.partition(".")[0] not in PROJECT_ROOTS:
        return name
    while name not in modules and "." in name:
        name = name.rpartition(".")[0]
    return name


def _from_base(module: Module, node: ast.ImportFrom) -> str:
    """The package a `from ... import` takes its names from, relative imports resolved."""
    if not node.level:
        return node.module or ""
    package = module.package.split(".")
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def _imports_at(
    node: ast.AST, kind: str, module: Module, modules: Mapping[str, Module]
) -> list[Import]:
    """The imports one node makes itself (its children not included)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    elif isinstance(node, ast.ImportFrom):
        base = _from_base(module, node)
        submodules = (f"{base}.{alias.name}" for alias in node.names)
        names = [submodule if submodule in modules else base for submodule in submodules]
    elif isinstance(node, ast.Call) and (name := _import_module_name(node)) is not None:
        names = [name]
    else:
        return []
    return [Import(module, _resolve_target(n, modules), node.lineno, kind) for n in names]


def _child_kind(node: ast.AST, kind: str) -> str:
    """The kind of the imports below `node`: a function body runs later, so EAGER turns LAZY."""
    lazy = isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
    return LAZY if lazy and kind == EAGER else kind


def read_imports(module: Module, source: str, modules: Mapping[str, Module]) -> list[Import]:
    """Every import of one module's source, with its kind (see the module docstring)."""
    found: list[Import] = []

    def walk(node: ast.AST, kind: str) -> None:
        found.extend(_imports_at(node, kind, module, modules))
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for stmt in node.body:
                walk(stmt, TYPING)
            for stmt in node.orelse:
                walk(stmt, kind)
            return
        for child in ast.iter_child_nodes(node):
            walk(child, _child_kind(node, kind))

    walk(ast.parse(source, filename=str(module.path)), EAGER)
    return found


@dataclass(frozen=True)
class Graph:
    """The project's modules and every import they make."""

    modules: dict[str, Module]
    imports: tuple[Import, ...]

    def of(self, *packages: str) -> Iterator[Import]:
        """Imports made by the modules of these packages (their faces included)."""
        return (i for i in self.imports if i.source.package in packages)

    def package_edges(self) -> Iterator[tuple[str, str, Import]]:
        """(importing package, imported package, import) across packages; see module docstring."""
        for imp in self.imports:
            if not imp.is_project or (imp.source.is_face and imp.kind != EAGER):
                continue
            src, dst = imp.source.package, self.modules[imp.target].package
            if src != dst:
                yield src, dst, imp


@cache
def graph() -> Graph:
    """The import graph of the working tree (read once per test session)."""
    modules = discover()
    imports: list[Import] = []
    for module in modules.values():
        imports += read_imports(module, module.path.read_text(encoding="utf-8"), modules)
    return Graph(modules, tuple(imports))


def find_cycle(edges: Mapping[str, set[str]]) -> list[str]:
    """One cycle of a directed graph as [a, b, ..., a], or [] when it has none."""
    try:
        graphlib.TopologicalSorter(edges).prepare()
    except graphlib.CycleError as exc:
        return list(exc.args[1])
    return []


def _violations(found: list[str]) -> str:
    return "\n  " + "\n  ".join(found)


# ------------------------------------------------------------------ the reader reads them all


def test_the_reader_sees_every_kind_of_import(tmp_path: Path) -> None:
    """Eager, lazy, TYPE_CHECKING, relative and import_module imports are read and told apart."""
    source = textwrap.dedent(
        """
        import rclpy.qos
        from typing import TYPE_CHECKING
        from . import kernel
        from .params import RobotParams
        from lca_sim.model import gantry, SOME_NAME
        if TYPE_CHECKING:
            from matplotlib.figure import Figure
        else:
            import yaml
        class Shell:
            def run(self) -> None:
                import can
                f = lambda: __import__("canopen")
                importlib.import_module("lca_sim.cli.fig15")
        """
    )
    names = ("kernel", "params", "gantry")
    modules = {
        **{f"lca_sim.model.{n}": Module(f"lca_sim.model.{n}", tmp_path / f"{n}.py", False)
           for n in names},
        "lca_sim.model": Module("lca_sim.model", tmp_path / "__init__.py", True),
        "lca_sim.cli.fig15": Module("lca_sim.cli.fig15", tmp_path / "fig15.py", False),
    }  # fmt: skip
    found = read_imports(modules["lca_sim.model.gantry"], source, modules)
    assert [(i.target, i.kind) for i in found] == [
        ("rclpy.qos", EAGER),
        ("typing", EAGER),
        ("lca_sim.model.kernel", EAGER),
        ("lca_sim.model.params", EAGER),
        ("lca_sim.model.gantry", EAGER),
        ("lca_sim.model", EAGER),
        ("matplotlib.figure", TYPING),
        ("yaml", EAGER),
        ("can", LAZY),
        ("canopen", LAZY),
        ("lca_sim.cli.fig15", LAZY),
    ]


def test_every_package_has_a_layer() -> None:
    """A new package must be placed in LAYER_RANK (and the order documented above it)."""
    packages = {m.package for m in graph().modules.values()}
    assert packages == set(LAYER_RANK), (
        f"unplaced: {sorted(packages - set(LAYER_RANK))}, "
        f"gone: {sorted(set(LAYER_RANK) - packages)}"
    )


# ----------------------------------------------------------------------------- a. the pure core


def test_pure_core_imports_no_io_ros_or_clock_library() -> None:
    """lca_control (not .ros), model, analysis, cia402: no ROS, CAN, plots, YAML, bags, clock."""
    found = [
        f"{imp}: {PURE_FORBIDDEN[imp.root]}"
        for imp in graph().of(*PURE_PACKAGES)
        if imp.root in PURE_FORBIDDEN
    ]
    assert not found, "the pure core imports an I/O library:" + _violations(found)


def _file_io_calls(module: Module) -> Iterator[tuple[str, int]]:
    tree = ast.parse(module.path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name in FILE_IO_CALLS:
                yield name, node.lineno


def test_pure_core_does_no_file_io() -> None:
    """No open(), Path.read_text/write_text/open, numpy file readers in the pure core."""
    found, used = [], set()
    for module in graph().modules.values():
        if module.package not in PURE_PACKAGES:
            continue
        for name, line in _file_io_calls(module):
            if (module.name, name) in FILE_IO_EXCEPTIONS:
                used.add((module.name, name))
            else:
                found.append(f"{module.where}:{line} calls {name}()")
    assert not found, "file I/O in the pure core (config and cli do it):" + _violations(found)
    assert used == set(FILE_IO_EXCEPTIONS), f"stale exceptions: {set(FILE_IO_EXCEPTIONS) - used}"


# ---------------------------------------------------------------------------------- b. the bus


def test_canbus_imports_no_ros() -> None:
    """lca_sim.canbus runs without ROS 2: the bridge node wraps it, not the other way round."""
    found = [str(imp) for imp in graph().of("lca_sim.canbus") if imp.root in ROS_PACKAGES]
    assert not found, "lca_sim.canbus imports ROS 2:" + _violations(found)


# ------------------------------------------------------------------------------- c. the layers


def test_lca_control_core_imports_nothing_from_lca_sim() -> None:
    """The controller states what it needs of a plant (lca_control.contract); lca_sim fills it.

    The controller node is a shell among the others in lca_sim.ros: lca_control is a library.
    """
    found = [str(imp) for imp in graph().of("lca_control") if imp.root == "lca_sim"]
    assert not found, "lca_control imports lca_sim:" + _violations(found)


def test_module_import_graph_has_no_cycle() -> None:
    """No module imports itself through others (eager and lazy imports; see module docstring)."""
    edges: dict[str, set[str]] = defaultdict(set)
    for imp in graph().imports:
        if imp.is_project and imp.kind != TYPING and imp.target != imp.source.name:
            edges[imp.source.name].add(imp.target)
    cycle = find_cycle(edges)
    assert not cycle, "module import cycle: " + " -> ".join(cycle)


def test_package_graph_has_no_cycle() -> None:
    """No package depends on itself through others (every kind of import)."""
    edges: dict[str, set[str]] = defaultdict(set)
    for src, dst, _ in graph().package_edges():
        edges[src].add(dst)
    cycle = find_cycle(edges)
    assert not cycle, "package import cycle: " + " -> ".join(cycle)


def test_packages_import_only_lower_layers() -> None:
    """Every cross-package import goes to a strictly lower rank of LAYER_RANK."""
    found = [
        f"{imp}: {src} (rank {LAYER_RANK[src]}) -> {dst} (rank {LAYER_RANK[dst]})"
        for src, dst, imp in graph().package_edges()
        if LAYER_RANK[dst] >= LAYER_RANK[src]
    ]
    assert not found, "imports that do not go down:" + _violations(found)


@pytest.mark.parametrize(
    ("edges", "cycle"),
    [
        ({"a": {"b"}, "b": {"c"}}, False),
        ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, True),
        ({"a": {"a"}}, True),
    ],
)
def test_find_cycle(edges: dict[str, set[str]], cycle: bool) -> None:
    """The cycle finder finds a cycle exactly when there is one, and closes it."""
    found = find_cycle(edges)
    assert bool(found) == cycle
    if cycle:
        assert found[0] == found[-1]


# -------------------------------------------------------------------------- d. cheap imports


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run `code` in a fresh interpreter of this venv."""
    env = {**os.environ, "MPLBACKEND": "Agg"}
    return subprocess.run(
        [sys.executable, "-c", code],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=TOOL_TIMEOUT_S,
        check=False,
    )


def _loaded_after(modules: list[str], tmp_path: Path) -> set[str]:
    """Which HEAVY top-level packages a fresh interpreter holds after importing `modules`."""
    code = (
        "import importlib, json, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        "print(json.dumps(sorted({m.partition('.')[0] for m in sys.modules})))\n"
    )
    proc = _python(code, tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return set(json.loads(proc.stdout)) & set(HEAVY)


@pytest.mark.parametrize(
    "modules",
    [
        pytest.param(["lca_sim"], id="lca_sim"),
        pytest.param(["lca_control"], id="lca_control"),
        pytest.param(
            ["lca_sim.cia402.device", "lca_sim.cia402.controlword", "lca_sim.cia402.bus_load"],
            id="cia402",
        ),
        # lca-plot reads bags: no model, no JIT (matplotlib only once it plots).
        pytest.param(["lca_sim.cli.bagplot"], id="lca-plot"),
    ],
)
def test_cheap_imports(modules: list[str], tmp_path: Path) -> None:
    """A fresh import of these loads nothing of HEAVY."""
    heavy = _loaded_after(modules, tmp_path)
    assert not heavy, f"import {', '.join(modules)} loads {sorted(heavy)}"


CONTROLLER_NODE = "lca_sim.ros.controller_node"


def test_controller_node_needs_no_model(tmp_path: Path) -> None:
    """What the controller node imports from the project loads rclpy, but no model or CAN."""
    node_imports = {
        imp.target
        for imp in graph().imports
        if imp.source.name == CONTROLLER_NODE and imp.is_project and imp.kind != TYPING
    }
    named = {"lca_control.controller", "lca_control.cascade", "lca_control.contract"}
    modules = sorted(named | node_imports)
    heavy = _loaded_after(modules, tmp_path) - {"rclpy"}
    assert not heavy, f"import {', '.join(modules)} loads {sorted(heavy)}"


# ---------------------------------------------------------------------- e. tools without ROS 2

# Prepended to a subprocess: from here on rclpy and the message packages cannot be imported,
# whatever sys.path holds (a sourced ROS 2 included).
NO_ROS = textwrap.dedent(
    f"""
    import importlib.abc, sys

    class NoRos(importlib.abc.MetaPathFinder):
        def find_spec(self, fullname, path=None, target=None):
            if fullname.partition(".")[0] in {sorted(ROS_PACKAGES)!r}:
                raise ModuleNotFoundError(f"No module named {{fullname!r}}", name=fullname)
            return None

    sys.meta_path.insert(0, NoRos())
    """
)


def _tool(script: str, args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run a console script's entry point with ROS 2 hidden; returns the finished process."""
    code = NO_ROS + textwrap.dedent(
        f"""
        from importlib.metadata import entry_points
        (main,) = [ep.load() for ep in entry_points(group="console_scripts", name={script!r})]
        raise SystemExit(main({args!r}))
        """
    )
    return _python(code, cwd)


def _ok(proc: subprocess.CompletedProcess[str]) -> None:
    assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout[-2000:]}{proc.stderr}"


def _written(path: Path, min_bytes: int = 100) -> None:
    assert path.is_file() and path.stat().st_size >= min_bytes, path


def test_ros_is_hidden_in_the_tool_subprocess(tmp_path: Path) -> None:
    """The hiding works: rclpy and a message package fail to import, numpy still imports."""
    probe = textwrap.dedent(
        """
        import numpy
        for name in ("rclpy", "rclpy.node", "sensor_msgs.msg"):
            try:
                __import__(name)
            except ModuleNotFoundError as exc:
                assert name.startswith(exc.name), exc  # rclpy.node fails at rclpy
            else:
                raise SystemExit(f"{name} imported")
        print("hidden")
        """
    )
    proc = _python(NO_ROS + probe, tmp_path)
    assert proc.returncode == 0 and proc.stdout.strip() == "hidden", proc.stderr


def test_tune_without_ros(tmp_path: Path) -> None:
    """`lca-hil tune` writes the controller's params file."""
    out = tmp_path / "tuned.yaml"
    _ok(_tool("lca-hil", ["tune", "--out", str(out)], tmp_path))
    params = yaml.safe_load(out.read_text(encoding="utf-8"))["controller"]["ros__parameters"]
    assert params["velocity_kp_a_per_rad_s"] > 0.0 and params["current_kp_v_per_a"] > 0.0


def test_closed_loop_run_without_ros(tmp_path: Path) -> None:
    """`lca-hil run` (the nodes' lockstep loop composed in one process) writes its two files."""
    out = tmp_path / "run"
    _ok(_tool("lca-hil", ["run", "--duration-s", "0.2", "--out", str(out)], tmp_path))
    rows = (out / "trajectory.csv").read_text(encoding="utf-8").splitlines()
    assert len(rows) == 1 + 51 and rows[0].startswith("t_s,")
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["duration_s"] == 0.2 and summary["realtime_factor"] > 0.0


def test_sweep_without_ros(tmp_path: Path) -> None:
    """`lca-hil sweep` runs a 2-point spec on a local Dask worker and draws its plots."""
    spec = tmp_path / "spec.yaml"
    doc = {
        "base": {"kind": "current_step", "axis": "pivot", "duration_s": 0.005},
        "parameters": [{"name": "kp", "path": "base.current_kp_v_per_a", "values": [20.0, 40.0]}],
        "metrics": [{"metric": "peak_current_a"}],
    }
    spec.write_text(yaml.safe_dump(doc), encoding="utf-8")
    out = tmp_path / "sweep"
    args = ["sweep", str(spec), "--out", str(out), "--workers", "1", "--plot", str(out)]
    _ok(_tool("lca-hil", args, tmp_path))
    _written(out / "results.parquet")
    _written(out / "plots" / "peak_current_a.png", 10_000)


def test_sim_run_and_identify_without_ros(tmp_path: Path) -> None:
    """`lca-sim run` on a 0.5 s scenario writes result.csv/.png; `lca-hil identify` reads it."""
    scenario = tmp_path / "short.yaml"
    doc = {
        "duration_s": 0.5,
        "dt_s": 1.0e-4,
        "record_period_s": 0.01,
        "inputs": {"pivot": {"time_s": [0.0, 0.2], "voltage_v": [0.0, 8.0]}},
    }
    scenario.write_text(yaml.safe_dump(doc), encoding="utf-8")
    run = tmp_path / "run"
    _ok(_tool("lca-sim", ["run", "--scenario", str(scenario), "--out", str(run)], tmp_path))
    rows = (run / "result.csv").read_text(encoding="utf-8").splitlines()
    assert len(rows) == 1 + 51 and rows[0].startswith("t_s,")
    _written(run / "result.png", 10_000)

    ident = tmp_path / "ident"
    _ok(_tool("lca-hil", ["identify", str(run / "result.csv"), "--out", str(ident)], tmp_path))
    report = json.loads((ident / "identification.json").read_text(encoding="utf-8"))
    assert report["axis"] == "pivot" and len(report["estimates"]) == 10
    _written(ident / "identified.yaml")


def test_paper_without_ros(tmp_path: Path) -> None:
    """`lca-hil paper --no-ros` writes every figure but Fig. 15, its CSV and numbers.json."""
    out = tmp_path / "paper"
    _ok(_tool("lca-hil", ["paper", "--no-ros", "--out", str(out)], tmp_path))
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert len(pngs) == 7 and not any(p.startswith("fig15") for p in pngs), pngs
    for png in pngs:
        _written(out / png, 10_000)
    for csv_file in out.glob("*.csv"):
        _written(csv_file, 1_000)
    numbers = json.loads((out / "numbers.json").read_text(encoding="utf-8"))["reproduced"]
    assert numbers["fig13_overshoot_pct"] > 0.0 and "fig15_transition_deg" not in numbers


def _write_bag(path: Path, n: int = 20) -> None:
    """A small MCAP bag of the plant's three state topics, written with rosbags (no rclpy)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    t = store.types
    joint_type, array_type = "sensor_msgs/msg/JointState", "diagnostic_msgs/msg/DiagnosticArray"
    joints = ["l_arm", "pivot", "c_arc", "lift"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            topic: writer.add_connection(f"/{topic}", msgtype, typestore=store)
            for topic, msgtype in (
                (contract.JOINT_STATES, joint_type),
                (contract.MOTOR_STATES, joint_type),
                (contract.DRIVE_CHAIN_STATES, array_type),
            )
        }
        for k in range(n):
            stamp_ns = k * 10_000_000
            header = t["std_msgs/msg/Header"](
                stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=stamp_ns), frame_id=""
            )
            value = np.full(4, 0.01 * k)
            state = t[joint_type](
                header=header, name=joints, position=value, velocity=value, effort=value
            )
            drives = t[array_type](
                header=header,
                status=[
                    t["diagnostic_msgs/msg/DiagnosticStatus"](
                        level=0,
                        name=f"{contract.DRIVE_STATUS_PREFIX}{joint}",
                        message="motor_driving",
                        hardware_id="",
                        values=[
                            t["diagnostic_msgs/msg/KeyValue"](key=key, value=text)
                            for key, text in (
                                ("drive_state", "motor_driving"),
                                ("eta_m", "0.9"),
                                ("eta_l", "nan"),
                            )
                        ],
                    )
                    for joint in joints
                ],
            )
            for topic, msg in (
                (contract.JOINT_STATES, state),
                (contract.MOTOR_STATES, state),
                (contract.DRIVE_CHAIN_STATES, drives),
            ):
                conn = conns[topic]
                writer.write(conn, 1_000_000_000 + stamp_ns, store.serialize_cdr(msg, conn.msgtype))


def test_plot_without_ros(tmp_path: Path) -> None:
    """`lca-plot` turns an MCAP bag into its five PNGs."""
    bag, out = tmp_path / "bag", tmp_path / "plots"
    _write_bag(bag)
    _ok(_tool("lca-plot", [str(bag), "--out", str(out)], tmp_path))
    for name in ("positions", "velocities", "currents", "drive_states", "efficiencies"):
        _written(out / f"{name}.png", 10_000)


def test_ros_commands_say_they_need_ros(tmp_path: Path) -> None:
    """`lca-hil fig15` and `lca-hil paper` without --no-ros: one error line, exit 2, no files."""
    code = NO_ROS + textwrap.dedent(
        """
        import contextlib, io, json
        from lca_sim.cli.hil import main
        said = []
        for args in (["fig15", "--out", "f15"], ["paper", "--out", "paper"]):
            with contextlib.redirect_stderr(io.StringIO()) as err:
                said.append([main(args), err.getvalue()])
        print(json.dumps(said))
        """
    )
    proc = _python(code, tmp_path)
    assert proc.returncode == 0, proc.stderr
    (fig15_code, fig15_err), (paper_code, paper_err) = json.loads(proc.stdout.splitlines()[-1])
    for exit_code, err in ((fig15_code, fig15_err), (paper_code, paper_err)):
        lines = err.strip().splitlines()
        assert exit_code == 2 and len(lines) == 1, err
        assert "runs over ROS 2" in lines[0] and "'rclpy'" in lines[0], lines
    assert paper_err.strip().endswith("or pass --no-ros")  # the paper's way round it
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------- f. small rooms, true paths

MODULE_BUDGET_LINES = 600
CLASS_BUDGET_LINES = 400
# A module or class may exceed the budget only with its reason in its module docstring, in a
# paragraph that starts with this phrase (the numba kernel: one compiled function per scheme,
# whose parts must see each other at compile time).
OVER_BUDGET = "Over the size budget:"


def _sources() -> Iterator[tuple[str, Path]]:
    for root in PROJECT_ROOTS:
        for path in sorted((ROOT / root).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), path


def test_modules_and_classes_keep_to_the_size_budget() -> None:
    """A module at most 600 lines, a class at most 400, or a stated reason in the docstring."""
    over = []
    for rel, path in _sources():
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text)
        doc = ast.get_docstring(tree) or ""
        if OVER_BUDGET in doc:
            reason = doc.split(OVER_BUDGET, 1)[1].strip()
            assert len(reason) > 20, f"{rel}: '{OVER_BUDGET}' without a reason"
            continue
        lines = len(text.splitlines())
        if lines > MODULE_BUDGET_LINES:
            over.append(f"{rel}: {lines} lines")
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and node.end_lineno is not None:
                size = node.end_lineno - node.lineno + 1
                if size > CLASS_BUDGET_LINES:
                    over.append(f"{rel}: class {node.name} {size} lines")
    assert not over, "over the size budget (split by composition, or state why):\n" + "\n".join(
        over
    )


# A path of this repository cited in code or prose: tests/... or docs/..., a file name at the end.
CITED_PATH = re.compile(
    r"(?<![\w./-])((?:tests|docs|bench|config|scripts)/[\w./-]*\w\.(?:py|md|yaml|png|eds|sh|urdf))"
)


def _citing_files() -> Iterator[Path]:
    for pattern in ("lca_sim/**/*.py", "lca_control/**/*.py", "tests/**/*.py", "bench/*.py"):
        yield from sorted(ROOT.glob(pattern))
    yield from sorted(ROOT.glob("docs/*.md"))
    yield ROOT / "README.md"
    yield ROOT / "bench" / "README.md"


def test_every_cited_path_exists() -> None:
    """Every tests/, docs/, bench/, config/ or scripts/ file named in code and docs exists."""
    missing = []
    for path in _citing_files():
        for match in CITED_PATH.finditer(path.read_text(encoding="utf-8")):
            cited = match.group(1)
            if "/.../" in cited or any(part.isupper() for part in cited.split("/")):
                continue  # an elision or a placeholder (config/KIND/NAME.yaml), not a path
            if not (ROOT / cited).exists() and not (path.parent / cited).exists():
                missing.append(f"{path.relative_to(ROOT)}: {cited}")
    assert not missing, "cited paths that do not exist:\n" + "\n".join(sorted(set(missing)))


def _exception_classes() -> Iterator[tuple[str, str, type[BaseException]]]:
    import importlib

    for rel, path in _sources():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        names = [n.name for n in tree.body if isinstance(n, ast.ClassDef)]
        if not names:
            continue
        module = importlib.import_module(rel.removesuffix(".py").replace("/", "."))
        for name in names:
            cls = getattr(module, name)
            if isinstance(cls, type) and issubclass(cls, BaseException):
                yield rel, name, cls


def test_every_project_error_derives_from_its_package_base() -> None:
    """lca_sim's errors are LcaHilErrors, lca_control's ControlParamErrors: one catch each."""
    from lca_control.pi import ControlParamError
    from lca_sim.errors import LcaHilError

    outside = [
        f"{rel}: {name}{tuple(base.__name__ for base in cls.__bases__)}"
        for rel, name, cls in _exception_classes()
        if not issubclass(cls, LcaHilError if rel.startswith("lca_sim/") else ControlParamError)
    ]
    assert not outside, "errors outside their package's base:\n" + "\n".join(outside)


# Builtins the project may raise itself: for its own bugs only (an invariant broken, a wrong
# argument type), which must not look like a user's error. A bad value gets a project error.
# AttributeError: a module's PEP 562 __getattr__ must raise it.
BUG_EXCEPTIONS = frozenset(
    {"RuntimeError", "TypeError", "NotImplementedError", "AssertionError", "AttributeError"}
)


def test_bad_values_raise_project_errors_not_builtins() -> None:
    """`raise ValueError(...)` and kin are project errors (`InvalidValueError` is a ValueError)."""
    builtin = {name for name in dir(builtins) if name.endswith("Error")} | {"Exception"}
    assert {"ValueError", "KeyError", "OSError"} <= builtin
    found = []
    for rel, path in _sources():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.Raise)
                and isinstance(node.exc, ast.Call)
                and isinstance(node.exc.func, ast.Name)
                and node.exc.func.id in builtin - BUG_EXCEPTIONS
            ):
                found.append(f"{rel}:{node.lineno}: raise {node.exc.func.id}")
    assert not found, "builtin errors raised for bad values:\n" + "\n".join(found)
