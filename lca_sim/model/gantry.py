"""The gantry's rigid-body dynamics, eq. (1)-(2), from Pinocchio.

A(q), C(q, qdot) qdot and Q(q) are never written by hand: they come from Pinocchio's crba,
nonLinearEffects and computeGeneralizedGravity on the URDF.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
import numpy.typing as npt
import pinocchio as pin

from lca_sim.errors import ConfigError

FloatArray = npt.NDArray[np.float64]


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
            joints.append(
                JointInfo(
                    name=self._model.names[joint_id],
                    prismatic="JointModelP" in kind,
                    position_min=float(self._model.lowerPositionLimit[idx]),
                    position_max=float(self._model.upperPositionLimit[idx]),
                )
            )
        self.joints: tuple[JointInfo, ...] = tuple(joints)
        self.nv: int = int(self._model.nv)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Actuated joint names in Pinocchio's (tree) order."""
        return tuple(j.name for j in self.joints)

    def dynamics_terms(self, q: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """A(q) (upper triangle filled) and C(q, qdot) qdot + Q(q), eq. (2).

        The arrays are new copies of Pinocchio's results (its bindings return by value).
        """
        mass = pin.crba(self._model, self._data, q)
        nle = pin.nonLinearEffects(self._model, self._data, q, v)
        return mass, nle

    def terms_at(
        self, q: FloatArray, v: FloatArray
    ) -> tuple[Callable[[], FloatArray], Callable[[], FloatArray]]:
        """`dynamics_terms` bound to two arrays, as two calls without arguments, for a hot path.

        Each call evaluates Pinocchio's crba (A(q), upper triangle) or nonLinearEffects
        (C(q, qdot) qdot + Q(q)) at what `q` and `v` hold at that moment: the arrays are bound,
        not their values, so the caller updates them in place. The same Pinocchio functions on
        the same inputs as `dynamics_terms`, so the same bits; without its Python frame and
        attribute lookups (bench/model_step.py).
        """
        mass_at: Callable[[], FloatArray] = partial(pin.crba, self._model, self._data, q)
        nle_at: Callable[[], FloatArray] = partial(
            pin.nonLinearEffects, self._model, self._data, q, v
        )
        return mass_at, nle_at

    def term_buffers(self) -> tuple[FloatArray, FloatArray]:
        """Views of the buffers in Pinocchio's `Data` that crba and nonLinearEffects write.

        A(q) (`Data.M`, column major, upper triangle written) and C(q, qdot) qdot + Q(q)
        (`Data.nle`), in place, valid for this object's life (the model's size never changes).
        """
        return self._data.M, self._data.nle

    def mass_matrix(self, q: FloatArray) -> FloatArray:
        """A(q), full symmetric copy (kg m^2 or kg on the diagonal)."""
        mass: FloatArray = np.array(pin.crba(self._model, self._data, q))
        full: FloatArray = np.triu(mass) + np.triu(mass, 1).T
        return full

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
