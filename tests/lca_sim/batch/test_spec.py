"""Sweep specs and the metric library: validation errors, points, resolution, analytic metrics."""

from __future__ import annotations

import dataclasses
import math
import re
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from support import CONFIG

from lca_sim.analysis.metric_spec import parse_metric
from lca_sim.analysis.metrics import MetricArgs, Trace
from lca_sim.analysis.paper import current_step
from lca_sim.batch.closed_loop_config import closed_loop_builder
from lca_sim.batch.compute import run_point
from lca_sim.batch.payload import add_payload
from lca_sim.batch.plan import load_spec
from lca_sim.batch.point import Documents, apply_point, expand_points, point_key
from lca_sim.batch.spec import parse_spec
from lca_sim.batch.tasks import CurrentStepRun, PointTask, build_task, build_tasks
from lca_sim.batch.version import package_version
from lca_sim.batch.worker import timed_point
from lca_sim.cli import hil
from lca_sim.config.yaml_files import read_yaml
from lca_sim.errors import EXIT_BAD_INPUT, ConfigError
from lca_sim.model.params import RobotParams

SWEEPS = CONFIG / "sweeps"


@pytest.fixture(autouse=True)
def _keep_the_switch_interval() -> Iterator[None]:
    """`timed_point` sets the worker's GIL switch interval; in this process, put it back."""
    interval = sys.getswitchinterval()
    yield
    sys.setswitchinterval(interval)


def _spec(**changes: Any) -> dict[str, Any]:
    """A small valid current-step spec, with top-level keys replaced."""
    spec: dict[str, Any] = {
        "base": {"kind": "current_step", "robot": "default", "axis": "pivot", "duration_s": 0.01},
        "parameters": [
            {"name": "kp", "path": "base.current_kp_v_per_a", "values": [20.0, 40.0]},
            {
                "name": "ti",
                "path": "base.current_ti_s",
                "range": {"start": 1e-3, "stop": 2e-3, "num": 3},
            },
        ],
        "metrics": [{"metric": "overshoot_pct", "signal": "current_a"}],
    }
    spec.update(changes)
    return spec


def _write(tmp_path: Path, spec: dict[str, Any]) -> Path:
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec), encoding="utf-8")
    return path


# ------------------------------------------------------------------------------- validation

BAD_SPECS: list[tuple[str, dict[str, Any], str]] = [
    ("unknown top-level key", _spec(paramters=[]), "paramters: unknown key"),
    ("unknown kind", _spec(base={"kind": "hover"}), "base.kind: expected one of"),
    ("unknown base key", _spec(base={"kind": "current_step", "speed": 1}), "base.speed: unknown"),
    ("no metrics", _spec(metrics=[]), "metrics: expected a non-empty list"),
    ("unknown metric", _spec(metrics=[{"metric": "wobble"}]), "metrics[0].metric: expected one"),
    (
        "argument a metric does not take",
        _spec(metrics=[{"metric": "peak_current_a", "band": 0.1}]),
        "metrics[0].band: not an argument of peak_current_a",
    ),
    (
        "path into a root the kind has not",
        _spec(parameters=[{"name": "k", "path": "controller.velocity_ti_s", "values": [1.0]}]),
        "parameters[0].path: controller.velocity_ti_s: expected a path into base, robot",
    ),
    (
        "two value kinds",
        _spec(parameters=[{"name": "k", "path": "base.setpoint_a", "values": [1.0],
                           "range": {"start": 1, "stop": 2, "num": 2}}]),
        "parameters[0]: expected exactly one of values, range, distribution",
    ),
    (
        "blend without to",
        _spec(parameters=[{"name": "k", "path": "base.setpoint_a", "mode": "blend",
                           "values": [0.5]}]),
        "parameters[0].to: missing",
    ),
    (
        "a distribution in a grid sweep",
        _spec(sampling="grid", parameters=[{"name": "k", "path": "base.setpoint_a",
                                            "distribution": {"kind": "uniform", "low": 1,
                                                             "high": 2}}]),
        "parameters[0]: expected values: or range: in a grid sweep",
    ),
    (
        "a random sweep without samples",
        _spec(parameters=[{"name": "k", "path": "base.setpoint_a",
                           "distribution": {"kind": "normal", "mean": 5, "std": 0.1}}]),
        "samples: expected a whole number >= 1",
    ),
    (
        "a column given twice",
        _spec(metrics=[{"name": "kp", "metric": "peak_current_a"}]),
        "metrics[0].name: 'kp' is taken",
    ),
    (
        "a path to a file read once",
        _spec(parameters=[{"name": "k", "path": "base.robot", "values": ["reversible"]}]),
        "parameters[0].path: base.robot names a file the sweep reads once",
    ),
    (
        "an empty window",
        _spec(metrics=[{"metric": "peak_current_a", "from_s": 2.0, "to_s": 1.0}]),
        "metrics[0].to_s: expected to_s >= from_s",
    ),
    (
        "a negative band",
        _spec(metrics=[{"metric": "settling_time_s", "band": -0.05}]),
        "metrics[0].band: expected a fraction of the target > 0",
    ),
    (
        "rise levels the wrong way round",
        _spec(metrics=[{"metric": "rise_time_s", "low": 0.9, "high": 0.1}]),
        "metrics[0].high: expected low < high",
    ),
    (
        "a range of zero points",
        _spec(parameters=[{"name": "k", "path": "base.setpoint_a",
                           "range": {"start": 1, "stop": 2, "num": 0}}]),
        "parameters[0].range.num: expected a whole number >= 1",
    ),
]  # fmt: skip


