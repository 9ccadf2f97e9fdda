"""The metric library of the sweeps: figures of one run, computed from its trace.

A `Trace` is what every kind of run (closed loop, open-loop voltages, the current step) records,
one row per sample: time, per axis its position, velocity, current, voltage and drive state,
and the reference of the loop the run closes (NaN where it has none). A metric is a function of
a trace and a few arguments (the axis, a time window, ...), declared once in `METRICS` with its
unit and arguments; a sweep spec names it (`lca_sim.analysis.metric_spec`).

Integrals (energy, time in a state) are left Riemann sums over the samples: a sample's value
holds until the next one, as a sampled controller sees it. Time windows are closed,
[from_s, to_s] (both optional: the whole run). A figure that does not exist in a run (no state
change, no crossing) is NaN, never an error. docs/sweeps.md has the table of every metric.

Pure: numbers in, numbers out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from lca_sim.errors import UnknownNameError

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

SIGNALS = ("position", "velocity", "current_a", "voltage_v")


@dataclass(frozen=True, slots=True)
class Trace:
    """The samples of one run, one row per sample.

    Attributes:
        axes: the robot's axis names (the columns of the per-axis arrays).
        state_names: drive-state names by index (`drive_state`).
        time_s: sample times, s, increasing.
        position: joint positions, rad (m for the lift).
        velocity: joint velocities, rad/s (m/s).
        current_a: armature currents, A.
        voltage_v: amplifier voltages, V.
        drive_state: drive-state index per axis.
        reference: the reference of the loop the run closes, per axis, in the unit of
            `reference_signal` (NaN on an axis it does not control, everywhere in an open-loop
            run).
        reference_signal: which signal `reference` is for: `velocity` (closed loop),
            `current_a` (the current step), or "" (open loop).
        position_limits: each axis's end stops (lower, upper), rad (m).
    """

    axes: tuple[str, ...]
    state_names: tuple[str, ...]
    time_s: FloatArray
    position: FloatArray
    velocity: FloatArray
    current_a: FloatArray
    voltage_v: FloatArray
    drive_state: IntArray
    reference: FloatArray
    reference_signal: str
    position_limits: tuple[tuple[float, float], ...]

    def axis(self, name: str) -> int:
        """The column of an axis.

        Raises:
            UnknownNameError: not an axis of the robot.
        """
        if name not in self.axes:
            raise UnknownNameError("axis", name, self.axes)
        return self.axes.index(name)

    def signal(self, name: str) -> FloatArray:
        """One of `SIGNALS`, every axis."""
        values: FloatArray = getattr(self, name)
        return values

    def window(self, from_s: float | None, to_s: float | None) -> npt.NDArray[np.bool_]:
        """The samples in [from_s, to_s] (None: open)."""
        t = self.time_s
        keep = np.ones(len(t), dtype=bool)
        if from_s is not None:
            keep &= t >= from_s
        if to_s is not None:
            keep &= t <= to_s
        return keep

    def hold_s(self) -> FloatArray:
        """How long each sample holds: the time to the next one (0 for the last)."""
        held: FloatArray = np.append(np.diff(self.time_s), 0.0)
        return held


@dataclass(frozen=True, slots=True)
class MetricArgs:
    """The arguments a metric reads, validated where the spec enters.

    Attributes:
        axis: the axis the metric is of.
        from_s, to_s: the time window, s (None: the run's start / end).
        signal: for the step-response metrics, one of `SIGNALS`.
        target: the value a step settles to; None: the signal's last value in the window.
        band: the settling band, a fraction of the target (0.05: the paper's 5 % t_r).
        low, high: the rise-time levels, fractions of the target.
        states: drive-state names (time in state, state change into).
        margin: how close to an end stop counts as contact, rad (m).
        occurrence: which change into `states` (1 the first, 2 the second, -1 the last).
    """

    axis: str
    from_s: float | None = None
    to_s: float | None = None
    signal: str = "velocity"
    target: float | None = None
    band: float = 0.05
    low: float = 0.1
    high: float = 0.9
    states: tuple[str, ...] = ()
    margin: float = 1e-6
    occurrence: int = 1


MetricFunction = Callable[[Trace, MetricArgs], float]


@dataclass(frozen=True, slots=True)
class MetricDef:
    """One entry of the library: the function, its unit and the arguments it takes."""

    function: MetricFunction
    unit: str
    description: str
    args: frozenset[str]


# --- the library -------------------------------------------------------------------------------


def _column(trace: Trace, args: MetricArgs, signal: str) -> tuple[FloatArray, FloatArray]:
    """(time, values) of one signal of the metric's axis, in its window."""
    a = trace.axis(args.axis)
    keep = trace.window(args.from_s, args.to_s)
    return trace.time_s[keep], trace.signal(signal)[keep, a]


def tracking_error(trace: Trace, args: MetricArgs) -> FloatArray:
    """Reference minus the signal it is for, on the metric's axis and window (may be empty)."""
    if not trace.reference_signal:
        return np.full(0, math.nan)
    a = trace.axis(args.axis)
    return window_error(
        trace.time_s,
        trace.reference[:, a],
        trace.signal(trace.reference_signal)[:, a],
        args.from_s,
        args.to_s,
    )


def window_error(
    time_s: FloatArray,
    reference: FloatArray,
    signal: FloatArray,
    from_s: float | None,
    to_s: float | None,
) -> FloatArray:
    """Reference minus signal at the samples in [from_s, to_s] (None: open), NaNs left out."""
    keep = np.ones(len(time_s), dtype=bool)
    if from_s is not None:
        keep &= time_s >= from_s
    if to_s is not None:
        keep &= time_s <= to_s
    error: FloatArray = reference[keep] - signal[keep]
    return error[np.isfinite(error)]


def error_rms(error: FloatArray) -> float:
    """Root mean square of an error's samples (NaN for none)."""
    return float(np.sqrt(np.mean(error**2))) if len(error) else math.nan


def error_max(error: FloatArray) -> float:
    """Largest |error| of the samples (NaN for none)."""
    return float(np.max(np.abs(error))) if len(error) else math.nan


def tracking_error_rms(trace: Trace, args: MetricArgs) -> float:
    """Root mean square of reference minus signal over the window's samples."""
    return error_rms(tracking_error(trace, args))


def tracking_error_max(trace: Trace, args: MetricArgs) -> float:
    """Largest |reference - signal| over the window's samples."""
    return error_max(tracking_error(trace, args))


# --- the velocity tracking error of a closed-loop run (lca-hil fig15, lca-hil run, bench) -----


@dataclass(frozen=True, slots=True)
class VelocityTracking:
    """The velocity tracking error of one joint over the reference profile's span.

    The one definition `lca-hil fig15`, `lca-hil run` and bench/closed_loop.py report: the
    library's `tracking_error_max` / `tracking_error_rms` (reference minus velocity at every
    state) over `tracking_window_s`.

    Attributes:
        joint: the joint the profile moves.
        unit: `rad/s`, or `m/s` for a prismatic joint.
        from_s, to_s: the window, s (closed; see `tracking_window_s`).
        max, rms: the error's largest magnitude and root mean square, in `unit`.
    """

    joint: str
    unit: str
    from_s: float
    to_s: float
    max: float
    rms: float

    def figures(self) -> dict[str, float]:
        """The figures by name, the unit in the name: `tracking_error_max_rad_s`, ..."""
        suffix = self.unit.replace("/", "_")
        return {f"tracking_error_max_{suffix}": self.max, f"tracking_error_rms_{suffix}": self.rms}

    def describe(self) -> str:
        """One line: the joint, the window, the figures with their unit."""
        return (
            f"{self.joint} velocity tracking error over {self.from_s:g}-{self.to_s:.6g} s: "
            f"max {self.max:.4g} {self.unit}, rms {self.rms:.4g} {self.unit}"
        )


def tracking_window_s(start_s: float, end_s: float) -> tuple[float, float]:
    """The velocity tracking window of a profile: its span, the start in, the end out.

    A built-in profile (`lca_control.profiles`) gives its reference from `start_s` on and steps
    it back to 0 at `end_s`: the state at `end_s` meets a step, which is no tracking, so the
    closed window ends at the float just before `end_s` ([start_s, end_s) on any time grid;
    the sweeps' `to_s: 10.99` for the Fig. 15 ramp at 4 ms states). The breakaway from the
    self-locking hold at the ramp's start is in the window: the gear's stop states are part of
    what the loop has to follow through.
    """
    return start_s, math.nextafter(end_s, -math.inf)


def velocity_tracking(
    joint: str,
    prismatic: bool,
    window_s: tuple[float, float],
    time_s: FloatArray,
    reference: FloatArray,
    velocity: FloatArray,
) -> VelocityTracking:
    """`VelocityTracking` of one joint's states: reference minus velocity in `window_s`."""
    error = window_error(time_s, reference, velocity, *window_s)
    return VelocityTracking(
        joint, "m/s" if prismatic else "rad/s", *window_s, error_max(error), error_rms(error)
    )


def _target(values: FloatArray, args: MetricArgs) -> float:
    return float(values[-1]) if args.target is None else args.target


def overshoot_pct(trace: Trace, args: MetricArgs) -> float:
    """How far the signal goes past its target, % of the target (0 if it never passes it).

    The target is `target` or the signal's last value in the window, as the paper reads
    Fig. 13 (the response's final value); the peak is taken in the target's direction.
    """
    _, values = _column(trace, args, args.signal)
    if not len(values):
        return math.nan
    final = _target(values, args)
    if final == 0.0:
        return math.nan
    peak = float(np.max(values)) if final > 0.0 else float(np.min(values))
    return max(0.0, (peak - final) / final * 100.0)


def rise_time_s(trace: Trace, args: MetricArgs) -> float:
    """Time from the first sample at `low` of the target to the first at `high` (10 -> 90 %)."""
    t, values = _column(trace, args, args.signal)
    if not len(values):
        return math.nan
    final = _target(values, args)
    if final == 0.0:
        return math.nan
    scaled = values / final
    above_low = np.flatnonzero(scaled >= args.low)
    above_high = np.flatnonzero(scaled >= args.high)
    if not len(above_low) or not len(above_high):
        return math.nan
    return float(t[above_high[0]] - t[above_low[0]])


def settling_time_s(trace: Trace, args: MetricArgs) -> float:
    """Time from the window's start until the signal stays within `band` of the target.

    The first sample after the last one outside the band (the paper's 5 % response time t_r
    with `band` 0.05); 0 if it never leaves the band, NaN if it ends outside.
    """
    t, values = _column(trace, args, args.signal)
    if not len(values):
        return math.nan
    final = _target(values, args)
    outside = np.flatnonzero(np.abs(values - final) > args.band * abs(final))
    if not len(outside):
        return 0.0
    if outside[-1] + 1 >= len(t):
        return math.nan
    return float(t[outside[-1] + 1] - t[0])


def peak_current_a(trace: Trace, args: MetricArgs) -> float:
    """Largest |current| in the window, A."""
    _, current = _column(trace, args, "current_a")
    return float(np.max(np.abs(current))) if len(current) else math.nan


def rms_current_a(trace: Trace, args: MetricArgs) -> float:
    """Root mean square current over the window's samples, A."""
    _, current = _column(trace, args, "current_a")
    return float(np.sqrt(np.mean(current**2))) if len(current) else math.nan


def _electrical_power(trace: Trace, args: MetricArgs) -> tuple[FloatArray, FloatArray]:
    """(v i, how long each sample holds) in the window, W and s."""
    a = trace.axis(args.axis)
    keep = trace.window(args.from_s, args.to_s)
    power: FloatArray = trace.voltage_v[keep, a] * trace.current_a[keep, a]
    hold = np.append(np.diff(trace.time_s[keep]), 0.0)
    return power, hold


def energy_drawn_j(trace: Trace, args: MetricArgs) -> float:
    """Electrical energy into the motor from the amplifier, J: the sum of max(v i, 0) dt."""
    power, hold = _electrical_power(trace, args)
    return float(np.sum(np.maximum(power, 0.0) * hold))


def energy_returned_j(trace: Trace, args: MetricArgs) -> float:
    """Electrical energy the motor sends back to the amplifier, J: the sum of max(-v i, 0) dt."""
    power, hold = _electrical_power(trace, args)
    return float(np.sum(np.maximum(-power, 0.0) * hold))


def _state_indices(trace: Trace, states: tuple[str, ...]) -> list[int]:
    for name in states:
        if name not in trace.state_names:
            raise UnknownNameError("drive state", name, trace.state_names)
    return [trace.state_names.index(name) for name in states]


def time_in_state_s(trace: Trace, args: MetricArgs) -> float:
    """Time the axis spends in any of `states` (each sample holds to the next), s."""
    a = trace.axis(args.axis)
    keep = trace.window(args.from_s, args.to_s)
    drive = trace.drive_state[keep, a]
    hold = np.append(np.diff(trace.time_s[keep]), 0.0)
    inside = np.isin(drive, _state_indices(trace, args.states))
    return float(np.sum(hold[inside]))


def _changes(trace: Trace, args: MetricArgs) -> tuple[IntArray, int]:
    """Sample indices (into the whole trace) where the axis's drive state changes, in window."""
    a = trace.axis(args.axis)
    drive = trace.drive_state[:, a]
    changed = np.flatnonzero(drive[1:] != drive[:-1]) + 1
    keep = trace.window(args.from_s, args.to_s)
    return changed[keep[changed]], a


def _change_into(trace: Trace, args: MetricArgs) -> int | None:
    """The sample of the `occurrence`-th change into any of `states` in the window (or None)."""
    changed, a = _changes(trace, args)
    wanted = _state_indices(trace, args.states)
    into = changed[np.isin(trace.drive_state[changed, a], wanted)]
    k = args.occurrence - 1 if args.occurrence > 0 else len(into) + args.occurrence
    return int(into[k]) if 0 <= k < len(into) else None


def state_change_position(trace: Trace, args: MetricArgs) -> float:
    """The position at the `occurrence`-th change into any of `states` in the window, rad (m)."""
    k = _change_into(trace, args)
    return math.nan if k is None else float(trace.position[k, trace.axis(args.axis)])


def state_change_time_s(trace: Trace, args: MetricArgs) -> float:
    """The time of the `occurrence`-th change into any of `states` in the window, s."""
    k = _change_into(trace, args)
    return math.nan if k is None else float(trace.time_s[k])


def state_change_count(trace: Trace, args: MetricArgs) -> float:
    """How many times the axis's drive state changes in the window (between samples)."""
    return float(len(_changes(trace, args)[0]))


def travel(trace: Trace, args: MetricArgs) -> float:
    """Position at the window's end minus at its start, rad (m)."""
    _, position = _column(trace, args, "position")
    return float(position[-1] - position[0]) if len(position) else math.nan


def hold_drift(trace: Trace, args: MetricArgs) -> float:
    """Largest |position - position at the window's start| in the window, rad (m)."""
    _, position = _column(trace, args, "position")
    return float(np.max(np.abs(position - position[0]))) if len(position) else math.nan


def end_stop_contact(trace: Trace, args: MetricArgs) -> float:
    """1 if the axis comes within `margin` of an end stop in the window, else 0."""
    _, position = _column(trace, args, "position")
    lower, upper = trace.position_limits[trace.axis(args.axis)]
    touching = (position <= lower + args.margin) | (position >= upper - args.margin)
    return 1.0 if bool(np.any(touching)) else 0.0


_WINDOW = frozenset({"axis", "from_s", "to_s"})
# The metrics of a loop's reference: NaN on a run that follows no reference (open loop).
TRACKING_METRICS = frozenset({"tracking_error_rms", "tracking_error_max"})
_STEP = _WINDOW | {"signal", "target"}

METRICS: dict[str, MetricDef] = {
    "tracking_error_rms": MetricDef(
        tracking_error_rms, "unit of the reference", "rms of reference - signal", _WINDOW
    ),
    "tracking_error_max": MetricDef(
        tracking_error_max, "unit of the reference", "max |reference - signal|", _WINDOW
    ),
    "overshoot_pct": MetricDef(overshoot_pct, "%", "peak past the target", _STEP),
    "rise_time_s": MetricDef(
        rise_time_s, "s", "low -> high of the target", _STEP | {"low", "high"}
    ),
    "settling_time_s": MetricDef(
        settling_time_s, "s", "until within band of the target", _STEP | {"band"}
    ),
    "peak_current_a": MetricDef(peak_current_a, "A", "max |i|", _WINDOW),
    "rms_current_a": MetricDef(rms_current_a, "A", "rms of i", _WINDOW),
    "energy_drawn_j": MetricDef(energy_drawn_j, "J", "sum of max(v i, 0) dt", _WINDOW),
    "energy_returned_j": MetricDef(energy_returned_j, "J", "sum of max(-v i, 0) dt", _WINDOW),
    "time_in_state_s": MetricDef(
        time_in_state_s, "s", "time in any of the states", _WINDOW | {"states"}
    ),
    "state_change_position": MetricDef(
        state_change_position,
        "rad (m)",
        "position at the k-th change into",
        _WINDOW | {"states", "occurrence"},
    ),
    "state_change_time_s": MetricDef(
        state_change_time_s, "s", "time of the k-th change into", _WINDOW | {"states", "occurrence"}
    ),
    "state_change_count": MetricDef(state_change_count, "1", "drive-state changes", _WINDOW),
    "travel": MetricDef(travel, "rad (m)", "position(to) - position(from)", _WINDOW),
    "hold_drift": MetricDef(hold_drift, "rad (m)", "max |position - position(from)|", _WINDOW),
    "end_stop_contact": MetricDef(
        end_stop_contact, "1 (0 or 1)", "within margin of an end stop", _WINDOW | {"margin"}
    ),
}
