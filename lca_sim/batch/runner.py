"""A sweep run on Dask: each point written as it finishes, retried once, the tables merged.

A point that raises, or whose worker dies, is submitted once more, then recorded as failed
with its reason; the sweep goes on. Wall times and attempts go to DIR/run_log.json.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

from lca_sim.batch.spec import SweepSpec
from lca_sim.batch.store import (
    LOG,
    OK,
    RECORD,
    PointStore,
    merge,
    outcome_row,
    sweep_record,
)
from lca_sim.batch.tasks import PointOutcome, PointTask
from lca_sim.batch.worker import timed_point, warm_up
from lca_sim.output import write_json

ATTEMPTS = 2  # a point is submitted at most twice: once, and once more after a failure


class Progress:
    """A progress line on stderr: points done, failed, and the time left."""

    def __init__(
        self, total: int, reused: int, stream: IO[str] | None, prog: str = "lca-hil sweep"
    ) -> None:
        self.total, self.reused, self.stream, self.prog = total, reused, stream, prog
        self.done = self.failed = 0
        self.start = time.perf_counter()
        self.tty = bool(stream is not None and stream.isatty())
        self._last_shown = -1.0

    def update(self, *, failed: bool = False, points: int = 1) -> None:
        """One more computation finished (or failed), for `points` points of one key."""
        self.done += points
        self.failed += points if failed else 0
        self.show()

    def show(self, final: bool = False) -> None:
        """Draw the line (on a terminal every time, in a log every 10 % or so)."""
        if self.stream is None:
            return
        todo = self.total - self.reused
        elapsed = time.perf_counter() - self.start
        left = elapsed / self.done * (todo - self.done) if self.done else math.nan
        finished = self.reused + self.done
        width = 30
        filled = int(width * finished / self.total) if self.total else width
        bar = "#" * filled + "." * (width - filled)
        eta = "?" if math.isnan(left) else f"{int(left) // 60}:{int(left) % 60:02d}"
        line = (
            f"{self.prog}: [{bar}] {finished}/{self.total} points ({self.reused} reused), "
            f"{self.failed} failed, {eta} left"
        )
        if self.tty:
            self.stream.write("\r" + line + ("\n" if final else ""))
        elif final or self.done == 1 or finished / self.total - self._last_shown >= 0.1:
            self._last_shown = finished / self.total
            self.stream.write(line + "\n")
        self.stream.flush()


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int) -> Iterator[Any]:
    """A client of `scheduler`, or of a local cluster on 127.0.0.1 (one process per worker).

    The local cluster's scheduler and its dashboard bind 127.0.0.1; each worker is a
    single-threaded process (the model holds the GIL), and a worker's death fails its point
    at once (allowed-failures 0) so that lca-hil's one retry is the only one (`run_tasks`
    retries a point whose worker died alone, so the points queued behind it are computed).
    """
    import dask  # noqa: PLC0415  (only when a sweep runs)
    from distributed import Client, LocalCluster  # noqa: PLC0415

    if scheduler is not None:
        with Client(scheduler, timeout="30s") as client:  # type: ignore[no-untyped-call]
            yield client
        return
    with (
        dask.config.set({"distributed.scheduler.allowed-failures": 0}),
        LocalCluster(  # type: ignore[no-untyped-call]
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address="127.0.0.1:0",
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,  # type: ignore[no-untyped-call]
    ):
        yield client


@dataclasses.dataclass
class RunStats:
    """What a run did, for run_log.json."""

    computed: int = 0
    failed: int = 0
    attempts: dict[int, int] = dataclasses.field(default_factory=dict)
    point_wall_s: dict[int, float] = dataclasses.field(default_factory=dict)
    errors: dict[int, str] = dataclasses.field(default_factory=dict)


def _reason(future: Any) -> str:
    """Why a future failed, in one line."""
    try:
        exc = future.exception()
    except Exception as err:  # a cancelled future raises here
        return f"{type(err).__name__}: {err}"
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    name = type(exc).__name__
    if name == "KilledWorker":
        return "KilledWorker: the worker running it died"
    return f"{name}: {text}" if text else name


def run_tasks(
    client: Any,
    tasks: Sequence[PointTask],
    store: PointStore,
    progress: Progress,
    function: Callable[[PointTask], tuple[PointOutcome, float]] = timed_point,
) -> RunStats:
    """Compute `tasks` on the client's cluster, writing each point as it finishes.

    Points of one key (two that resolve to one configuration, e.g. a value given twice) are
    computed once, by the first of them, and count for all. A point that raises is submitted
    once more at once. A point whose worker died is submitted once more after all the others,
    alone: Dask hands a worker more than one point, and those queued behind a point that kills
    its worker die with it, so the retry isolates the one that kills (it dies alone and is
    written as failed) from those that only shared its worker. A second failure is written as
    failed with its reason; the others go on.
    """
    from distributed import as_completed, wait  # noqa: PLC0415

    stats = RunStats()
    owner: dict[str, tuple[PointTask, int]] = {}
    queue = as_completed()  # type: ignore[no-untyped-call]
    alone: list[tuple[PointTask, int]] = []  # whose worker died: retried one at a time
    shares = collections.Counter(task.key for task in tasks)

    def submit(task: PointTask, attempt: int) -> Any:
        future = client.submit(function, task, key=f"lca-point-{task.key}-{attempt}", pure=False)
        owner[future.key] = (task, attempt)
        return future

    def settle(future: Any) -> None:
        task, attempt = owner.pop(future.key)
        stats.attempts[task.index] = attempt
        if future.status == "finished":
            outcome, wall_s = future.result()
            store.write(task.key, outcome_row(task, outcome, ""), outcome.trajectory)
            stats.computed += 1
            stats.point_wall_s[task.index] = wall_s
            progress.update(points=shares[task.key])
        elif attempt < ATTEMPTS:
            reason = _reason(future)
            stats.errors[task.index] = reason
            if reason.startswith("KilledWorker"):
                alone.append((task, attempt + 1))
            else:
                queue.add(submit(task, attempt + 1))  # type: ignore[no-untyped-call]
        else:
            reason = _reason(future)
            store.write(task.key, outcome_row(task, None, reason), None)
            stats.computed += 1
            stats.failed += 1
            stats.errors[task.index] = reason
            progress.update(failed=True, points=shares[task.key])
        future.release()

    first: dict[str, PointTask] = {}
    for task in tasks:
        first.setdefault(task.key, task)
    for task in first.values():
        queue.add(submit(task, 1))  # type: ignore[no-untyped-call]
    for future in queue:
        settle(future)
    for task, attempt in alone:
        future = submit(task, attempt)
        wait(future)  # type: ignore[no-untyped-call]
        settle(future)
    return stats


@dataclasses.dataclass(frozen=True, slots=True)
class SweepPlan:
    """A sweep validated whole, ready to run.

    Attributes:
        spec_path: the sweep YAML (copied into the output folder).
        spec: the validated spec.
        tasks: every point's task, by index.
        version: the version the points' keys were made with (`lca_sim.batch.version`).
        planned_s: the wall time it took to read the files and build the tasks, s.
    """

    spec_path: Path
    spec: SweepSpec
    tasks: tuple[PointTask, ...]
    version: str
    planned_s: float = 0.0


def run_plan(
    plan: SweepPlan,
    out: Path,
    scheduler: str | None = None,
    workers: int | None = None,
    stream: IO[str] | None = sys.stderr,
    function: Callable[[PointTask], tuple[PointOutcome, float]] = timed_point,
    client: Any = None,
) -> dict[str, Any]:
    """Run a planned sweep into `out` (see the module docstring); returns the run log.

    Args:
        plan: the sweep (`lca_sim.batch.plan.plan_sweep` reads it from its files).
        out: the output folder (created; its points are reused).
        scheduler: an existing Dask scheduler's address; None starts a local cluster.
        workers: local worker processes (default: one per core).
        stream: where the progress line goes (None: nowhere).
        function: what the workers run per point (tests swap it).
        client: an existing Dask client to use instead (tests).
    """
    start = time.perf_counter()
    spec, tasks, version = plan.spec, list(plan.tasks), plan.version
    store = PointStore(out)
    shutil.copyfile(plan.spec_path, out / "spec.yaml")
    write_json(out / RECORD, sweep_record(spec, len(tasks), version))
    pending = [t for t in tasks if store.status(t.key) != OK]
    n_workers = workers or os.cpu_count() or 1
    progress = Progress(len(tasks), len(tasks) - len(pending), stream)
    progress.show()
    stats = RunStats()
    setup_s = 0.0
    if pending:
        setup = time.perf_counter()
        with contextlib.ExitStack() as stack:
            if client is None:
                client = stack.enter_context(dask_client(scheduler, n_workers))
                client.run(warm_up, pending[0])
            setup_s = time.perf_counter() - setup
            stats = run_tasks(client, pending, store, progress, function)
    progress.show(final=True)
    failed = merge(spec, tasks, store, out)
    log = {
        "spec": str(plan.spec_path),
        "version": version,
        "scheduler": scheduler or "local",
        "workers": None if scheduler else n_workers,
        "points": len(tasks),
        "reused": len(tasks) - len(pending),
        "computed": stats.computed,
        # points whose key another point computed (one configuration, computed once)
        "shared": len(pending) - len({t.key for t in pending}),
        "computed_indices": sorted(stats.attempts),
        "failed": failed,
        "retried": {str(i): e for i, e in sorted(stats.errors.items())},
        "cluster_setup_s": setup_s,
        "wall_s": plan.planned_s + time.perf_counter() - start,
        "point_wall_s": {str(i): w for i, w in sorted(stats.point_wall_s.items())},
    }
    write_json(out / LOG, log)
    return log