@pytest.mark.parametrize(("case", "spec", "message"), BAD_SPECS, ids=[c[0] for c in BAD_SPECS])
def test_a_bad_spec_names_its_key(case: str, spec: dict[str, Any], message: str) -> None:
    """Each invalid spec is one ConfigError naming the bad key."""
    with pytest.raises(ConfigError) as caught:
        parse_spec(spec, "spec.yaml")
    assert message in str(caught.value), (case, str(caught.value))
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize(
    ("parameter", "message"),
    [
        (
            {"name": "r", "path": "robot.axes.pivot.motor.resistanse_ohm", "values": [1.0]},
            "parameters[0].path: robot.axes.pivot.motor: no key 'resistanse_ohm' (valid: "
            "resistance_ohm,",
        ),
        (
            {"name": "r", "path": "robot.axes.pivott.motor.resistance_ohm", "values": [1.0]},
            "parameters[0].path: robot.axes: no item 'pivott' (valid: l_arm, pivot, c_arc, lift)",
        ),
        (
            {"name": "r", "path": "robot.axes.pivot.motor.resistance_ohm", "values": [-1.0]},
            "parameters (point 0: r=-1.0): default: axes[1].motor.resistance_ohm: expected a "
            "number > 0",
        ),
    ],
)
def test_a_bad_path_or_value_is_caught_before_anything_runs(
    tmp_path: Path, parameter: dict[str, Any], message: str
) -> None:
    """A path the documents lack, or a value the robot refuses: one error, nothing written."""
    path = _write(tmp_path, _spec(parameters=[parameter]))
    spec, documents = load_spec(path)
    with pytest.raises(ConfigError) as caught:
        build_tasks(spec, documents, "0", closed_loop_builder)
    assert message in str(caught.value)


