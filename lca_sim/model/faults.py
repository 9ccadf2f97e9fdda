"""Fault injection: what a user can break in the plant, and how it enters the model (pure core).

Every fault goes through the model, never around it (docs/faults.md):

* **mechanics and actuator** faults change the constants the compiled step runs on (the packed
  `model` array of `Simulator`, and Pinocchio's link inertias for a payload), so the state
  machine, eq. (10) and the end stops treat them as they treat the robot's own values: a jam is
  a breakaway and Coulomb friction no motor can overcome, safe torque off opens the armature
  circuit (the power stage's switches off: no current, no torque, no braking), a demagnetised
  motor has a smaller k_t for its torque and its back-EMF alike;
* the **current sensor** faults act where a drive's sensor acts: on the current the in-drive
  current loop regulates (`CommandedPlant`), and on the current the plant reports;
* the **encoder** faults and **backlash** act on what the plant reports of its joints
  (`measure`): the controller closes its loops on them, the dynamics keep the true state;
* the **I2t** monitor integrates i^2 - I_n^2 as drives do, derates the current to the rated
  current at 100 % and trips (safe torque off, latched) when the demand stays above the derated
  limit for `i2t_trip_after_s`;
* the **link** faults (dropped, delayed, stale state messages) act on the simulator node's
  publishing: `StateLink`.

With no fault set, nothing here runs: `CommandedPlant` and the simulator node take their
original paths, so results are bit for bit those without fault injection.

Units: a joint's position faults are in rad, or m for a prismatic joint (the lift), as
joint_states; currents in A; friction at the motor shaft in N m; a payload in kg.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from lca_control.parameters import ParameterError, ParameterTable, ParamKind, ParamSpec
from lca_sim.errors import ConfigError
from lca_sim.model import kernel
from lca_sim.model.simulator import Simulator

FloatArray = npt.NDArray[np.float64]

B, D, S, INT = ParamKind.BOOL, ParamKind.DOUBLE, ParamKind.STRING, ParamKind.INTEGER

# A joint that cannot move: breakaway and Coulomb friction at the motor shaft, N m (no motor
# here gives a thousandth of it).
JAM_FRICTION_NM = 1.0e6
# Safe torque off: the armature circuit is open (the power stage's transistors off). With the
# kernel's exact electrical step, a resistance this large makes the current vanish at once
# and stay at nanoamperes, without a special case in the compiled step.
OPEN_CIRCUIT_OHM = 1.0e12
# The I2t monitor derates at this fraction of its capacity (I_peak^2 - I_n^2) t_peak.
I2T_DERATE_AT = 1.0

LINK = "link"  # the node-level namespace: faults.link.<kind>
CATEGORIES = ("sensor", "actuator", "mechanics", "thermal", "communication")


@dataclass(frozen=True, slots=True)
class FaultKind:
    """One kind of fault: its parameter (off by default), its category and what it does."""

    spec: ParamSpec
    category: str
    does: str

    @property
    def name(self) -> str:
        """The kind's name (the last part of `faults.<joint>.<kind>`)."""
        return self.spec.name

    def is_on(self, value: object) -> bool:
        """True when `value` is not the kind's default (the fault acts)."""
        return bool(value != self.spec.default)


def _kind(
    name: str,
    kind: ParamKind,
    default: object,
    category: str,
    description: str,
    does: str,
    low: float | None = None,
    high: float | None = None,
) -> FaultKind:
    return FaultKind(ParamSpec(name, kind, default, description, low, high), category, does)


