"""Benchmark: the composed closed loop (`lca-hil run`) against real time, on one core.

What it measures, in one process: the controller core and the commanded plant of
`lca_sim.analysis.closed_loop`, configured from config/ros/controller.yaml and simulator.yaml
(the 4-axis robot, the cascade on current commands at a 4 ms control period, the plant at a
0.1 ms step with Pinocchio's terms held for 1 ms, Fig. 15's 10 s ramp of the pivot), over a
13 s run: the same loop as the lockstep run of the two nodes over ROS 2, bit for bit
(tests/lca_sim/analysis/test_closed_loop.py). It prints the run's velocity tracking error as
`lca-hil run` does (`lca_sim.analysis.metrics.VelocityTracking`), a check that the timed loop
is the loop that tracks.

1. ``ClosedLoop.run``: the whole composed run (the model and the plant are built once,
   outside the timing, as a sweep builds them once per point); the real-time factor is the
   simulated time over the wall time.
2. The plant alone: the same run's commands replayed into a fresh commanded plant, period by
   period (``CommandedPlant.command`` then ``advance``), with a check that it ends in the same
   state to the last bit: what the loop would cost with a free controller.
3. The controller alone: ``JointController.update`` on the same run's states.

The loop's own cost per period (recording, the stamps, the argument lists) is what 1 leaves
after 2 and 3. The repeats of the three are interleaved (one of each in turn), every figure is
the median; the target (at least 25x real time) is reported, never enforced (exit status 0).
The last stdout line is one JSON object.

Run from the repository root::

    .venv/bin/python bench/closed_loop.py                 # 7 repeats of the 13 s run
    .venv/bin/python bench/closed_loop.py --repeats 3     # quick look
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from lca_control.controller import JointController
from lca_sim.analysis.closed_loop import ClosedLoop, ClosedLoopConfig, ClosedLoopResult
from lca_sim.batch.closed_loop_config import load_config
from lca_sim.output import strict_json

REPO_ROOT = Path(__file__).resolve().parent.parent
ROS_CONFIG = REPO_ROOT / "config" / "ros"
DURATION_S = 13.0  # Fig. 15: 1 s still, the 10 s ramp, 2 s after it
TARGET_RTF = 25.0
DEFAULT_REPEATS = 7


def _plant_alone(loop: ClosedLoop, commands: np.ndarray) -> Callable[[], float]:
    """A replay of `commands` into the loop's plant, period by period; returns its wall time."""
    config = loop.config
    sim, plant = loop.sim, loop.plant
    axes = sim.axis_names
    rows = [list(row) for row in commands[:-1]]  # the last command is never applied

    def replay() -> float:
        sim.reset(position=dict(zip(axes, config.initial_position, strict=True)))
        plant.hold_zero()
        period, end, done = config.substeps_per_period, config.end_steps, 0
        start = time.perf_counter()
        for row in rows:
            plant.command(row)
            steps = min(period, end - done)
            plant.advance(steps)
            done += steps
        return time.perf_counter() - start

    return replay


def _controller_alone(config: ClosedLoopConfig, result: ClosedLoopResult) -> Callable[[], float]:
    """The run's states fed to a fresh controller core; returns its wall time."""
    index = [result.axes.index(j) for j in config.controller.joints]
    states = [
        (float(t), [float(x) for x in q[index]], [float(x) for x in v[index]])
        for t, q, v in zip(result.time_s, result.position, result.velocity, strict=True)
    ]
    currents = None if config.command_interface == "current" else result.current_a[:, index]

    def control() -> float:
        controller = JointController(config.controller)
        start = time.perf_counter()
        for k, (t_s, positions, velocities) in enumerate(states):
            amps = None if currents is None else currents[k].tolist()
            controller.update(t_s, positions, velocities, amps)
        return time.perf_counter() - start

    return control


