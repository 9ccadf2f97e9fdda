"""Physics of the whole model: holds, steady states, energy, symmetry, convergence, determinism.

Every expected number here is computed independently of the kernel: from the paper's equations
solved by hand, from Pinocchio's own mass matrix and energies, or from a second run.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from lca_sim import RobotParams, Simulator, load_robot, load_scenario, run_scenario
from lca_sim.cli.results import write_csv
from lca_sim.model.params import FrictionParams
from lca_sim.model.scenario import Scenario, ScenarioResult, parse_scenario
from lca_sim.model.state_machine import MotionState

PIVOT, LIFT = 1, 3


def _scenario(robot: RobotParams, **doc: object) -> Scenario:
    return parse_scenario(doc, "<test>", robot.axis_names)


def _gravity_phase_rad(sim: Simulator) -> float:
    """phi0 in Q_pivot(q) = c cos(q + phi0) (c_arc = lift = 0), from Pinocchio."""
    q0 = np.zeros(4)
    q90 = np.array([0.0, math.pi / 2, 0.0, 0.0])
    return math.atan2(-sim.gantry.gravity(q90)[PIVOT], sim.gantry.gravity(q0)[PIVOT])


# --- holding ---------------------------------------------------------------------------------


def test_irreversible_pivot_holds_gravity_for_10_s(default_robot: RobotParams) -> None:
    """A gravity-loaded pivot at 0 V does not move in 10 s: the worm gear self-locks."""
    sim = Simulator(default_robot)
    result = run_scenario(sim, load_scenario("hold_pivot", sim.axis_names))
    load_nm = result.signal("load_torque_nm", "pivot")
    assert load_nm.min() > 0.4  # the load really is there: about 0.43 N m at the motor
    assert np.all(result.position[:, PIVOT] == 0.0)
    assert np.all(result.velocity == 0.0)
    assert [p.state for p in result.phases("pivot")] == ["stop_hold"]


def test_reversible_pivot_falls(reversible_robot: RobotParams) -> None:
    """The velocity-friction-only baseline cannot hold the same load: the pivot falls.

    With 0 V the shorted motor brakes it (k^2/R), so it sinks at the quasi-steady speed where
    gravity balances dynamic braking and eq. (4) friction.
    """
    sim = Simulator(reversible_robot)
    result = run_scenario(sim, load_scenario("hold_pivot", sim.axis_names))
    first_move = next(p for p in result.phases("pivot") if p.state != "stop_hold")
    assert first_move.time_s < 0.01
    assert first_move.state == "load_driving"
    assert result.position[-1, PIVOT] < -0.4  # rad fallen in 10 s
    pivot = reversible_robot.axes[PIVOT]
    k, r = pivot.motor.torque_constant_nm_per_a, pivot.motor.resistance_ohm
    f = pivot.friction
    tau_l = result.signal("load_torque_nm", "pivot")[-1]
    w_terminal = -(tau_l - f.coulomb_reverse_nm) / (k * k / r + f.viscous_reverse_nm_s_per_rad)
    assert result.signal("motor_velocity_rad_s", "pivot")[-1] == pytest.approx(w_terminal, rel=0.01)


# --- steady states ---------------------------------------------------------------------------


def _run_lift(
    robot: RobotParams, volts: float, seconds: float = 1.5, pivot_rad: float = 0.0
) -> Simulator:
    sim = Simulator(robot)
    sim.reset(position={"lift": 0.17, "pivot": pivot_rad})
    command = np.array([0.0, 0.0, 0.0, volts])
    for _ in range(round(seconds / sim.dt_s)):
        sim.step(command)
    return sim


def test_steady_lifting_recovers_eta_m(default_robot: RobotParams) -> None:
    """Lifting the detector at constant voltage: eq. (10) steady state and eta_m = 0.9."""
    sim = _run_lift(default_robot, 12.0)
    sig = sim.signals
    axis = default_robot.axes[LIFT]
    k, r = axis.motor.torque_constant_nm_per_a, axis.motor.resistance_ohm
    f = axis.friction
    eta_m = axis.efficiency[(MotionState.DIRECT, "motor_driving")].eta_m
    tau_l = float(sig["load_torque_nm"][LIFT])
    # Detector weight through the screw: m g / N (the lift axis is vertical at this pose).
    assert tau_l == pytest.approx(65.0 * 9.81 / axis.gear_ratio, rel=1e-9)
    w_expected = (eta_m * k * 12.0 / r - tau_l - f.coulomb_direct_nm) / (
        eta_m * k * k / r + f.viscous_direct_nm_s_per_rad
    )
    assert sig.drive[LIFT] == "motor_driving"
    assert sig["motor_velocity_rad_s"][LIFT] == pytest.approx(w_expected, rel=1e-7)
    recovered = (sig["load_power_w"][LIFT] + sig["friction_loss_w"][LIFT]) / sig["motor_power_w"][
        LIFT
    ]
    assert recovered == pytest.approx(eta_m, rel=1e-7)


def test_steady_lowering_recovers_eta_l(default_robot: RobotParams) -> None:
    """Lowering it: the load drives, the reverse load-dominant eta_l = 0.16 comes back."""
    sim = _run_lift(default_robot, -12.0)
    sig = sim.signals
    axis = default_robot.axes[LIFT]
    k, r = axis.motor.torque_constant_nm_per_a, axis.motor.resistance_ohm
    f = axis.friction
    state = "motor_and_load_driving_load_dominant"
    eta_l = axis.efficiency[(MotionState.REVERSE, state)].eta_l
    tau_l = float(sig["load_torque_nm"][LIFT])
    w_expected = (k * -12.0 / r - eta_l * tau_l + f.coulomb_reverse_nm) / (
        k * k / r + f.viscous_reverse_nm_s_per_rad
    )
    assert sig.drive[LIFT] == state
    assert sig["motor_velocity_rad_s"][LIFT] == pytest.approx(w_expected, rel=1e-7)
    # The load emits -P_load; of it eta_l goes on, together with the motor's power, to friction.
    recovered = (sig["friction_loss_w"][LIFT] - sig["motor_power_w"][LIFT]) / -sig["load_power_w"][
        LIFT
    ]
    assert recovered == pytest.approx(eta_l, rel=1e-6)


# --- energy ----------------------------------------------------------------------------------

BUSY = {
    "duration_s": 4.0,
    "dt_s": 1e-4,
    "record_period_s": 1e-4,
    "initial": {"position": {"pivot": 0.9, "lift": 0.17, "l_arm": 0.0}},
    "inputs": {
        "l_arm": {"time_s": [0.0, 0.5, 2.0, 2.5], "voltage_v": [0.0, 20.0, 20.0, -20.0]},
        "pivot": {"time_s": [0.0, 0.3, 2.5, 2.5], "voltage_v": [0.0, 8.0, 8.0, 0.0]},
        "c_arc": {"time_s": [0.0, 1.0, 1.5], "voltage_v": [0.0, 15.0, -15.0]},
        "lift": {"time_s": [0.0, 0.2, 1.8, 1.8], "voltage_v": [0.0, 14.0, 14.0, -14.0]},
    },
}


@pytest.fixture(scope="module", params=["default", "reversible"])
def busy_run(request: pytest.FixtureRequest) -> tuple[Simulator, ScenarioResult]:
    """Every axis moving, both ways, through the pivot's gravity crossing: every state."""
    robot = load_robot(request.param)
    sim = Simulator(robot)
    return sim, run_scenario(sim, _scenario(robot, **BUSY))


