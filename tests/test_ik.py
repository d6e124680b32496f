"""Collision-avoiding IK (gsp_jax.solvers.ik): closed-form Jacobian vs autodiff, reaching targets that are reachable by
construction, flagging unreachable targets and collisions, gradients vs finite differences, joint limits, vmap.

Every jitted function is built once per module (module-scoped fixtures) and called with fixed shapes. They are
compiled at XLA backend optimisation level 0 (per function, `jit(..., compiler_options=FAST)`; nothing global):
the IK's scans compile about twice as fast on a small CPU, with the same results to float32 rounding.
"""
import dataclasses
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import tolerances as tol
from gsp_jax.model import load as model_lib
from gsp_jax.solvers import ik
from gsp_jax.model import kinematics, scenario

CFG = ik.IKConfig()
SINGLE = dataclasses.replace(CFG, extra_starts=())  # the model's start alone (no extra starts)
I3 = jnp.eye(3, dtype=jnp.float32)
FAR = jnp.asarray([0.0, 0.0, -1.0], jnp.float32)  # a tool placement no finger can touch
FAST = {"xla_backend_optimization_level": 0}


def _rows(hand):
    """Row blocks of residuals_and_jacobian: link (L), sphere-tool (S), sphere-table (S), self (P), reg (J)."""
    L, S, P, J = hand.n_links, len(hand.sphere_body), len(hand.self_pairs), hand.n_joints
    edges = np.cumsum([0, L, S, S, P, J])
    return {k: slice(edges[i], edges[i + 1]) for i, k in enumerate(["link", "tool", "table", "self", "reg"])}


@pytest.fixture(scope="module")
def space():
    return model_lib.default_space()


@pytest.fixture(scope="module")
def nominal_waypoints():
    return np.asarray(scenario.make_episode().waypoints)


@pytest.fixture(scope="module")
def solve_grasp(hand):
    """jit: (options (L,), tool_pos (3,)) -> IKResult, identity tool orientation, default config."""

    def f(options, tool_pos):
        active, targets, _ = ik.grasp_targets(hand, options, tool_pos, I3)
        return ik.solve(hand, active, targets, tool_pos, I3)

    return jax.jit(f, compiler_options=FAST)


BATCH = 16  # every batched solve runs in chunks of this size: one compilation for the module


@pytest.fixture(scope="module")
def solve_batch(hand):
    """(active (N, L), targets (N, L, 3), tool_pos (N, 3)) -> IKResult as numpy, identity tool orientation,
    default config; vmapped and jitted once for batches of BATCH (the input is padded)."""
    f = jax.jit(jax.vmap(lambda a, t, p: ik.solve(hand, a, t, p, I3)), compiler_options=FAST)

    def run(active, targets, tool_pos):
        n = len(active)
        pad = -n % BATCH
        args = [np.concatenate([x, np.repeat(x[-1:], pad, 0)]) for x in (active, targets, tool_pos)]
        outs = [
            jax.tree.map(np.asarray, f(*(jnp.asarray(x[i : i + BATCH]) for x in args)))
            for i in range(0, n + pad, BATCH)
        ]
        return jax.tree.map(lambda *xs: np.concatenate(xs)[:n], *outs)

    return run


# ------------------------------------------------------------------------------------ (a) Jacobian vs jacfwd


