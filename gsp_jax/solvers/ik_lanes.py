"""`ik.solve` for a whole batch of problems at once, with the batch as the vector lane: the CPU form of the IK.

    res = ik_lanes.solve(hand, active, targets, tool_pos, tool_mat, cfg)   # leading axes: the batch

The same Levenberg-Marquardt descent, residuals, starts and result as `ik.solve` (its docstring says what they
are), written for arrays whose *last* axis is the batch: a joint angle is an (N,) vector, a rotation a (3, 3, N)
array, and every 3-vector and 3x3 product is written out component by component. `vmap`ping the one-problem form
puts the batch first, so each array's fastest-varying axis is a 3-vector or a handful of spheres: XLA's CPU code
then vectorises little and copies between layouts. Here every operation is an elementwise operation over long,
contiguous batch vectors, which the CPU runs in full SIMD width.

Besides the layout, the form uses the Jacobian's structure. Every hand point moves with the joints of one finger
only (the model's joints that move a body form blocks, one per finger; a self-collision pair spans two), so each
residual row is computed on its finger's joints alone and J^T J is assembled from per-finger blocks (and the
cross blocks of the finger pairs that self-collision rows couple) instead of summing R outer products of length J.
The damped step is an unrolled Cholesky factorisation over the batch.

Two things make XLA's CPU code fast here. Values that several operations read (the new cost, each level of the
kinematic chain, the per-point distances and scales, each Jacobian row) sit behind `jax.lax.optimization_barrier`:
XLA's loop fusion would otherwise recompute them inside every consumer (the cost inside each accept/reject select,
the chain inside every point). And the batch is solved in chunks (`IKConfig.lanes_chunk` problems) whose arrays
stay in the caches. Neither changes the arithmetic.

Must equal `ik.solve` (its reference) to float32 rounding; checked by
`tests/test_ik_lanes.py::test_solve_matches_vmapped_solve` (the normal equations:
`::test_normal_equations_match_the_reference`; a DP table built either way: `::test_table_is_the_same_either_way`),
within the tolerances of two float32 computations of the IK (tests/tolerances.py: the Levenberg-Marquardt
accept/reject test can take the other branch on a rounding tie, as between two CPUs). The table of an episode
(`dp.realise_all`) uses it on a CPU; `ik.solve` stays the form for one problem, for `vmap`, for GPUs and for
gradients (this form is not meant to be differentiated).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from flax import struct

from gsp_jax.solvers import ik
from gsp_jax.model import kinematics
from gsp_jax.model.hand import HandModel


Vec = tuple  # three (n, N) arrays (or constants (n, 1)): the x, y and z components of n points over the batch N


@functools.lru_cache(maxsize=8)
def _blocks(hand: HandModel):
    """The joints in blocks (one per finger: joints that move a common body share a block), each a contiguous
    range of joint indices, and the block of each body (-1: a body no joint moves). Raises if the hand's joints do
    not come block by block."""
    moves = np.asarray(hand.joint_moves_body) > 0  # (B, J)
    n_j = hand.n_joints
    group = np.arange(n_j)
    for row in moves:  # merge the joints of each body's chain (union by smallest index, to a fixed point)
        js = np.flatnonzero(row)
        if len(js):
            group[js] = group[js].min()
    for _ in range(n_j):
        group = group[group]
    blocks = [np.flatnonzero(group == g) for g in dict.fromkeys(group.tolist())]
    if not all(np.array_equal(b, np.arange(b[0], b[0] + len(b))) for b in blocks):
        raise ValueError("ik_lanes: the hand's joints must come finger by finger (contiguous blocks)")
    block_of_joint = np.zeros(n_j, int)
    for k, b in enumerate(blocks):
        block_of_joint[b] = k
    body_block = np.array([block_of_joint[np.flatnonzero(r)[0]] if r.any() else -1 for r in moves])
    return tuple(blocks), body_block


def _c(x, dtype=jnp.float32):
    """A constant (n,) as an (n, 1) array that broadcasts against (n, N)."""
    return jnp.asarray(np.asarray(x, np.float64)[:, None], dtype)


def _rot(m: list, v: Vec) -> Vec:
    """Rotation (3 x 3 nested lists of (n, N) arrays) times vectors."""
    return tuple(m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2] for i in range(3))


def _add(a: Vec, b: Vec) -> Vec:
    return tuple(x + y for x, y in zip(a, b))


def _sub(a: Vec, b: Vec) -> Vec:
    return tuple(x - y for x, y in zip(a, b))


def _scale(a: Vec, s) -> Vec:
    return tuple(x * s for x in a)


def _dot0(x, y):
    """sum_n x[n] * y[n] over the leading (static, short) axis, as a chain of elementwise products and adds read
    straight from x and y (no product array is stored)."""
    out = x[0] * y[0]
    for i in range(1, x.shape[0]):
        out = out + x[i] * y[i]
    return out


def _dot(a: Vec, b: Vec):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _take(a: Vec, index) -> Vec:
    return tuple(_rows(x, index) for x in a)


def _rows(x: jax.Array, index: np.ndarray) -> jax.Array:
    """x[index] for a static index array: a slice where the index is a strided range, one row (broadcasting)
    where it repeats one value, a gather (slow on a CPU) only otherwise."""
    index = np.asarray(index)
    if len(index) > 1 and np.all(index == index[0]):
        return x[int(index[0]):int(index[0]) + 1]
    step = int(index[1] - index[0]) if len(index) > 1 else 1
    if len(index) and step > 0 and np.array_equal(index, index[0] + step * np.arange(len(index))):
        return x[int(index[0]):int(index[-1]) + 1:step]
    return x[index]


def _const_vec(x: np.ndarray, dtype) -> Vec:
    """(n, 3) constants -> a Vec of (n, 1) arrays."""
    return tuple(_c(x[:, i], dtype) for i in range(3))


@struct.dataclass
class Chain:
    """Body poses and joint frames over a batch, one entry per body or joint: each a Vec of (N,) arrays (or of
    constants, for a body no joint moves), rotations as 3 x 3 nested lists."""

    pos: list  # (B) body positions
    mat: list  # (B) body rotation matrices' entries
    axis: list  # (J) joint axes, world frame
    anchor: list  # (J) joint anchors, world frame
    n: int = struct.field(pytree_node=False, default=1)  # the batch size N


def chain(hand: HandModel, q: jax.Array) -> Chain:
    """`kinematics.chain` over a batch: q (J, N) -> `Chain` (the tree walked level by level, all bodies of a level
    at once, as there). Must equal `kinematics.chain` (its reference); checked by
    `tests/test_kinematics.py::test_batch_last_chain_equals_chain`."""
    dtype = q.dtype
    n_b = len(hand.body_parent)
    pos, mat, axes, anchors = [None] * n_b, [None] * n_b, [None] * hand.n_joints, [None] * hand.n_joints
    prev = None
    for bodies, parent_slot in kinematics._levels(hand):
        bp = _const_vec(hand.body_pos[bodies], dtype)
        rel = hand.body_mat[bodies]
        if prev is None:
            p = bp
            r = [[_c(rel[:, i, k], dtype) for k in range(3)] for i in range(3)]
        else:
            pp, pr = _take(prev[0], parent_slot), [[_rows(x, parent_slot) for x in row] for row in prev[1]]
            p = _add(pp, _rot(pr, bp))
            r = [[sum(pr[i][j] * _c(rel[:, j, k], dtype) for j in range(3)) for k in range(3)] for i in range(3)]
        j = hand.body_joint[bodies]
        has = j >= 0
        anchor = _const_vec(np.where(has[:, None], hand.joint_pos[np.maximum(j, 0)], 0.0), dtype)
        axis = np.where(has[:, None], hand.joint_axis[np.maximum(j, 0)], 0.0)
        p_anchor = _add(p, _rot(r, anchor))
        axis_w = _rot(r, _const_vec(axis, dtype))
        if has.any():
            k = np.zeros((len(bodies), 3, 3))
            k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
            k = k - np.swapaxes(k, 1, 2)
            k2 = k @ k
            angle = jnp.where(_c(has, bool), _rows(q, np.maximum(j, 0)), 0.0)  # (n, N)
            sin, vers = jax.lax.optimization_barrier((jnp.sin(angle), 1 - jnp.cos(angle)))  # once, not per entry
            rot = [[float(i == m) + sin * _c(k[:, i, m], dtype) + vers * _c(k2[:, i, m], dtype) for m in range(3)]
                   for i in range(3)]  # Rodrigues, per body
            r = [[sum(r[i][j] * rot[j][m] for j in range(3)) for m in range(3)] for i in range(3)]
            p = _sub(p_anchor, _rot(r, anchor))
        # each level's poses computed once (XLA would otherwise recompute the chain above inside every consumer)
        p, r, p_anchor, axis_w = jax.lax.optimization_barrier((p, r, p_anchor, axis_w))
        for row, b in enumerate(bodies):
            pos[b] = tuple(x[row] for x in p)
            mat[b] = [[x[row] for x in line] for line in r]
            if has[row]:
                axes[j[row]], anchors[j[row]] = tuple(x[row] for x in axis_w), tuple(x[row] for x in p_anchor)
        prev = (p, r)
    return Chain(pos=pos, mat=mat, axis=axes, anchor=anchors, n=q.shape[-1])


def _runs(index: np.ndarray):
    """Runs of equal consecutive values: [(start, stop), ...]."""
    edges = np.flatnonzero(np.diff(index)) + 1
    bounds = np.concatenate([[0], edges, [len(index)]])
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))


def _points(ch: Chain, body: np.ndarray, local: np.ndarray, dtype, rotate_only: bool = False) -> Vec:
    """World points (n, N) of bodies `body` (n,) at body-frame offsets (n, 3) (`rotate_only`: world directions
    of body-frame directions), computed body by body (a broadcast of the body's pose, no gather), concatenated."""
    parts = [[], [], []]
    for start, stop in _runs(body):
        b, loc = body[start], local[start:stop]
        for i in range(3):
            x = sum(ch.mat[b][i][j] * _c(loc[:, j], dtype) for j in range(3))
            x = x if rotate_only else ch.pos[b][i] + x
            parts[i].append(jnp.broadcast_to(x, (stop - start, ch.n)))
    return tuple(jnp.concatenate(p) if len(p) > 1 else p[0] for p in parts)


def _slice(members: np.ndarray):
    """A static index array as a slice where it is a contiguous range (a gather otherwise)."""
    if len(members) and np.array_equal(members, np.arange(members[0], members[0] + len(members))):
        return slice(int(members[0]), int(members[0]) + len(members))
    return members


def _segment_closest(p0: Vec, p1: Vec, q0: Vec, q1: Vec):
    """`ik.segment_closest` over a batch: parameters s, t (n, N). Must equal it (its reference); checked within
    `_Problem.evaluate` by `tests/test_ik_lanes.py::test_normal_equations_match_the_reference`."""
    d1, d2, r = _sub(p1, p0), _sub(q1, q0), _sub(p0, q0)
    a, e = _dot(d1, d1), _dot(d2, d2)
    b, c, f = _dot(d1, d2), _dot(d1, r), _dot(d2, r)
    denom = a * e - b * b
    general = denom > 1e-6 * a * e
    s = jnp.where(general, jnp.clip((b * f - c * e) / jnp.where(general, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    s = jnp.where(t < 0, jnp.clip(-c / a, 0.0, 1.0), jnp.where(t > 1, jnp.clip((b - c) / a, 0.0, 1.0), s))
    return s, jnp.clip(t, 0.0, 1.0)


def _frame(tool_pos, tool_mat, mat: np.ndarray, pos: np.ndarray):
    """A primitive's axes in the world (3 x 3 nested (1, N) arrays, axes as columns) and centre (Vec (1, N))."""
    rot = [[sum(tool_mat[i, j] * float(mat[j, k]) for j in range(3))[None] for k in range(3)] for i in range(3)]
    centre = tuple((tool_pos[i] + sum(tool_mat[i, j] * float(pos[j]) for j in range(3)))[None] for i in range(3))
    return rot, centre


def _box_frames(hand: HandModel, tool_pos, tool_mat):
    """Per tool box, then per round primitive: its world frame (`_frame`)."""
    return ([_frame(tool_pos, tool_mat, m, p) for m, p in zip(hand.tool_box_mat, hand.tool_box_pos)]
            + [_frame(tool_pos, tool_mat, m, p) for m, p in zip(hand.tool_round_mat, hand.tool_round_pos)])


def _box_sdf_and_grad(points: Vec, frames, hand: HandModel):
    """`ik.box_sdf_and_grad` over a batch: distance (n, N) from points to the union of the tool's primitives, and
    its gradient (Vec; the nearest primitive's, ties to the earlier one, as there). Must equal it (its reference);
    checked within `_Problem.evaluate` by `tests/test_ik_lanes.py::test_normal_equations_match_the_reference`."""
    dtype = points[0].dtype
    best = None
    shapes = [("box", h) for h in hand.tool_box_half] + list(zip(hand.tool_round_type, hand.tool_round_size))
    for (rot, centre), (kind, h) in zip(frames, shapes):
        dx = _sub(points, centre)
        rel = [dx[0] * rot[0][i] + dx[1] * rot[1][i] + dx[2] * rot[2][i] for i in range(3)]
        if kind == "box":
            d = [jnp.abs(rel[i]) - float(h[i]) for i in range(3)]
            o = [jnp.maximum(di, 0.0) for di in d]
            outside = jnp.sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2] + 1e-12)
            deepest = jnp.maximum(jnp.maximum(d[0], d[1]), d[2])
            dist = outside + jnp.minimum(deepest, 0.0)
            inside = deepest < 0.0
            g = [jnp.sign(rel[i]) * (o[i] / outside + ((d[i] == deepest) & inside).astype(dtype)) for i in range(3)]
        else:
            dist, *g = ik.round_sdf(kind, h, *rel)
        grad = tuple(g[0] * rot[k][0] + g[1] * rot[k][1] + g[2] * rot[k][2] for k in range(3))
        if best is None:
            best = (dist, grad)
        else:
            closer = dist < best[0]
            best = (jnp.where(closer, dist, best[0]), tuple(jnp.where(closer, x, y) for x, y in zip(grad, best[1])))
    return best


class _Problem:
    """One batch of IK problems (the batch last), with what stays fixed over the iterations."""

    def __init__(self, hand: HandModel, cfg: ik.IKConfig, active, targets, tool_pos, tool_mat):
        self.hand, self.cfg = hand, cfg
        self.dtype = dtype = targets.dtype
        self.active = active  # (L, N) bool
        self.targets = tuple(targets[:, i] for i in range(3))  # Vec (L, N)
        self.frames = _box_frames(hand, tool_pos, tool_mat)
        sphere_active = jnp.where(_c(hand.sphere_link >= 0, bool), active[np.maximum(hand.sphere_link, 0)], False)
        self.margin = jnp.where(sphere_active, -cfg.contact_slack, cfg.clearance).astype(dtype)  # (S, N)
        self.blocks, body_block = _blocks(hand)
        # the self-collision pairs in the order of their two blocks, so that each pair of blocks is a slice
        i, k = hand.self_pairs[:, 0], hand.self_pairs[:, 1]
        pair_blocks = np.stack([body_block[hand.capsule_body[i]], body_block[hand.capsule_body[k]]], 1)
        self.pair_order = np.lexsort((pair_blocks[:, 1], pair_blocks[:, 0]))
        self.pair_blocks = pair_blocks[self.pair_order]
        # the single rows' groups: each block's members of the links and of the spheres
        self.link_members = [np.flatnonzero(body_block[hand.link_body] == b) for b in range(len(self.blocks))]
        self.sphere_members = [np.flatnonzero(body_block[hand.sphere_body] == b) for b in range(len(self.blocks))]

    def geometry(self, ch: Chain) -> dict:
        """Gaps, and the points and directions of the Jacobian's rows, at one configuration."""
        hand, dtype = self.hand, self.dtype
        centre = _points(ch, hand.link_body, hand.link_site, dtype)
        axis = _points(ch, hand.link_body, hand.link_axis, dtype, rotate_only=True)
        half = _c(hand.link_half, dtype)
        s = jnp.clip(_dot(_sub(self.targets, centre), axis), -half, half)
        axis_pt = _add(centre, _scale(axis, s))
        offset = _sub(self.targets, axis_pt)
        dist = jnp.sqrt(_dot(offset, offset) + 1e-12)
        spheres = _points(ch, hand.sphere_body, hand.sphere_pos, dtype)
        sdf, sdf_grad = _box_sdf_and_grad(spheres, self.frames, hand)
        radius = _c(hand.sphere_radius, dtype)
        order = self.pair_order
        i, k = hand.self_pairs[order, 0], hand.self_pairs[order, 1]
        ends = [[_points(ch, hand.capsule_body[c], hand.capsule_ends[c, e], dtype) for e in range(2)]
                for c in (i, k)]
        (a0, a1), (b0, b1) = ends
        sp, tp = _segment_closest(a0, a1, b0, b1)
        pi, pk = _add(a0, _scale(_sub(a1, a0), sp)), _add(b0, _scale(_sub(b1, b0), tp))
        pd = jnp.sqrt(_dot(_sub(pi, pk), _sub(pi, pk)) + 1e-12)
        cr = hand.capsule_radius
        return dict(axis_pt=axis_pt, offset=offset, dist=dist, link_gap=dist - _c(hand.link_radius, dtype),
                    spheres=spheres, tool_gap=sdf - radius, tool_grad=sdf_grad, table_gap=spheres[2] - radius,
                    pi=pi, pk=pk, pd=pd, self_gap=pd - _c(cr[i] + cr[k], dtype))

    def evaluate(self, q):
        """The normal equations at q (J, N): J^T J packed (its upper triangle row by row, (J (J + 1) / 2, N)),
        J^T r (J, N), the cost |r|^2 (N,) and the cost without the pull towards the start (N,). Must equal those of
        `ik.residuals_and_jacobian` (its reference); checked by
        `tests/test_ik_lanes.py::test_normal_equations_match_the_reference`."""
        hand, cfg, dtype = self.hand, self.cfg, self.dtype
        ch = chain(hand, q)
        twist = [ax + _cross(an, ax) for ax, an in zip(ch.axis, ch.anchor)]  # (J) 6 components (N,) each
        geo = self.geometry(ch)
        active = self.active.astype(dtype)
        r_link = geo["link_gap"] * active
        unit_offset = _scale(geo["offset"], 1.0 / geo["dist"])
        r_tool, s_tool = ik._hinge(cfg.w_collision, self.margin, geo["tool_gap"])
        r_table, s_table = ik._hinge(cfg.w_collision, cfg.table_margin, geo["table_gap"])
        unit = _scale(_sub(geo["pi"], geo["pk"]), 1.0 / geo["pd"])
        r_self, s_self = ik._hinge(cfg.w_collision, cfg.self_margin, geo["self_gap"])
        # the per-point quantities computed once: XLA would otherwise fuse them (the box distance above all) into
        # every Jacobian row that reads them
        twist, geo, r_link, unit_offset, r_tool, s_tool, r_table, s_table, unit, r_self, s_self = (
            jax.lax.optimization_barrier((twist, geo, r_link, unit_offset, r_tool, s_tool, r_table, s_table, unit,
                                          r_self, s_self)))
        order = self.pair_order
        pair_bodies = hand.capsule_body[hand.self_pairs[order, 0]], hand.capsule_body[hand.self_pairs[order, 1]]

        def wrench(p: Vec, d: Vec):
            return _cross(p, d) + d

        def rows(w, bodies, scale, members, joints):
            """The rows (n, N) (None: identically zero) of points `members` on each of `joints`: the wrench w (6
            terms, None: zero; a float: constant) against the joint's twist, where the joint moves the point's body,
            times d(residual)/d(gap) `scale`."""
            sl = _slice(members)
            moves = hand.joint_moves_body[bodies[members]]
            out = []
            for j in joints:
                mask = moves[:, j]
                if not mask.any():
                    out.append(None)
                    continue
                terms = [(wc if isinstance(wc, float) else wc[sl]) * twist[j][c] for c, wc in enumerate(w)
                         if wc is not None]
                row = sum(terms[1:], terms[0]) * scale[sl]
                out.append(jax.lax.optimization_barrier(row if mask.all() else row * _c(mask, dtype)))  # computed
                # once, not again inside each J^T J entry that XLA would fuse it into
            return out

        jtj, jtr = {}, {}

        def add(table, key, x, y):
            table[key] = table.get(key, 0.0) + _dot0(x, y)

        def add_block(rows_a, ja, rows_b, jb, residual):
            """J^T J's entries of the rows on joints ja and jb (upper triangle), and J^T r's on ja."""
            for x, j1 in zip(rows_a, ja):
                if x is None:
                    continue
                if residual is not None:
                    add(jtr, j1, x, residual)
                for y, j2 in zip(rows_b, jb):
                    if y is None:
                        continue
                    if j1 <= j2:
                        add(jtj, (j1, j2), x, y)
                    elif rows_a is not rows_b:  # within one block the lower triangle mirrors the upper
                        add(jtj, (j2, j1), x, y)

        # the links and spheres (rows on one block each)
        tool_w = wrench(geo["spheres"], geo["tool_grad"])
        table_w = (geo["spheres"][1], -geo["spheres"][0], None, None, None, 1.0)  # the wrench of (0, 0, 1)
        link_w = wrench(geo["axis_pt"], unit_offset)
        for b, js in enumerate(self.blocks):
            for w, bodies, scale, residual, members in (
                    (link_w, hand.link_body, -active, r_link, self.link_members[b]),
                    (tool_w, hand.sphere_body, s_tool, r_tool, self.sphere_members[b]),
                    (table_w, hand.sphere_body, s_table, r_table, self.sphere_members[b])):
                if len(members):
                    x = rows(w, bodies, scale, members, js)
                    add_block(x, js, x, js, residual[_slice(members)])
        # the self-collision pairs: rows on two blocks each
        wa, wb = wrench(geo["pi"], unit), wrench(geo["pk"], _scale(unit, -1.0))
        for ba, bb in dict.fromkeys(map(tuple, self.pair_blocks.tolist())):
            members = np.flatnonzero((self.pair_blocks[:, 0] == ba) & (self.pair_blocks[:, 1] == bb))
            res = r_self[_slice(members)]
            ja, jb = self.blocks[ba], self.blocks[bb]
            xa = rows(wa, pair_bodies[0], s_self, members, ja)
            xb = rows(wb, pair_bodies[1], s_self, members, jb)
            add_block(xa, ja, xa, ja, res)
            add_block(xb, jb, xb, jb, res)
            add_block(xa, ja, xb, jb, None)

        n_j, n = hand.n_joints, q.shape[-1]
        full = lambda v: jnp.broadcast_to(jnp.asarray(v, dtype), (n,))  # noqa: E731
        packed = [full(jtj.get((a, c), 0.0) + (cfg.w_regular**2 if a == c else 0.0))
                  for a in range(n_j) for c in range(a, n_j)]
        r_reg = cfg.w_regular * (q - _c(hand.q_start, dtype))
        jtr = jnp.stack([full(jtr.get(j, 0.0)) for j in range(n_j)]) + cfg.w_regular * r_reg
        nopull = _dot0(r_link, r_link) + _dot0(r_tool, r_tool) + _dot0(r_table, r_table) + _dot0(r_self, r_self)
        return jnp.stack(packed), jtr, nopull + _dot0(r_reg, r_reg), nopull


def _packed_index(n: int) -> dict:
    return {(a, c): i for i, (a, c) in enumerate((a, c) for a in range(n) for c in range(a, n))}


def _cholesky_solve(packed: jax.Array, lam: jax.Array, b: jax.Array) -> jax.Array:
    """x (n, N) with (A + lam I) x = b, for A positive semidefinite given packed (`_Problem.evaluate`), lam (N,)
    > 0 and b (n, N): Cholesky entry by entry, unrolled over the static n, every operation over the batch lane
    (XLA fuses it into a few loops over the batch; no intermediate matrix is stored). Must equal numpy's float64
    solve (its reference, as `ik._damped_step` must); checked by
    `tests/test_ik_lanes.py::test_cholesky_solve_matches_float64`."""
    n = b.shape[0]
    index = _packed_index(n)
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        s = packed[index[j, j]] + lam
        for k in range(j):
            s = s - low[j][k] * low[j][k]
        d = jnp.sqrt(s)
        low[j][j] = d
        for i in range(j + 1, n):
            v = packed[index[j, i]]
            for k in range(j):
                v = v - low[i][k] * low[j][k]
            low[i][j] = v / d
    y = []
    for j in range(n):
        v = b[j]
        for k in range(j):
            v = v - low[j][k] * y[k]
        y.append(v / low[j][j])
    x = [None] * n
    for j in reversed(range(n)):
        v = y[j]
        for k in range(j + 1, n):
            v = v - low[k][j] * x[k]
        x[j] = v / low[j][j]
    return jnp.stack(x)


def solve(hand: HandModel, active, targets, tool_pos, tool_mat, cfg: ik.IKConfig = ik.IKConfig()) -> ik.IKResult:
    """`ik.solve` for a batch: active (..., L), targets (..., L, 3), tool poses (..., 3), (..., 3, 3), any leading
    batch axes -> an `ik.IKResult` with the same leading axes. The batch is solved `cfg.lanes_chunk` problems at a
    time (see `ik.IKConfig`)."""
    chunk = cfg.lanes_chunk
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise ValueError(f"IKConfig.lanes_chunk: must be an int >= 1 (problems per chunk), got {chunk!r}")
    lead = active.shape[:-1]
    n_l = hand.n_links
    n = int(np.prod(lead, dtype=np.int64))
    n_c = max(-(-n // chunk), 1)  # chunks, as even as they can be; the last padded with copies of the first problem
    size = -(-n // n_c)

    def split(x, tail):  # (..., tail) -> (chunks, tail, size)
        x = x.reshape((n,) + tail)
        if n_c * size > n:
            x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (n_c * size - n,) + tail)])
        return jnp.moveaxis(x.reshape((n_c, size) + tail), 1, -1)

    args = (split(active.astype(bool), (n_l,)), split(targets, (n_l, 3)), split(tool_pos, (3,)),
            split(tool_mat, (3, 3)))
    with jax.default_matmul_precision("highest"):
        res = jax.lax.map(lambda a: _solve(hand, cfg, *a), args) if n_c > 1 else jax.tree.map(
            lambda x: x[None], _solve(hand, cfg, *(a[0] for a in args)))
    return jax.tree.map(lambda x: jnp.moveaxis(x, -1, 1).reshape((n_c * size,) + x.shape[1:-1])[:n].reshape(
        lead + x.shape[1:-1]), res)


def _solve(hand, cfg, active, targets, tool_pos, tool_mat) -> ik.IKResult:
    """`ik._solve` with the batch last: active (L, N), targets (L, 3, N), tool_pos (3, N), tool_mat (3, 3, N); the
    result's leaves batch-last."""
    dtype = targets.dtype
    n = targets.shape[-1]
    starts = np.asarray(ik.start_configurations(hand, cfg))  # (S, J)
    n_s = len(starts)
    tile = lambda x: jnp.concatenate([x] * n_s, -1) if n_s > 1 else x  # noqa: E731  start-major copies
    prob = _Problem(hand, cfg, tile(active), tile(targets), tile(tool_pos), tile(tool_mat))
    lo, hi = _c(hand.joint_range[:, 0], dtype), _c(hand.joint_range[:, 1], dtype)
    q0 = jnp.asarray(np.repeat(starts.T, n, axis=1), dtype)  # (J, S * N)

    def iteration(carry, i):
        q, normal, lam = carry
        # iteration 0 evaluates the start (a zero step, always accepted, the damping kept): the program holds one
        # copy of the evaluation, which is most of its compile time
        step = jnp.where(i > 0, _cholesky_solve(normal[0], lam, -normal[1]), 0.0)
        q_new = jnp.clip(q + step, lo, hi)
        normal_new = jax.lax.optimization_barrier(prob.evaluate(q_new))
        better = (normal_new[2] < normal[2]) | (i == 0)
        keep = lambda new, old: jnp.where(better, new, old)  # noqa: E731
        lam = jnp.where(i > 0, jnp.clip(jnp.where(better, lam * cfg.damping_down, lam * cfg.damping_up), 1e-9, 1e2),
                        lam)
        return (keep(q_new, q), jax.tree.map(keep, normal_new, normal), lam), None

    m = q0.shape[-1]
    n_j = hand.n_joints
    blank = (jnp.zeros((n_j * (n_j + 1) // 2, m), dtype), jnp.zeros((n_j, m), dtype), jnp.zeros(m, dtype),
             jnp.zeros(m, dtype))
    init = (q0, blank, jnp.full((m,), cfg.damping0, dtype))
    (q, normal, _), _ = jax.lax.scan(iteration, init, jnp.arange(cfg.iterations + 1), unroll=cfg.unroll)
    if n_s > 1:
        best = jnp.argmin(normal[3].reshape(n_s, n), 0)  # the lowest cost without the pull; ties to the earlier
        q = jnp.take_along_axis(q.reshape(hand.n_joints, n_s, n), best[None, None], 1)[:, 0]
        prob = _Problem(hand, cfg, active, targets, tool_pos, tool_mat)

    geo = prob.geometry(chain(hand, q))
    link_error = jnp.where(active, jnp.abs(geo["link_gap"]), 0.0)
    surface = _add(geo["axis_pt"], _scale(geo["offset"], _c(hand.link_radius, dtype) / geo["dist"]))
    penetration = -jnp.min(jnp.concatenate([geo["tool_gap"], geo["table_gap"], geo["self_gap"]]), 0)
    return ik.IKResult(q=q, points=jnp.stack(surface, 1), link_error=link_error, error=jnp.max(link_error, 0),
                       penetration=penetration, collision=penetration > cfg.collision_tol)
