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
from dataclasses import dataclass
from typing import Protocol

from lca_sim.cli import fig15_command, identify, paper, sweep, tune
from lca_sim.cli import run as run_command


class CommandModule(Protocol):
    """What a sub-command's module provides: its options and its run (an exit code)."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Add the command's options to its sub-parser."""

    def run(self, args: argparse.Namespace) -> int:
        """Run the command on parsed arguments; returns the exit code."""


@dataclass(frozen=True, slots=True)
class Subcommand:
    """One sub-command of lca-hil.

    Attributes:
        module: adds the options and runs the command.
        help: its line in `lca-hil --help`.
        described: its own --help opens with the module docstring's first paragraph.
    """

    module: CommandModule
    help: str
    described: bool = False


# The one registry: `lca-hil --help` lists the sub-commands in this order.
SUBCOMMANDS: dict[str, Subcommand] = {
    "fig15": Subcommand(fig15_command, "closed-loop Fig. 15 velocity ramp over ROS 2"),
    "tune": Subcommand(tune, "section 6 PI gains from linearised models"),
    "paper": Subcommand(paper, "regenerate the paper's figures (PNG + CSV)"),
    "identify": Subcommand(
        identify,
        "identify the drive-state efficiencies from a result.csv or a bag",
        described=True,
    ),
    "run": Subcommand(
        run_command,
        "the controller and simulator closed loop in one process, without ROS 2",
        described=True,
    ),
    "sweep": Subcommand(
        sweep,
        "run a sweep spec's points on Dask (resumable); --plot DIR draws its results",
        described=True,
    ),
}


def build_parser() -> argparse.ArgumentParser:
    """The parser of lca-hil, a sub-parser per entry of `SUBCOMMANDS`."""
    parser = argparse.ArgumentParser(prog="lca-hil", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, command in SUBCOMMANDS.items():
        doc = command.module.__doc__ or ""
        description = doc.split("\n\n")[0] if command.described else None
        command.module.add_arguments(
            sub.add_parser(name, help=command.help, description=description)
        )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of lca-hil."""
    args = build_parser().parse_args(argv)
    return SUBCOMMANDS[args.command].module.run(args)


if __name__ == "__main__":
    raise SystemExit(main())
