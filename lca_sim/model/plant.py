"""One wiring of the plant for every backend: model, command intake, in-drive current loop, faults.

The simulator node, the composed closed loop (`lca-hil run`, sweeps) and the virtual drive rack
each run the same plant: a `Simulator` of the robot, a `CommandedPlant` in front of it with the
current PI "in the drive" (lca_control's PI law, docs/control.md), and, where the backend takes
them, the model-level faults of docs/faults.md. `PlantConfig` says what differs between them;
`build_plant` is the one place that puts the parts together. It sits in the model layer, below
config/ and analysis/, so that every backend can use it.
"""

from __future__ import annotations

from dataclasses import dataclass

from lca_control.pi import PIParams
from lca_sim.errors import ConfigError
from lca_sim.model.commanded_plant import CURRENT, VOLTAGE, CommandedPlant
from lca_sim.model.faults import FaultInjector
from lca_sim.model.params import RobotParams
from lca_sim.model.simulator import Simulator


@dataclass(frozen=True, slots=True)
class PlantConfig:
    """What one backend's plant is made of.

    Attributes:
        robot: the robot's parameters.
        dt_s: the model step.
        rigid_body_update_steps: model steps per evaluation of eq. (2)'s A(q) and C qdot + Q.
        joints: the order of the command arrays (a subset of the robot's axes).
        interface: `voltage` (V per joint) or `current` (A; the current PI runs in the plant).
        current_kp_v_per_a, current_ti_s: the in-drive current PI; its output is limited to
            each axis's amplifier voltage.
        max_abs_command: a command beyond this magnitude is refused as absurd.
        current_limit_a: current setpoints beyond this are saturated (None: the plant's 20 A).
        enabled: amplifiers on at start.
        fault_period_s: take model-level faults (`FaultInjector`) judged at this period, the
            backend's control period; None: this backend has none (the rack's faults are
            CAN-level, its own part).
    """

    robot: RobotParams
    dt_s: float
    rigid_body_update_steps: int
    joints: tuple[str, ...]
    interface: str
    current_kp_v_per_a: float
    current_ti_s: float
    max_abs_command: float
    current_limit_a: float | None = None
    enabled: bool = True
    fault_period_s: float | None = None


@dataclass(frozen=True, slots=True)
class Plant:
    """The parts `build_plant` made: the model, the plant in front of it, its faults if any."""

    sim: Simulator
    commanded: CommandedPlant
    faults: FaultInjector | None


def build_plant(config: PlantConfig) -> Plant:
    """The simulator, the commanded plant and the fault injector of `config`, wired.

    Raises:
        ConfigError: an interface other than voltage or current.
    """
    if config.interface not in (VOLTAGE, CURRENT):
        raise ConfigError(
            "plant", "interface", f"expected {VOLTAGE} or {CURRENT}, got {config.interface!r}"
        )
    sim = Simulator(
        config.robot, dt_s=config.dt_s, rigid_body_update_steps=config.rigid_body_update_steps
    )
    faults = (
        None
        if config.fault_period_s is None
        else FaultInjector(sim, period_s=config.fault_period_s)
    )
    commanded = CommandedPlant(
        sim=sim,
        joints=config.joints,
        interface=config.interface,
        # The loop's output limits are replaced by each axis's amplifier limit (CommandedPlant).
        current_pi=PIParams(config.current_kp_v_per_a, config.current_ti_s, -1.0, 1.0),
        max_abs_command=config.max_abs_command,
        enabled=config.enabled,
        faults=faults,
    )
    if config.current_limit_a is not None:
        commanded.current_limit_a = config.current_limit_a
    return Plant(sim=sim, commanded=commanded, faults=faults)
