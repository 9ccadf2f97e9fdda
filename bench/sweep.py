"""Benchmark: `lca-hil sweep`'s throughput on Dask against a plain loop, and its scaling.

What it measures, on Fig. 15's 13-s closed-loop point (config/ros/*.yaml: the 4-axis robot,
the cascade on current commands at a 4 ms control period, the plant at 0.1 ms with the rigid-body
terms held for 1 ms), `--points` times (the same work under distinct keys):

1. the composed closed loop's real-time factor: one `ClosedLoop.run` of the 13-s point (the
   model built outside the timing), median of `--repeats`;
2. a plain loop: `run_point` on every point in this process, one after the other: the work a
   sweep cannot avoid;
3. the sweep on a local Dask cluster of 1 worker, then of one worker per core (127.0.0.1, one
   single-threaded process each, the compiled kernel loaded once per worker before the timing):
   `run_tasks`, the same code as `lca-hil sweep` (each point written to its Parquet file as it
   finishes); the clusters' start-up is reported apart. 2 and 3 are repeated `--repeats`
   times, interleaved, and each figure is the median (the machine is shared).

Figures: points per second with 1 worker and with all cores, the scaling ratio (target >= 1.8
from 1 to 2 workers), and Dask's overhead per point against the plain loop (1 worker's wall time
per point over the plain loop's, minus 1; target under 5 %). Last, the model step against
MuJoCo's: bench/model_step.py's measurement, run here (`model_step_*` keys; target <= 1.0).
Targets are reported, never enforced (exit status 0). The last stdout line is one JSON object.

Run from the repository root::

    .venv/bin/python bench/sweep.py                  # 24 points of 13 s
    .venv/bin/python bench/sweep.py --points 8       # quick look
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lca_sim.analysis.closed_loop import ClosedLoop, ClosedLoopConfig
from lca_sim.analysis.metrics import parse_metric
from lca_sim.analysis.sweep import PointTask, run_point
from lca_sim.cli.output import strict_json
from lca_sim.cli.run import load_config
from lca_sim.cli.sweep import PointStore, Progress, dask_client, run_tasks, warm_up

REPO_ROOT = Path(__file__).resolve().parent.parent
ROS_CONFIG = REPO_ROOT / "config" / "ros"
DURATION_S = 13.0
TARGET_SCALING = 1.8
TARGET_OVERHEAD = 0.05


def _tasks(n: int, tag: str = "") -> list[PointTask]:
    config = load_config(ROS_CONFIG / "controller.yaml", ROS_CONFIG / "simulator.yaml", DURATION_S)
    metrics = tuple(
        parse_metric(m, "bench", f"metrics[{i}]", "pivot")
        for i, m in enumerate(
            [
                {"metric": "peak_current_a"},
                {"metric": "tracking_error_rms"},
                {"metric": "state_change_position", "states": ["load_driving"]},
            ]
        )
    )
    return [
        PointTask(i, 0, (("i", i),), f"bench{tag}-{i:04d}", config, metrics, None) for i in range(n)
    ]


def _realtime_factor(tasks: Sequence[PointTask], repeats: int) -> float:
    run = tasks[0].run
    assert isinstance(run, ClosedLoopConfig)
    loop = ClosedLoop(run)
    loop.run()  # the kernel's first call (numba's cache) outside the timing
    walls = []
    for _ in range(repeats):
        start = time.perf_counter()
        loop.run()
        walls.append(time.perf_counter() - start)
    return DURATION_S / statistics.median(walls)


def _plain_loop(tasks: Sequence[PointTask]) -> float:
    start = time.perf_counter()
    for task in tasks:
        run_point(task)
    return time.perf_counter() - start


def _dask(client: Any, tasks: Sequence[PointTask]) -> float:
    """The sweep's wall time on the client's cluster, s (each point written as it finishes)."""
    with tempfile.TemporaryDirectory(prefix="lca-bench-sweep-") as tmp:
        store = PointStore(Path(tmp))
        start = time.perf_counter()
        stats = run_tasks(client, tasks, store, Progress(len(tasks), 0, None))
        wall_s = time.perf_counter() - start
    assert stats.failed == 0 and stats.computed == len(tasks)
    return wall_s


def _model_step(steps: int, repeats: int) -> dict[str, object]:
    """bench/model_step.py's record (full step against mj_step), its printout kept short."""
    spec = importlib.util.spec_from_file_location(
        "model_step", Path(__file__).with_name("model_step.py")
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    with contextlib.redirect_stdout(io.StringIO()):
        record: dict[str, object] = module.measure(steps, repeats)
    print(
        f"model step: {record['full_step_us']} us, mj_step {record['mj_step_us']} us, ratio "
        f"{record['ratio_full_to_mj']} (target <= {record['target_ratio_max']}: "
        f"{'met' if record['meets_ratio_target'] else 'not met'})"
    )
    return record


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark; print its figures and one JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=24, help="13-s points per measurement")
    parser.add_argument("--repeats", type=int, default=3, help="repeats of every measurement")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="all cores")
    parser.add_argument(
        "--model-steps", type=int, default=20_000, help="calls per repeat of the model step bench"
    )
    args = parser.parse_args(argv)
    tasks = _tasks(args.points)
    rtf = _realtime_factor(tasks, args.repeats)
    print(f"composed closed loop: {rtf:.1f}x real time ({DURATION_S:g} s point)")
    run_point(tasks[0])  # warm this process too
    plain, one, all_ = [], [], []
    with contextlib.ExitStack() as stack:
        clients = []
        setup_s = {}
        for workers in (1, args.workers):
            start = time.perf_counter()
            client = stack.enter_context(dask_client(None, workers))
            client.run(warm_up, tasks[0])
            setup_s[str(workers)] = time.perf_counter() - start
            clients.append(client)
        for r in range(args.repeats):  # interleaved: a busy spell of the machine hits all three
            plain.append(_plain_loop(_tasks(args.points, f"p{r}")))
            one.append(_dask(clients[0], _tasks(args.points, f"a{r}")))
            all_.append(_dask(clients[1], _tasks(args.points, f"b{r}")))
    plain_s, wall1, wall_n = (statistics.median(x) for x in (plain, one, all_))
    n = len(tasks)
    print(
        f"plain loop: {n} points in {plain_s:.2f} s ({n / plain_s:.2f}/s), median of {args.repeats}"
    )
    print(f"dask, 1 worker: {wall1:.2f} s ({n / wall1:.2f}/s; start-up {setup_s['1']:.1f} s)")
    print(
        f"dask, {args.workers} workers: {wall_n:.2f} s ({n / wall_n:.2f}/s; "
        f"start-up {setup_s[str(args.workers)]:.1f} s)"
    )
    scaling = wall1 / wall_n
    overhead = wall1 / plain_s - 1.0
    per_point_ms = (wall1 - plain_s) / len(tasks) * 1e3
    print(
        f"scaling 1 -> {args.workers} workers: {scaling:.2f}x (target >= {TARGET_SCALING}); "
        f"Dask overhead {overhead * 100:.1f} % ({per_point_ms:.1f} ms per point; target < "
        f"{TARGET_OVERHEAD * 100:.0f} %)"
    )
    model = _model_step(args.model_steps, max(args.repeats, 5))
    result = {
        "bench": "sweep",
        "points": len(tasks),
        "point_duration_s": DURATION_S,
        "composed_realtime_factor": rtf,
        "plain_loop_points_per_s": len(tasks) / plain_s,
        "points_per_s_1_worker": len(tasks) / wall1,
        "workers": args.workers,
        "points_per_s_all_workers": len(tasks) / wall_n,
        "scaling_ratio": scaling,
        "scaling_target": TARGET_SCALING,
        "dask_overhead_fraction": overhead,
        "dask_overhead_ms_per_point": per_point_ms,
        "overhead_target": TARGET_OVERHEAD,
        "cluster_startup_s": setup_s,
        "model_step_ratio_to_mj": model["ratio_full_to_mj"],
        "model_step_ratio_to_mj_cpu": model["ratio_full_to_mj_cpu"],
        "model_step_us": model["full_step_us"],
        "mj_step_us": model["mj_step_us"],
        "model_step_target_ratio_max": model["target_ratio_max"],
        "model_step_meets_target": model["meets_ratio_target"],
        "repeats": args.repeats,
        "wall_s": {"plain": plain, "1_worker": one, "all_workers": all_},
        "cpu_count": os.cpu_count(),
        "load_average": os.getloadavg()[0],
        "python": platform.python_version(),
    }
    print(strict_json(result, indent=None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