def main(argv: Sequence[str] | None = None) -> int:
    """Time the composed loop, the plant alone and the controller alone; end with one JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=DEFAULT_REPEATS)
    parser.add_argument("--duration-s", type=float, default=DURATION_S)
    parser.add_argument("--controller-config", type=Path, default=ROS_CONFIG / "controller.yaml")
    parser.add_argument("--simulator-config", type=Path, default=ROS_CONFIG / "simulator.yaml")
    args = parser.parse_args(argv)

    config = load_config(args.controller_config, args.simulator_config, args.duration_s)
    built = time.perf_counter()
    loop = ClosedLoop(config)
    build_s = time.perf_counter() - built
    result = loop.run()  # also the warm-up: nothing is compiled or loaded in a timed repeat
    periods = len(result.time_s) - 1
    print(
        f"composed closed loop: {len(config.robot.axes)} axes, {config.command_interface} "
        f"commands, control period {config.control_period_s * 1e3:g} ms, model step "
        f"{config.dt_s * 1e3:g} ms (rigid-body terms every {config.plant.rigid_body_update_steps} "
        f"steps), {config.controller.reference_source} on {config.controller.profile_joint}, "
        f"{config.duration_s:g} s = {periods} periods; built in {build_s:.2f} s"
    )
    tracking = result.velocity_tracking(config.controller, config.controller.profile_joint)
    print(tracking.describe())  # the figure lca-hil run and lca-hil fig15 report

    replay = _plant_alone(loop, result.command)
    replay()
    replayed_same = bool(np.array_equal(loop.sim.state_array[0], result.position[-1]))
    control = _controller_alone(config, result)

    def composed() -> float:
        start = time.perf_counter()
        loop.run()
        return time.perf_counter() - start

    walls: dict[str, list[float]] = {"loop": [], "plant": [], "controller": []}
    for _ in range(args.repeats):
        walls["loop"].append(composed())
        walls["plant"].append(replay())
        walls["controller"].append(control())
    loop_s = statistics.median(walls["loop"])
    plant_s = statistics.median(walls["plant"])
    controller_s = statistics.median(walls["controller"])
    duration_s = float(result.time_s[-1])
    rtf = duration_s / loop_s
    plant_rtf = duration_s / plant_s
    per_period_us = 1e6 / periods
    overhead_us = (loop_s - plant_s - controller_s) * per_period_us
    met = rtf >= TARGET_RTF

    print(f"\ntiming (median of {args.repeats} interleaved repeats)")
    low = min(walls["loop"])
    print(f"  composed loop     {loop_s:7.4f} s  {rtf:7.1f}x real time (min {low:.4f} s)")
    plant_us = plant_s * per_period_us
    print(
        f"  plant alone       {plant_s:7.4f} s  {plant_rtf:7.1f}x real time, "
        f"{plant_us:.1f} us/period"
    )
    print(
        f"  controller alone  {controller_s:7.4f} s  {controller_s * per_period_us:.1f} us/period"
    )
    print(f"  the loop itself   {overhead_us:.1f} us/period (composed - plant - controller)")
    print(f"  replayed plant ends in the same state: {replayed_same}")
    print(f"\ntarget >= {TARGET_RTF:g}x real time: {'met' if met else 'NOT met'}")

    record: dict[str, object] = {
        "bench": "closed_loop",
        "realtime_factor": round(rtf, 2),
        "target": TARGET_RTF,
        "met": met,
        "wall_s": round(loop_s, 5),
        "wall_min_s": round(min(walls["loop"]), 5),
        "plant_alone_realtime_factor": round(plant_rtf, 2),
        "plant_us_per_period": round(plant_s * per_period_us, 2),
        "controller_us_per_period": round(controller_s * per_period_us, 2),
        "loop_overhead_us_per_period": round(overhead_us, 2),
        "replayed_plant_same_state": replayed_same,
        **tracking.figures(),
        "tracking_window_s": [tracking.from_s, tracking.to_s],
        "duration_s": duration_s,
        "periods": periods,
        "axes": len(config.robot.axes),
        "command_interface": config.command_interface,
        "control_period_s": config.control_period_s,
        "dt_s": config.dt_s,
        "rigid_body_update_steps": config.plant.rigid_body_update_steps,
        "build_s": round(build_s, 3),
        "repeats": args.repeats,
        "timing": "median of interleaved repeats, one process, one core",
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
    print(strict_json(record, indent=None))  # strict: NaN/inf as null, with why
    return 0


if __name__ == "__main__":
    sys.exit(main())
