"""A closed-loop scenario file (config/runs/): its files, its length and its key checks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from support import CONFIG

from lca_sim.config.loader import shipped_names
from lca_sim.config.run_scenario import SCENARIO_KEYS, RunScenario, load_run_scenario
from lca_sim.errors import ConfigError, UnknownNameError


def _write(tmp_path: Path, document: Any) -> Path:
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


@pytest.mark.parametrize("name", shipped_names("runs"))
def test_the_shipped_scenarios_load(name: str) -> None:
    """Every file in config/runs/ is a valid scenario whose files exist."""
    scenario = load_run_scenario(name)
    for path in (scenario.controller, scenario.simulator, scenario.robot, scenario.faults):
        assert path is None or path.is_file()


def test_a_shipped_name_and_a_path_from_the_scenarios_folder(tmp_path: Path) -> None:
    """`simulator: simulator` is config/ros/; `controller: mine.yaml` sits beside the file."""
    (tmp_path / "mine.yaml").write_text("controller: {ros__parameters: {}}\n", encoding="utf-8")
    path = _write(tmp_path, {"controller": "mine.yaml", "simulator": "simulator", "duration_s": 2})
    assert load_run_scenario(str(path)) == RunScenario(
        controller=tmp_path / "mine.yaml",
        simulator=CONFIG / "ros" / "simulator.yaml",
        duration_s=2.0,
    )


def test_an_empty_mapping_gives_nothing() -> None:
    """Every key is optional: `{}` says nothing, and the options decide."""
    assert RunScenario() == RunScenario(None, None, None, None, None)
    assert set(SCENARIO_KEYS) == {"description", *RunScenario.__dataclass_fields__}


@pytest.mark.parametrize(
    ("document", "key", "message"),
    [
        ({"contoller": "x"}, "contoller", "unknown key contoller; did you mean controller?"),
        ({"duration_s": 0}, "duration_s", "expected a time > 0 s, got 0"),
        ({"duration_s": True}, "duration_s", "expected a time > 0 s, got True"),
        ({"duration_s": "5"}, "duration_s", "expected a time > 0 s, got '5'"),
        ({"robot": 3}, "robot", "expected a shipped robots name or a path"),
        ({"faults": "none.yaml"}, "faults", "file not found: {home}/none.yaml"),
        (["controller"], "<top level>", "expected a closed-loop scenario (a mapping)"),
    ],
    ids=["unknown key", "zero length", "a boolean", "text", "not a name", "missing", "a list"],
)
def test_a_bad_scenario_names_its_key(
    tmp_path: Path, document: Any, key: str, message: str
) -> None:
    """One ConfigError: the scenario's file, the key, what was expected."""
    path = _write(tmp_path, document)
    with pytest.raises(ConfigError) as caught:
        load_run_scenario(str(path))
    assert str(caught.value) == f"{path}: {key}: {message.format(home=tmp_path)}"


def test_an_unknown_shipped_name_lists_the_valid_ones(tmp_path: Path) -> None:
    """A scenario name not in config/runs/, or a file name not in config/ros/."""
    with pytest.raises(UnknownNameError, match="fig15_encoder_freeze"):
        load_run_scenario("fig16")
    with pytest.raises(UnknownNameError, match="controller"):
        load_run_scenario(str(_write(tmp_path, {"simulator": "simulatr"})))
