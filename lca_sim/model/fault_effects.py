"""How the faults in force act on the plant: its constants, its drive's limits, its sensors.

The parts `lca_sim.model.faults.FaultInjector` composes, each owning its state. Each takes the
values in force of one axis as a mapping from the kind's name to its value (docs/faults.md).
Units: positions in rad (m for the lift), currents in A, friction at the motor shaft in N m.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from lca_control.parameters import ParameterError
from lca_sim.model import kernel
from lca_sim.model.simulator import Simulator

FloatArray = npt.NDArray[np.float64]
Values = Mapping[str, Any]  # one axis's faults in force, by kind

# A joint that cannot move: breakaway and Coulomb friction at the motor shaft, N m (no motor
# here gives a thousandth of it).
JAM_FRICTION_NM = 1.0e6
# Safe torque off: the armature circuit is open (the power stage's transistors off). With the
# kernel's exact electrical step, a resistance this large makes the current vanish at once
# and stay at nanoamperes, without a special case in the compiled step.
OPEN_CIRCUIT_OHM = 1.0e12
# The I2t monitor derates at this fraction of its capacity (I_peak^2 - I_n^2) t_peak.
I2T_DERATE_AT = 1.0


class PlantConstants:
    """The mechanics and actuator faults: the simulator's constants, rewritten from nominal.

    A jam is breakaway and Coulomb friction no motor overcomes, safe torque off an open
    armature circuit, a demagnetised motor a smaller k_t for torque and back-EMF alike; a
    payload changes the link's inertia in Pinocchio's model.
    """

    def __init__(self, sim: Simulator) -> None:
        self._sim = sim
        self._nominal_model = sim._model.copy()
        self._nominal_inertia = [sim.gantry.link_inertia(a) for a in range(sim.n_axes)]
        self._n_rules = int(self._nominal_model[kernel.P_N_RULES, 0])

    def restore(self) -> None:
        """Every constant back to the robot's own."""
        self._sim._model[:] = self._nominal_model

    def apply(self, a: int, v: Values) -> None:
        """Axis a's supply sag, k_t loss, extra friction, jam and efficiency drift."""
        model = self._sim._model
        model[kernel.P_VOLTAGE_LIMIT_V, a] *= 1.0 - float(v["supply_sag"])
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
            names = self._sim.state_names[kernel.FIRST_MOVING :]
            for rule in range(self._n_rules):
                if v["drift_state"] and names[rule] != v["drift_state"]:
                    continue
                for direction in (1, -1):
                    for which, drift in ((0, drift_m), (1, drift_l)):
                        row = kernel.eta_row(self._n_rules, direction, rule, which)
                        model[row, a] = max(0.0, model[row, a] + drift)

    def open_circuit(self, a: int) -> None:
        """Safe torque off on axis a: the power stage's switches open."""
        self._sim._model[kernel.P_RESISTANCE_OHM, a] = OPEN_CIRCUIT_OHM

    def apply_payload(self, a: int, extra_kg: float, parameter: str) -> None:
        """Add `extra_kg` to axis a's link (its rotational inertia in proportion).

        Raises:
            ParameterError: the link would have no mass left (named `parameter`).
        """
        gantry = self._sim.gantry
        nominal = self._nominal_inertia[a]
        if extra_kg == 0.0:
            gantry.set_link_inertia(a, nominal)
            return
        mass = float(nominal.mass)
        if mass + extra_kg <= 0.0:
            raise ParameterError(parameter, f"more than -{mass:g} (the link's own mass)", extra_kg)
        scale = (mass + extra_kg) / mass
        inertia = nominal.copy()
        inertia.mass = mass + extra_kg
        inertia.inertia = nominal.inertia * scale
        gantry.set_link_inertia(a, inertia)


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