def test_busy_run_visits_every_moving_state(busy_run: tuple[Simulator, ScenarioResult]) -> None:
    """The energy tests below really cover every drive state of the machine."""
    sim, result = busy_run
    visited = {sim.state_names[d] for d in np.unique(result.drive)}
    moving = set(sim.state_names[4:])
    assert moving <= visited


def test_eq10_power_balance_per_state(busy_run: tuple[Simulator, ScenarioResult]) -> None:
    """In every state: motor power = load power + inertial power + losses, losses >= 0.

    The inertial power uses Pinocchio's full symmetric A(q), independently of the kernel.
    """
    sim, result = busy_run
    gear = np.array([a.gear_ratio for a in sim.robot.axes])
    rotor = np.array([a.motor.rotor_inertia_kg_m2 for a in sim.robot.axes])
    names = sim.state_names
    p_motor = result.signals[:, 8]
    p_load = result.signals[:, 9]
    gear_loss = result.signals[:, 10]
    friction_loss = result.signals[:, 11]
    acc = result.signals[:, 14]
    w = result.signals[:, 0]
    checked: dict[str, int] = {}
    for k in range(1, len(result.time_s), 7):  # every 7th step: all states, a fast test
        q_before = result.position[k - 1]
        inertia = sim.gantry.mass_matrix(q_before) / np.outer(gear, gear) + np.diag(rotor)
        p_inertial = w[k] * (inertia @ acc[k])
        for a in range(4):
            if result.motion[k, a] == 0:
                continue
            state = names[result.drive[k, a]]
            assert gear_loss[k, a] >= -1e-12, state
            assert friction_loss[k, a] >= 0.0, state
            residual = p_motor[k, a] - p_load[k, a] - gear_loss[k, a] - friction_loss[k, a]
            scale = abs(p_motor[k, a]) + abs(p_load[k, a]) + 1e-9
            assert residual - p_inertial[a] == pytest.approx(0.0, abs=1e-7 * scale), state
            checked[state] = checked.get(state, 0) + 1
    assert set(checked) == set(names[4:])
    if not sim.robot.state_machine.irreversible_stop:  # the reversible baseline: eta = 1
        assert np.all(gear_loss == 0.0)


