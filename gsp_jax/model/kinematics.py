"""Forward kinematics of the hand in pure JAX, built from the model file's kinematic tree.

All functions take joint angles `q` of shape (J,) and are differentiable; `jax.vmap` them for batches.
They agree with MuJoCo's own `mj_kinematics` (tests/test_kinematics.py). The chain is written twice more, each copy
checked against `chain` here: batch last in `ik_lanes.chain`, in numba in `physics.native._chain` and `_links`.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.core import platform
from gsp_jax.model.hand import HandModel


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Unit quaternion(s) (..., 4) as (w, x, y, z) -> rotation matrix (..., 3, 3)."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def body_poses(hand: HandModel, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World poses of the hand's bodies: positions (B, 3) and rotation matrices (B, 3, 3)."""
    pos, mat, _, _ = chain(hand, q)
    return pos, mat


def chain(hand: HandModel, q: jax.Array):
    """Body poses (B, 3), (B, 3, 3) plus every joint's world axis (J, 3) and anchor (J, 3).

    The tree is walked level by level (all bodies at one depth at once: for this hand, one body per finger), with
    the 3x3 products as `small_einsum`s, so on a GPU a pose costs a few fused kernels per level rather than a few
    matmuls per body (the IK evaluates it every iteration, and each kernel is a launch).
    The reference of `ik_lanes.chain` and `physics.native._chain`, which must equal it; checked by
    `tests/test_kinematics.py::test_batch_last_chain_equals_chain` and
    `tests/test_native.py::test_native_chain_and_links_are_kinematics`."""
    dtype = q.dtype
    q_ext = jnp.concatenate([q, jnp.zeros(1, dtype)])  # index J: the angle of a body without a joint (identity)
    pos_l, mat_l, axis_l, anchor_l, order = [], [], [], [], []
    prev = None
    for bodies, parent_slot in _levels(hand):
        bp = jnp.asarray(hand.body_pos[bodies], dtype)
        rel = jnp.asarray(hand.body_mat[bodies], dtype)
        if prev is None:
            p, r = bp, rel
        else:
            pp, pr = prev[0][parent_slot], prev[1][parent_slot]
            p = pp + _matvec(pr, bp)
            r = _matmul(pr, rel)
        j = hand.body_joint[bodies]
        has = j >= 0
        anchor = jnp.asarray(np.where(has[:, None], hand.joint_pos[np.maximum(j, 0)], 0.0), dtype)
        axis = np.where(has[:, None], hand.joint_axis[np.maximum(j, 0)], 0.0)
        p_anchor = p + _matvec(r, anchor)
        axis_w = _matvec(r, jnp.asarray(axis, dtype))
        k = np.zeros((len(bodies), 3, 3))
        k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
        k = k - np.swapaxes(k, 1, 2)  # (n, 3, 3) cross-product matrices of the axes (0 without a joint)
        angle = q_ext[np.where(has, j, hand.n_joints)][:, None, None]
        rot = np.eye(3) + jnp.sin(angle) * k + (1 - jnp.cos(angle)) * (k @ k)  # Rodrigues, per body
        r = _matmul(r, rot.astype(dtype))
        p = p_anchor - _matvec(r, anchor)
        pos_l.append(p), mat_l.append(r), axis_l.append(axis_w), anchor_l.append(p_anchor), order.append(bodies)
        prev = (p, r)
    order = np.concatenate(order)
    slot = np.argsort(order)  # body b sits at row slot[b] of the level-stacked arrays
    pos, mat = jnp.concatenate(pos_l)[slot], jnp.concatenate(mat_l)[slot]
    body_of_joint = np.argsort(np.where(hand.body_joint >= 0, hand.body_joint, np.iinfo(np.int64).max))[: hand.n_joints]
    axes, anchors = jnp.concatenate(axis_l)[slot[body_of_joint]], jnp.concatenate(anchor_l)[slot[body_of_joint]]
    return pos, mat, axes, anchors


