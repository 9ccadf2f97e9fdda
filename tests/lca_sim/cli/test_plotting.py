"""The shared plot helpers: units, robust limits, merged labels; `lca-hil run --plot` uses them.

The run's figures are lca-plot's, drawn from a composed run of the Fig. 15 ramp instead of a bag.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lca_sim.cli import plotting
from lca_sim.cli import run as run_cli


@pytest.mark.parametrize(
    ("name", "unit", "axis", "reference", "scale", "label"),
    [
        ("travel_after_cut_rad", "rad (m)", "pivot", "", 180.0 / math.pi, "travel_after_cut (deg)"),
        ("travel", "rad (m)", "lift", "", 1.0, "travel (m)"),
        ("end_stop_contact", "1 (0 or 1)", "pivot", "", 1.0, "end_stop_contact (0 or 1)"),
        ("state_changes", "1", "pivot", "", 1.0, "state_changes"),
        ("peak_current_a", "A", "pivot", "", 1.0, "peak_current_a (A)"),
        (
            "tracking_error_rms_rad_s",
            "unit of the reference",
            "pivot",
            "velocity",
            180.0 / math.pi,
            "tracking_error_rms (deg/s)",
        ),
        ("err", "unit of the reference", "pivot", "current_a", 1.0, "err (A)"),
    ],
)
def test_metric_labels_read_as_a_reader_writes_them(
    name: str, unit: str, axis: str, reference: str, scale: float, label: str
) -> None:
    """A metric's axis label: deg for angles, m for the lift, no unit said twice."""
    got_scale, got_unit = plotting.metric_unit(unit, axis, reference)
    assert got_scale == pytest.approx(scale)
    assert plotting.metric_label(name, got_unit) == label


@given(st.lists(st.floats(0.0, 100.0), max_size=50), st.floats(0.001, 10.0))
def test_merged_events_start_a_gap_apart(times: list[float], gap: float) -> None:
    """Every event is in one group; the groups' first times are at least `gap` apart."""
    times = sorted(times)
    groups = plotting.merge_events(times, gap)
    assert [k for g in groups for k in g] == list(range(len(times)))
    starts = [times[g[0]] for g in groups]
    assert all(b - a >= gap for a, b in itertools.pairwise(starts))
    assert all(times[k] - times[g[0]] < gap for g in groups for k in g)


def test_robust_limits_clip_a_short_spike_and_keep_a_step() -> None:
    """20 of 3000 samples at -20 clip; a step held for a third of the run does not."""
    bulk = np.linspace(0.0, 2.5, 3000)
    spiked = bulk.copy()
    spiked[2000:2010] = -20.0
    limits = plotting.robust_limits(spiked)
    assert limits is not None
    low, high, clip_low, clip_high = limits
    assert (clip_low, clip_high) == (True, False)
    assert -1.0 < low < 0.0 and 2.5 < high < 3.0
    step = np.where(np.arange(3000) < 1000, -20.0, bulk)
    stepped = plotting.robust_limits(step)
    assert stepped is not None and stepped[2:] == (False, False) and stepped[0] < -20.0


def test_run_plot_draws_the_trajectory_with_lca_plots_figures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`lca-hil run --plot DIR`: the ramp's figures, the reference drawn, the spike clipped."""
    out = tmp_path / "run"
    assert run_cli.main(["run", "--out", str(out), "--plot", str(out / "plots")]) == 0
    printed = capsys.readouterr().out
    written = sorted(p.name for p in (out / "plots").glob("*.png"))
    assert written == ["currents.png", "drive_states.png", "positions.png", "velocities.png"]
    assert "efficiencies.png skipped" in printed  # the composed run keeps no eta
    assert "currents.png:pivot: " in printed and "clipped (min -20" in printed
    for name in written:
        assert f"wrote {out / 'plots' / name}" in printed
