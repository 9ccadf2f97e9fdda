"""`lca-hil sweep`: run a sweep spec's points on Dask, resumably; plot its results.

    lca-hil sweep config/sweeps/gear_wear_pivot.yaml --out out/wear       # a local cluster
    lca-hil sweep SPEC --out DIR --workers 1                               # one worker process
    lca-hil sweep SPEC --out DIR --scheduler tcp://127.0.0.1:8786          # an existing cluster
    lca-hil sweep --plot DIR                                               # PNGs of DIR's table

The spec is validated and every point's configuration built before anything runs (a bad spec:
one error line, exit 2). Finished points are kept in DIR/points/, so a rerun computes only the
missing and failed ones; a failing point is retried once, then recorded as failed (exit 1).
DIR/results.parquet holds a row per point, the same on any number of workers. docs/sweeps.md
has the spec format, the metric library, the files written and how resuming works.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lca_sim.batch.plan import run_sweep
from lca_sim.batch.store import RESULTS
from lca_sim.cli.sweep_plots import plot_sweep
from lca_sim.errors import EXIT_FAILED, EXIT_OK, ConfigError, run_guarded

PROG = "lca-hil sweep"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `lca-hil sweep`."""
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
