"""A sweep's tasks: each point's documents resolved, its run built and validated, its key.

Three kinds of run, each from the existing model API:

* `closed_loop`: the composed closed loop (`lca_sim.analysis.closed_loop.ClosedLoop`), the
  controller core against the commanded plant, bit for bit the lockstep run of the nodes;
* `open_loop`: a voltage scenario on the simulator (`lca_sim.model.scenario.run_scenario`), as
  `lca-sim` runs it (the paper's Figs 9-10);
* `current_step`: Fig. 13's bench test, the current PI at the model rate against the locked
  rotor (`lca_sim.analysis.paper.current_step`, with the gains as parameters).

A task is self-contained and picklable: what a Dask worker needs (`lca_sim.batch.compute`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from lca_control.parameters import ParameterError
from lca_sim.analysis.closed_loop import ClosedLoopConfig
from lca_sim.analysis.metric_spec import MetricSpec, check_metric_names
from lca_sim.analysis.metrics import TRACKING_METRICS
from lca_sim.batch.payload import add_payload, payload_of
from lca_sim.batch.point import Documents, Point, apply_point, expand_points, point_key
from lca_sim.batch.spec import Scalar, SweepSpec, Trajectories
from lca_sim.errors import ConfigError, InvalidValueError
from lca_sim.model.params import RobotParams, parse_robot
from lca_sim.model.scenario import Scenario, parse_scenario

# Fig. 13's bench test, the defaults of a current_step base (lca_sim.analysis.paper.current_step).
STEP_DEFAULTS: dict[str, Any] = {
    "axis": "pivot",
    "setpoint_a": 5.0,
    "duration_s": 0.05,
    "dt_s": 1e-4,
    "current_kp_v_per_a": 31.62,
    "current_ti_s": 1e-3,
}


@dataclass(frozen=True, slots=True)
class OpenLoopRun:
    """A voltage scenario on the simulator (`lca-sim`'s run)."""

    robot: RobotParams
    scenario: Scenario
    rigid_body_update_steps: int = 1


@dataclass(frozen=True, slots=True)
class CurrentStepRun:
    """Fig. 13: a current step through the current PI at the model rate, rotor locked.

    The axis sits on its upper end stop and the positive current pushes it into the stop, as
    on a bench; the PI's output is limited to the motor's voltage limit.
    """

    robot: RobotParams
    axis: str
    setpoint_a: float
    duration_s: float
    dt_s: float
    current_kp_v_per_a: float
    current_ti_s: float


RunConfig = ClosedLoopConfig | OpenLoopRun | CurrentStepRun


ClosedLoopBuilder = Callable[[Documents, RobotParams], ClosedLoopConfig]


@dataclass(frozen=True, slots=True)
class PointTask:
    """Everything a worker needs for one point (picklable, self-contained).

    `version` is the lca_hil (and code) version the point's key was made with: a worker that
    runs another refuses the point (`lca_sim.batch.worker.timed_point`).
    """

    index: int
    seed: int
    values: tuple[tuple[str, Scalar], ...]
    key: str
    run: RunConfig
    metrics: tuple[MetricSpec, ...]
    trajectories: Trajectories | None
    version: str = ""


@dataclass(frozen=True, slots=True)
class PointOutcome:
    """A finished point: its metrics by column, and its downsampled trajectory (or None)."""

    key: str
    metrics: dict[str, float]
    trajectory: dict[str, list[Any]] | None


def robot_of(spec: SweepSpec, documents: Documents) -> RobotParams:
    """The point's robot: its document parsed against its URDF, the payload added.

    Raises:
        ConfigError: a bad value, named by the robot's key.
    """
    urdf = documents.urdf_xml
    payload = payload_of(documents.base, spec.source)
    if payload is not None:
        link, mass, xyz = payload
        urdf = add_payload(urdf, link, mass, (xyz[0], xyz[1], xyz[2]), spec.source)
    return parse_robot(documents.robot, str(documents.base.get("robot", "robot")), urdf)


def _step_run(spec: SweepSpec, documents: Documents, robot: RobotParams) -> CurrentStepRun:
    values = {**STEP_DEFAULTS, **{k: v for k, v in documents.base.items() if k in STEP_DEFAULTS}}
    for key in STEP_DEFAULTS:
        if key == "axis":
            continue
        value = values[key]
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise ConfigError(spec.source, f"base.{key}", f"expected a number > 0, got {value!r}")
    axis = str(values["axis"])
    if axis not in robot.axis_names:
        raise ConfigError(
            spec.source, "base.axis", f"expected one of {', '.join(robot.axis_names)}"
        )
    return CurrentStepRun(
        robot=robot,
        axis=axis,
        setpoint_a=float(values["setpoint_a"]),
        duration_s=float(values["duration_s"]),
        dt_s=float(values["dt_s"]),
        current_kp_v_per_a=float(values["current_kp_v_per_a"]),
        current_ti_s=float(values["current_ti_s"]),
    )


def build_run(
    spec: SweepSpec,
    documents: Documents,
    closed_loop: ClosedLoopBuilder | None = None,
) -> RunConfig:
    """The run of a point's documents.

    Args:
        spec: the sweep.
        documents: the point's documents (`apply_point`).
        closed_loop: builds a closed-loop config from the documents and the robot (the nodes'
            parameter validation lives above this layer, so the CLI hands it in).

    Raises:
        ConfigError: a bad value in a document.
        ParameterError: a bad node parameter (closed loop).
    """
    robot = robot_of(spec, documents)
    if spec.kind == "closed_loop":
        if closed_loop is None:
            raise InvalidValueError("a closed-loop sweep needs its config builder")
        return closed_loop(documents, robot)
    if spec.kind == "open_loop":
        source = str(documents.base.get("scenario", "scenario"))
        scenario = parse_scenario(documents.scenario, source, robot.axis_names)
        steps = documents.base.get("rigid_body_update_steps", 1)
        if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
            raise ConfigError(
                spec.source, "base.rigid_body_update_steps", f"expected >= 1, got {steps!r}"
            )
        return OpenLoopRun(robot, scenario, steps)
    return _step_run(spec, documents, robot)


def build_task(
    spec: SweepSpec,
    documents: Documents,
    point: Point,
    version: str,
    closed_loop: ClosedLoopBuilder | None = None,
) -> PointTask:
    """A point's task: its documents resolved, its run built and validated, its key.

    Raises:
        ConfigError: a bad path or value (what `apply_point` and `build_run` raise).
        ParameterError: a bad node parameter (closed loop).
    """
    resolved = apply_point(spec, documents, point)
    run = build_run(spec, resolved, closed_loop)
    robot = run.robot
    check_metric_names(spec.metrics, robot.axis_names, robot.state_machine.state_names, spec.source)
    if spec.trajectories is not None:
        for axis in spec.trajectories.axes:
            if axis not in robot.axis_names:
                raise ConfigError(
                    spec.source,
                    "trajectories.axes",
                    f"expected axes among {', '.join(robot.axis_names)}, got {axis!r}",
                )
    if spec.kind == "open_loop":
        for i, metric in enumerate(spec.metrics):
            if metric.metric in TRACKING_METRICS:
                raise ConfigError(
                    spec.source,
                    f"metrics[{i}].metric",
                    f"{metric.metric} needs a reference; an open-loop run follows a voltage "
                    "table and has none (use a closed_loop or current_step base)",
                )
    return PointTask(
        index=point.index,
        seed=point.seed,
        values=point.values,
        key=point_key(spec, resolved, version),
        run=run,
        metrics=spec.metrics,
        trajectories=spec.trajectories,
        version=version,
    )


def build_tasks(
    spec: SweepSpec,
    documents: Documents,
    version: str,
    closed_loop: ClosedLoopBuilder | None = None,
) -> list[PointTask]:
    """Every point's task, validated; the first bad point is one error naming its values.

    Args:
        spec, documents, version: as for `build_task`.
        closed_loop: the closed-loop config builder (`build_run`).

    Raises:
        ConfigError: the spec, the point and what is wrong with it.
    """
    tasks = []
    for point in expand_points(spec):
        try:
            tasks.append(build_task(spec, documents, point, version, closed_loop))
        except ConfigError as exc:
            if exc.source == spec.source:
                raise
            where = ", ".join(f"{k}={v!r}" for k, v in point.values)
            raise ConfigError(
                spec.source, f"parameters (point {point.index}: {where})", str(exc)
            ) from exc
        except ParameterError as exc:
            where = ", ".join(f"{k}={v!r}" for k, v in point.values)
            raise ConfigError(
                spec.source, f"parameters (point {point.index}: {where})", str(exc)
            ) from exc
    return tasks
