"""The CAN loop in lockstep: the master is the clock, one SYNC per command (no ROS).

A lockstep loop runs SYNC k+1 only once SYNC k's state is complete and the controller has
answered it, and every party counts time in cycles: the master's watches read `CycleClock`, the
virtual rack advances 0x1006 per SYNC (`RackConfig.timing_mode`). So the same inputs give the
same frames and the same topics on any host, however slow. docs/can.md, "Lockstep".
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

from lca_sim.errors import InvalidValueError


class CycleClock:
    """Simulated time of a lockstep CAN loop: SYNC k (k = 0, 1, ...) is at k / cycle_hz.

    Args:
        period_s: the cycle period, 1 / cycle_hz (what the master writes to 0x1006).
    """

    def __init__(self, period_s: float) -> None:
        if not period_s > 0.0:
            raise InvalidValueError(f"period_s must be > 0, got {period_s!r}")
        self.period_s = period_s
        self.syncs = 0  # SYNCs sent; the last one was SYNC syncs - 1

    def now(self) -> float:
        """The time of the last SYNC sent (0 before the first), s."""
        return max(self.syncs - 1, 0) * self.period_s

    def next_sync(self) -> float:
        """Count one more SYNC and return its time, s."""
        self.syncs += 1
        return self.now()


@dataclass(slots=True)
class LockstepCounters:
    """What a lockstep loop counts for /diagnostics."""

    syncs: int = 0
    states: int = 0  # complete cycles handed on
    commands: int = 0  # commands that released the next SYNC
    early_commands: int = 0  # commands that came while no state awaited an answer
    resent_states: int = 0  # the last state again, after `resend_s` of controller silence
    incomplete_cycles: int = 0  # SYNCs sent after `resend_s` without a complete cycle


class LockstepLoop:
    """When the next SYNC goes: after the state of this one is out and a command came.

    Thread-safe: `on_state` runs on the CAN notifier's thread, `on_command` and `on_tick` on the
    node's executor. The SYNC itself (`run_cycle`, the master's `cycle`) is called outside the
    lock, by whichever of them released it, so exactly one runs per released cycle.

    Args:
        clock: the loop's `CycleClock` (the master's watches read it).
        run_cycle: sends the RPDOs with the commands in force and SYNC (`Cia402Master.cycle`),
            given the SYNC's simulated time.
        resend_s: wall time after which a silent controller gets the last state again, and an
            incomplete cycle (a TPDO lost) is given up and the next SYNC sent.
    """

    def __init__(
        self, clock: CycleClock, run_cycle: Callable[[float], None], resend_s: float
    ) -> None:
        self.clock = clock
        self._run_cycle = run_cycle
        self.resend_s = resend_s
        self.counters = LockstepCounters()
        self._lock = threading.Lock()
        self._started = False
        self._awaiting_command = False  # the state of the last SYNC is out
        self._since_wall_s = 0.0  # when the loop began waiting (for a state or a command)

    @property
    def started(self) -> bool:
        """The first SYNC has been sent."""
        return self._started

    def waiting_for_command_s(self, wall_s: float) -> float:
        """How long (wall) the loop has waited for the controller, or 0 when it does not."""
        with self._lock:
            return wall_s - self._since_wall_s if self._awaiting_command else 0.0

    def start(self, wall_s: float) -> None:
        """Send SYNC 0 (t = 0): the first state, which the controller then answers."""
        with self._lock:
            if self._started:
                return
            self._started = True
            self._since_wall_s = wall_s
        self._sync()

    def on_state(self, wall_s: float) -> None:
        """A complete cycle's state was handed on: the loop waits for the controller."""
        with self._lock:
            self.counters.states += 1
            self._since_wall_s = wall_s
            self._awaiting_command = True

    def on_command(self, wall_s: float) -> bool:
        """A command came; True when it released the next SYNC (it was sent)."""
        with self._lock:
            if not self._started:
                return False
            if not self._awaiting_command:
                # In force from the next SYNC, but it answers no state: it releases nothing
                # (a controller on a timer of its own, or a second answer to one state).
                self.counters.early_commands += 1
                return False
            self._awaiting_command = False
            self.counters.commands += 1
            self._since_wall_s = wall_s
        self._sync()
        return True

    def on_tick(self, wall_s: float) -> str:
        """The node's timer: what was due ('', 'resend' or 'incomplete').

        'resend': the controller was silent for `resend_s`; send the last state again.
        'incomplete': no complete cycle for `resend_s`; the next SYNC was sent.
        """
        with self._lock:
            if not self._started or wall_s - self._since_wall_s <= self.resend_s:
                return ""
            self._since_wall_s = wall_s
            if self._awaiting_command:
                self.counters.resent_states += 1
                return "resend"
            self.counters.incomplete_cycles += 1
        self._sync()
        return "incomplete"

    def sync_now(self) -> None:
        """Send the next SYNC whatever the loop waits for.

        For a teardown: the drives must see their disable, and no controller answers any more.
        """
        self._sync()

    def _sync(self) -> None:
        self.counters.syncs += 1
        self._run_cycle(self.clock.next_sync())
