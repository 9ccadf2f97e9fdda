"""One point of a sweep: build its run from its documents, run it, compute its metrics.

Three kinds of run, each from the existing model API:

* `closed_loop`: the composed closed loop (`lca_sim.analysis.closed_loop.ClosedLoop`), the
  controller core against the commanded plant, bit for bit the lockstep run of the nodes;
* `open_loop`: a voltage scenario on the simulator (`lca_sim.model.scenario.run_scenario`), as
  `lca-sim` runs it (the paper's Figs 9-10: the voltage cut of the braking phase is a step to
  0 V in the scenario's table, the amplifier then holds the winding at 0 V);
* `current_step`: Fig. 13's bench test, the current PI at the model rate against the locked
  rotor (`lca_sim.analysis.paper.current_step`, with the gains as parameters).

`run_point` is what a Dask worker calls; it is pure (no clock, no files) and deterministic, so
a point gives the same numbers on any worker. The CLI (`lca_sim.cli.sweep`) reads the files,
times the points and writes the results.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from lca_control.pi import PIController, PIParams
from lca_sim.analysis.closed_loop import ClosedLoop, ClosedLoopConfig
from lca_sim.analysis.metrics import TRACKING_METRICS, MetricSpec, Trace, check_metric_names
from lca_sim.analysis.sweep_spec import (
    Documents,
    Point,
    Scalar,
    SweepSpec,
    Trajectories,
    add_payload,
    apply_point,
    payload_of,
    point_key,
)
from lca_sim.errors import ConfigError
from lca_sim.model.params import RobotParams, parse_robot
from lca_sim.model.scenario import Scenario, parse_scenario, run_scenario
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator

FloatArray = npt.NDArray[np.float64]

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
    runs another refuses the point (`lca_sim.cli.sweep.timed_point`).
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


# --- building ----------------------------------------------------------------------------------


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
            raise ValueError("a closed-loop sweep needs its config builder")
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


# --- running -----------------------------------------------------------------------------------


def _closed_loop_trace(config: ClosedLoopConfig) -> Trace:
    loop = ClosedLoop(config)
    result = loop.run()
    reference = np.full(result.position.shape, np.nan)
    for j, joint in enumerate(result.joints):
        reference[:, result.axes.index(joint)] = result.velocity_reference[:, j]
    return Trace(
        axes=result.axes,
        state_names=result.state_names,
        time_s=result.time_s,
        position=result.position,
        velocity=result.velocity,
        current_a=result.current_a,
        voltage_v=result.voltage_v,
        drive_state=result.drive_state,
        reference=reference,
        reference_signal="velocity",
        position_limits=loop.sim.position_limits,
    )


def _open_loop_trace(run: OpenLoopRun) -> Trace:
    sim = Simulator(
        run.robot, dt_s=run.scenario.dt_s, rigid_body_update_steps=run.rigid_body_update_steps
    )
    result = run_scenario(sim, run.scenario)
    return Trace(
        axes=result.axis_names,
        state_names=result.state_names,
        time_s=result.time_s,
        position=result.position,
        velocity=result.velocity,
        current_a=result.signals[:, SIGNAL_NAMES.index("current_a"), :].copy(),
        voltage_v=result.signals[:, SIGNAL_NAMES.index("voltage_v"), :].copy(),
        drive_state=result.drive,
        reference=np.full(result.position.shape, np.nan),
        reference_signal="",
        position_limits=sim.position_limits,
    )


def _current_step_trace(run: CurrentStepRun) -> Trace:
    """Fig. 13 as `lca_sim.analysis.paper.current_step` runs it, gains from the run.

    One sample at t = 0 (at rest, 0 A), then one after every model step.
    """
    sim = Simulator(run.robot, dt_s=run.dt_s)
    a = sim.axis_names.index(run.axis)
    sim.reset(position={run.axis: sim.position_limits[a][1]})
    limit_v = run.robot.axes[a].motor.voltage_limit_v
    loop = PIController(PIParams(run.current_kp_v_per_a, run.current_ti_s, -limit_v, limit_v))
    n = round(run.duration_s / run.dt_s) + 1
    n_axes = sim.n_axes
    position, velocity = np.empty((n, n_axes)), np.empty((n, n_axes))
    current, voltage = np.empty((n, n_axes)), np.empty((n, n_axes))
    drive = np.empty((n, n_axes), dtype=np.int64)
    state, modes = sim.state_array, sim.mode_array
    voltage_row = sim.signal_array[SIGNAL_NAMES.index("voltage_v")]
    volts = np.zeros(n_axes)

    def record(k: int) -> None:
        position[k], velocity[k], current[k] = state[0], state[1], state[2]
        voltage[k], drive[k] = voltage_row, modes[1]

    record(0)
    voltage[0] = 0.0
    for k in range(1, n):
        volts[a] = loop.update(run.setpoint_a, float(state[2, a]), sim.dt_s)
        sim.step(volts)
        record(k)
    reference = np.full((n, n_axes), np.nan)
    reference[:, a] = run.setpoint_a
    time_s: FloatArray = np.arange(n, dtype=np.float64) * run.dt_s
    return Trace(
        axes=sim.axis_names,
        state_names=sim.state_names,
        time_s=time_s,
        position=position,
        velocity=velocity,
        current_a=current,
        voltage_v=voltage,
        drive_state=drive,
        reference=reference,
        reference_signal="current_a",
        position_limits=sim.position_limits,
    )


def trace_of(run: RunConfig) -> Trace:
    """Run one configuration and return its samples."""
    if isinstance(run, ClosedLoopConfig):
        return _closed_loop_trace(run)
    if isinstance(run, OpenLoopRun):
        return _open_loop_trace(run)
    return _current_step_trace(run)


def downsample(trace: Trace, every_s: float, axes: tuple[str, ...]) -> dict[str, list[Any]]:
    """The samples nearest to 0, every_s, 2 every_s, ...: t_s and per axis its signals."""
    t = trace.time_s
    grid = np.arange(0.0, t[-1] + 0.5 * every_s, every_s)
    rows = np.unique(np.clip(np.searchsorted(t, grid - 1e-9 * every_s), 0, len(t) - 1))
    columns: dict[str, list[Any]] = {"t_s": t[rows].tolist()}
    for axis in axes:
        a = trace.axis(axis)
        for name in ("position", "velocity", "current_a", "voltage_v"):
            columns[f"{axis}_{name}"] = trace.signal(name)[rows, a].tolist()
        columns[f"{axis}_drive_state"] = [
            trace.state_names[int(s)] for s in trace.drive_state[rows, a]
        ]
    return columns


def run_point(task: PointTask) -> PointOutcome:
    """Run a point and compute its metrics (what a Dask worker calls)."""
    trace = trace_of(task.run)
    metrics = {m.name: m.compute(trace) for m in task.metrics}
    trajectory = None
    if task.trajectories is not None:
        trajectory = downsample(trace, task.trajectories.every_s, task.trajectories.axes)
    return PointOutcome(task.key, metrics, trajectory)
