"""Every class of bad robot config and scenario gives one clear `ConfigError`.

Each bad file is a shipped YAML loaded with `yaml.safe_load`, changed in exactly one place and
written to `tmp_path`. The error must name the file, the exact dotted key path and what was
expected, in one line.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from support import CONFIG

from lca_sim import (
    AXIS_NAMES,
    ConfigError,
    MotionState,
    RobotParams,
    UnknownNameError,
    load_robot,
    load_scenario,
)
from lca_sim.config.loader import shipped_names
from lca_sim.model.scenario import MAX_STEPS

DEFAULT_YAML = CONFIG / "robots" / "default.yaml"
FIG9_YAML = CONFIG / "scenarios" / "fig9_open_loop_pivot.yaml"
URDF = CONFIG / "urdf" / "lca_gantry.urdf"

Key = str | int
Mutation = Callable[[Any], None]


def _set(keys: tuple[Key, ...], value: object) -> Mutation:
    """A mutation that sets the value at `keys` (creating nothing but the last key)."""

    def mutate(doc: Any) -> None:
        node = doc
        for key in keys[:-1]:
            node = node[key]
        node[keys[-1]] = value

    return mutate


def _delete(keys: tuple[Key, ...]) -> Mutation:
    """A mutation that removes the key or list item at `keys`."""

    def mutate(doc: Any) -> None:
        node = doc
        for key in keys[:-1]:
            node = node[key]
        del node[keys[-1]]

    return mutate


def _set_top(values: dict[str, object]) -> Mutation:
    """A mutation that sets several top-level keys at once."""

    def mutate(doc: Any) -> None:
        doc.update(values)

    return mutate


def _swap_first_axes(doc: Any) -> None:
    """Swap the first two axes (l_arm and pivot)."""
    doc["axes"][0], doc["axes"][1] = doc["axes"][1], doc["axes"][0]


def _axis_efficiency_override(doc: Any) -> None:
    """Give the pivot its own efficiency table with a forbidden eta_l < 1 while motor driving."""
    table = copy.deepcopy(doc["efficiency"])
    table["motor_driving"]["reverse"]["eta_l"] = 0.5
    doc["axes"][1]["efficiency"] = table


def _default_robot_doc() -> Any:
    """The shipped default robot, with `robot.urdf` made absolute so the copy can live anywhere."""
    doc = yaml.safe_load(DEFAULT_YAML.read_text(encoding="utf-8"))
    doc["robot"]["urdf"] = str(URDF)
    return doc


def _write(path: Path, doc: object) -> Path:
    """Dump `doc` as YAML to `path` and return the path."""
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def _write_robot(tmp_path: Path, mutate: Mutation, name: str = "robot.yaml") -> Path:
    """The default robot with one mutation applied, written to `tmp_path / name`."""
    doc = _default_robot_doc()
    mutate(doc)
    return _write(tmp_path / name, doc)


def _write_scenario(tmp_path: Path, mutate: Mutation, name: str = "scenario.yaml") -> Path:
    """The shipped fig9 scenario with one mutation applied, written to `tmp_path / name`."""
    doc = yaml.safe_load(FIG9_YAML.read_text(encoding="utf-8"))
    mutate(doc)
    return _write(tmp_path / name, doc)


def _assert_config_error(exc: ConfigError, path: Path, key: str, expected: str) -> None:
    """The one-line message names the file, the exact key path and what was expected."""
    message = str(exc)
    assert exc.source == str(path)
    assert exc.key == key
    assert "\n" not in message
    assert message.startswith(f"{path}: {key or '<top level>'}: ")
    assert expected in exc.expected


ROBOT_CASES = [
    # --- unknown keys
    pytest.param(_set(("colour",), "red"), "colour", "unknown key", id="unknown-top-level"),
    pytest.param(
        _set(("robot", "mass_kg"), 1.0), "robot.mass_kg", "unknown key", id="unknown-in-robot"
    ),
    pytest.param(
        _set(("axes", 2, "backlash_rad"), 0.01),
        "axes[2].backlash_rad",
        "unknown key",
        id="unknown-in-axis",
    ),
    pytest.param(
        _set(("axes", 1, "motor", "brush_count"), 2),
        "axes[1].motor.brush_count",
        "unknown key",
        id="unknown-in-axis-motor",
    ),
    pytest.param(
        _set(("axes", 3, "friction", "stribeck_nm"), 0.1),
        "axes[3].friction.stribeck_nm",
        "unknown key",
        id="unknown-in-axis-friction",
    ),
    pytest.param(
        _set(("state_machine", "states", 0, "priority"), 1),
        "state_machine.states[0].priority",
        "unknown key",
        id="unknown-in-state-row",
    ),
    pytest.param(
        _set(("state_machine", "hysteresis_rad_s"), 0.5),
        "state_machine.hysteresis_rad_s",
        "unknown key",
        id="unknown-in-state-machine",
    ),
    pytest.param(
        _set(("efficiency", "freewheeling"), {"direct": {"eta_m": 1.0, "eta_l": 1.0}}),
        "efficiency.freewheeling",
        "unknown key",
        id="unknown-efficiency-state",
    ),
    pytest.param(
        _set(("efficiency", "motor_driving", "direct", "eta_x"), 1.0),
        "efficiency.motor_driving.direct.eta_x",
        "unknown key",
        id="unknown-in-efficiency-direction",
    ),
    # --- missing required keys
    pytest.param(
        _delete(("axes", 1, "motor", "resistance_ohm")),
        "axes[1].motor.resistance_ohm",
        "missing required key",
        id="missing-motor-resistance",
    ),
    pytest.param(
        _delete(("state_machine", "irreversible_stop")),
        "state_machine.irreversible_stop",
        "missing required key",
        id="missing-irreversible-stop",
    ),
    pytest.param(
        _delete(("robot", "name")), "robot.name", "missing required key", id="missing-robot-name"
    ),
    pytest.param(
        _delete(("efficiency", "coasting")),
        "efficiency.coasting",
        "missing required key",
        id="missing-efficiency-state",
    ),
    pytest.param(
        _delete(("efficiency", "load_driving", "reverse")),
        "efficiency.load_driving.reverse",
        "missing required key",
        id="missing-efficiency-direction",
    ),
    pytest.param(
        _delete(("state_machine", "states", 2, "dominant")),
        "state_machine.states[2].dominant",
        "missing required key",
        id="missing-state-condition",
    ),
    pytest.param(_delete(("axes",)), "axes", "missing required key", id="missing-axes"),
    pytest.param(
        _delete(("robot", "urdf")), "robot.urdf", "path of the gantry URDF", id="missing-urdf"
    ),
    # --- wrong types
    pytest.param(
        _set(("axes", 1, "motor", "resistance_ohm"), "one ohm"),
        "axes[1].motor.resistance_ohm",
        "expected a number",
        id="string-for-number",
    ),
    pytest.param(
        _set(("axes", 1, "motor"), [1.0, 2.0]),
        "axes[1].motor",
        "expected a mapping, got list",
        id="list-for-mapping",
    ),
    pytest.param(
        _set(("axes", 0, "gear_ratio"), True),
        "axes[0].gear_ratio",
        "expected a number",
        id="bool-for-number",
    ),
    pytest.param(
        _set(("state_machine", "irreversible_stop"), "yes"),
        "state_machine.irreversible_stop",
        "expected true or false",
        id="string-for-bool",
    ),
    pytest.param(
        _set(("state_machine", "states"), {"motor_driving": "drives"}),
        "state_machine.states",
        "expected a list",
        id="mapping-for-list",
    ),
    pytest.param(
        _set(("robot", "name"), 5), "robot.name", "expected a string", id="number-for-string"
    ),
    pytest.param(
        _set(("robot", "gravity_m_s2"), [0.0, -9.81]),
        "robot.gravity_m_s2",
        "expected a list of 3 numbers",
        id="gravity-wrong-length",
    ),
    pytest.param(
        _set(("robot", "gravity_m_s2", 2), "down"),
        "robot.gravity_m_s2[2]",
        "expected a number",
        id="gravity-item-string",
    ),
    # --- non-finite numbers (written as .nan / .inf by yaml.safe_dump)
    pytest.param(
        _set(("axes", 1, "motor", "inductance_h"), float("nan")),
        "axes[1].motor.inductance_h",
        "expected a finite number",
        id="nan",
    ),
    pytest.param(
        _set(("efficiency", "motor_driving", "direct", "eta_m"), float("inf")),
        "efficiency.motor_driving.direct.eta_m",
        "expected a finite number",
        id="inf",
    ),
    pytest.param(
        _set(("robot", "gravity_m_s2", 2), float("-inf")),
        "robot.gravity_m_s2[2]",
        "expected a finite number",
        id="minus-inf",
    ),
    # --- out of range
    pytest.param(
        _set(("axes", 1, "motor", "resistance_ohm"), -1.0),
        "axes[1].motor.resistance_ohm",
        "expected a number > 0",
        id="negative-resistance",
    ),
    pytest.param(
        _set(("axes", 2, "motor", "inductance_h"), 0.0),
        "axes[2].motor.inductance_h",
        "expected a number > 0",
        id="zero-inductance",
    ),
    pytest.param(
        _set(("axes", 3, "gear_ratio"), 0),
        "axes[3].gear_ratio",
        "expected a number > 0",
        id="zero-gear-ratio",
    ),
    pytest.param(
        _set(("axes", 0, "friction", "viscous_reverse_nm_s_per_rad"), -1e-4),
        "axes[0].friction.viscous_reverse_nm_s_per_rad",
        "expected a number >= 0",
        id="negative-viscous",
    ),
    pytest.param(
        _set(("state_machine", "velocity_eps_rad_s"), 0.0),
        "state_machine.velocity_eps_rad_s",
        "expected a number > 0",
        id="zero-velocity-eps",
    ),
    pytest.param(
        _set(("efficiency", "motor_driving", "direct", "eta_m"), 1.2),
        "efficiency.motor_driving.direct.eta_m",
        "expected a number <= 1",
        id="eta-m-above-1",
    ),
    pytest.param(
        _set(("efficiency", "load_driving", "direct", "eta_l"), -0.1),
        "efficiency.load_driving.direct.eta_l",
        "expected a number >= 0",
        id="eta-l-negative",
    ),
    pytest.param(
        _set(("efficiency", "motor_driving", "reverse", "eta_m"), 0.0),
        "efficiency.motor_driving.reverse.eta_m",
        "expected a number > 0",
        id="eta-m-zero",
    ),
    # --- static friction below Coulomb friction
    pytest.param(
        _set(("axes", 1, "friction", "static_direct_nm"), 0.05),
        "axes[1].friction.static_direct_nm",
        "expected >= coulomb_direct_nm",
        id="static-below-coulomb-direct",
    ),
    pytest.param(
        _set(("axes", 1, "friction", "static_reverse_nm"), 0.01),
        "axes[1].friction.static_reverse_nm",
        "expected >= coulomb_reverse_nm",
        id="static-below-coulomb-reverse",
    ),
    # --- power-flow rule (eq. 11)
    pytest.param(
        _set(("efficiency", "motor_driving", "direct", "eta_l"), 0.9),
        "efficiency.motor_driving.direct.eta_l",
        "expected 1.0",
        id="eta-l-below-1-motor-driving",
    ),
    pytest.param(
        _set(("efficiency", "load_driving", "reverse", "eta_m"), 0.9),
        "efficiency.load_driving.reverse.eta_m",
        "expected 1.0",
        id="eta-m-below-1-load-driving",
    ),
    pytest.param(
        _set(("efficiency", "coasting", "direct", "eta_m"), 0.8),
        "efficiency.coasting.direct.eta_m",
        "expected 1.0",
        id="eta-m-below-1-coasting",
    ),
    pytest.param(
        _axis_efficiency_override,
        "axes[1].efficiency.motor_driving.reverse.eta_l",
        "expected 1.0",
        id="eta-l-below-1-in-axis-override",
    ),
    # --- the state table
    pytest.param(
        _delete(("state_machine", "states", 4)),
        "state_machine.states",
        "do not cover motor brakes, load resists",
        id="table-misses-coasting",
    ),
    pytest.param(
        _set(("state_machine", "states"), []),
        "state_machine.states",
        "expected at least one state",
        id="table-empty",
    ),
    pytest.param(
        _set(("state_machine", "states", 4, "name"), "motor_driving"),
        "state_machine.states[4].name",
        "used twice",
        id="duplicate-state-name",
    ),
    pytest.param(
        _set(("state_machine", "states", 0, "name"), "stop_hold"),
        "state_machine.states[0].name",
        "used twice",
        id="state-name-of-a-stop-state",
    ),
    pytest.param(
        _set(("state_machine", "states", 0, "motor"), "pushes"),
        "state_machine.states[0].motor",
        "expected one of any, drives, brakes",
        id="unknown-motor-word",
    ),
    pytest.param(
        _set(("state_machine", "states", 3, "load"), "helps"),
        "state_machine.states[3].load",
        "expected one of any, drives, resists",
        id="unknown-load-word",
    ),
    pytest.param(
        _set(("state_machine", "states", 1, "dominant"), "both"),
        "state_machine.states[1].dominant",
        "expected one of any, motor, load",
        id="unknown-dominant-word",
    ),
    # --- the axes list
    pytest.param(_swap_first_axes, "axes", "in that order", id="axes-wrong-order"),
    pytest.param(_delete(("axes", 3)), "axes", "in that order", id="axes-missing-lift"),
    pytest.param(
        _set(("axes", 3, "name"), "tilt"), "axes", "in that order", id="axes-unknown-name"
    ),
    pytest.param(_set(("axes",), {"l_arm": {}}), "axes", "expected a list", id="axes-not-a-list"),
    # --- the URDF
    pytest.param(
        _set(("robot", "urdf"), "no/such/gantry.urdf"),
        "robot.urdf",
        "file not found: ",
        id="urdf-not-found",
    ),
]


@pytest.mark.parametrize(("mutate", "key", "expected"), ROBOT_CASES)
def test_bad_robot_config(tmp_path: Path, mutate: Mutation, key: str, expected: str) -> None:
    """A robot config with one mistake gives a ConfigError naming file, key and expectation."""
    path = _write_robot(tmp_path, mutate)
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(info.value, path, key, expected)


SCENARIO_CASES = [
    # --- unknown keys and names
    pytest.param(_set(("repeat",), 2), "repeat", "unknown key", id="unknown-top-level"),
    pytest.param(
        _set(("initial", "acceleration"), {}),
        "initial.acceleration",
        "unknown key",
        id="unknown-in-initial",
    ),
    pytest.param(
        _set(("inputs", "pivot", "interpolation"), "linear"),
        "inputs.pivot.interpolation",
        "unknown key",
        id="unknown-in-table",
    ),
    pytest.param(
        _set(("initial", "position", "tilt"), 0.1),
        "initial.position.tilt",
        "expected an axis name (l_arm, pivot, c_arc, lift)",
        id="unknown-axis-initial-position",
    ),
    pytest.param(
        _set(("initial", "velocity"), {"pivott": 0.0}),
        "initial.velocity.pivott",
        "expected an axis name",
        id="unknown-axis-initial-velocity",
    ),
    pytest.param(
        _set(("inputs", "tilt"), {"time_s": [0.0], "voltage_v": [1.0]}),
        "inputs.tilt",
        "expected an axis name (l_arm, pivot, c_arc, lift)",
        id="unknown-axis-inputs",
    ),
    # --- missing keys and wrong types
    pytest.param(
        _delete(("duration_s",)), "duration_s", "missing required key", id="missing-duration"
    ),
    pytest.param(
        _delete(("inputs", "pivot", "voltage_v")),
        "inputs.pivot.voltage_v",
        "missing required key",
        id="missing-voltage-list",
    ),
    pytest.param(
        _set(("duration_s",), "42 s"), "duration_s", "expected a number", id="string-duration"
    ),
    pytest.param(
        _set(("inputs", "pivot", "voltage_v", 2), "high"),
        "inputs.pivot.voltage_v[2]",
        "expected a number",
        id="string-voltage",
    ),
    pytest.param(
        _set(("inputs", "pivot", "voltage_v", 1), True),
        "inputs.pivot.voltage_v[1]",
        "expected a number",
        id="bool-voltage",
    ),
    pytest.param(
        _set(("inputs", "pivot", "voltage_v", 2), float("nan")),
        "inputs.pivot.voltage_v[2]",
        "expected a finite number",
        id="nan-voltage",
    ),
    pytest.param(
        _set(("initial", "position"), [0.44]),
        "initial.position",
        "expected a mapping, got list",
        id="list-for-initial-position",
    ),
    pytest.param(
        _set(("inputs", "pivot"), [0.0, 5.5]),
        "inputs.pivot",
        "expected a mapping, got list",
        id="list-for-table",
    ),
    pytest.param(
        _set(("inputs", "pivot", "time_s"), 0.0),
        "inputs.pivot.time_s",
        "expected a list",
        id="number-for-time-list",
    ),
    pytest.param(
        _set(("initial", "position", "pivot"), float("inf")),
        "initial.position.pivot",
        "expected a finite number",
        id="inf-initial-position",
    ),
    # --- voltage tables
    pytest.param(
        _set(("inputs", "pivot", "voltage_v"), [0.0, 0.0, 5.5]),
        "inputs.pivot.voltage_v",
        "expected as many voltages as times",
        id="mismatched-lengths",
    ),
    pytest.param(
        _set(("inputs", "pivot"), {"time_s": [], "voltage_v": []}),
        "inputs.pivot.voltage_v",
        "(>= 1)",
        id="empty-table",
    ),
    pytest.param(
        _set(("inputs", "pivot", "time_s", 2), 20.0),
        "inputs.pivot.time_s[2]",
        "expected non-decreasing times",
        id="decreasing-times",
    ),
    pytest.param(
        _set(("inputs", "pivot", "time_s"), [0.0, 24.0, 24.0, 24.0, 40.2]),
        "inputs.pivot.time_s[3]",
        "expected a time at most twice",
        id="time-three-times",
    ),
    pytest.param(
        _set(("inputs", "pivot", "time_s", 0), -1.0),
        "inputs.pivot.time_s[0]",
        "expected a number >= 0",
        id="negative-time",
    ),
    # --- timing
    pytest.param(
        _set(("record_period_s",), 0.01234),
        "record_period_s",
        "expected a whole multiple of dt_s",
        id="record-not-multiple-of-dt",
    ),
    pytest.param(
        _set(("record_period_s",), 5e-5),
        "record_period_s",
        "expected a whole multiple of dt_s",
        id="record-shorter-than-dt",
    ),
    pytest.param(_set(("dt_s",), 0.0), "dt_s", "expected a number > 0", id="zero-dt"),
    pytest.param(_set(("dt_s",), -1e-4), "dt_s", "expected a number > 0", id="negative-dt"),
    pytest.param(_set(("dt_s",), 0.02), "dt_s", "expected a number <= 0.01", id="dt-too-large"),
    pytest.param(
        _set(("duration_s",), -1.0), "duration_s", "expected a number > 0", id="negative-duration"
    ),
    pytest.param(
        _set_top({"duration_s": 1.0e4, "dt_s": 1e-5}),
        "dt_s",
        f"expected at most {MAX_STEPS} steps",
        id="too-many-steps",
    ),
]


@pytest.mark.parametrize(("mutate", "key", "expected"), SCENARIO_CASES)
def test_bad_scenario(tmp_path: Path, mutate: Mutation, key: str, expected: str) -> None:
    """A scenario with one mistake gives a ConfigError naming file, key and expectation."""
    path = _write_scenario(tmp_path, mutate)
    with pytest.raises(ConfigError) as info:
        load_scenario(str(path), AXIS_NAMES)
    _assert_config_error(info.value, path, key, expected)


def test_scenario_that_is_a_list(tmp_path: Path) -> None:
    """A scenario document that is a list, not a mapping, is rejected at the top level."""
    path = _write(tmp_path / "list.yaml", [{"duration_s": 1.0}])
    with pytest.raises(ConfigError) as info:
        load_scenario(str(path), AXIS_NAMES)
    _assert_config_error(info.value, path, "", "expected a mapping, got list")


def test_empty_scenario_file(tmp_path: Path) -> None:
    """An empty scenario file says the top level should be a mapping and got nothing."""
    path = tmp_path / "empty.yaml"
    path.write_text("", encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_scenario(str(path), AXIS_NAMES)
    _assert_config_error(info.value, path, "", "expected a mapping, got nothing")


@pytest.mark.parametrize("text", ["", "- 1\n- 2\n"], ids=["empty", "list"])
def test_robot_file_that_is_not_a_mapping(tmp_path: Path, text: str) -> None:
    """An empty or non-mapping robot file is reported at the top level as 'expected a mapping'."""
    path = tmp_path / "robot.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(info.value, path, "", "expected a mapping")


def test_robot_file_without_robot_section(tmp_path: Path) -> None:
    """A robot file without the `robot:` section names robot.urdf, the first thing needed."""
    path = _write_robot(tmp_path, _delete(("robot",)))
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(info.value, path, "robot.urdf", "expected the path of the gantry URDF")


@pytest.mark.parametrize("kind", ["robot", "scenario"])
def test_file_not_utf8(tmp_path: Path, kind: str) -> None:
    """A Latin-1 encoded file gives a ConfigError naming the file, not a decode traceback."""
    path = tmp_path / f"{kind}.yaml"
    path.write_bytes("robot:\n  name: caf\u00e9\n".encode("latin-1"))
    with pytest.raises(ConfigError) as info:
        if kind == "robot":
            load_robot(str(path))
        else:
            load_scenario(str(path), AXIS_NAMES)
    assert info.value.source == str(path)
    assert "UTF-8" in info.value.expected


def _break_line(text: str, marker: str, replacement: str) -> tuple[str, int]:
    """Replace the first line containing `marker`; return the new text and that line's number."""
    lines = text.splitlines()
    index = next(i for i, line in enumerate(lines) if marker in line)
    lines[index] = replacement
    return "\n".join(lines) + "\n", index + 1