def test_residual_jacobian_matches_jacfwd(hand, space, nominal_waypoints, random_q):
    rng = np.random.default_rng(11)
    n = 12
    qs = random_q(hand, rng, n)
    qs[: n // 2] = (hand.q_start + rng.uniform(-0.3, 0.3, size=(n // 2, hand.n_joints))).clip(
        hand.joint_range[:, 0], hand.joint_range[:, 1]
    )  # half near the start: fingers near the tool, so tool-collision rows are exercised
    gs = rng.integers(0, space.n_grasps, size=n)
    opts = np.asarray(space.decode(gs))
    tool_pos = nominal_waypoints[rng.integers(0, 16, size=n)]
    tool_pos[n // 2 :, :2] += rng.uniform(-0.03, 0.03, size=(n - n // 2, 2))

    def both(q, options, tp):
        active, targets, _ = ik.grasp_targets(hand, options, tp, I3)
        f = lambda q: ik.residuals_and_jacobian(hand, CFG, q, active, targets, tp, I3)  # noqa: E731
        r, jac = f(q)
        return r, jac, jax.jacfwd(lambda q: f(q)[0])(q)

    batched = jax.jit(jax.vmap(both), compiler_options=FAST)
    r, jac, auto = batched(jnp.asarray(qs), jnp.asarray(opts), jnp.asarray(tool_pos, jnp.float32))
    r, jac, auto = np.asarray(r), np.asarray(jac), np.asarray(auto)
    rows = _rows(hand)
    assert jac.shape == auto.shape == (n, rows["reg"].stop, hand.n_joints)
    np.testing.assert_allclose(jac, auto, atol=1e-5, rtol=0)
    # the comparison is not vacuous: every block has active (non-zero) rows somewhere in the sample
    for name, sl in rows.items():
        assert np.any(r[:, sl] != 0), name
        assert np.max(np.abs(auto[:, sl])) > 1e-3, name


# ---------------------------------------------------------------------------------------- box_sdf reference


def _box_surface_samples(hand, spacing=4e-4):
    """Points on the union's boundary (tool frame): box faces sampled on a grid, minus covered/internal parts."""
    pts = []
    for c, m, half in zip(hand.tool_box_pos, hand.tool_box_mat, hand.tool_box_half):
        for ax in range(3):
            u, v = [a for a in range(3) if a != ax]
            nu, nv = int(np.ceil(2 * half[u] / spacing)) + 1, int(np.ceil(2 * half[v] / spacing)) + 1
            gu, gv = np.meshgrid(np.linspace(-half[u], half[u], nu), np.linspace(-half[v], half[v], nv))
            for sign in (-1.0, 1.0):
                local = np.zeros((gu.size, 3))
                local[:, u], local[:, v], local[:, ax] = gu.ravel(), gv.ravel(), sign * half[ax]
                normal = np.zeros(3)
                normal[ax] = sign
                p = c + local @ m.T
                n_out = m @ normal
                # a face point is on the union's boundary iff just outside it (along its normal) is outside all boxes
                probe = p + 1e-7 * n_out
                keep = ~_inside_any(hand, probe)
                pts.append(p[keep])
    return np.concatenate(pts)


def _inside_any(hand, p):
    inside = np.zeros(len(p), bool)
    for c, m, half in zip(hand.tool_box_pos, hand.tool_box_mat, hand.tool_box_half):
        local = (p - c) @ m
        inside |= np.all(np.abs(local) <= half, axis=-1)
    return inside


def _count_inside(hand, p):
    count = np.zeros(len(p), int)
    for c, m, half in zip(hand.tool_box_pos, hand.tool_box_mat, hand.tool_box_half):
        count += np.all(np.abs((p - c) @ m) <= half, axis=-1)
    return count


def _union_sdf_reference(hand, p_tool, surface):
    """Brute force: distance to the nearest boundary sample, negative inside any box."""
    d = np.empty(len(p_tool))
    for i in range(0, len(p_tool), 64):
        chunk = p_tool[i : i + 64]
        d[i : i + 64] = np.sqrt(np.min(np.sum((chunk[:, None, :] - surface[None]) ** 2, -1), axis=1))
    return np.where(_inside_any(hand, p_tool), -d, d)


def _exterior_distance(hand, p_tool):
    """Exact distance to the union for outside points: nearest point of each box by clamping."""
    best = np.full(len(p_tool), np.inf)
    for c, m, half in zip(hand.tool_box_pos, hand.tool_box_mat, hand.tool_box_half):
        local = (p_tool - c) @ m
        best = np.minimum(best, np.linalg.norm(local - np.clip(local, -half, half), axis=-1))
    return best


@pytest.fixture(scope="module")
def sdf_case(hand):
    rng = np.random.default_rng(5)
    # a random tool pose
    quat = rng.normal(size=4)
    quat /= np.linalg.norm(quat)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, quat)
    mat = mat.reshape(3, 3)
    tool_pos = np.array([0.01, -0.02, 0.05])
    # points in the tool frame: around the boxes, a third of them inside
    lo = np.min(hand.tool_box_pos - hand.tool_box_half, 0) - 0.01
    hi = np.max(hand.tool_box_pos + hand.tool_box_half, 0) + 0.01
    p_out = rng.uniform(lo, hi, size=(300, 3))
    b = rng.integers(0, len(hand.tool_box_pos), size=150)
    p_in = hand.tool_box_pos[b] + np.einsum(
        "nij,nj->ni", hand.tool_box_mat[b], rng.uniform(-1, 1, size=(150, 3)) * hand.tool_box_half[b]
    )
    p_tool = np.concatenate([p_out, p_in])
    world = tool_pos + p_tool @ mat.T
    got = np.asarray(
        ik.box_sdf(
            jnp.asarray(world, jnp.float32), jnp.asarray(tool_pos, jnp.float32), jnp.asarray(mat, jnp.float32), hand
        )
    )
    return p_tool, got


def test_box_sdf_outside_points_match_exact_distance(hand, sdf_case):
    p_tool, got = sdf_case
    outside = ~_inside_any(hand, p_tool)
    assert outside.sum() > 200
    np.testing.assert_allclose(got[outside], _exterior_distance(hand, p_tool[outside]), atol=2e-6)


def test_box_sdf_matches_brute_force_union_sdf(hand, sdf_case):
    """Inside/outside always right; the value exact (to the reference's sampling) everywhere except where boxes
    overlap, where box_sdf documents a shallower bound: never deeper than the true depth."""
    p_tool, got = sdf_case
    ref = _union_sdf_reference(hand, p_tool, _box_surface_samples(hand))
    inside = _inside_any(hand, p_tool)
    assert inside.sum() > 100
    np.testing.assert_array_equal(got < 0, ref < 0)
    # grid spacing 0.4 mm -> every boundary point is within 0.29 mm of a sample
    assert np.all(got >= ref - 3e-4)  # never reports more penetration than there is
    n_boxes_containing = _count_inside(hand, p_tool)
    single = n_boxes_containing <= 1
    assert single.sum() > 0.9 * len(p_tool)
    np.testing.assert_allclose(got[single], ref[single], atol=3e-4)