JOINT_FAULTS: tuple[FaultKind, ...] = (
    _kind("encoder_freeze", B, False, "sensor", "the joint's encoder reading stops changing",
          "position holds its last reading, velocity reads 0"),
    _kind("encoder_bias", D, 0.0, "sensor", "offset added to the position reading, rad (m)",
          "position + bias", -10.0, 10.0),
    _kind("encoder_noise", D, 0.0, "sensor",
          "standard deviation of white noise on the position reading, rad (m)",
          "position + N(0, s^2); velocity + N(0, 2 s^2) / period^2 (a differentiated encoder)",
          0.0, 1.0),
    _kind("encoder_quantisation", D, 0.0, "sensor", "encoder resolution: step of the position "
          "reading, rad (m); 0: none", "position rounded to whole steps", 0.0, 1.0),
    _kind("encoder_dropout", D, 0.0, "sensor",
          "probability that a reading is lost (published as NaN)",
          "position and velocity NaN in that sample", 0.0, 1.0),
    _kind("current_offset_a", D, 0.0, "sensor", "offset of the current sensor, A",
          "measured current + offset: the current loop regulates the wrong current", -20.0, 20.0),
    _kind("current_gain_error", D, 0.0, "sensor", "relative gain error of the current sensor "
          "(0.1: reads 10 % high)", "measured current * (1 + error)", -0.9, 10.0),
    _kind("current_noise_a", D, 0.0, "sensor",
          "standard deviation of white noise on the current sensor, A",
          "measured current + N(0, s^2) at every model step", 0.0, 20.0),
    _kind("supply_sag", D, 0.0, "actuator", "fraction of the supply voltage lost (0.3: the "
          "amplifier gives at most 70 % of its voltage limit)",
          "voltage_limit_v * (1 - sag) in the current loop and the amplifier", 0.0, 1.0),
    _kind("current_limit_a", D, 0.0, "actuator", "the drive's current limit, A (0: none "
          "beyond the plant's own)", "current setpoints clamped to +-limit", 0.0, 100.0),
    _kind("torque_constant_loss", D, 0.0, "actuator", "fraction of k_t lost (a demagnetised "
          "motor, a lost phase)", "k_t * (1 - loss), for the torque and the back-EMF", 0.0, 0.99),
    _kind("sto", B, False, "actuator", "safe torque off: the power stage is off",
          "armature circuit open: no current, no torque; the gear's stop state decides"),
    _kind("eta_m_drift", D, 0.0, "mechanics", "added to eta_m of the drifted drive states "
          "(gear wear)", "eta_m + drift, at least 0", -1.0, 1.0),
    _kind("eta_l_drift", D, 0.0, "mechanics", "added to eta_l of the drifted drive states "
          "(gear wear)", "eta_l + drift, at least 0", -1.0, 1.0),
    _kind("drift_state", S, "", "mechanics", "the drive state eta_m_drift and eta_l_drift "
          "apply to (empty: every moving state)", "selects the Table 1 row(s) drifted"),
    _kind("backlash", D, 0.0, "mechanics", "play between the gear and the load side encoder, "
          "rad (m)", "the position reading follows the joint with this play (a play "
          "operator): it lags by up to the play after each reversal", 0.0, 1.0),
    _kind("extra_friction_nm", D, 0.0, "mechanics", "friction added at the motor shaft, N m",
          "static (breakaway) and Coulomb friction + extra, both directions", 0.0, 100.0),
    _kind("payload_kg", D, 0.0, "mechanics", "mass added to the joint's link, kg",
          "the link's mass (and rotational inertia in proportion) in Pinocchio's model",
          -1000.0, 1000.0),
    _kind("jam", B, False, "mechanics", "the joint jams",
          "breakaway and Coulomb friction no motor can overcome: the axis stops and stays"),
    _kind("i2t_rated_a", D, 0.0, "thermal", "I2t monitor: rated (continuous) current, A "
          "(0: no monitor)", "integrates i^2 - I_n^2; derates to I_n, then trips", 0.0, 100.0),
    _kind("i2t_peak_a", D, 20.0, "thermal", "I2t monitor: peak current, A", "capacity "
          "(I_peak^2 - I_n^2) * i2t_peak_time_s", 0.0, 100.0),
    _kind("i2t_peak_time_s", D, 2.0, "thermal", "I2t monitor: time the peak current is "
          "allowed, s", "see i2t_peak_a", 0.0, 3600.0),
    _kind("i2t_trip_after_s", D, 1.0, "thermal", "I2t monitor: trip (safe torque off, "
          "latched) when the current demand stays above the derated limit this long, s",
          "the drive faults; clear it by setting i2t_rated_a to 0", 0.0, 3600.0),
)  # fmt: skip