@pytest.mark.parametrize(
    ("marker", "replacement", "problem"),
    [
        pytest.param(
            "resistance_ohm: 1.2",
            "      resistance_ohm: 1.2: 3",
            "mapping values are not allowed here",
            id="two-colons",
        ),
        pytest.param(
            "irreversible_stop",
            "\tirreversible_stop: true",
            "found character '\\t' that cannot start any token",
            id="tab-indent",
        ),
    ],
)
def test_robot_yaml_syntax_error_names_the_line(
    tmp_path: Path, marker: str, replacement: str, problem: str
) -> None:
    """A YAML syntax error gives one line naming the file, the line number and the problem."""
    text, line = _break_line(DEFAULT_YAML.read_text(encoding="utf-8"), marker, replacement)
    path = tmp_path / "robot.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(info.value, path, f"line {line}", "expected valid YAML")
    assert problem in info.value.expected


def test_scenario_yaml_syntax_error_names_the_line(tmp_path: Path) -> None:
    """An unclosed bracket in a scenario is reported at the line where the parser notices it."""
    text, line = _break_line(
        FIG9_YAML.read_text(encoding="utf-8"), "voltage_v:", "    voltage_v: [0.0, 0.0"
    )
    path = tmp_path / "scenario.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_scenario(str(path), AXIS_NAMES)
    assert info.value.source == str(path)
    assert info.value.key.startswith("line ")
    assert int(info.value.key.removeprefix("line ")) >= line
    assert "expected valid YAML" in info.value.expected


