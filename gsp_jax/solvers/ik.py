"""Collision-avoiding inverse kinematics of a grasp, in pure JAX.

Given the contact links that should touch the tool and where (`targets`), find joint angles by damped
Gauss-Newton (Levenberg-Marquardt) descent on a sum of squared residuals, from the model's fixed start
configuration and from fixed variations of it (`IKConfig.extra_starts`, keeping the lowest cost: from the start
alone the descent sometimes stops in a local minimum), for a fixed number of iterations (static shapes; `vmap`
runs every problem, and every start, in lock step; the result is a function of (grasp, tool pose) alone):

* active links: distance from the tool's contact point to the link's contact segment, minus the link radius
  (the link's surface passes through the contact point; with the collision terms below this puts a fingertip
  on a face along its normal, and lets a phalanx touch a face anywhere along its length),
* every hand sphere against the tool: penetration, and for spheres of inactive links a clearance margin
  (inactive links stay clear of the tool),
* every hand sphere against the table (z = 0), and the medial and distal capsules of different fingers against
  each other (self-collision, exact capsule-capsule distance),
* a small pull towards the start configuration (keeps the solution unique).

Joint limits are enforced by projection after every step. Why Gauss-Newton rather than plain gradient descent:
the residuals mix millimetre-scale targets with joint angles of very different lever arms; a 16x16 normal-
equation solve per iteration makes the step scale-free, reaching sub-millimetre error in a few tens of
iterations where plain gradient descent needs hundreds. The adaptive damping accepts only steps that lower the
cost, so the iteration is monotone.

Local minima. From the model's start alone the descent sometimes stops in a local minimum, seen as a *spike*
(`python -m experiments ik-spikes`: a collision-free IK more than 2 mm off while both neighbouring waypoints of the
same grasp are below 1 mm). Mostly a finger whose *medial* phalanx is the contact stops curled over the tool's edge:
its distal phalanx (an inactive link) sits on its clearance margin and a medial sphere on its contact slack, so
uncurling the finger (the way to the solution, which the neighbouring waypoints find) first raises the cost and LM
is stationary there; more rarely a fingertip stops on a tool edge. Starting the fingers less curled frees them: the
default extra starts, chosen on the training set's spike problems from a grid of 31 per-finger offsets, straighten the
middle and distal joints (pip -0.3, dip -0.4), the second also flexing the proximal one (mcp +0.3, pip -0.6). The
start is chosen by the cost *without* the pull towards the model's start: with it, a converged solution far from
the start can cost more than the local minimum near it (the pull weighs 3 um per mrad). Every finger shares one
start, so a grasp that needs one finger opened and another not is freed only if some start suits all its fingers
at once. Spike counts, cost and the candidates tried: docs/model.md ("IK: local minima, measured").
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.model import kinematics
from gsp_jax.core import platform
from gsp_jax.model.hand import HandModel


@dataclasses.dataclass(frozen=True)
class IKConfig:
    iterations: int = 60  # fixed Gauss-Newton iterations
    unroll: int = 1  # iterations per loop trip (`lax.scan`'s unroll): the same result, fewer loop trips on a GPU
    extra_starts: tuple = ((0.0, 0.0, -0.3, -0.4), (0.0, 0.3, -0.6, -0.4))  # more start configurations: per-finger
    # joint offsets (abd, mcp, pip, dip) from the model's start, the same for every finger; the solve runs from each
    # and keeps the lowest cost without the pull towards the start, so the result stays a function of (grasp, pose);
    # each start is one more descent. () runs the model's start alone (its spikes: docs/model.md)
    clearance: float = 0.004  # inactive links keep this far from the tool [m]
    contact_slack: float = 0.001  # active links may sink this far into the tool before the collision term acts [m]
    table_margin: float = 0.001  # every sphere keeps this far above the table [m]
    self_margin: float = 0.001  # extra gap between spheres of different fingers [m]
    w_collision: float = 3.0  # weight of the collision residuals relative to the target residuals
    w_regular: float = 3e-3  # weight [m/rad] of the pull towards the start configuration
    damping0: float = 1e-4  # initial Levenberg-Marquardt damping [m^2]
    damping_down: float = 0.3  # damping factor after an accepted step
    damping_up: float = 4.0  # damping factor after a rejected step
    collision_tol: float = 0.002  # penetration [m] beyond which the result counts as a collision
    lanes: bool | None = None  # an episode's table (`dp.realise_all`) solves its G x T problems in the batch-last
    # form (`ik_lanes`: the same solve, to float32 rounding; on a CPU faster to run and slower to compile than
    # `solve` vmapped, docs/performance.md): None on a CPU only, True everywhere, False never (`solve` vmapped).
    # True also for a lookahead root's few problems (`Surrogate.step_every`; None: vmapped there, as its longer
    # compile outweighs what a few dozen problems save, docs/performance.md; except online: `planners` L1-physics
    # on a CPU)
    lanes_chunk: int = 288  # the batch-last form solves its batch this many problems at a time (`lax.map` over
    # chunks, each chunk's iterations run to the end before the next starts): a chunk's arrays stay in the CPU's
    # caches, where the whole batch at once goes to memory every operation (docs/performance.md); the same
    # result, lane by lane


@struct.dataclass
class IKResult:
    """A solved grasp. Shapes for one problem (vmap adds leading axes)."""

    q: jax.Array  # (J,) joint angles [rad]
    points: jax.Array  # (L, 3) achieved contact point on each link's surface, nearest the target [m]
    link_error: jax.Array  # (L,) |link point - tool point| per link; 0 for inactive links [m]
    error: jax.Array  # () max link_error over active links (0 if none) [m]
    penetration: jax.Array  # () worst penetration: tool, table or self [m]
    collision: jax.Array  # () bool, penetration > collision_tol


def box_sdf(points: jax.Array, tool_pos: jax.Array, tool_mat: jax.Array, hand: HandModel) -> jax.Array:
    """Signed distance (N,) from world points (N, 3) to the tool's union of primitives (negative inside).

    Boxes, spheres, capsules and cylinders: exact outside the tool. Inside, it is minus the deepest penetration into
    any single primitive: exact wherever that primitive's nearest face is on the tool's surface, and otherwise (near
    where primitives meet) a shallower bound; the wrench model overlaps its boxes so that no point of the tool is
    shallow in every box. Ellipsoids: the scaled-sphere estimate (k0 - 1) x the shortest semi-axis (`round_sdf`)."""
    return box_sdf_and_grad(points, tool_pos, tool_mat, hand)[0]


def round_sdf(kind: str, size, x, y, z):
    """Signed distance and its gradient (dist, gx, gy, gz) of points (x, y, z) (arrays of any one shape, in the
    primitive's frame) to a round MuJoCo primitive of `size` (3,): "sphere" (radius), "capsule" (radius,
    half-length along z), "cylinder" (the same) or "ellipsoid" (semi-axes; an estimate: (k0 - 1) min(size) with
    k0 = |p / size|, exact for a sphere, gradient the normal of the scaled sphere)."""
    a, b, c = (float(v) for v in size)
    eps = 1e-12
    if kind in ("sphere", "capsule"):
        dz = z - jnp.clip(z, -b, b) if kind == "capsule" else z
        r = jnp.sqrt(x * x + y * y + dz * dz + eps)
        return r - a, x / r, y / r, dz / r
    if kind == "cylinder":
        rho = jnp.sqrt(x * x + y * y + eps)
        dr, dz = rho - a, jnp.abs(z) - b
        o_r, o_z = jnp.maximum(dr, 0.0), jnp.maximum(dz, 0.0)
        outside = jnp.sqrt(o_r * o_r + o_z * o_z + eps)
        side = dr >= dz  # inside: the nearer of the side and the caps
        w_r = jnp.where(outside > 1e-6, o_r / outside, side.astype(x.dtype))
        w_z = jnp.where(outside > 1e-6, o_z / outside, (~side).astype(x.dtype))
        return outside + jnp.minimum(jnp.maximum(dr, dz), 0.0), w_r * x / rho, w_r * y / rho, w_z * jnp.sign(z)
    if kind == "ellipsoid":
        k0 = jnp.sqrt((x / a) ** 2 + (y / b) ** 2 + (z / c) ** 2 + eps)
        nx, ny, nz = x / a**2, y / b**2, z / c**2
        n = jnp.sqrt(nx * nx + ny * ny + nz * nz + eps)
        return (k0 - 1.0) * min(a, b, c), nx / n, ny / n, nz / n
    raise ValueError(f"round_sdf: kind {kind!r} is not sphere, capsule, cylinder or ellipsoid")


def box_sdf_and_grad(points: jax.Array, tool_pos: jax.Array, tool_mat: jax.Array, hand: HandModel):
    """`box_sdf` (N,) and its gradient (N, 3) with respect to the world points, the latter in closed form (the
    IK evaluates it for every sphere every iteration; autodiff of the distance costs several times the distance).
    Where it is not unique it takes one primitive's (a point equidistant from two: the earlier box, boxes before
    round primitives) and, inside a box, the sum of the tied faces' normals (a point exactly equidistant from two
    faces)."""
    local = kinematics.small_einsum("nj,ji->ni", points - tool_pos, tool_mat)  # (N, 3) in the tool frame
    dt = points.dtype
    best = None
    if len(hand.tool_box_half):
        box_mat = jnp.asarray(hand.tool_box_mat, dt)  # (NB, 3, 3) box frames in the tool frame
        rel = kinematics.small_einsum("nbj,bji->nbi", local[:, None, :] - hand.tool_box_pos[None].astype(dt), box_mat)
        d = jnp.abs(rel) - hand.tool_box_half.astype(dt)  # (N, NB, 3)
        out = jnp.maximum(d, 0.0)
        outside = jnp.sqrt(jnp.sum(out**2, -1) + 1e-12)
        deepest = jnp.max(d, -1)
        dist = outside + jnp.minimum(deepest, 0.0)  # (N, NB)
        # d(dist)/d(rel): along the outward offset outside; inside, along the normal of the nearest face
        face = (d == deepest[..., None]) & (deepest[..., None] < 0.0)
        g_rel = jnp.sign(rel) * (out / outside[..., None] + face.astype(dt))  # (N, NB, 3)
        nearest = jnp.argmin(dist, -1)  # (N,)
        g_rel = jnp.take_along_axis(g_rel, nearest[:, None, None], 1)[:, 0]  # (N, 3)
        best = jnp.min(dist, -1), kinematics.small_einsum("nij,nj->ni", box_mat[nearest], g_rel)
    for kind, pos, mat, size in zip(hand.tool_round_type, hand.tool_round_pos, hand.tool_round_mat,
                                    hand.tool_round_size):
        rel = kinematics.small_einsum("nj,ji->ni", local - pos.astype(dt), jnp.asarray(mat, dt))
        dist, *g = round_sdf(kind, size, rel[:, 0], rel[:, 1], rel[:, 2])
        grad = kinematics.small_einsum("ij,nj->ni", jnp.asarray(mat, dt), jnp.stack(g, -1))
        if best is None:
            best = dist, grad
        else:
            closer = dist < best[0]
            best = jnp.where(closer, dist, best[0]), jnp.where(closer[:, None], grad, best[1])
    return best[0], kinematics.small_einsum("ij,nj->ni", tool_mat, best[1])


def segment_closest(p0, p1, q0, q1):
    """Parameters s, t in [0, 1] (N,) of the closest points of segments p0-p1 and q0-q1 (N, 3) (Ericson,
    Real-Time Collision Detection, 5.1.9); segments must have nonzero length."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e = jnp.sum(d1 * d1, -1), jnp.sum(d2 * d2, -1)
    b, c, f = jnp.sum(d1 * d2, -1), jnp.sum(d1 * r, -1), jnp.sum(d2 * r, -1)
    denom = a * e - b * b
    general = denom > 1e-6 * a * e  # else (nearly) parallel: start from s = 0
    s = jnp.where(general, jnp.clip((b * f - c * e) / jnp.where(general, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    s = jnp.where(t < 0, jnp.clip(-c / a, 0.0, 1.0), jnp.where(t > 1, jnp.clip((b - c) / a, 0.0, 1.0), s))
    return s, jnp.clip(t, 0.0, 1.0)


def _self_closest(hand: HandModel, pos, mat, dtype):
    """Closest points (P, 3), (P, 3) of the self-collision capsule pairs' axes, in the world frame."""
    ends = pos[hand.capsule_body][:, None] + kinematics.small_einsum(
        "cij,cej->cei", mat[hand.capsule_body], hand.capsule_ends.astype(dtype)
    )  # (C, 2, 3)
    i, k = hand.self_pairs[:, 0], hand.self_pairs[:, 1]
    s, t = segment_closest(ends[i, 0], ends[i, 1], ends[k, 0], ends[k, 1])
    pi = ends[i, 0] + s[:, None] * (ends[i, 1] - ends[i, 0])
    pk = ends[k, 0] + t[:, None] * (ends[k, 1] - ends[k, 0])
    return pi, pk


@struct.dataclass
class _Geometry:
    """Everything the IK measures at one configuration, from the body poses."""

    link_axis_pt: jax.Array  # (L, 3) point of each contact segment nearest its tool contact point
    link_offset: jax.Array  # (L, 3) tool contact point - link_axis_pt
    link_dist: jax.Array  # (L,) |link_offset|
    link_gap: jax.Array  # (L,) link surface to tool contact point, signed [m]
    spheres: jax.Array  # (S, 3) sphere centres
    tool_gap: jax.Array  # (S,) sphere surface to tool [m]
    tool_grad: jax.Array  # (S, 3) d(tool_gap)/d(centre)
    table_gap: jax.Array  # (S,) sphere surface to the table [m]
    self_pi: jax.Array  # (P, 3) closest points of the self-collision capsule pairs
    self_pk: jax.Array  # (P, 3)
    self_dist: jax.Array  # (P,) |self_pi - self_pk|
    self_gap: jax.Array  # (P,) capsule surfaces apart [m]


def _geometry(hand: HandModel, pos, mat, targets, tool_pos, tool_mat) -> _Geometry:
    dt = pos.dtype
    axis_pt = kinematics.closest_on_segments(hand, *kinematics.segments_on_links(hand, pos, mat), targets)
    d = targets - axis_pt
    dist = jnp.sqrt(jnp.sum(d**2, -1) + 1e-12)
    c = kinematics.points_on_bodies(pos, mat, hand.sphere_body, hand.sphere_pos)
    sr = hand.sphere_radius.astype(dt)
    sdf, sdf_grad = box_sdf_and_grad(c, tool_pos, tool_mat, hand)
    pi, pk = _self_closest(hand, pos, mat, dt)
    pd = jnp.sqrt(jnp.sum((pi - pk) ** 2, -1) + 1e-12)
    cr = hand.capsule_radius.astype(dt)
    return _Geometry(
        link_axis_pt=axis_pt,
        link_offset=d,
        link_dist=dist,
        link_gap=dist - hand.link_radius.astype(dt),
        spheres=c,
        tool_gap=sdf - sr,
        tool_grad=sdf_grad,
        table_gap=c[:, 2] - sr,
        self_pi=pi,
        self_pk=pk,
        self_dist=pd,
        self_gap=pd - cr[hand.self_pairs[:, 0]] - cr[hand.self_pairs[:, 1]],
    )


def _hinge(weight, margin, gap):
    """Residual weight * max(margin - gap, 0) (N,) and d(residual)/d(gap) (N,)."""
    on = margin - gap > 0
    return weight * jnp.where(on, margin - gap, 0.0), jnp.where(on, -weight, 0.0)


def residuals_and_jacobian(hand: HandModel, cfg: IKConfig, q, active, targets, tool_pos, tool_mat):
    """The IK residual vector (R,) and its Jacobian (R, J), the latter in closed form from the chain's joint
    axes: every row is d(residual)/d(gap) times a contact normal or surface gradient at a point, and that
    direction at that point is a wrench against the joints' twists (`kinematics.direction_jacobian`; all rows
    in one product). Rows: link gaps (L), sphere-tool (S), sphere-table (S), self capsule pairs (P),
    regularisation (J).
    The reference of `ik_lanes._Problem.evaluate`, whose normal equations must equal those of these rows; checked
    by `tests/test_ik_lanes.py::test_normal_equations_match_the_reference`."""
    pos, mat, axes, anchors = kinematics.chain(hand, q)
    geo = _geometry(hand, pos, mat, targets, tool_pos, tool_mat)
    # contact links: distance of the tool point to the link's segment, minus the radius
    r_link = geo.link_gap * active
    unit_offset = geo.link_offset / geo.link_dist[:, None]  # d(gap)/d(segment point) = -unit_offset
    # spheres against tool and table
    sphere_active = jnp.where(hand.sphere_link >= 0, active[jnp.maximum(hand.sphere_link, 0)], False)
    margin = jnp.where(sphere_active, -cfg.contact_slack, cfg.clearance)
    r_tool, s_tool = _hinge(cfg.w_collision, margin, geo.tool_gap)
    r_table, s_table = _hinge(cfg.w_collision, cfg.table_margin, geo.table_gap)
    up = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], q.dtype), geo.spheres.shape)
    # capsule pairs: the distance's gradient moves the two closest points with their bodies (envelope theorem)
    i, k = hand.self_pairs[:, 0], hand.self_pairs[:, 1]
    unit = (geo.self_pi - geo.self_pk) / geo.self_dist[:, None]
    r_self, s_self = _hinge(cfg.w_collision, cfg.self_margin, geo.self_gap)
    rows = kinematics.direction_jacobian(
        hand,
        kinematics.joint_twists(axes, anchors),
        np.concatenate([hand.link_body, hand.sphere_body, hand.sphere_body, hand.capsule_body[i],
                        hand.capsule_body[k]]),
        jnp.concatenate([geo.link_axis_pt, geo.spheres, geo.spheres, geo.self_pi, geo.self_pk]),
        jnp.concatenate([unit_offset, geo.tool_grad, up, unit, -unit]),
    ) * jnp.concatenate([-active.astype(q.dtype), s_tool, s_table, s_self, s_self])[:, None]
    n_single, n_pairs = hand.n_links + 2 * len(hand.sphere_body), len(i)
    n = hand.n_joints
    r_reg = cfg.w_regular * (q - hand.q_start.astype(q.dtype))
    j_reg = cfg.w_regular * jnp.eye(n, dtype=q.dtype)
    return (
        jnp.concatenate([r_link, r_tool, r_table, r_self, r_reg]),
        jnp.concatenate([rows[:n_single], rows[n_single:n_single + n_pairs] + rows[n_single + n_pairs:], j_reg]),
    )


