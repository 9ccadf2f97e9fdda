"""Eq. (2)'s rigid-body terms, A(q) and C(q, qdot) qdot + Q(q), in compiled code.

Pinocchio's two calls per step cost more through their bindings than their arithmetic, and
numba cannot call its C++, so the step evaluates the same algorithms here (CRBA for A(q), RNEA
at zero acceleration for C qdot + Q; Featherstone 2008, ch. 5-6) on the numbers of Pinocchio's
own model (`Gantry.pack_tree`). All in the world frame at its origin, Pinocchio's spatial
ordering; 1-DoF revolute and prismatic joints only, as `Gantry` enforces. Held to Pinocchio
to 1e-12 by tests/lca_sim/model/test_rigid_body.py; why and how: docs/model.md, section 2.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from numba import njit

from lca_sim.model import code_version

FloatArray = npt.NDArray[np.float64]

# Columns of `tree[row, col]`: row 0 is the fixed base (the "universe"), row j > 0 Pinocchio's
# joint j, whose q and v are at index j - 1 (checked by `Gantry.pack_tree`).
T_PARENT = 0  # parent row (0: the base), as an exact float
T_PRISMATIC = 1  # 1.0 prismatic, 0.0 revolute
T_AXIS = 2  # 3: the unit axis in the joint frame
T_PLACEMENT_R = 5  # 9: rotation of the joint frame in the parent's (row major)
T_PLACEMENT_P = 14  # 3: origin of the joint frame in the parent's, m
T_MASS = 17  # link mass, kg
T_LEVER = 18  # 3: centre of mass in the joint frame, m
T_INERTIA = 21  # 9: rotational inertia about the centre of mass, joint frame, kg m^2
T_ARMATURE = 30  # added to A(q)'s diagonal, as Pinocchio's crba does (kg m^2 or kg)
TREE_COLS = 31
T_GRAVITY = 0  # row 0, 3 columns: the gravity vector, m/s^2

# Columns of the scratch `body[row, col]`, one row per tree row.
B_R = 0  # 9: world rotation of the joint frame
B_P = 9  # 3: world origin of the joint frame
B_S = 12  # 6: motion subspace in the world frame at its origin
B_V = 18  # 6: spatial velocity
B_A = 24  # 6: bias acceleration (zero joint acceleration, base at -gravity)
B_F = 30  # 6: force of the body, then of its subtree (RNEA)
B_MASS = 36  # composite mass
B_H = 37  # 3: composite first moment m c
B_J = 40  # 9: composite rotational inertia about the world origin
B_FC = 49  # 6: CRBA's force Ic_j S_j
# Scratch of the passes (numba allocates a small array for about as long as the arithmetic of
# a joint takes, so they live in the row): B = R_parent R_placement, the joint's rotation, the
# joint origin in the parent's frame, the world axis, the centre of mass, a momentum.
B_TMP_B = 55  # 9
B_TMP_RJ = 64  # 9
B_TMP_LOCAL = 73  # 3
B_TMP_AXIS = 76  # 3
B_TMP_COM = 79  # 3
B_TMP_MOMENTUM = 82  # 6
BODY_COLS = 88


@njit(cache=True, inline="always")
def _cross_into(
    out: FloatArray, o: int, x: FloatArray, i: int, y: FloatArray, j: int, scale: float
) -> None:
    """out[o:o+3] += scale * (x[i:i+3] x y[j:j+3])."""
    out[o] += scale * (x[i + 1] * y[j + 2] - x[i + 2] * y[j + 1])
    out[o + 1] += scale * (x[i + 2] * y[j] - x[i] * y[j + 2])
    out[o + 2] += scale * (x[i] * y[j + 1] - x[i + 1] * y[j])


@njit(cache=True, inline="always")
def _apply_inertia(row: FloatArray, motion: FloatArray, m0: int, out: FloatArray, f0: int) -> None:
    """out[f0:f0+6] = I motion[m0:m0+6] for the body in `row` (m, h, J_O): momentum.

    Linear: m v + w x h; angular: J_O w + h x v (v, w the linear and angular parts).
    """
    mass = row[B_MASS]
    for k in range(3):
        out[f0 + k] = mass * motion[m0 + k]
        acc = 0.0
        for c in range(3):
            acc += row[B_J + 3 * k + c] * motion[m0 + 3 + c]
        out[f0 + 3 + k] = acc
    _cross_into(out, f0, motion, m0 + 3, row, B_H, 1.0)
    _cross_into(out, f0 + 3, row, B_H, motion, m0, 1.0)


@njit(cache=True, inline="always")
def _joint_transform(qj: float, t: FloatArray, out: FloatArray) -> None:
    """The joint's own motion in the parent's frame, into `B_TMP_RJ` and `B_TMP_LOCAL`.

    Revolute: Rj = cos 1 + sin [u]x + (1 - cos) u u^T (Rodrigues), origin p_placement.
    Prismatic: Rj = 1, origin p_placement + R_placement u q.
    """
    rj = out[B_TMP_RJ : B_TMP_RJ + 9]
    local = out[B_TMP_LOCAL : B_TMP_LOCAL + 3]
    ux, uy, uz = t[T_AXIS], t[T_AXIS + 1], t[T_AXIS + 2]
    for r in range(3):
        local[r] = t[T_PLACEMENT_P + r]
    if t[T_PRISMATIC] != 0.0:
        for r in range(3):
            local[r] += qj * (
                t[T_PLACEMENT_R + 3 * r] * ux
                + t[T_PLACEMENT_R + 3 * r + 1] * uy
                + t[T_PLACEMENT_R + 3 * r + 2] * uz
            )
        for k in range(9):
            rj[k] = 1.0 if k % 4 == 0 else 0.0
        return
    cq, sq = math.cos(qj), math.sin(qj)
    vq = 1.0 - cq
    rj[0] = cq + vq * ux * ux
    rj[1] = vq * ux * uy - sq * uz
    rj[2] = vq * ux * uz + sq * uy
    rj[3] = vq * uy * ux + sq * uz
    rj[4] = cq + vq * uy * uy
    rj[5] = vq * uy * uz - sq * ux
    rj[6] = vq * uz * ux - sq * uy
    rj[7] = vq * uz * uy + sq * ux
    rj[8] = cq + vq * uz * uz


@njit(cache=True, inline="always")
def _joint_pose(qj: float, t: FloatArray, parent: FloatArray, out: FloatArray) -> None:
    """The joint frame's world rotation and origin, and its world axis (`B_TMP_AXIS`).

    With B = R_parent R_placement: R = B Rj, origin p_parent + R_parent local, axis B u (the
    joint's rotation leaves u fixed).
    """
    _joint_transform(qj, t, out)
    b = out[B_TMP_B : B_TMP_B + 9]
    for r in range(3):
        for col in range(3):
            acc = 0.0
            for k in range(3):
                acc += parent[B_R + 3 * r + k] * t[T_PLACEMENT_R + 3 * k + col]
            b[3 * r + col] = acc
    for r in range(3):
        acc = parent[B_P + r]
        for k in range(3):
            acc += parent[B_R + 3 * r + k] * out[B_TMP_LOCAL + k]
        out[B_P + r] = acc
        for col in range(3):
            acc = 0.0
            for k in range(3):
                acc += b[3 * r + k] * out[B_TMP_RJ + 3 * k + col]
            out[B_R + 3 * r + col] = acc
        out[B_TMP_AXIS + r] = (
            b[3 * r] * t[T_AXIS] + b[3 * r + 1] * t[T_AXIS + 1] + b[3 * r + 2] * t[T_AXIS + 2]
        )


@njit(cache=True, inline="always")
def _joint_motion(vj: float, t: FloatArray, parent: FloatArray, out: FloatArray) -> None:
    """S = (p x a, a) revolute or (a, 0) prismatic; V = V_parent + S v; A = A_parent + (V x S) v."""
    for k in range(6):
        out[B_S + k] = 0.0
    if t[T_PRISMATIC] != 0.0:
        for k in range(3):
            out[B_S + k] = out[B_TMP_AXIS + k]
    else:
        for k in range(3):
            out[B_S + 3 + k] = out[B_TMP_AXIS + k]
        _cross_into(out, B_S, out, B_P, out, B_TMP_AXIS, 1.0)
    for k in range(6):
        out[B_V + k] = parent[B_V + k] + out[B_S + k] * vj
        out[B_A + k] = parent[B_A + k]
    # The motion cross product V x S: linear w x s_lin + v x s_ang, angular w x s_ang.
    _cross_into(out, B_A, out, B_V + 3, out, B_S, vj)
    _cross_into(out, B_A, out, B_V, out, B_S + 3, vj)
    _cross_into(out, B_A + 3, out, B_V + 3, out, B_S + 3, vj)


@njit(cache=True, inline="always")
def _link_inertia(t: FloatArray, out: FloatArray) -> None:
    """The link in the world: c = p + R lever, I_c = R I R^T, then (m, h = m c, J_O)."""
    mass = t[T_MASS]
    com = out[B_TMP_COM : B_TMP_COM + 3]
    for r in range(3):
        acc = out[B_P + r]
        for k in range(3):
            acc += out[B_R + 3 * r + k] * t[T_LEVER + k]
        com[r] = acc
    cc = com[0] * com[0] + com[1] * com[1] + com[2] * com[2]
    out[B_MASS] = mass
    for r in range(3):
        out[B_H + r] = mass * com[r]
        for col in range(3):
            acc = 0.0
            for k in range(3):
                rk = out[B_R + 3 * r + k]
                for m in range(3):
                    acc += rk * t[T_INERTIA + 3 * k + m] * out[B_R + 3 * col + m]
            shift = mass * ((cc if r == col else 0.0) - com[r] * com[col])
            out[B_J + 3 * r + col] = acc + shift


@njit(cache=True, inline="always")
def _body_force(row: FloatArray) -> None:
    """RNEA's force of one body with zero joint acceleration: f = I A + V x* (I V)."""
    _apply_inertia(row, row, B_A, row, B_F)
    _apply_inertia(row, row, B_V, row, B_TMP_MOMENTUM)
    # V x* h: linear w x h_lin; angular w x h_ang + v x h_lin.
    _cross_into(row, B_F, row, B_V + 3, row, B_TMP_MOMENTUM, 1.0)
    _cross_into(row, B_F + 3, row, B_V + 3, row, B_TMP_MOMENTUM + 3, 1.0)
    _cross_into(row, B_F + 3, row, B_V, row, B_TMP_MOMENTUM, 1.0)


@njit(cache=True, inline="always")
def _add_to_parent(row: FloatArray, parent: FloatArray) -> None:
    """The subtree's force and composite inertia (m, h, J_O) into its parent's."""
    for k in range(6):
        parent[B_F + k] += row[B_F + k]
    parent[B_MASS] += row[B_MASS]
    for k in range(3):
        parent[B_H + k] += row[B_H + k]
    for k in range(9):
        parent[B_J + k] += row[B_J + k]


@njit(cache=True, inline="always")
def _crba(tree: FloatArray, body: FloatArray, mass_matrix: FloatArray) -> None:
    """A[i, j] = S_i . (Ic_j S_j) for every ancestor i of j, zero across branches.

    The tree rows are in Pinocchio's order, parents first; the composite inertias are summed.
    """
    n = tree.shape[0]
    for i in range(n - 1):
        for j in range(n - 1):
            mass_matrix[i, j] = 0.0
    for j in range(1, n):
        row = body[j]
        _apply_inertia(row, row, B_S, row, B_FC)
        i = j
        while i > 0:
            s = body[i]
            acc = 0.0
            for k in range(6):
                acc += s[B_S + k] * row[B_FC + k]
            mass_matrix[i - 1, j - 1] = acc
            mass_matrix[j - 1, i - 1] = acc
            i = int(tree[i, T_PARENT])
        mass_matrix[j - 1, j - 1] += tree[j, T_ARMATURE]


@njit(cache=True)
def terms(
    q: FloatArray,
    v: FloatArray,
    tree: FloatArray,
    body: FloatArray,
    mass_matrix: FloatArray,
    nonlinear_effects: FloatArray,
) -> None:
    """Eq. (2)'s A(q) (both triangles) and C(q, qdot) qdot + Q(q), written in place.

    Args:
        q, v: joint positions (rad, m) and velocities (rad/s, m/s), in Pinocchio's order.
        tree: the packed model (`T_*` columns; `Gantry.pack_tree`), read only.
        body: scratch of `tree`'s row count x BODY_COLS, overwritten.
        mass_matrix: n x n output, any layout.
        nonlinear_effects: n output.
    """
    n = tree.shape[0]
    base = body[0]
    base[:] = 0.0
    base[B_R] = base[B_R + 4] = base[B_R + 8] = 1.0
    for k in range(3):
        base[B_A + k] = -tree[0, T_GRAVITY + k]  # the base accelerates against gravity
    for j in range(1, n):
        t, out, parent = tree[j], body[j], body[int(tree[j, T_PARENT])]
        _joint_pose(q[j - 1], t, parent, out)
        _joint_motion(v[j - 1], t, parent, out)
        _link_inertia(t, out)
        _body_force(out)
    # RNEA's backward pass, tau = S . f of the subtree, with CRBA's composite inertias.
    for j in range(n - 1, 0, -1):
        row = body[j]
        tau = 0.0
        for k in range(6):
            tau += row[B_S + k] * row[B_F + k]
        nonlinear_effects[j - 1] = tau
        p = int(tree[j, T_PARENT])
        if p > 0:
            _add_to_parent(row, body[p])
    _crba(tree, body, mass_matrix)


# numba's on-disk cache of a function is keyed on its own file only, so the cached
# `kernel.step_in_frame` would keep running an older `terms` after this file changed, on the old
# `TREE_COLS` / `BODY_COLS`: `kernel.make_frame` writes this value into the frame, the compiled
# step compares it with the one it was compiled with and refuses to run on a mismatch
# (`kernel.STALE_CODE`), and the simulator recompiles it (`code_version`).
CODE_VERSION = code_version.fingerprint(globals(), __name__)
