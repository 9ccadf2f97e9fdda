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

from lca_sim.cli.output import REASONS_KEY, strict_json, write_json

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


@pytest.mark.slow
def test_fig15_names_the_simulator_when_it_dies(tmp_path: Path) -> None:
    """A simulator that refuses its parameters: a one-line error naming it and its log."""
    pytest.importorskip("rclpy")
    out = tmp_path / "run"
    # not a whole multiple of the model step: the simulator refuses lockstep_end_s and exits
    result = support.run_tool("lca-hil", "fig15", "--duration-s", "1.00005", "--out", str(out))
    assert result.returncode != 0
    assert "the simulator exited" in result.stderr
    assert str(out / "simulator.log") in result.stderr
    assert "lockstep_end_s" in (out / "simulator.log").read_text(encoding="utf-8")
    assert not (out / "summary.json").exists()
