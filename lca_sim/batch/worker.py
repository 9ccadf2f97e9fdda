"""What a Dask worker runs: a point timed on its worker, and the kernel warmed up before."""

from __future__ import annotations

import dataclasses
import sys
import time

from lca_sim.analysis.closed_loop import ClosedLoop, ClosedLoopConfig
from lca_sim.batch.compute import run_point
from lca_sim.batch.tasks import PointOutcome, PointTask
from lca_sim.batch.version import package_version

# A worker computes a point in one thread while its event loop (heartbeats, transfers) waits in
# another; with Python's 5 ms GIL switch interval that loop takes the GIL back every few ms and
# a 13-s closed-loop point runs about 8 % slower than in a plain loop. 50 ms leaves the loop
# answering well within Dask's timeouts (seconds) and the point at the plain loop's speed
# (bench/sweep.py).
WORKER_SWITCH_INTERVAL_S = 0.05


def timed_point(task: PointTask) -> tuple[PointOutcome, float]:
    """`run_point` and its wall time on the worker, s (what the workers run).

    Raises:
        RuntimeError: this worker's lca_hil is not the one the point's key was made with (a
            cluster's workers must run the driver's code, docs/sweeps.md).
    """
    version = package_version()
    if task.version and task.version != version:
        raise RuntimeError(
            f"this worker runs lca_hil {version}, the sweep {task.version}: install the "
            "driver's lca_hil on every worker"
        )
    sys.setswitchinterval(WORKER_SWITCH_INTERVAL_S)
    start = time.perf_counter()
    outcome = run_point(task)
    return outcome, time.perf_counter() - start


def warm_up(task: PointTask) -> bool:
    """Load the compiled kernel in this worker (numba's on-disk cache) before the points."""
    if isinstance(task.run, ClosedLoopConfig):
        short = dataclasses.replace(task.run, duration_s=task.run.control_period_s)
        ClosedLoop(short).run()
    else:
        from lca_sim.model.simulator import Simulator  # noqa: PLC0415

        sim = Simulator(task.run.robot)
        sim.step([0.0] * sim.n_axes)
    return True
