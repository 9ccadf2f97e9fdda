"""Shared test support: repository paths and the one polling helper.

tests/ is on sys.path through its conftest, so every test module imports this as `support`.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.executors import Executor, SingleThreadedExecutor

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


def domain_contexts(
    first_domain_id: int, span: int
) -> Callable[[], AbstractContextManager[tuple[Context, SingleThreadedExecutor]]]:
    """A `ros_context()` for one test module, on its own range of domain ids.

    Each call gives a fresh rclpy Context and executor on the next domain id of
    `first_domain_id .. first_domain_id + span - 1`, torn down afterwards. Each module takes
    its own range, so modules that run one after another never see each
    other's late DDS traffic.
    """
    domains = itertools.count()

    @contextmanager
    def ros_context() -> Iterator[tuple[Context, SingleThreadedExecutor]]:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        ctx = Context()
        rclpy.init(context=ctx, domain_id=first_domain_id + next(domains) % span)
        executor = SingleThreadedExecutor(context=ctx)
        try:
            yield ctx, executor
        finally:
            executor.shutdown()
            rclpy.shutdown(context=ctx)

    return ros_context


class FreezeWatch(threading.Thread):
    """Measures the longest stall of this process's Python threads while it runs.

    It wakes every 2 ms; a late wake-up means no thread of this process ran Python (a stalled
    host, or the GIL held by a long garbage collection): on the wall clock a plant went on
    meanwhile. Tests that judge wall-clock timing repeat a run that froze.
    """

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.longest_s = 0.0
        self._stop_event = threading.Event()

    def run(self) -> None:
        """Watch until `stop()`."""
        last = time.monotonic()
        while not self._stop_event.wait(0.002):
            now = time.monotonic()
            self.longest_s = max(self.longest_s, now - last - 0.002)
            last = now

    def stop(self) -> None:
        """Stop watching (and wait for the thread)."""
        self._stop_event.set()
        if self.is_alive():
            self.join()
