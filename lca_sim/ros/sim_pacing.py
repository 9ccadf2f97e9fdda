"""The simulator node's simulated time: realtime pacing or lockstep, pause and step, the end.

Realtime: each tick runs the model steps wall time asks for, at most `MAX_CATCH_UP_PERIODS`
publish periods' worth; a larger backlog (a stall) is skipped and counted, so stamps stay
continuous and lag the wall clock (`skipped_s`, `stamp_lag_s`, a per-period `realtime_factor`,
WARN "stalled" beyond `STALL_WARN_S`). Pauses and `~/step` steps are neither running nor a
stall. Lockstep: one control period per command after the first state went out; while paused
a command waits for `~/step` or `~/resume`; at `lockstep_end_s` the run ends (later commands
are counted, nothing more goes out; raising it live resumes the run). `SimPacing` keeps these
counts for the shell, `lca_sim.ros.simulator_node`; docs/simulation-control.md and
docs/reliability.md have the whole story.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticStatus

from lca_sim.config.simulator_params import SimulatorNodeParams

MAX_CATCH_UP_PERIODS = 4
# Time skipped within one diagnostics period above which it is reported as a stall (WARN):
# five control periods. A few ms skipped on a loaded host is counted in skipped_s only.
STALL_WARN_S = 0.02


class SimPacing:
    """Model steps against the wall clock, the pause, the `~/step` budget and the run's end.

    Args:
        params: the node's parameters in force (a live set replaces them).
        lockstep: `timing_mode` lockstep (read-only).
    """

    def __init__(self, params: Callable[[], SimulatorNodeParams], lockstep: bool) -> None:
        now = time.monotonic()
        self._params = params
        self.lockstep = lockstep
        # Simulated time of step 0: lockstep 0, realtime the wall time at the first tick.
        self.time_base_s = 0.0 if lockstep else time.time()
        self.steps = 0  # model steps since start-up, or in lockstep since the last ~/reset
        self.started = not lockstep  # lockstep: the first state has gone out
        self.commanded = False  # a command came since start (before it: waiting, no loss)
        self.last_command_wall = now
        self.last_publish_wall = now
        self.overrun_steps = 0  # realtime: steps skipped after stalls
        self.paused = False
        self.pending = False  # lockstep, paused: a command came, its period has not run
        self.step_budget = 0  # lockstep, paused: commands ~/step still lets through
        self.after_end = 0  # lockstep: commands that came after the run's end
        self.end_reported = False
        self._wall_start = now  # moved on by the time skipped after a stall
        self._wall_clock_started = lockstep  # realtime: at the first tick
        self._wall_origin = now
        self._pause_began = 0.0  # monotonic, s
        self._paused_s = 0.0  # realtime: wall time spent paused (ended pauses), s
        self._manual_steps = 0  # realtime: model steps taken by ~/step (not wall-paced)
        # The last diagnostics period: wall time, steps, skipped, paused, ~/step steps.
        self._window_wall = now
        self._window_steps = 0
        self._window_overrun = 0
        self._window_paused_s = 0.0
        self._window_manual = 0

    @property
    def sim_time_s(self) -> float:
        """Simulated time of the published states (the /clock value in lockstep)."""
        return self.time_base_s + self.steps * self._params().dt_s

    @property
    def ended(self) -> bool:
        """A lockstep run has reached `lockstep_end_s`: no further state goes out."""
        end = self._params().lockstep_end_steps
        return self.lockstep and end is not None and self.steps >= end

    def command_came(self) -> None:
        """A command is in force now (the controller peer is alive)."""
        self.last_command_wall = time.monotonic()
        self.commanded = True

    # --- lockstep ------------------------------------------------------------------------

    def admit_paused_command(self) -> bool:
        """Lockstep, paused: True when `~/step` lets this command's period run, else it waits."""
        if self.step_budget > 0:
            self.step_budget -= 1
            return True
        self.pending = True
        return False

    def period_steps(self) -> int:
        """Lockstep: the model steps of the next period (a shorter last one up to the end)."""
        p = self._params()
        steps = p.substeps_per_period
        end = p.lockstep_end_steps
        return steps if end is None else min(steps, end - self.steps)

    def rewind(self) -> bool:
        """Lockstep `~/reset`: simulated time back to 0; True when it had moved on.

        A reset before the first period keeps the command already taken (the caller keeps it).
        """
        rewound = self.steps > 0
        if rewound:
            self.steps = 0
            self.pending = False
            self.step_budget = 0
        self.end_reported = False
        return rewound

    # --- pause and step ------------------------------------------------------------------

    def pause(self) -> bool:
        """Stop simulated time; False when it was stopped already."""
        if self.paused:
            return False
        self.paused = True
        self._pause_began = time.monotonic()
        return True

    def resume(self) -> bool:
        """Let simulated time run again; True when a lockstep command waits to run now.

        Realtime: the pause is not caught up (it is no backlog) nor is it command silence.
        """
        self.paused = False
        self.step_budget = 0
        if self.lockstep:
            pending, self.pending = self.pending, False
            return pending
        paused_s = time.monotonic() - self._pause_began
        self._paused_s += paused_s
        self._wall_start += paused_s
        self.last_command_wall += paused_s
        return False

    def budget_steps(self, periods: int) -> bool:
        """Lockstep `~/step`: the next `periods` commands run; True when one waits to run now."""
        self.step_budget = periods
        if not self.pending:
            return False
        self.pending = False
        self.step_budget -= 1
        return True

    def stepped(self, steps: int) -> None:
        """Realtime `~/step`: model steps taken by hand (not wall-paced)."""
        self.steps += steps
        self._manual_steps += steps

    def stepped_done(self, steps: int) -> None:
        """Realtime `~/step` done: a resume goes on from the time stepped to."""
        p = self._params()
        self._wall_start -= steps * p.dt_s / p.realtime_factor

    # --- realtime ------------------------------------------------------------------------

    def tick_started(self) -> None:
        """Realtime: simulated time starts at the first tick of the running node.

        Not at construction: between it and the first tick the process settles its heap (a
        full collection, 0.1-0.6 s on a 2-core host still starting its peers) and the executor
        comes up, and that time counted as a stall of the first diagnostics period (a WARN
        on every healthy start).
        """
        if self._wall_clock_started:
            return
        now = time.monotonic()
        self.time_base_s = time.time() - self.steps * self._params().dt_s
        self._wall_start = self._wall_origin = self._window_wall = now
        self.last_command_wall = self.last_publish_wall = now
        self._wall_clock_started = True

    def steps_due(self) -> int:
        """Realtime: the model steps due now, at most the catch-up cap; the rest is skipped.

        A backlog beyond MAX_CATCH_UP_PERIODS (a stall) is dropped: simulated time slips and
        the dropped steps are counted (`overrun_steps`). Also called by the diagnostics before
        they report, so a stall shows in the period it happened, even when the diagnostics
        timer runs before the next tick after it.
        """
        if not self._wall_clock_started:
            return 0  # simulated time starts at the first tick
        p = self._params()
        factor = p.realtime_factor
        due = round((time.monotonic() - self._wall_start) * factor / p.dt_s) - self.steps
        cap = MAX_CATCH_UP_PERIODS * max(1, round(factor / (p.publish_rate_hz * p.dt_s)))
        if due > cap:
            self.overrun_steps += due - cap
            self._wall_start += (due - cap) * p.dt_s / factor  # drop the backlog
            due = cap
        return due

    def set_realtime_factor(self, old: float, new: float) -> None:
        """Realtime: simulated time goes on from where it is, at the new pace."""
        now = self._pause_began if self.paused else time.monotonic()
        self._wall_start = now - (now - self._wall_start) * (old / new)

    def timing_health(self, values: dict[str, object]) -> tuple[bytes, str] | None:
        """Realtime: the stamp lag and the time skipped; a WARN for a period with a stall.

        The realtime factor is that of the last diagnostics period (simulated over wall time),
        so a stall shows in the period it happened instead of vanishing in a run's average.
        """
        if self.lockstep:
            return None
        if not self.paused:
            self.steps_due()  # a stall not yet seen by a tick is counted in this period
        dt_s = self._params().dt_s
        now = time.monotonic()
        paused_s = self._paused_s + (now - self._pause_began if self.paused else 0.0)
        # Wall time paused and steps taken by ~/step are neither running nor a stall.
        wall_s = now - self._window_wall - (paused_s - self._window_paused_s)
        paced = (self.steps - self._window_steps) - (self._manual_steps - self._window_manual)
        skipped = self.overrun_steps - self._window_overrun
        values["stamp_lag_s"] = (now - self._wall_origin) - self.steps * dt_s
        values["skipped_s"] = self.overrun_steps * dt_s
        values["paused_s"] = paused_s
        if wall_s > 1e-3:
            values["realtime_factor"] = paced * dt_s / wall_s
        self._window_wall, self._window_steps = now, self.steps
        self._window_overrun = self.overrun_steps
        self._window_paused_s, self._window_manual = paused_s, self._manual_steps
        if skipped * dt_s <= STALL_WARN_S:
            return None  # a scheduling hiccup of a few ms: counted (skipped_s), not a stall
        return DiagnosticStatus.WARN, (
            f"stalled: simulated time fell {skipped * dt_s:.3f} s behind the wall clock (skipped)"
        )