# --- base: inheritance --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("base", "expected"),
    [
        pytest.param(
            "no_such_robot",
            "unknown robot 'no_such_robot'; valid: default, reversible",
            id="unknown-name",
        ),
        pytest.param("missing.yaml", "file not found", id="missing-file"),
        pytest.param("sub/", "file not found", id="folder"),
        pytest.param(5, "expected a robot name or a path, got 5", id="not-a-string"),
    ],
)
def test_bad_base(tmp_path: Path, base: object, expected: str) -> None:
    """A `base:` that names no robot file is an error on the key `base` of the user file."""
    (tmp_path / "sub").mkdir()
    path = _write(tmp_path / "mine.yaml", {"base": base, "robot": {"name": "mine"}})
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(info.value, path, "base", expected)


def test_base_cycle(tmp_path: Path) -> None:
    """a.yaml based on b.yaml based on a.yaml is reported as a cycle, not a RecursionError."""
    a = _write(tmp_path / "a.yaml", {"base": "b.yaml", "robot": {"name": "a"}})
    _write(tmp_path / "b.yaml", {"base": "a.yaml", "robot": {"name": "b"}})
    with pytest.raises(ConfigError) as info:
        load_robot(str(a))
    _assert_config_error(info.value, a.resolve(), "base", "expected no cycle of base files")