def test_whole_run_energy_closes(busy_run: tuple[Simulator, ScenarioResult]) -> None:
    """Electrical energy in = kinetic + potential + magnetic energy gained + all losses."""
    sim, result = busy_run
    dt = result.time_s[1] - result.time_s[0]
    sig = result.signals
    axes = sim.robot.axes
    rotor = np.array([a.motor.rotor_inertia_kg_m2 for a in axes])
    inductance = np.array([a.motor.inductance_h for a in axes])

    def stored_j(k: int) -> float:
        q, v = result.position[k], result.velocity[k]
        w = sig[k, 0]
        i = sig[k, 1]
        return (
            sim.gantry.kinetic_energy_j(q, v)
            + 0.5 * float(rotor @ (w * w))
            + sim.gantry.potential_energy_j(q)
            + 0.5 * float(inductance @ (i * i))
        )

    e_in = float(sig[1:, 12].sum()) * dt
    losses = float((sig[1:, 13] + sig[1:, 10] + sig[1:, 11]).sum()) * dt
    gained = stored_j(len(result.time_s) - 1) - stored_j(0)
    assert e_in > 100.0  # a real amount of work was done
    assert (gained + losses) == pytest.approx(e_in, rel=2e-3)


def test_held_rigid_body_terms_match_the_exact_run(default_robot: RobotParams) -> None:
    """Pinocchio's terms held for 1 ms (the node's default) cost a tenth of the step's error.

    The busy run moves by less than a tenth of what the 0.1 ms step itself costs, and energy
    still closes. Held at the hold's mean position, the error is second order in the hold:
    10 steps move the busy run by microradians, while the step's own error
    (test_convergence_as_dt_shrinks) is up to 2e-4 rad.
    """
    scenario = _scenario(default_robot, **BUSY)
    exact = run_scenario(Simulator(default_robot), scenario)
    held_sim = Simulator(default_robot, rigid_body_update_steps=10)
    held = run_scenario(held_sim, scenario)
    assert np.abs(held.position - exact.position).max() < 2e-5  # rad (m for the lift)
    assert np.abs(held.velocity - exact.velocity).max() < 1e-4  # rad/s
    assert np.mean(held.drive == exact.drive) > 0.999  # switches move by a step or two at most
    # Held terms are really held: a run with them re-evaluated at every step differs.
    assert np.abs(held.position - exact.position).max() > 0.0

    dt = held.time_s[1] - held.time_s[0]
    sig = held.signals
    axes = default_robot.axes
    rotor = np.array([a.motor.rotor_inertia_kg_m2 for a in axes])
    inductance = np.array([a.motor.inductance_h for a in axes])

    def stored_j(k: int) -> float:
        q, v = held.position[k], held.velocity[k]
        return (
            held_sim.gantry.kinetic_energy_j(q, v)
            + 0.5 * float(rotor @ (sig[k, 0] ** 2))
            + held_sim.gantry.potential_energy_j(q)
            + 0.5 * float(inductance @ (sig[k, 1] ** 2))
        )

    e_in = float(sig[1:, 12].sum()) * dt
    losses = float((sig[1:, 13] + sig[1:, 10] + sig[1:, 11]).sum()) * dt
    assert (stored_j(len(held.time_s) - 1) - stored_j(0) + losses) == pytest.approx(e_in, rel=2e-3)


