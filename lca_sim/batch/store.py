"""A sweep's files: one Parquet file per finished point, the merged tables, the sweep record.

DIR/points/ holds one small Parquet file per finished point, named by its key and written as it
finishes, so a rerun computes only the points without one. `merge` writes DIR/results.parquet
(a row per point, by index: parameters, seed, metrics, status, error; no timing, so the same
spec gives the same table on any number of workers) and DIR/trajectories.parquet.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lca_sim.analysis.metrics import METRICS
from lca_sim.batch.spec import SweepSpec
from lca_sim.batch.tasks import PointOutcome, PointTask
from lca_sim.errors import OutputError
from lca_sim.output import atomic_path

POINTS_DIR = "points"
RESULTS = "results.parquet"
TRAJECTORIES = "trajectories.parquet"
RECORD = "sweep.json"
LOG = "run_log.json"
OK, FAILED = "ok", "failed"


def pyarrow_modules() -> tuple[Any, Any]:
    """The modules pyarrow and pyarrow.parquet, imported when a sweep reads or writes a table."""
    import pyarrow as pa  # type: ignore[import-untyped]  # noqa: PLC0415
    import pyarrow.parquet as pq  # type: ignore[import-untyped]  # noqa: PLC0415

    return pa, pq


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
        _pa, pq = pyarrow_modules()

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
        pa, pq = pyarrow_modules()

        if trajectory is not None:
            with atomic_path(self.path(key, trajectory=True)) as tmp:
                pq.write_table(pa.table(dict(trajectory)), tmp)
        with atomic_path(self.path(key)) as tmp:
            pq.write_table(pa.table({k: [v] for k, v in row.items()}), tmp)

    def read(self, key: str, trajectory: bool = False) -> Any:
        """A point's table."""
        _pa, pq = pyarrow_modules()

        return pq.read_table(self.path(key, trajectory))


def outcome_row(task: PointTask, outcome: PointOutcome | None, error: str) -> dict[str, Any]:
    """A point's row in its file: key, status, error and its metrics (NaN when failed)."""
    row: dict[str, Any] = {"key": task.key, "status": OK if outcome else FAILED, "error": error}
    for metric in task.metrics:
        row[metric.name] = outcome.metrics[metric.name] if outcome else math.nan
    return row


def merge(spec: SweepSpec, tasks: Sequence[PointTask], store: PointStore, out: Path) -> int:
    """DIR/results.parquet (and trajectories.parquet) from the points, by index.

    Returns the number of failed points.
    """
    pa, pq = pyarrow_modules()

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