def test_box_sdf_inside_the_seam_between_handle_and_head(hand):
    """Minimal case: a point 5 mm deep inside the tool, where the handle meets the head (the model overlaps the
    boxes so that no point there is shallow in both)."""
    handle_end = hand.tool_box_pos[0, 0] + hand.tool_box_half[0, 0]
    head_start = hand.tool_box_pos[1, 0] - hand.tool_box_half[1, 0]
    assert handle_end > head_start + 5e-3  # the boxes overlap by more than the handle's half thickness
    p = jnp.asarray([[head_start, 0.0, 0.0]], jnp.float32)
    d = float(ik.box_sdf(p, jnp.zeros(3, jnp.float32), I3, hand)[0])
    # the nearest point of the tool's surface is on the handle's top/bottom face, 5 mm away
    assert d == pytest.approx(-hand.tool_box_half[0, 2], abs=1e-4)


def _box_sdf_float64(hand, p_tool):
    """box_sdf's definition in numpy float64 (tool frame): min over boxes of outside distance + inside depth
    (the outside distance regularised as sqrt(|.|^2 + 1e-12), as there: differentiable on the surface)."""
    best = np.full(len(p_tool), np.inf)
    for c, m, half in zip(hand.tool_box_pos, hand.tool_box_mat, hand.tool_box_half):
        d = np.abs((p_tool - c) @ m) - half
        outside = np.sqrt(np.sum(np.maximum(d, 0.0) ** 2, -1) + 1e-12)
        best = np.minimum(best, outside + np.minimum(d.max(-1), 0.0))
    return best


def test_box_sdf_gradient_matches_central_differences_and_autodiff(hand):
    """The closed-form gradient of `box_sdf_and_grad` against float64 central differences of the distance (an
    independent numpy implementation) and against autodiff of the float32 distance, at points around and inside
    the tool in a random pose; points within 10 um of a kink (equidistant faces or boxes, where the gradient is not
    unique) are left out: there the one-sided slopes differ from the central one by O(1)."""
    rng = np.random.default_rng(8)
    quat = rng.normal(size=4)
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, quat / np.linalg.norm(quat))
    mat, tool_pos = mat.reshape(3, 3), np.array([0.02, 0.01, 0.06])
    lo = np.min(hand.tool_box_pos - hand.tool_box_half, 0) - 0.01
    hi = np.max(hand.tool_box_pos + hand.tool_box_half, 0) + 0.01
    p_tool = rng.uniform(lo, hi, size=(600, 3))
    def slopes(h, one_sided=False):
        lo_ = 0.0 if one_sided else h
        return np.stack([(_box_sdf_float64(hand, p_tool + h * e) - _box_sdf_float64(hand, p_tool - lo_ * e)) / (h + lo_)
                         for e in np.eye(3)], -1)

    fd_local = slopes(1e-7)  # float64: truncation ~(h / distance to an edge)^2, rounding ~1e-10
    # away from kinks the distance is smooth on a 10 um stencil: the one-sided slopes agree with the central ones
    one_sided, central = slopes(1e-5, one_sided=True), slopes(1e-5)
    smooth = np.all(np.abs(one_sided - central) < 0.05, -1)
    assert smooth.sum() > 500 and np.any(_inside_any(hand, p_tool[smooth]))
    world = jnp.asarray(tool_pos + p_tool @ mat.T, jnp.float32)
    tp, tm = jnp.asarray(tool_pos, jnp.float32), jnp.asarray(mat, jnp.float32)
    dist, grad = ik.box_sdf_and_grad(world, tp, tm, hand)
    auto = jax.vmap(jax.grad(lambda x: ik.box_sdf(x[None], tp, tm, hand)[0]))(world)
    np.testing.assert_allclose(np.asarray(dist)[smooth], _box_sdf_float64(hand, p_tool[smooth]), atol=2e-6)
    np.testing.assert_allclose(np.asarray(grad)[smooth], (fd_local @ mat.T)[smooth], atol=1e-4)
    np.testing.assert_allclose(np.asarray(grad)[smooth], np.asarray(auto)[smooth], atol=1e-5)
    clear = smooth & (np.abs(np.asarray(dist)) > 1e-3)  # beyond the regularisation's reach: a distance's gradient
    np.testing.assert_allclose(np.linalg.norm(np.asarray(grad)[clear], axis=-1), 1.0, atol=1e-5)


# ---------------------------------------------------------------------------- (b) reachable targets are reached


def _reachable_single_link_problems(hand, mjmodel, n, seed):
    """Targets reachable by construction: a random configuration of one finger (the others at the start
    configuration), and a point on the surface of one of that finger's contact links.

    Filter (feasibility only): the configuration itself must be free of table and self collisions (every
    collision residual zero with the tool far away, i.e. the configuration is a zero-cost solution for the link
    term), and the target must be at least 2 cm above the table."""
    rng = np.random.default_rng(seed)
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    finger_of_joint = np.array([hand.finger_names.index(n.split("_")[0]) for n in hand.joint_names])
    link_finger = np.array([hand.finger_names.index(n.split("_")[0]) for n in hand.link_names])
    rows = _rows(hand)
    data = mujoco.MjData(mjmodel)
    sites = [mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_SITE, f"contact_{n}") for n in hand.link_names]
    res = jax.jit(
        lambda q, a, t: ik.residuals_and_jacobian(hand, CFG, q, a, t, FAR, I3)[0], compiler_options=FAST
    )
    actives, targets, qrefs = [], [], []
    while len(actives) < n:
        li = len(actives) % hand.n_links  # every link in turn
        sel = finger_of_joint == link_finger[li]
        q = hand.q_start.copy()
        q[sel] = rng.uniform(lo[sel], hi[sel])
        q = q.astype(np.float32)
        # the link's contact segment from MuJoCo: site centre and z axis
        data.qpos[hand.qpos_adr] = q
        mujoco.mj_kinematics(mjmodel, data)
        centre, axis = data.site_xpos[sites[li]].copy(), data.site_xmat[sites[li]].reshape(3, 3)[:, 2].copy()
        u = rng.normal(size=3)
        if hand.link_half[li] > 0:
            u -= (u @ axis) * axis  # a phalanx: a point on the cylinder's side
        u /= np.linalg.norm(u)
        s = rng.uniform(-hand.link_half[li], hand.link_half[li])
        target = centre + s * axis + hand.link_radius[li] * u
        t = np.zeros((hand.n_links, 3), np.float32)
        t[li] = target
        a = np.zeros(hand.n_links, bool)
        a[li] = True
        r = np.asarray(res(jnp.asarray(q), jnp.asarray(a), jnp.asarray(t)))
        assert abs(r[li]) < 1e-6  # the reference configuration realises the target (gsp_jax FK agrees)
        collision_free = np.all(r[rows["tool"].start : rows["self"].stop] == 0)
        if collision_free and target[2] > 0.02:
            actives.append(a)
            targets.append(t)
            qrefs.append(q)
    return np.array(actives), np.array(targets), np.array(qrefs)