def test_base_on_itself(tmp_path: Path) -> None:
    """A file that is its own base is a cycle."""
    path = _write(tmp_path / "self.yaml", {"base": "./self.yaml"})
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(info.value, path.resolve(), "base", "expected no cycle of base files")


def test_base_partial_axes_list_replaces_the_whole_list(tmp_path: Path) -> None:
    """Lists are not merged: a one-axis `axes:` override replaces base's list, so it is invalid.

    The merge is deep for mappings only; `axes: [{name: pivot, ...}]` becomes the whole axes list
    and its first missing field is reported, on the user file that holds the override.
    """
    path = _write(
        tmp_path / "mine.yaml",
        {"base": "default", "axes": [{"name": "pivot", "motor": {"resistance_ohm": 2.5}}]},
    )
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(info.value, path, "axes[0].gear_ratio", "missing required key")


def test_error_inherited_from_base_is_reported_on_the_loaded_file(tmp_path: Path) -> None:
    """A mistake that sits in the base file is reported with the name of the file loaded."""
    base = _write_robot(tmp_path, _set(("axes", 2, "motor", "resistance_ohm"), -2.0), "base.yaml")
    child = _write(tmp_path / "child.yaml", {"base": base.name, "robot": {"name": "child"}})
    with pytest.raises(ConfigError) as info:
        load_robot(str(child))
    _assert_config_error(info.value, child, "axes[2].motor.resistance_ohm", "> 0")


