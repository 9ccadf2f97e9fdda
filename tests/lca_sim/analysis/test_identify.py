"""Efficiency identification (`lca_sim.analysis.identify`, `lca-hil identify`): Table 1 comes back.

The excitation of config/scenarios/identify_pivot.yaml is simulated once per robot; the
identification must return the efficiencies the simulator ran with, without and with realistic
measurement noise, report what it could not identify, and the CLI must turn a result.csv or a
bag into a robot config that `load_robot` accepts.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from lca_control.contract import JOINT_STATE_TYPE, JOINT_STATES, MOTOR_STATES
from lca_sim.analysis.identify import identify
from lca_sim.analysis.identify_samples import classify_samples
from lca_sim.analysis.identify_types import (
    EstimateStatus,
    FloatArray,
    IdentificationError,
    IdentificationResult,
    IdentifyOptions,
    MotionRecord,
)
from lca_sim.cli.identify import main, write_outputs
from lca_sim.cli.results import csv_header, write_csv
from lca_sim.config.loader import load_robot
from lca_sim.config.paths import config_dir
from lca_sim.model import kernel
from lca_sim.model.params import AXIS_NAMES, RobotParams
from lca_sim.model.scenario import ScenarioResult, parse_scenario, run_scenario
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator
from lca_sim.model.state_machine import FIRST_MOVING_STATE, Efficiency, MotionState

CONFIG = config_dir()
DEFAULT_YAML = CONFIG / "robots" / "default.yaml"
SCENARIO = CONFIG / "scenarios" / "identify_pivot.yaml"
AXIS = "pivot"
STATES = (
    "motor_driving",
    "motor_and_load_driving_load_dominant",
    "motor_and_load_driving_motor_dominant",
    "load_driving",
    "coasting",
)
DIRECTIONS = (MotionState.DIRECT, MotionState.REVERSE)
JOINT_STATE = JOINT_STATE_TYPE

NOISE_FREE_TOLERANCE = 0.02
NOISY_TOLERANCE = 0.05
# Widest 95 % interval (high - low, absolute) accepted. Noise-free, only the numerical residue
# widens it: 0.00003-0.0004 measured. With the noise below: up to 0.0092 at NOISE_SEED and 0.0113
# over 13 seeds; wider would make the "error within the interval" check say little.
NOISE_FREE_CI_WIDTH = 0.002
NOISY_CI_WIDTH = 0.025
# Measurement noise of the noisy case: white current noise of 50 mA (0.6 % of the excitation's
# 8.3 A peak, 1-5 % of its usual 1-5 A), and a 4096-count-per-revolution encoder on the motor
# shaft: the position is quantised to its counts and the velocity is the backward difference of
# that position over the 1 ms sample period (steps of 1.5 rad/s at the motor, half a sample
# late). Over 30 seeds the worst state, reverse motor-dominant (eta_l = 0.06), errs by 1.05 % rms
# and 3.2 % at most; at 80 mA by 1.7 % rms and 4.8 % at most.
CURRENT_NOISE_A = 0.05
ENCODER_COUNTS_PER_REV = 4096
NOISE_SEED = 20240607

# An efficiency table other than Table 1 (eq. 11's convention: the emitter's coefficient < 1).
OTHER_TABLE: dict[str, dict[str, dict[str, float]]] = {
    "motor_driving": {
        "direct": {"eta_m": 0.8, "eta_l": 1.0},
        "reverse": {"eta_m": 0.85, "eta_l": 1.0},
    },
    "motor_and_load_driving_load_dominant": {
        "direct": {"eta_m": 1.0, "eta_l": 0.7},
        "reverse": {"eta_m": 1.0, "eta_l": 0.3},
    },
    "motor_and_load_driving_motor_dominant": {
        "direct": {"eta_m": 1.0, "eta_l": 0.6},
        "reverse": {"eta_m": 1.0, "eta_l": 0.2},
    },
    "load_driving": {
        "direct": {"eta_m": 1.0, "eta_l": 0.75},
        "reverse": {"eta_m": 1.0, "eta_l": 0.35},
    },
}

# The first 4.6 s of the excitation: direct motion only (motor_driving, then coasting).
ONE_DIRECTION: dict[str, Any] = {
    "duration_s": 4.6,
    "dt_s": 1.0e-4,
    "record_period_s": 0.001,
    "initial": {"position": {"pivot": -0.35}},
    "inputs": {
        "pivot": {
            "time_s": [0.0, 0.2, 0.7, 3.7, 3.7, 4.2],
            "voltage_v": [0.0, 0.0, 30.0, 30.0, 28.0, 0.0],
        }
    },
}


# --- shared runs ------------------------------------------------------------------------------


def _simulate(robot: RobotParams, doc: object, source: str) -> ScenarioResult:
    """Run a scenario document on a robot."""
    scenario = parse_scenario(doc, source, robot.axis_names)
    return run_scenario(Simulator(robot, dt_s=scenario.dt_s), scenario)


def _record(run: ScenarioResult) -> MotionRecord:
    """The noise-free measurements of a run: positions, velocities, the pivot's current."""
    return MotionRecord(run.time_s, run.position, run.velocity, run.signal("current_a", AXIS))


