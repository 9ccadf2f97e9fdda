"""`lca-hil identify` says what it does not know (issue item 12).

End-stop samples are left out and counted, an interval wider than the documented bound makes a
state "not identifiable" (the prior is kept in identified.yaml), and small efficiencies are judged
on the absolute width of their interval. Each case is a simulated record; the numbers the code
before this fix gave are in the docstrings. The tools' own run on a record into an end stop
(`lca-sim run`, then `lca-hil identify`: the report's count and the prior kept in the written
robot file) is item 12 of the fault matrix, tests/test_fault_matrix.py.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from support import INTO_END_STOP

from lca_sim.analysis.identify import identify
from lca_sim.analysis.identify_estimate import judge_interval
from lca_sim.analysis.identify_types import (
    Criterion,
    EstimateStatus,
    IdentificationResult,
    IdentifyOptions,
    MotionRecord,
)
from lca_sim.cli.identify import main, write_outputs
from lca_sim.cli.results import write_csv
from lca_sim.config.loader import load_robot
from lca_sim.config.paths import config_dir
from lca_sim.model.kernel import STOP_END_STOP
from lca_sim.model.params import RobotParams
from lca_sim.model.scenario import ScenarioResult, parse_scenario, run_scenario
from lca_sim.model.simulator import Simulator
from lca_sim.model.state_machine import MotionState

SCENARIO = config_dir() / "scenarios" / "identify_pivot.yaml"
AXIS = "pivot"
MOTOR_DOMINANT = "motor_and_load_driving_motor_dominant"
# The clean run's tolerance (test_identify.NOISE_FREE_TOLERANCE) on the relative error, and the
# same at the criteria's switch (0.5) on the absolute error of a small efficiency.
RELATIVE_TOLERANCE = 0.02
ABSOLUTE_TOLERANCE = RELATIVE_TOLERANCE * 0.5

# Current noise that leaves the short direct motor-dominant state (about 370 samples) with a
# 95 % interval wider than its bound (0.12 > 0.1 at NOISY_SEED), the other states within theirs.
HEAVY_CURRENT_NOISE_A = 0.6
ENCODER_COUNTS_PER_REV = 4096
NOISY_SEED = 0


def _simulate(robot: RobotParams, doc: object, source: str) -> ScenarioResult:
    """Run a scenario document on a robot."""
    scenario = parse_scenario(doc, source, robot.axis_names)
    return run_scenario(Simulator(robot, dt_s=scenario.dt_s), scenario)


def _record(run: ScenarioResult) -> MotionRecord:
    """The noise-free measurements of a run."""
    return MotionRecord(run.time_s, run.position, run.velocity, run.signal("current_a", AXIS))


def _noisy_record(
    run: ScenarioResult, robot: RobotParams, current_noise_a: float, seed: int
) -> MotionRecord:
    """White current noise and a quantised encoder, as test_identify._noisy_record."""
    rng = np.random.default_rng(seed)
    a = robot.axis_names.index(AXIS)
    count_rad = 2.0 * math.pi / ENCODER_COUNTS_PER_REV / robot.axes[a].gear_ratio
    position = run.position.copy()
    velocity = run.velocity.copy()
    position[:, a] = np.floor(run.position[:, a] / count_rad + rng.uniform()) * count_rad
    velocity[1:, a] = np.diff(position[:, a]) / np.diff(run.time_s)
    velocity[0, a] = 0.0
    current = run.signal("current_a", AXIS) + rng.normal(0.0, current_noise_a, len(run.time_s))
    return MotionRecord(run.time_s, position, velocity, current)


def _judged_error(estimate: float, truth: float, criterion: Criterion) -> float:
    """The error as the state is judged: relative, or absolute for a small efficiency."""
    if criterion is Criterion.RELATIVE:
        return abs(estimate / truth - 1.0)
    return abs(estimate - truth) * RELATIVE_TOLERANCE / ABSOLUTE_TOLERANCE


def _assert_honest(result: IdentificationResult, robot: RobotParams) -> None:
    """Every identified state within the clean run's tolerance, judged by its criterion."""
    table = robot.axes[robot.axis_names.index(AXIS)].efficiency
    for e in result.estimates:
        if e.status is not EstimateStatus.IDENTIFIED:
            assert e.identified == e.prior, (e.state, e.direction)
            continue
        assert e.coefficient is not None and e.criterion is not None
        truth = getattr(table[(e.direction, e.state)], e.coefficient)
        error = _judged_error(e.estimate, truth, e.criterion)
        assert error < RELATIVE_TOLERANCE, (e.state, e.direction, e.estimate, truth)
        assert e.ci_width <= e.ci_width_bound


