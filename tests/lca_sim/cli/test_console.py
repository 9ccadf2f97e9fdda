"""The console scripts' common parts: the failure line, the stop signals and their restoring."""

from __future__ import annotations

import os
import signal

import pytest

from lca_sim.cli.console import script_arguments
from lca_sim.errors import EXIT_BAD_INPUT, fail
from lca_sim.runtime import STOP_SIGNALS, stop_signals


def test_fail_says_one_line_and_returns_the_bad_input_code(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`fail` prints `prog: error: message` on stderr only and returns 2."""
    assert fail("lca-plot", "bag x: not a rosbag2 bag") == EXIT_BAD_INPUT
    out, err = capsys.readouterr()
    assert out == "" and err == "lca-plot: error: bag x: not a rosbag2 bag\n"


@pytest.mark.parametrize("sig", STOP_SIGNALS)
def test_stop_signals_call_back_inside_and_restore_after(sig: signal.Signals) -> None:
    """SIGINT and SIGTERM reach `on_stop` by name inside the block; the old handler comes back."""
    before = signal.getsignal(sig)
    seen: list[str] = []
    with stop_signals(seen.append):
        os.kill(os.getpid(), sig)
    assert seen == [sig.name]
    assert signal.getsignal(sig) is before


def test_stop_signals_restore_after_an_error() -> None:
    """An exception in the block still puts the previous handlers back."""
    before = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    with pytest.raises(RuntimeError), stop_signals(lambda _name: None):
        raise RuntimeError("boom")
    assert {sig: signal.getsignal(sig) for sig in STOP_SIGNALS} == before


def test_script_arguments_take_argv_or_the_process_arguments(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Given arguments are kept; None reads sys.argv after the program name."""
    monkeypatch.setattr("sys.argv", ["lca-echo", "joint_states", "--once"])
    assert script_arguments(None) == ["joint_states", "--once"]
    assert script_arguments(["-h"]) == ["-h"]
