"""The modes' shared parts (lca_sim.cia402.mode_common): window timers, limits, validation."""

from __future__ import annotations

import math

import pytest

from lca_sim.cia402.mode_common import (
    WINDOW_OFF,
    Dwell,
    FollowingErrorWatch,
    SoftwareLimits,
    WindowParams,
    falling,
    rising,
)
from lca_sim.errors import InvalidValueError


def test_dwell_needs_the_condition_for_its_whole_time() -> None:
    """3 ms at 1 ms steps: true on the 4th step in a row; any break starts over."""
    dwell = Dwell()
    seq = [True, True, True, True, False, True, True, True, True, True]
    assert [dwell.update(c, 1e-3, 3e-3) for c in seq] == [
        False, False, False, True, False, False, False, False, True, True,
    ]  # fmt: skip
    assert Dwell().update(True, 1e-3, 0.0)  # time 0: at once


def test_following_error_watch_rises_once() -> None:
    """|demand - actual| > window for longer than the time: active; the edge comes once."""
    watch = FollowingErrorWatch()
    window = WindowParams(10.0, 0.0)
    assert watch.update(0.0, 10.0, 1e-3, window) == (False, False)  # on the edge: inside
    assert watch.update(0.0, 10.5, 1e-3, window) == (True, True)
    assert watch.update(0.0, -11.0, 1e-3, window) == (True, False)
    assert watch.active
    assert watch.update(0.0, 11.0, 1e-3, WindowParams(WINDOW_OFF, 0.0)) == (False, False)


def test_software_limits() -> None:
    """0x607D clamps; min above max is refused; the default limits nothing an INTEGER32 holds."""
    limits = SoftwareLimits(-10.0, 20.0)
    assert [limits.clamp(x) for x in (-50.0, 0.0, 50.0)] == [-10.0, 0.0, 20.0]
    assert SoftwareLimits().clamp(-(2.0**31)) == -(2.0**31)
    with pytest.raises(InvalidValueError, match="0x607D"):
        SoftwareLimits(1.0, 0.0)


@pytest.mark.parametrize(("window", "time_s"), [(-1.0, 0.0), (math.nan, 0.0), (1.0, -1e-3)])
def test_bad_windows_are_refused(window: float, time_s: float) -> None:
    """A window must be >= 0, its time finite and >= 0."""
    with pytest.raises(InvalidValueError):
        WindowParams(window, time_s)


def test_edges() -> None:
    """Rising and falling edges of a controlword bit."""
    assert rising(0x1F, 0x0F, 0x10) and not rising(0x1F, 0x1F, 0x10)
    assert falling(0x0F, 0x1F, 0x10) and not falling(0x0F, 0x0F, 0x10)
