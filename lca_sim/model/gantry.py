"""The gantry's rigid-body dynamics, eq. (1)-(2), from Pinocchio.

The robot is never written by hand: Pinocchio's URDF parser builds the model (tree, placements,
axes, link inertias with fixed links merged), and its algorithms give A(q), C(q, qdot) qdot and
Q(q), the energies and the forward dynamics. The simulator's step evaluates A(q) and
C qdot + Q through `lca_sim.model.rigid_body`, the same two algorithms (CRBA, RNEA) compiled
with the step on that same model's numbers (`pack_tree`), because Pinocchio's Python bindings
cost more per call than the arithmetic at four joints; a model whose compiled terms do not agree
with Pinocchio's is refused when it is built.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pinocchio as pin

from lca_sim.errors import ConfigError
from lca_sim.model import rigid_body

FloatArray = npt.NDArray[np.float64]

# Joints whose motion is a rotation about, or a translation along, one fixed axis of the joint
# frame: the ones `rigid_body` evaluates (Pinocchio's short names).
_AXIS_JOINTS = {
    **{f"JointModelR{x}": False for x in "XYZ"},
    **{f"JointModelP{x}": True for x in "XYZ"},
    "JointModelRevoluteUnaligned": False,
    "JointModelPrismaticUnaligned": True,
}
# How far the compiled terms may be from Pinocchio's (relative to the largest term) before a
# model is refused: rounding is about 1e-15 here, a wrong axis or placement is order 1.
_TERMS_AGREEMENT = 1e-9


@dataclass(frozen=True, slots=True)
class JointInfo:
    """One actuated joint of the URDF."""

    name: str
    prismatic: bool
    position_min: float
    position_max: float


class Gantry:
    """A Pinocchio model of the gantry, built once; `Data` is scratch owned by this object.

    Not thread-safe: each simulator owns its own `Gantry`.
    """

    def __init__(
        self, urdf_xml: str, gravity_m_s2: tuple[float, float, float], source: str
    ) -> None:
        try:
            self._model = pin.buildModelFromXML(urdf_xml)
        except (RuntimeError, ValueError) as exc:  # Pinocchio reports URDF errors as RuntimeError
            raise ConfigError(source, "robot.urdf", f"expected a valid URDF ({exc})") from exc
        self._model.gravity.linear = np.asarray(gravity_m_s2, dtype=float)
        self._data = self._model.createData()
        joints = []
        for joint_id in range(1, self._model.njoints):
            joint = self._model.joints[joint_id]
            if joint.nq != 1 or joint.nv != 1:
                raise ConfigError(
                    source, "robot.urdf", "expected only 1-DoF revolute or prismatic joints"
                )
            kind = joint.shortname()
            idx = joint.idx_q
            if kind not in _AXIS_JOINTS or idx != joint_id - 1 or joint.idx_v != idx:
                raise ConfigError(
                    source,
                    "robot.urdf",
                    "expected only 1-DoF revolute or prismatic joints about or along one axis "
                    f"(joint {self._model.names[joint_id]!r} is {kind})",
                )
            joints.append(
                JointInfo(
                    name=self._model.names[joint_id],
                    prismatic=_AXIS_JOINTS[kind],
                    position_min=float(self._model.lowerPositionLimit[idx]),
                    position_max=float(self._model.upperPositionLimit[idx]),
                )
            )
        self.joints: tuple[JointInfo, ...] = tuple(joints)
        self.nv: int = int(self._model.nv)
        self._tree = np.zeros((self._model.njoints, rigid_body.TREE_COLS))
        self._body = np.zeros((self._model.njoints, rigid_body.BODY_COLS))
        self._mass = np.zeros((self.nv, self.nv), order="F")
        self._nle = np.zeros(self.nv)
        self.pack_tree()
        self._check_terms(source)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Actuated joint names in Pinocchio's (tree) order."""
        return tuple(j.name for j in self.joints)

    def pack_tree(self) -> None:
        """Copy the Pinocchio model's numbers into the compiled terms' `tree` (in place).

        Called at construction and by `set_link_inertia`; the array keeps its address, so a
        step that holds it sees the change at its next call.
        """
        model, tree = self._model, self._tree
        tree[0, :] = 0.0
        tree[0, rigid_body.T_GRAVITY : rigid_body.T_GRAVITY + 3] = model.gravity.linear
        data = model.createData()
        for joint_id in range(1, model.njoints):
            row = tree[joint_id]
            info = self.joints[joint_id - 1]
            # The motion subspace in the joint frame: (axis, 0) prismatic, (0, axis) revolute.
            subspace = np.asarray(data.joints[joint_id].S, dtype=float).reshape(6)
            axis = subspace[:3] if info.prismatic else subspace[3:]
            placement = model.jointPlacements[joint_id]
            inertia = model.inertias[joint_id]
            row[rigid_body.T_PARENT] = float(model.parents[joint_id])
            row[rigid_body.T_PRISMATIC] = 1.0 if info.prismatic else 0.0
            row[rigid_body.T_AXIS : rigid_body.T_AXIS + 3] = axis
            row[rigid_body.T_PLACEMENT_R : rigid_body.T_PLACEMENT_R + 9] = np.asarray(
                placement.rotation
            ).reshape(9)
            row[rigid_body.T_PLACEMENT_P : rigid_body.T_PLACEMENT_P + 3] = placement.translation
            row[rigid_body.T_MASS] = inertia.mass
            row[rigid_body.T_LEVER : rigid_body.T_LEVER + 3] = inertia.lever
            row[rigid_body.T_INERTIA : rigid_body.T_INERTIA + 9] = np.asarray(
                inertia.inertia
            ).reshape(9)
            row[rigid_body.T_ARMATURE] = model.armature[joint_id - 1]

    def _check_terms(self, source: str) -> None:
        """Refuse a model whose compiled terms are not Pinocchio's (a joint they misread)."""
        rng = np.random.default_rng(0)
        lo = np.array([j.position_min for j in self.joints])
        hi = np.array([j.position_max for j in self.joints])
        bounded = np.isfinite(lo) & np.isfinite(hi)
        for _ in range(3):
            q = rng.normal(size=self.nv)
            q[bounded] = rng.uniform(lo[bounded], hi[bounded])
            v = rng.normal(size=self.nv)
            mass, nle = self.terms_in_place(q, v)
            ref_mass, ref_nle = self.pinocchio_terms(q, v)
            scale = max(float(np.max(np.abs(ref_mass))), float(np.max(np.abs(ref_nle))), 1.0)
            error = max(
                float(np.max(np.abs(mass - ref_mass))), float(np.max(np.abs(nle - ref_nle)))
            )
            if not error <= _TERMS_AGREEMENT * scale:
                raise ConfigError(
                    source,
                    "robot.urdf",
                    "a model the compiled rigid-body terms reproduce (they differ from "
                    f"Pinocchio's by {error:.3g} of {scale:.3g})",
                )

    def terms_in_place(self, q: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A(q) (full, symmetric) and C(q, qdot) qdot + Q(q), eq. (2), compiled.

        Returns this object's own two buffers, overwritten by the next call: for a caller that
        uses them at once (the simulator's step). `dynamics_terms` returns copies.
        """
        rigid_body.terms(q, v, self._tree, self._body, self._mass, self._nle)
        return self._mass, self._nle

    def dynamics_terms(self, q: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A(q) (full, symmetric) and C(q, qdot) qdot + Q(q), eq. (2): new arrays.

        The terms the simulator steps on (`terms_in_place`), as copies.
        """
        mass, nle = self.terms_in_place(q, v)
        return mass.copy(), nle.copy()

    def pinocchio_terms(self, q: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Pinocchio's crba (made symmetric) and nonLinearEffects at (q, qdot): the reference."""
        nle: FloatArray = np.array(pin.nonLinearEffects(self._model, self._data, q, v))
        return self.mass_matrix(q), nle

    def term_buffers(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The arrays the compiled terms read and write: A(q), C qdot + Q, tree and scratch.

        In place, valid for this object's life (never replaced), for a step that holds their
        addresses (`kernel.make_frame`).
        """
        return self._mass, self._nle, self._tree, self._body

    def link_inertia(self, axis: int) -> pin.Inertia:
        """A copy of the inertia of the link moved by joint `axis` (0-based, in axis order)."""
        inertia: pin.Inertia = self._model.inertias[axis + 1].copy()
        return inertia

    def set_link_inertia(self, axis: int, inertia: pin.Inertia) -> None:
        """Replace the inertia of the link moved by joint `axis` (a payload), everywhere.

        Pinocchio's model and the compiled terms' copy of it change together.
        """
        self._model.inertias[axis + 1] = inertia.copy()
        self.pack_tree()

    def mass_matrix(self, q: FloatArray) -> FloatArray:
        """A(q) from Pinocchio's crba, full symmetric copy (kg m^2 or kg on the diagonal)."""
        upper = np.triu(np.array(pin.crba(self._model, self._data, q)))
        mass: FloatArray = upper + np.triu(upper, 1).T
        return mass

    def gravity(self, q: FloatArray) -> FloatArray:
        """Q(q): the generalized gravity torques/forces, joint side (N m or N)."""
        return np.array(pin.computeGeneralizedGravity(self._model, self._data, q))

    def coriolis(self, q: FloatArray, v: FloatArray) -> FloatArray:
        """C(q, qdot) qdot, joint side."""
        return np.array(pin.nonLinearEffects(self._model, self._data, q, v)) - self.gravity(q)

    def kinetic_energy_j(self, q: FloatArray, v: FloatArray) -> float:
        """Kinetic energy of the links, J (rotor inertia not included)."""
        return float(pin.computeKineticEnergy(self._model, self._data, q, v))

    def potential_energy_j(self, q: FloatArray) -> float:
        """Gravitational potential energy of the links, J (zero at the world origin)."""
        return float(pin.computePotentialEnergy(self._model, self._data, q))

    def aba(self, q: FloatArray, v: FloatArray, tau: FloatArray) -> FloatArray:
        """Joint accelerations from joint torques (Pinocchio's ABA), for checks and benchmarks."""
        return np.array(pin.aba(self._model, self._data, q, v, tau))