def _single_axis(
    time_s: FloatArray,
    position: FloatArray,
    velocity: FloatArray,
    current_a: FloatArray,
    axis_index: int,
    fixed_position: FloatArray,
) -> MotionRecord:
    """A record of one moving axis, the others held at `fixed_position` (velocity 0)."""
    pose = np.tile(np.asarray(fixed_position, dtype=np.float64), (len(time_s), 1))
    pose[:, axis_index] = position
    rate = np.zeros_like(pose)
    rate[:, axis_index] = velocity
    return MotionRecord(np.asarray(time_s, dtype=np.float64), pose, rate, np.asarray(current_a))


def _noisy_record(run: ScenarioResult, robot: RobotParams, seed: int) -> MotionRecord:
    """The run as a drive would measure it (see CURRENT_NOISE_A, ENCODER_COUNTS_PER_REV)."""
    rng = np.random.default_rng(seed)
    a = robot.axis_names.index(AXIS)
    ratio = robot.axes[a].gear_ratio
    count_rad = 2.0 * math.pi / ENCODER_COUNTS_PER_REV / ratio  # one count, joint side
    offset = rng.uniform()  # where the encoder's zero falls between two counts
    position = run.position.copy()
    velocity = run.velocity.copy()
    counts = np.floor(run.position[:, a] / count_rad + offset)
    position[:, a] = counts * count_rad
    velocity[1:, a] = np.diff(position[:, a]) / np.diff(run.time_s)
    velocity[0, a] = 0.0
    current = run.signal("current_a", AXIS) + rng.normal(0.0, CURRENT_NOISE_A, len(run.time_s))
    return MotionRecord(run.time_s, position, velocity, current)