def _levels(hand: HandModel) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """The kinematic tree by depth: per level, its bodies (n,) and each one's parent's row in the level above."""
    parent = np.asarray(hand.body_parent)
    depth = np.zeros(len(parent), int)
    for b, pa in enumerate(parent):
        if pa >= b:
            raise ValueError(f"hand.body_parent[{b}]: {pa}; a parent must come before its children")
        depth[b] = 0 if pa < 0 else depth[pa] + 1
    levels, above = [], None
    for d in range(depth.max() + 1):
        bodies = np.flatnonzero(depth == d)
        slot = None if above is None else np.searchsorted(above, parent[bodies])
        levels.append((bodies, slot))
        above = bodies
    return levels


def _matvec(a: jax.Array, v: jax.Array) -> jax.Array:
    """(..., 3, 3) @ (..., 3)."""
    return small_einsum("...ij,...j->...i", a, v)


def _matmul(a: jax.Array, b: jax.Array) -> jax.Array:
    """(..., 3, 3) @ (..., 3, 3)."""
    return small_einsum("...ij,...jk->...ik", a, b)


def small_einsum(spec: str, a: jax.Array, b: jax.Array) -> jax.Array:
    """`jnp.einsum(spec, a, b)` for the IK's tiny contractions (3-vectors, 3x3 matrices, point Jacobians). On a
    GPU it is written as a broadcast product and a sum, which XLA fuses with its neighbours (a tiny matmul is a
    kernel launch of its own, and the IK runs hundreds of them per iteration); the CPU keeps the matmul (there
    the broadcast form is slower). Two operands; "..." stands for leading axes that broadcast as in numpy.
    Both forms must equal numpy's einsum (the reference); checked by
    `tests/test_kinematics.py::test_small_einsum_both_forms_match_numpy` (in the chain and the IK:
    `::test_gpu_form_of_the_contractions_gives_the_same_fk_and_ik`)."""
    return platform.by_platform(a, b, cpu=lambda a, b: jnp.einsum(spec, a, b),
                                default=lambda a, b: _broadcast_einsum(spec, a, b))


def _broadcast_einsum(spec: str, a: jax.Array, b: jax.Array) -> jax.Array:
    """`small_einsum`'s GPU form: both operands broadcast to the union of their axes, multiplied, summed."""
    ins, out = spec.replace("...", "").split("->")
    sa, sb = ins.split(",")
    letters = list(dict.fromkeys(sa + sb))
    lead = jnp.broadcast_shapes(a.shape[: a.ndim - len(sa)], b.shape[: b.ndim - len(sb)])
    n_lead = len(lead)

    def expand(x, sub):
        x = jnp.broadcast_to(x, lead + x.shape[x.ndim - len(sub):])
        present = [c for c in letters if c in sub]
        x = jnp.moveaxis(x, [n_lead + sub.index(c) for c in present], range(n_lead, n_lead + len(present)))
        shape = list(lead) + [x.shape[n_lead + present.index(c)] if c in sub else 1 for c in letters]
        return x.reshape(shape)

    prod = expand(a, sa) * expand(b, sb)
    kept = [c for c in letters if c in out]
    r = jnp.sum(prod, axis=tuple(n_lead + i for i, c in enumerate(letters) if c not in out))
    return jnp.moveaxis(r, [n_lead + kept.index(c) for c in out], range(n_lead, n_lead + len(out)))


def point_jacobian(hand: HandModel, axes: jax.Array, anchors: jax.Array, body: np.ndarray, points: jax.Array):
    """d(points)/dq (N, 3, J) of world points (N, 3) fixed to bodies (N,), from `chain`'s axes and anchors."""
    moves = hand.joint_moves_body[body].astype(points.dtype)  # (N, J) joint j moves body b
    jac = jnp.cross(axes[None], points[:, None, :] - anchors[None])  # (N, J, 3)
    return jnp.swapaxes(jac * moves[..., None], 1, 2)