@pytest.fixture(scope="module")
def reachable(hand, mjmodel, solve_batch):
    active, targets, qref = _reachable_single_link_problems(hand, mjmodel, 48, seed=2024)
    out = solve_batch(active, targets, np.tile(np.asarray(FAR), (len(active), 1)))
    return active, targets, qref, out


def test_damped_step_solves_the_normal_equations_like_float64_lapack(hand, space, nominal_waypoints, random_q):
    """Both forms of the Levenberg-Marquardt step (LAPACK's Cholesky on a CPU; the unrolled `_gauss_jordan_solve` a
    GPU runs, called here directly) on the IK's own normal equations at random configurations, for the damping's
    whole range: backward error at float32 rounding (Cholesky is backward stable whatever the conditioning; Gauss-Jordan
    is not in general, so this checks it on the IK's matrices), and
    the step within float32 rounding times the condition number of numpy's float64 solve."""
    rng = np.random.default_rng(13)
    qs = random_q(hand, rng, 6)
    opts = np.asarray(space.decode(rng.integers(0, space.n_grasps, size=6)))
    tp = jnp.asarray(nominal_waypoints[5], jnp.float32)

    def normal(q, options):
        active, targets, _ = ik.grasp_targets(hand, options, tp, I3)
        return ik._normal_equations(*ik.residuals_and_jacobian(hand, CFG, q, active, targets, tp, I3)[::-1])

    jtj, jtr = jax.vmap(normal)(jnp.asarray(qs), jnp.asarray(opts))
    for lam in (1e-9, 1e-4, 1e-1):
        eye = jnp.eye(hand.n_joints, dtype=jnp.float32)
        steps = {"lapack": jax.vmap(ik._damped_step, (0, 0, None))(jtj, jtr, jnp.float32(lam)),
                 "unrolled": jax.vmap(ik._gauss_jordan_solve)(jtj + lam * eye, -jtr)}
        a = np.asarray(jtj, np.float64) + lam * np.eye(hand.n_joints)
        b = -np.asarray(jtr, np.float64)
        want = np.linalg.solve(a, b[..., None])[..., 0]
        cond = np.linalg.cond(a)
        for name, x in steps.items():
            x = np.asarray(x, np.float64)
            backward = np.linalg.norm(np.einsum("nij,nj->ni", a, x) - b, axis=-1) / (
                np.linalg.norm(a, axis=(1, 2)) * np.linalg.norm(x, axis=-1) + np.linalg.norm(b, axis=-1))
            assert np.all(backward < 1e-5), (name, lam, backward)
            forward = np.linalg.norm(x - want, axis=-1) / np.linalg.norm(want, axis=-1)
            assert np.all(forward < 1e-5 * cond + 1e-6), (name, lam, forward, cond)


def test_normal_equations_both_forms(hand, space, nominal_waypoints, random_q, monkeypatch):
    """`ik._normal_equations`' two forms (broadcast products and sums on a CPU; matmuls elsewhere, forced here by
    `platform.current`) on the IK's own Jacobians at random configurations: J^T J and J^T r equal to float32
    rounding of sums of ~200 rows, relative to each problem's largest entry."""
    from gsp_jax.core import platform

    rng = np.random.default_rng(17)
    qs = random_q(hand, rng, 6)
    opts = np.asarray(space.decode(rng.integers(0, space.n_grasps, size=6)))
    tp = jnp.asarray(nominal_waypoints[5], jnp.float32)

    def rows(q, options):
        active, targets, _ = ik.grasp_targets(hand, options, tp, I3)
        return ik.residuals_and_jacobian(hand, CFG, q, active, targets, tp, I3)

    r, jac = jax.vmap(rows)(jnp.asarray(qs), jnp.asarray(opts))
    with jax.default_matmul_precision("highest"):
        cpu = jax.vmap(ik._normal_equations)(jac, r)
        monkeypatch.setattr(platform, "current", lambda: "gpu")
        matmul = jax.vmap(ik._normal_equations)(jac, r)
    for name, a, b in zip(("J^T J", "J^T r"), cpu, matmul):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        scale = np.abs(b).reshape(len(qs), -1).max(1)
        assert np.all(scale > 0), name
        rel = np.abs(a - b).reshape(len(qs), -1).max(1) / scale
        assert np.all(rel < 1e-5), (name, rel)


