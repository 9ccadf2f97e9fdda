"""Compiled code from numba's cache of older files: refused, compiled again, never run.

numba keys a cached function on its own file, so `commanded_plant`'s current loops, which
compile in kernel's step, rigid_body's terms and lca_control's PI law, kept running the old
step after an edit of kernel.py: the current-loop path (the virtual drive's, the simulator
node's) and the voltage path then disagreed, silently.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from lca_control import pi as lca_pi
from lca_control.pi import PIParams
from lca_sim.config.loader import load_robot
from lca_sim.model import code_version, commanded_plant, kernel, rigid_body
from lca_sim.model.commanded_plant import (
    CODE_VERSION,
    CommandedPlant,
    _current_loops_steps,
    _sensed_current_loops_steps,
)
from lca_sim.model.simulator import Simulator

REPO = Path(__file__).resolve().parents[3]


def _plant(hold_steps: int = 10) -> CommandedPlant:
    sim = Simulator(load_robot("default"), 1e-4, rigid_body_update_steps=hold_steps)
    return CommandedPlant(sim, sim.axis_names, "current", PIParams(31.62, 0.001, -1, 1), 50.0)


def test_the_versions_follow_the_code_of_every_file_compiled_in() -> None:
    """Each file's functions and constants move the version; another module's names do not."""
    kernel_vars = {k: v for k, v in vars(kernel).items() if k != "CODE_VERSION"}  # as at import
    own = code_version.fingerprint(kernel_vars, kernel.__name__)
    assert code_version.combined(rigid_body.CODE_VERSION, own) == kernel.CODE_VERSION
    assert (
        code_version.combined(
            kernel.CODE_VERSION, code_version.fingerprint(vars(lca_pi), lca_pi.__name__)
        )
        == CODE_VERSION
    )
    assert code_version.fingerprint({**kernel_vars, "step": kernel.steps}, kernel.__name__) != own
    assert code_version.fingerprint({**kernel_vars, "OK": 7}, kernel.__name__) != own
    assert code_version.fingerprint({**kernel_vars, "half": 0.25}, kernel.__name__) != own
    fast_step = njit(fastmath=True)(kernel.step.py_func)  # the same code, other options
    assert code_version.fingerprint({**kernel_vars, "step": fast_step}, kernel.__name__) != own
    foreign = {**kernel_vars, "pi_law": lca_pi.pi_law}  # imported, not kernel's: not hashed
    assert code_version.fingerprint(foreign, kernel.__name__) == own
    assert code_version.combined(own, 1) != code_version.combined(own, 2)
    assert 0 <= CODE_VERSION < 2**63  # an int64 in compiled code


def test_the_stale_steppers_take_no_step() -> None:
    """Called with another version (compiled against other code), each returns -1, untouched."""
    plant = _plant()
    path = plant.sim._path
    before = path._work.copy()
    n = plant.sim.n_axes
    mass, nle = path._held_mass, path._held_nle
    args = (path._work, path._model, path._dt_s)
    stale = CODE_VERSION ^ 1
    assert (
        _current_loops_steps(5, plant._volts, plant._loops, plant._gains, stale, mass, nle, *args)
        == -1
    )
    sense, noise = np.vstack((np.ones(n), np.zeros(n))), np.zeros((5, n))
    assert (
        _sensed_current_loops_steps(
            5, plant._volts, plant._loops, plant._gains, stale, sense, noise, mass, nle, *args
        )
        == -1
    )
    assert np.array_equal(path._work, before, equal_nan=True)
    assert (
        _current_loops_steps(
            5, plant._volts, plant._loops, plant._gains, CODE_VERSION, mass, nle, *args
        )
        == 5
    )


def test_a_plant_on_stale_compiled_code_compiles_it_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """Another CODE_VERSION stands for an edited kernel.py: compiled again once, same bits.

    The warm-up finds every compiled function stale, compiles them all again once, and the
    plant then steps as one built on the real version does.
    """
    reference = _plant()
    recompiled: list[bool] = []
    recompile = commanded_plant.recompile_current_loops

    def counted() -> None:
        recompiled.append(True)
        recompile()

    monkeypatch.setattr(commanded_plant, "recompile_current_loops", counted)
    monkeypatch.setattr(commanded_plant, "CODE_VERSION", CODE_VERSION ^ 1)
    plant = _plant()
    assert recompiled == [True]
    for targets in ([2.0, -1.0, 0.5, 3.0], [-2.0, 1.5, 0.0, -3.0]):
        for each in (plant, reference):
            assert each.command(targets) is None
            each.advance(37)
    assert np.array_equal(plant.sim._work, reference.sim._work, equal_nan=True)
    _plant()  # compiled with the patched version: the same again, no recompile
    assert recompiled == [True]
    monkeypatch.undo()
    again = _plant()  # back on the real version: compiled again (and numba's cache rewritten)
    for each in (again, reference := _plant()):
        assert each.command([1.0, -2.0, 0.5, 1.5]) is None
        each.advance(23)
    assert np.array_equal(again.sim._work, reference.sim._work, equal_nan=True)


_PROBE = """
import json, sys
from lca_control.pi import PIParams
from lca_sim.config.loader import load_robot
from lca_sim.model.commanded_plant import CommandedPlant
from lca_sim.model.simulator import Simulator
sim = Simulator(load_robot("default"), 1e-4, rigid_body_update_steps=int(sys.argv[1]))
plant = CommandedPlant(sim, sim.axis_names, "current", PIParams(31.62, 0.001, -1, 1), 50.0)
plant.command([2.0, 2.0, 2.0, 2.0])
plant.advance(200)
json.dump(plant.current_loop_outputs_v.tolist(), sys.stdout)  # the loops' volts
"""


def _probe(tree: Path, cache: Path, hold_steps: int, jit: bool = True) -> list[float]:
    env = {**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(cache)}
    if not jit:
        env["NUMBA_DISABLE_JIT"] = "1"
    done = subprocess.run(
        [sys.executable, "-c", _PROBE, str(hold_steps)],
        check=False,
        env=env,
        cwd=tree,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    volts: list[float] = json.loads(done.stdout)
    return volts


@pytest.mark.parametrize(
    ("edited", "line", "edit", "holds"),
    [
        # kernel.step with the armature resistance tripled, on the same argument layout
        (
            "lca_sim/model/kernel.py",
            "r_ohm = model[P_RESISTANCE_OHM, a]",
            "r_ohm = 3.0 * model[P_RESISTANCE_OHM, a]",
            (10, 10),
        ),
        # the PI law's proportional part tripled, then a plant whose held terms are laid out
        # otherwise (terms at every step): its loops are compiled afresh, not loaded
        (
            "lca_control/pi.py",
            "unclamped = kp * error + new_integral",
            "unclamped = 3.0 * kp * error + new_integral",
            (10, 1),
        ),
    ],
    ids=["kernel.py", "pi.py"],
)
def test_an_edit_reaches_the_cached_current_loops(
    tmp_path: Path, edited: str, line: str, edit: str, holds: tuple[int, int]
) -> None:
    """The developer's case: edit a file the loops compile in, run on the cache of before.

    A copy of the packages, its own numba cache: the current loops' voltages after 20 ms at
    2 A, then the edit. The run on the old cache must give the edited physics (as the
    interpreted code does), not the old one.
    """
    tree = tmp_path / "tree"
    for package in ("lca_sim", "lca_control", "config"):
        shutil.copytree(
            REPO / package, tree / package, ignore=shutil.ignore_patterns("__pycache__")
        )
    cache = tmp_path / "numba"
    before, after_hold = _probe(tree, cache, holds[0]), holds[1]
    path = tree / edited
    source = path.read_text()
    assert source.count(line) == 1, "the probe's edit no longer applies: update the test"
    path.write_text(source.replace(line, edit))
    after = _probe(tree, cache, after_hold)
    interpreted = _probe(tree, cache, after_hold, jit=False)
    assert np.abs(np.subtract(interpreted, before)).max() > 0.1, (before, interpreted)  # V
    np.testing.assert_allclose(after, interpreted, rtol=1e-9, atol=1e-12)