@pytest.fixture(scope="module")
def end_stop_run(default_robot: RobotParams) -> ScenarioResult:
    """INTO_END_STOP simulated on the default robot."""
    return _simulate(default_robot, INTO_END_STOP, "into_end_stop")


@pytest.fixture(scope="module")
def heavy_noise_result(default_robot: RobotParams) -> IdentificationResult:
    """The shipped excitation measured with HEAVY_CURRENT_NOISE_A."""
    run = _simulate(default_robot, yaml.safe_load(SCENARIO.read_text("utf-8")), str(SCENARIO))
    record = _noisy_record(run, default_robot, HEAVY_CURRENT_NOISE_A, NOISY_SEED)
    return identify(default_robot, AXIS, record)


# --- (1) end stops ----------------------------------------------------------------------------


@pytest.mark.parametrize("noisy", [False, True])
def test_end_stop_samples_are_excluded_and_counted(
    end_stop_run: ScenarioResult, default_robot: RobotParams, noisy: bool
) -> None:
    """A run into the end stop: its samples are out and counted, no confident wrong estimate.

    Before the fix the reverse motor-dominant state (truth 0.06) came out identified at 0.290,
    CI [0.142, 0.438], from 186 samples (noisy: 0.297, CI [0.148, 0.446], 171 samples).
    """
    q = end_stop_run.position[:, 1]
    at_stop = end_stop_run.drive[:, 1] == STOP_END_STOP
    assert at_stop.sum() > 1000 and q.min() == pytest.approx(-2.0)
    record = (
        _noisy_record(end_stop_run, default_robot, 0.05, NOISY_SEED)
        if noisy
        else _record(end_stop_run)
    )
    result = identify(default_robot, AXIS, record)
    assert result.position_limits == pytest.approx((-2.0, 2.0))
    margin = result.options.end_stop_margin_rad
    near = q <= -2.0 + margin
    assert np.all(result.state_index[near] == -4) and np.all(result.state_index[at_stop] == -4)
    assert not np.any(result.used[near])
    # The margin plus its guard on each side of the one visit.
    assert near.sum() < result.n_end_stop <= near.sum() + 2 * 21
    e = result.estimate(MOTOR_DOMINANT, MotionState.REVERSE)
    assert e.status is EstimateStatus.TOO_FEW_SAMPLES and e.identified == e.prior
    assert result.estimate("motor_driving", MotionState.DIRECT).status is (
        EstimateStatus.IDENTIFIED
    )
    _assert_honest(result, default_robot)


def test_end_stop_margin_is_an_option(default_robot: RobotParams) -> None:
    """A pivot resting 0.05 rad from its stop is inside the 3 deg margin, outside a margin of 0."""
    n = 200
    time_s = np.arange(n, dtype=np.float64) * 1e-3
    position = np.zeros((n, 4))
    position[:, 1] = 1.95  # within 3 deg of +2 rad, not within 0
    record = MotionRecord(time_s, position, np.zeros((n, 4)), np.zeros(n))
    assert identify(default_robot, AXIS, record).n_end_stop == n
    off = IdentifyOptions(end_stop_margin_rad=0.0)
    assert identify(default_robot, AXIS, record, off).n_end_stop == 0


# --- (2) intervals wider than the bound -------------------------------------------------------