LINK_FAULTS: tuple[FaultKind, ...] = (
    _kind("state_drop", D, 0.0, "communication",
          "probability that a state instant is not published", "no message for it", 0.0, 1.0),
    _kind("state_delay_s", D, 0.0, "communication",
          "age of the published states, s (they go out this much later)",
          "each instant is published this much later, with its own stamp", 0.0, 10.0),
    _kind("state_stale", B, False, "communication",
          "the published state stops updating (same stamp and values again)",
          "the last instant before it is published again"),
    _kind("seed", INT, 0, "communication", "seed of the noise and dropout random numbers",
          "same seed, same faults: runs repeat to the bit", 0.0, 2.0**31 - 1),
)  # fmt: skip

JOINT_KIND = {k.name: k for k in JOINT_FAULTS}
LINK_KIND = {k.name: k for k in LINK_FAULTS}
# The kinds a schedule may name (seed is configuration, not a fault).
SCHEDULABLE = frozenset(JOINT_KIND) | (frozenset(LINK_KIND) - {"seed"})


def parameter_name(owner: str, kind: str) -> str:
    """`faults.<joint>.<kind>` or `faults.link.<kind>`."""
    return f"faults.{owner}.{kind}"


def fault_table(joints: Sequence[str]) -> ParameterTable:
    """Every fault parameter of a plant with these joints (all live)."""
    specs = [
        ParamSpec(
            parameter_name(joint, k.name),
            k.spec.kind,
            k.spec.default,
            k.spec.description,
            k.spec.low,
            k.spec.high,
        )
        for joint in joints
        for k in JOINT_FAULTS
    ]
    specs += [
        ParamSpec(
            parameter_name(LINK, k.name),
            k.spec.kind,
            k.spec.default,
            k.spec.description,
            k.spec.low,
            k.spec.high,
        )
        for k in LINK_FAULTS
    ]
    return ParameterTable(tuple(specs))


FAULT_SCHEDULE = "fault_schedule"  # the node parameter naming a schedule file


def is_fault_parameter(name: str) -> bool:
    """True for a plant node's fault parameters (`faults.*`, `fault_schedule`)."""
    return name.startswith("faults.") or name == FAULT_SCHEDULE


def standing_faults(values: Mapping[str, Any], joints: Sequence[str]) -> tuple[ScheduledFault, ...]:
    """The `faults.<owner>.<kind>` values of a params file as entries on from t = 0 for good.

    Raises:
        ParameterError: an unknown name or a value outside its range.
    """
    table = fault_table(joints)
    entries = []
    for name, value in values.items():
        if not name.startswith("faults."):
            continue
        if name not in table:
            raise ParameterError(name, "faults.<joint>.<kind> of a known joint and kind", value)
        checked = table[name].check(value)
        owner, kind = split_name(name)
        if checked != table[name].default:
            entries.append(ScheduledFault(owner, kind, checked, 0.0, math.inf))
    return tuple(entries)


def split_name(name: str) -> tuple[str, str]:
    """(owner, kind) of `faults.<owner>.<kind>`.

    Raises:
        ParameterError: not a fault parameter name.
    """
    parts = name.split(".")
    if len(parts) != 3 or parts[0] != "faults":
        raise ParameterError(name, "faults.<joint>.<kind> or faults.link.<kind>", name)
    return parts[1], parts[2]


# --- schedules ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ScheduledFault:
    """One entry of a fault schedule: `kind` of `owner` is `value` from start_s until end_s."""

    owner: str  # a joint, or LINK
    kind: str
    value: Any
    start_s: float
    end_s: float  # inf: to the end of the run

    def active(self, t_s: float) -> bool:
        """True at simulated time t_s (start inclusive, end exclusive)."""
        return self.start_s <= t_s < self.end_s