# --- unknown names and missing files ------------------------------------------------------


def test_unknown_shipped_robot_lists_valid_names() -> None:
    """An unknown shipped robot name lists the shipped robots."""
    with pytest.raises(UnknownNameError) as info:
        load_robot("no_such_robot")
    assert info.value.kind == "robot"
    assert info.value.valid == ("default", "reversible")
    assert str(info.value) == "unknown robot 'no_such_robot'; valid: default, reversible"


def test_unknown_shipped_scenario_lists_valid_names() -> None:
    """An unknown shipped scenario name lists the shipped scenarios."""
    with pytest.raises(UnknownNameError) as info:
        load_scenario("no_such_scenario", AXIS_NAMES)
    assert info.value.valid == ("fig9_open_loop_pivot", "hold_pivot", "identify_pivot")
    assert "valid: fig9_open_loop_pivot, hold_pivot, identify_pivot" in str(info.value)


@pytest.mark.parametrize("kind", ["robot", "scenario"])
def test_missing_file_path(tmp_path: Path, kind: str) -> None:
    """A path to a file that does not exist names the path and says it was not found."""
    path = tmp_path / "missing.yaml"
    with pytest.raises(ConfigError) as info:
        if kind == "robot":
            load_robot(str(path))
        else:
            load_scenario(str(path), AXIS_NAMES)
    _assert_config_error(info.value, path, "", "file not found")