def test_wide_interval_is_not_identifiable(
    heavy_noise_result: IdentificationResult, default_robot: RobotParams
) -> None:
    """A state whose interval is wider than its bound is not identifiable and keeps its prior.

    Before the fix the direct motor-dominant state (truth 0.45) was identified at 0.4286,
    CI [0.3674, 0.4897] (0.12 wide), and 0.4286 was written over the prior.
    """
    e = heavy_noise_result.estimate(MOTOR_DOMINANT, MotionState.DIRECT)
    assert e.status is EstimateStatus.NOT_IDENTIFIABLE
    assert e.ci_width > e.ci_width_bound == pytest.approx(0.1)
    assert math.isfinite(e.estimate)  # reported, but not used
    assert e.identified == e.prior
    for item in heavy_noise_result.estimates:
        if item.criterion is not None:
            identifiable = item.ci_width <= item.ci_width_bound
            assert (item.status is EstimateStatus.IDENTIFIED) is identifiable, item.state
    assert e in heavy_noise_result.not_identified
    _assert_noisy_within_interval(heavy_noise_result, default_robot)


def _assert_noisy_within_interval(result: IdentificationResult, robot: RobotParams) -> None:
    """Every identified state's truth within twice its interval's half width."""
    table = robot.axes[1].efficiency
    for e in result.estimates:
        if e.status is EstimateStatus.IDENTIFIED:
            assert e.coefficient is not None
            truth = getattr(table[(e.direction, e.state)], e.coefficient)
            assert abs(e.estimate - truth) < e.ci_width, (e.state, e.direction)


def test_not_identifiable_keeps_the_prior_in_the_files(
    heavy_noise_result: IdentificationResult,
    default_robot: RobotParams,
    tmp_path: Path,
) -> None:
    """identified.yaml keeps the prior of a not-identifiable state; the JSON says why, no NaN."""
    yaml_path, json_path = write_outputs(heavy_noise_result, default_robot, Path("x.csv"), tmp_path)
    written = load_robot(str(yaml_path)).axes[1].efficiency
    assert written[(MotionState.DIRECT, MOTOR_DOMINANT)].eta_l == 0.45  # the prior, exactly
    text = yaml_path.read_text(encoding="utf-8")
    assert "prior kept: not identifiable: 95 % CI [" in text
    raw = json_path.read_text(encoding="utf-8")
    assert "NaN" not in raw and "Infinity" not in raw
    doc = json.loads(raw)
    entry = next(
        x for x in doc["estimates"] if x["state"] == MOTOR_DOMINANT and x["direction"] == "direct"
    )
    assert entry["status"] == "not_identifiable" and entry["prior_kept"] is True
    assert entry["identified"] == {"eta_m": 1.0, "eta_l": 0.45}
    assert entry["ci_width"] > entry["ci_width_bound"] == pytest.approx(0.1)
    assert "wider than 0.1 (absolute criterion)" in entry["reason"]
    for item in doc["estimates"]:
        if item["estimate"] is None:
            assert item["reason"], item  # null plus reason


def test_the_issues_interval_is_not_identifiable() -> None:
    """The issue's interval [-0.15, 3.41] is far wider than any bound (0.2 at most)."""
    criterion, bound = judge_interval(1.0, IdentifyOptions())  # its estimate, clipped to 1
    assert criterion is Criterion.RELATIVE and 3.41 - (-0.15) > bound == pytest.approx(0.2)


# --- (3) small efficiencies -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "criterion", "bound"),
    [
        (0.06, Criterion.ABSOLUTE, 0.1),  # Table 1, reverse motor-dominant
        (0.16, Criterion.ABSOLUTE, 0.1),  # Table 1, reverse load-driving
        (0.45, Criterion.ABSOLUTE, 0.1),
        (0.5, Criterion.RELATIVE, 0.1),  # the switch: both give 0.1
        (0.55, Criterion.RELATIVE, 0.11),
        (0.9, Criterion.RELATIVE, 0.18),
        (1.7, Criterion.RELATIVE, 0.2),  # an efficiency is never above 1
        (0.0, Criterion.ABSOLUTE, 0.1),
    ],
)
def test_criterion_table(value: float, criterion: Criterion, bound: float) -> None:
    """Relative width above an estimate of 0.5, absolute below, continuous at the switch."""
    judged, width = judge_interval(value, IdentifyOptions())
    assert judged is criterion and width == pytest.approx(bound)


