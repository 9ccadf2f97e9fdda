"""The simulator node's simulated time: realtime pacing or lockstep, pause and step, the end.

`SimPacing` holds the node's side of it (the time base of the stamps, command and publish wall
times, the run's end as reported) and composes the pure clocks of `lca_sim.model.pacing`: a
`RealtimeClock` (steps due by the wall clock, the catch-up cap, pauses and `~/step` steps that
are neither running nor a stall) or a `LockstepGate` (a command's period runs now or waits for
`~/step` / `~/resume`). It reads the wall clock and passes it in. docs/simulation-control.md
has the whole story; `lca_sim.ros.simulator_node` is the shell that drives it.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticStatus

from lca_sim.config.simulator_params import SimulatorNodeParams
from lca_sim.model.pacing import LockstepGate, RealtimeClock
from lca_sim.runtime import Freeze, FreezeWatch, discounted

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
        p = params()
        self._params = params
        self.lockstep = lockstep
        # Simulated time of step 0: lockstep 0, realtime the wall time at the first tick.
        self.time_base_s = 0.0 if lockstep else time.time()
        self.started = not lockstep  # lockstep: the first state has gone out
        self.commanded = False  # a command came since start (before it: waiting, no loss)
        self.last_command_wall = now
        self.last_publish_wall = now
        self.after_end = 0  # lockstep: commands that came after the run's end
        self.end_reported = False
        self.gate = LockstepGate()  # lockstep's periods (unused in realtime)
        self.clock = RealtimeClock(p.dt_s, p.realtime_factor, p.publish_rate_hz, now)
        self.freezes = FreezeWatch()  # the command deadline forgives every freeze in full
        self._last_wake_wall = now  # the last timer callback that judged the wall clock

    @property
    def steps(self) -> int:
        """Model steps since start-up, or in lockstep since the last `~/reset`."""
        return self.gate.steps if self.lockstep else self.clock.steps

    @property
    def paused(self) -> bool:
        """Simulated time stands (`~/pause`)."""
        return self.gate.paused if self.lockstep else self.clock.paused

    @property
    def pending(self) -> bool:
        """Lockstep, paused: a command came and its period has not run."""
        return self.gate.pending

    @property
    def step_budget(self) -> int:
        """Lockstep, paused: the commands `~/step` still lets through."""
        return self.gate.budget

    @property
    def overrun_steps(self) -> int:
        """Realtime: model steps skipped after stalls."""
        return self.clock.overrun_steps

    @property
    def sim_time_s(self) -> float:
        """Simulated time of the published states (the /clock value in lockstep)."""
        return self.time_base_s + self.steps * self._params().dt_s

    @property
    def ended(self) -> bool:
        """A lockstep run has reached `lockstep_end_s`: no further state goes out."""
        return self.lockstep and self.gate.ended(self._params().lockstep_end_steps)

    def check_freeze(self, tick_period_s: float) -> Freeze | None:
        """A freeze of this process since its last timer callback, forgiven by the command deadline.

        The node's timers (the realtime tick or the lockstep kick, and the diagnostics) call
        this first, with the tick's period. A callback later than the last one by more than
        that period plus `FREEZE_THRESHOLD_S` means the process stood still (a collection, a
        library load, a paused host): the commands the controller sent meanwhile wait unread
        in the queue, and judging its silence on waking would blame it for the simulator's
        freeze (holding 0 V, a WARN asking whether the controller runs). So the last command's
        time moves on by the freeze, never past now: a controller silent while the node runs
        is still caught on time. The CAN bridge's master does the same (docs/can.md). None
        before simulated time starts (start-up is no freeze) and when no freeze was seen.
        """
        now = time.monotonic()
        late_s = now - self._last_wake_wall - tick_period_s
        self._last_wake_wall = now
        running = self.started if self.lockstep else self.clock.started
        if not running:
            return None
        freeze = self.freezes.check(late_s)
        if freeze is not None:
            self.last_command_wall = discounted(self.last_command_wall, freeze.discount_s, now)
        return freeze

    def command_came(self) -> None:
        """A command is in force now (the controller peer is alive)."""
        self.last_command_wall = time.monotonic()
        self.commanded = True

    def advanced(self, steps: int) -> None:
        """The plant took `steps` model steps (a lockstep period, or those due in realtime)."""
        (self.gate if self.lockstep else self.clock).advanced(steps)

    # --- lockstep ------------------------------------------------------------------------

    def admit_paused_command(self) -> bool:
        """Lockstep, paused: True when `~/step` lets this command's period run, else it waits."""
        return self.gate.command()

    def period_steps(self) -> int:
        """Lockstep: the model steps of the next period (a shorter last one up to the end)."""
        p = self._params()
        return self.gate.period_steps(p.substeps_per_period, p.lockstep_end_steps)

    def rewind(self) -> bool:
        """Lockstep `~/reset`: simulated time back to 0; True when it had moved on.

        A reset before the first period keeps the command already taken (the caller keeps it).
        """
        self.end_reported = False
        return self.gate.rewind()

    # --- pause and step ------------------------------------------------------------------

    def pause(self) -> bool:
        """Stop simulated time; False when it was stopped already."""
        if self.lockstep:
            return self.gate.pause()
        return self.clock.pause(time.monotonic())

    def resume(self) -> bool:
        """Let simulated time run again; True when a lockstep command waits to run now.

        Realtime: the pause is not caught up (it is no backlog) nor is it command silence.
        """
        if self.lockstep:
            return self.gate.resume()
        paused_s = self.clock.resume(time.monotonic())
        if paused_s is not None:
            self.last_command_wall += paused_s
        return False

    def budget_steps(self, periods: int) -> bool:
        """Lockstep `~/step`: the next `periods` commands run; True when one waits to run now."""
        return self.gate.step(periods)

    def stepped(self, steps: int) -> None:
        """Realtime `~/step`: one period's model steps taken by hand (not wall-paced)."""
        self.clock.advanced(steps)

    def stepped_done(self, steps: int) -> None:
        """Realtime `~/step` done, `steps` in all: a resume goes on from the time stepped to."""
        self.clock.stepped(steps)

    # --- realtime ------------------------------------------------------------------------

    def tick_started(self) -> None:
        """Realtime: simulated time starts at the first tick of the running node.

        Not at construction: between it and the first tick the process settles its heap (a
        full collection, 0.1-0.6 s on a 2-core host still starting its peers) and the executor
        comes up, and that time counted as a stall of the first diagnostics period (a WARN
        on every healthy start).
        """
        if self.clock.started:
            return
        now = time.monotonic()
        self.time_base_s = time.time() - self.steps * self._params().dt_s
        self.clock.start(now)
        self.last_command_wall = self.last_publish_wall = now

    def steps_due(self) -> int:
        """Realtime: the model steps due now, at most the catch-up cap; the rest is skipped.

        A backlog beyond the cap (a stall) is dropped: simulated time slips and the dropped
        steps are counted (`overrun_steps`). Also called by the diagnostics before they
        report, so a stall shows in the period it happened.
        """
        return self.clock.due(time.monotonic())

    def set_realtime_factor(self, realtime_factor: float) -> None:
        """Realtime: simulated time goes on from where it is, at the new pace."""
        self.clock.set_realtime_factor(realtime_factor, time.monotonic())

    def timing_health(self, values: dict[str, object]) -> tuple[bytes, str] | None:
        """Realtime: the stamp lag and the time skipped; a WARN for a period with a stall.

        The realtime factor is that of the last diagnostics period (simulated over wall time),
        so a stall shows in the period it happened instead of vanishing in a run's average.
        """
        if self.lockstep:
            return None
        window = self.clock.window(time.monotonic())
        values["stamp_lag_s"] = window.stamp_lag_s
        values["skipped_s"] = window.skipped_s
        values["paused_s"] = window.paused_s
        if window.realtime_factor is not None:
            values["realtime_factor"] = window.realtime_factor
        if window.stalled_s <= STALL_WARN_S:
            return None  # a scheduling hiccup of a few ms: counted (skipped_s), not a stall
        return DiagnosticStatus.WARN, (
            f"stalled: simulated time fell {window.stalled_s:.3f} s behind the wall clock (skipped)"
        )
