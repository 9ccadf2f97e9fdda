"""`lca-hil fig15` ends where the simulator ends the run, and every JSON the tools write is strict.

The end-to-end test here starts the three ROS 2 processes through the console script, on
loopback DDS (`scripts/env.sh`; ROS_DOMAIN_ID from the environment). The run beside a CPU hog
that must end exactly at its duration with a strict summary.json is item 7 of the fault matrix,
tests/test_fault_matrix.py: the old orchestrator stopped on its own /clock samples and recorded
past the end (3.072 s for a 3 s run on a quiet machine, 38-40 s for 13 s on a loaded one) and
wrote NaN into summary.json.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import support
from support import strict_loads

from lca_sim.config.params_file import node_parameters
from lca_sim.output import REASONS_KEY, strict_json, write_json

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

    from lca_control.contract import ENDED_KEY, SIMULATOR_STATUS
    from lca_sim.cli.fig15 import _Progress
    from lca_sim.ros.node_util import status

    progress = _Progress()
    running = status(SIMULATOR_STATUS, DiagnosticStatus.OK, "running", {ENDED_KEY: False})
    other = status("lca_hil/simulator/pivot", DiagnosticStatus.OK, "x", {ENDED_KEY: True})
    progress.on_diagnostics(DiagnosticArray(status=[running, other]))
    assert not progress.ended
    ended = status(SIMULATOR_STATUS, DiagnosticStatus.OK, "ended at 3 s", {ENDED_KEY: True})
    progress.on_diagnostics(DiagnosticArray(status=[ended]))
    assert progress.ended and progress.end_message == "ended at 3 s"
    assert math.isnan(progress.steps_per_s(0.004))  # no /clock seen


# --- the run over ROS 2 ----------------------------------------------------------------------


def test_fig15_says_the_range_before_it_starts_anything(tmp_path: Path) -> None:
    """A duration out of range: `lca-hil run`'s one line, exit 2, no process, no file."""
    out = tmp_path / "run"
    for duration, got in (("-1", "-1.0"), ("1.00005", "1.00005")):
        result = support.run_tool("lca-hil", "fig15", "--duration-s", duration, "--out", str(out))
        assert result.returncode == 2, result.stderr
        assert result.stderr.strip() == (
            "lca-hil fig15: error: duration_s: expected a time > 0 s, a whole multiple of "
            f"dt_s = 0.0001 s, got {got}"
        )
        assert not out.exists()


def test_fig15_runs_the_scenario_that_lca_hil_run_runs(tmp_path: Path) -> None:
    """The nodes get config/runs/fig15.yaml's params files unchanged; the recorder the reference.

    No initial pose, command interface or control period of fig15's own.
    """
    pytest.importorskip("rclpy")
    from lca_control import contract as pc
    from lca_sim.cli import fig15

    run = fig15.fig15_run(13.0)
    argvs = fig15._argvs(tmp_path / "bag", 13.0, run)
    simulator = " ".join(argvs["simulator"])
    assert f"--params-file {run.simulator_yaml}" in simulator
    assert "initial_position" not in simulator and "command_interface" not in simulator
    assert "control_period_s" not in simulator
    assert pc.VELOCITY_COMMANDS in argvs["recorder"]
    expected = node_parameters(run.simulator_yaml, "simulator")["initial_position"]
    assert list(run.config.initial_position) == expected  # the one file both tools read
    velocity = fig15.ramp_profile()  # the controller file's ramp, not a copy of it
    assert velocity(11.0 - 1e-9) == pytest.approx(
        node_parameters(run.controller_yaml, "controller")["ramp_end_velocity"]
    )


@pytest.mark.slow
def test_fig15_names_the_simulator_when_it_dies(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A simulator that refuses its parameters: a one-line error naming it and its log."""
    pytest.importorskip("rclpy")
    from lca_sim.cli import fig15

    argvs = fig15._argvs

    def refused(bag: Path, duration_s: float, run: fig15.Fig15Run) -> dict[str, list[str]]:
        commands = argvs(bag, duration_s, run)
        # not a whole multiple of the model step: the simulator refuses it and exits
        commands["simulator"] += ["-p", "lockstep_end_s:=1.00005"]
        return commands

    monkeypatch.setattr(fig15, "_argvs", refused)
    out = tmp_path / "run"
    assert fig15.run_fig15(out, 1.0) == 1
    err = capsys.readouterr().err
    assert "the simulator exited" in err and str(out / "simulator.log") in err
    assert "lockstep_end_s" in (out / "simulator.log").read_text(encoding="utf-8")
    assert not (out / "summary.json").exists()


def test_a_recording_that_lost_states_is_reported() -> None:
    """A bag that misses the run's end, or states in between, gets a warning each; a whole one none.

    The run publishes a state at 0 and every 4 ms to 13 s: 3,251 states.
    """
    from lca_sim.cli import fig15

    period_s, duration_s = 0.004, 13.0
    whole = [k * period_s for k in range(3251)]
    assert fig15.recording_problems(whole, duration_s, period_s) == []
    cut = whole[:2661]  # fault matrix item 7's bag: stopped at 10.64 s, no gap
    (end,) = fig15.recording_problems(cut, duration_s, period_s)
    assert "last state is at 10.640000 s" in end
    gap = whole[:1000] + whole[1100:]  # 100 states lost mid-run
    (lost,) = fig15.recording_problems(gap, duration_s, period_s)
    assert "3151 states up to 13 s of the 3251" in lost
