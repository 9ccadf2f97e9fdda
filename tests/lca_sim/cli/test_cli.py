"""`lca-sim run`: exit codes, one-line errors, the result files and atomic output."""

from __future__ import annotations

import contextlib
import csv
import io
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import pytest
import yaml
from support import CONFIG

from lca_sim.cli.sim import main

DEFAULT_YAML = CONFIG / "robots" / "default.yaml"
URDF = CONFIG / "urdf" / "lca_gantry.urdf"

AXES = ("l_arm", "pivot", "c_arc", "lift")
AXIS_COLUMNS = (
    "position",
    "velocity",
    "motor_velocity_rad_s",
    "current_a",
    "voltage_v",
    "motor_torque_nm",
    "load_torque_nm",
    "friction_torque_nm",
    "motion_state",
    "drive_state",
    "eta_m",
    "eta_l",
)
EXPECTED_HEADER = ["t_s", *(f"{axis}_{col}" for axis in AXES for col in AXIS_COLUMNS)]

SHORT_DURATION_S = 0.5
SHORT_RECORD_S = 0.01
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _short_scenario(duration_s: float = SHORT_DURATION_S) -> dict[str, Any]:
    """A short pivot ramp to 8 V: enough to leave stop_hold and reach motor_driving."""
    return {
        "duration_s": duration_s,
        "dt_s": 1.0e-4,
        "record_period_s": SHORT_RECORD_S,
        "inputs": {"pivot": {"time_s": [0.0, 0.2], "voltage_v": [0.0, 8.0]}},
    }


def _write(path: Path, doc: object) -> Path:
    """Dump `doc` as YAML to `path` and return the path."""
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def _robot_doc() -> Any:
    """The shipped default robot with an absolute robot.urdf, ready to be changed and copied."""
    doc = yaml.safe_load(DEFAULT_YAML.read_text(encoding="utf-8"))
    doc["robot"]["urdf"] = str(URDF)
    return doc


class Outcome(NamedTuple):
    """What one in-process `lca-sim` call returned and printed."""

    code: int
    out: str
    err: str


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> Outcome:
    """Call `lca_sim.cli.sim.main` in-process and capture what it prints."""
    capsys.readouterr()
    code = main(args)
    captured = capsys.readouterr()
    return Outcome(code, captured.out, captured.err)


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """The header and the data rows (as dicts) of a result.csv."""
    with path.open(newline="", encoding="utf-8") as handle:
        rows = list(csv.reader(handle))
    header = rows[0]
    return header, [dict(zip(header, row, strict=True)) for row in rows[1:]]


def _assert_one_error_line(outcome: Outcome, *fragments: str) -> str:
    """Exit code 2, exactly one `lca-sim: error:` line on stderr with every fragment, no trace."""
    assert outcome.code == 2
    assert "Traceback" not in outcome.err
    assert "Traceback" not in outcome.out
    lines = outcome.err.splitlines()
    assert len(lines) == 1, outcome.err
    assert outcome.err.endswith("\n")
    line = lines[0]
    assert line.startswith("lca-sim: error: ")
    for fragment in fragments:
        assert fragment in line
    return line


def _lca_sim_command() -> list[str]:
    """The installed console script next to this interpreter, else `python -m lca_sim.cli.sim`."""
    script = Path(sys.executable).parent / "lca-sim"
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-m", "lca_sim.cli.sim"]


# --- a good run -----------------------------------------------------------------------------


class GoodRun(NamedTuple):
    """One successful `lca-sim run --no-plot` of the short scenario."""

    outcome: Outcome
    out_dir: Path
    scenario: Path


@pytest.fixture(scope="module")
def good_run(tmp_path_factory: pytest.TempPathFactory) -> GoodRun:
    """Run the short scenario once in-process (no plot) for the tests that read its output."""
    root = tmp_path_factory.mktemp("good_run")
    scenario = _write(root / "short.yaml", _short_scenario())
    out_dir = root / "out"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(["run", "--scenario", str(scenario), "--out", str(out_dir), "--no-plot"])
    return GoodRun(Outcome(code, stdout.getvalue(), stderr.getvalue()), out_dir, scenario)


def test_good_run_exits_0_and_writes_only_result_csv(good_run: GoodRun) -> None:
    """A good --no-plot run exits 0, prints nothing on stderr and leaves only result.csv."""
    assert good_run.outcome.code == 0
    assert good_run.outcome.err == ""
    assert sorted(p.name for p in good_run.out_dir.iterdir()) == ["result.csv"]


