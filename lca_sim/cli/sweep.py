"""`lca-hil sweep`: run a sweep spec's points on Dask, resumably; plot its results.

    lca-hil sweep config/sweeps/gear_wear_pivot.yaml --out out/wear       # a local cluster
    lca-hil sweep SPEC --out DIR --workers 1                               # one worker process
    lca-hil sweep SPEC --out DIR --scheduler tcp://127.0.0.1:8786          # an existing cluster
    lca-hil sweep --plot DIR                                               # PNGs of DIR's table

The spec is validated whole, every point's configuration built, before anything runs: a bad
spec is one error line naming its key (exit 2). Each point is keyed by a hash of its resolved
configuration and the package version; DIR/points/ holds one small Parquet file per finished
point, written as it finishes, so a rerun computes only the points without one (a failed point
is computed again). At the end the points are merged into DIR/results.parquet (a row per point,
by index: parameters, seed, metrics, status, error; no timing, so the same spec gives the same
table on any number of workers) and DIR/trajectories.parquet when the spec keeps trajectories.
Wall times and attempts go to DIR/run_log.json. A point that raises, or whose worker dies, is
submitted once more, then recorded as failed with its reason; the sweep goes on (exit 1 if a
point failed). docs/sweeps.md has the spec format and the metric library.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import dataclasses
import hashlib
import importlib.metadata
import itertools
import json
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

import lca_control
import lca_sim
from lca_control.parameters import ParameterError
from lca_sim.analysis.closed_loop import ClosedLoop, ClosedLoopConfig
from lca_sim.analysis.metrics import METRICS
from lca_sim.analysis.sweep import PointOutcome, PointTask, build_task, run_point
from lca_sim.analysis.sweep_spec import Documents, SweepSpec, expand_points, parse_spec
from lca_sim.cli.output import atomic_path, save_png, write_json
from lca_sim.cli.plotting import metric_label, metric_unit
from lca_sim.cli.run import closed_loop_config, file_ref, node_parameters
from lca_sim.config.loader import config_dir, read_robot_document, read_yaml, resolve
from lca_sim.config.simulator_params import validate_simulator_params
from lca_sim.errors import EXIT_FAILED, EXIT_OK, ConfigError, OutputError, run_guarded
from lca_sim.model.faults import (
    FAULT_SCHEDULE,
    is_fault_parameter,
    parse_fault_schedule,
    schedule_entries,
    standing_faults,
)
from lca_sim.model.params import RobotParams

PROG = "lca-hil sweep"
POINTS_DIR = "points"
RESULTS = "results.parquet"
TRAJECTORIES = "trajectories.parquet"
RECORD = "sweep.json"
LOG = "run_log.json"
ATTEMPTS = 2  # a point is submitted at most twice: once, and once more after a failure
# A worker computes a point in one thread while its event loop (heartbeats, transfers) waits in
# another; with Python's 5 ms GIL switch interval that loop takes the GIL back every few ms and
# a 13-s closed-loop point runs about 8 % slower than in a plain loop. 50 ms leaves the loop
# answering well within Dask's timeouts (seconds) and the point at the plain loop's speed
# (bench/sweep.py).
WORKER_SWITCH_INTERVAL_S = 0.05
OK, FAILED = "ok", "failed"


def _code_hash() -> str:
    """SHA-256 (12 hex) of every module of lca_sim and lca_control as this process loaded them.

    Taken when this module is imported, so a long-lived worker reports the code it runs, not
    what a later upgrade put on its disk.
    """
    digest = hashlib.sha256()
    for package in (lca_control, lca_sim):
        root = Path(str(package.__file__)).resolve().parent
        for module in sorted(root.rglob("*.py")):
            digest.update(module.relative_to(root.parent).as_posix().encode())
            digest.update(module.read_bytes())
    return digest.hexdigest()[:12]


_CODE_HASH = _code_hash()


def package_version() -> str:
    """lca_hil's version and a hash of its code (part of every point's key).

    `<release>+code.<12 hex>`: the installed release, and the SHA-256 of every module of
    lca_sim and lca_control when this process loaded them (`_code_hash`). The release alone is
    not bumped by every change of the model, and a result of older code must not be taken for a
    result of this one; nor may a worker with other code compute a point (`timed_point`
    refuses it).
    """
    try:
        release = importlib.metadata.version("lca_hil")
    except importlib.metadata.PackageNotFoundError:
        release = "0+unknown"
    return f"{release}+code.{_CODE_HASH}"


# --- the spec and its documents ----------------------------------------------------------------


def load_spec(spec_path: Path) -> tuple[SweepSpec, Documents]:
    """The validated spec and the base documents it names.

    Raises:
        ConfigError: the spec (or a file it names), the key, what was expected.
    """
    spec = parse_spec(read_yaml(spec_path), str(spec_path))
    base = spec.base
    controller: dict[str, Any] = {}
    simulator: dict[str, Any] = {}
    scenario: Any = {}
    faults: tuple[Any, ...] = ()
    faults_source = ""
    ros = config_dir() / "ros"
    if spec.kind == "closed_loop":
        controller_path = (
            file_ref(base["controller"], spec_path, "ros", "base.controller")
            if "controller" in base
            else ros / "controller.yaml"
        )
        simulator_path = (
            file_ref(base["simulator"], spec_path, "ros", "base.simulator")
            if "simulator" in base
            else ros / "simulator.yaml"
        )
        controller = node_parameters(controller_path, "controller")
        simulator = node_parameters(simulator_path, "simulator")
        faults, faults_source = _fault_schedule(base, simulator, spec_path, simulator_path)
    if spec.kind == "open_loop":
        if "scenario" not in base:
            raise ConfigError(spec.source, "base.scenario", "missing (an open-loop scenario)")
        scenario = read_yaml(file_ref(base["scenario"], spec_path, "scenarios", "base.scenario"))
        if not isinstance(scenario, Mapping):
            raise ConfigError(spec.source, "base.scenario", "expected a scenario document")
    urdf_xml, robot_doc = _robot(base, simulator, spec_path)
    documents = Documents(
        base=dict(base),
        robot=dict(robot_doc),
        urdf_xml=urdf_xml,
        controller=controller,
        simulator=simulator,
        scenario=dict(scenario),
        faults=faults,
        faults_source=faults_source,
    )
    return spec, documents


def _robot(
    base: Mapping[str, Any], simulator: Mapping[str, Any], spec_path: Path
) -> tuple[str, Mapping[str, Any]]:
    """The robot's URDF text and its document (after its `base:` merge).

    `base.robot` (a shipped name or a path from the spec's folder); else, closed loop, the
    simulator params' `robot`, as the node and `lca-hil run` take it; else `default`.

    Raises:
        ConfigError: a missing or unreadable robot or URDF.
    """
    if "robot" in base:
        robot_path = file_ref(base["robot"], spec_path, "robots", "base.robot")
    elif isinstance(simulator.get("robot"), str) and simulator["robot"]:
        robot_path = resolve(simulator["robot"], "robots")
    else:
        robot_path = resolve("default", "robots")
    robot_doc, urdf_xml = read_robot_document(robot_path)
    return urdf_xml, robot_doc


def _fault_schedule(
    base: Mapping[str, Any], simulator: Mapping[str, Any], spec_path: Path, simulator_path: Path
) -> tuple[tuple[Any, ...], str]:
    """A closed-loop run's fault schedule entries and file: `base.faults`, else the simulator's.

    `base.faults` (a shipped name in config/faults/ or a path from the spec's folder) wins over
    the simulator params file's `fault_schedule`, as `lca-hil run --faults` does. The entries
    are checked against the robot when each point is built (`closed_loop_builder`).

    Raises:
        ConfigError: a missing file, or one that is not a schedule (a mapping with a list).
    """
    if "faults" in base:
        path = file_ref(base["faults"], spec_path, "faults", "base.faults")
    elif simulator.get(FAULT_SCHEDULE):
        ref = simulator[FAULT_SCHEDULE]
        if not isinstance(ref, str):
            raise ConfigError(str(simulator_path), FAULT_SCHEDULE, "expected a schedule's name")
        path = resolve(ref, "faults")
    else:
        return (), ""
    return tuple(schedule_entries(read_yaml(path), str(path))), str(path)


def closed_loop_builder(documents: Documents, robot: RobotParams) -> ClosedLoopConfig:
    """A closed-loop point's config: the nodes' parameters validated as the nodes do.

    The spec's robot replaces the simulator's `robot`; `base.duration_s` (default: the
    simulator's `lockstep_end_s`) is the run's length. The faults are those `lca-hil run`
    applies: the simulator's standing `faults.<joint>.<kind>` values and the schedule
    (`_fault_schedule`), each entry checked against the point's robot.

    Raises:
        ParameterError: a node parameter the node would refuse (a fault value included).
        ConfigError: a bad schedule entry, named by its file and key.
    """
    plant_values = {k: v for k, v in documents.simulator.items() if not is_fault_parameter(k)}
    simulator = validate_simulator_params(plant_values)
    duration = documents.base.get("duration_s", simulator.lockstep_end_s)
    if isinstance(duration, bool) or not isinstance(duration, int | float) or duration <= 0:
        raise ParameterError("duration_s", "a run's length > 0 (base.duration_s)", duration)
    config = closed_loop_config(
        documents.controller, documents.simulator, float(duration), robot=robot
    )
    faults = standing_faults(documents.simulator, robot.axis_names)
    if documents.faults:
        schedule = {"faults": list(documents.faults)}
        faults += parse_fault_schedule(schedule, documents.faults_source, robot.axis_names)
    return dataclasses.replace(config, faults=faults) if faults else config


def build_tasks(spec: SweepSpec, documents: Documents, version: str) -> list[PointTask]:
    """Every point's task, validated; the first bad point is one error naming its values.

    Raises:
        ConfigError: the spec, the point and what is wrong with it.
    """
    tasks = []
    for point in expand_points(spec):
        try:
            tasks.append(build_task(spec, documents, point, version, closed_loop_builder))
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


def _pyarrow() -> tuple[Any, Any]:
    """The modules pyarrow and pyarrow.parquet, imported when a sweep reads or writes a table."""
    import pyarrow as pa  # type: ignore[import-untyped]  # noqa: PLC0415
    import pyarrow.parquet as pq  # type: ignore[import-untyped]  # noqa: PLC0415

    return pa, pq


# --- the store ---------------------------------------------------------------------------------


class PointStore:
    """DIR/points/: one Parquet file per finished point, named by its key, written atomically."""

    def __init__(self, out: Path) -> None:
        self.folder = out / POINTS_DIR
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create {self.folder}: {exc.strerror}") from exc

    def path(self, key: str, trajectory: bool = False) -> Path:
        """A point's file (or its trajectory's)."""
        return self.folder / (f"{key}.trajectory.parquet" if trajectory else f"{key}.parquet")

    def status(self, key: str) -> str | None:
        """`ok`, `failed`, or None when the point has no readable file."""
        _pa, pq = _pyarrow()

        path = self.path(key)
        if not path.is_file():
            return None
        try:
            return str(pq.read_table(path, columns=["status"]).column(0)[0].as_py())
        except (OSError, ValueError, KeyError, IndexError):
            return None  # a damaged file: the point is computed again

    def write(
        self, key: str, row: Mapping[str, Any], trajectory: Mapping[str, list[Any]] | None
    ) -> None:
        """A finished point: its trajectory first, then its row (the row marks it done)."""
        pa, pq = _pyarrow()

        if trajectory is not None:
            with atomic_path(self.path(key, trajectory=True)) as tmp:
                pq.write_table(pa.table(dict(trajectory)), tmp)
        with atomic_path(self.path(key)) as tmp:
            pq.write_table(pa.table({k: [v] for k, v in row.items()}), tmp)

    def read(self, key: str, trajectory: bool = False) -> Any:
        """A point's table."""
        _pa, pq = _pyarrow()

        return pq.read_table(self.path(key, trajectory))


def _outcome_row(task: PointTask, outcome: PointOutcome | None, error: str) -> dict[str, Any]:
    row: dict[str, Any] = {"key": task.key, "status": OK if outcome else FAILED, "error": error}
    for metric in task.metrics:
        row[metric.name] = outcome.metrics[metric.name] if outcome else math.nan
    return row


# --- running on Dask ---------------------------------------------------------------------------


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


class Progress:
    """A progress line on stderr: points done, failed, and the time left."""

    def __init__(self, total: int, reused: int, stream: IO[str] | None) -> None:
        self.total, self.reused, self.stream = total, reused, stream
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
            f"{PROG}: [{bar}] {finished}/{self.total} points ({self.reused} reused), "
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
            store.write(task.key, _outcome_row(task, outcome, ""), outcome.trajectory)
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
            store.write(task.key, _outcome_row(task, None, reason), None)
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


# --- results -----------------------------------------------------------------------------------


def merge(spec: SweepSpec, tasks: Sequence[PointTask], store: PointStore, out: Path) -> int:
    """DIR/results.parquet (and trajectories.parquet) from the points, by index.

    Returns the number of failed points.
    """
    pa, pq = _pyarrow()

    columns: dict[str, list[Any]] = {"index": [], "seed": []}
    names = [p.name for p in spec.parameters]
    for name in names:
        columns[name] = []
    metric_names = [m.name for m in spec.metrics]
    for name in [*metric_names, "status", "error", "key"]:
        columns[name] = []
    trajectories = []
    failed = 0
    for task in sorted(tasks, key=lambda t: t.index):
        row = store.read(task.key).to_pylist()[0]
        columns["index"].append(task.index)
        columns["seed"].append(task.seed)
        values = dict(task.values)
        for name in names:
            columns[name].append(values[name])
        for name in [*metric_names, "status", "error", "key"]:
            columns[name].append(row[name])
        failed += row["status"] != OK
        if spec.trajectories is not None and row["status"] == OK:
            table = store.read(task.key, trajectory=True)
            index = pa.array([task.index] * table.num_rows, type=pa.int64())
            trajectories.append(table.add_column(0, "index", index))
    schema = {name: pa.float64() for name in metric_names}
    table = pa.table(
        {
            k: pa.array(v, type=schema.get(k, pa.int64() if k in ("index", "seed") else None))
            for k, v in columns.items()
        }
    )
    with atomic_path(out / RESULTS) as tmp:
        pq.write_table(table, tmp)
    if trajectories:
        with atomic_path(out / TRAJECTORIES) as tmp:
            pq.write_table(pa.concat_tables(trajectories), tmp)
    return failed


def sweep_record(spec: SweepSpec, n_points: int, version: str) -> dict[str, Any]:
    """DIR/sweep.json: what the plots need to know of the spec."""
    return {
        "spec": spec.source,
        "description": spec.description,
        "kind": spec.kind,
        "sampling": spec.sampling,
        "points": n_points,
        "seed": spec.seed,
        "version": version,
        "parameters": [
            {
                "name": p.name,
                "paths": list(p.paths),
                "mode": p.mode,
                "values": list(p.values) if p.values is not None else None,
            }
            for p in spec.parameters
        ],
        "metrics": [{**m.as_dict(), "unit": METRICS[m.metric].unit} for m in spec.metrics],
        "plot": dict(spec.plot),
    }


def run_sweep(
    spec_path: Path,
    out: Path,
    scheduler: str | None = None,
    workers: int | None = None,
    stream: IO[str] | None = sys.stderr,
    function: Callable[[PointTask], tuple[PointOutcome, float]] = timed_point,
    client: Any = None,
) -> dict[str, Any]:
    """Run a sweep into `out` (see the module docstring); returns the run log.

    Args:
        spec_path: the sweep YAML.
        out: the output folder (created; its points are reused).
        scheduler: an existing Dask scheduler's address; None starts a local cluster.
        workers: local worker processes (default: one per core).
        stream: where the progress line goes (None: nowhere).
        function: what the workers run per point (tests swap it).
        client: an existing Dask client to use instead (tests).

    Raises:
        ConfigError: a bad spec, before anything runs.
    """
    start = time.perf_counter()
    version = package_version()
    spec, documents = load_spec(spec_path)
    tasks = build_tasks(spec, documents, version)
    store = PointStore(out)
    shutil.copyfile(spec_path, out / "spec.yaml")
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
        "spec": str(spec_path),
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
        "wall_s": time.perf_counter() - start,
        "point_wall_s": {str(i): w for i, w in sorted(stats.point_wall_s.items())},
    }
    write_json(out / LOG, log)
    return log


# --- plots -------------------------------------------------------------------------------------


def plot_sweep(out: Path) -> list[Path]:
    """PNGs of DIR's results: a metric over one or two grid parameters, histograms for random.

    One figure per metric in DIR/plots/: a line over one varying parameter; over two, lines
    (one per value of `plot.lines_by`, of the parameter with at most 4 values, or of the one
    that is not a number) or a heatmap; a histogram of the metric for a random sweep.
    `plot.mark` ({parameter: value}) marks a point (e.g. the paper's gains) on a heatmap.

    Raises:
        OutputError: DIR has no results, or a grid these plots cannot draw (more than two
            varying parameters, or two that are not numbers): the figure would mix points.
    """
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    _pa, pq = _pyarrow()

    if not (out / RESULTS).is_file() or not (out / RECORD).is_file():
        raise OutputError(f"{out}: no {RESULTS} and {RECORD} (run the sweep first)")
    record = json.loads((out / RECORD).read_text(encoding="utf-8"))
    rows = pq.read_table(out / RESULTS).to_pylist()
    ok = [r for r in rows if r["status"] == OK]
    written = []
    varying = [
        p["name"] for p in record["parameters"] if p["values"] is None or len(p["values"]) > 1
    ]
    if record["sampling"] != "random" and len(varying) > 2:
        raise OutputError(
            f"{out}: the plots draw a metric over one or two parameters, this grid varies "
            f"{len(varying)} ({', '.join(varying)}): read {RESULTS} with pandas or pyarrow"
        )
    title = Path(record["spec"]).stem
    degrees = set(record["plot"].get("degrees", []))
    for metric in record["metrics"]:
        name = metric["name"]
        scale, unit = metric_unit(metric["unit"], metric.get("axis"), _REFERENCE[record["kind"]])
        if name in degrees:  # plot.degrees: a radian metric drawn in degrees
            scale, unit = 180.0 / math.pi, "deg"
        label = metric_label(name, unit)
        fig, ax = plt.subplots(figsize=(7.0, 4.6))
        if scale != 1.0:
            ok = [{**r, name: None if r[name] is None else r[name] * scale} for r in ok]
        if record["sampling"] == "random" or not varying:
            _histogram(ax, [r[name] for r in ok], label, len(rows) - len(ok))
        elif len(varying) == 1:
            _line(ax, ok, varying[0], name, label)
        else:
            _two(ax, fig, ok, record, varying[:2], name, label)
        ax.set_title(f"{title}: {name}")
        path = out / "plots" / f"{name}.png"
        save_png(fig, path)
        plt.close(fig)
        written.append(path)
    return written


# What the reference of each kind of run is for (the tracking metrics' unit).
_REFERENCE = {"closed_loop": "velocity", "current_step": "current_a", "open_loop": ""}


def _finite(values: Sequence[Any]) -> list[float]:
    return [float(v) for v in values if v is not None and math.isfinite(float(v))]


def _histogram(ax: Any, values: Sequence[Any], label: str, failed: int) -> None:
    import numpy as np  # noqa: PLC0415

    data = _finite(values)
    ax.hist(data, bins=min(50, max(5, len(data) // 20)), color="tab:blue", alpha=0.8)
    if data:
        q = np.percentile(data, [5, 50, 95])
        for x, style in zip(q, (":", "-", ":"), strict=True):
            ax.axvline(x, color="k", linestyle=style, linewidth=1)
        ax.text(
            0.98,
            0.95,
            f"n = {len(data)} ({failed} failed, {len(values) - len(data)} NaN)\n"
            f"5/50/95 %: {q[0]:.6g} / {q[1]:.6g} / {q[2]:.6g}",
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=8,
        )
    ax.ticklabel_format(axis="x", useOffset=False)
    ax.set_xlabel(label)
    ax.set_ylabel("points")


def _line(ax: Any, rows: Sequence[Mapping[str, Any]], x: str, name: str, label: str) -> None:
    pairs = sorted((r[x], r[name]) for r in rows)
    ax.plot([p[0] for p in pairs], [p[1] for p in pairs], "o-")
    ax.set_xlabel(x)
    ax.set_ylabel(label)
    ax.grid(True, alpha=0.3)


def _two(
    ax: Any,
    fig: Any,
    rows: Sequence[Mapping[str, Any]],
    record: Mapping[str, Any],
    varying: list[str],
    name: str,
    label: str,
) -> None:
    import numpy as np  # noqa: PLC0415

    values = {p["name"]: p["values"] for p in record["parameters"]}
    lines_by = record["plot"].get("lines_by")
    words = [v for v in varying if not all(_is_number(x) for x in values[v])]
    if len(words) == 2:
        raise OutputError(f"no plot of {name} over two parameters that are not numbers: {words}")
    if words and lines_by not in varying:
        lines_by = words[0]  # a heatmap needs numbers on both axes
    if lines_by is None:
        small = [v for v in varying if len(values[v]) <= 4]
        lines_by = small[-1] if small else None
    if lines_by in varying:
        x = varying[0] if lines_by == varying[1] else varying[1]
        for value in values[lines_by]:
            pairs = sorted((r[x], r[name]) for r in rows if r[lines_by] == value)
            ax.plot(
                [p[0] for p in pairs],
                [p[1] for p in pairs],
                "o-",
                label=f"{lines_by} = {value:g}" if _is_number(value) else f"{lines_by} = {value}",
            )
        ax.set_xlabel(x)
        ax.set_ylabel(label)
        ax.legend()
        ax.grid(True, alpha=0.3)
        return
    xs, ys = sorted(values[varying[1]]), sorted(values[varying[0]])
    grid = np.full((len(ys), len(xs)), np.nan)
    for r in rows:
        v = r[name]
        grid[ys.index(r[varying[0]]), xs.index(r[varying[1]])] = np.nan if v is None else v
    mesh = ax.pcolormesh(_edges(xs), _edges(ys), grid, shading="flat", cmap="viridis")
    fig.colorbar(mesh, ax=ax, label=label)
    for axis_set, vals in ((ax.set_xscale, xs), (ax.set_yscale, ys)):
        if _is_log(vals):
            axis_set("log")
    ax.set_xlabel(varying[1])
    ax.set_ylabel(varying[0])
    mark = record["plot"].get("mark")
    if isinstance(mark, Mapping) and varying[1] in mark and varying[0] in mark:
        ax.plot(
            [mark[varying[1]]],
            [mark[varying[0]]],
            "r*",
            markersize=14,
            label=str(mark.get("label", "mark")),
        )
        ax.legend(loc="upper right")


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_log(values: Sequence[float]) -> bool:
    """Sorted values spaced by a constant ratio (a `range: {log: true}`)."""
    if len(values) < 3 or min(values) <= 0.0:
        return False
    ratios = [b / a for a, b in itertools.pairwise(values)]
    return max(ratios) - min(ratios) < 1e-6 * max(ratios) and ratios[0] > 1.0


def _edges(values: Sequence[float]) -> list[float]:
    """Cell edges around sorted centres (geometric for a log-spaced set)."""
    import numpy as np  # noqa: PLC0415

    v = np.asarray(values, dtype=float)
    if len(v) == 1:
        return [v[0] * 0.9, v[0] * 1.1] if v[0] else [-0.5, 0.5]
    log = _is_log(values)
    w = np.log(v) if log else v
    mid = (w[1:] + w[:-1]) / 2
    edges = np.concatenate([[w[0] - (mid[0] - w[0])], mid, [w[-1] + (w[-1] - mid[-1])]])
    return list(np.exp(edges) if log else edges)


# --- command line ------------------------------------------------------------------------------


def add_parser(sub: Any) -> None:
    """Register `sweep` on the lca-hil subcommands (an argparse subparsers object)."""
    parser = sub.add_parser(
        "sweep",
        help="run a sweep spec's points on Dask (resumable); --plot DIR draws its results",
        description=__doc__.split("\n\n")[0],
    )
    parser.add_argument("spec", type=Path, nargs="?", help="the sweep spec (YAML)")
    parser.add_argument("--out", type=Path, help="output folder (its finished points are reused)")
    parser.add_argument(
        "--scheduler", help="an existing Dask scheduler's address (default: a local cluster)"
    )
    parser.add_argument(
        "--workers", type=int, help="local worker processes (default: one per core)"
    )
    parser.add_argument("--plot", type=Path, metavar="DIR", help="draw DIR's results as PNGs")
    parser.add_argument("--no-progress", action="store_true", help="no progress line on stderr")


def run(args: argparse.Namespace) -> int:
    """Run `lca-hil sweep` on parsed arguments; returns the exit code."""
    return run_guarded(PROG, lambda: _run(args))


def main(argv: Sequence[str] | None = None) -> int:
    """`lca-hil sweep ...` on its own (the lca-hil entry point registers `add_parser`)."""
    parser = argparse.ArgumentParser(prog="lca-hil")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser(sub)
    return run(parser.parse_args(argv))


def _run(args: argparse.Namespace) -> int:
    if args.spec is None:
        if args.plot is None:
            raise ConfigError("", "spec", "expected a sweep spec, or --plot DIR")
        for path in plot_sweep(args.plot):
            print(f"{PROG}: {path}")
        return EXIT_OK
    if args.out is None:
        raise ConfigError("", "--out", "expected an output folder")
    if args.workers is not None and args.workers < 1:
        raise ConfigError("", "--workers", f"expected >= 1, got {args.workers}")
    log = run_sweep(
        args.spec,
        args.out,
        scheduler=args.scheduler,
        workers=args.workers,
        stream=None if args.no_progress else sys.stderr,
    )
    print(
        f"{PROG}: {log['points']} points ({log['reused']} reused, {log['computed']} computed, "
        f"{log['failed']} failed) in {log['wall_s']:.1f} s; {args.out / RESULTS}"
    )
    if args.plot is not None:
        for path in plot_sweep(args.plot):
            print(f"{PROG}: {path}")
    return EXIT_FAILED if log["failed"] else EXIT_OK