def test_the_cli_exits_2_with_one_line_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`lca-hil sweep` on a bad spec: exit 2, one stderr line naming the key, no output folder."""
    path = _write(tmp_path, _spec(metrics=[{"metric": "peak_current_a", "axis": "elbow"}]))
    out = tmp_path / "out"
    assert hil.main(["sweep", str(path), "--out", str(out)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "metrics[0].axis: expected one of l_arm, pivot" in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("name", sorted(p.name for p in SWEEPS.glob("*.yaml")))
def test_the_shipped_specs_are_valid(name: str) -> None:
    """Every example in config/sweeps/ validates and builds every point."""
    spec, documents = load_spec(SWEEPS / name)
    tasks = build_tasks(spec, documents, "0", closed_loop_builder)
    assert len(tasks) == spec.n_points >= 2
    assert len({t.key for t in tasks}) == len(tasks)


# ------------------------------------------------------------------------------ the points


def test_grid_points_are_the_product_last_fastest() -> None:
    """A 2 x 3 grid: 6 points, the last parameter varying fastest, ranges as linspace."""
    points = expand_points(parse_spec(_spec(), "s"))
    assert [p.index for p in points] == list(range(6))
    assert [dict(p.values)["ti"] for p in points[:3]] == [1e-3, 1.5e-3, 2e-3]
    assert [dict(p.values)["kp"] for p in points] == [20.0] * 3 + [40.0] * 3


def test_random_points_do_not_depend_on_the_sample_count() -> None:
    """Point i of a random sweep is drawn from (seed, i): 5 samples are the first of 10."""
    distribution = {"kind": "normal", "mean": 5.0, "std": 1.0, "low": 4.0}
    parameter = {"name": "k", "path": "base.setpoint_a", "distribution": distribution}
    five = expand_points(parse_spec(_spec(parameters=[parameter], samples=5, seed=7), "s"))
    ten = expand_points(parse_spec(_spec(parameters=[parameter], samples=10, seed=7), "s"))
    other = expand_points(parse_spec(_spec(parameters=[parameter], samples=5, seed=8), "s"))
    assert five == ten[:5]
    assert [p.values for p in five] != [p.values for p in other]
    assert all(float(dict(p.values)["k"]) >= 4.0 for p in ten)


def test_blend_and_scale_and_the_axis_efficiency_copy(tmp_path: Path) -> None:
    """Blending eta_l 0.55 half-way to 1 gives 0.775, on the pivot alone; scale multiplies."""
    spec_doc = _spec(
        parameters=[
            {"name": "wear", "path": "robot.axes.pivot.efficiency.load_driving.direct.eta_l",
             "mode": "blend", "to": 1.0, "values": [0.5]},
            {"name": "r", "path": "robot.axes.pivot.motor.resistance_ohm", "mode": "scale",
             "values": [1.1]},
        ]
    )  # fmt: skip
    spec, documents = load_spec(_write(tmp_path, spec_doc))
    (point,) = expand_points(spec)
    resolved = apply_point(spec, documents, point)
    axes = {a["name"]: a for a in resolved.robot["axes"]}
    assert axes["pivot"]["efficiency"]["load_driving"]["direct"]["eta_l"] == pytest.approx(0.775)
    assert axes["pivot"]["motor"]["resistance_ohm"] == pytest.approx(1.1)
    assert "efficiency" not in axes["l_arm"]
    assert resolved.robot["efficiency"]["load_driving"]["direct"]["eta_l"] == 0.55
    assert documents.robot["axes"][1].get("efficiency") is None  # the base is untouched
    assert point_key(spec, resolved, "1") != point_key(spec, resolved, "2")
    assert point_key(spec, resolved, "1") == point_key(
        spec, apply_point(spec, documents, point), "1"
    )


def test_a_payload_adds_its_mass_and_moves_the_centre_of_mass(default_robot: RobotParams) -> None:
    """10 kg at 0.3 m beside a 150 kg link: mass 160 kg, CoG at the mass-weighted mean."""
    urdf = add_payload(default_robot.urdf_xml, "c_arc_link", 10.0, (0.3, 0.0, -0.22), "s")
    link = next(el for el in ET.fromstring(urdf).iter("link") if el.get("name") == "c_arc_link")
    inertial = link.find("inertial")
    assert inertial is not None
    mass, origin = inertial.find("mass"), inertial.find("origin")
    assert mass is not None and origin is not None
    assert float(mass.get("value", "nan")) == pytest.approx(160.0)
    xyz = [float(x) for x in origin.get("xyz", "").split()]
    assert xyz == pytest.approx([10.0 * 0.3 / 160.0, 0.0, -0.22])
    inertia = inertial.find("inertia")
    assert inertia is not None
    # Parallel axes about z: 28 + 150 d1^2 + 10 d2^2 with d1 = x_c, d2 = 0.3 - x_c.
    x_c = 3.0 / 160.0
    expected = 28.0 + 150.0 * x_c**2 + 10.0 * (0.3 - x_c) ** 2
    assert float(inertia.get("izz", "nan")) == pytest.approx(expected)
    assert add_payload(default_robot.urdf_xml, "c_arc_link", 0.0, (0, 0, 0), "s") == (
        default_robot.urdf_xml
    )
    with pytest.raises(ConfigError, match=r"base\.payload\.link: expected one of"):
        add_payload(default_robot.urdf_xml, "tray", 1.0, (0, 0, 0), "s")


def test_the_current_step_equals_the_papers_fig13(default_robot: RobotParams) -> None:
    """With the paper's gains the sweep's current step gives Fig. 13's figures exactly."""
    paper = current_step(default_robot)
    spec = parse_spec(
        _spec(
            base={"kind": "current_step", "axis": "pivot"},
            parameters=[],
            metrics=[
                {"metric": "overshoot_pct", "signal": "current_a"},
                {"metric": "rise_time_s", "signal": "current_a"},
                {"metric": "settling_time_s", "signal": "current_a"},
            ],
        ),
        "s",
    )
    run = CurrentStepRun(default_robot, "pivot", 5.0, 0.05, 1e-4, 31.62, 1e-3)
    from lca_sim.batch.tasks import PointTask

    outcome = run_point(PointTask(0, 0, (), "k", run, spec.metrics, None))
    assert outcome.metrics["overshoot_pct"] == paper.overshoot_pct
    assert outcome.metrics["rise_time_s"] == paper.rise_time_s
    assert outcome.metrics["settling_time_s"] == paper.response_time_s


