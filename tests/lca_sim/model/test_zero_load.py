"""An axis without a gravity load: the load-sign band of Fig. 8 (docs/model.md, section 4).

The L-arm turns about the vertical, so Q(q) has no L-arm component and, moving alone, it has no
Coriolis term either: Pinocchio returns tau_l as a rounding residue of 1e-20 to 1e-13 N m of
random sign. Before the band the drive state followed that sign (24,886 changes in 12 s at 12 V
from the zero pose, 49,736 with the pivot at 0.44 rad); now it keeps the state of a zero load.
The step's compiled terms (`lca_sim.model.rigid_body`, world frame) give exactly 0 on this
vertical axis, but a robot whose axes are not aligned with gravity has the residue, so the band
is tested on hand-set residues and on Pinocchio's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lca_sim import RobotParams, Simulator, load_robot, run_scenario
from lca_sim.model import kernel
from lca_sim.model.scenario import ScenarioResult, parse_scenario
from lca_sim.model.state_machine import MotionState, load_torque_band_nm

L_ARM = 0
VOLTS = 12.0
POSES = {
    "zero-pose": {},
    "pivot-tilted": {"pivot": 0.44, "lift": 0.17},
}


def _constant_voltage_run(
    robot: RobotParams, pose: dict[str, float], hold_steps: int = 1, record_period_s: float = 1e-2
) -> tuple[Simulator, ScenarioResult]:
    """12 s of the L-arm alone at 12 V from rest (0.09 rad/s, 1.1 rad of travel)."""
    sim = Simulator(robot, rigid_body_update_steps=hold_steps)
    doc = {
        "duration_s": 12.0,
        "dt_s": 1e-4,
        "record_period_s": record_period_s,
        "initial": {"position": pose},
        "inputs": {"l_arm": {"time_s": [0.0], "voltage_v": [VOLTS]}},
    }
    return sim, run_scenario(sim, parse_scenario(doc, "<test>", sim.axis_names))


@pytest.mark.parametrize("hold_steps", [1, 10], ids=["exact", "held-1ms"])
@pytest.mark.parametrize("pose", list(POSES.values()), ids=list(POSES))
def test_unloaded_l_arm_keeps_its_state_at_constant_speed(
    default_robot: RobotParams, pose: dict[str, float], hold_steps: int
) -> None:
    """12 s at constant voltage: only the start-up transitions, then motor_driving throughout."""
    _, result = _constant_voltage_run(default_robot, pose, hold_steps)
    tau_l = result.signal("load_torque_nm", "l_arm")
    assert np.abs(tau_l).max() < 1e-14  # rounding only: no physical load
    states = [p.state for p in result.phases("l_arm")]
    assert states == ["stop_hold", "stop_motor_direct", "motor_driving"]


def test_unloaded_l_arm_runs_at_the_eq10_speed_of_motor_driving(default_robot: RobotParams) -> None:
    """Steady state of eq. (10) with tau_l = 0 and Table 1 row 1 (eta_m = 0.9), to rounding.

    Mixed states gave eta_m = 1 on 29 % of the steps and a speed 0.2 % too high.
    """
    sim, _ = _constant_voltage_run(default_robot, POSES["pivot-tilted"])
    axis = default_robot.axes[L_ARM]
    k, r = axis.motor.torque_constant_nm_per_a, axis.motor.resistance_ohm
    f = axis.friction
    eta_m = axis.efficiency[(MotionState.DIRECT, "motor_driving")].eta_m
    w_expected = (eta_m * k * VOLTS / r - f.coulomb_direct_nm) / (
        eta_m * k * k / r + f.viscous_direct_nm_s_per_rad
    )
    sig = sim.signals
    assert sig.drive[L_ARM] == "motor_driving"
    assert (sig["eta_m"][L_ARM], sig["eta_l"][L_ARM]) == (eta_m, 1.0)
    assert sig["motor_velocity_rad_s"][L_ARM] == pytest.approx(w_expected, rel=1e-9)


# --- the state a zero load picks ------------------------------------------------------------


def _l_arm_state(direction: int, tau_m_nm: float, tau_l_nm: float) -> tuple[str, float, float]:
    """The drive state and (eta_m, eta_l) the kernel gives the moving L-arm for hand-set torques.

    One zero-length kernel step (it evaluates without moving) on the L-arm's own packed
    constants, its band included, moving at 10 rad/s motor side.
    """
    robot = load_robot("default")
    model = np.ascontiguousarray(Simulator(robot).model_array[:, L_ARM : L_ARM + 1])
    ratio = model[kernel.P_GEAR_RATIO, 0]
    k_t = model[kernel.P_TORQUE_CONSTANT, 0]
    r_ohm = model[kernel.P_RESISTANCE_OHM, 0]
    w_m = direction * 10.0
    work = np.zeros((kernel.work_rows(1), 1))
    work[kernel.X_VELOCITY] = w_m / ratio
    work[kernel.X_MOTION] = direction
    work[kernel.X_CURRENT] = tau_m_nm / k_t
    volts = r_ohm * tau_m_nm / k_t + k_t * w_m  # holds the current where it is
    code = kernel.step(
        np.array([[600.0]]), np.array([tau_l_nm * ratio]), np.array([volts]), work, model, 0.0
    )
    assert code == kernel.OK
    assert int(work[kernel.X_MOTION, 0]) == direction
    name = robot.state_machine.state_names[int(work[kernel.X_DRIVE, 0])]
    return name, float(work[kernel.S_ETA_M, 0]), float(work[kernel.S_ETA_L, 0])


# (tau_m, tau_l, state) in direct motion; the reverse rows are their mirror images. 1e-15 N m is
# the rounding residue seen on the L-arm, 1e-9 N m a load far inside physics but 150 bands out.
ZERO_LOAD = [
    (0.12, 0.0, "motor_driving"),  # physically zero: the motor alone drives (Table 1 row 1)
    (0.12, -0.0, "motor_driving"),
    (0.12, 7e-20, "motor_driving"),
    (0.12, -7e-20, "motor_driving"),  # was motor_and_load_driving_motor_dominant
    (0.12, 1e-15, "motor_driving"),
    (0.12, -1e-15, "motor_driving"),  # was motor_and_load_driving_motor_dominant
    (-0.05, 0.0, "coasting"),  # the motor brakes and nothing else emits power
    (-0.05, -1e-15, "coasting"),  # was load_driving
    (1e-8, -1e-15, "motor_driving"),  # a tiny motor torque still dominates a zero load
    (0.12, -1e-9, "motor_and_load_driving_motor_dominant"),  # a real load still drives
    (0.12, 1e-9, "motor_driving"),
    (-0.05, -1e-9, "load_driving"),
]


@pytest.mark.parametrize("direction", [1, -1], ids=["direct", "reverse"])
@pytest.mark.parametrize(("tau_m", "tau_l", "state"), ZERO_LOAD)
def test_zero_load_picks_the_documented_state(
    default_robot: RobotParams, direction: int, tau_m: float, tau_l: float, state: str
) -> None:
    """A load inside the band is a zero load: it neither drives nor dominates (Fig. 8)."""
    name, eta_m, eta_l = _l_arm_state(direction, direction * tau_m, direction * tau_l)
    assert name == state
    efficiency = default_robot.axes[L_ARM].efficiency[(MotionState(direction), state)]
    assert (eta_m, eta_l) == (efficiency.eta_m, efficiency.eta_l)


@pytest.mark.parametrize("tau_l", [0.0, 1e-15, -1e-15])
def test_breakaway_under_a_zero_load_enters_motor_driving(
    default_robot: RobotParams, tau_l: float
) -> None:
    """Fig. 7 -> Fig. 8: a motor starting an unloaded L-arm enters motor_driving, either way."""
    robot = default_robot
    sim = Simulator(robot)
    model = np.ascontiguousarray(sim.model_array[:, L_ARM : L_ARM + 1])
    ratio = model[kernel.P_GEAR_RATIO, 0]
    for direction in (1, -1):
        work = np.zeros((kernel.work_rows(1), 1))
        volts = direction * 12.0
        code = kernel.step(
            np.array([[600.0]]), np.array([tau_l * ratio]), np.array([volts]), work, model, 1e-3
        )
        assert code == kernel.OK
        assert int(work[kernel.X_MOTION, 0]) == direction
        assert robot.state_machine.state_names[int(work[kernel.X_DRIVE, 0])] == "motor_driving"


def test_band_is_the_documented_multiple_of_the_stall_torque(default_robot: RobotParams) -> None:
    """Every axis's band is 2**12 eps times k_t V_max / R (docs/model.md), in the kernel too."""
    model = Simulator(default_robot).model_array
    for a, axis in enumerate(default_robot.axes):
        m = axis.motor
        stall_nm = m.torque_constant_nm_per_a * m.voltage_limit_v / m.resistance_ohm
        band = load_torque_band_nm(stall_nm)
        assert band == 4096.0 * np.finfo(np.float64).eps * stall_nm
        assert model[kernel.P_LOAD_TORQUE_BAND, a] == band
        # Far below any torque the paper resolves (T_m_eps, Fig. 7).
        assert band < 1e-5 * default_robot.state_machine.motor_torque_eps_nm


