"""Injected faults: each kind's physical consequence, on the composed closed loop (issue 16).

The composed loop (`lca_sim.analysis.closed_loop`) is the lockstep loop of the simulator and
controller nodes to the last bit, with the fault schedule switched at each period's start as the
node does; so these runs are what the nodes do, without ROS. The shipped Fig. 15 run: the pivot
from 35 deg on a ramp to 5 deg/s over 10 s from t = 1 s, the other joints holding, the drive's
current loop inside the plant.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from lca_control.pi import PIParams
from lca_sim.analysis.closed_loop import ClosedLoop, ClosedLoopConfig, ClosedLoopResult
from lca_sim.batch.closed_loop_config import closed_loop_config
from lca_sim.config.loader import load_robot
from lca_sim.config.params_file import node_parameters
from lca_sim.config.paths import config_dir
from lca_sim.model.commanded_plant import CommandedPlant
from lca_sim.model.fault_schedule import ScheduledFault
from lca_sim.model.faults import (
    JOINT_FAULTS,
    LINK,
    FaultInjector,
    StateLink,
)
from lca_sim.model.simulator import SIGNAL_NAMES, Simulator

CONFIG = config_dir()
PIVOT = 1
DT_S = 1e-4
PERIOD_S = 0.004


def _config(duration_s: float, *faults: ScheduledFault, robot: str = "default") -> ClosedLoopConfig:
    controller = node_parameters(CONFIG / "ros" / "controller.yaml", "controller")
    simulator = {**node_parameters(CONFIG / "ros" / "simulator.yaml", "simulator"), "robot": robot}
    config = closed_loop_config(controller, simulator, duration_s=duration_s)
    return dataclasses.replace(config, faults=tuple(faults))


def _run(duration_s: float, *faults: ScheduledFault, robot: str = "default") -> ClosedLoopResult:
    return ClosedLoop(_config(duration_s, *faults, robot=robot)).run()


def _on(kind: str, value: Any, start_s: float, end_s: float = math.inf) -> ScheduledFault:
    return ScheduledFault("pivot", kind, value, start_s, end_s)


def _window(result: ClosedLoopResult, start_s: float, end_s: float) -> np.ndarray:
    return (result.time_s >= start_s) & (result.time_s < end_s)


@pytest.fixture(scope="module")
def nominal() -> ClosedLoopResult:
    """The fault-free run, 5 s."""
    return _run(5.0)


def test_no_fault_configured_is_bit_for_bit_the_fault_free_run(nominal: ClosedLoopResult) -> None:
    """An injector with a schedule that has not started changes nothing, to the last bit."""
    later = _run(5.0, _on("jam", True, 100.0))
    for name in ("position", "velocity", "current_a", "voltage_v", "command"):
        np.testing.assert_array_equal(getattr(later, name), getattr(nominal, name), name)


def test_encoder_freeze_winds_the_velocity_loop_up(nominal: ClosedLoopResult) -> None:
    """Frozen at 2.0-2.5 s, the controller reads 0 rad/s: it pushes, the pivot overspeeds."""
    frozen = _run(5.0, _on("encoder_freeze", True, 2.0, 2.5))
    before = _window(frozen, 1.9, 2.0)
    during = _window(frozen, 2.3, 2.5)
    np.testing.assert_array_equal(frozen.position[before], nominal.position[before])
    assert frozen.current_a[during, PIVOT].max() > nominal.current_a[during, PIVOT].max() + 0.5
    overspeed = frozen.velocity[during, PIVOT] - frozen.velocity_reference[during, PIVOT]
    assert overspeed.max() > 0.01  # rad/s, against a reference of about 0.01 rad/s
    recovered = _window(frozen, 4.0, 5.0)
    error = np.abs(frozen.velocity[recovered, PIVOT] - frozen.velocity_reference[recovered, PIVOT])
    assert error.max() < math.radians(0.3)  # tracking as before, after the fault


def test_jam_stops_the_axis_and_the_current_rises_to_the_limit() -> None:
    """Jammed at 2 s: the pivot stops and stays; the velocity loop drives the current to 20 A."""
    jammed = _run(4.0, _on("jam", True, 2.0))
    after = _window(jammed, 2.1, 4.0)
    assert np.all(jammed.velocity[after, PIVOT] == 0.0)
    assert np.ptp(jammed.position[after, PIVOT]) == 0.0
    assert jammed.current_a[jammed.time_s >= 3.9, PIVOT].min() > 0.95 * 20.0
    assert jammed.drive_state[after, PIVOT].max() < 4  # a stop state of the state machine


def test_sto_self_locking_axis_holds_and_reversible_one_falls() -> None:
    """Safe torque off at 3 s: no current; the worm gear holds, the reversible gear does not."""
    locked = _run(4.0, _on("sto", True, 3.0))
    reversible = _run(4.0, _on("sto", True, 3.0), robot="reversible")
    after = _window(locked, 3.01, 4.0)
    for result in (locked, reversible):
        assert np.abs(result.current_a[after, PIVOT]).max() < 1e-6
    assert np.ptp(locked.position[_window(locked, 3.05, 4.0), PIVOT]) < 1e-9
    fell = reversible.position[-1, PIVOT] - reversible.position[after, PIVOT][0]
    assert abs(fell) > math.radians(1.0)  # the load drives the gear back


def test_current_limit_caps_the_current() -> None:
    """A 1 A drive limit from 2 s: the true current stays within it (the loop's overshoot)."""
    limited = _run(4.0, _on("current_limit_a", 1.0, 2.0))
    after = _window(limited, 2.2, 4.0)
    assert np.abs(limited.current_a[after, PIVOT]).max() < 1.05


def test_supply_sag_caps_the_amplifier_voltage(nominal: ClosedLoopResult) -> None:
    """99 % sag: the pivot's amplifier gives at most 1 % of its 300 V, less than it needs."""
    limit = load_robot("default").axes[PIVOT].motor.voltage_limit_v
    sagged = _run(5.0, _on("supply_sag", 0.99, 2.0))
    after = _window(sagged, 2.0, 5.0)
    assert np.abs(sagged.voltage_v[after, PIVOT]).max() <= 0.01 * limit + 1e-9
    assert np.abs(nominal.voltage_v[after, PIVOT]).max() > 0.01 * limit
    lag = nominal.position[-1, PIVOT] - sagged.position[-1, PIVOT]
    assert lag > 0.0  # the starved motor falls behind the ramp


def test_torque_constant_loss_needs_proportionally_more_current(
    nominal: ClosedLoopResult,
) -> None:
    """k_t halved: the same motion takes twice the current."""
    weak = _run(5.0, _on("torque_constant_loss", 0.5, 0.0))
    steady = _window(weak, 4.0, 5.0)
    ratio = np.mean(weak.current_a[steady, PIVOT]) / np.mean(nominal.current_a[steady, PIVOT])
    assert ratio == pytest.approx(2.0, rel=0.05)


def test_extra_friction_costs_its_current(nominal: ClosedLoopResult) -> None:
    """0.05 N m more friction at the motor: about 0.05 / (eta_m k_t) more current, moving."""
    extra_nm = 0.05
    rough = _run(5.0, _on("extra_friction_nm", extra_nm, 0.0))
    steady = _window(rough, 4.0, 5.0)
    k_t = load_robot("default").axes[PIVOT].motor.torque_constant_nm_per_a
    extra_a = np.mean(rough.current_a[steady, PIVOT] - nominal.current_a[steady, PIVOT])
    assert extra_nm / k_t < extra_a < extra_nm / (0.2 * k_t)  # eta_m in (0.2, 1]


def test_efficiency_drift_moves_eta_of_the_drifted_state_only() -> None:
    """Gear wear: eta_l + 0.1 in the pivot's motor-driving state, exactly, and nowhere else."""
    robot = load_robot("default")
    sim = Simulator(robot, DT_S)
    injector = FaultInjector(sim, PERIOD_S)
    before = sim.model_array.copy()
    injector.set("pivot", "drift_state", "motor_driving")
    injector.set("pivot", "eta_l_drift", 0.1)
    changed = np.argwhere(sim.model_array != before)
    assert {int(axis) for _, axis in changed} == {PIVOT}
    assert len(changed) == 2  # eta_l of motor driving, direct and reverse
    assert np.allclose(sim.model_array[tuple(changed.T)] - before[tuple(changed.T)], 0.1)
    injector.set("pivot", "eta_l_drift", 0.0)
    np.testing.assert_array_equal(sim.model_array, before)


def test_payload_raises_the_gravity_load_and_goes_back() -> None:
    """50 kg on the C-arc's link: its gravity torque and inertia rise; 0 restores them."""
    sim = Simulator(load_robot("default"), DT_S)
    injector = FaultInjector(sim, PERIOD_S)
    q = np.array([0.0, 0.6109, 0.5, 0.0])
    gravity, mass = sim.gantry.gravity(q), sim.gantry.mass_matrix(q)
    injector.set("c_arc", "payload_kg", 50.0)
    assert abs(sim.gantry.gravity(q)[2]) > abs(gravity[2]) * 1.1
    assert sim.gantry.mass_matrix(q)[2, 2] > mass[2, 2]
    injector.set("c_arc", "payload_kg", 0.0)
    np.testing.assert_array_equal(sim.gantry.gravity(q), gravity)


def _held_plant(**faults: Any) -> tuple[Simulator, CommandedPlant, FaultInjector]:
    """The default robot at rest with 2 A commanded on the l_arm (a self-locking held axis)."""
    sim = Simulator(load_robot("default"), DT_S)
    plant = CommandedPlant(sim, sim.axis_names, "current", PIParams(31.62, 0.001, -1, 1), 50.0)
    injector = FaultInjector(sim, PERIOD_S)
    plant.faults = injector
    for kind, value in faults.items():
        injector.set("l_arm", kind, value)
    plant.command([2.0, 0.0, 0.0, 0.0])
    for _ in range(100):
        plant.advance(40)
    return sim, plant, injector


def test_current_sensor_offset_and_gain_error_move_the_true_current() -> None:
    """The drive regulates the reading: true = (2 A - offset) / (1 + gain error)."""
    sim, _, injector = _held_plant(current_offset_a=0.5, current_gain_error=0.25)
    assert sim.state.current_a[0] == pytest.approx((2.0 - 0.5) / 1.25, abs=1e-3)
    read = (np.zeros(4), np.zeros(4), np.zeros(4))
    injector.measure(sim.state_array[0], sim.state_array[1], sim.state_array[2], read)
    assert read[2][0] == pytest.approx(2.0, abs=1e-3)  # what the drive (and motor_states) says


def test_current_sensor_noise_shakes_the_current_reproducibly() -> None:
    """Noise on the sensor: the true current scatters about 2 A, the same for the same seed."""
    sims = [_held_plant(current_noise_a=0.2)[0] for _ in range(2)]
    np.testing.assert_array_equal(sims[0].state_array, sims[1].state_array)
    sim, plant, _ = _held_plant(current_noise_a=0.2)
    samples = []
    for _ in range(200):
        plant.advance(1)
        samples.append(sim.state.current_a[0])
    assert 0.01 < float(np.std(samples)) < 0.5
    assert float(np.mean(samples)) == pytest.approx(2.0, abs=0.1)


def test_i2t_derates_then_trips() -> None:
    """A jammed l_arm at 8 A: the monitor derates to 2 A at its capacity, then trips."""
    sim, plant, injector = _held_plant(
        jam=True, i2t_rated_a=2.0, i2t_peak_a=8.0, i2t_peak_time_s=0.2, i2t_trip_after_s=0.3
    )
    plant.command([8.0, 0.0, 0.0, 0.0])
    currents, states = [], []
    for _ in range(300):  # 1.2 s
        plant.advance(40)
        currents.append(sim.state.current_a[0])
        states.append(injector.describe("l_arm"))
    capacity_s = 0.2 * (8.0**2 - 2.0**2) / (8.0**2 - 2.0**2)
    assert "i2t_derate" in states[int(0.3 / PERIOD_S)]
    assert currents[int(capacity_s / PERIOD_S) - 5] > 7.5  # full current until the capacity
    derated = [c for c, s in zip(currents, states, strict=True) if "i2t_derate" in s]
    assert max(derated[5:]) < 2.1
    assert "i2t_trip" in states[-1]
    assert abs(currents[-1]) < 1e-6  # tripped: torque off
    injector.set("l_arm", "i2t_rated_a", 0.0)  # clearing the monitor clears the trip
    assert not injector.drive.sto[0]


def test_encoder_faults_on_the_reading() -> None:
    """Bias adds, quantisation rounds, freeze holds, dropout gives NaN at about its rate."""
    sim = Simulator(load_robot("default"), DT_S)
    injector = FaultInjector(sim, PERIOD_S)
    q, v, i = np.array([0.1, 0.61234, 0.0, 0.2]), np.array([0.0, 0.05, 0.0, 0.0]), np.zeros(4)
    read = (np.zeros(4), np.zeros(4), np.zeros(4))
    injector.set("pivot", "encoder_bias", 0.01)
    injector.set("pivot", "encoder_quantisation", 0.001)
    injector.measure(q, v, i, read)
    assert read[0][PIVOT] == pytest.approx(0.622)
    assert read[0][0] == 0.1 and read[1][PIVOT] == 0.05
    injector.set("pivot", "encoder_freeze", True)
    injector.measure(q + 0.5, v, i, read)
    assert read[0][PIVOT] == pytest.approx(0.622) and read[1][PIVOT] == 0.0
    injector.set("pivot", "encoder_freeze", False)
    injector.set("lift", "encoder_dropout", 0.25)
    lost = 0
    for _ in range(2000):
        injector.measure(q, v, i, read)
        lost += math.isnan(read[0][3])
    assert 400 < lost < 600


def test_backlash_reading_lags_by_the_play_after_a_reversal() -> None:
    """A play of 0.02 rad: going up the reading trails by 0.01, after a reversal it stands."""
    sim = Simulator(load_robot("default"), DT_S)
    injector = FaultInjector(sim, PERIOD_S)
    injector.set("pivot", "backlash", 0.02)
    read = (np.zeros(4), np.zeros(4), np.zeros(4))
    path = [0.001 * k for k in range(100)] + [0.099 - 0.001 * k for k in range(30)]
    readings = []
    for angle in path:
        injector.measure(np.array([0.0, angle, 0.0, 0.0]), np.zeros(4), np.zeros(4), read)
        readings.append(read[0][PIVOT])
    assert readings[99] == pytest.approx(0.099 - 0.01)
    assert readings[100 + 19] == pytest.approx(readings[99])  # inside the play: no change
    assert readings[-1] == pytest.approx(path[-1] + 0.01)


def test_state_link_drops_delays_and_repeats() -> None:
    """Dropped instants never come; delayed ones come late with their own time; stale repeat."""
    sim = Simulator(load_robot("default"), DT_S)
    injector = FaultInjector(sim, PERIOD_S)
    link = StateLink(injector)
    injector.set(LINK, "state_delay_s", 0.012)
    out = [link.route(k * PERIOD_S, k) for k in range(10)]
    assert out[:3] == [[], [], []] and out[3] == [0] and out[9] == [6]
    injector.set(LINK, "state_delay_s", 0.0)
    injector.set(LINK, "state_stale", True)
    assert link.route(0.5, "new") == [6] and link.stale_sent == 1
    injector.set(LINK, "state_stale", False)
    injector.set(LINK, "state_drop", 1.0)
    assert link.route(0.6, "x") == [] and link.dropped == 1


def test_every_kind_is_a_typed_parameter_off_by_default() -> None:
    """Every joint fault kind has a range and is off at its default (no fault unless asked)."""
    sim = Simulator(load_robot("default"), DT_S)
    injector = FaultInjector(sim, PERIOD_S)
    injector.apply()
    assert not injector.any_active
    assert {k.category for k in JOINT_FAULTS} == {"sensor", "actuator", "mechanics", "thermal"}
    with pytest.raises(ValueError, match=r"faults\.pivot\.supply_sag"):
        injector.set("pivot", "supply_sag", 1.5)
    with pytest.raises(ValueError, match="drift_state"):
        injector.set("pivot", "drift_state", "no_such_state")


def test_a_composed_run_refuses_link_faults() -> None:
    """The link faults need the simulator node: a composed run's schedule naming one is refused."""
    with pytest.raises(ValueError, match="link"):
        _config(1.0, ScheduledFault(LINK, "state_drop", 0.5, 0.0, 1.0))


def test_signals_report_the_open_circuit_without_nan() -> None:
    """Under STO every signal the plant publishes stays finite (no inf * 0)."""
    sim, _plant, injector = _held_plant(sto=True)
    assert np.all(np.isfinite(sim.signal_array[[SIGNAL_NAMES.index("copper_loss_w")]]))
    assert injector.describe("l_arm") == "sto"


def test_lca_hil_run_takes_a_schedule_and_fault_parameters(tmp_path: Path) -> None:
    """`lca-hil run --faults NAME`, and faults.<joint>.<kind> in the simulator's params file."""
    from lca_sim.cli import run

    out = tmp_path / "scheduled"
    assert run.main(["run", "--duration-s", "3", "--faults", "pivot_encoder_freeze",
                     "--out", str(out)]) == 0  # fmt: skip
    assert (out / "trajectory.csv").is_file()
    params = yaml.safe_load((CONFIG / "ros" / "simulator.yaml").read_text())
    params["simulator"]["ros__parameters"]["faults.pivot.jam"] = True
    jammed_config = tmp_path / "simulator.yaml"
    jammed_config.write_text(yaml.safe_dump(params))
    out = tmp_path / "jammed"
    assert run.main(["run", "--duration-s", "2", "--simulator-config", str(jammed_config),
                     "--out", str(out)]) == 0  # fmt: skip
    summary = json.loads((out / "summary.json").read_text())
    assert summary["joints"]["pivot"]["max_abs_current_a"] > 19.0  # jammed from t = 0
    params["simulator"]["ros__parameters"]["faults.pivot.jam"] = "yes"
    jammed_config.write_text(yaml.safe_dump(params))
    assert run.main(["run", "--simulator-config", str(jammed_config), "--out", str(out)]) == 2


def test_encoder_noise_has_its_deviation_and_a_differentiated_velocity() -> None:
    """Position noise of sigma; velocity noise of sqrt(2) sigma / T, as a differentiator."""
    sim = Simulator(load_robot("default"), DT_S)
    injector = FaultInjector(sim, PERIOD_S)
    injector.set("pivot", "encoder_noise", 1e-4)
    read = (np.zeros(4), np.zeros(4), np.zeros(4))
    q_noise, v_noise = [], []
    for _ in range(4000):
        injector.measure(np.zeros(4), np.zeros(4), np.zeros(4), read)
        q_noise.append(read[0][PIVOT])
        v_noise.append(read[1][PIVOT])
    assert float(np.std(q_noise)) == pytest.approx(1e-4, rel=0.05)
    assert float(np.std(v_noise)) == pytest.approx(math.sqrt(2) * 1e-4 / PERIOD_S, rel=0.05)


def test_dropped_encoder_samples_leave_the_loop_running(nominal: ClosedLoopResult) -> None:
    """10 % of the pivot's samples lost: the controller resends its last command, no NaN."""
    lossy = ClosedLoop(_config(5.0, _on("encoder_dropout", 0.1, 1.0)))
    result = lossy.run()
    assert np.all(np.isfinite(result.command))
    assert result.commands_rejected == 0
    steady = _window(result, 3.0, 5.0)
    error = np.abs(result.velocity[steady, PIVOT] - result.velocity_reference[steady, PIVOT])
    assert error.max() < math.radians(0.5)  # still tracking


def test_worn_gear_changes_the_current_it_takes(nominal: ClosedLoopResult) -> None:
    """eta_m 0.2 lower in every moving state: the same motion takes more current."""
    worn = _run(5.0, _on("eta_m_drift", -0.2, 0.0))
    steady = _window(worn, 4.0, 5.0)
    assert np.mean(worn.current_a[steady, PIVOT]) > 1.1 * np.mean(nominal.current_a[steady, PIVOT])
