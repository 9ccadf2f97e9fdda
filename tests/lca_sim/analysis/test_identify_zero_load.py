"""Identification on an axis without a gravity load (the L-arm): float noise decides nothing."""

from __future__ import annotations

from lca_sim.analysis.identify import EstimateStatus, MotionRecord, identify
from lca_sim.config.loader import load_robot
from lca_sim.model.scenario import parse_scenario, run_scenario
from lca_sim.model.simulator import Simulator

L_ARM_RUN = {
    "duration_s": 6.0,
    "dt_s": 1.0e-4,
    "record_period_s": 1.0e-3,
    "initial": {"position": {"pivot": 0.44, "lift": 0.17}},  # a pose where tau_l is noise
    "inputs": {"l_arm": {"time_s": [0.0, 0.5, 1.0, 6.0], "voltage_v": [0.0, 0.0, 12.0, 12.0]}},
}


def test_l_arm_motor_driving_is_identified_not_reported_unvisited() -> None:
    """The L-arm's motor driving is identified: its load is zero, not rounding noise.

    Its load torque is Pinocchio's rounding residue (~1e-19 N m): inside the model's load band
    it is zero, so its samples are motor driving (Table 1 row 1), not ambiguous. Before the
    band reached the identification every state read "not visited".
    """
    robot = load_robot("default")
    scenario = parse_scenario(L_ARM_RUN, "l_arm_run", robot.axis_names)
    run = run_scenario(Simulator(robot, dt_s=scenario.dt_s), scenario)
    a = robot.axis_names.index("l_arm")
    record = MotionRecord(run.time_s, run.position, run.velocity, run.signal("current_a", "l_arm"))
    result = identify(robot, "l_arm", record)
    direct = {e.state: e for e in result.estimates if e.direction.name == "DIRECT"}
    motor = direct["motor_driving"]
    assert motor.n_samples > 1000, motor
    assert motor.status is EstimateStatus.IDENTIFIED, motor
    assert abs(motor.estimate - motor.prior.eta_m) < 0.02, (motor.estimate, motor.prior)
    assert robot.axes[a].name == "l_arm"
