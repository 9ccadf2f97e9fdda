"""Loading robot configs and scenarios from YAML files (the I/O edge of lca_sim).

Shipped files live in the package (`lca_sim.data`, mapped from the top-level config/ folder),
so they are found after a plain, non-editable install as well as in a source checkout.
A name such as `default` is a shipped file; anything with a path separator or a .yaml suffix is a
path.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pinocchio as pin

from lca_sim.config.paths import config_dir
from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import FILE_NOT_FOUND, ConfigError, UnknownNameError, file_problem
from lca_sim.model.fault_schedule import ScheduledFault, parse_fault_schedule
from lca_sim.model.params import RobotParams, parse_robot
from lca_sim.model.scenario import Scenario, parse_scenario


def shipped_names(kind: str) -> tuple[str, ...]:
    """Names of the shipped files of one kind: `robots` or `scenarios`."""
    folder = config_dir() / kind
    return tuple(sorted(p.stem for p in folder.glob("*.yaml")))


def resolve(name_or_path: str, kind: str) -> Path:
    """A shipped name (`default`) or a file path, as a path to an existing file."""
    looks_like_path = "/" in name_or_path or name_or_path.endswith((".yaml", ".yml"))
    if looks_like_path:
        path = Path(name_or_path)
        if not path.is_file():
            raise ConfigError(str(path), "", FILE_NOT_FOUND)
        return path
    path = config_dir() / kind / f"{name_or_path}.yaml"
    if not path.is_file():
        raise UnknownNameError(kind.rstrip("s"), name_or_path, shipped_names(kind))
    return path


def file_ref(ref: object, home: Path, kind: str, key: str) -> Path:
    """A shipped name (config/KIND/NAME.yaml) or a path from `home`'s folder, as a file.

    For a file that names another (a closed-loop scenario, a sweep spec's base); `key` is
    where `home` names it.

    Raises:
        ConfigError: `home`, `key`: not a name or path, or no such file.
        UnknownNameError: no shipped file of that name.
    """
    if not isinstance(ref, str):
        raise ConfigError(str(home), key, f"expected a shipped {kind} name or a path")
    if "/" in ref or ref.endswith((".yaml", ".yml")):
        path = Path(ref) if Path(ref).is_absolute() else home.parent / ref
        if not path.is_file():
            raise ConfigError(str(home), key, f"{FILE_NOT_FOUND}: {path}")
        return path
    return resolve(ref, kind)


def _merge(base: Any, override: Any) -> Any:
    """Deep-merge mappings; any other value in `override` replaces the base value."""
    if isinstance(base, Mapping) and isinstance(override, Mapping):
        merged = dict(base)
        for key, value in override.items():
            merged[key] = _merge(base[key], value) if key in base else value
        return merged
    return override


def _read_with_base(path: Path, seen: tuple[Path, ...] = ()) -> tuple[Any, Path]:
    """Read a robot YAML, following `base:` (a shipped name or a path relative to the file).

    Returns the merged document and the path that defines `robot.urdf`'s folder.
    """
    if path.resolve() in seen:
        raise ConfigError(str(path), "base", "expected no cycle of base files")
    data = read_yaml(path)
    if not isinstance(data, Mapping) or "base" not in data:
        return data, path
    base_ref = data["base"]
    if not isinstance(base_ref, str):
        raise ConfigError(str(path), "base", f"expected a robot name or a path, got {base_ref!r}")
    if "/" in base_ref or base_ref.endswith((".yaml", ".yml")):
        base_path = (path.parent / base_ref).resolve()
        if not base_path.is_file():
            raise ConfigError(str(path), "base", f"{FILE_NOT_FOUND}: {base_path}")
    else:
        try:
            base_path = resolve(base_ref, "robots")
        except UnknownNameError as exc:
            raise ConfigError(str(path), "base", str(exc)) from exc
    base_data, urdf_home = _read_with_base(base_path, (*seen, path.resolve()))
    override = {k: v for k, v in data.items() if k != "base"}
    robot_override = override.get("robot")
    if isinstance(robot_override, Mapping) and "urdf" in robot_override:
        urdf_home = path
    return _merge(base_data, override), urdf_home


def load_robot(name_or_path: str = "default") -> RobotParams:
    """Load and validate a robot config: a shipped name (`default`, `reversible`) or a path.

    Raises:
        ConfigError: the file, the key and what was expected, in one line.
        UnknownNameError: an unknown shipped name (the message lists the valid ones).

    """
    path = resolve(name_or_path, "robots")
    data, urdf_xml = read_robot_document(path)
    return parse_robot(data, str(path), urdf_xml)


def read_robot_document(path: Path) -> tuple[Mapping[str, Any], str]:
    """A robot file's document (its `base:` merged in) and its gantry URDF's text, unparsed.

    For a caller that changes the document before parsing it (a sweep's points).

    Raises:
        ConfigError: the file, the key and what was expected, in one line.
    """
    data, urdf_home = _read_with_base(path)
    if not isinstance(data, Mapping):
        kind = "nothing (an empty file)" if data is None else type(data).__name__
        raise ConfigError(str(path), "", f"expected a mapping with robot, axes, ..., got {kind}")
    robot = data.get("robot")
    urdf_ref = robot.get("urdf") if isinstance(robot, Mapping) else None
    if not isinstance(urdf_ref, str):
        raise ConfigError(str(path), "robot.urdf", "expected the path of the gantry URDF")
    urdf_path = (urdf_home.parent / urdf_ref).resolve()
    try:
        urdf_xml = urdf_path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), "robot.urdf", file_problem(exc, urdf_path)) from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), "robot.urdf", f"expected UTF-8 text in {urdf_path}") from exc
    _check_urdf(urdf_xml, str(path), urdf_path)
    return data, urdf_xml


def _check_urdf(urdf_xml: str, source: str, urdf_path: Path) -> None:
    """Let Pinocchio parse the URDF once, with the native parser's stderr chatter captured.

    urdfdom prints its diagnostics straight to file descriptor 2; a user should see one clear
    line instead, so they are collected and folded into the ConfigError.
    """
    with tempfile.TemporaryFile(mode="w+b") as capture:
        saved = os.dup(2)
        try:
            os.dup2(capture.fileno(), 2)
            try:
                pin.buildModelFromXML(urdf_xml)
                error = None
            except (RuntimeError, ValueError) as exc:
                error = str(exc)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        chatter = capture.read().decode("utf-8", "replace").strip().split("\n")[0].strip()
    if error is not None:
        detail = error.strip().splitlines()[0] if error.strip() else chatter
        if chatter and chatter not in detail:
            detail = f"{detail}; {chatter}"
        raise ConfigError(source, "robot.urdf", f"expected a valid URDF in {urdf_path} ({detail})")


def load_scenario(name_or_path: str, axis_names: tuple[str, ...]) -> Scenario:
    """Load and validate a scenario: a shipped name (`fig9_open_loop_pivot`) or a path."""
    path = resolve(name_or_path, "scenarios")
    return parse_scenario(read_yaml(path), str(path), axis_names)


def load_fault_schedule(name_or_path: str, joints: Sequence[str]) -> tuple[ScheduledFault, ...]:
    """A fault schedule (docs/faults.md): a file path, or a name in config/faults/; () for "".

    Raises:
        ConfigError: unreadable file, or the first bad entry, named by its key path.
        UnknownNameError: no shipped schedule of that name.
    """
    if not name_or_path:
        return ()
    path = resolve(name_or_path, "faults")
    return parse_fault_schedule(read_yaml(path), str(path), joints)