def parse_fault_schedule(
    data: object, source: str, joints: Sequence[str]
) -> tuple[ScheduledFault, ...]:
    """A schedule from YAML data: a mapping with `faults:`, a list of entries.

    Each entry: `kind`, `value`, `start_s`, optional `end_s` (default: never ends) and `joint`
    (required for a joint's fault, absent for a link fault). Entries of one kind and owner may
    not overlap in time.

    Raises:
        ConfigError: the first bad key, named by its path.
    """
    raw = schedule_entries(data, source)
    entries = [_parse_entry(item, source, f"faults[{i}]", joints) for i, item in enumerate(raw)]
    _check_overlaps(entries, source)
    return tuple(sorted(entries, key=lambda e: (e.start_s, e.owner, e.kind)))


def schedule_entries(data: object, source: str) -> list[Any]:
    """The unparsed entries of a schedule document: a mapping with only a `faults` list.

    Raises:
        ConfigError: not such a mapping, or another key.
    """
    if not isinstance(data, Mapping) or "faults" not in data:
        raise ConfigError(source, "faults", "expected a mapping with a 'faults' list")
    extra = sorted(str(k) for k in data if k != "faults")
    if extra:
        raise ConfigError(source, extra[0], "unknown key; a fault schedule has only 'faults'")
    raw = data["faults"]
    if not isinstance(raw, list):
        raise ConfigError(source, "faults", "expected a list of fault entries")
    return raw


def _parse_entry(item: object, source: str, path: str, joints: Sequence[str]) -> ScheduledFault:
    if not isinstance(item, Mapping):
        raise ConfigError(source, path, "expected a mapping with kind, value, start_s")
    allowed = {"joint", "kind", "value", "start_s", "end_s"}
    for key in item:
        if key not in allowed:
            raise ConfigError(source, f"{path}.{key}", f"unknown key; expected {sorted(allowed)}")
    owner, spec = _entry_target(item, source, path, joints)
    if "value" not in item:
        raise ConfigError(source, f"{path}.value", "missing")
    try:
        value = spec.check(item["value"])
    except ParameterError as exc:
        raise ConfigError(source, f"{path}.value", str(exc)) from exc
    start_s = _time(item.get("start_s"), source, f"{path}.start_s")
    end_s = math.inf if item.get("end_s") is None else _time(item["end_s"], source, f"{path}.end_s")
    if not end_s > start_s:
        raise ConfigError(source, f"{path}.end_s", f"expected a time after start_s {start_s:g}")
    return ScheduledFault(owner, spec.name, value, start_s, end_s)


def _entry_target(
    item: Mapping[Any, Any], source: str, path: str, joints: Sequence[str]
) -> tuple[str, ParamSpec]:
    """The owner (a joint, or LINK) and the kind's spec of a schedule entry."""
    kind = item.get("kind")
    if kind not in SCHEDULABLE:
        raise ConfigError(source, f"{path}.kind", f"expected one of {sorted(SCHEDULABLE)}")
    if kind in JOINT_KIND:
        owner = item.get("joint")
        if owner not in joints:
            raise ConfigError(source, f"{path}.joint", f"expected one of {list(joints)}")
        return str(owner), JOINT_KIND[str(kind)].spec
    if "joint" in item:
        raise ConfigError(source, f"{path}.joint", f"{kind} is a link fault: no joint")
    return LINK, LINK_KIND[str(kind)].spec