def joint_twists(axes: jax.Array, anchors: jax.Array) -> jax.Array:
    """Each joint's unit twist (J, 6) in the world frame, (axis, anchor x axis), from `chain`'s axes and anchors:
    a point p on a body that joint j moves has velocity axis_j x p + (anchor_j x axis_j) per unit joint speed."""
    return jnp.concatenate([axes, jnp.cross(anchors, axes)], -1)


def direction_jacobian(hand: HandModel, twists: jax.Array, body: np.ndarray, points: jax.Array, dirs: jax.Array):
    """d(dirs . points)/dq (N, J), dirs (N, 3) held fixed, for world points (N, 3) fixed to bodies (N,): row n is
    `dirs[n] @ point_jacobian(...)[n]`, computed as the wrench (points x dirs, dirs) against each joint's twist
    (`joint_twists`, (J, 6)): an (N, 6) x (6, J) product instead of N x J cross products."""
    wrench = jnp.concatenate([jnp.cross(points, dirs), dirs], -1)  # (N, 6)
    moves = hand.joint_moves_body[body].astype(points.dtype)  # (N, J) joint j moves body b
    rows = sum(wrench[:, None, k] * twists[None, :, k] for k in range(6))  # the 6-term product written out: on
    # a CPU faster than a batched (N, 6) x (6, J) matmul (docs/performance.md), on a GPU one fused kernel
    return rows * moves


def points_on_bodies(pos: jax.Array, mat: jax.Array, body: np.ndarray, local: np.ndarray) -> jax.Array:
    """World positions (N, 3) of points given in their bodies' frames, from body poses (B, 3), (B, 3, 3)."""
    return pos[body] + _matvec(mat[body], jnp.asarray(local, pos.dtype))


def local_points(hand: HandModel, q: jax.Array, body: np.ndarray, local: np.ndarray) -> jax.Array:
    """World positions (N, 3) of points given in their bodies' frames: body (N,) indices, local (N, 3)."""
    pos, mat = body_poses(hand, q)
    return points_on_bodies(pos, mat, body, local)


def segments_on_links(hand: HandModel, pos: jax.Array, mat: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World centres (L, 3) and unit directions (L, 3) of the contact links' segments, from body poses."""
    centre = points_on_bodies(pos, mat, hand.link_body, hand.link_site)
    return centre, _matvec(mat[hand.link_body], jnp.asarray(hand.link_axis, pos.dtype))


def closest_on_segments(hand: HandModel, centre: jax.Array, axis: jax.Array, points: jax.Array) -> jax.Array:
    """For each contact link's segment (centre, axis: (L, 3)), its point (L, 3) closest to `points` (L, 3)."""
    half = hand.link_half.astype(centre.dtype)
    s = jnp.clip(jnp.sum((points - centre) * axis, -1), -half, half)
    return centre + s[:, None] * axis


def contact_segments(hand: HandModel, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World centres (L, 3) and unit directions (L, 3) of the contact links' segments."""
    return segments_on_links(hand, *body_poses(hand, q))


def closest_on_links(hand: HandModel, q: jax.Array, points: jax.Array) -> jax.Array:
    """For each contact link, the point (L, 3) of its contact segment closest to `points` (L, 3)."""
    return closest_on_segments(hand, *contact_segments(hand, q), points)


def closest_on_links_and_jacobians(hand: HandModel, q: jax.Array, points: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`closest_on_links` (L, 3) and the point Jacobians (L, 3, J) there, from one pass of the kinematic chain.
    The reference of `physics.native._links`, which must equal it; checked by
    `tests/test_native.py::test_native_chain_and_links_are_kinematics`."""
    pos, mat, axes, anchors = chain(hand, q)
    x = closest_on_segments(hand, *segments_on_links(hand, pos, mat), points)
    return x, point_jacobian(hand, axes, anchors, hand.link_body, x)


def sphere_centers(hand: HandModel, q: jax.Array) -> jax.Array:
    """World centres (S, 3) of the hand's collision spheres."""
    return local_points(hand, q, hand.sphere_body, hand.sphere_pos)
