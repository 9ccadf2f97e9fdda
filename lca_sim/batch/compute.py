"""One point computed: its run's samples, its metrics and its downsampled trajectory.

`run_point` is what a Dask worker calls (through `lca_sim.batch.worker.timed_point`); it is
pure (no clock, no files) and deterministic, so a point gives the same numbers on any worker.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from lca_control.pi import PIController, PIParams
from lca_sim.analysis.closed_loop import ClosedLoop, ClosedLoopConfig
from lca_sim.analysis.metrics import Trace
from lca_sim.batch.tasks import CurrentStepRun, OpenLoopRun, PointOutcome, PointTask, RunConfig
from lca_sim.model.scenario import run_scenario
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator

FloatArray = npt.NDArray[np.float64]


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
