"""Fault injection: the kinds a user can break in the plant, and their injector (pure core).

The kinds (each a parameter `faults.<joint>.<kind>` or `faults.link.<kind>`, off by default)
and `FaultInjector`, which composes the parts of `lca_sim.model.fault_effects`: the plant's
constants, the drive's limits and I2t, the sensors; `StateLink` applies the link faults to the
simulator node's publishing. Schedules: `lca_sim.model.fault_schedule`. With no fault set the
callers take their fault-free paths, bit for bit. What each kind does: docs/faults.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from lca_control.parameters import ParameterError, ParameterTable, ParamKind, ParamSpec
from lca_sim.model import kernel
from lca_sim.model.fault_effects import DriveLimits, PlantConstants, SensorFaults
from lca_sim.model.simulator import Simulator

if TYPE_CHECKING:
    # fault_schedule reads the kinds from here; the injector only takes its entries.
    from lca_sim.model.fault_schedule import ScheduledFault

FloatArray = npt.NDArray[np.float64]

B, D, S, INT = ParamKind.BOOL, ParamKind.DOUBLE, ParamKind.STRING, ParamKind.INTEGER

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


def split_name(name: str) -> tuple[str, str]:
    """(owner, kind) of `faults.<owner>.<kind>`.

    Raises:
        ParameterError: not a fault parameter name.
    """
    parts = name.split(".")
    if len(parts) != 3 or parts[0] != "faults":
        raise ParameterError(name, "faults.<joint>.<kind> or faults.link.<kind>", name)
    return parts[1], parts[2]


# --- the injector ------------------------------------------------------------------------


class FaultSettings:
    """The faults set (from parameters) and scheduled, and the value in force of each."""

    def __init__(self) -> None:
        self.values: dict[tuple[str, str], Any] = {}
        self.schedule: tuple[ScheduledFault, ...] = ()
        self.scheduled: dict[tuple[str, str], Any] = {}

    def value(self, owner: str, kind: str) -> Any:
        """The value in force (a scheduled entry wins over the parameter while active)."""
        key = (owner, kind)
        if key in self.scheduled:
            return self.scheduled[key]
        if key in self.values:
            return self.values[key]
        table = LINK_KIND if owner == LINK else JOINT_KIND
        return table[kind].spec.default

    def switch(self, t_s: float) -> list[str] | None:
        """Switch the scheduled entries for simulated time t_s; the changes as text, or None."""
        if not self.schedule:
            return None
        now = {(e.owner, e.kind): e.value for e in self.schedule if e.active(t_s)}
        if now == self.scheduled:
            return None
        before = self.scheduled
        changes = [
            f"{kind} on {owner}: " + (f"{now[(owner, kind)]}" if (owner, kind) in now else "off")
            for owner, kind in sorted(set(now) | set(before))
            if now.get((owner, kind)) != before.get((owner, kind))
        ]
        self.scheduled = now
        return changes


class FaultInjector:
    """The faults in force on one simulator, and their effect on it.

    `set(owner, kind, value)` changes one (from a parameter or a schedule); the model's
    constants are rewritten at once from the robot's nominal ones. `any_active` is False when
    every value is its default: then callers take their fault-free paths.

    Args:
        sim: the simulator whose constants (and Pinocchio model) the faults change.
        period_s: the publishing period, for the velocity noise of a differentiated encoder.
    """

    def __init__(self, sim: Simulator, period_s: float) -> None:
        self.sim = sim
        self.period_s = period_s
        self.n = sim.n_axes
        self.joints = sim.axis_names
        self.any_active = False
        self.settings = FaultSettings()
        self.constants = PlantConstants(sim)
        self.drive = DriveLimits(self.joints)
        self.sensors = SensorFaults(sim.state_array[0], period_s)
        defaults = {k.name: k.spec.default for k in JOINT_FAULTS}
        for a in range(self.n):
            self.sensors.configure(a, defaults)

    @property
    def values(self) -> dict[tuple[str, str], Any]:
        """The faults set by parameter, by (owner, kind); `apply` after changing them here."""
        return self.settings.values

    # --- setting -------------------------------------------------------------------------

    def value(self, owner: str, kind: str) -> Any:
        """The value in force (a scheduled entry wins over the parameter while active)."""
        return self.settings.value(owner, kind)

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
            self.sensors.rng = np.random.default_rng(int(checked))
        self.settings.values[(owner, kind)] = checked
        if kind == "i2t_rated_a" and not checked:
            self.drive.i2t.pop(self.joints.index(owner), None)  # clears a trip, too
        self.apply()

    def restart(self) -> None:
        """Back to the start of a run (a reset).

        The random numbers start from their seed again, the I2t monitors are cold, and the
        encoder's held readings and the scheduled faults are cleared.
        """
        self.sensors.restart(int(self.value(LINK, "seed")), self.sim.state_array[0])
        self.drive.cool()
        self.settings.scheduled = {}
        self.apply()

    def set_schedule(self, schedule: Sequence[ScheduledFault]) -> None:
        """The scheduled faults; `at(t_s)` switches them."""
        for entry in schedule:
            self._spec(entry.owner, entry.kind)
        self.settings.schedule = tuple(schedule)

    def at(self, t_s: float) -> list[str]:
        """Switch the scheduled faults for simulated time t_s; the changes, as text."""
        changes = self.settings.switch(t_s)
        if changes is None:
            return []
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
            monitor = self.drive.i2t.get(self.joints.index(owner))
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
        """Rewrite the model's constants, the sensors and the drive limits from the faults."""
        per_axis = [
            {k.name: self.value(joint, k.name) for k in JOINT_FAULTS} for joint in self.joints
        ]
        for a, v in enumerate(per_axis):
            self.sensors.configure(a, v)
        self.constants.restore()
        self.any_active = False
        for a, (joint, v) in enumerate(zip(self.joints, per_axis, strict=True)):
            on = any(k.is_on(v[k.name]) for k in JOINT_FAULTS if k.category != "thermal")
            self.constants.apply(a, v)
            self.constants.apply_payload(
                a, float(v["payload_kg"]), parameter_name(joint, "payload_kg")
            )
            monitor = self.drive.apply(a, v)
            if self.drive.sto[a]:
                self.constants.open_circuit(a)
            self.any_active = self.any_active or on or monitor is not None
        link_on = any(k.is_on(self.value(LINK, k.name)) for k in LINK_FAULTS if k.name != "seed")
        self.any_active = self.any_active or link_on

    # --- per control period ----------------------------------------------------------------

    def thermal(self, current_a: FloatArray, demand_a: FloatArray, dt_s: float) -> list[str]:
        """Advance the I2t monitors one interval; what changed (derate, trip), as text."""
        events = self.drive.thermal(current_a, demand_a, dt_s)
        if events:
            self.apply()
        return events

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
        self.sensors.measure(position, velocity, current_a, out)


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
        if drop > 0.0 and inj.sensors.rng.random() < drop:
            self.dropped += 1
            return []
        delay_s = float(inj.value(LINK, "state_delay_s"))
        self._queue.append((t_s, item))
        due = [entry for when, entry in self._queue if when <= t_s - delay_s + 1e-12]
        self._queue = [(when, entry) for when, entry in self._queue if when > t_s - delay_s + 1e-12]
        if due:
            self._last = due[-1]
        return due