@pytest.mark.parametrize("hold_steps", [1, 10])
def test_refused_voltages_change_nothing(default_robot: RobotParams, hold_steps: int) -> None:
    """NaN commands through every entry point: refused, state and time kept, still usable."""
    from lca_sim.model import kernel
    from lca_sim.model.simulator import InputError

    sim = Simulator(default_robot, rigid_body_update_steps=hold_steps)
    sim.reset(position={"pivot": 0.9})
    good = np.array([0.0, 8.0, 0.0, 0.0])
    bad = np.array([0.0, math.nan, 0.0, 0.0])
    sim.advance(3, good)  # mid-hold when held
    before = sim.state
    with pytest.raises(InputError):
        sim.step(bad)
    with pytest.raises(InputError):
        sim.advance(5, bad)
    with pytest.raises(InputError):
        sim.advance_with(5, kernel.steps, bad.copy())
    assert sim.state == before
    sim.set_state(before)  # re-evaluates with the last good command, which is finite
    sim.advance(7, good)
    assert sim.time_s == pytest.approx(before.time_s + 7 * sim.dt_s)
    assert sim.state.current_a[PIVOT] > before.current_a[PIVOT] > 0.0  # still driven


def test_fig9_transition_angle_with_held_terms(default_robot: RobotParams) -> None:
    """The motor driving -> load driving switch of Fig 9 moves by under 0.01 deg with a hold."""
    angles = []
    for steps in (1, 10):
        sim = Simulator(default_robot, rigid_body_update_steps=steps)
        phases = run_scenario(sim, load_scenario("fig9_open_loop_pivot", sim.axis_names)).phases(
            "pivot"
        )
        angles.append(math.degrees(phases[3].position))
    assert angles[1] == pytest.approx(angles[0], abs=0.01)


# --- symmetry, convergence, determinism ------------------------------------------------------


def _swap_directions(robot: RobotParams) -> RobotParams:
    """The same robot with every direct and reverse coefficient exchanged."""
    axes = []
    for axis in robot.axes:
        f = axis.friction
        friction = FrictionParams(
            f.static_reverse_nm,
            f.static_direct_nm,
            f.coulomb_reverse_nm,
            f.coulomb_direct_nm,
            f.viscous_reverse_nm_s_per_rad,
            f.viscous_direct_nm_s_per_rad,
        )
        flip = {MotionState.DIRECT: MotionState.REVERSE, MotionState.REVERSE: MotionState.DIRECT}
        table = {(flip[d], s): e for (d, s), e in axis.efficiency.items()}
        axes.append(dataclasses.replace(axis, friction=friction, efficiency=table))
    return dataclasses.replace(robot, axes=tuple(axes))


def test_reverse_motion_mirrors_direct(default_robot: RobotParams) -> None:
    """Pivot run in DIRECT from q, and its mirror in REVERSE: identical up to the sign.

    The mirror pose q' = pi - 2 phi0 - q gives the opposite gravity torque, the voltage is
    negated and every direct coefficient is swapped with its reverse one.
    """
    sim = Simulator(default_robot)
    phi0 = _gravity_phase_rad(sim)
    q0 = 0.85
    doc = {
        "duration_s": 3.0,
        "dt_s": 1e-4,
        "record_period_s": 1e-3,
        "initial": {"position": {"pivot": q0}},
        "inputs": {"pivot": {"time_s": [0.0, 0.5, 2.5, 2.5], "voltage_v": [0.0, 9.0, 9.0, 0.0]}},
    }
    direct = run_scenario(sim, _scenario(default_robot, **doc))
    mirror_robot = _swap_directions(default_robot)
    doc["initial"] = {"position": {"pivot": math.pi - 2 * phi0 - q0}}
    doc["inputs"] = {"pivot": {"time_s": [0.0, 0.5, 2.5, 2.5], "voltage_v": [0.0, -9.0, -9.0, 0.0]}}
    mirror = run_scenario(Simulator(mirror_robot), _scenario(mirror_robot, **doc))

    states = {p.state for p in direct.phases("pivot")}
    assert {"motor_driving", "motor_and_load_driving_motor_dominant", "load_driving"} <= states
    np.testing.assert_allclose(
        mirror.position[:, PIVOT], math.pi - 2 * phi0 - direct.position[:, PIVOT], atol=1e-9
    )
    np.testing.assert_allclose(
        mirror.signal("current_a", "pivot"), -direct.signal("current_a", "pivot"), atol=1e-7
    )
    np.testing.assert_array_equal(mirror.motion[:, PIVOT], -direct.motion[:, PIVOT])
    # Moving states keep their names; the stop sub-states that name a direction swap.
    names = list(direct.state_names)
    swap = {names.index("stop_motor_direct"): names.index("stop_motor_reverse")}
    swap.update({v: k for k, v in swap.items()})
    mirrored = [swap.get(int(d), int(d)) for d in mirror.drive[:, PIVOT]]
    np.testing.assert_array_equal(mirrored, direct.drive[:, PIVOT])