# --- what loads -----------------------------------------------------------------------------


def test_shipped_names() -> None:
    """The shipped robots and scenarios are found by name."""
    assert shipped_names("robots") == ("default", "reversible")
    assert shipped_names("scenarios") == ("fig9_open_loop_pivot", "hold_pivot", "identify_pivot")


@pytest.mark.parametrize("name", ["default", "reversible"])
def test_shipped_robot_loads(name: str) -> None:
    """Each shipped robot loads with the four axes in model order and the gantry URDF."""
    robot = load_robot(name)
    assert robot.axis_names == ("l_arm", "pivot", "c_arc", "lift")
    assert Path(robot.source).name == f"{name}.yaml"
    assert '<robot name="lca_gantry">' in robot.urdf_xml
    assert robot.gravity_m_s2 == (0.0, 0.0, -9.81)


def test_shipped_scenarios_load() -> None:
    """The shipped scenarios load with the values written in their files."""
    fig9 = load_scenario("fig9_open_loop_pivot", AXIS_NAMES)
    assert (fig9.duration_s, fig9.dt_s, fig9.record_period_s) == (42.0, 1e-4, 0.01)
    assert (fig9.n_steps, fig9.record_every) == (420_000, 100)
    assert fig9.initial_position == (0.0, 0.44, 0.0, 0.0)
    assert fig9.initial_velocity == (0.0, 0.0, 0.0, 0.0)
    pivot = fig9.inputs[1]
    assert pivot is not None
    raw = yaml.safe_load((CONFIG / "scenarios" / "fig9_open_loop_pivot.yaml").read_text())
    assert pivot.time_s == tuple(raw["inputs"]["pivot"]["time_s"])
    assert pivot.voltage_v == tuple(raw["inputs"]["pivot"]["voltage_v"])
    assert (fig9.inputs[0], fig9.inputs[2], fig9.inputs[3]) == (None, None, None)

    hold = load_scenario("hold_pivot", AXIS_NAMES)
    assert hold.duration_s == 10.0
    assert hold.initial_position == (0.0, 0.0, 0.0, 0.0)
    assert hold.inputs[1] is not None
    assert hold.inputs[1].voltage_v == (0.0,)


