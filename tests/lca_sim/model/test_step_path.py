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

from lca_control.pi import PIParams
from lca_sim.config.loader import load_robot
from lca_sim.model import kernel
from lca_sim.model.commanded_plant import (
    _L_TARGET_A,
    CODE_VERSION,
    CommandedPlant,
    _current_loops_held,
    _current_loops_steps,
)
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


def _current_plant(hold_steps: int) -> CommandedPlant:
    """The default robot's plant under its in-drive current loops, terms held `hold_steps`."""
    sim = Simulator(load_robot("default"), 1e-4, rigid_body_update_steps=hold_steps)
    return CommandedPlant(sim, sim.axis_names, "current", PIParams(31.62, 0.001, -1, 1), 50.0)


def test_the_fused_held_advance_equals_the_stepper_over_its_holds() -> None:
    """`_current_loops_held` (one compiled call) against `advance_with`'s Python holds.

    The virtual rack and the simulator node advance their plant so (1 ms holds of 0.1 ms
    steps); the fused call must take the same steps on the same terms: every row of `work`,
    the loops, the hold's age and the clock identical after each advance, whole holds and
    parts of holds, under changing current targets through the gear's state changes.
    """
    fused, reference = _current_plant(10), _current_plant(10)
    rng = np.random.default_rng(11)
    drive_states: set[tuple[int, ...]] = set()
    for n_steps in (20, 7, 13, 37, 1, 20, 9, 40, 3, 20) * 6:
        targets = rng.uniform(-3.0, 3.0, 4)
        for plant in (fused, reference):
            assert plant.command(targets.tolist()) is None
        fused.advance(n_steps)  # the shipped path: fused
        ref_sim = reference.sim
        reference._loops[_L_TARGET_A] = reference._target
        ref_sim.advance_with(
            n_steps,
            _current_loops_steps,
            reference._volts,
            reference._loops,
            reference._gains,
            CODE_VERSION,
        )
        assert np.array_equal(fused.sim._work, ref_sim._work, equal_nan=True)
        assert np.array_equal(fused._loops, reference._loops)
        assert fused.sim._path._age == ref_sim._path._age
        assert fused.sim.time_s == ref_sim.time_s
        drive_states.add(tuple(fused.sim.state.drive))
    assert len(drive_states) > 3, drive_states  # the comparison ran through state changes


def test_a_fused_advance_compiled_against_other_code_refuses_to_run() -> None:
    """A stale cache (another `commanded_plant.CODE_VERSION`) runs no step: -1, untouched."""
    plant = _current_plant(10)
    path = plant.sim._path
    before = path._work.copy()
    mass, nle, tree, body = path._term_buffers
    out = np.zeros(2, dtype=np.int64)
    verdict = _current_loops_held(
        20, 0, 10, path._hold_lead_s, path._hold_position, path._held_mass, path._held_nle,
        mass, nle, tree, body, plant._volts, plant._loops, plant._gains, CODE_VERSION ^ 1,
        path._work, path._model, path._dt_s, out,
    )  # fmt: skip
    assert verdict == -1
    assert np.array_equal(path._work, before, equal_nan=True)
