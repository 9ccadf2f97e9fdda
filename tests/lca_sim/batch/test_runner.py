"""`lca-hil sweep` on Dask: the same table on any number of workers, resume, retry, a cluster.

One and two local workers give the same table; a sweep killed with SIGKILL resumes with only the
missing points; a failing point is retried, then recorded failed; a real scheduler with two
worker processes finishes a sweep with one of them killed in the middle.

Every Dask process binds 127.0.0.1. The points are Fig. 13's current step, lengthened where a
test needs points in flight (a 0.5 s step is about half a second of work).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from support import ROOT, wait_until

from lca_sim.batch.plan import run_sweep
from lca_sim.batch.store import LOG, POINTS_DIR, RESULTS, TRAJECTORIES
from lca_sim.batch.tasks import PointOutcome, PointTask
from lca_sim.batch.worker import timed_point

DEADLINE_S = 240.0  # a loaded, shared 2-core machine


@pytest.fixture(autouse=True)
def _keep_the_switch_interval() -> Iterator[None]:
    """`timed_point` sets the worker's GIL switch interval; in this process, put it back."""
    interval = sys.getswitchinterval()
    yield
    sys.setswitchinterval(interval)


def _spec(tmp_path: Path, n: int, duration_s: float, trajectories: bool = False) -> Path:
    """A spec of n current-step points (Kp values), each `duration_s` of simulated time."""
    spec: dict[str, Any] = {
        "base": {"kind": "current_step", "robot": "default", "axis": "pivot",
                 "duration_s": duration_s},
        "parameters": [
            {"name": "kp", "path": "base.current_kp_v_per_a",
             "range": {"start": 10.0, "stop": 60.0, "num": n}},
        ],
        "metrics": [
            {"metric": "overshoot_pct", "signal": "current_a"},
            {"metric": "rise_time_s", "signal": "current_a"},
            {"metric": "energy_drawn_j"},
        ],
    }  # fmt: skip
    if trajectories:
        spec["trajectories"] = {"every_s": 0.002}
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec), encoding="utf-8")
    return path


def _rows(out: Path) -> list[dict[str, Any]]:
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    rows: list[dict[str, Any]] = pq.read_table(out / RESULTS).to_pylist()
    return rows


def _log(out: Path) -> dict[str, Any]:
    log: dict[str, Any] = json.loads((out / LOG).read_text(encoding="utf-8"))
    return log


def _finished(out: Path) -> set[str]:
    folder = out / POINTS_DIR
    return {p.name for p in folder.glob("*.parquet") if ".trajectory." not in p.name}


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[str]]]:
    """Processes a test starts, each in its own session; killed (their groups) at the end."""
    started: list[subprocess.Popen[str]] = []
    yield started
    for proc in started:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