def test_default_robot_values(default_robot: RobotParams) -> None:
    """The default robot has the irreversible stop and the Table 1 efficiencies of its file."""
    assert default_robot.name == "lca_default"
    assert default_robot.state_machine.irreversible_stop is True
    pivot = default_robot.axes[1]
    raw = yaml.safe_load((CONFIG / "robots" / "default.yaml").read_text())["axes"][1]
    assert pivot.motor.resistance_ohm == raw["motor"]["resistance_ohm"]
    assert pivot.motor.inductance_h == raw["motor"]["inductance_h"]
    assert pivot.friction.static_reverse_nm == raw["friction"]["static_reverse_nm"]
    table = pivot.efficiency
    assert table[(MotionState.DIRECT, "motor_driving")].eta_m == 0.9
    assert table[(MotionState.REVERSE, "motor_and_load_driving_load_dominant")].eta_l == 0.16
    assert table[(MotionState.REVERSE, "motor_and_load_driving_motor_dominant")].eta_l == 0.06


def test_reversible_inherits_default(
    default_robot: RobotParams, reversible_robot: RobotParams
) -> None:
    """`reversible` keeps default's axes, URDF and states but has eta = 1 and a reversible stop."""
    assert reversible_robot.name == "lca_reversible"
    assert reversible_robot.urdf_xml == default_robot.urdf_xml
    assert reversible_robot.gravity_m_s2 == default_robot.gravity_m_s2
    assert reversible_robot.state_machine.irreversible_stop is False
    assert reversible_robot.state_machine.rules == default_robot.state_machine.rules
    assert (
        reversible_robot.state_machine.velocity_eps_rad_s
        == default_robot.state_machine.velocity_eps_rad_s
    )
    for mine, theirs in zip(reversible_robot.axes, default_robot.axes, strict=True):
        assert (mine.name, mine.gear_ratio) == (theirs.name, theirs.gear_ratio)
        assert mine.motor == theirs.motor
        assert mine.friction == theirs.friction
        assert len(mine.efficiency) == 10
        assert {(e.eta_m, e.eta_l) for e in mine.efficiency.values()} == {(1.0, 1.0)}


def test_user_robot_base_default_merges_mappings(
    tmp_path: Path, default_robot: RobotParams
) -> None:
    """With `base: default`, mapping keys merge deeply and robot.urdf resolves beside default."""
    path = _write(
        tmp_path / "mine.yaml",
        {
            "base": "default",
            "robot": {"name": "mine"},
            "state_machine": {"velocity_eps_rad_s": 0.02},
        },
    )
    robot = load_robot(str(path))
    assert robot.name == "mine"
    assert robot.source == str(path)
    assert robot.urdf_xml == default_robot.urdf_xml
    assert robot.state_machine.velocity_eps_rad_s == 0.02
    assert robot.state_machine.motor_torque_eps_nm == 1.0e-5
    assert robot.state_machine.irreversible_stop is True
    assert robot.state_machine.rules == default_robot.state_machine.rules
    assert robot.axes == default_robot.axes


def test_user_robot_base_default_full_axes_list_overrides_one_field(
    tmp_path: Path, default_robot: RobotParams
) -> None:
    """To change one axis field under `base: default` the whole axes list must be given."""
    axes = _default_robot_doc()["axes"]
    axes[1]["motor"]["resistance_ohm"] = 2.5
    path = _write(tmp_path / "mine.yaml", {"base": "default", "axes": axes})
    robot = load_robot(str(path))
    assert robot.axes[1].motor.resistance_ohm == 2.5
    assert robot.axes[1].motor.inductance_h == default_robot.axes[1].motor.inductance_h
    assert robot.axes[1].friction == default_robot.axes[1].friction
    assert robot.axes[0] == default_robot.axes[0]
    assert robot.axes[2:] == default_robot.axes[2:]


def test_user_robot_urdf_relative_to_the_user_file(tmp_path: Path) -> None:
    """An overriding robot.urdf is resolved relative to the file that gives it."""
    (tmp_path / "gantry").mkdir()
    urdf_text = URDF.read_text(encoding="utf-8")
    (tmp_path / "gantry" / "copy.urdf").write_text(urdf_text, encoding="utf-8")
    path = _write(
        tmp_path / "mine.yaml", {"base": "default", "robot": {"urdf": "gantry/copy.urdf"}}
    )
    assert load_robot(str(path)).urdf_xml == urdf_text

    wrong = _write(
        tmp_path / "wrong.yaml", {"base": "default", "robot": {"urdf": "gantry/none.urdf"}}
    )
    with pytest.raises(ConfigError) as info:
        load_robot(str(wrong))
    _assert_config_error(info.value, wrong, "robot.urdf", "file not found: ")
    assert str(tmp_path / "gantry" / "none.urdf") in info.value.expected


def test_base_by_relative_path(tmp_path: Path) -> None:
    """`base:` with a path is resolved relative to the file that names it."""
    _write_robot(tmp_path, _set(("robot", "name"), "parent"), "parent.yaml")
    (tmp_path / "sub").mkdir()
    child = _write(tmp_path / "sub" / "child.yaml", {"base": "../parent.yaml"})
    robot = load_robot(str(child))
    assert robot.name == "parent"
    assert robot.axis_names == AXIS_NAMES


