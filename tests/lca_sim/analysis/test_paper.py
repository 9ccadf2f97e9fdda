"""The paper's reproduction: linearisation, section 6 tuning, Figs 4-5, 9-10, 12-14, lca-hil paper.

The numbers asserted are the paper's where the model can meet them (docs/paper.md says why
where it cannot), and analytic ones where the paper gives none.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from lca_control.cascade import PAPER_CURRENT_KP_V_PER_A, PAPER_VELOCITY_KP_A_PER_RAD_S
from lca_control.controller import validate_controller_params
from lca_control.tuning import response_time_to_crossover, tune_pi
from lca_sim import RobotParams
from lca_sim.analysis.linear import (
    LinearisationError,
    OperatingPoint,
    independence_frequency,
    linearise,
    linearise_points,
)
from lca_sim.analysis.paper import (
    bode_study,
    constant_velocity_torques,
    open_loop_phases,
)
from lca_sim.analysis.tuning import tune_axis
from lca_sim.config.loader import load_scenario
from lca_sim.model.scenario import run_scenario
from lca_sim.model.simulator import Simulator
from lca_sim.model.state_machine import MotionState

PIVOT = 1


def _joint_inertia(sim: Simulator, q_pivot: float) -> float:
    """A_pp(q) + N^2 J_m of the pivot (joint side) with the other axes at 0."""
    q = np.zeros(4)
    q[PIVOT] = q_pivot
    axis = sim.robot.axes[PIVOT]
    return float(sim.gantry.mass_matrix(q)[PIVOT, PIVOT]) + (
        axis.gear_ratio**2 * axis.motor.rotor_inertia_kg_m2
    )


def _gravity_slope(sim: Simulator, q_pivot: float) -> float:
    """dQ_pivot/dq_pivot by central differences (joint side, N m per rad)."""
    h = 1e-6
    q = np.zeros(4)
    q[PIVOT] = q_pivot + h
    up = float(sim.gantry.gravity(q)[PIVOT])
    q[PIVOT] = q_pivot - h
    return (up - float(sim.gantry.gravity(q)[PIVOT])) / (2 * h)


@pytest.mark.parametrize(
    ("position_deg", "speed_deg_s", "state"),
    [(30.0, 7.0, "motor_driving"), (80.0, 7.0, "load_driving"),
     (30.0, -7.0, "motor_and_load_driving_load_dominant")],
)  # fmt: skip
def test_numerical_linearisation_matches_eq10_by_hand(
    default_robot: RobotParams, position_deg: float, speed_deg_s: float, state: str
) -> None:
    """A and B of the full model equal the linearisation of eq. (10) and the armature equation.

    With x = [q, qdot, i]: di/dt = (u - R i - k_t N qdot) / L, and on the joint side
    qddot = (eta_m k_t N i - eta_l Q(q) - N f(N qdot)) / (A(q) + N^2 J_m) at zero acceleration.
    """
    sim = Simulator(default_robot)
    point = OperatingPoint(math.radians(position_deg), math.radians(speed_deg_s))
    model = linearise(sim, "pivot", point)
    assert model.drive_state == state
    axis = default_robot.axes[PIVOT]
    m, n = axis.motor, axis.gear_ratio
    direction = "direct" if speed_deg_s > 0 else "reverse"
    eta = axis.efficiency[(_motion(speed_deg_s), state)]
    viscous = (
        axis.friction.viscous_direct_nm_s_per_rad
        if direction == "direct"
        else axis.friction.viscous_reverse_nm_s_per_rad
    )
    j = _joint_inertia(sim, point.position_rad)
    expected_a = np.array(
        [
            [0.0, 1.0, 0.0],
            [-eta.eta_l * _gravity_slope(sim, point.position_rad) / j, -viscous * n * n / j,
             eta.eta_m * m.torque_constant_nm_per_a * n / j],
            [0.0, -m.torque_constant_nm_per_a * n / m.inductance_h,
             -m.resistance_ohm / m.inductance_h],
        ]
    )  # fmt: skip
    np.testing.assert_allclose(model.a, expected_a, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(model.b.ravel(), [0.0, 0.0, 1.0 / m.inductance_h], rtol=1e-6)
    # The equilibrium: the voltage holds the current against R and the back-EMF.
    assert model.voltage_v == pytest.approx(
        m.resistance_ohm * model.current_a + m.torque_constant_nm_per_a * n * point.velocity_rad_s
    )


def _motion(speed_deg_s: float) -> MotionState:
    return MotionState.DIRECT if speed_deg_s > 0 else MotionState.REVERSE


def test_a_stopped_operating_point_has_no_linear_model(default_robot: RobotParams) -> None:
    with pytest.raises(LinearisationError, match="nonzero velocity"):
        linearise(Simulator(default_robot), "pivot", OperatingPoint(0.5, 0.0))


def test_independence_frequency_finds_where_responses_agree() -> None:
    omega = np.logspace(-1, 4, 501)
    # Two first-order lags that differ only by a low-frequency pole: 1/(s+a) vs 1/(s+2a).
    r1 = (1.0 / (1j * omega + 1.0)).astype(np.complex128)
    r2 = (1.0 / (1j * omega + 2.0)).astype(np.complex128)
    found = independence_frequency(omega, [r1, r2], tolerance_db=1.0, tolerance_deg=90.0)
    # |r1/r2|^2 = (w^2 + 4) / (w^2 + 1) = 10^(1/10) at w = sqrt((4 - g) / (g - 1)), g = 1.2589
    g = 10**0.1
    assert found == pytest.approx(math.sqrt((4 - g) / (g - 1)), rel=0.03)
    assert math.isnan(independence_frequency(omega, [r1, (2 * r1).astype(np.complex128)]))


def test_tune_pi_reads_unity_gain_from_the_smallest_plant_magnitude() -> None:
    tuning = tune_pi(100.0, [10 ** (-49.5 / 20), 10 ** (-48.6 / 20)])
    assert tuning.kp == pytest.approx(10 ** (49.5 / 20))
    assert tuning.ti_s == pytest.approx(0.01)
    assert tuning.plant_gain_spread_db == pytest.approx(0.9)
    assert response_time_to_crossover(3e-3) == pytest.approx(1000.0)


def test_tune_finds_the_papers_velocity_gains_and_margins(default_robot: RobotParams) -> None:
    """Section 6 on the default pivot: Ti exactly, the velocity Kp within 10 % of 316.23.

    The current Kp is the RL plant's |R + j wc L| (the method, checked analytically); that it
    is 30 % below the paper's 31.62 is the Fig. 13 calibration trade-off of docs/paper.md.
    """
    report = tune_axis(Simulator(default_robot), "pivot")
    assert report.current.ti_s == pytest.approx(1e-3)
    assert report.velocity.ti_s == pytest.approx(1e-2)
    assert report.velocity.kp == pytest.approx(PAPER_VELOCITY_KP_A_PER_RAD_S, rel=0.10)
    motor = default_robot.axes[PIVOT].motor
    rl = math.hypot(motor.resistance_ohm, 1000.0 * motor.inductance_h)
    assert report.current.kp == pytest.approx(rl, rel=3e-3)  # the back-EMF moves it by 0.1 %
    for point in report.points:
        # A crossover at or above wc everywhere, with the PI's margin left at every point.
        assert point.current.crossover_rad_s >= 1000.0
        assert point.velocity.crossover_rad_s >= 100.0
        assert point.current.phase_margin_deg > 45.0
        assert point.velocity.phase_margin_deg > 45.0
        assert point.velocity.sampled_phase_margin_deg > 30.0


@pytest.mark.xfail(
    strict=True,
    reason="the pivot is calibrated to Fig. 13's response; the paper's 30 dB reading needs "
    "L = 31.6 mH, which overshoots 28 % in 4.4 ms (docs/paper.md)",
)
def test_tune_finds_the_papers_current_gain_within_10_percent(
    default_robot: RobotParams,
) -> None:
    report = tune_axis(Simulator(default_robot), "pivot")
    assert report.current.kp == pytest.approx(PAPER_CURRENT_KP_V_PER_A, rel=0.10)


def test_tune_cli_writes_params_the_controller_accepts(tmp_path: Path) -> None:
    from lca_sim.cli.hil import main

    out = tmp_path / "tuned.yaml"
    assert main(["tune", "--out", str(out), "--velocity-crossover-rad-s", "50"]) == 0
    params = yaml.safe_load(out.read_text())["controller"]["ros__parameters"]
    assert params["velocity_ti_s"] == pytest.approx(0.02)
    controller = validate_controller_params(params)
    assert controller.cascade.velocity.kp == params["velocity_kp_a_per_rad_s"]
    # Half the crossover on a 1/s plant: about half the gain (6 dB less).
    assert params["velocity_kp_a_per_rad_s"] == pytest.approx(298.1 / 2, rel=0.05)


def test_tune_margins_with_the_loops_period_and_delay(default_robot: RobotParams) -> None:
    """A pure delay takes wc tau of phase at the crossover: the CAN loop's margins per period.

    Over a synchronous drive the command acts a cycle after its SYNC and is held a cycle (1.5
    periods); a late command adds one. At the paper's gains the loop keeps its margin at
    500 Hz and loses it with two periods of delay at 250 Hz (8 ms).
    """
    can_500 = tune_axis(
        Simulator(default_robot), "pivot", control_period_s=0.002, delay_periods=1.5
    )
    can_250 = tune_axis(
        Simulator(default_robot), "pivot", control_period_s=0.004, delay_periods=1.5
    )
    for point in can_500.points:
        v = point.velocity
        assert v.delay_s == pytest.approx(0.003)
        assert v.sampled_phase_margin_deg == pytest.approx(
            v.phase_margin_deg - math.degrees(v.crossover_rad_s * 0.003)
        )
        assert v.phase_margin_with_delay_deg(0.0) == v.phase_margin_deg
    # Crossover about 128-138 rad/s: 2 ms of delay take 15-16 deg, 8 ms 59-63 deg.
    assert can_500.velocity_margin_at_deg(2.0) > 20.0
    assert can_250.velocity_margin_at_deg(1.0) == pytest.approx(can_500.velocity_margin_at_deg(2.0))
    assert can_250.velocity_margin_at_deg(2.0) < 0.0


def test_tune_cli_reports_margins_at_one_and_two_periods(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lca_sim.cli.hil import main

    out = tmp_path / "tuned.yaml"
    argv = ["tune", "--out", str(out), "--control-period-s", "0.004", "--delay-periods", "1.5"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "delay 1.5 periods (6 ms)" in text
    assert "with 1 periods (4 ms) of delay" in text
    assert "with 2 periods (8 ms) of delay" in text and "UNSTABLE" in text
    assert main(["tune", "--out", str(out), "--delay-periods", "-1"]) == 2
    assert "--delay-periods" in capsys.readouterr().err


def test_tune_cli_bad_axis_is_one_error_line_and_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from lca_sim.cli.hil import main

    assert main(["tune", "--axis", "elbow", "--out", str(tmp_path / "x.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "elbow" in err[0]
    assert not (tmp_path / "x.yaml").exists()


@pytest.mark.parametrize("speed_deg_s", [7.0, -7.0])
def test_figs_4_5_torques_at_constant_velocity(
    default_robot: RobotParams, reversible_robot: RobotParams, speed_deg_s: float
) -> None:
    """Eq. (10) at zero acceleration, the load switch at the gravity top, irreversibility."""
    positions = np.radians(np.arange(10.0, 110.0, 0.25))
    sim = Simulator(default_robot)
    sweep = constant_velocity_torques(
        sim, Simulator(reversible_robot), math.radians(speed_deg_s), positions
    )
    axis = default_robot.axes[PIVOT]
    n = axis.gear_ratio
    w_m = n * math.radians(speed_deg_s)
    f = axis.friction
    tau_fv = (
        f.coulomb_direct_nm + f.viscous_direct_nm_s_per_rad * w_m
        if speed_deg_s > 0
        else -f.coulomb_reverse_nm + f.viscous_reverse_nm_s_per_rad * w_m
    )
    # The reversible model is eq. (5): tau_m = tau_l + tau_fv.
    np.testing.assert_allclose(
        sweep.reversible_motor_torque_nm, sweep.load_torque_nm + tau_fv, atol=1e-9
    )
    # The state-machine model: eta_m tau_m = eta_l tau_l + tau_fv with its state's efficiencies.
    motion = _motion(speed_deg_s)
    for tau_m, tau_l, state in zip(
        sweep.state_machine_motor_torque_nm, sweep.load_torque_nm, sweep.drive_state, strict=True
    ):
        eta = axis.efficiency[(motion, state)]
        assert eta.eta_m * tau_m == pytest.approx(eta.eta_l * tau_l + tau_fv, abs=1e-9)
    # The load becomes driving where gravity's torque changes sign: the centre of gravity over
    # the axis (found here from Pinocchio directly).
    q = np.zeros(4)
    top = []
    for x in positions:
        q[PIVOT] = x
        top.append(float(sim.gantry.gravity(q)[PIVOT]))
    crossing = positions[np.nonzero(np.diff(np.sign(top)))[0][0]]
    assert sweep.load_driving_from_rad == pytest.approx(crossing, abs=math.radians(0.5))
    assert math.degrees(sweep.load_driving_from_rad) == pytest.approx(55.0, abs=1.0)
    # Irreversibility: where the load drives, the worm holds part of gravity back, so the
    # state-machine motor needs more torque along the motion than the reversible one expects.
    direction = 1.0 if speed_deg_s > 0 else -1.0
    driving = np.array([s != "motor_driving" for s in sweep.drive_state])
    assert driving.sum() > 50
    assert np.all(
        direction * sweep.state_machine_motor_torque_nm[driving]
        > direction * sweep.reversible_motor_torque_nm[driving]
    )


def test_figs_9_10_four_phases_from_the_drive_states(default_robot: RobotParams) -> None:
    scenario = load_scenario("fig9_open_loop_pivot", default_robot.axis_names)
    result = run_scenario(Simulator(default_robot, dt_s=scenario.dt_s), scenario)
    phases = open_loop_phases(result, default_robot)
    assert [p.name for p in phases] == ["starting", "motor driving", "load driving", "braking"]
    starting, motor, load, braking = phases
    for a, b in itertools.pairwise(phases):
        assert a.end_s == b.start_s
    assert starting.start_s == pytest.approx(24.0, abs=2e-3)  # the voltage ramp begins
    assert starting.end_s == pytest.approx(25.0, abs=0.5)  # breakaway (paper: 25 s)
    assert motor.end_s == pytest.approx(37.8, abs=0.5)  # paper: 37.8 s
    assert math.degrees(load.start_position_rad) == pytest.approx(55.0, abs=1.0)
    assert braking.start_s == pytest.approx(40.2, abs=2e-3)  # the voltage cut
    assert braking.end_s - braking.start_s < 0.5  # held again within the paper's 0.1 s order


def test_figs_12_14_responses_stop_depending_on_the_operating_point(
    default_robot: RobotParams,
) -> None:
    sim = Simulator(default_robot)
    study = bode_study(sim, linearise_points(sim))
    assert len(set(study.drive_states)) >= 4  # the points cover the different drive states
    # Above the paper's frequencies the responses no longer depend on the operating point...
    assert study.current_independent_from_rad_s <= 1000.0
    assert study.velocity_independent_from_rad_s <= 20.0
    # ...and below they do (by more than the tolerance), which is why the paper looks there.
    low = study.omega_rad_s < 1.0
    for loop in (study.current_loop, study.velocity_loop):
        spread_db = np.ptp(20 * np.log10(np.abs(loop[:, low])), axis=0)
        assert spread_db.max() > 5.0
    # High-frequency asymptote of the current loop: Kp / (w L).
    motor = default_robot.axes[PIVOT].motor
    w = study.omega_rad_s[-1]
    np.testing.assert_allclose(
        np.abs(study.current_loop[:, -1]),
        PAPER_CURRENT_KP_V_PER_A / (w * motor.inductance_h),
        rtol=1e-3,
    )


def _ros_env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain_id))
    return env


@pytest.mark.slow
def test_lca_hil_paper_writes_every_figure_and_its_numbers(tmp_path: Path) -> None:
    """The whole command, Fig. 15 over ROS 2 included (its own domain)."""
    out = tmp_path / "paper"
    script = Path(sys.executable).with_name("lca-hil")
    proc = subprocess.run(
        [str(script), "paper", "--out", str(out)],
        env=_ros_env(141),
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    stems = [
        "fig04_constant_velocity_plus7deg_s",
        "fig05_constant_velocity_minus7deg_s",
        "fig12_current_open_loop_bode",
        "fig14_velocity_open_loop_bode",
        "fig13_current_step",
        "fig15_velocity_ramp",
    ]
    for stem in stems:
        assert (out / f"{stem}.png").stat().st_size > 10_000
        assert (out / f"{stem}.csv").stat().st_size > 1_000
    for png in ("fig09_voltage.png", "fig10_outputs.png"):
        assert (out / png).stat().st_size > 10_000
    assert (out / "fig09_10_open_loop.csv").stat().st_size > 1_000
    numbers = json.loads((out / "numbers.json").read_text())["reproduced"]
    assert numbers["fig15_transition_deg"] == pytest.approx(55.0, abs=1.0)
    assert numbers["fig15_max_velocity_error_deg_s"] < 0.3
    assert numbers["fig13_overshoot_pct"] == pytest.approx(24.0, abs=5.0)
    assert numbers["fig4_load_driving_deg"] == pytest.approx(55.0, abs=1.0)
    # Fig. 15's CSV: the velocity follows the ramp reference through the transition.
    rows = np.genfromtxt(out / "fig15_velocity_ramp.csv", delimiter=",", names=True)
    inside = (rows["t_s"] > 2.0) & (rows["t_s"] < 10.9)
    assert inside.sum() > 1000
    error = np.abs(rows["velocity_deg_s"][inside] - rows["velocity_ref_deg_s"][inside])
    assert error.max() < 0.3