def test_reachable_problems_cover_every_link(hand, reachable):
    active, _, _, _ = reachable
    assert np.all(active.sum(-1) == 1)
    assert np.all(active.sum(0) >= 2)  # every contact link, distal and medial, at least twice


def test_ik_reaches_reachable_single_link_targets(hand, reachable):
    active, targets, qref, out = reachable
    bad = [
        (hand.link_names[int(np.flatnonzero(a)[0])], float(e), q.round(3).tolist())
        for a, e, q in zip(active, out.error, qref)
        if not e < 2e-3
    ]
    assert not bad, f"{len(bad)}/{len(active)} reachable targets missed by > 2 mm: {bad}"
    assert not np.any(out.collision)


def test_ik_result_is_consistent_with_kinematics(hand, reachable):
    """points lie on the link surfaces nearest the targets, link_error/error agree with them."""
    active, targets, _, out = reachable
    for a, t, q, pts, le, e in zip(active, targets, out.q, out.points, out.link_error, out.error):
        axis_pt = np.asarray(kinematics.closest_on_links(hand, jnp.asarray(q), jnp.asarray(t)))
        np.testing.assert_allclose(np.linalg.norm(pts - axis_pt, axis=-1), hand.link_radius, atol=1e-6)
        li = int(np.flatnonzero(a)[0])
        assert le[li] == pytest.approx(abs(np.linalg.norm(t[li] - axis_pt[li]) - hand.link_radius[li]), abs=1e-6)
        assert le[li] == pytest.approx(np.linalg.norm(t[li] - pts[li]), abs=1e-6)
        assert np.all(le[~a] == 0) and e == pytest.approx(le.max())


# ---------------------------------------------------------------------------- (c) unreachable targets flagged


def test_unreachable_target_is_flagged(hand, mjmodel, solve_grasp):
    tool_pos = jnp.asarray([0.5, 0.0, 0.05], jnp.float32)
    options = jnp.asarray([1, 0, 0, 0, 0, 0])  # thumb distal on its first option
    out = solve_grasp(options, tool_pos)
    assert float(out.error) > 0.1
    # independent lower bound: the target is farther from the thumb's base than the thumb is long
    active, targets, _ = ik.grasp_targets(hand, options, tool_pos, I3)
    d = mujoco.MjData(mjmodel)
    mujoco.mj_kinematics(mjmodel, d)
    base = d.xpos[mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_BODY, "thumb_knuckle")]
    length = 0.015 + 0.06 + 0.045 + 0.03  # knuckle + proximal + medial + distal (models/hand.xml)
    bound = np.linalg.norm(np.asarray(targets[0]) - base) - length - hand.link_radius[0]
    assert bound > 0.1
    assert float(out.error) >= bound - 1e-4
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    assert np.all((np.asarray(out.q) >= lo) & (np.asarray(out.q) <= hi))


# ------------------------------------------------------------------------ (d) gradient of the error vs FD


@pytest.fixture(scope="module")
def error_and_grad(hand):
    """The error and its gradient, of one descent (from the model's start alone): the default's result is one of
    its descents, picked by an argmin, so this is the derivative it takes; but with three descents the error has
    three times the kinks (accept/reject branches of the damping), and at 5e-4 central differences of the default
    straddle one on the partly reachable case (2.8 % off, measured)."""

    def err(tool_pos, options):
        active, targets, _ = ik.grasp_targets(hand, options, tool_pos, I3)
        return ik.solve(hand, active, targets, tool_pos, I3, SINGLE).error

    return jax.jit(lambda p, o: err(p, o), compiler_options=FAST), jax.jit(jax.grad(err), compiler_options=FAST)


@pytest.mark.parametrize(
    "tool_pos, options",
    [
        ([0.0, 0.0, -0.03], [0, 1, 0, 0, 0, 0]),  # index tip towards a tool under the table: unreachable by 2.6 cm
        ([0.0, 0.0, 0.03], [0, 0, 0, 3, 0, 0]),  # middle tip under the handle: partly reachable (5 mm short)
    ],
    ids=["unreachable", "partly_reachable"],
)
def test_error_gradient_matches_central_differences(error_and_grad, tool_pos, options):
    err, grad = error_and_grad
    tp, o = jnp.asarray(tool_pos, jnp.float32), jnp.asarray(options)
    assert float(err(tp, o)) > 3e-3  # away from the kink of |gap| at zero
    g = np.asarray(grad(tp, o))
    fd = {}
    for eps in (1e-3, 5e-4):
        fd[eps] = np.array(
            [(float(err(tp.at[k].add(eps), o)) - float(err(tp.at[k].add(-eps), o))) / (2 * eps) for k in range(3)]
        )
    assert np.linalg.norm(g) > 0.1
    for eps, f in fd.items():
        assert np.linalg.norm(g - f) <= 2e-2 * np.linalg.norm(f), (eps, g, f)


# ---------------------------------------------------------------------------------------- (e) collision flag


def test_tool_inside_the_fingers_is_a_collision(hand, mjmodel, solve_grasp):
    d = mujoco.MjData(mjmodel)
    d.qpos[hand.qpos_adr] = hand.q_start
    mujoco.mj_kinematics(mjmodel, d)
    inside = d.xpos[mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_BODY, "index_proximal")]
    out = solve_grasp(jnp.asarray(scenario.START_OPTIONS), jnp.asarray(inside, jnp.float32))
    assert bool(out.collision)
    assert float(out.penetration) > CFG.collision_tol