def test_convergence_as_dt_shrinks(default_robot: RobotParams) -> None:
    """Halving dt shrinks the error against a fine reference about linearly (order ~1)."""
    doc: dict[str, object] = {
        "duration_s": 2.0,
        "record_period_s": 0.1,
        "initial": {"position": {"pivot": 0.9}},
        "inputs": {"pivot": {"time_s": [0.0, 0.5], "voltage_v": [0.0, 7.0]}},
    }

    def final_position(dt_s: float) -> float:
        robot_doc = {**doc, "dt_s": dt_s}
        sim = Simulator(default_robot, dt_s=dt_s)
        return float(run_scenario(sim, _scenario(default_robot, **robot_doc)).position[-1, PIVOT])

    reference = final_position(1e-5)
    errors = [abs(final_position(dt) - reference) for dt in (8e-4, 4e-4, 2e-4, 1e-4)]
    assert errors[0] > errors[1] > errors[2] > errors[3]
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(3)]
    assert all(0.6 < order < 1.6 for order in orders), orders
    assert errors[3] < 2e-4  # rad, at the default step


def test_same_run_twice_gives_identical_csv(default_robot: RobotParams, tmp_path: Path) -> None:
    """Determinism: two fresh simulators, the same scenario, byte-identical result.csv."""
    doc = {**BUSY, "duration_s": 1.5, "record_period_s": 0.005}
    for name in ("a", "b"):
        sim = Simulator(default_robot)
        write_csv(run_scenario(sim, _scenario(default_robot, **doc)), tmp_path / name / "r.csv")
    first = (tmp_path / "a" / "r.csv").read_bytes()
    assert len(first.splitlines()) == 1 + 301  # header, then t = 0 and 300 periods
    assert first == (tmp_path / "b" / "r.csv").read_bytes()


def test_fig9_phases_and_transition_angle(default_robot: RobotParams) -> None:
    """The shipped Fig 9 run: the paper's four phases, motor -> load driving at Q = 0."""
    sim = Simulator(default_robot)
    result = run_scenario(sim, load_scenario("fig9_open_loop_pivot", sim.axis_names))
    phases = result.phases("pivot")
    states = [p.state for p in phases]
    assert states[:4] == [
        "stop_hold",
        "stop_motor_direct",
        "motor_driving",
        "motor_and_load_driving_motor_dominant",
    ]
    assert "load_driving" in states
    assert states[-1] == "stop_hold"
    crossing_deg = math.degrees(math.pi / 2 - _gravity_phase_rad(sim))
    assert 55.0 <= crossing_deg <= 60.0  # the paper's Figs 4, 5, 15
    assert math.degrees(phases[3].position) == pytest.approx(crossing_deg, abs=0.05)
    # The paper's timeline (Fig 10): start 24-25 s, load driving from 37.8 s, stop by 40.3 s.
    assert 24.0 < phases[2].time_s < 25.0
    assert phases[3].time_s == pytest.approx(37.8, abs=0.3)
    stopped = next(p for p in phases[4:] if p.state.startswith("stop_"))
    assert 40.2 < stopped.time_s < 40.4  # braking phase: the paper has 40.2-40.3 s