def test_good_run_csv_header(good_run: GoodRun) -> None:
    """The header is t_s, then the twelve columns of each axis in model order."""
    header, _ = _read_csv(good_run.out_dir / "result.csv")
    assert len(EXPECTED_HEADER) == 1 + 4 * 12
    assert header == EXPECTED_HEADER


def test_good_run_csv_rows(good_run: GoodRun) -> None:
    """There is one row per record period, both ends included, at the record times."""
    _, rows = _read_csv(good_run.out_dir / "result.csv")
    n_rows = round(SHORT_DURATION_S / SHORT_RECORD_S) + 1
    assert len(rows) == n_rows == 51
    times = [float(row["t_s"]) for row in rows]
    assert times == pytest.approx([k * SHORT_RECORD_S for k in range(n_rows)], abs=1e-12)
    assert float(rows[0]["pivot_voltage_v"]) == 0.0
    assert float(rows[-1]["pivot_voltage_v"]) == 8.0
    assert float(rows[-1]["pivot_position"]) > 0.0
    assert {float(row["l_arm_position"]) for row in rows} == {0.0}


def test_good_run_state_columns_are_names(good_run: GoodRun) -> None:
    """Motion and drive states are written as readable names, not numbers."""
    _, rows = _read_csv(good_run.out_dir / "result.csv")
    pivot_motion = [row["pivot_motion_state"] for row in rows]
    pivot_drive = [row["pivot_drive_state"] for row in rows]
    assert pivot_motion[0] == "stop"
    assert pivot_motion[-1] == "direct"
    assert set(pivot_motion) == {"stop", "direct"}
    assert pivot_drive[0] == "stop_hold"
    assert pivot_drive[-1] == "motor_driving"
    assert "stop_motor_direct" in pivot_drive
    for axis in ("l_arm", "c_arc", "lift"):
        assert {row[f"{axis}_motion_state"] for row in rows} == {"stop"}
        assert {row[f"{axis}_drive_state"] for row in rows} == {"stop_hold"}
    driving = [row for row in rows if row["pivot_drive_state"] == "motor_driving"]
    assert {(row["pivot_eta_m"], row["pivot_eta_l"]) for row in driving} == {("0.9", "1.0")}


def test_good_run_prints_the_pivot_phases(good_run: GoodRun) -> None:
    """Stdout names the run, lists the pivot's phases in order and where the CSV was written."""
    lines = good_run.outcome.out.splitlines()
    assert lines[0] == (
        "lca-sim: robot lca_default, scenario short.yaml: 0.5 s at dt 0.0001 s (5000 steps)"
    )
    assert lines[1].startswith("simulated 0.5 s in ")
    assert lines[2] == "pivot phases:"
    phase_states = [line.split()[2] for line in lines[3:6]]
    assert phase_states == ["stop_hold", "stop_motor_direct", "motor_driving"]
    assert lines[3].split()[:2] == ["0.0000", "s"]
    assert lines[-1] == f"wrote {good_run.out_dir / 'result.csv'}"
    assert not any(line.endswith("phases:") and line != "pivot phases:" for line in lines)