def test_band_covers_pinocchio_rounding_on_the_l_arm(default_robot: RobotParams) -> None:
    """Over random poses and L-arm speeds, the L-arm's tau_l stays a hundredth of the band.

    Both Pinocchio's nonLinearEffects (a residue of random sign) and the step's compiled terms.
    """
    sim = Simulator(default_robot)
    band = sim.model_array[kernel.P_LOAD_TORQUE_BAND, L_ARM]
    ratio = default_robot.axes[L_ARM].gear_ratio
    limits = np.array(sim.position_limits)
    rng = np.random.default_rng(7)
    worst_nm = 0.0
    for _ in range(2_000):
        q = rng.uniform(limits[:, 0], limits[:, 1])
        v = np.zeros(4)
        v[L_ARM] = rng.uniform(-0.2, 0.2)
        _, nle = sim.gantry.dynamics_terms(q, v)
        _, reference = sim.gantry.pinocchio_terms(q, v)
        worst_nm = max(worst_nm, abs(float(nle[L_ARM])) / ratio, abs(reference[L_ARM]) / ratio)
    assert worst_nm < 0.01 * band


# --- energy and hold stay exact -------------------------------------------------------------


@pytest.fixture(scope="module")
def l_arm_run() -> tuple[Simulator, ScenarioResult]:
    """The unloaded L-arm at 12 V, recorded at every step."""
    return _constant_voltage_run(load_robot("default"), POSES["pivot-tilted"], record_period_s=1e-4)


