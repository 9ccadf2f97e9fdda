"""When model steps are due: the simulator node's realtime and lockstep pacing, as pure clocks.

`RealtimeClock` paces by a monotonic wall time passed in as `now_s` (it reads no clock): the steps
due since its start at `realtime_factor`, at most `MAX_CATCH_UP_PERIODS` ticks' worth (a stall's
backlog beyond that is skipped and counted), held while paused and not caught up on resume.
`LockstepGate` decides, per command, whether its control period runs now or waits for `~/step`
or `~/resume`. The node's behaviour they carry: docs/simulation-control.md.
"""

from __future__ import annotations

from dataclasses import dataclass

# A tick runs at most this many publishing periods of steps; a larger backlog is skipped.
MAX_CATCH_UP_PERIODS = 4


@dataclass(frozen=True, slots=True)
class TimingWindow:
    """Realtime timing since the last window, for the node's diagnostics.

    Attributes:
        stamp_lag_s: wall time since the start minus the simulated time, s.
        skipped_s: simulated time skipped after stalls since the start, s.
        paused_s: wall time paused since the start, s.
        realtime_factor: simulated over wall time in this window, pauses and `~/step` left
            out; None for a window under 1 ms of running wall time.
        stalled_s: simulated time skipped in this window, s.
    """

    stamp_lag_s: float
    skipped_s: float
    paused_s: float
    realtime_factor: float | None
    stalled_s: float


class RealtimeClock:
    """Model steps due by the wall clock (the node's `timing_mode: realtime`).

    Args:
        dt_s: the model step, s.
        realtime_factor: simulated seconds per wall second.
        publish_rate_hz: ticks per wall second (they set the catch-up cap).
        now_s: the monotonic wall time at construction, s. Simulated time starts at `start`.
    """

    def __init__(
        self, dt_s: float, realtime_factor: float, publish_rate_hz: float, now_s: float
    ) -> None:
        self.dt_s = dt_s
        self.realtime_factor = realtime_factor
        self.publish_rate_hz = publish_rate_hz
        self.started = False
        self.paused = False
        self.steps = 0  # model steps taken (paced and by `stepped`)
        self.overrun_steps = 0  # skipped after stalls
        self.manual_steps = 0  # taken by `stepped` (not wall-paced)
        self._wall_start = now_s  # moved on by time skipped, paused, or stepped
        self._wall_origin = now_s
        self._pause_began = 0.0
        self._paused_s = 0.0  # ended pauses
        self._window = (now_s, 0, 0, 0.0, 0)  # wall, steps, overrun, paused_s, manual

    def start(self, now_s: float) -> None:
        """Simulated time starts running now (the node: at its first tick)."""
        self._wall_start = self._wall_origin = now_s
        self._window = (now_s, *self._window[1:])
        self.started = True

    def due(self, now_s: float) -> int:
        """The model steps due at `now_s`, at most the catch-up cap; a larger backlog is skipped.

        0 before `start`. Does not take them (`advanced` does), so calling it again is safe:
        the node's diagnostics call it to count a stall in the period it happened.
        """
        if not self.started:
            return 0
        factor = self.realtime_factor
        due = round((now_s - self._wall_start) * factor / self.dt_s) - self.steps
        cap = MAX_CATCH_UP_PERIODS * max(1, round(factor / (self.publish_rate_hz * self.dt_s)))
        if due > cap:
            self.overrun_steps += due - cap
            self._wall_start += (due - cap) * self.dt_s / factor  # drop the backlog
            due = cap
        return due

    def advanced(self, n_steps: int) -> None:
        """`n_steps` of those due were taken."""
        self.steps += n_steps

    def stepped(self, n_steps: int) -> None:
        """Of the steps `advanced`, `n_steps` were `~/step`'s: a resume goes on from them.

        Called once per `~/step`, after its periods, with all their steps (the node's order).
        """
        self.manual_steps += n_steps
        self._wall_start -= n_steps * self.dt_s / self.realtime_factor

    def pause(self, now_s: float) -> bool:
        """Stop simulated time; False if it was paused already."""
        if self.paused:
            return False
        self.paused = True
        self._pause_began = now_s
        return True

    def resume(self, now_s: float) -> float | None:
        """Run again without catching up the pause; the pause's wall time, None if running."""
        if not self.paused:
            return None
        self.paused = False
        paused_s = now_s - self._pause_began
        self._paused_s += paused_s
        self._wall_start += paused_s  # no catch-up: the pause is not a backlog
        return paused_s

    def set_realtime_factor(self, realtime_factor: float, now_s: float) -> None:
        """A new pace; simulated time goes on from where it is (paused: where it stopped)."""
        now = self._pause_began if self.paused else now_s
        self._wall_start = now - (now - self._wall_start) * (self.realtime_factor / realtime_factor)
        self.realtime_factor = realtime_factor

    def window(self, now_s: float) -> TimingWindow:
        """The timing since the last call (or `start`), and a new window from `now_s`."""
        if not self.paused:
            self.due(now_s)  # a stall not yet seen by a tick is counted in this window
        dt_s = self.dt_s
        wall0, steps0, overrun0, paused0_s, manual0 = self._window
        paused_s = self._paused_s + (now_s - self._pause_began if self.paused else 0.0)
        # Wall time paused and steps taken by ~/step are neither running nor a stall.
        wall_s = now_s - wall0 - (paused_s - paused0_s)
        paced = (self.steps - steps0) - (self.manual_steps - manual0)
        skipped = self.overrun_steps - overrun0
        self._window = (now_s, self.steps, self.overrun_steps, paused_s, self.manual_steps)
        return TimingWindow(
            stamp_lag_s=(now_s - self._wall_origin) - self.steps * dt_s,
            skipped_s=self.overrun_steps * dt_s,
            paused_s=paused_s,
            realtime_factor=paced * dt_s / wall_s if wall_s > 1e-3 else None,
            stalled_s=skipped * dt_s,
        )


