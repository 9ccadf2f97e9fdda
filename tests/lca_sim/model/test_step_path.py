"""The exact step's fast path (`lca_sim.model.step_path.StepPath`) against the kernel call.

The fast path reaches `work`, `model` and the gantry's compiled terms' tree, scratch and output
buffers through a frame of raw addresses (docs/model.md, "The exact step's call path"). These
tests hold it to the general path, `Gantry.dynamics_terms` then `kernel.step`, step by step,
under random voltages: the same bits; and they check
that a simulator, whose step holds those addresses, refuses to be copied.
"""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

from lca_sim.config.loader import load_robot
from lca_sim.model import kernel
from lca_sim.model.faults import FaultInjector
from lca_sim.model.simulator import Simulator


def _reference_step(sim: Simulator, work: np.ndarray, volts: np.ndarray) -> None:
    """`kernel.step` with the gantry's terms at the state in `work` (the general path)."""
    mass, nle = sim.gantry.dynamics_terms(work[kernel.X_POSITION], work[kernel.X_VELOCITY])
    assert kernel.step(mass, nle, volts, work, sim.model_array, sim.dt_s) == kernel.OK


@pytest.mark.parametrize("robot", ["default", "reversible"])
def test_fast_step_equals_the_kernel_on_pinocchios_terms(robot: str) -> None:
    """3000 steps of random voltages: every row of `work` identical after every step."""
    sim = Simulator(load_robot(robot), 1e-4)
    rng = np.random.default_rng(7)
    reference = sim._work.copy()  # the state before the first step
    limits = np.array([a.motor.voltage_limit_v for a in sim.robot.axes])
    for k in range(3000):
        volts = rng.uniform(-1.0, 1.0, sim.n_axes) * limits * (0.2 if k % 500 < 250 else 1.0)
        sim.step(volts)
        _reference_step(sim, reference, volts)
        np.testing.assert_array_equal(sim._work, reference, f"step {k}")
    assert np.ptp(reference[kernel.X_POSITION]) > 0.0  # the run did move


def test_fast_step_follows_a_fault_that_rewrites_the_model() -> None:
    """The frame points at the live model: a jam set mid-run acts at the next step."""
    sim = Simulator(load_robot("default"), 1e-4)
    injector = FaultInjector(sim, 0.004)
    volts = np.array([0.0, 40.0, 0.0, 0.0])
    for _ in range(500):
        sim.step(volts)
    assert sim.state.velocity[1] != 0.0
    injector.set("pivot", "jam", True)
    for _ in range(200):
        sim.step(volts)
    assert sim.state.velocity[1] == 0.0


def test_fast_step_follows_a_payload_that_rewrites_a_link() -> None:
    """A payload set mid-run reaches the frame's packed tree: still the general path's bits."""
    sim = Simulator(load_robot("default"), 1e-4)
    healthy = Simulator(load_robot("default"), 1e-4)
    injector = FaultInjector(sim, 0.004)
    volts = np.array([3.0, 30.0, 3.0, 6.0])
    for _ in range(300):
        sim.step(volts)
        healthy.step(volts)
    injector.set("c_arc", "payload_kg", 60.0)
    reference = sim._work.copy()
    for k in range(300):
        sim.step(volts)
        healthy.step(volts)
        _reference_step(sim, reference, volts)
        np.testing.assert_array_equal(sim._work, reference, f"step {k}")
    assert not np.array_equal(sim._work, healthy._work)  # the payload did act


def test_a_simulator_refuses_copies() -> None:
    """copy, deepcopy and pickle would share the original's memory: refused with the reason."""
    sim = Simulator(load_robot("default"), 1e-4)
    for clone in (copy.copy, copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="raw addresses"):
            clone(sim)


def test_a_step_compiled_against_another_rigid_body_is_recompiled(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A cached step compiled against another rigid_body.py is refused, then compiled again.

    A different rigid_body.CODE_VERSION stands for an edited rigid_body.py: the cached step
    refuses to run (nothing touched), the simulator recompiles it, and it then steps as the
    general path does.
    """
    from lca_sim.model import rigid_body

    recompiled: list[bool] = []
    recompile = kernel.recompile_step_in_frame
    monkeypatch.setattr(rigid_body, "CODE_VERSION", rigid_body.CODE_VERSION ^ 1)

    def counted_recompile() -> None:
        recompiled.append(True)
        recompile()

    monkeypatch.setattr(kernel, "recompile_step_in_frame", counted_recompile)
    sim = Simulator(load_robot("default"), 1e-4)
    assert recompiled == [True]
    reference = sim._work.copy()
    volts = np.array([3.0, 30.0, 3.0, 6.0])
    for _ in range(50):
        sim.step(volts)
        _reference_step(sim, reference, volts)
    np.testing.assert_array_equal(sim._work, reference)
    monkeypatch.undo()
    Simulator(load_robot("default"), 1e-4)  # back on the real version: compiled again
