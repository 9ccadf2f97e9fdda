"""lca_sim: the drive-chain model of the LCA robot, its backends and its tools.

The sub-packages are layers (docs/architecture.md draws them; tests/test_architecture.py holds
them): the pure model and CiA 402 cores, config, analysis, the CAN bus, the ROS 2 node shells
and the console tools. The names below are faces of the model layer, loaded on first use so
that `import lca_sim` stays cheap (no numba, Pinocchio or SciPy until a model is built)::

    from lca_sim import load_robot, Simulator
    sim = Simulator(load_robot("default"), dt_s=1e-4)
    sim.step([0.0, 8.0, 0.0, 0.0])
    print(sim.signals.drive)
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from lca_sim.errors import ConfigError, LcaHilError, UnknownNameError

if TYPE_CHECKING:
    from lca_sim.config.loader import load_robot, load_scenario
    from lca_sim.model.params import AXIS_NAMES, RobotParams
    from lca_sim.model.scenario import Scenario, ScenarioResult, run_scenario
    from lca_sim.model.simulator import (
        SIGNAL_NAMES,
        AxisSignals,
        InputError,
        PlantState,
        Simulator,
    )
    from lca_sim.model.state_machine import MotionState, StopState

# Public name -> the module that defines it (PEP 562 lazy attributes).
_LAZY = {
    "load_robot": "lca_sim.config.loader",
    "load_scenario": "lca_sim.config.loader",
    "AXIS_NAMES": "lca_sim.model.params",
    "RobotParams": "lca_sim.model.params",
    "Scenario": "lca_sim.model.scenario",
    "ScenarioResult": "lca_sim.model.scenario",
    "run_scenario": "lca_sim.model.scenario",
    "SIGNAL_NAMES": "lca_sim.model.simulator",
    "AxisSignals": "lca_sim.model.simulator",
    "InputError": "lca_sim.model.simulator",
    "PlantState": "lca_sim.model.simulator",
    "Simulator": "lca_sim.model.simulator",
    "MotionState": "lca_sim.model.state_machine",
    "StopState": "lca_sim.model.state_machine",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'lca_sim' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])


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