@pytest.fixture(scope="module")
def excitation_doc() -> object:
    """The shipped excitation scenario, as parsed YAML."""
    return yaml.safe_load(SCENARIO.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def excitation_run(default_robot: RobotParams, excitation_doc: object) -> ScenarioResult:
    """The excitation simulated on the default robot (Table 1)."""
    return _simulate(default_robot, excitation_doc, str(SCENARIO))


@pytest.fixture(scope="module")
def table1_result(
    default_robot: RobotParams, excitation_run: ScenarioResult
) -> IdentificationResult:
    """The identification of the noise-free excitation on the default robot."""
    return identify(default_robot, AXIS, _record(excitation_run))


@pytest.fixture(scope="module")
def other_robot(tmp_path_factory: pytest.TempPathFactory) -> RobotParams:
    """The default robot with OTHER_TABLE, written as a `base:` override in a temporary file."""
    path = tmp_path_factory.mktemp("other") / "other.yaml"
    doc = {"base": str(DEFAULT_YAML), "robot": {"name": "other"}, "efficiency": OTHER_TABLE}
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return load_robot(str(path))


@pytest.fixture(scope="module")
def one_direction_run(default_robot: RobotParams) -> ScenarioResult:
    """A run that only moves in the direct direction."""
    return _simulate(default_robot, ONE_DIRECTION, "one_direction")


def _relative_error(result: IdentificationResult, robot: RobotParams) -> dict[str, float]:
    """Relative error of every identified coefficient against the robot's own table."""
    table = robot.axes[robot.axis_names.index(AXIS)].efficiency
    errors = {}
    for e in result.estimates:
        if e.status is EstimateStatus.IDENTIFIED:
            assert e.coefficient is not None
            truth = getattr(table[(e.direction, e.state)], e.coefficient)
            errors[f"{e.state} {e.direction.name.lower()}"] = e.estimate / truth - 1.0
    return errors


# --- the excitation scenario ------------------------------------------------------------------


@pytest.mark.slow
def test_excitation_visits_every_moving_state(
    table1_result: IdentificationResult, excitation_run: ScenarioResult
) -> None:
    """identify_pivot takes the pivot through all 10 moving states, inside its end stops."""
    for state in STATES:
        for direction in DIRECTIONS:
            e = table1_result.estimate(state, direction)
            assert e.n_samples >= 400, (state, direction, e.n_samples)
            expected = EstimateStatus.FIXED if state == "coasting" else EstimateStatus.IDENTIFIED
            assert e.status is expected, (state, direction)
    q = excitation_run.position[:, 1]
    assert q.min() > -0.36 and q.max() < 1.75  # end stops at +-2 rad, never touched
    assert np.abs(excitation_run.signal("current_a", AXIS)).max() < 9.0


@pytest.mark.slow
def test_classification_matches_the_simulator(
    table1_result: IdentificationResult, excitation_run: ScenarioResult
) -> None:
    """Every sample used is in the state and direction the simulator was in (no recorded eta)."""
    used = table1_result.used
    simulated_state = excitation_run.drive[:, 1] - FIRST_MOVING_STATE
    assert used.sum() > 15_000
    assert np.array_equal(table1_result.state_index[used], simulated_state[used])
    assert np.array_equal(table1_result.direction[used], excitation_run.motion[used, 1])


# --- recovery ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_recovers_table1_without_noise(
    table1_result: IdentificationResult, default_robot: RobotParams
) -> None:
    """Table 1 comes back within 2 % in every state, with the emitter's coefficient free."""
    errors = _relative_error(table1_result, default_robot)
    assert len(errors) == 8
    assert max(abs(x) for x in errors.values()) < NOISE_FREE_TOLERANCE, errors
    for e in table1_result.estimates:
        if e.state == "motor_driving":
            assert e.coefficient == "eta_m" and e.identified.eta_l == 1.0
        elif e.state == "coasting":
            assert e.coefficient is None and e.identified == Efficiency(1.0, 1.0)
            # Eq. (10) with both coefficients 1 holds there: a small mean residual.
            assert abs(e.residual_mean_nm) < 1e-3
        else:
            assert e.coefficient == "eta_l" and e.identified.eta_m == 1.0


@pytest.mark.slow
def test_recovers_table1_with_noise(
    excitation_run: ScenarioResult, default_robot: RobotParams
) -> None:
    """With current noise and a quantised encoder: within 5 %, inside twice the 95 % CI."""
    record = _noisy_record(excitation_run, default_robot, NOISE_SEED)
    result = identify(default_robot, AXIS, record)
    assert result.current_noise_a == pytest.approx(CURRENT_NOISE_A, rel=0.1)
    errors = _relative_error(result, default_robot)
    assert len(errors) == 8
    assert max(abs(x) for x in errors.values()) < NOISY_TOLERANCE, errors
    table = default_robot.axes[1].efficiency
    for e in result.estimates:
        if e.status is EstimateStatus.IDENTIFIED:
            assert e.coefficient is not None
            truth = getattr(table[(e.direction, e.state)], e.coefficient)
            half_width = (e.ci_high - e.ci_low) / 2.0
            assert 0.0 < 2.0 * half_width < NOISY_CI_WIDTH, (e.state, e.direction, half_width)
            # An honest interval: the error is not many times what it claims.
            assert abs(e.estimate - truth) < 2.0 * half_width, (e.state, e.direction)