def solve(
    hand: HandModel,
    active: jax.Array,
    targets: jax.Array,
    tool_pos: jax.Array,
    tool_mat: jax.Array,
    cfg: IKConfig = IKConfig(),
) -> IKResult:
    """IK for one grasp: active (L,) bool, targets (L, 3) contact points on the tool [m], tool pose (3,), (3, 3).

    Differentiable (the iterations are a `lax.scan`); `vmap` it over grasps, poses and episodes. Matmuls run
    in full float32 (no TF32 on GPUs: sub-millimetre targets need it).
    The reference of `ik_lanes.solve` (the same solve, batch last), which must equal it; checked by
    `tests/test_ik_lanes.py::test_solve_matches_vmapped_solve`.
    """
    with jax.default_matmul_precision("highest"):
        return _solve(hand, active, targets, tool_pos, tool_mat, cfg)


def _solve(hand, active, targets, tool_pos, tool_mat, cfg) -> IKResult:
    dtype = targets.dtype
    active = active.astype(bool)
    lo, hi = jnp.asarray(hand.joint_range[:, 0], dtype), jnp.asarray(hand.joint_range[:, 1], dtype)
    n = hand.n_joints

    def evaluate(q):
        """The Gauss-Newton normal equations at q: J^T J (J, J), J^T r (J,), the cost |r|^2 and the cost without
        the pull towards the start (the last J rows): what the iteration carries instead of the (R, J) Jacobian."""
        r, jac = residuals_and_jacobian(hand, cfg, q, active, targets, tool_pos, tool_mat)
        return *_normal_equations(jac, r), jnp.sum(r**2), jnp.sum(r[:-n] ** 2)

    def iteration(carry, i):
        q, normal, lam = carry
        jtj, jtr = normal[:2]
        # iteration 0 evaluates the start (a zero step, always accepted, the damping kept): the program holds one
        # copy of the evaluation, which is most of its compile time
        step = jnp.where(i > 0, _damped_step(jtj, jtr, lam), 0.0)
        q_new = jnp.clip(q + step, lo, hi)
        normal_new = evaluate(q_new)
        better = (normal_new[2] < normal[2]) | (i == 0)
        keep = lambda new, old: jnp.where(better, new, old)  # noqa: E731
        lam = jnp.where(i > 0, jnp.clip(jnp.where(better, lam * cfg.damping_down, lam * cfg.damping_up), 1e-9, 1e2),
                        lam)
        return (keep(q_new, q), jax.tree.map(keep, normal_new, normal), lam), None

    def run(q0):
        blank = (jnp.zeros((n, n), dtype), jnp.zeros(n, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype))
        init = (q0, blank, jnp.asarray(cfg.damping0, dtype))
        (q, normal, _), _ = jax.lax.scan(iteration, init, jnp.arange(cfg.iterations + 1), unroll=cfg.unroll)
        return q, normal[3]  # the cost without the pull towards the start

    starts = jnp.asarray(start_configurations(hand, cfg), dtype)
    if len(starts) == 1:  # the model's start alone (the default): one descent
        q, _ = run(starts[0])
    else:
        qs, cost = jax.vmap(run)(starts)
        # the lowest cost without the pull: a converged solution far from the start can cost more *with* the pull
        # than a local minimum near it (the pull is 3 um per mrad); ties break towards the earlier start
        q = qs[jnp.argmin(cost)]

    geo = _geometry(hand, *kinematics.body_poses(hand, q), targets, tool_pos, tool_mat)
    link_error = jnp.where(active, jnp.abs(geo.link_gap), 0.0)
    radius = hand.link_radius.astype(dtype)
    surface = geo.link_axis_pt + geo.link_offset * (radius / geo.link_dist)[:, None]  # link point nearest target
    penetration = -jnp.min(jnp.concatenate([geo.tool_gap, geo.table_gap, geo.self_gap]))
    return IKResult(
        q=q,
        points=surface,
        link_error=link_error,
        error=jnp.max(link_error),
        penetration=penetration,
        collision=penetration > cfg.collision_tol,
    )


