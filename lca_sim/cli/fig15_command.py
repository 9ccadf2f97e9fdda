"""`lca-hil fig15`: its options, and its start; rclpy is imported only when it runs.

The run itself (`lca_sim.cli.fig15`) needs ROS 2; without it the command exits 2 with one line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lca_sim.cli.ros_guard import ros_required
from lca_sim.errors import run_guarded


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `lca-hil fig15`."""
    parser.add_argument("--out", type=Path, default=Path("out/fig15"), help="output folder")
    parser.add_argument("--duration-s", type=float, default=13.0, help="simulated seconds")


def run(args: argparse.Namespace) -> int:
    """Run `lca-hil fig15` on parsed arguments; returns the exit code."""
    return run_guarded("lca-hil fig15", lambda: _fig15(args))


def _fig15(args: argparse.Namespace) -> int:
    with ros_required("this command"):
        from lca_sim.cli.fig15 import run_fig15  # noqa: PLC0415  (rclpy: only for this command)
    return run_fig15(args.out, args.duration_s)
