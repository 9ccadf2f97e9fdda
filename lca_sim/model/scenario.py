"""Scenarios: open-loop voltage experiments run headless on the simulator.

A scenario YAML gives the duration, the step, the record period, the initial pose and velocity,
and per axis a piecewise-linear voltage table. Unknown keys are errors.

    duration_s: 42.0
    dt_s: 1.0e-4
    record_period_s: 0.01
    initial:
      position: {pivot: 0.2}          # rad (m for the lift); axes not named start at 0
      velocity: {}                    # rad/s (m/s)
    inputs:
      pivot:
        time_s:    [0.0, 24.0, 25.0]  # non-decreasing; a repeated time is a step
        voltage_v: [0.0, 0.0, 9.0]    # held after the last point; axes not named get 0 V
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from lca_sim.errors import ConfigError
from lca_sim.model.schema import MappingReader, check_number
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

MAX_STEPS = 50_000_000  # a guard against a typo such as dt_s: 1e-9


@dataclass(frozen=True, slots=True)
class VoltageTable:
    """A piecewise-linear, right-continuous voltage command of one axis."""

    time_s: tuple[float, ...]
    voltage_v: tuple[float, ...]

    def sample(self, t_s: FloatArray) -> FloatArray:
        """The command at the times `t_s` (held constant outside the table)."""
        times = np.asarray(self.time_s)
        volts = np.asarray(self.voltage_v)
        right = np.searchsorted(times, t_s, side="right")
        out = np.empty_like(t_s)
        before = right == 0
        after = right == len(times)
        inside = ~(before | after)
        out[before] = volts[0]
        out[after] = volts[-1]
        hi = right[inside]
        lo = hi - 1
        frac = (t_s[inside] - times[lo]) / (times[hi] - times[lo])
        out[inside] = volts[lo] + frac * (volts[hi] - volts[lo])
        return out


@dataclass(frozen=True, slots=True)
class Scenario:
    """A validated open-loop scenario."""

    source: str
    duration_s: float
    dt_s: float
    record_period_s: float
    initial_position: tuple[float, ...]
    initial_velocity: tuple[float, ...]
    inputs: tuple[VoltageTable | None, ...]

    @property
    def n_steps(self) -> int:
        """Number of integration steps."""
        return round(self.duration_s / self.dt_s)

    @property
    def record_every(self) -> int:
        """Steps between two recorded rows."""
        return round(self.record_period_s / self.dt_s)


def parse_scenario(data: object, source: str, axis_names: tuple[str, ...]) -> Scenario:
    """Validate a scenario document against the robot's axis names.

    Raises:
        ConfigError: the file, the key and what was expected, in one line.

    """
    top = MappingReader(data, source)
    duration = top.number("duration_s", min_value=0.0, min_exclusive=True)
    dt = top.number("dt_s", min_value=0.0, min_exclusive=True, max_value=0.01)
    record = top.number("record_period_s", min_value=0.0, min_exclusive=True)
    if duration / dt > MAX_STEPS:
        raise ConfigError(
            source, "dt_s", f"expected at most {MAX_STEPS} steps, got {duration / dt:.3g}"
        )
    ratio = record / dt
    if abs(ratio - round(ratio)) > 1e-6 * ratio or round(ratio) < 1:
        raise ConfigError(
            source, "record_period_s", f"expected a whole multiple of dt_s = {dt:g}, got {record:g}"
        )

    position = [0.0] * len(axis_names)
    velocity = [0.0] * len(axis_names)
    if top.has("initial"):
        initial = top.sub("initial")
        for key, target in (("position", position), ("velocity", velocity)):
            if initial.has(key):
                values = initial.sub(key)
                for name in values.key_names():
                    target[_axis_index(values, name, axis_names)] = values.number(name)
                values.finish()
        initial.finish()

    tables: list[VoltageTable | None] = [None] * len(axis_names)
    if top.has("inputs"):
        inputs = top.sub("inputs")
        for name in inputs.key_names():
            tables[_axis_index(inputs, name, axis_names)] = _parse_table(inputs.sub(name))
        inputs.finish()
    top.finish()
    return Scenario(source, duration, dt, record, tuple(position), tuple(velocity), tuple(tables))


def _axis_index(reader: MappingReader, name: str, axis_names: tuple[str, ...]) -> int:
    """The index of an axis named as a key, or the ConfigError naming the key."""
    if name not in axis_names:
        raise ConfigError(
            reader.source, reader.key_path(name), f"expected an axis name ({', '.join(axis_names)})"
        )
    return axis_names.index(name)


def _parse_table(reader: MappingReader) -> VoltageTable:
    times_raw = reader.sequence("time_s")
    volts_raw = reader.sequence("voltage_v")
    if len(times_raw) != len(volts_raw) or not times_raw:
        raise ConfigError(
            reader.source,
            reader.key_path("voltage_v"),
            f"expected as many voltages as times (>= 1), got {len(volts_raw)} and {len(times_raw)}",
        )
    times = [
        check_number(t, reader.source, f"{reader.key_path('time_s')}[{i}]", min_value=0.0)
        for i, t in enumerate(times_raw)
    ]
    volts = [
        check_number(v, reader.source, f"{reader.key_path('voltage_v')}[{i}]")
        for i, v in enumerate(volts_raw)
    ]
    for i in range(1, len(times)):
        if times[i] < times[i - 1]:
            raise ConfigError(
                reader.source, f"{reader.key_path('time_s')}[{i}]", "expected non-decreasing times"
            )
        if i >= 2 and times[i] == times[i - 1] == times[i - 2]:
            raise ConfigError(
                reader.source, f"{reader.key_path('time_s')}[{i}]", "expected a time at most twice"
            )
    reader.finish()
    return VoltageTable(tuple(times), tuple(volts))


@dataclass(frozen=True, slots=True)
class Transition:
    """A drive-state change of one axis, at full step resolution."""

    time_s: float
    axis: str
    state: str
    position: float


@dataclass(frozen=True, slots=True)
class ScenarioResult:
    """Recorded rows of a scenario run, plus every drive-state transition.

    Attributes:
        time_s: [rows] record times.
        position, velocity: [rows, axes] joint side (rad, rad/s; m, m/s for the lift).
        signals: [rows, signal, axes], signals in `SIGNAL_NAMES` order.
        motion: [rows, axes] upper-level state (0, +1, -1).
        drive: [rows, axes] drive-state index into `state_names`.
        transitions: every drive-state change, in time order.

    """

    axis_names: tuple[str, ...]
    state_names: tuple[str, ...]
    time_s: FloatArray
    position: FloatArray
    velocity: FloatArray
    signals: FloatArray
    motion: IntArray
    drive: IntArray
    transitions: tuple[Transition, ...]

    def signal(self, name: str, axis: str) -> FloatArray:
        """One recorded signal of one axis."""
        return self.signals[:, SIGNAL_NAMES.index(name), self.axis_names.index(axis)]

    def phases(self, axis: str) -> list[Transition]:
        """The drive-state phases of one axis: where each one began."""
        return [t for t in self.transitions if t.axis == axis]


def _check_fits(sim: Simulator, scenario: Scenario) -> None:
    """The scenario's step is the simulator's and its pose is within the end stops."""
    if abs(sim.dt_s - scenario.dt_s) > 1e-15:
        raise ConfigError(scenario.source, "dt_s", f"expected the simulator's step {sim.dt_s:g}")
    for name, q, (q_min, q_max) in zip(
        sim.axis_names, scenario.initial_position, sim.position_limits, strict=True
    ):
        if not q_min <= q <= q_max:
            raise ConfigError(
                scenario.source,
                f"initial.position.{name}",
                f"expected a position within the joint's end stops [{q_min:g}, {q_max:g}], "
                f"got {q:g}",
            )


def _transitions(
    sim: Simulator, drive_log: IntArray, position_log: FloatArray, dt_s: float
) -> tuple[Transition, ...]:
    """Every drive-state change of every axis, at the step it happened (and each start)."""
    changed = np.nonzero(np.any(drive_log[1:] != drive_log[:-1], axis=1))[0] + 1
    transitions = []
    for k in [0, *changed.tolist()]:
        for a, name in enumerate(sim.axis_names):
            if k == 0 or drive_log[k, a] != drive_log[k - 1, a]:
                state = sim.state_names[int(drive_log[k, a])]
                transitions.append(Transition(k * dt_s, name, state, float(position_log[k, a])))
    return tuple(transitions)


def run_scenario(sim: Simulator, scenario: Scenario) -> ScenarioResult:
    """Run a scenario from its initial state and record it.

    The simulator's `dt_s` must equal the scenario's. Drive-state transitions are found at every
    step, not only at the recorded rows.
    """
    _check_fits(sim, scenario)
    n_steps = scenario.n_steps
    every = scenario.record_every
    n_axes = sim.n_axes
    t_grid: FloatArray = np.arange(n_steps + 1, dtype=np.float64) * scenario.dt_s
    commands = np.zeros((n_steps + 1, n_axes))
    for a, table in enumerate(scenario.inputs):
        if table is not None:
            commands[:, a] = table.sample(t_grid)

    sim.reset(scenario.initial_position, scenario.initial_velocity, commands[0])
    n_rows = n_steps // every + 1
    time_s = np.zeros(n_rows)
    state_rows = np.zeros((n_rows, 2, n_axes))
    signals = np.zeros((n_rows, len(SIGNAL_NAMES), n_axes))
    modes = np.zeros((n_rows, 2, n_axes), dtype=np.int64)
    drive_log = np.zeros((n_steps + 1, n_axes), dtype=np.int64)
    position_log = np.zeros((n_steps + 1, n_axes))

    state_view = sim.state_array
    mode_view = sim.mode_array
    signal_view = sim.signal_array
    drive_view = mode_view[1]
    position_view = state_view[0]

    def record(row: int, k: int) -> None:
        time_s[row] = k * scenario.dt_s
        state_rows[row] = state_view[:2]
        signals[row] = signal_view
        modes[row] = mode_view

    record(0, 0)
    drive_log[0] = drive_view
    position_log[0] = position_view
    row = 1
    step = sim.step
    for k in range(1, n_steps + 1):
        step(commands[k - 1])
        drive_log[k] = drive_view
        position_log[k] = position_view
        if k % every == 0:
            record(row, k)
            row += 1

    transitions = _transitions(sim, drive_log, position_log, scenario.dt_s)
    return ScenarioResult(
        axis_names=sim.axis_names,
        state_names=sim.state_names,
        time_s=time_s,
        position=state_rows[:, 0, :].copy(),
        velocity=state_rows[:, 1, :].copy(),
        signals=signals,
        motion=modes[:, 0, :].copy(),
        drive=modes[:, 1, :].copy(),
        transitions=transitions,
    )
