"""`lca-hil`: the paper's experiments and the drive-chain tools, one sub-command each.

    lca-hil fig15 --out out/fig15          # closed loop over ROS 2 (needs rclpy)
    lca-hil paper --out out/paper          # every figure (--no-ros: without Fig. 15 and rclpy)
    lca-hil tune --axis pivot              # section 6 tuning
    lca-hil identify RESULT --axis pivot   # efficiencies from recorded motion
    lca-hil run --out out/run              # the nodes' closed loop in one process, no ROS
    lca-hil sweep SPEC --out out/sweep     # a sweep spec's points on Dask (--plot DIR: PNGs)

Only `fig15` (and `paper` with Fig. 15) imports rclpy, and only when it runs, so the other
sub-commands work where ROS 2 is not installed; there, those two exit 2 with one error line.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from lca_sim.cli import identify as identify_cli
from lca_sim.cli import paper as paper_cli
from lca_sim.cli import run as run_cli
from lca_sim.cli import sweep as sweep_cli
from lca_sim.cli import tune
from lca_sim.cli.ros_guard import ros_required
from lca_sim.errors import run_guarded


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of lca-hil."""
    parser = argparse.ArgumentParser(prog="lca-hil", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    fig15 = sub.add_parser("fig15", help="closed-loop Fig. 15 velocity ramp over ROS 2")
    fig15.add_argument("--out", type=Path, default=Path("out/fig15"), help="output folder")
    fig15.add_argument("--duration-s", type=float, default=13.0, help="simulated seconds")
    tune.add_parser(sub)
    paper_cli.add_parser(sub)
    identify_cli.add_parser(sub)
    run_cli.add_parser(sub)
    sweep_cli.add_parser(sub)
    args = parser.parse_args(argv)
    if args.command == "identify":
        return identify_cli.run(args)
    if args.command == "tune":
        return tune.run(args)
    if args.command == "run":
        return run_cli.run(args)
    if args.command == "sweep":
        return sweep_cli.run(args)
    if args.command == "paper":
        return paper_cli.run(args)
    return run_guarded("lca-hil fig15", lambda: _fig15(args))


def _fig15(args: argparse.Namespace) -> int:
    with ros_required("this command"):
        from lca_sim.cli.fig15 import run_fig15  # noqa: PLC0415  (rclpy: only for this command)
    return run_fig15(args.out, args.duration_s)


if __name__ == "__main__":
    raise SystemExit(main())