@pytest.mark.slow
def test_recovers_another_table(other_robot: RobotParams, excitation_doc: object) -> None:
    """A table other than Table 1, given as a `base:` override, comes back within 2 %."""
    assert other_robot.axes[1].efficiency[(MotionState.DIRECT, "motor_driving")].eta_m == 0.8
    run = _simulate(other_robot, excitation_doc, str(SCENARIO))
    result = identify(other_robot, AXIS, _record(run))
    errors = _relative_error(result, other_robot)
    assert len(errors) == 8
    assert max(abs(x) for x in errors.values()) < NOISE_FREE_TOLERANCE, errors
    for state, directions in OTHER_TABLE.items():
        for name, values in directions.items():
            e = result.estimate(state, MotionState[name.upper()])
            assert e.identified.eta_m == pytest.approx(values["eta_m"], rel=NOISE_FREE_TOLERANCE)
            assert e.identified.eta_l == pytest.approx(values["eta_l"], rel=NOISE_FREE_TOLERANCE)


@pytest.mark.slow
def test_irregular_stamps_are_resampled(
    table1_result: IdentificationResult,
    excitation_run: ScenarioResult,
    default_robot: RobotParams,
) -> None:
    """Dropping a random third of the samples (1-4 ms stamps) still gives Table 1 within 2 %."""
    keep = np.random.default_rng(7).uniform(size=len(excitation_run.time_s)) > 0.33
    keep[[0, -1]] = True
    full = _record(excitation_run)
    record = MotionRecord(
        full.time_s[keep], full.position[keep], full.velocity[keep], full.current_a[keep]
    )
    result = identify(default_robot, AXIS, record)
    assert result.sample_period_s == pytest.approx(0.001)
    errors = _relative_error(result, default_robot)
    assert len(errors) == len(_relative_error(table1_result, default_robot))
    assert max(abs(x) for x in errors.values()) < NOISE_FREE_TOLERANCE, errors


# --- what cannot be identified ----------------------------------------------------------------


def test_unvisited_states_are_reported(
    one_direction_run: ScenarioResult, default_robot: RobotParams
) -> None:
    """A direct-only run identifies motor_driving and flags every reverse state as not visited."""
    result = identify(default_robot, AXIS, _record(one_direction_run))
    assert result.estimate("motor_driving", MotionState.DIRECT).status is (
        EstimateStatus.IDENTIFIED
    )
    assert result.estimate("coasting", MotionState.DIRECT).status is EstimateStatus.FIXED
    not_identified = {(e.state, e.direction) for e in result.not_identified}
    for state in STATES:
        e = result.estimate(state, MotionState.REVERSE)
        assert e.status is EstimateStatus.NOT_VISITED and e.n_samples == 0
        assert (state, MotionState.REVERSE) in not_identified
        # The identified table keeps the prior value there.
        assert e.identified == e.prior
    for state in STATES[1:4]:  # the load never drives direct motion below 55 deg
        e = result.estimate(state, MotionState.DIRECT)
        assert e.status is EstimateStatus.NOT_VISITED
        assert math.isnan(e.estimate) and math.isnan(e.ci_low)