def _start(processes: list[subprocess.Popen[str]], args: list[str], cwd: Path) -> Any:
    proc = subprocess.Popen(
        args,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    processes.append(proc)
    return proc


@contextlib.contextmanager
def _in_process_cluster(workers: int) -> Iterator[Any]:
    """A client of a cluster of `workers` one-thread workers in this process, on 127.0.0.1."""
    from distributed import Client, LocalCluster

    with (
        LocalCluster(n_workers=workers, threads_per_worker=1, processes=False,
                     protocol="tcp://", host="127.0.0.1",
                     dashboard_address="127.0.0.1:0") as cluster,  # type: ignore[no-untyped-call]
        Client(cluster) as client,  # type: ignore[no-untyped-call]
    ):  # fmt: skip
        yield client


def _sweep_args(spec: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "lca_sim.cli.hil", "sweep", str(spec), "--out", str(out),
            "--no-progress", *extra]  # fmt: skip


def test_one_or_two_workers_give_the_same_table(tmp_path: Path) -> None:
    """The same spec on 1 and on 2 local workers: results and trajectories equal bit for bit."""
    spec = _spec(tmp_path, 6, 0.01, trajectories=True)
    one, two = tmp_path / "one", tmp_path / "two"
    run_sweep(spec, one, workers=1, stream=None)
    run_sweep(spec, two, workers=2, stream=None)
    for name in (RESULTS, TRAJECTORIES):
        assert (one / name).read_bytes() == (two / name).read_bytes(), name
    rows = _rows(one)
    assert [r["index"] for r in rows] == list(range(6))
    assert all(r["status"] == "ok" and r["error"] == "" for r in rows)
    assert rows[0]["overshoot_pct"] > rows[-1]["overshoot_pct"] > 0.0  # more Kp, less overshoot
    again = run_sweep(spec, one, workers=1, stream=None)
    assert again["computed"] == 0 and again["reused"] == 6
    assert (one / RESULTS).read_bytes() == (two / RESULTS).read_bytes()


def test_a_sigkilled_sweep_resumes_with_only_the_missing_points(
    tmp_path: Path, processes: list[subprocess.Popen[str]]
) -> None:
    """SIGKILL the sweep (and its workers) mid-run; the rerun computes only what is missing."""
    n = 8
    spec = _spec(tmp_path, n, 0.5)
    out = tmp_path / "out"
    proc = _start(processes, _sweep_args(spec, out, "--workers", "1"), tmp_path)
    wait_until(lambda: len(_finished(out)) >= 2 or proc.poll() is not None, "2 points", DEADLINE_S)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    before = _finished(out)
    assert 2 <= len(before) < n, f"{len(before)} points finished before the kill"
    mtimes = {name: (out / POINTS_DIR / name).stat().st_mtime_ns for name in before}
    log = run_sweep(spec, out, workers=1, stream=None)
    assert log["reused"] == len(before)
    assert log["computed"] == n - len(before)
    keys = {row["index"]: row["key"] for row in _rows(out)}
    assert {f"{keys[i]}.parquet" for i in log["computed_indices"]}.isdisjoint(before)
    assert {name: (out / POINTS_DIR / name).stat().st_mtime_ns for name in before} == mtimes
    assert [r["status"] for r in _rows(out)] == ["ok"] * n


def _flaky(calls: Path, task: PointTask) -> tuple[PointOutcome, float]:
    """timed_point, except that point 1 always raises; every call is counted in `calls`."""
    with calls.open("a", encoding="utf-8") as log:
        log.write(f"{task.index}\n")
    if task.index == 1:
        raise RuntimeError("a point that always fails")
    return timed_point(task)


def test_a_failing_point_is_retried_once_then_recorded_failed(tmp_path: Path) -> None:
    """Point 1 raises: submitted twice, then a failed row with its reason; the rest are ok."""
    spec = _spec(tmp_path, 4, 0.005)
    out = tmp_path / "out"
    calls = tmp_path / "calls.txt"
    with _in_process_cluster(1) as client:
        log = run_sweep(
            spec, out, stream=None, client=client, function=functools.partial(_flaky, calls)
        )
    counts = calls.read_text(encoding="utf-8").split()
    assert sorted(counts) == ["0", "1", "1", "2", "3"]
    assert log["failed"] == 1 and log["retried"]["1"].startswith("RuntimeError: a point that")
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok", "ok"]
    assert rows[1]["error"] == "RuntimeError: a point that always fails"
    assert rows[1]["overshoot_pct"] != rows[1]["overshoot_pct"]  # NaN
    rerun = run_sweep(spec, out, workers=1, stream=None)  # a failed point is computed again
    assert rerun["computed"] == 1 and rerun["computed_indices"] == [1]
    assert [r["status"] for r in _rows(out)] == ["ok"] * 4


def test_an_existing_cluster_with_a_worker_killed_mid_sweep(
    tmp_path: Path, processes: list[subprocess.Popen[str]]
) -> None:
    """`dask scheduler` + two `dask worker` processes; SIGKILL one mid-sweep; the sweep ends."""
    dask = str(Path(sys.executable).parent / "dask")
    scheduler_file = tmp_path / "scheduler.json"
    _start(
        processes,
        [
            dask,
            "scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--no-dashboard",
            "--scheduler-file",
            str(scheduler_file),
        ],
        tmp_path,
    )
    wait_until(
        lambda: scheduler_file.is_file() and scheduler_file.stat().st_size > 0,
        "the scheduler file",
        60.0,
    )
    address = json.loads(scheduler_file.read_text(encoding="utf-8"))["address"]
    assert address.startswith("tcp://127.0.0.1:")
    workers = [
        _start(processes, [dask, "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                           "--no-nanny", "--no-dashboard", "--name", f"w{i}"], tmp_path)
        for i in range(2)
    ]  # fmt: skip
    from distributed import Client

    with Client(address, timeout="60s") as client:  # type: ignore[no-untyped-call]
        client.wait_for_workers(2, timeout=120)
    n = 10
    spec = _spec(tmp_path, n, 0.5)
    out = tmp_path / "out"
    sweep = _start(processes, _sweep_args(spec, out, "--scheduler", address), tmp_path)
    wait_until(lambda: len(_finished(out)) >= 2 or sweep.poll() is not None, "2 points", DEADLINE_S)
    assert sweep.poll() is None, "the sweep ended before a worker could be killed"
    os.killpg(workers[0].pid, signal.SIGKILL)
    sweep.wait(timeout=DEADLINE_S)
    assert sweep.returncode == 0, sweep.stderr.read() if sweep.stderr else ""
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["ok"] * n
    log = _log(out)
    assert log["scheduler"] == address and log["computed"] == n


def _dying(task: PointTask) -> tuple[PointOutcome, float]:
    """timed_point, except that point 1 kills the worker process running it."""
    if task.index == 1:
        os._exit(3)
    return timed_point(task)


class _Recording:
    """A Dask client that notes, at every submit, its key and the futures then not yet done."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.futures: list[Any] = []
        self.submits: dict[str, int] = {}

    def submit(self, *args: Any, **kwargs: Any) -> Any:
        future = self.client.submit(*args, **kwargs)
        self.futures.append(future)
        self.submits[kwargs["key"]] = sum(not f.done() for f in self.futures)
        return future

    def run(self, *args: Any, **kwargs: Any) -> Any:
        return self.client.run(*args, **kwargs)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_point_whose_worker_dies_is_retried_alone_then_recorded_failed(
    tmp_path: Path, workers: int
) -> None:
    """Point 1 kills its worker, twice: a failed row saying so; the others are all computed.

    Dask hands a worker more than one point, and a point queued behind the dying one dies with
    it: the retry of a point whose worker died comes after the others, alone, so the one that
    kills dies alone and the ones that shared its worker are computed.
    """
    import cloudpickle  # type: ignore[import-untyped]

    from lca_sim.batch.runner import dask_client

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the worker has no tests/
    try:
        spec = _spec(tmp_path, 4, 0.005)
        out = tmp_path / "out"
        with dask_client(None, workers) as client:
            recording = _Recording(client)
            log = run_sweep(spec, out, stream=None, client=recording, function=_dying)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok", "ok"], rows
    assert rows[1]["error"] == "KilledWorker: the worker running it died"
    assert log["retried"]["1"] == rows[1]["error"] and log["failed"] == 1
    retries = {key: n for key, n in recording.submits.items() if key.endswith("-2")}
    assert f"lca-point-{rows[1]['key']}-2" in retries
    assert all(n == 1 for n in retries.values()), retries  # each alone on the cluster


def test_points_of_one_configuration_are_computed_once(tmp_path: Path) -> None:
    """A value given twice: one computation, two equal rows (the driver once died of it)."""
    spec_doc = yaml.safe_load(_spec(tmp_path, 2, 0.005).read_text(encoding="utf-8"))
    spec_doc["parameters"][0] = {
        "name": "kp", "path": "base.current_kp_v_per_a", "values": [20.0, 20.0, 30.0]
    }  # fmt: skip
    spec = tmp_path / "twice.yaml"
    spec.write_text(yaml.safe_dump(spec_doc), encoding="utf-8")
    out = tmp_path / "out"
    with _in_process_cluster(1) as client:
        log = run_sweep(spec, out, stream=None, client=client)
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["ok"] * 3
    assert (log["computed"], log["shared"], log["reused"]) == (2, 1, 0)
    assert rows[0]["key"] == rows[1]["key"] != rows[2]["key"]
    assert rows[0]["overshoot_pct"] == rows[1]["overshoot_pct"] != rows[2]["overshoot_pct"]


def test_closed_and_open_loop_sweeps_run_on_worker_processes(tmp_path: Path) -> None:
    """A closed loop with a fault schedule and an open-loop scenario, through worker processes.

    The points are pickled to a worker process and back: the results are those of the same
    points computed here, bit for bit.
    """
    from distributed import Client, LocalCluster

    from lca_sim.batch.closed_loop_config import closed_loop_builder
    from lca_sim.batch.compute import run_point
    from lca_sim.batch.plan import load_spec
    from lca_sim.batch.tasks import build_tasks
    from lca_sim.batch.version import package_version

    (tmp_path / "jam.yaml").write_text(
        yaml.safe_dump(
            {"faults": [{"joint": "pivot", "kind": "jam", "value": True, "start_s": 1.5}]}
        ),
        encoding="utf-8",
    )
    (tmp_path / "lift.yaml").write_text(
        yaml.safe_dump(
            {
                "duration_s": 2.0,
                "dt_s": 1e-4,
                "record_period_s": 0.01,
                "initial": {"position": {"pivot": 0.44}},
                "inputs": {"pivot": {"time_s": [0.0, 0.5], "voltage_v": [0.0, 20.0]}},
            }
        ),
        encoding="utf-8",
    )
    specs = {
        "closed": {
            "base": {"kind": "closed_loop", "duration_s": 2.5, "axis": "pivot",
                     "faults": "jam.yaml"},
            "parameters": [{"name": "jam_s", "path": "faults.0.start_s", "values": [1.5, 2.2]}],
            "metrics": [{"metric": "peak_current_a"}, {"metric": "hold_drift", "from_s": 2.3}],
        },
        "open": {
            "base": {"kind": "open_loop", "scenario": "lift.yaml", "axis": "pivot"},
            "parameters": [{"name": "r_scale", "mode": "scale", "values": [1.0, 1.2],
                            "path": "robot.axes.pivot.motor.resistance_ohm"}],
            "metrics": [{"metric": "peak_current_a"}, {"metric": "hold_drift"}],
        },
    }  # fmt: skip
    with (
        LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                     dashboard_address="127.0.0.1:0") as cluster,  # type: ignore[no-untyped-call]
        Client(cluster) as client,  # type: ignore[no-untyped-call]
    ):  # fmt: skip
        for name, doc in specs.items():
            path = tmp_path / f"{name}.yaml"
            path.write_text(yaml.safe_dump(doc), encoding="utf-8")
            out = tmp_path / name
            log = run_sweep(path, out, stream=None, client=client)
            assert log["computed"] == 2 and log["failed"] == 0, log
            spec, documents = load_spec(path)
            here = [
                run_point(t).metrics
                for t in build_tasks(spec, documents, package_version(), closed_loop_builder)
            ]
            rows = _rows(out)
            for row, metrics in zip(rows, here, strict=True):
                assert {k: row[k] for k in metrics} == metrics, name
            assert rows[0]["peak_current_a"] != rows[1]["peak_current_a"], name
