"""Shared test support: repository paths and the one polling helper.

tests/ is on sys.path through its conftest, so every test module imports this as `support`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from rclpy.executors import Executor

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config"


def wait_until(
    condition: Callable[[], bool],
    what: str,
    timeout_s: float = 30.0,
    *,
    step: Callable[[], object] | None = None,
    check: Callable[[], None] | None = None,
) -> None:
    """Poll `condition()` until it holds; fail naming `what` after `timeout_s`.

    The one polling helper of the tests: no test sleeps a fixed time or waits without a
    deadline.

    Args:
        condition: what to wait for.
        what: said in the failure.
        timeout_s: the deadline, s (generous: the machines are shared 2-core ones).
        step: run between polls, e.g. one spin of an executor; default a 2 ms pause.
        check: run before each poll; it may fail the test early (a subprocess that exited).
    """
    deadline_s = time.monotonic() + timeout_s
    while True:
        if check is not None:
            check()
        if condition():
            return
        if time.monotonic() > deadline_s:
            pytest.fail(f"not within {timeout_s:g} s: {what}")
        if step is None:
            time.sleep(0.002)
        else:
            step()


def spin_until(
    executor: Executor,
    condition: Callable[[], bool],
    what: str = "condition",
    timeout_s: float = 30.0,
) -> None:
    """Spin `executor` until `condition()` holds; fail naming `what` after `timeout_s`."""
    wait_until(condition, what, timeout_s, step=lambda: executor.spin_once(timeout_sec=0.05))