# --------------------------------------------------------------------------------- metrics


def _trace(
    t: np.ndarray,
    *,
    position: np.ndarray | None = None,
    velocity: np.ndarray | None = None,
    current: np.ndarray | None = None,
    voltage: np.ndarray | None = None,
    drive: np.ndarray | None = None,
    reference: np.ndarray | None = None,
) -> Trace:
    """A one-axis trace (`pivot`) with the given columns (zeros elsewhere)."""

    def col(x: np.ndarray | None) -> np.ndarray:
        return np.zeros((len(t), 1)) if x is None else np.asarray(x, dtype=float)[:, None]

    return Trace(
        axes=("pivot",),
        state_names=("stop_hold", "motor_driving", "load_driving"),
        time_s=np.asarray(t, dtype=float),
        position=col(position),
        velocity=col(velocity),
        current_a=col(current),
        voltage_v=col(voltage),
        drive_state=(np.zeros((len(t), 1), dtype=np.int64) if drive is None
                     else np.asarray(drive, dtype=np.int64)[:, None]),
        reference=np.full((len(t), 1), np.nan) if reference is None else col(reference),
        reference_signal="" if reference is None else "velocity",
        position_limits=((-1.0, 1.0),),
    )  # fmt: skip


def _metric(trace: Trace, **entry: Any) -> float:
    return parse_metric(entry, "s", "metrics[0]", "pivot").compute(trace)


def test_first_order_step_rise_and_settling_times() -> None:
    """1 - exp(-t/tau): 10-90 % rise tau ln 9, 5 % settling tau ln 20, no overshoot."""
    tau, dt = 0.01, 1e-6
    t = np.arange(0.0, 0.2, dt)
    y = 1.0 - np.exp(-t / tau)
    trace = _trace(t, velocity=y)
    kw = {"signal": "velocity", "target": 1.0}
    assert _metric(trace, metric="rise_time_s", **kw) == pytest.approx(tau * math.log(9), abs=dt)
    assert _metric(trace, metric="settling_time_s", **kw) == pytest.approx(
        tau * math.log(20), abs=dt
    )
    assert _metric(trace, metric="overshoot_pct", **kw) == 0.0


def test_second_order_overshoot() -> None:
    """An underdamped step, zeta 0.5: overshoot exp(-zeta pi / sqrt(1 - zeta^2)) = 16.3 %."""
    zeta, wn = 0.5, 100.0
    t = np.arange(0.0, 0.5, 1e-6)
    wd = wn * math.sqrt(1 - zeta**2)
    phi = math.acos(zeta)
    y = 1 - np.exp(-zeta * wn * t) * np.sin(wd * t + phi) / math.sqrt(1 - zeta**2)
    expected = 100.0 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2))
    trace = _trace(t, current=y)
    got = _metric(trace, metric="overshoot_pct", signal="current_a")
    assert got == pytest.approx(expected, rel=1e-6) and got == pytest.approx(16.303, abs=1e-3)


def test_energy_current_and_tracking() -> None:
    """2 V x 3 A for 1 s then 2 V x -1 A for 1 s: 6 J drawn, 2 J returned; rms and peaks."""
    t = np.arange(0.0, 2.0 + 1e-9, 0.001)
    current = np.where(t < 1.0 - 1e-9, 3.0, -1.0)
    trace = _trace(t, voltage=np.full(len(t), 2.0), current=current,
                   velocity=np.full(len(t), 0.5), reference=np.ones(len(t)))  # fmt: skip
    assert _metric(trace, metric="energy_drawn_j") == pytest.approx(6.0)
    assert _metric(trace, metric="energy_returned_j") == pytest.approx(2.0)
    assert _metric(trace, metric="peak_current_a") == 3.0
    assert _metric(trace, metric="rms_current_a") == pytest.approx(math.sqrt(5.0), rel=1e-3)
    assert _metric(trace, metric="tracking_error_rms") == pytest.approx(0.5)
    assert _metric(trace, metric="tracking_error_max") == pytest.approx(0.5)
    assert _metric(trace, metric="energy_drawn_j", from_s=1.0) == 0.0
    assert math.isnan(_metric(_trace(t), metric="tracking_error_rms"))  # no reference


