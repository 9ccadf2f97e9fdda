"""lca_sim: the drive-chain model of the LCA robot and a headless simulator.

Pure core (numpy, Pinocchio, numba): no ROS, no clock, no I/O beyond `lca_sim.config`, which
reads YAML files. Start with::

    from lca_sim import load_robot, Simulator
    sim = Simulator(load_robot("default"), dt_s=1e-4)
    sim.step([0.0, 8.0, 0.0, 0.0])
    print(sim.signals.drive)
"""

from lca_sim.config import load_robot, load_scenario
from lca_sim.errors import ConfigError, LcaHilError, UnknownNameError
from lca_sim.params import AXIS_NAMES, RobotParams
from lca_sim.scenario import Scenario, ScenarioResult, run_scenario
from lca_sim.simulator import SIGNAL_NAMES, AxisSignals, InputError, PlantState, Simulator
from lca_sim.state_machine import MotionState, StopState

__all__ = [
    "AXIS_NAMES",
    "SIGNAL_NAMES",
    "AxisSignals",
    "ConfigError",
    "InputError",
    "LcaHilError",
    "MotionState",
    "PlantState",
    "RobotParams",
    "Scenario",
    "ScenarioResult",
    "Simulator",
    "StopState",
    "UnknownNameError",
    "load_robot",
    "load_scenario",
    "run_scenario",
]
