"""The step's compiled rigid-body terms (`lca_sim.model.rigid_body`) against Pinocchio's.

A(q) from the compiled CRBA and C(q, qdot) qdot + Q(q) from the compiled RNEA must be what
Pinocchio's crba and nonLinearEffects give on the same model, over random states: on both
shipped robots, under a payload fault (which rewrites a link inertia at run time), and on a
made-up tree that uses what the gantry does not (a branch, unaligned axes, rotated placements,
a fixed joint merged into its parent, a prismatic joint first, armature). A model the compiled
terms would misread is refused when it is built.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lca_sim.config.loader import load_robot
from lca_sim.errors import ConfigError
from lca_sim.model.faults import FaultInjector
from lca_sim.model.gantry import Gantry
from lca_sim.model.simulator import Simulator

# Rounding of the two algorithms in two frames (world here, local in Pinocchio): measured
# 3e-14 of the largest term over 2000 random states of the gantry.
AGREEMENT = 1e-12

TREE_URDF = """<?xml version="1.0"?>
<robot name="branching">
  <link name="base"/>
  <joint name="slide" type="prismatic">
    <parent link="base"/><child link="carriage"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0.2 -0.1 0.4"/>
    <axis xyz="0.6 0 0.8"/>
    <limit lower="-0.5" upper="0.5" effort="100" velocity="1"/>
  </joint>
  <link name="carriage">
    <inertial><origin xyz="0.05 0.02 -0.1" rpy="0.3 0 0.1"/><mass value="12"/>
      <inertia ixx="0.4" ixy="0.01" ixz="-0.02" iyy="0.5" iyz="0.03" izz="0.3"/></inertial>
  </link>
  <joint name="bracket" type="fixed">
    <parent link="carriage"/><child link="bracket_link"/>
    <origin xyz="0 0.3 0" rpy="0 0.5 0"/>
  </joint>
  <link name="bracket_link">
    <inertial><origin xyz="0.1 0 0"/><mass value="3"/>
      <inertia ixx="0.02" ixy="0" ixz="0" iyy="0.03" iyz="0" izz="0.02"/></inertial>
  </link>
  <joint name="left" type="revolute">
    <parent link="bracket_link"/><child link="left_link"/>
    <origin xyz="0.2 0.1 0" rpy="0 0 0.3"/>
    <axis xyz="0.3 0.4 0.866"/>
    <limit lower="-3" upper="3" effort="100" velocity="1"/>
  </joint>
  <link name="left_link">
    <inertial><origin xyz="0.3 0 0.05"/><mass value="5"/>
      <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.2" iyz="0" izz="0.15"/></inertial>
  </link>
  <joint name="right" type="revolute">
    <parent link="carriage"/><child link="right_link"/>
    <origin xyz="-0.2 0 0.1" rpy="1.0 0 0"/>
    <axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="1"/>
  </joint>
  <link name="right_link">
    <inertial><origin xyz="0 0.25 0"/><mass value="4"/>
      <inertia ixx="0.08" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.08"/></inertial>
  </link>
  <joint name="wrist" type="revolute">
    <parent link="right_link"/><child link="wrist_link"/>
    <origin xyz="0 0.5 0"/>
    <axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="100" velocity="1"/>
  </joint>
  <link name="wrist_link">
    <inertial><origin xyz="0 0.1 0.02"/><mass value="1.5"/>
      <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.005" iyz="0" izz="0.01"/></inertial>
  </link>
</robot>
"""
GRAVITY = (0.0, 0.0, -9.81)


def _relative_error(gantry: Gantry, q: np.ndarray, v: np.ndarray) -> float:
    """The largest difference to Pinocchio's terms, over the largest of Pinocchio's terms."""
    mass, nle = gantry.dynamics_terms(q, v)
    ref_mass, ref_nle = gantry.pinocchio_terms(q, v)
    scale = max(np.max(np.abs(ref_mass)), np.max(np.abs(ref_nle)))
    return float(max(np.max(np.abs(mass - ref_mass)), np.max(np.abs(nle - ref_nle))) / scale)


def _state(gantry: Gantry, unit_q: list[float], v: list[float]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([j.position_min for j in gantry.joints])
    hi = np.array([j.position_max for j in gantry.joints])
    return lo + np.array(unit_q) * (hi - lo), np.array(v)


UNIT = st.floats(0.0, 1.0)
SPEED = st.floats(-2.0, 2.0)


@pytest.mark.parametrize("robot", ["default", "reversible"])
@settings(max_examples=300, deadline=None)
@given(unit_q=st.lists(UNIT, min_size=4, max_size=4), v=st.lists(SPEED, min_size=4, max_size=4))
def test_gantry_terms_are_pinocchios(robot: str, unit_q: list[float], v: list[float]) -> None:
    """Anywhere inside the joint limits, at any speed up to 2 rad/s: Pinocchio's terms."""
    gantry = _gantry(robot)
    q, qdot = _state(gantry, unit_q, v)
    assert _relative_error(gantry, q, qdot) < AGREEMENT


