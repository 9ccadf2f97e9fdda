"""`lca-hil fig15` ends where the simulator ends the run, and every JSON the tools write is strict.

The end-to-end tests start the three ROS 2 processes through the console script, on loopback
DDS (`scripts/env.sh`; ROS_DOMAIN_ID from the environment, 73 if unset), beside a CPU hog: the
old orchestrator stopped on its own /clock samples and recorded past the end (3.072 s for a
3 s run on a quiet machine, 38-40 s for 13 s on a loaded one) and wrote NaN into
summary.json.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from lca_sim.cli.output import REASONS_KEY, strict_json, write_json

DURATION_S = 3.0
RUN_TIMEOUT_S = 300.0  # a deadline for the whole run, far beyond its ~15 s


def _refuse_constant(name: str) -> float:
    """parse_constant for json.loads: NaN, Infinity and -Infinity are not JSON."""
    raise ValueError(f"not strict JSON: {name}")


def strict_loads(text: str) -> object:
    """json.loads that fails on the non-standard NaN / Infinity tokens."""
    return json.loads(text, parse_constant=_refuse_constant)


# --- the strict JSON helper ------------------------------------------------------------------


def test_strict_json_nulls_non_finite_floats_and_says_why() -> None:
    """NaN and +-inf, also numpy ones and nested, become null with a reason by their path."""
    data: dict[str, object] = {
        "ok": 1.5,
        "count": 3,
        "missing": math.nan,
        "nested": {"rate": np.float64(math.inf), "list": [1.0, -math.inf, "x", None]},
    }
    text = strict_json(data, {"missing": "no transition in the run"})
    doc = strict_loads(text)
    assert doc == {
        "ok": 1.5,
        "count": 3,
        "missing": None,
        "nested": {"rate": None, "list": [1.0, None, "x", None]},
        REASONS_KEY: {
            "missing": "no transition in the run",
            "nested.rate": "not a finite number (inf)",
            "nested.list[1]": "not a finite number (-inf)",
        },
    }
    missing = data["missing"]
    assert isinstance(missing, float) and math.isnan(missing)  # the caller's data is unchanged


def test_strict_json_of_finite_data_is_plain_json() -> None:
    """Finite data is written as json.dumps writes it, with no reasons added; one line too."""
    data = {"a": [1.0, 2], "b": {"c": "d"}, "e": True}
    assert strict_json(data) == json.dumps(data, indent=2)
    assert strict_json(data, indent=None) == json.dumps(data)
    assert strict_json([math.nan], indent=None) == "[null]"  # no dict: nowhere to say why


def test_write_json_writes_strict_json(tmp_path: Path) -> None:
    """write_json: the file parses strictly and ends with a newline."""
    path = tmp_path / "sub" / "summary.json"
    write_json(path, {"x": math.nan}, {"x": "why"})
    text = path.read_text(encoding="utf-8")
    assert text.endswith("}\n")
    assert strict_loads(text) == {"x": None, REASONS_KEY: {"x": "why"}}


def test_progress_sees_the_simulators_end() -> None:
    """The orchestrator takes the end from the simulator's status, not from another one."""
    pytest.importorskip("rclpy")
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from lca_sim.cli.fig15 import _Progress
    from lca_sim.ros.node_util import status
    from lca_sim.ros.simulator_params import ENDED_KEY, SIMULATOR_STATUS

    progress = _Progress()
    running = status(SIMULATOR_STATUS, DiagnosticStatus.OK, "running", {ENDED_KEY: False})
    other = status("lca_hil/simulator/pivot", DiagnosticStatus.OK, "x", {ENDED_KEY: True})
    progress.on_diagnostics(DiagnosticArray(status=[running, other]))
    assert not progress.ended
    ended = status(SIMULATOR_STATUS, DiagnosticStatus.OK, "ended at 3 s", {ENDED_KEY: True})
    progress.on_diagnostics(DiagnosticArray(status=[ended]))
    assert progress.ended and progress.end_message == "ended at 3 s"
    assert math.isnan(progress.steps_per_s())  # no /clock seen


# --- the run over ROS 2 ----------------------------------------------------------------------


def _ros_env() -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("ROS_DOMAIN_ID", "73")
    return env


@contextmanager
def cpu_hog() -> Iterator[None]:
    """One process spinning a busy loop for the block's duration (a loaded machine)."""
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield
    finally:
        hog.kill()
        hog.wait()


def _lca_hil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(Path(sys.executable).with_name("lca-hil")), *args],
        env=_ros_env(),
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        check=False,
    )


@pytest.mark.slow
def test_fig15_ends_exactly_at_the_duration_under_load(tmp_path: Path) -> None:
    """The bag's last joint state is stamped the duration; summary.json is strict JSON."""
    pytest.importorskip("rclpy")
    from lca_sim.cli.bagplot import read_bag

    out = tmp_path / "run"
    with cpu_hog():
        result = _lca_hil("fig15", "--duration-s", f"{DURATION_S:g}", "--out", str(out))
    assert result.returncode == 0, result.stdout + result.stderr
    data = read_bag(out / "bag")
    assert data.time_base == "header"
    for joint, series in data.joints.items():
        assert series.time_s[0] == 0.0, joint
        assert abs(series.time_s[-1] - DURATION_S) < 1e-9, (joint, series.time_s[-1])
    steps = round(DURATION_S / 0.004) + 1  # t = 0 and every 4 ms control period to the end
    assert len(data.joints["pivot"].time_s) == steps
    summary = strict_loads((out / "summary.json").read_text(encoding="utf-8"))
    assert isinstance(summary, dict)
    assert summary["last_state_s"] == DURATION_S
    assert summary["states_recorded"] == steps
    # 3 s is too short for the pivot to leave motor driving (that comes near 10 s)
    assert summary["transition_time_s"] is None
    assert "motor driving" in summary[REASONS_KEY]["transition_time_s"]


@pytest.mark.slow
def test_fig15_names_the_simulator_when_it_dies(tmp_path: Path) -> None:
    """A simulator that refuses its parameters: a one-line error naming it and its log."""
    pytest.importorskip("rclpy")
    out = tmp_path / "run"
    # not a whole multiple of the model step: the simulator refuses lockstep_end_s and exits
    result = _lca_hil("fig15", "--duration-s", "1.00005", "--out", str(out))
    assert result.returncode != 0
    assert "the simulator exited" in result.stderr
    assert str(out / "simulator.log") in result.stderr
    assert "lockstep_end_s" in (out / "simulator.log").read_text(encoding="utf-8")
    assert not (out / "summary.json").exists()