def collisions(hand: HandModel, q, tool_pos, tool_mat, tol: float = 0.0) -> list[str]:
    """The collisions of the hand at joint angles q (J,) [rad] with the tool at (3,), (3, 3), in words, deepest
    first: each body into the tool or the table, each pair of fingers' capsules overlapping, with its depth in mm,
    where deeper than `tol` [m] (the IK's `collision_tol` counts a collision; 0: every overlap). What
    `IKResult.penetration` measures, per body (one line each: its deepest sphere)."""
    pos, mat = kinematics.body_poses(hand, jnp.asarray(q, jnp.float32))
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    geo = _geometry(hand, pos, mat, jnp.zeros((hand.n_links, 3), jnp.float32), f32(tool_pos), f32(tool_mat))
    depth = {}
    for kind, gap in (("the tool", geo.tool_gap), ("the table", geo.table_gap)):
        d = -np.asarray(gap)
        for s in np.flatnonzero(d > tol):
            key = (hand.body_names[hand.sphere_body[s]], kind)
            depth[key] = max(depth.get(key, 0.0), float(d[s]))
    d = -np.asarray(geo.self_gap)
    for p in np.flatnonzero(d > tol):
        i, k = hand.self_pairs[p]
        key = (hand.body_names[hand.capsule_body[i]], hand.body_names[hand.capsule_body[k]])
        depth[key] = max(depth.get(key, 0.0), float(d[p]))
    return [f"{a} {'into' if b.startswith('the ') else 'and'} {b}{'' if b.startswith('the ') else ' overlap'} "
            f"{d * 1e3:.1f} mm" for (a, b), d in sorted(depth.items(), key=lambda kv: -kv[1])]