@settings(max_examples=300, deadline=None)
@given(unit_q=st.lists(UNIT, min_size=4, max_size=4), v=st.lists(SPEED, min_size=4, max_size=4))
def test_branching_tree_terms_are_pinocchios(unit_q: list[float], v: list[float]) -> None:
    """A branch, unaligned axes, rotated frames, a merged fixed link: Pinocchio's terms."""
    gantry = _tree()
    q, qdot = _state(gantry, unit_q, v)
    mass, _ = gantry.dynamics_terms(q, qdot)
    assert mass[1, 2] == 0.0 and mass[1, 3] == 0.0  # 'left' and 'right'/'wrist': two branches
    assert _relative_error(gantry, q, qdot) < AGREEMENT


def test_terms_move_with_the_state() -> None:
    """The comparison is not between constants: the terms change with q and qdot."""
    gantry = _tree()
    a_mass, a_nle = gantry.dynamics_terms(np.zeros(4), np.zeros(4))
    b_mass, b_nle = gantry.dynamics_terms(np.array([0.2, 1.0, -0.5, 0.7]), np.ones(4))
    assert np.max(np.abs(a_mass - b_mass)) > 0.01 and np.max(np.abs(a_nle - b_nle)) > 0.1


def test_armature_is_on_the_diagonal_as_in_pinocchios_crba() -> None:
    """Pinocchio's model armature enters A(q)'s diagonal in both (kg m^2, kg)."""
    gantry = _tree()
    q, v = np.array([0.1, 0.2, 0.3, 0.4]), np.array([0.5, -0.5, 0.2, 0.1])
    before, _ = gantry.dynamics_terms(q, v)
    gantry._model.armature = np.array([0.5, 0.25, 0.125, 2.0])
    gantry.pack_tree()
    after, _ = gantry.dynamics_terms(q, v)
    np.testing.assert_allclose(np.diag(after - before), [0.5, 0.25, 0.125, 2.0], rtol=1e-12)
    assert _relative_error(gantry, q, v) < AGREEMENT


def test_payload_fault_reaches_the_compiled_terms() -> None:
    """A 40 kg payload on the C-arc: Pinocchio's and the step's terms both carry it, and agree."""
    sim = Simulator(load_robot("default"), 1e-4)
    gantry = sim.gantry
    q, v = np.array([0.3, 0.7, 0.5, 0.1]), np.array([0.05, -0.1, 0.08, 0.02])
    mass, nle = gantry.dynamics_terms(q, v)
    injector = FaultInjector(sim, 0.004)
    injector.set("c_arc", "payload_kg", 40.0)
    loaded_mass, loaded_nle = gantry.dynamics_terms(q, v)
    assert loaded_mass[2, 2] > mass[2, 2] * 1.1 and abs(loaded_nle[2] - nle[2]) > 10.0  # N m
    assert _relative_error(gantry, q, v) < AGREEMENT
    injector.set("c_arc", "payload_kg", 0.0)
    np.testing.assert_array_equal(gantry.dynamics_terms(q, v)[0], mass)  # nominal again


def test_a_model_the_compiled_terms_misread_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """If the packed tree is wrong (here a joint axis flipped), building the gantry fails."""
    pack = Gantry.pack_tree

    def wrong_axis(self: Gantry) -> None:
        pack(self)
        self._tree[2, 2:5] *= -1.0  # rigid_body.T_AXIS of the pivot

    monkeypatch.setattr(Gantry, "pack_tree", wrong_axis)
    with pytest.raises(ConfigError, match="compiled rigid-body terms"):
        Simulator(load_robot("default"), 1e-4)


def test_unsupported_joint_is_refused() -> None:
    """A joint that is not a rotation about or translation along one axis: one clear error."""
    urdf = TREE_URDF.replace('type="prismatic"', 'type="floating"')
    with pytest.raises(ConfigError, match="1-DoF revolute or prismatic"):
        Gantry(urdf, GRAVITY, "<test>")


_CACHE: dict[str, Gantry] = {}


def _gantry(robot: str) -> Gantry:
    if robot not in _CACHE:
        params = load_robot(robot)
        _CACHE[robot] = Gantry(params.urdf_xml, params.gravity_m_s2, params.source)
    return _CACHE[robot]


def _tree() -> Gantry:
    return Gantry(TREE_URDF, GRAVITY, "<test>")