def test_drive_states_travel_drift_and_end_stop() -> None:
    """Hand-made states: time in each, the change positions and count, travel, drift, contact."""
    t = np.arange(0.0, 1.0 + 1e-9, 0.1)  # 11 samples
    drive = np.array([0, 0, 1, 1, 1, 2, 2, 2, 0, 0, 0])
    position = np.array([0.0, 0.0, 0.1, 0.3, 0.5, 0.6, 0.65, 0.7, 1.0, 1.0, 1.0])
    trace = _trace(t, drive=drive, position=position)
    assert _metric(trace, metric="time_in_state_s", states=["motor_driving"]) == pytest.approx(0.3)
    assert _metric(trace, metric="time_in_state_s", states=["stop_hold"]) == pytest.approx(0.4)
    assert _metric(trace, metric="state_change_position", states=["load_driving"]) == 0.6
    assert _metric(trace, metric="state_change_time_s", states=["load_driving"]) == (
        pytest.approx(0.5)
    )
    assert math.isnan(_metric(trace, metric="state_change_position", states=["load_driving"],
                              from_s=0.6))  # fmt: skip
    assert _metric(trace, metric="state_change_count") == 3.0
    assert _metric(trace, metric="travel", from_s=0.5) == pytest.approx(0.4)
    assert _metric(trace, metric="hold_drift", from_s=0.2, to_s=0.4) == pytest.approx(0.4)
    assert _metric(trace, metric="end_stop_contact") == 1.0
    assert _metric(trace, metric="end_stop_contact", to_s=0.7) == 0.0
    with pytest.raises(ConfigError, match="states"):
        parse_metric({"metric": "time_in_state_s"}, "s", "metrics[0]", "pivot")
    assert MetricArgs("pivot").band == 0.05


def test_each_change_into_a_state_by_its_occurrence() -> None:
    """Three changes into motor_driving: the 1st, 2nd, 3rd and last, then none (NaN)."""
    t = np.arange(8) * 0.1
    drive = np.array([0, 1, 1, 0, 1, 2, 1, 1])
    trace = _trace(t, drive=drive, position=t * 2.0)
    entry = {"metric": "state_change_position", "states": ["motor_driving"]}
    assert [_metric(trace, **entry, occurrence=k) for k in (1, 2, 3, -1)] == pytest.approx(
        [0.2, 0.8, 1.2, 1.2]
    )
    assert math.isnan(_metric(trace, **entry, occurrence=4))
    assert _metric(
        trace, metric="state_change_time_s", states=["motor_driving"], occurrence=-2
    ) == (pytest.approx(0.4))
    with pytest.raises(ConfigError, match=r"metrics\[0\]\.occurrence: expected a whole number"):
        _metric(trace, **entry, occurrence=0)


def test_documents_root_names() -> None:
    """Documents answers each root a path can start at."""
    documents = Documents(base={"a": 1}, robot={}, urdf_xml="")
    assert documents.root("base") == {"a": 1} and documents.root("scenario") == {}


def test_what_a_point_cannot_compute_is_refused_before_it_runs(tmp_path: Path) -> None:
    """Trajectories of an axis the robot lacks; tracking error of a run with no reference."""
    bad_axes = _spec(trajectories={"every_s": 0.01, "axes": ["elbow"]})
    spec, documents = load_spec(_write(tmp_path, bad_axes))
    with pytest.raises(ConfigError, match=r"trajectories\.axes: expected axes among"):
        build_tasks(spec, documents, "0", closed_loop_builder)
    open_loop = {
        "base": {"kind": "open_loop", "scenario": "hold_pivot", "axis": "pivot"},
        "parameters": [],
        "metrics": [{"metric": "tracking_error_rms"}],
    }
    spec, documents = load_spec(_write(tmp_path, open_loop))
    with pytest.raises(ConfigError, match=r"metrics\[0\]\.metric: tracking_error_rms needs a"):
        build_tasks(spec, documents, "0", closed_loop_builder)


def test_the_version_in_a_key_names_the_code_and_a_worker_checks_it() -> None:
    """The key's version carries a hash of the code; a worker with other code refuses a point."""
    version = package_version()
    assert re.fullmatch(r".+\+code\.[0-9a-f]{12}", version), version
    task = dataclasses.replace(_current_step_task(), version="0.1.0+code.000000000000")
    with pytest.raises(RuntimeError, match="install the driver's lca_hil on every worker"):
        timed_point(task)
    outcome, wall_s = timed_point(dataclasses.replace(task, version=version))
    assert outcome.metrics["overshoot_pct"] > 0.0 and wall_s > 0.0


def _current_step_task() -> PointTask:
    spec = parse_spec(_spec(), "spec.yaml")
    documents = Documents(
        base=dict(spec.base),
        robot=read_yaml(CONFIG / "robots" / "default.yaml"),
        urdf_xml=(CONFIG / "urdf" / "lca_gantry.urdf").read_text(encoding="utf-8"),
    )
    return build_task(spec, documents, expand_points(spec)[0], package_version())