class DriveLimits:
    """The drive's current limit, safe torque off and I2t monitors (per axis).

    `current_limit` and `sto` are what the in-drive current loop obeys
    (`lca_sim.model.commanded_plant`).
    """

    def __init__(self, joints: Sequence[str]) -> None:
        self._joints = tuple(joints)
        n = len(self._joints)
        self.current_limit = np.full(n, math.inf)
        self.sto = np.zeros(n, dtype=bool)
        self.i2t: dict[int, I2tMonitor] = {}

    def apply(self, a: int, v: Values) -> I2tMonitor | None:
        """Axis a's limit and STO from its values and its I2t monitor; the monitor, if any."""
        limit = float(v["current_limit_a"])
        self.current_limit[a] = limit if limit > 0.0 else math.inf
        monitor = self._configure_i2t(a, v)
        if monitor is not None and monitor.derated:
            self.current_limit[a] = min(self.current_limit[a], monitor.rated_a)
        self.sto[a] = bool(v["sto"]) or (monitor is not None and monitor.tripped)
        return monitor

    def _configure_i2t(self, a: int, v: Values) -> I2tMonitor | None:
        rated = float(v["i2t_rated_a"])
        if rated <= 0.0:
            self.i2t.pop(a, None)
            return None
        monitor = self.i2t.get(a)
        if monitor is None:
            monitor = self.i2t[a] = I2tMonitor(rated, 0.0, 0.0, 0.0)
        monitor.rated_a = rated
        monitor.peak_a = float(v["i2t_peak_a"])
        monitor.peak_time_s = float(v["i2t_peak_time_s"])
        monitor.trip_after_s = float(v["i2t_trip_after_s"])
        return monitor

    def cool(self) -> None:
        """Every I2t monitor cold and untripped (a reset)."""
        for monitor in self.i2t.values():
            monitor.level_a2s, monitor.above_s, monitor.tripped = 0.0, 0.0, False

    def thermal(self, current_a: FloatArray, demand_a: FloatArray, dt_s: float) -> list[str]:
        """Advance the I2t monitors one interval; what changed (derate, trip), as text."""
        events: list[str] = []
        for a, monitor in self.i2t.items():
            was = (monitor.derated, monitor.tripped)
            monitor.update(float(current_a[a]), float(demand_a[a]), dt_s)
            if (monitor.derated, monitor.tripped) != was:
                joint = self._joints[a]
                events.append(
                    f"{joint}: I2t trip, torque off (latched)"
                    if monitor.tripped
                    else f"{joint}: I2t derates the current to {monitor.rated_a:g} A"
                )
        return events


class SensorFaults:
    """What the sensors report: the current sensor's faults, the encoders' and backlash.

    The controller closes its loops on these readings while the dynamics keep the true state.
    One random stream (seeded by `faults.link.seed`) serves the noise, dropouts and the link
    faults, in the order they are drawn, so runs repeat to the bit.

    Args:
        position: the joints' true position now, where backlash starts.
        period_s: the publishing period, for the velocity noise of a differentiated encoder.
    """

    def __init__(self, position: FloatArray, period_s: float) -> None:
        n = len(position)
        self.period_s = period_s
        self.rng = np.random.default_rng(0)
        # The current sensor, as the in-drive loop reads it: gain, offset, noise per axis.
        self.gain = np.ones(n)
        self.offset = np.zeros(n)
        self.noise_a = np.zeros(n)
        self._encoders: list[Values] = [{} for _ in range(n)]
        self._frozen_q = np.zeros(n)
        self._play_q = np.array(position, copy=True)

    def restart(self, seed: int, position: FloatArray) -> None:
        """The random numbers from `seed` again; the encoders' held readings at `position`."""
        self.rng = np.random.default_rng(seed)
        self._play_q[:] = position
        self._frozen_q[:] = position

    def configure(self, a: int, v: Values) -> None:
        """Axis a's sensor faults from its values in force."""
        self.gain[a] = 1.0 + float(v["current_gain_error"])
        self.offset[a] = float(v["current_offset_a"])
        self.noise_a[a] = float(v["current_noise_a"])
        self._encoders[a] = v

    def current_noise(self, n_steps: int) -> FloatArray:
        """[n_steps, n] samples of the current sensors' noise (zeros where there is none)."""
        noise: FloatArray = self.rng.standard_normal((n_steps, len(self.gain))) * self.noise_a
        return noise

    def measure(
        self,
        position: FloatArray,
        velocity: FloatArray,
        current_a: FloatArray,
        out: tuple[FloatArray, FloatArray, FloatArray],
    ) -> None:
        """The readings of the true state, written into `out` (position, velocity, current)."""
        q_out, v_out, i_out = out
        q_out[:] = position
        v_out[:] = velocity
        np.multiply(current_a, self.gain, out=i_out)
        i_out += self.offset
        if np.any(self.noise_a):
            i_out += self.rng.standard_normal(len(self.gain)) * self.noise_a
        for a, v in enumerate(self._encoders):
            self._measure_joint(a, v, q_out, v_out)

    def _measure_joint(self, a: int, v: Values, q_out: FloatArray, v_out: FloatArray) -> None:
        play = float(v["backlash"])
        if play > 0.0:
            # The play operator: the reading moves only once the joint has taken up the play.
            half = 0.5 * play
            self._play_q[a] = min(max(self._play_q[a], q_out[a] - half), q_out[a] + half)
            q_out[a] = self._play_q[a]
        else:
            self._play_q[a] = q_out[a]
        q_out[a] += float(v["encoder_bias"])
        sigma = float(v["encoder_noise"])
        if sigma > 0.0:
            q_out[a] += sigma * self.rng.standard_normal()
            v_out[a] += math.sqrt(2.0) * sigma / self.period_s * self.rng.standard_normal()
        step = float(v["encoder_quantisation"])
        if step > 0.0:
            q_out[a] = step * round(q_out[a] / step)
        if v["encoder_freeze"]:
            q_out[a] = self._frozen_q[a]
            v_out[a] = 0.0
        else:
            self._frozen_q[a] = q_out[a]
        dropout = float(v["encoder_dropout"])
        if dropout > 0.0 and self.rng.random() < dropout:
            q_out[a] = math.nan
            v_out[a] = math.nan