def test_small_efficiency_is_judged_on_absolute_width(
    heavy_noise_result: IdentificationResult,
    default_robot: RobotParams,
    tmp_path: Path,
) -> None:
    """eta_l = 0.06 with a 0.047-wide interval: identified on the absolute bound, and said so.

    A relative bound (0.2 x 0.037 = 0.0075) would call it not identifiable although its
    interval contains the truth and its torque error is 2 % of the load torque. Before the fix
    the report had no criterion at all (no `criterion` on the estimate, none in the JSON).
    """
    e = heavy_noise_result.estimate(MOTOR_DOMINANT, MotionState.REVERSE)
    assert e.criterion is Criterion.ABSOLUTE and e.status is EstimateStatus.IDENTIFIED
    assert 0.2 * e.estimate < e.ci_width <= e.ci_width_bound == pytest.approx(0.1)
    assert abs(e.estimate - 0.06) < ABSOLUTE_TOLERANCE * 5  # judged absolute: 0.023 off
    big = heavy_noise_result.estimate("motor_driving", MotionState.DIRECT)
    assert big.criterion is Criterion.RELATIVE and big.ci_width_bound == pytest.approx(0.18, 0.01)
    _, json_path = write_outputs(heavy_noise_result, default_robot, Path("x.csv"), tmp_path)
    doc = json.loads(json_path.read_text(encoding="utf-8"))
    criteria = {(x["state"], x["direction"]): x["criterion"] for x in doc["estimates"]}
    assert criteria[(MOTOR_DOMINANT, "reverse")] == "absolute"
    assert criteria[("motor_driving", "direct")] == "relative"
    assert criteria[("coasting", "direct")] is None  # nothing estimated, nothing judged


@pytest.mark.slow
def test_clean_excitation_reports_the_criterion_per_state(
    default_robot: RobotParams, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Clean excitation: Table 1's 0.06 and 0.16 states judged absolute, the rest relative."""
    run = _simulate(default_robot, yaml.safe_load(SCENARIO.read_text("utf-8")), str(SCENARIO))
    csv_path = tmp_path / "result.csv"
    write_csv(run, csv_path)
    assert main(["identify", str(csv_path)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    for state, direction, judged in (
        ("motor_driving", "direct", "relative:"),
        ("load_driving", "direct", "relative:"),
        (MOTOR_DOMINANT, "direct", "absolute:"),  # 0.45
        (MOTOR_DOMINANT, "reverse", "absolute:"),  # 0.06
        ("load_driving", "reverse", "absolute:"),  # 0.16
    ):
        row = next(r for r in rows if r[:2] == [state, direction])
        assert judged in row, row
    result = identify(default_robot, AXIS, _record(run))
    assert result.n_end_stop == 0
    _assert_honest(result, default_robot)


def test_cli_end_stop_margin_flag(
    end_stop_run: ScenarioResult, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--end-stop-margin-deg sets the margin; a negative one is one error line, exit 2."""
    csv_path = tmp_path / "result.csv"
    write_csv(end_stop_run, csv_path)
    assert main(["identify", str(csv_path), "--end-stop-margin-deg", "6"]) == 0
    doc = json.loads((tmp_path / "identification.json").read_text(encoding="utf-8"))
    assert doc["options"]["end_stop_margin_rad"] == pytest.approx(math.radians(6.0))
    capsys.readouterr()
    assert main(["identify", str(csv_path), "--end-stop-margin-deg", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["lca-hil identify: error: --end-stop-margin-deg: expected >= 0, got -1.0"]