def _damped_step(jtj: jax.Array, jtr: jax.Array, lam: jax.Array) -> jax.Array:
    """The Levenberg-Marquardt step (J,): solves (J^T J + lam I) step = -J^T r, positive definite for lam > 0. On a
    CPU by LAPACK's Cholesky; on a GPU by Gauss-Jordan elimination written out for the static size
    (`_gauss_jordan_solve`): fused kernels instead of the solver library's seven calls, and small enough to compile
    fast (against the Cholesky forms tried: docs/lookahead.md). Both forms, and the batch-last copy
    `ik_lanes._cholesky_solve`, must equal numpy's float64 solve (the reference); checked by
    `tests/test_ik.py::test_damped_step_solves_the_normal_equations_like_float64_lapack` and
    `tests/test_ik_lanes.py::test_cholesky_solve_matches_float64`."""
    a = jtj + lam * jnp.eye(jtj.shape[-1], dtype=jtj.dtype)
    return platform.by_platform(
        a, -jtr, cpu=lambda a, b: jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(a), True), b),
        default=_gauss_jordan_solve,
    )


def _gauss_jordan_solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """x (n,) with a x = b for a positive definite a (n, n): Gauss-Jordan elimination of the augmented matrix [a | b]
    without pivoting (stable for positive definite matrices: every pivot is a Schur complement's diagonal, > 0),
    unrolled over the static n: n rank-one updates of an (n, n + 1) matrix, elementwise operations that XLA fuses."""
    n = a.shape[-1]
    m = jnp.concatenate([a, b[:, None]], 1)
    row_index = jnp.arange(n)[:, None]
    for j in range(n):
        pivot_row = m[j] / m[j, j]
        m = jnp.where(row_index == j, pivot_row[None, :], m - m[:, j:j + 1] * pivot_row[None, :])
    return m[:, n]


