"""`build_plant`: one wiring of model, commanded plant, in-drive current loop and faults."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lca_sim.config.loader import load_robot
from lca_sim.errors import ConfigError
from lca_sim.model.plant import PlantConfig, build_plant

PIVOT = 1


def _config(**changes: object) -> PlantConfig:
    base = PlantConfig(
        robot=load_robot("default"),
        dt_s=1e-4,
        rigid_body_update_steps=10,
        joints=("l_arm", "pivot", "c_arc", "lift"),
        interface="current",
        current_kp_v_per_a=31.62,
        current_ti_s=1e-3,
        max_abs_command=50.0,
    )
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]


def test_the_in_drive_current_loop_regulates_the_armature_current() -> None:
    """3 A asked of the pivot at rest: after 50 ms its armature carries 3 A within 1 %."""
    plant = build_plant(_config())
    plant.sim.reset({"pivot": 0.44})
    assert plant.commanded.command([0.0, 3.0, 0.0, 0.0]) is None
    plant.commanded.advance(500)
    current_a = plant.sim.state.current_a[PIVOT]
    assert current_a == pytest.approx(3.0, rel=0.01)
    assert plant.sim.time_s == pytest.approx(0.05)
    assert plant.faults is None


def test_limits_and_faults_are_wired_as_configured() -> None:
    """The setpoint saturates at current_limit_a; the faults act through the commanded plant."""
    plant = build_plant(_config(current_limit_a=5.0, fault_period_s=4e-3))
    assert plant.commanded.command([0.0, 30.0, 0.0, 0.0]) is None
    assert plant.commanded.counters.saturated == 1
    assert plant.commanded.target[PIVOT] == 5.0
    assert plant.commanded.command([0.0, 60.0, 0.0, 0.0]) is not None  # beyond max_abs_command
    assert plant.faults is not None and plant.commanded.faults is plant.faults


def test_voltage_interface_puts_the_command_on_the_armature() -> None:
    """Voltage commands go to the amplifier as they are: the pivot moves from rest."""
    plant = build_plant(_config(interface="voltage", max_abs_command=100.0))
    plant.sim.reset({"pivot": 0.44})
    plant.commanded.command([0.0, 8.0, 0.0, 0.0])
    plant.commanded.advance(2_000)
    assert np.isclose(plant.sim.signals["voltage_v"][PIVOT], 8.0)
    assert plant.sim.state.velocity[PIVOT] > 0.0


def test_an_unknown_interface_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="voltage or current"):
        build_plant(_config(interface="torque"))