class LockstepGate:
    """Whether a command's control period runs now (the node's `timing_mode: lockstep`).

    Running, every command runs its period. Paused, a command waits (`pending`, the latest one)
    until `resume`, or until `step(n)`, which lets it and then the next n - 1 commands through,
    one period each. Simulated time is `steps` model steps from 0.
    """

    def __init__(self) -> None:
        self.steps = 0  # model steps taken since the start or the last rewind
        self.paused = False
        self.pending = False  # paused: a command came, its period has not run
        self.budget = 0  # paused: commands `step` still lets through

    def command(self) -> bool:
        """A command came: True when its period runs now, False when it waits."""
        if not self.paused:
            return True
        if self.budget > 0:
            self.budget -= 1
            return True
        self.pending = True
        return False

    def pause(self) -> bool:
        """Hold the commands' periods; False if paused already."""
        if self.paused:
            return False
        self.paused = True
        return True

    def resume(self) -> bool:
        """Run every command again: True when the pending command's period runs now."""
        if not self.paused:
            return False
        self.paused = False
        self.budget = 0
        ran, self.pending = self.pending, False
        return ran

    def step(self, n_periods: int) -> bool:
        """Paused: let `n_periods` commands through; True when the pending one runs now."""
        self.budget = n_periods
        if not self.pending:
            return False
        self.pending = False
        self.budget -= 1
        return True

    def period_steps(self, substeps_per_period: int, end_steps: int | None) -> int:
        """The model steps of the next period, shortened to end at `end_steps` (None: no end)."""
        if end_steps is None:
            return substeps_per_period
        return min(substeps_per_period, end_steps - self.steps)

    def ended(self, end_steps: int | None) -> bool:
        """The run has reached `end_steps` (None: it never ends)."""
        return end_steps is not None and self.steps >= end_steps

    def advanced(self, n_steps: int) -> None:
        """A period of `n_steps` was taken."""
        self.steps += n_steps

    def rewind(self) -> bool:
        """A reset: back to t = 0, nothing waits, nothing let through; False if at 0 already.

        At 0 nothing changes: a command taken before the first period keeps its place.
        """
        if self.steps == 0:
            return False
        self.steps = 0
        self.pending = False
        self.budget = 0
        return True