@pytest.mark.slow
def test_too_few_samples_keep_the_prior(
    excitation_run: ScenarioResult, default_robot: RobotParams
) -> None:
    """Below min_samples a visited state is flagged, not estimated, and keeps its prior."""
    record = _record(excitation_run)
    result = identify(default_robot, AXIS, record, IdentifyOptions(min_samples=2000))
    statuses = {(e.state, e.direction): e for e in result.estimates}
    few = statuses[("motor_and_load_driving_load_dominant", MotionState.DIRECT)]
    assert few.status is EstimateStatus.TOO_FEW_SAMPLES and 0 < few.n_samples < 2000
    assert few.identified == few.prior
    many = statuses[("motor_driving", MotionState.DIRECT)]
    assert many.status is EstimateStatus.IDENTIFIED and many.n_samples >= 2000


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"current_a": np.zeros(5)}, "current_a: expected shape"),
        ({"time_s": np.array([0.0, 0.001, 0.001, 0.003, 0.004, 0.005] * 10)}, "increasing"),
        ({"velocity": np.full((60, 4), np.nan)}, "velocity: expected finite"),
        ({"position": np.zeros((60, 3))}, "position: expected shape"),
    ],
)
def test_bad_arrays_are_rejected(
    default_robot: RobotParams, change: dict[str, Any], message: str
) -> None:
    """Inconsistent, non-finite or non-increasing samples raise one clear error."""
    n = 60
    fields: dict[str, Any] = {
        "time_s": np.arange(n) * 1e-3,
        "position": np.zeros((n, 4)),
        "velocity": np.zeros((n, 4)),
        "current_a": np.zeros(n),
    }
    fields.update(change)
    with pytest.raises(IdentificationError, match=message):
        identify(default_robot, AXIS, MotionRecord(**fields))


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (IdentifyOptions(window_s=0.0), "window_s: expected > 0"),
        (IdentifyOptions(confidence=1.0), "confidence: expected in \\(0, 1\\)"),
        (IdentifyOptions(min_samples=0), "min_samples: expected >= 1"),
    ],
)
def test_bad_options_are_rejected(
    default_robot: RobotParams, options: IdentifyOptions, message: str
) -> None:
    """Options the procedure cannot run with are one clear error."""
    n = 60
    record = _single_axis(
        np.arange(n, dtype=np.float64) * 1e-3, np.zeros(n), np.zeros(n), np.zeros(n), 1, np.zeros(4)
    )
    with pytest.raises(IdentificationError, match=message):
        identify(default_robot, AXIS, record, options)


def test_too_short_record_is_rejected(default_robot: RobotParams) -> None:
    """A record shorter than the differentiator's window says how many samples it needs."""
    n = 10
    record = _single_axis(
        np.arange(n, dtype=np.float64) * 1e-3, np.zeros(n), np.zeros(n), np.zeros(n), 1, np.zeros(4)
    )
    with pytest.raises(IdentificationError, match="expected at least 31 samples"):
        identify(default_robot, AXIS, record)


# --- classification ---------------------------------------------------------------------------


def _kernel_model(robot: RobotParams) -> Any:
    """A packed kernel model carrying only the robot's rule table."""
    machine = robot.state_machine
    n_rules = len(machine.rules)
    return kernel.pack_model(
        np.zeros((kernel.N_PARAMS, 1)),
        machine.rule_codes(),
        np.ones((1, 2, n_rules, 2)),
        machine.irreversible_stop,
    )


torques = st.floats(min_value=-2.0, max_value=2.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    samples=st.lists(st.tuples(st.sampled_from([1, -1]), torques, torques), min_size=1, max_size=20)
)
def test_classification_is_the_kernels(
    default_robot: RobotParams, samples: list[tuple[int, float, float]]
) -> None:
    """Without a noise margin the samples get exactly the kernel's moving state."""
    robot = default_robot
    model = _kernel_model(robot)
    direction = np.array([s[0] for s in samples], dtype=np.int64)
    tau_m = np.array([s[1] for s in samples])
    tau_l = np.array([s[2] for s in samples])
    states = classify_samples(robot.state_machine.rules, direction, tau_m, tau_l, 0.0)
    expected = [kernel.classify(int(d), m, lo, model) for d, m, lo in samples]
    assert states.tolist() == expected


@pytest.mark.parametrize(
    ("direction", "tau_m", "tau_l", "ambiguous"),
    [
        (1, 1e-4, 0.3, True),  # motor_driving or coasting: tau_m within the margin of 0
        (1, 0.5, 1e-4, True),  # motor_driving or motor-dominant: tau_l within the margin
        (-1, -0.3001, 0.3, True),  # motor- or load-dominant: |tau_m| ~ |tau_l|
        (1, 0.5, 0.3, False),  # plainly motor_driving
        (-1, -0.05, 0.3, False),  # plainly load-dominant
    ],
)
def test_samples_near_a_boundary_are_ambiguous(
    default_robot: RobotParams, direction: int, tau_m: float, tau_l: float, ambiguous: bool
) -> None:
    """A condition within the noise margin of its boundary makes the sample ambiguous (-2)."""
    state = classify_samples(
        default_robot.state_machine.rules,
        np.array([direction], dtype=np.int64),
        np.array([tau_m]),
        np.array([tau_l]),
        1e-3,
    )
    assert (int(state[0]) == -2) is ambiguous


