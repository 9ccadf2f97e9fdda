"""The benchmarks' machine-load figure (bench/ros_loop.py, used by bench/can_loop.py too).

"Other processes" is /proc/stat's busy time over a window minus the measured processes' own
CPU. On the project's virtual machines /proc/stat counts some windows short (160 of 200 ticks a
second) or its busy time falls below the measured processes' own; the figure then read as
"another load kept half a core busy" where there was none. Such a window gives no figure and
says why. And bench/can_loop.py's reading of the relay's stalls from its stop line, and the
window its CPU targets are judged on.
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parent.parent / "bench"
CPUS = os.cpu_count() or 1


def _bench_module(name: str) -> ModuleType:
    """A script of bench/ imported as a module (its siblings importable meanwhile)."""
    sys.path.insert(0, str(BENCH))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(BENCH))


@pytest.fixture(scope="module")
def ros_loop() -> ModuleType:
    return _bench_module("ros_loop")


def test_a_consistent_window_gives_the_rest_of_the_machine(ros_loop: ModuleType) -> None:
    """10 s on every CPU counted, 4.5 s busy of which 3.0 s ours: 15 % of a core elsewhere."""
    share, why = ros_loop.other_processes_share(4.5, 10.0 * CPUS, 3.0, 10.0)
    assert share == pytest.approx(0.15) and why == ""
    share, why = ros_loop.other_processes_share(2.95, 10.0 * CPUS, 3.0, 10.0)  # tick rounding
    assert share == 0.0 and why == ""


def test_a_window_proc_stat_counted_short_gives_no_figure(ros_loop: ModuleType) -> None:
    """160 of 200 ticks a second (seen here): not measurable, with the counts."""
    share, why = ros_loop.other_processes_share(9.0, 8.0 * CPUS, 3.0, 10.0)
    assert share is None
    assert why.startswith("not measurable") and f"{8.0 * CPUS:.1f} s" in why


def test_busy_time_below_the_processes_own_gives_no_figure(ros_loop: ModuleType) -> None:
    """/proc/stat's busy 0.5 s against 3.9 s the measured processes used: not measurable."""
    share, why = ros_loop.other_processes_share(0.5, 10.0 * CPUS, 3.9, 10.0)
    assert share is None and "0.50 s" in why and "3.90 s" in why


def test_the_note_says_which(ros_loop: ModuleType) -> None:
    """A busy machine warns with its share; an unmeasurable one says so; a quiet one is silent."""
    assert "51 % of a core" in ros_loop.other_processes_note({"cpu_share": 0.51}, "scenario")
    assert ros_loop.other_processes_note({"cpu_share": 0.05}, "scenario") == ""
    why = "not measurable: /proc/stat counted 16.0 s"
    assert why in ros_loop.other_processes_note({"cpu_share": None, "why": why}, "phase")


@pytest.fixture(scope="module")
def can_loop() -> ModuleType:
    return _bench_module("can_loop")


def test_the_relay_s_stalls_are_read_from_its_stop_line(can_loop: ModuleType) -> None:
    """bench/can_loop.py reads what `lca-can-server` prints as it stops (its `RelayStats`)."""
    from lca_sim.canbus.relay import RelayStats

    stats = RelayStats(connections=3, frames_in=10, freezes=2, longest_freeze_s=0.3125)
    log = f"relaying on ws://127.0.0.1:1/\nlca-can-server: stopped; {stats}\n"
    assert can_loop.relay_stalls(log) == {"count": 2, "longest_ms": 312.5}
    assert can_loop.relay_stalls("relaying on ws://127.0.0.1:1/\n") is None  # killed: no line


def _scenario(
    cpu_share: float, unobserved_cpu: float, fired: bool, unobserved_fired: bool
) -> dict[str, object]:
    """A scenario's figures as bench/can_loop.py records them, reduced to what targets() reads."""
    return {
        "ok": True,
        "cycle_hz": 500.0,
        "in_time_share": 0.999,
        "watchdogs": {"fired": fired},
        "cpu": {"bridge": {"cpu_share": cpu_share}, "rack": {"cpu_share": cpu_share}},
        "unobserved": {
            "watchdogs": {"fired": unobserved_fired},
            "cpu": {"bridge": {"cpu_share": unobserved_cpu}, "rack": {"cpu_share": unobserved_cpu}},
        },
    }


def test_cpu_targets_are_judged_on_the_unobserved_window(can_loop: ModuleType) -> None:
    """The bench's own readers cost the bridge CPU: its targets take the window without them.

    Both figures are in the line, and a watchdog of either window counts.
    """
    met = can_loop.targets(
        {
            "shipped": _scenario(0.38, 0.24, fired=False, unobserved_fired=False),
            "remote": _scenario(0.20, 0.16, fired=False, unobserved_fired=True),
        }
    )
    assert met["bridge_cpu_500"] == 0.24 and met["bridge_cpu_500_observed"] == 0.38
    assert met["meets_bridge_cpu_500"] is True
    assert met["rack_cpu_remote"] == 0.16 and met["meets_rack_cpu_remote"] is False
    assert met["meets_no_watchdog_shipped"] is True
    assert met["meets_no_watchdog"] is False  # the remote scenario's second window