def _normal_equations(jac: jax.Array, r: jax.Array) -> tuple[jax.Array, jax.Array]:
    """J^T J (J, J) and J^T r (J,) from the Jacobian (R, J) and residuals (R,). On a CPU as broadcast products and
    sums, on a GPU as matmuls: each the faster form on its platform for these sizes (docs/performance.md). The two
    forms must be equal (the matmuls the reference); checked by `tests/test_ik.py::test_normal_equations_both_forms`."""
    return platform.by_platform(
        jac, r,
        cpu=lambda jac, r: (jnp.sum(jac[:, :, None] * jac[:, None, :], 0), jnp.sum(jac * r[:, None], 0)),
        default=lambda jac, r: (jac.T @ jac, jac.T @ r),
    )


def start_configurations(hand: HandModel, cfg: IKConfig) -> np.ndarray:
    """(1 + len(cfg.extra_starts), J) joint configurations the solve starts from: the model's start, then each
    extra start's per-finger offsets added to every finger (the model's joints come finger by finger; an offset of
    n values goes to each finger's last n joints, so a finger with more joints keeps its first ones and one with
    fewer takes the offset's last values; clipped to the joint limits)."""
    q0 = np.asarray(hand.q_start, np.float64)
    finger = np.asarray(hand.joint_finger)
    rank = np.array([np.sum(finger[:j] == finger[j]) for j in range(hand.n_joints)])  # joint's place in its finger
    from_end = np.bincount(finger)[finger] - 1 - rank  # 0: the finger's last joint
    starts = [q0]
    for offset in cfg.extra_starts:
        offset = np.asarray(offset, np.float64)
        if offset.ndim != 1 or offset.size == 0 or not np.all(np.isfinite(offset)):
            raise ValueError(f"IKConfig.extra_starts: each offset needs finite values for a finger's last joints, got "
                             f"{offset.tolist()}")
        index = offset.size - 1 - from_end
        starts.append(np.clip(q0 + np.where(index >= 0, offset[np.maximum(index, 0)], 0.0), *hand.joint_range.T))
    return np.stack(starts)


def grasp_targets(hand: HandModel, options: jax.Array, tool_pos: jax.Array, tool_mat: jax.Array):
    """A grasp's contacts in the world frame: options (L,) int -> active (L,) bool, contact points on the tool
    (L, 3) and inward contact normals (L, 3)."""
    li = np.arange(hand.n_links)
    p_local = jnp.asarray(hand.option_pos, tool_pos.dtype)[li, options]
    n_local = jnp.asarray(hand.option_normal, tool_pos.dtype)[li, options]
    return options > 0, tool_pos + p_local @ tool_mat.T, n_local @ tool_mat.T