# --- the CLI ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_cli_on_a_result_csv(
    excitation_run: ScenarioResult,
    default_robot: RobotParams,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """result.csv -> table on stdout, identified.yaml that loads with Table 1, and the JSON."""
    csv_path = tmp_path / "run" / "result.csv"
    csv_path.parent.mkdir()
    write_csv(excitation_run, csv_path)
    assert main(["identify", str(csv_path)]) == 0  # --out defaults to the CSV's folder
    stdout = capsys.readouterr().out
    rows = [line.split() for line in stdout.splitlines()]
    row = next(r for r in rows if r[:2] == ["motor_and_load_driving_motor_dominant", "reverse"])
    assert row[2] == "eta_l" and float(row[3]) == pytest.approx(0.06, rel=NOISE_FREE_TOLERANCE)
    assert "every state with an emitter coefficient was identified" in stdout

    yaml_path = csv_path.parent / "identified.yaml"
    text = yaml_path.read_text(encoding="utf-8")
    assert f'base: "{DEFAULT_YAML}"' in text
    identified = load_robot(str(yaml_path))
    prior = default_robot.axes[1].efficiency
    for key, value in identified.axes[1].efficiency.items():
        assert value.eta_m == pytest.approx(prior[key].eta_m, rel=NOISE_FREE_TOLERANCE), key
        assert value.eta_l == pytest.approx(prior[key].eta_l, rel=NOISE_FREE_TOLERANCE), key
    assert identified.axes[1].friction == default_robot.axes[1].friction  # the rest from base

    doc = json.loads((csv_path.parent / "identification.json").read_text(encoding="utf-8"))
    assert doc["axis"] == AXIS and doc["robot_file"] == str(DEFAULT_YAML)
    assert len(doc["estimates"]) == 10
    assert {(x["state"], x["status"]) for x in doc["not_identified"]} == {("coasting", "fixed")}
    for entry in doc["estimates"]:
        if entry["status"] == "identified":
            assert 0.0 < entry["ci_high"] - entry["ci_low"] < NOISE_FREE_CI_WIDTH, entry
            assert entry["n_samples"] >= 400