def _time(value: object, source: str, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0.0:
        raise ConfigError(source, path, f"expected a time >= 0 s, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(source, path, f"expected a finite time, got {value!r}")
    return float(value)


def _check_overlaps(entries: Sequence[ScheduledFault], source: str) -> None:
    by_target: dict[tuple[str, str], list[ScheduledFault]] = {}
    for entry in entries:
        by_target.setdefault((entry.owner, entry.kind), []).append(entry)
    for (owner, kind), group in by_target.items():
        group.sort(key=lambda e: e.start_s)
        for before, after in itertools.pairwise(group):
            if after.start_s < before.end_s:
                raise ConfigError(
                    source,
                    "faults",
                    f"two entries of {kind} on {owner} overlap at {after.start_s:g} s",
                )


# --- the injector ------------------------------------------------------------------------


@dataclass
class I2tMonitor:
    """A drive's I2t protection of one motor (the thermal fault).

    level = integral of (i^2 - I_n^2) dt, never below 0. At the capacity
    (I_peak^2 - I_n^2) t_peak it derates the current limit to I_n; if the current demand then
    stays above that limit for `trip_after_s`, it trips (latched).
    """

    rated_a: float
    peak_a: float
    peak_time_s: float
    trip_after_s: float
    level_a2s: float = 0.0
    above_s: float = 0.0
    tripped: bool = False

    @property
    def capacity_a2s(self) -> float:
        """(I_peak^2 - I_n^2) t_peak, A^2 s."""
        return max(self.peak_a**2 - self.rated_a**2, 0.0) * self.peak_time_s

    @property
    def derated(self) -> bool:
        """True while the current is limited to the rated current."""
        return self.level_a2s >= I2T_DERATE_AT * self.capacity_a2s

    def update(self, current_a: float, demand_a: float, dt_s: float) -> None:
        """Integrate one interval at current `current_a` with the setpoint `demand_a`."""
        self.level_a2s = max(0.0, self.level_a2s + (current_a**2 - self.rated_a**2) * dt_s)
        if self.derated and abs(demand_a) > self.rated_a:
            self.above_s += dt_s
        else:
            self.above_s = 0.0
        if self.derated and self.above_s >= self.trip_after_s:
            self.tripped = True


@dataclass
class FaultInjector:
    """The faults in force on one simulator, and their effect on it.

    `set(owner, kind, value)` changes one (from a parameter or a schedule); the model's
    constants are rewritten at once from the robot's nominal ones. `any_active` is False when
    every value is its default: then callers take their fault-free paths.

    Args:
        sim: the simulator whose constants (and Pinocchio model) the faults change.
        period_s: the publishing period, for the velocity noise of a differentiated encoder.
    """

    sim: Simulator
    period_s: float
    values: dict[tuple[str, str], Any] = field(default_factory=dict)
    i2t: dict[int, I2tMonitor] = field(default_factory=dict)

    def __post_init__(self) -> None:
        sim = self.sim
        self.n = sim.n_axes
        self.joints = sim.axis_names
        self._nominal_model = sim._model.copy()
        self._nominal_inertia = [sim.gantry.link_inertia(a) for a in range(self.n)]
        self._rng = np.random.default_rng(0)
        self._frozen_q = np.zeros(self.n)
        self._play_q = np.array(sim.state_array[0], copy=True)
        self._schedule: tuple[ScheduledFault, ...] = ()
        self._scheduled: dict[tuple[str, str], Any] = {}
        self.any_active = False
        # The current sensor, as the in-drive loop reads it: gain, offset per axis.
        self.sense_gain = np.ones(self.n)
        self.sense_offset = np.zeros(self.n)
        self.sense_noise = np.zeros(self.n)
        self.current_limit = np.full(self.n, math.inf)
        self.sto = np.zeros(self.n, dtype=bool)

    # --- setting -------------------------------------------------------------------------

    def value(self, owner: str, kind: str) -> Any:
        """The value in force (a scheduled entry wins over the parameter while active)."""
        key = (owner, kind)
        if key in self._scheduled:
            return self._scheduled[key]
        if key in self.values:
            return self.values[key]
        table = LINK_KIND if owner == LINK else JOINT_KIND
        return table[kind].spec.default

    def set(self, owner: str, kind: str, value: Any) -> None:
        """Set one fault (a parameter's value) and apply the faults in force.

        Raises:
            ParameterError: unknown owner or kind, a value outside its range, or a drift state
                the robot does not have.
        """
        spec = self._spec(owner, kind)
        try:
            checked = spec.check(value)
        except ParameterError as exc:
            raise ParameterError(
                parameter_name(owner, kind), f"{spec.kind.value} {spec.range_text()}", value
            ).with_traceback(exc.__traceback__) from None
        if kind == "drift_state" and checked and checked not in self._moving_states():
            raise ParameterError(
                parameter_name(owner, kind), f"'' or one of {self._moving_states()}", checked
            )
        if kind == "seed":
            self._rng = np.random.default_rng(int(checked))
        self.values[(owner, kind)] = checked
        if kind == "i2t_rated_a" and not checked:
            self.i2t.pop(self.joints.index(owner), None)  # clears a trip, too
        self.apply()

    def restart(self) -> None:
        """Back to the start of a run (a reset).

        The random numbers start from their seed again, the I2t monitors are cold, and the
        encoder's held readings and the scheduled faults are cleared.
        """
        self._rng = np.random.default_rng(int(self.value(LINK, "seed")))
        for monitor in self.i2t.values():
            monitor.level_a2s, monitor.above_s, monitor.tripped = 0.0, 0.0, False
        self._play_q[:] = self.sim.state_array[0]
        self._frozen_q[:] = self.sim.state_array[0]
        self._scheduled = {}
        self.apply()

    def set_schedule(self, schedule: Sequence[ScheduledFault]) -> None:
        """The scheduled faults; `at(t_s)` switches them."""
        for entry in schedule:
            self._spec(entry.owner, entry.kind)
        self._schedule = tuple(schedule)

    def at(self, t_s: float) -> list[str]:
        """Switch the scheduled faults for simulated time t_s; the changes, as text."""
        if not self._schedule:
            return []
        now = {(e.owner, e.kind): e.value for e in self._schedule if e.active(t_s)}
        if now == self._scheduled:
            return []
        before = self._scheduled
        changes = [
            f"{kind} on {owner}: " + (f"{now[(owner, kind)]}" if (owner, kind) in now else "off")
            for owner, kind in sorted(set(now) | set(before))
            if now.get((owner, kind)) != before.get((owner, kind))
        ]
        self._scheduled = now
        self.apply()
        return changes

    def _spec(self, owner: str, kind: str) -> ParamSpec:
        if owner == LINK:
            if kind not in LINK_KIND:
                raise ParameterError(parameter_name(owner, kind), f"one of {list(LINK_KIND)}")
            return LINK_KIND[kind].spec
        if owner not in self.joints:
            raise ParameterError(parameter_name(owner, kind), f"a joint of {list(self.joints)}")
        if kind not in JOINT_KIND:
            raise ParameterError(parameter_name(owner, kind), f"one of {list(JOINT_KIND)}")
        return JOINT_KIND[kind].spec

    def _moving_states(self) -> list[str]:
        return list(self.sim.state_names[kernel.FIRST_MOVING :])

    # --- what is on ----------------------------------------------------------------------

    def active(self, owner: str) -> list[str]:
        """The kinds acting on a joint (or the link) now, by name; a trip shows as i2t_trip."""
        table = LINK_FAULTS if owner == LINK else JOINT_FAULTS
        on = [
            k.name
            for k in table
            if k.category != "thermal"
            and k.name not in ("drift_state", "seed")
            and k.is_on(self.value(owner, k.name))
        ]
        if owner != LINK:
            monitor = self.i2t.get(self.joints.index(owner))
            if monitor is not None:
                on.append(
                    "i2t_trip" if monitor.tripped else "i2t_derate" if monitor.derated else "i2t"
                )
        return on

    def describe(self, owner: str) -> str:
        """The active faults of a joint as text: `encoder_bias=0.01, jam`; `none`."""
        parts = []
        for name in self.active(owner):
            value = self.value(owner, name) if name in JOINT_KIND or name in LINK_KIND else True
            parts.append(name if isinstance(value, bool) else f"{name}={value:g}")
        return ", ".join(parts) if parts else "none"

    # --- applying to the model -----------------------------------------------------------

    def apply(self) -> None:
        """Rewrite the model's constants, the sensor and the drive limits from the faults."""
        model = self.sim._model
        model[:] = self._nominal_model
        self.any_active = False
        n_rules = int(model[kernel.P_N_RULES, 0])
        for a, joint in enumerate(self.joints):
            v = {k.name: self.value(joint, k.name) for k in JOINT_FAULTS}
            on = any(k.is_on(v[k.name]) for k in JOINT_FAULTS if k.category != "thermal")
            self._apply_constants(model, a, v, n_rules)
            self._apply_payload(a, float(v["payload_kg"]))
            self.sense_gain[a] = 1.0 + float(v["current_gain_error"])
            self.sense_offset[a] = float(v["current_offset_a"])
            self.sense_noise[a] = float(v["current_noise_a"])
            limit = float(v["current_limit_a"])
            self.current_limit[a] = limit if limit > 0.0 else math.inf
            self._apply_i2t(a, v)
            monitor = self.i2t.get(a)
            if monitor is not None and monitor.derated:
                self.current_limit[a] = min(self.current_limit[a], monitor.rated_a)
            self.sto[a] = bool(v["sto"]) or (monitor is not None and monitor.tripped)
            if self.sto[a]:
                model[kernel.P_RESISTANCE_OHM, a] = OPEN_CIRCUIT_OHM
            self.any_active = self.any_active or on or monitor is not None
        link_on = any(k.is_on(self.value(LINK, k.name)) for k in LINK_FAULTS if k.name != "seed")
        self.any_active = self.any_active or link_on

    def _apply_constants(
        self, model: FloatArray, a: int, v: Mapping[str, Any], n_rules: int
    ) -> None:
        sag = float(v["supply_sag"])
        model[kernel.P_VOLTAGE_LIMIT_V, a] *= 1.0 - sag
        model[kernel.P_TORQUE_CONSTANT, a] *= 1.0 - float(v["torque_constant_loss"])
        extra = float(v["extra_friction_nm"])
        if v["jam"]:
            extra += JAM_FRICTION_NM
        for row in (
            kernel.P_STATIC_DIRECT,
            kernel.P_STATIC_REVERSE,
            kernel.P_COULOMB_DIRECT,
            kernel.P_COULOMB_REVERSE,
        ):
            model[row, a] += extra
        drift_m, drift_l = float(v["eta_m_drift"]), float(v["eta_l_drift"])
        if drift_m or drift_l:
            names = self.sim.state_names[kernel.FIRST_MOVING :]
            for rule in range(n_rules):
                if v["drift_state"] and names[rule] != v["drift_state"]:
                    continue
                for direction in (1, -1):
                    for which, drift in ((0, drift_m), (1, drift_l)):
                        row = kernel.eta_row(n_rules, direction, rule, which)
                        model[row, a] = max(0.0, model[row, a] + drift)

    def _apply_payload(self, a: int, extra_kg: float) -> None:
        nominal = self._nominal_inertia[a]
        if extra_kg == 0.0:
            self.sim.gantry.set_link_inertia(a, nominal)
            return
        mass = float(nominal.mass)
        if mass + extra_kg <= 0.0:
            raise ParameterError(
                parameter_name(self.joints[a], "payload_kg"),
                f"more than -{mass:g} (the link's own mass)",
                extra_kg,
            )
        scale = (mass + extra_kg) / mass
        inertia = nominal.copy()
        inertia.mass = mass + extra_kg
        inertia.inertia = nominal.inertia * scale
        self.sim.gantry.set_link_inertia(a, inertia)

    def _apply_i2t(self, a: int, v: Mapping[str, Any]) -> None:
        rated = float(v["i2t_rated_a"])
        if rated <= 0.0:
            self.i2t.pop(a, None)
            return
        monitor = self.i2t.get(a)
        if monitor is None:
            monitor = self.i2t[a] = I2tMonitor(rated, 0.0, 0.0, 0.0)
        monitor.rated_a = rated
        monitor.peak_a = float(v["i2t_peak_a"])
        monitor.peak_time_s = float(v["i2t_peak_time_s"])
        monitor.trip_after_s = float(v["i2t_trip_after_s"])

    # --- per control period ----------------------------------------------------------------

    def thermal(self, current_a: FloatArray, demand_a: FloatArray, dt_s: float) -> list[str]:
        """Advance the I2t monitors one interval; what changed (derate, trip), as text."""
        events: list[str] = []
        for a, monitor in self.i2t.items():
            was = (monitor.derated, monitor.tripped)
            monitor.update(float(current_a[a]), float(demand_a[a]), dt_s)
            if (monitor.derated, monitor.tripped) != was:
                joint = self.joints[a]
                events.append(
                    f"{joint}: I2t trip, torque off (latched)"
                    if monitor.tripped
                    else f"{joint}: I2t derates the current to {monitor.rated_a:g} A"
                )
        if events:
            self.apply()
        return events

    def current_noise(self, n_steps: int) -> FloatArray:
        """[n_steps, n] samples of the current sensors' noise (zeros where there is none)."""
        noise: FloatArray = self._rng.standard_normal((n_steps, self.n)) * self.sense_noise
        return noise

    def measure(
        self,
        position: FloatArray,
        velocity: FloatArray,
        current_a: FloatArray,
        out: tuple[FloatArray, FloatArray, FloatArray],
    ) -> None:
        """What the sensors report of the true state (the encoder, backlash, current faults).

        Writes into `out` (position, velocity, current); the true arrays are not touched.
        """
        q_out, v_out, i_out = out
        q_out[:] = position
        v_out[:] = velocity
        np.multiply(current_a, self.sense_gain, out=i_out)
        i_out += self.sense_offset
        if np.any(self.sense_noise):
            i_out += self._rng.standard_normal(self.n) * self.sense_noise
        for a, joint in enumerate(self.joints):
            self._measure_joint(a, joint, q_out, v_out)

    def _measure_joint(self, a: int, joint: str, q_out: FloatArray, v_out: FloatArray) -> None:
        play = float(self.value(joint, "backlash"))
        if play > 0.0:
            # The play operator: the reading moves only once the joint has taken up the play.
            half = 0.5 * play
            self._play_q[a] = min(max(self._play_q[a], q_out[a] - half), q_out[a] + half)
            q_out[a] = self._play_q[a]
        else:
            self._play_q[a] = q_out[a]
        q_out[a] += float(self.value(joint, "encoder_bias"))
        sigma = float(self.value(joint, "encoder_noise"))
        if sigma > 0.0:
            q_out[a] += sigma * self._rng.standard_normal()
            v_out[a] += math.sqrt(2.0) * sigma / self.period_s * self._rng.standard_normal()
        step = float(self.value(joint, "encoder_quantisation"))
        if step > 0.0:
            q_out[a] = step * round(q_out[a] / step)
        if self.value(joint, "encoder_freeze"):
            q_out[a] = self._frozen_q[a]
            v_out[a] = 0.0
        else:
            self._frozen_q[a] = q_out[a]
        dropout = float(self.value(joint, "encoder_dropout"))
        if dropout > 0.0 and self._rng.random() < dropout:
            q_out[a] = math.nan
            v_out[a] = math.nan


@dataclass
class StateLink:
    """The simulator node's state publishing under link faults (dropped, delayed, stale).

    `route(t_s, item)` takes each instant as it is made and returns the instants to publish
    now: the delay line holds them `state_delay_s` of simulated time; a dropped one is never
    returned; while stale, the last one published before is returned again instead.
    """

    injector: FaultInjector
    _queue: list[tuple[float, Any]] = field(default_factory=list)
    _last: Any = None
    dropped: int = 0
    stale_sent: int = 0

    def route(self, t_s: float, item: Any) -> list[Any]:
        """The instants to publish at simulated time t_s, `item` being the newest."""
        inj = self.injector
        if inj.value(LINK, "state_stale") and self._last is not None:
            self.stale_sent += 1
            return [self._last]
        drop = float(inj.value(LINK, "state_drop"))
        if drop > 0.0 and inj._rng.random() < drop:
            self.dropped += 1
            return []
        delay_s = float(inj.value(LINK, "state_delay_s"))
        self._queue.append((t_s, item))
        due = [entry for when, entry in self._queue if when <= t_s - delay_s + 1e-12]
        self._queue = [(when, entry) for when, entry in self._queue if when > t_s - delay_s + 1e-12]
        if due:
            self._last = due[-1]
        return due