def test_nominal_thumb_index_grasp_is_clean(hand, nominal_waypoints, solve_grasp):
    """Nominal episode, waypoint 8 (mid-lift), thumb + index fingertips on their first options."""
    out = solve_grasp(jnp.asarray([1, 1, 0, 0, 0, 0]), jnp.asarray(nominal_waypoints[8]))
    assert not bool(out.collision)
    assert float(out.penetration) < CFG.collision_tol
    assert float(out.error) < 2e-3, f"error {float(out.error) * 1e3:.2f} mm, link errors {np.asarray(out.link_error)}"


# ------------------------------------------------------------------- (f) all 288 grasps, (g) vmap vs loop


@pytest.fixture(scope="module")
def all_grasps(hand, space, nominal_waypoints, solve_batch):
    tool_pos = jnp.asarray(nominal_waypoints[8])
    opts = space.decode(jnp.arange(space.n_grasps))
    active, targets, _ = jax.vmap(lambda o: ik.grasp_targets(hand, o, tool_pos, I3))(opts)
    out = solve_batch(np.asarray(active), np.asarray(targets), np.tile(np.asarray(tool_pos), (len(opts), 1)))
    return np.asarray(opts), out


def test_joint_limits_hold_for_all_grasps(hand, all_grasps):
    opts, out = all_grasps
    assert out.q.shape == (288, hand.n_joints)
    assert np.all(np.isfinite(out.q))
    lo, hi = hand.joint_range[:, 0].astype(np.float32), hand.joint_range[:, 1].astype(np.float32)
    assert np.all(out.q >= lo) and np.all(out.q <= hi)
    # the limits are binding somewhere (the check is not vacuous) ...
    assert np.any(np.isclose(out.q, lo, atol=1e-6) | np.isclose(out.q, hi, atol=1e-6))
    # ... and the empty grasp stays at the start configuration (nothing pulls it away)
    np.testing.assert_allclose(out.q[0], hand.q_start, atol=1e-6)
    assert out.error[0] == 0


def test_all_grasps_errors_are_per_active_link(all_grasps):
    opts, out = all_grasps
    active = opts > 0
    assert np.all(out.link_error[~active] == 0)
    np.testing.assert_allclose(out.error, out.link_error.max(-1), atol=0)
    np.testing.assert_array_equal(out.collision, out.penetration > CFG.collision_tol)


def test_vmapped_solve_equals_looped_solve(hand, space, all_grasps, solve_grasp, nominal_waypoints):
    opts, out = all_grasps
    tool_pos = jnp.asarray(nominal_waypoints[8])
    for g in (0, 5, 100, 200, 287):
        one = solve_grasp(jnp.asarray(opts[g]), tool_pos)
        # tolerances from the IK's measured float32 precision (tests/tolerances.py)
        np.testing.assert_allclose(np.asarray(one.q), out.q[g], atol=tol.Q_ATOL, err_msg=f"grasp {g}")
        assert float(one.error) == pytest.approx(float(out.error[g]), abs=tol.IK_ATOL)
        assert bool(one.collision) == bool(out.collision[g])


# ------------------------------------------------------------------------------------------------ dtypes