def test_eq10_power_balance_of_the_unloaded_l_arm(
    l_arm_run: tuple[Simulator, ScenarioResult],
) -> None:
    """Motor power = load power + inertial power + losses at every step; the noise burns nothing.

    The inertial power uses Pinocchio's full A(q), independently of the kernel. In motor_driving
    eta_l = 1, so the gear loss is exactly the motor's 10 %: (1 - eta_m) tau_m w_m.
    """
    sim, result = l_arm_run
    axis = sim.robot.axes[L_ARM]
    gear = np.array([a.gear_ratio for a in sim.robot.axes])
    rotor = np.array([a.motor.rotor_inertia_kg_m2 for a in sim.robot.axes])
    eta_m = axis.efficiency[(MotionState.DIRECT, "motor_driving")].eta_m
    sig = result.signals
    moving = np.nonzero(result.motion[:, L_ARM] != 0)[0]
    assert len(moving) > 0.99 * len(result.time_s)
    for k in moving[::97]:
        inertia = sim.gantry.mass_matrix(result.position[k - 1]) / np.outer(gear, gear) + np.diag(
            rotor
        )
        p_inertial = sig[k, 0, L_ARM] * float((inertia @ sig[k, 14])[L_ARM])
        p_motor, p_load = sig[k, 8, L_ARM], sig[k, 9, L_ARM]
        gear_loss, friction_loss = sig[k, 10, L_ARM], sig[k, 11, L_ARM]
        assert gear_loss == pytest.approx((1.0 - eta_m) * p_motor, rel=1e-12)
        assert friction_loss >= 0.0
        residual = p_motor - p_load - gear_loss - friction_loss - p_inertial
        assert residual == pytest.approx(0.0, abs=1e-9 * abs(p_motor))


def test_whole_run_energy_of_the_unloaded_l_arm_closes(
    l_arm_run: tuple[Simulator, ScenarioResult],
) -> None:
    """Electrical energy in = kinetic + potential + magnetic energy gained + all losses."""
    sim, result = l_arm_run
    dt = result.time_s[1] - result.time_s[0]
    sig = result.signals
    axes = sim.robot.axes
    rotor = np.array([a.motor.rotor_inertia_kg_m2 for a in axes])
    inductance = np.array([a.motor.inductance_h for a in axes])

    def stored_j(k: int) -> float:
        q, v = result.position[k], result.velocity[k]
        w, i = sig[k, 0], sig[k, 1]
        return (
            sim.gantry.kinetic_energy_j(q, v)
            + 0.5 * float(rotor @ (w * w))
            + sim.gantry.potential_energy_j(q)
            + 0.5 * float(inductance @ (i * i))
        )

    e_in = float(sig[1:, 12].sum()) * dt
    losses = float((sig[1:, 13] + sig[1:, 10] + sig[1:, 11]).sum()) * dt
    gained = stored_j(len(result.time_s) - 1) - stored_j(0)
    assert e_in > 100.0
    assert (gained + losses) == pytest.approx(e_in, rel=2e-3)


def test_unloaded_l_arm_holds_bit_for_bit_at_zero_volts(default_robot: RobotParams) -> None:
    """At 0 V the stopped L-arm stays exactly put for 2 s despite its noisy tau_l (Fig. 7)."""
    sim = Simulator(default_robot)
    sim.reset(position={"l_arm": 0.3, "pivot": 0.44, "lift": 0.17})
    sim.advance(20_000, np.zeros(4))
    assert sim.state.position[L_ARM] == 0.3
    assert sim.state.velocity[L_ARM] == 0.0
    assert sim.signals.drive[L_ARM] == "stop_hold"
    assert math.isnan(sim.signals["eta_m"][L_ARM])