def test_cli_flags_unvisited_states(
    one_direction_run: ScenarioResult, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The report and identified.yaml say which states kept their prior, and why."""
    csv_path = tmp_path / "result.csv"
    write_csv(one_direction_run, csv_path)
    out = tmp_path / "ident"
    assert main(["identify", str(csv_path), "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "not identified, prior value kept in identified.yaml:" in stdout
    assert "  load_driving reverse: not visited" in stdout
    text = (out / "identified.yaml").read_text(encoding="utf-8")
    assert text.count("prior kept: not visited") == 8
    robot = load_robot(str(out / "identified.yaml"))
    eff = robot.axes[1].efficiency
    assert eff[(MotionState.REVERSE, "motor_and_load_driving_motor_dominant")].eta_l == 0.06
    assert eff[(MotionState.DIRECT, "motor_driving")].eta_m == pytest.approx(0.9, rel=0.02)


def _write_rows(path: Path, rows: list[list[str]]) -> Path:
    path.write_text("\n".join(",".join(r) for r in rows) + "\n", encoding="utf-8")
    return path


def _write_empty(path: Path) -> Path:
    path.write_bytes(b"")
    return path


def _bad_inputs(tmp: Path) -> dict[str, tuple[Path, str]]:
    """Bad INPUTs and a fragment of the error line each must give."""
    header = csv_header(AXIS_NAMES)
    good = ["0.0"] * len(header)
    bad_cell = list(good)
    bad_cell[header.index("pivot_current_a")] = "abc"
    (tmp / "folder").mkdir()
    (tmp / "binary.csv").write_bytes(b"\xff\xfe\x00garbage")
    return {
        "missing column": (_write_rows(tmp / "a.csv", [["t", "x"], ["1", "2"]]), "missing column"),
        "not a number": (
            _write_rows(tmp / "b.csv", [header, good, bad_cell]),
            "line 3, column pivot_current_a: expected a number, got 'abc'",
        ),
        "too short": (_write_rows(tmp / "c.csv", [header, good]), "expected at least 3 samples"),
        "blank line": (_write_rows(tmp / "d.csv", []), "missing column"),
        "empty": (_write_empty(tmp / "e.csv"), "empty file, expected a result.csv header"),
        "no such file": (tmp / "nope.csv", "file not found (nor a folder)"),
        "not a bag": (tmp / "folder", "not a rosbag2 bag (no metadata.yaml)"),
        "binary": (tmp / "binary.csv", "expected UTF-8 text"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "missing column",
        "not a number",
        "too short",
        "blank line",
        "empty",
        "no such file",
        "not a bag",
        "binary",
    ],
)
def test_cli_bad_input_is_one_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bad INPUT exits 2 with one error line naming the file, and writes nothing."""
    path, fragment = _bad_inputs(tmp_path)[case]
    out = tmp_path / "out"
    assert main(["identify", str(path), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("lca-hil identify: error: ")
    assert str(path) in lines[0] and fragment in lines[0]
    assert not out.exists()


def test_cli_unknown_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An unknown --axis exits 2 and lists the robot's axes."""
    path = _write_rows(tmp_path / "r.csv", [["t_s"], ["0"]])
    assert main(["identify", str(path), "--axis", "elbow"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "lca-hil identify: error: unknown axis 'elbow'; valid: l_arm, pivot, c_arc, lift"
    ]


@pytest.mark.slow
def test_identified_yaml_overrides_a_per_axis_table(
    excitation_run: ScenarioResult, tmp_path: Path
) -> None:
    """If the base gives the pivot its own table, identified.yaml lists the axes in full."""
    doc = yaml.safe_load(DEFAULT_YAML.read_text(encoding="utf-8"))
    doc["robot"]["urdf"] = str(CONFIG / "urdf" / "lca_gantry.urdf")
    doc["axes"][1]["efficiency"] = doc["efficiency"]  # the pivot keeps Table 1 ...
    other = {state: dict(values) for state, values in doc["efficiency"].items()}
    for state in STATES[1:4]:  # ... while the other axes get another default
        other[state] = {d: {"eta_m": 1.0, "eta_l": 0.5} for d in ("direct", "reverse")}
    doc["efficiency"] = other
    base = tmp_path / "per_axis.yaml"
    base.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    robot = load_robot(str(base))
    result = identify(robot, AXIS, _record(excitation_run))
    written = write_outputs(result, robot, Path("run.csv"), tmp_path / "out")
    text = written[0].read_text(encoding="utf-8")
    assert "\naxes:\n" in text
    identified = load_robot(str(written[0]))
    pivot = identified.axes[1].efficiency
    for key, value in result.efficiency_table().items():
        assert pivot[key].eta_l == pytest.approx(value.eta_l, abs=1e-5)
        assert pivot[key].eta_m == pytest.approx(value.eta_m, abs=1e-5)
    assert dict(identified.axes[0].efficiency) == dict(robot.axes[0].efficiency)
    # The other axes in full, and the pivot's parameters other than its table, from the base.
    for index in (0, 2, 3):
        assert identified.axes[index] == robot.axes[index], AXIS_NAMES[index]
    pivot_axis, base_pivot = identified.axes[1], robot.axes[1]
    assert pivot_axis.gear_ratio == base_pivot.gear_ratio
    assert pivot_axis.motor == base_pivot.motor
    assert pivot_axis.friction == base_pivot.friction


# --- a bag ------------------------------------------------------------------------------------


def _write_bag(path: Path, run: ScenarioResult, robot: RobotParams, every: int) -> None:
    """joint_states and motor_states of a run, as the simulator node publishes them."""
    rosbag2 = pytest.importorskip("rosbags.rosbag2")
    typesys = pytest.importorskip("rosbags.typesys")
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    types = store.types
    joint_state = types[JOINT_STATE]
    header = types["std_msgs/msg/Header"]
    stamp = types["builtin_interfaces/msg/Time"]
    ratios = np.array([axis.gear_ratio for axis in robot.axes])
    torque = run.signals[:, SIGNAL_NAMES.index("motor_torque_nm"), :]
    current = run.signals[:, SIGNAL_NAMES.index("current_a"), :]
    names = list(robot.axis_names)
    with rosbag2.Writer(path, version=9, storage_plugin=rosbag2.StoragePlugin.MCAP) as writer:
        joints = writer.add_connection(f"/{JOINT_STATES}", JOINT_STATE, typestore=store)
        motors = writer.add_connection(f"/{MOTOR_STATES}", JOINT_STATE, typestore=store)
        for k in range(0, len(run.time_s), every):
            ns = 1_000_000_000 + round(run.time_s[k] * 1e9)
            head = header(stamp=stamp(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="")
            joint_msg = joint_state(
                header=head,
                name=names,
                position=run.position[k].copy(),
                velocity=run.velocity[k].copy(),
                effort=torque[k] * ratios,
            )
            motor_msg = joint_state(
                header=head,
                name=names,
                position=run.position[k] * ratios,
                velocity=run.velocity[k] * ratios,
                effort=current[k].copy(),
            )
            writer.write(joints, ns, store.serialize_cdr(joint_msg, JOINT_STATE))
            writer.write(motors, ns, store.serialize_cdr(motor_msg, JOINT_STATE))


@pytest.mark.slow
def test_cli_on_a_bag(
    excitation_run: ScenarioResult,
    default_robot: RobotParams,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """An MCAP bag at 250 Hz (joint_states + motor_states) gives Table 1 within 2 %."""
    bag = tmp_path / "bag"
    _write_bag(bag, excitation_run, default_robot, every=4)
    out = tmp_path / "out"
    assert main(["identify", str(bag), "--out", str(out)]) == 0
    assert "every 4 ms" in capsys.readouterr().out
    doc = json.loads((out / "identification.json").read_text(encoding="utf-8"))
    assert doc["sample_period_s"] == pytest.approx(0.004)
    prior = default_robot.axes[1].efficiency
    identified = [e for e in doc["estimates"] if e["status"] == "identified"]
    assert len(identified) == 8
    for entry in identified:
        truth = getattr(
            prior[(MotionState[entry["direction"].upper()], entry["state"])],
            entry["coefficient"],
        )
        assert entry["estimate"] == pytest.approx(truth, rel=NOISE_FREE_TOLERANCE), entry
    load_robot(str(out / "identified.yaml"))


def test_cli_bag_without_motor_states(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A bag lacking the current (motor_states) exits 2 and says what is missing."""
    rosbag2 = pytest.importorskip("rosbags.rosbag2")
    typesys = pytest.importorskip("rosbags.typesys")
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    joint_state = store.types[JOINT_STATE]
    header = store.types["std_msgs/msg/Header"]
    stamp = store.types["builtin_interfaces/msg/Time"]
    bag = tmp_path / "bag"
    with rosbag2.Writer(bag, version=9, storage_plugin=rosbag2.StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(f"/{JOINT_STATES}", JOINT_STATE, typestore=store)
        for k in range(5):
            msg = joint_state(
                header=header(stamp=stamp(sec=1, nanosec=k * 1000), frame_id=""),
                name=list(AXIS_NAMES),
                position=np.zeros(4),
                velocity=np.zeros(4),
                effort=np.zeros(4),
            )
            writer.write(conn, 1_000_000_000 + k, store.serialize_cdr(msg, JOINT_STATE))
    assert main(["identify", str(bag), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "motor_states has no joint 'pivot'" in err[0]