def test_float32_problem_stays_float32_with_x64_enabled():
    """kinematics keeps the dtype of q (it casts the model's float64 constants); the IK must do the same, or its
    lax.scan carry changes dtype and float32 problems fail whenever jax_enable_x64 is on. Run in a fresh
    process with x64 on from the start (toggling x64 inside a process that already traced under x32 trips over
    JAX's own caches, which is not what a user does). Traced only."""
    code = textwrap.dedent(
        """
        import jax, jax.numpy as jnp
        from gsp_jax.solvers import ik
        from gsp_jax.model import kinematics, load as model, scenario
        hand = model.load_hand()
        p, m = jnp.zeros(3, jnp.float32), jnp.eye(3, dtype=jnp.float32)
        q = jnp.asarray(hand.q_start, jnp.float32)
        assert jax.eval_shape(lambda q: kinematics.body_poses(hand, q), q)[0].dtype == jnp.float32
        active, targets, _ = ik.grasp_targets(hand, jnp.asarray(scenario.START_OPTIONS), p, m)
        r, jac = jax.eval_shape(lambda q: ik.residuals_and_jacobian(hand, ik.IKConfig(), q, active, targets, p, m), q)
        assert r.dtype == jnp.float32 and jac.dtype == jnp.float32, (r.dtype, jac.dtype)
        out = jax.eval_shape(lambda t: ik.solve(hand, active, t, p, m), targets)
        assert out.q.dtype == jnp.float32 and out.error.dtype == jnp.float32, (out.q.dtype, out.error.dtype)
        print("ok")
        """
    )
    env = {**os.environ, "JAX_ENABLE_X64": "1", "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-3000:]



def test_segment_closest_matches_dense_sampling():
    """Closest points of random segment pairs (parallel ones included) against a dense grid over (s, t)."""
    rng = np.random.default_rng(7)
    p0, p1, q0, q1 = (rng.normal(size=(40, 3)).astype(np.float32) for _ in range(4))
    q1[:5] = q0[:5] + (p1[:5] - p0[:5]) * 0.7  # parallel pairs
    s, t = ik.segment_closest(*(jnp.asarray(x) for x in (p0, p1, q0, q1)))
    got = np.linalg.norm(p0 + np.asarray(s)[:, None] * (p1 - p0) - q0 - np.asarray(t)[:, None] * (q1 - q0), axis=-1)
    grid = np.linspace(0, 1, 401)
    ps = p0[:, None] + grid[None, :, None] * (p1 - p0)[:, None]  # (N, G, 3)
    qs = q0[:, None] + grid[None, :, None] * (q1 - q0)[:, None]
    ref = np.min(np.linalg.norm(ps[:, :, None] - qs[:, None, :], axis=-1), axis=(1, 2))
    assert np.all(got <= ref + 1e-5)  # never worse than the best sampled pair
    np.testing.assert_allclose(got, ref, atol=2e-2 * np.linalg.norm(p1 - p0, axis=-1).max() / 400 * 4 + 1e-4)


# ------------------------------------------------------------------ (h) local minima: the default's extra starts

@pytest.fixture(scope="module")
def solve_on_path(hand, space):
    """cfg -> jit: (grasps (N,), tool positions (N, 3), quaternions (N, 4)) -> (error, final cost without the pull
    towards the start, collision) (N,)."""

    def build(cfg):
        def one(g, pos, quat):
            mat = kinematics.quat_to_mat(quat)
            active, pts, _ = ik.grasp_targets(hand, space.decode(g), pos, mat)
            res = ik.solve(hand, active, pts, pos, mat, cfg)
            with jax.default_matmul_precision("highest"):
                r, _ = ik.residuals_and_jacobian(hand, cfg, res.q, active, pts, pos, mat)
            return res.error, jnp.sum(r[: -hand.n_joints] ** 2), res.collision  # the cost the starts compete on

        f = jax.jit(jax.vmap(one), compiler_options=FAST)
        return lambda g, pos, quat: tuple(np.asarray(x) for x in f(jnp.asarray(g), jnp.asarray(pos), jnp.asarray(quat)))

    return build


# spikes of the start alone (python -m experiments ik-spikes): (episode, grasp options, waypoint, error there [m])
SPIKES = [
    ("nominal", [1, 1, 0, 1, 0, 1], 13, 5e-3),  # fingertips stopped on the tool's top edge (5.4 mm)
    ("nominal", [2, 2, 0, 0, 0, 0], 7, 2e-3),  # (2.8 mm)
    ("shift+6mm_+1Nm", [1, 0, 1, 0, 0, 0], 12, 2e-3),  # index medial, the finger curled over the edge (2.4 mm)
    ("shift+8mm_+1Nm", [0, 0, 0, 0, 1, 1], 11, 2e-3),  # middle medial, the same (2.3 mm)
]


def test_default_starts_free_known_spikes(space, solve_on_path):
    """Each case: from the model's start alone the IK stops in a local minimum (more than 2 mm off, collision-free;
    measured, its neighbouring waypoints converge there too, but one of them sits near a branch of the damping and
    does not under every compilation); the default's extra starts converge at all three waypoints (< 1 mm, no
    collision), each result still a function of (grasp, pose) alone."""
    eps = scenario.training_set()
    g, pos, quat = [], [], []
    for name, opts, t, _ in SPIKES:
        for tt in (t - 1, t, t + 1):
            g.append(int(space.encode(opts)))
            pos.append(np.asarray(eps[name].waypoints[tt]))
            quat.append(np.asarray(eps[name].quats[tt]))
    g, pos, quat = np.array(g), np.array(pos, np.float32), np.array(quat, np.float32)
    e1, _, c1 = solve_on_path(SINGLE)(g, pos, quat)
    e3, _, c3 = solve_on_path(CFG)(g, pos, quat)
    e1, e3, c1, c3 = (x.reshape(len(SPIKES), 3) for x in (e1, e3, c1, c3))
    for k, (name, opts, t, spike) in enumerate(SPIKES):
        msg = f"{name} {opts} t={t}: start alone {e1[k] * 1e3} mm, default {e3[k] * 1e3} mm"
        assert e1[k, 1] > spike and not c1[k, 1], msg  # the local minimum (the neighbours: see the docstring)
        assert np.all(e3[k] < 1e-3) and not np.any(c3[k]), msg


def test_default_never_ends_worse_than_the_start_alone(space, solve_on_path):
    """The solve keeps the lowest final cost (without the pull towards the model's start) over its starts, the model's
    start first: per problem that cost is at most the start alone's, up to float32
    rounding (the batched descents round differently) and rare solver bifurcations (tests/tolerances.py). Problems:
    every third grasp at the last five waypoints of the highest training path (where the local minima were), and
    the default converges (< 1 mm, collision-free) on more of them."""
    ep = scenario.training_set()["shift+8mm_+1Nm"]
    grasp_ids = np.arange(1, space.n_grasps, 3)
    ts = np.arange(11, 16)
    g = np.repeat(grasp_ids, len(ts))
    t = np.tile(ts, len(grasp_ids))
    pos, quat = np.asarray(ep.waypoints)[t], np.asarray(ep.quats)[t]
    e1, cost1, c1 = solve_on_path(SINGLE)(g, pos, quat)
    e3, cost3, c3 = solve_on_path(CFG)(g, pos, quat)
    worse = cost3 > cost1 * (1 + 1e-4) + 1e-12
    assert worse.sum() <= int(tol.TIE_FRACTION * len(g)), (worse.sum(), cost1[worse], cost3[worse])
    ok1, ok3 = np.sum((e1 < 1e-3) & ~c1), np.sum((e3 < 1e-3) & ~c3)
    assert ok3 > ok1, (ok1, ok3)


def test_extra_starts_are_validated(hand):
    """Each extra start adds its offsets to every finger's last joints: on a hand of four-joint fingers, an offset of
    four values is the finger's, one of three leaves each finger's first joint and one of five drops its first
    value; on fingers of 4 and 5 joints the five-joint finger keeps its first joint."""
    starts = ik.start_configurations(hand, CFG)
    assert starts.shape == (1 + len(CFG.extra_starts), hand.n_joints)
    np.testing.assert_array_equal(ik.start_configurations(hand, SINGLE), hand.q_start[None])
    finger = np.asarray(hand.joint_finger)
    lo, hi = hand.joint_range.T
    cases = (((0.0, 0.1, -0.2), (0.0, 0.0, 0.1, -0.2)), ((9.0, 0.1, 0.0, -0.1, 0.2), (0.1, 0.0, -0.1, 0.2)))
    for offset, per_finger in cases:
        got = ik.start_configurations(hand, ik.IKConfig(extra_starts=(offset,)))[1]
        want = np.clip(hand.q_start + np.tile(per_finger, len(set(finger.tolist()))), lo, hi)
        np.testing.assert_allclose(got, want)
    five = dataclasses.replace(hand, joint_finger=np.array([0] * 5 + [1] * 4 + [2] * 4 + [3] * 3), q_start=np.zeros(16),
                               joint_range=np.tile([[-1.0, 1.0]], (16, 1)))
    got = ik.start_configurations(five, ik.IKConfig(extra_starts=((0.1, 0.2, 0.3, 0.4),)))[1]
    np.testing.assert_allclose(got, [0, .1, .2, .3, .4] + [.1, .2, .3, .4] * 2 + [.2, .3, .4])
    with pytest.raises(ValueError, match="extra_starts"):
        ik.start_configurations(hand, ik.IKConfig(extra_starts=((0.0, np.nan),)))


@pytest.mark.parametrize("unroll", [3, 7])
def test_unrolled_loop_solves_the_same_problems(hand, all_grasps, nominal_waypoints, unroll):
    """`IKConfig.unroll` (iterations per loop trip; `table1` unrolls on a GPU) leaves the solve as it is: 16 grasps
    spread over the 288 at the nominal mid waypoint, unrolled 3 (a divisor of the 60 iterations) and 7 (not: a
    remainder trip), against the plain loop's solutions, to the tolerances of converged IK (joint angles Q_ATOL,
    link errors IK_ATOL)."""
    opts, plain = all_grasps
    pick = np.linspace(0, len(opts) - 1, BATCH).astype(int)
    tool_pos = jnp.asarray(nominal_waypoints[8])
    cfg = dataclasses.replace(CFG, unroll=unroll)

    def f(o):
        active, targets, _ = ik.grasp_targets(hand, o, tool_pos, I3)
        return ik.solve(hand, active, targets, tool_pos, I3, cfg)

    out = jax.tree.map(np.asarray, jax.jit(jax.vmap(f), compiler_options=FAST)(jnp.asarray(opts[pick])))
    np.testing.assert_allclose(out.q, plain.q[pick], rtol=0, atol=tol.Q_ATOL)
    np.testing.assert_allclose(out.link_error, plain.link_error[pick], rtol=0, atol=tol.IK_ATOL)


def test_collisions_name_the_bodies_and_the_depth(hand):
    """`ik.collisions` (what check-model and `Surrogate.explain` print): the tool's centre put at a sphere of the
    index tip names the index distal among the bodies in the tool, each body once, deepest first, the first as deep
    as the IK's own penetration measure at that configuration; a tool far away names no tool contact, and a
    tolerance beyond the depth names nothing."""
    q = jnp.asarray(hand.q_start, jnp.float32)
    pos, mat = kinematics.body_poses(hand, q)
    s = int(np.flatnonzero(np.asarray(hand.sphere_body) == hand.body_names.index("index_distal"))[-1])
    centre = kinematics.points_on_bodies(pos, mat, hand.sphere_body[s:s + 1], hand.sphere_pos[s:s + 1])[0]
    eye = jnp.eye(3, dtype=jnp.float32)
    lines = ik.collisions(hand, q, centre, eye, tol=0.0)
    geo = ik._geometry(hand, pos, mat, jnp.zeros((hand.n_links, 3), jnp.float32), centre, eye)
    deepest = -float(jnp.min(jnp.concatenate([geo.tool_gap, geo.table_gap, geo.self_gap])))
    assert any(x.startswith("index_distal into the tool ") for x in lines), lines
    depths = [float(x.split()[-2]) for x in lines]
    assert depths == sorted(depths, reverse=True) and len({x.split(" into ")[0] for x in lines}) == len(lines)
    assert float(lines[0].split()[-2]) == pytest.approx(deepest * 1e3, abs=0.051), (lines[0], deepest)
    far = jnp.asarray([0.5, 0.5, 0.5], jnp.float32)
    assert [x for x in ik.collisions(hand, q, far, eye) if "into the tool" in x] == []
    assert ik.collisions(hand, q, centre, eye, tol=deepest + 1e-4) == []  # tol: only deeper ones