def test_plot_run_writes_a_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Without --no-plot the run also writes result.png, a real PNG file."""
    scenario = _write(tmp_path / "short.yaml", _short_scenario(duration_s=0.2))
    out_dir = tmp_path / "out"
    outcome = _run(["run", "--scenario", str(scenario), "--out", str(out_dir)], capsys)
    assert outcome.code == 0
    png = out_dir / "result.png"
    data = png.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    assert len(data) > 10_000
    assert sorted(p.name for p in out_dir.iterdir()) == ["result.csv", "result.png"]
    assert outcome.out.splitlines()[-2:] == [
        f"wrote {out_dir / 'result.csv'}",
        f"wrote {png}",
    ]


# --- bad input ------------------------------------------------------------------------------

Case = Callable[[Path], tuple[list[str], list[str]]]


def _robot_missing(tmp: Path) -> tuple[list[str], list[str]]:
    path = tmp / "nope.yaml"
    return ["--robot", str(path)], [str(path), "file not found"]


def _robot_bad_value(tmp: Path) -> tuple[list[str], list[str]]:
    doc = _robot_doc()
    doc["axes"][1]["motor"]["resistance_ohm"] = -1.0
    path = _write(tmp / "robot.yaml", doc)
    return ["--robot", str(path)], [
        f"{path}: axes[1].motor.resistance_ohm: expected a number > 0, got -1"
    ]


def _robot_unknown_key(tmp: Path) -> tuple[list[str], list[str]]:
    doc = _robot_doc()
    doc["axes"][0]["colour"] = "red"
    path = _write(tmp / "robot.yaml", doc)
    return ["--robot", str(path)], [f"{path}: axes[0].colour: unknown key"]


def _robot_bad_base(tmp: Path) -> tuple[list[str], list[str]]:
    path = _write(tmp / "robot.yaml", {"base": "nope"})
    return ["--robot", str(path)], [f"{path}: base: ", "valid: default, reversible"]


def _scenario_bad_dt(tmp: Path) -> tuple[list[str], list[str]]:
    doc = _short_scenario()
    doc["dt_s"] = 0.02
    path = _write(tmp / "bad.yaml", doc)
    return ["--scenario", str(path)], [f"{path}: dt_s: expected a number <= 0.01, got 0.02"]


def _scenario_unknown_axis(tmp: Path) -> tuple[list[str], list[str]]:
    doc = _short_scenario()
    doc["inputs"]["tilt"] = {"time_s": [0.0], "voltage_v": [1.0]}
    path = _write(tmp / "bad.yaml", doc)
    return ["--scenario", str(path)], [f"{path}: inputs.tilt: expected an axis name"]


def _scenario_missing(tmp: Path) -> tuple[list[str], list[str]]:
    path = tmp / "nope.yaml"
    return ["--scenario", str(path)], [str(path), "file not found"]


def _scenario_syntax(tmp: Path) -> tuple[list[str], list[str]]:
    path = tmp / "bad.yaml"
    path.write_text("duration_s: 0.5\ndt_s: 1.0e-4: 2\n", encoding="utf-8")
    return ["--scenario", str(path)], [f"{path}: line 2: expected valid YAML"]


@pytest.mark.parametrize(
    "case",
    [
        pytest.param(_robot_missing, id="robot-path-missing"),
        pytest.param(_robot_bad_value, id="robot-bad-value"),
        pytest.param(_robot_unknown_key, id="robot-unknown-key"),
        pytest.param(_robot_bad_base, id="robot-bad-base"),
        pytest.param(_scenario_bad_dt, id="scenario-bad-dt"),
        pytest.param(_scenario_unknown_axis, id="scenario-unknown-axis"),
        pytest.param(_scenario_missing, id="scenario-path-missing"),
        pytest.param(_scenario_syntax, id="scenario-yaml-syntax"),
    ],
)
def test_bad_input_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: Case
) -> None:
    """Bad config or scenario: exit 2, one `lca-sim: error:` line, no traceback, no --out."""
    extra, fragments = case(tmp_path)
    if "--scenario" not in extra:
        extra += ["--scenario", str(_write(tmp_path / "short.yaml", _short_scenario()))]
    out_dir = tmp_path / "out"
    outcome = _run(["run", *extra, "--out", str(out_dir), "--no-plot"], capsys)
    _assert_one_error_line(outcome, *fragments)
    assert outcome.out == ""
    assert not out_dir.exists()


def test_unknown_shipped_scenario_lists_valid_names(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An unknown shipped scenario name is one error line listing the shipped scenarios."""
    out_dir = tmp_path / "out"
    outcome = _run(["run", "--scenario", "no_such", "--out", str(out_dir)], capsys)
    line = _assert_one_error_line(outcome)
    assert line == (
        "lca-sim: error: unknown scenario 'no_such'; "
        "valid: fig9_open_loop_pivot, hold_pivot, identify_pivot"
    )
    assert not out_dir.exists()


def test_unknown_shipped_robot_lists_valid_names(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An unknown shipped robot name is one error line listing the shipped robots."""
    out_dir = tmp_path / "out"
    args = ["run", "--robot", "no_such", "--scenario", "hold_pivot", "--out", str(out_dir)]
    line = _assert_one_error_line(_run(args, capsys))
    assert line == "lca-sim: error: unknown robot 'no_such'; valid: default, reversible"
    assert not out_dir.exists()


def test_missing_scenario_argument_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Forgetting --scenario is an argparse usage error with exit code 2."""
    with pytest.raises(SystemExit) as info:
        main(["run", "--out", str(tmp_path / "out")])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (
        "lca-sim run: error: the following arguments are required: --scenario"
    )
    assert "Traceback" not in err


# --- atomic output ------------------------------------------------------------------------


def test_existing_result_is_replaced_atomically_on_success(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A good run renames a new result.csv over the old one (new inode), leaving no .part."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    old = out_dir / "result.csv"
    old.write_bytes(b"old,result\n1,2\n")
    old_inode = old.stat().st_ino
    scenario = _write(tmp_path / "short.yaml", _short_scenario(duration_s=0.1))
    args = ["run", "--scenario", str(scenario), "--out", str(out_dir), "--no-plot"]
    assert _run(args, capsys).code == 0
    assert old.stat().st_ino != old_inode
    header, rows = _read_csv(old)
    assert header == EXPECTED_HEADER
    assert len(rows) == 11
    assert sorted(p.name for p in out_dir.iterdir()) == ["result.csv"]


def test_existing_result_is_untouched_on_failure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A failing run (bad scenario) leaves an existing out folder byte for byte as it was."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    (out_dir / "result.csv").write_bytes(b"old,result\n1,2\n")
    (out_dir / "result.png").write_bytes(PNG_SIGNATURE + b"old")
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out_dir.iterdir()}
    extra, fragments = _scenario_bad_dt(tmp_path)
    outcome = _run(["run", *extra, "--out", str(out_dir)], capsys)
    _assert_one_error_line(outcome, *fragments)
    after = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out_dir.iterdir()}
    assert after == before


