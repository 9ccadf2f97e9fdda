"""`lca-sim`: run a scenario headless and write its results.

    lca-sim run --robot default --scenario fig9_open_loop_pivot --out out/fig9

Exit codes: 0 success, 2 bad config, scenario or arguments (one line on stderr, no traceback),
130 interrupted. Nothing half-written is left in --out.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from pathlib import Path

from lca_sim.cli.results import write_csv, write_plot
from lca_sim.config.loader import load_robot, load_scenario, shipped_names
from lca_sim.errors import OutputError, run_guarded
from lca_sim.model.scenario import ScenarioResult, run_scenario
from lca_sim.model.simulator import Simulator


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of lca-sim."""
    parser = argparse.ArgumentParser(prog="lca-sim", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a scenario and write DIR/result.csv (and result.png)")
    run.add_argument(
        "--robot",
        default="default",
        help=f"robot YAML path or shipped name ({', '.join(shipped_names('robots'))})",
    )
    run.add_argument(
        "--scenario",
        required=True,
        help=f"scenario YAML path or shipped name ({', '.join(shipped_names('scenarios'))})",
    )
    run.add_argument("--out", required=True, type=Path, help="output folder")
    run.add_argument("--no-plot", action="store_true", help="skip result.png")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the lca-sim console script."""
    args = build_parser().parse_args(argv)
    return run_guarded("lca-sim", lambda: _run(args), "interrupted; nothing written")


def _run(args: argparse.Namespace) -> int:
    out: Path = args.out
    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {out}: expected a folder, but it is a file")
    robot = load_robot(args.robot)
    sim = Simulator(robot, dt_s=_scenario_dt(args.scenario, robot.axis_names))
    scenario = load_scenario(args.scenario, robot.axis_names)
    print(
        f"lca-sim: robot {robot.name}, scenario {Path(scenario.source).name}: "
        f"{scenario.duration_s:g} s at dt {scenario.dt_s:g} s ({scenario.n_steps} steps)",
        flush=True,
    )
    start = time.perf_counter()
    result = run_scenario(sim, scenario)
    wall_s = time.perf_counter() - start
    try:
        write_csv(result, out / "result.csv")
        written = [out / "result.csv"]
        if args.no_plot:
            # A plot from an earlier run would no longer match result.csv.
            (out / "result.png").unlink(missing_ok=True)
        else:
            title = f"{robot.name}: {Path(scenario.source).stem}"
            write_plot(result, out / "result.png", title)
            written.append(out / "result.png")
    except OSError as exc:
        raise OutputError(f"--out {out}: cannot write ({exc.strerror or exc})") from exc
    print(
        f"simulated {scenario.duration_s:g} s in {wall_s:.2f} s "
        f"(real-time factor {scenario.duration_s / wall_s:.1f}, "
        f"{wall_s / scenario.n_steps * 1e6:.1f} us/step)"
    )
    _print_phases(result)
    for path in written:
        print(f"wrote {path}")
    return 0


def _scenario_dt(scenario: str, axis_names: tuple[str, ...]) -> float:
    return load_scenario(scenario, axis_names).dt_s


def _print_phases(result: ScenarioResult) -> None:
    """Where each drive-state phase began, for every axis that did anything."""
    for axis in result.axis_names:
        phases = result.phases(axis)
        if len(phases) <= 1 and phases and phases[0].state == "stop_hold":
            continue
        print(f"{axis} phases:")
        unit, scale = ("m", 1.0) if axis == "lift" else ("deg", 180.0 / math.pi)
        for phase in phases:
            position = phase.position * scale
            print(f"  {phase.time_s:9.4f} s  {phase.state:40s} at {position:8.3f} {unit}")


if __name__ == "__main__":
    raise SystemExit(main())