def test_voltage_table_with_a_step(tmp_path: Path) -> None:
    """A repeated time is a step: the table is right-continuous and held after its end."""
    path = _write(
        tmp_path / "step.yaml",
        {
            "duration_s": 1.0,
            "dt_s": 0.001,
            "record_period_s": 0.01,
            "inputs": {"lift": {"time_s": [0.0, 0.5, 0.5], "voltage_v": [0.0, 2.0, 6.0]}},
        },
    )
    scenario = load_scenario(str(path), AXIS_NAMES)
    table = scenario.inputs[3]
    assert table is not None
    sampled = table.sample(np.array([0.0, 0.25, 0.5, 0.9]))
    assert sampled.tolist() == [0.0, 1.0, 6.0, 6.0]


def test_key_given_twice_is_an_error(tmp_path: Path) -> None:
    """A key repeated in one mapping names its line instead of silently taking the last."""
    path = tmp_path / "twice.yaml"
    path.write_text("duration_s: 1.0\ndt_s: 1.0e-4\ndt_s: 2.0e-4\nrecord_period_s: 0.01\n")
    with pytest.raises(ConfigError) as info:
        load_scenario(str(path), AXIS_NAMES)
    assert info.value.key == "line 3"
    assert "'dt_s' is given twice" in info.value.expected


def test_exponent_without_dot_is_a_number(tmp_path: Path) -> None:
    """YAML 1.1 reads 1e-4 as a string; the loader still takes it as the number it plainly is."""
    path = tmp_path / "exp.yaml"
    path.write_text("duration_s: 1\ndt_s: 1e-4\nrecord_period_s: 1e-2\n")
    scenario = load_scenario(str(path), AXIS_NAMES)
    assert (scenario.dt_s, scenario.record_period_s, scenario.n_steps) == (1e-4, 1e-2, 10_000)


# --- simulator node parameters ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (2.5e-4, "expected a whole multiple of dt_s = 0.0001"),
        (5e-5, "expected a whole multiple of dt_s = 0.0001"),
        (0.02, "expected a number in (0, 0.01]"),
        (0.0, "expected a number in (0, 0.01]"),
        ("1ms", "expected a number"),
    ],
)
def test_bad_rigid_body_period(value: object, expected: str) -> None:
    """The rigid-body update period must be a whole number of model steps, at most 10 ms."""
    from lca_control.parameters import ParameterError
    from lca_sim.config.simulator_params import SIMULATOR_PARAMETERS, validate_simulator_params

    values = SIMULATOR_PARAMETERS.defaults()
    assert validate_simulator_params(values).rigid_body_update_steps == 10  # 1 ms / 0.1 ms
    values["rigid_body_period_s"] = value
    with pytest.raises(ParameterError) as info:
        validate_simulator_params(values)
    assert info.value.name == "rigid_body_period_s"
    assert expected in str(info.value)


# --- error texts: a misspelt key beside the missing one, one wording per missing file -------


def test_a_misspelt_required_key_is_named_beside_the_missing_one(tmp_path: Path) -> None:
    """`resistence_ohm` for `resistance_ohm`: the unknown key and what it probably is."""

    def misspell(document: Any) -> None:
        motor = document["axes"][0]["motor"]
        motor["resistence_ohm"] = motor.pop("resistance_ohm")

    path = _write_robot(tmp_path, misspell, "typo.yaml")
    with pytest.raises(ConfigError) as info:
        load_robot(str(path))
    _assert_config_error(
        info.value,
        path,
        "axes[0].motor.resistance_ohm",
        "missing required key; unknown key resistence_ohm; did you mean resistance_ohm?",
    )


def test_a_misspelt_optional_key_gets_its_suggestion() -> None:
    """An unknown key next to a known one it resembles: `did you mean`; else the known keys."""
    from lca_sim.model.schema import MappingReader

    reader = MappingReader({"dt_s": 1e-4, "gain_kp": 2.0}, "x.yaml", "ctl")
    assert reader.number("dt_s") == 1e-4
    assert reader.number("gain_kv", default=1.0) == 1.0
    with pytest.raises(ConfigError) as info:
        reader.finish()
    assert str(info.value) == "x.yaml: ctl.gain_kp: unknown key gain_kp; did you mean gain_kv?"
    reader = MappingReader({"dt_s": 1e-4, "colour": "red"}, "x.yaml")
    reader.number("dt_s")
    with pytest.raises(ConfigError) as info:
        reader.finish()
    assert str(info.value) == "x.yaml: colour: unknown key colour (valid keys here: dt_s)"


def test_a_missing_yaml_reads_file_not_found(tmp_path: Path) -> None:
    """The YAML and params-file readers say a missing file `file not found`, as `resolve` does.

    On the file that names a missing one, `file not found: PATH` (robot.urdf, above).
    """
    from lca_sim.config.params_file import node_parameters
    from lca_sim.config.yaml_files import read_yaml

    missing = tmp_path / "missing.yaml"
    for read in (read_yaml, lambda path: node_parameters(path, "simulator")):
        with pytest.raises(ConfigError) as info:
            read(missing)
        _assert_config_error(info.value, missing, "", "file not found")