# --- the real console script ----------------------------------------------------------------


def test_console_script_good_run(tmp_path: Path) -> None:
    """The installed `lca-sim` script runs a short scenario and exits 0."""
    scenario = _write(tmp_path / "short.yaml", _short_scenario(duration_s=0.2))
    out_dir = tmp_path / "out"
    args = ["run", "--scenario", str(scenario), "--out", str(out_dir), "--no-plot"]
    proc = subprocess.run(
        [*_lca_sim_command(), *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "pivot phases:" in proc.stdout
    header, rows = _read_csv(out_dir / "result.csv")
    assert header == EXPECTED_HEADER
    assert len(rows) == 21


def test_console_script_bad_key(tmp_path: Path) -> None:
    """The installed script exits 2 with one stderr line naming file and key, and no --out."""
    doc = _robot_doc()
    doc["state_machine"]["states"][0]["motor"] = "pushes"
    robot = _write(tmp_path / "robot.yaml", doc)
    out_dir = tmp_path / "out"
    args = ["run", "--robot", str(robot), "--scenario", "hold_pivot", "--out", str(out_dir)]
    proc = subprocess.run(
        [*_lca_sim_command(), *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    line = _assert_one_error_line(Outcome(proc.returncode, proc.stdout, proc.stderr))
    assert line == (
        f"lca-sim: error: {robot}: state_machine.states[0].motor: "
        "expected one of any, drives, brakes, got 'pushes'"
    )
    assert proc.stdout == ""
    assert not out_dir.exists()


# --- bugs found by these tests, now fixed ---------------------------------------------------


def test_initial_position_outside_limits_names_file_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An initial position beyond the end stops names the scenario file and the key."""
    doc = _short_scenario()
    doc["initial"] = {"position": {"pivot": 10.0}}
    scenario = _write(tmp_path / "far.yaml", doc)
    out_dir = tmp_path / "out"
    outcome = _run(["run", "--scenario", str(scenario), "--out", str(out_dir)], capsys)
    assert not out_dir.exists()
    _assert_one_error_line(outcome, str(scenario), "initial.position.pivot")


def test_out_that_is_a_file_is_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--out naming an existing file exits 2 with one error line and leaves the file alone."""
    scenario = _write(tmp_path / "short.yaml", _short_scenario(duration_s=0.1))
    target = tmp_path / "taken"
    target.write_bytes(b"keep me")
    outcome = _run(["run", "--scenario", str(scenario), "--out", str(target)], capsys)
    assert target.read_bytes() == b"keep me"
    _assert_one_error_line(outcome, str(target))


def test_invalid_urdf_gives_one_stderr_line(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """A robot whose URDF is not valid XML gives exactly one stderr line (fd level)."""
    (tmp_path / "gantry.urdf").write_text("<robot name='x'><link name='a'/>", encoding="utf-8")
    doc = _robot_doc()
    doc["robot"]["urdf"] = str(tmp_path / "gantry.urdf")
    robot = _write(tmp_path / "robot.yaml", doc)
    out_dir = tmp_path / "out"
    capfd.readouterr()
    code = main(["run", "--robot", str(robot), "--scenario", "hold_pivot", "--out", str(out_dir)])
    captured = capfd.readouterr()
    assert not out_dir.exists()
    assert code == 2
    assert f"{robot}: robot.urdf: expected a valid URDF" in captured.err
    _assert_one_error_line(Outcome(code, captured.out, captured.err))


def test_no_plot_removes_a_stale_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """With --no-plot an old result.png (of another run) does not survive next to the new CSV."""
    scenario = _write(tmp_path / "short.yaml", _short_scenario(duration_s=0.05))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    (out_dir / "result.png").write_bytes(PNG_SIGNATURE + b"old")
    outcome = _run(["run", "--scenario", str(scenario), "--out", str(out_dir), "--no-plot"], capsys)
    assert outcome.code == 0
    assert sorted(p.name for p in out_dir.iterdir()) == ["result.csv"]
