"""Forward kinematics of the hand in pure JAX, built from the model file's kinematic tree.

All functions take joint angles `q` of shape (J,) and are differentiable; `jax.vmap` them for batches.
They agree with MuJoCo's own `mj_kinematics` (tests/test_kinematics.py).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.hand import HandModel


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


def _axis_angle(axis: np.ndarray, angle: jax.Array) -> jax.Array:
    """Rotation about a constant unit axis (3,) by `angle` (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + jnp.sin(angle) * k + (1 - jnp.cos(angle)) * (k @ k)


def body_poses(hand: HandModel, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World poses of the hand's bodies: positions (B, 3) and rotation matrices (B, 3, 3)."""
    pos, mat, _, _ = chain(hand, q)
    return pos, mat


def chain(hand: HandModel, q: jax.Array):
    """Body poses (B, 3), (B, 3, 3) plus every joint's world axis (J, 3) and anchor (J, 3)."""
    dtype = q.dtype
    rel_mat = hand.body_mat
    pos, mat = [], []
    axes, anchors = [None] * hand.n_joints, [None] * hand.n_joints
    for b, parent in enumerate(hand.body_parent):  # static tree: unrolled at trace time
        if parent < 0:
            p, r = jnp.asarray(hand.body_pos[b], dtype), jnp.asarray(rel_mat[b], dtype)
        else:
            p = pos[parent] + mat[parent] @ hand.body_pos[b].astype(dtype)
            r = mat[parent] @ rel_mat[b].astype(dtype)
        j = hand.body_joint[b]
        if j >= 0:
            anchor = hand.joint_pos[j].astype(dtype)
            p_anchor = p + r @ anchor
            axes[j], anchors[j] = r @ hand.joint_axis[j].astype(dtype), p_anchor
            r = r @ _axis_angle(hand.joint_axis[j], q[j]).astype(dtype)
            p = p_anchor - r @ anchor
        pos.append(p)
        mat.append(r)
    return jnp.stack(pos), jnp.stack(mat), jnp.stack(axes), jnp.stack(anchors)


def point_jacobian(hand: HandModel, axes: jax.Array, anchors: jax.Array, body: np.ndarray, points: jax.Array):
    """d(points)/dq (N, 3, J) of world points (N, 3) fixed to bodies (N,), from `chain`'s axes and anchors."""
    moves = hand.joint_moves_body[body].astype(points.dtype)  # (N, J) joint j moves body b
    jac = jnp.cross(axes[None], points[:, None, :] - anchors[None])  # (N, J, 3)
    return jnp.swapaxes(jac * moves[..., None], 1, 2)


def points_on_bodies(pos: jax.Array, mat: jax.Array, body: np.ndarray, local: np.ndarray) -> jax.Array:
    """World positions (N, 3) of points given in their bodies' frames, from body poses (B, 3), (B, 3, 3)."""
    return pos[body] + jnp.einsum("nij,nj->ni", mat[body], local.astype(pos.dtype))


def local_points(hand: HandModel, q: jax.Array, body: np.ndarray, local: np.ndarray) -> jax.Array:
    """World positions (N, 3) of points given in their bodies' frames: body (N,) indices, local (N, 3)."""
    pos, mat = body_poses(hand, q)
    return points_on_bodies(pos, mat, body, local)


def segments_on_links(hand: HandModel, pos: jax.Array, mat: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World centres (L, 3) and unit directions (L, 3) of the contact links' segments, from body poses."""
    centre = points_on_bodies(pos, mat, hand.link_body, hand.link_site)
    return centre, jnp.einsum("lij,lj->li", mat[hand.link_body], hand.link_axis.astype(pos.dtype))


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


def sphere_centers(hand: HandModel, q: jax.Array) -> jax.Array:
    """World centres (S, 3) of the hand's collision spheres."""
    return local_points(hand, q, hand.sphere_body, hand.sphere_pos)
