"""Tests of gsp_jax.solvers.wrench: the friction-cone projection, the grasp matrix and the contact-force solve.

References are independent of the code under test: geometric characterisations of the Euclidean projection
(hypothesis), a direct numpy sum of forces and moments, and a conic reference for the solve built from
scipy's non-negative least squares over inscribed and circumscribed polyhedral cones (which sandwich the
exact second-order-cone optimum; SLSQP was tried first and stalled above the true optimum on some
problems, so it is not trustworthy as a reference at 1e-3).
"""
from __future__ import annotations

import functools
import itertools
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from hypothesis import assume, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from scipy.optimize import nnls  # noqa: E402

import tolerances as tol  # noqa: E402
from gsp_jax.solvers import wrench  # noqa: E402

CFG = wrench.WrenchConfig()
# both methods run to convergence: Newton at its default, projected gradient with 10x its old default iterations
CONVERGED = (CFG, wrench.WrenchConfig(method="apg", iterations=1500))
L, RHO = CFG.torque_length, CFG.force_penalty
S = np.diag([1.0, 1.0, 1.0, 1.0 / L, 1.0 / L, 1.0 / L])
S2 = np.diag(S) ** 2

# ------------------------------------------------------------------------------------------ compiled once
_project = jax.jit(wrench.project_cone)
_solve = jax.jit(wrench.solve, static_argnames=("cfg",))


@functools.lru_cache(maxsize=None)
def _vsolver(cfg: wrench.WrenchConfig):
    """jit(vmap(solve)) for one config, compiled once per batch shape."""
    return jax.jit(jax.vmap(functools.partial(wrench.solve, cfg=cfg)))


def _error(p, n, a, mu, w, c):
    return wrench.solve(p, n, a, mu, w, c).error


_grad_w = jax.jit(jax.grad(_error, argnums=4))
_grad_p = jax.jit(jax.grad(_error, argnums=0))
_error_jit = jax.jit(_error)


# ------------------------------------------------------------------------------------------ helpers
def _skew(r):
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def _grasp_matrix_np(points, center):
    """G (6, 3K) built column block by column block: [I; [p_k - c]x]."""
    k = len(points)
    g = np.zeros((6, 3 * k))
    for i in range(k):
        g[:3, 3 * i : 3 * i + 3] = np.eye(3)
        g[3:, 3 * i : 3 * i + 3] = _skew(points[i] - center)
    return g


def _cone_generators(normal, mu, m, outer):
    """m generators (3, m) of a polyhedral cone inscribed in (outer=False) or circumscribing (outer=True) the
    circular cone {|f_t| <= mu f_n} around `normal`."""
    a = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    th = 2 * np.pi * np.arange(m) / m
    s = mu / np.cos(np.pi / m) if outer else mu
    return (normal[None] + s * (np.cos(th)[:, None] * a + np.sin(th)[:, None] * b)).T


def _polyhedral_optimum(points, normals, active, mu, w, center, outer, m=512, prefer=None):
    """min |S(G f - w)|^2 + rho |f|^2 with each active f_k in the polyhedral cone (f = E lam, lam >= 0), inactive
    f_k = 0: a non-negative least-squares problem, solved exactly by scipy's active-set NNLS. Returns (value,
    forces (K, 3))."""
    k = len(points)
    e = np.zeros((3 * k, k * m))
    for i in range(k):
        if active[i]:
            e[3 * i : 3 * i + 3, i * m : (i + 1) * m] = _cone_generators(normals[i], mu, m, outer)
    a = S @ _grasp_matrix_np(points, center)
    mat = np.vstack([a @ e, np.sqrt(RHO) * e])
    pull = np.zeros(3 * k) if prefer is None else np.sqrt(RHO) * (prefer * active[:, None]).ravel()
    rhs = np.concatenate([S @ w, pull])
    lam, rnorm = nnls(mat, rhs, maxiter=50 * k * m)
    return rnorm**2, (e @ lam).reshape(k, 3)


def _random_problem(rng, k, p_inactive=0.3, mu_range=(0.3, 1.2)):
    """Contacts scattered ~3 cm around a centre, inward normals (towards the centre, tilted), a required wrench
    of a few N and ~0.1 N m; at least one contact active."""
    center = rng.normal(size=3) * 0.01
    points = center + rng.normal(size=(k, 3)) * 0.03
    normals = (center - points) + rng.normal(size=(k, 3)) * 0.01
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    active = rng.random(k) >= p_inactive
    active[rng.integers(k)] = True
    mu = rng.uniform(*mu_range)
    w = np.concatenate([rng.normal(size=3) * 3.0, rng.normal(size=3) * 0.1])
    # float32 inputs for gsp_jax; the references use exactly these (rounded) values in float64
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    return f32(points), f32(normals), active, f32(mu), f32(w), f32(center)


def _as_jax(problem):
    p, n, a, mu, w, c = problem
    return jnp.asarray(p), jnp.asarray(n), jnp.asarray(a), jnp.asarray(mu), jnp.asarray(w), jnp.asarray(c)


def _as_f64(problem):
    p, n, a, mu, w, c = problem
    return p.astype(np.float64), n.astype(np.float64), a, float(mu), w.astype(np.float64), c.astype(np.float64)


def _cone_violation(f, n, mu):
    """max over contacts of |f_t| - mu f_n (<= 0 inside)."""
    fn = np.sum(f * n, -1)
    ft = np.linalg.norm(f - fn[..., None] * n, axis=-1)
    return ft - mu * fn


# ------------------------------------------------------------------------------------------ project_cone
_unit = st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)] * 3).map(np.asarray)


@st.composite
def cone_case(draw):
    """A force (magnitudes 1e-3 .. 1e3 N), a unit normal, mu in [0.1, 2], and a seed for extra samples."""
    d, nv = draw(_unit), draw(_unit)
    assume(np.linalg.norm(d) > 0.05 and np.linalg.norm(nv) > 0.05)
    mag = 10.0 ** draw(st.floats(-3.0, 3.0))
    f = (d / np.linalg.norm(d) * mag).astype(np.float32)
    n = (nv / np.linalg.norm(nv)).astype(np.float32)
    mu = np.float32(draw(st.floats(0.1, 2.0)))
    seed = draw(st.integers(0, 2**31 - 1))
    return f, n, mu, seed


def _proj(f, n, mu):
    return np.asarray(_project(jnp.asarray(f, jnp.float32), jnp.asarray(n, jnp.float32), jnp.float32(mu)))


def _tangent_dirs(n, rng, m):
    """m random unit vectors orthogonal to n (float64)."""
    v = rng.normal(size=(m, 3))
    v -= (v @ n)[:, None] * n
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@settings(max_examples=200, deadline=None)
@given(cone_case())
def test_project_cone_lands_in_cone_and_is_idempotent(case):
    f, n, mu, _ = case
    scale = float(np.linalg.norm(f))
    p = _proj(f, n, mu)
    n64 = n.astype(np.float64)
    assert _cone_violation(p.astype(np.float64), n64, float(mu)) <= 1e-5 * scale
    assert np.linalg.norm(p) <= scale * (1 + 1e-5)  # projection onto a cone containing 0 never grows the vector
    pp = _proj(p, n, mu)
    np.testing.assert_allclose(pp, p, rtol=0, atol=1e-5 * scale)


@settings(max_examples=200, deadline=None)
@given(cone_case())
def test_project_cone_is_nearest_point(case):
    """P(p) is the nearest cone point: for points c of the cone, |p - P| <= |p - c| and the variational
    inequality (p - P).(c - P) <= 0; for a cone also (p - P).P = 0."""
    f, n, mu, seed = case
    rng = np.random.default_rng(seed)
    p64, n64, mu64 = f.astype(np.float64), n.astype(np.float64), float(mu)
    proj = _proj(f, n, mu).astype(np.float64)
    scale = np.linalg.norm(p64)
    m = 64
    t = _tangent_dirs(n64, rng, m)
    s = rng.uniform(0.0, 1.0, size=(m, 1))
    s[:8] = 1.0  # boundary rays too
    a = scale * 10.0 ** rng.uniform(-2, 0.5, size=(m, 1))
    c = a * (n64 + mu64 * s * t)  # (m, 3) points of the cone
    # the point in the cone nearest to p along each sampled ray, to make the distance test sharp
    c_ray = np.maximum(np.sum(c * p64, 1, keepdims=True), 0) / np.sum(c * c, 1, keepdims=True) * c
    cands = np.concatenate([c, c_ray, np.zeros((1, 3))])
    tol = 1e-5 * scale
    d_proj = np.linalg.norm(p64 - proj)
    assert np.all(d_proj <= np.linalg.norm(p64 - cands, axis=1) + tol)
    vi = (cands - proj) @ (p64 - proj)
    assert np.all(vi <= 1e-5 * scale * (scale + np.linalg.norm(cands, axis=1)))
    assert abs(np.dot(p64 - proj, proj)) <= 1e-5 * scale**2


@settings(max_examples=200, deadline=None)
@given(cone_case(), st.floats(0.0, 0.98))
def test_project_cone_leaves_interior_points_and_zeroes_polar_points(case, s):
    f, n, mu, seed = case
    rng = np.random.default_rng(seed)
    n64, mu64 = n.astype(np.float64), float(mu)
    mag = float(np.linalg.norm(f))
    t = _tangent_dirs(n64, rng, 1)[0]
    inside = (mag * (n64 + mu64 * s * t)).astype(np.float32)  # |f_t| = s mu f_n, strictly inside
    np.testing.assert_array_equal(_proj(inside, n, mu), inside)
    polar = (mag * (-n64 + s / mu64 * t)).astype(np.float32)  # mu |f_t| = s |f_n|, f_n < 0: the polar cone
    np.testing.assert_array_equal(_proj(polar, n, mu), np.zeros(3, np.float32))


def test_project_cone_batched_with_broadcast_mu_matches_single():
    rng = np.random.default_rng(3)
    f = rng.normal(size=(7, 5, 3)).astype(np.float32) * 4
    n = rng.normal(size=(7, 5, 3))
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
    mu = rng.uniform(0.1, 2.0, size=(7, 1, 1)).astype(np.float32)
    out = np.asarray(wrench.project_cone(jnp.asarray(f), jnp.asarray(n), jnp.asarray(mu)))
    ref = np.stack([[_proj(f[i, j], n[i, j], mu[i, 0, 0]) for j in range(5)] for i in range(7)])
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(cone_case())
def test_cone_jacobian_matches_finite_differences_of_the_projection(case):
    """The Newton solve's closed-form Jacobian of the projection equals central differences of `project_cone` in
    float64 (away from the two kinks, the cone's and its polar's boundary, where the projection is not
    differentiable)."""
    f, n, mu, _ = case
    f64, n64, mu64 = f.astype(np.float64), n.astype(np.float64), float(mu)
    n64 /= np.linalg.norm(n64)  # unit in float64 (float32's unit normal is off by ~1e-8)
    fn = f64 @ n64
    ft = np.linalg.norm(f64 - fn * n64)
    scale = np.linalg.norm(f64)
    assume(abs(ft - mu64 * fn) > 1e-2 * scale and abs(mu64 * ft + fn) > 1e-2 * scale and ft > 1e-2 * scale)
    with jax.enable_x64(True):
        jac = np.asarray(wrench.cone_jacobian(jnp.asarray(f64), jnp.asarray(n64), jnp.asarray(mu64)))
        eps = 1e-6 * scale
        fd = np.stack([
            (np.asarray(wrench.project_cone(jnp.asarray(f64 + eps * e), jnp.asarray(n64), mu64))
             - np.asarray(wrench.project_cone(jnp.asarray(f64 - eps * e), jnp.asarray(n64), mu64))) / (2 * eps)
            for e in np.eye(3)
        ], axis=1)
    np.testing.assert_allclose(jac, fd, atol=1e-6)
    np.testing.assert_allclose(jac, jac.T, atol=1e-12)  # symmetric (a projection onto a convex set)
    assert np.all(np.linalg.eigvalsh(jac) >= -1e-9) and np.all(np.linalg.eigvalsh(jac) <= 1 + 1e-9)


def test_solve_rejects_an_unknown_method():
    p, n, a, mu, w, c = _random_problem(np.random.default_rng(1), 3)
    with pytest.raises(ValueError, match="WrenchConfig.method.*'lbfgs'"):
        wrench.solve(*_as_jax((p, n, a, mu, w, c)), wrench.WrenchConfig(method="lbfgs"))


# ------------------------------------------------------------------------------------------ grasp_matrix
@pytest.mark.parametrize("k", [1, 2, 5])
def test_grasp_matrix_gives_net_force_and_torque(k):
    rng = np.random.default_rng(k)
    points = rng.normal(size=(k, 3)) * 0.05
    center = rng.normal(size=3) * 0.02
    g = np.asarray(wrench.grasp_matrix(jnp.asarray(points, jnp.float32), jnp.asarray(center, jnp.float32)))
    assert g.shape == (6, 3 * k)
    pts, cen = points.astype(np.float32).astype(np.float64), center.astype(np.float32).astype(np.float64)
    for _ in range(5):
        f = rng.normal(size=(k, 3)) * 3.0
        net_force = f.sum(0)
        net_torque = np.cross(pts - cen, f).sum(0)
        np.testing.assert_allclose(g @ f.ravel(), np.concatenate([net_force, net_torque]), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------ solve
N_SCIPY = 10


@pytest.fixture(scope="module")
def scipy_problems():
    rng = np.random.default_rng(20240611)
    return [_random_problem(rng, int(rng.integers(2, 6))) for _ in range(N_SCIPY)]


@pytest.mark.parametrize("i", range(N_SCIPY))
def test_solve_matches_conic_reference(scipy_problems, i):
    """The wrench error equals the exact optimum to 1e-3 relative. The optimum is bracketed by NNLS over a
    circumscribed (lower bound) and an inscribed (upper bound) 512-sided polyhedral cone."""
    prob = scipy_problems[i]
    p, n, a, mu, w, c = _as_f64(prob)
    lo, _ = _polyhedral_optimum(p, n, a, mu, w, c, outer=True)
    hi, f_ref = _polyhedral_optimum(p, n, a, mu, w, c, outer=False)
    assert lo <= hi * (1 + 1e-9) and hi - lo <= 2e-4 * hi  # the bracket is tight
    res = _solve(*_as_jax(prob))
    err = float(res.error)
    assert lo * (1 - 1e-3) <= err <= hi * (1 + 1e-3), (err, lo, hi)
    forces = np.asarray(res.forces, np.float64)
    fscale = max(np.abs(forces).max(), 1e-3)
    assert np.all(_cone_violation(forces[a], n[a], mu) <= 1e-5 * fscale)
    assert np.all(np.asarray(res.forces)[~a] == 0.0)
    # the reported error is the objective of the reported forces
    r = _grasp_matrix_np(p, c) @ forces.ravel() - w
    np.testing.assert_allclose(err, np.sum((S @ r) ** 2) + RHO * np.sum(forces**2), rtol=1e-4)
    # and those forces are the optimum's (strong convexity: close values => close minimisers)
    np.testing.assert_allclose(forces, f_ref, atol=0.05 * max(np.abs(f_ref).max(), 0.1))


@pytest.mark.parametrize("i", range(4))
def test_solve_with_a_preferred_grip_and_a_warm_start_matches_conic_reference(scipy_problems, i):
    """`prefer` (the physics controller's squeeze: 8 N along every normal) changes the penalty to rho |f - prefer|^2:
    the solution equals NNLS's over the sandwiching polyhedral cones with that pull, and a warm start from another
    point reaches the same optimum (the problem is strongly convex)."""
    prob = scipy_problems[i]
    p, n, a, mu, w, c = _as_f64(prob)
    prefer = 8.0 * n
    lo, _ = _polyhedral_optimum(p, n, a, mu, w, c, outer=True, prefer=prefer)
    hi, f_ref = _polyhedral_optimum(p, n, a, mu, w, c, outer=False, prefer=prefer)
    jp = jnp.asarray(prefer, jnp.float32)
    for cfg, init in itertools.product(
        CONVERGED, (None, jnp.asarray(np.random.default_rng(i).normal(size=p.shape) * 5.0, jnp.float32))
    ):
        res = wrench.solve(*_as_jax(prob), cfg, init, jp)
        forces = np.asarray(res.forces, np.float64)
        r = _grasp_matrix_np(p, c) @ forces.ravel() - w
        value = np.sum((S @ r) ** 2) + RHO * np.sum(((forces - prefer) * a[:, None]) ** 2)
        assert lo * (1 - 2e-3) - 1e-6 <= value <= hi * (1 + 2e-3) + 1e-6, (value, lo, hi)
        assert np.all(_cone_violation(forces[a], n[a], mu) <= 1e-5 * max(np.abs(forces).max(), 1e-3))
        assert np.all(forces[~a] == 0.0)
        np.testing.assert_allclose(forces, f_ref, atol=0.05 * max(np.abs(f_ref).max(), 0.1))


@pytest.mark.parametrize("i", range(3))
def test_solve_with_a_minimum_grip_matches_the_shifted_conic_reference(scipy_problems, i):
    """`grip`: forces f_k = grip n_k + g_k, g_k in the cone. The error equals the NNLS optimum of the shifted
    problem min |S(G g - (w - G f0))|^2 + rho |g|^2 (f0 = grip n on the active contacts); the reported forces are
    f0 + g, every active one pressing with at least `grip`; `unmet` is relative to w. grip = 0 is the plain solve,
    bit for bit."""
    prob = scipy_problems[i]
    p, n, a, mu, w, c = _as_f64(prob)
    grip = 2.0
    f0 = grip * n * a[:, None]
    shifted = w - _grasp_matrix_np(p, c) @ f0.ravel()
    lo, _ = _polyhedral_optimum(p, n, a, mu, shifted, c, outer=True)
    hi, g_ref = _polyhedral_optimum(p, n, a, mu, shifted, c, outer=False)
    for cfg in CONVERGED:
        _check_minimum_grip(prob, cfg, grip, f0, lo, hi, g_ref)


def _check_minimum_grip(prob, cfg, grip, f0, lo, hi, g_ref):
    p, n, a, mu, w, c = _as_f64(prob)
    res = wrench.solve(*_as_jax(prob), cfg, grip=grip)
    err = float(res.error)
    assert lo * (1 - 2e-3) - 1e-6 <= err <= hi * (1 + 2e-3) + 1e-6, (err, lo, hi)
    forces = np.asarray(res.forces, np.float64)
    np.testing.assert_allclose(forces, f0 + g_ref, atol=0.05 * max(np.abs(g_ref).max(), 0.1))
    assert np.all(np.sum(forces[a] * n[a], -1) >= grip * (1 - 1e-4))
    assert np.all(forces[~a] == 0.0)
    r = _grasp_matrix_np(p, c) @ forces.ravel() - w
    np.testing.assert_allclose(np.asarray(res.residual, np.float64), r, atol=1e-4 * max(np.abs(w).max(), 1.0))
    np.testing.assert_allclose(float(res.unmet), np.linalg.norm(S @ r) / np.linalg.norm(S @ w), rtol=1e-3)
    # a warm start from the returned (total) forces stays at the optimum
    warm = wrench.solve(*_as_jax(prob), cfg, res.forces, grip=grip)
    np.testing.assert_allclose(np.asarray(warm.forces), np.asarray(res.forces),
                               atol=1e-3 * max(np.abs(forces).max(), 1.0))
    plain, zero = wrench.solve(*_as_jax(prob), cfg), wrench.solve(*_as_jax(prob), cfg, grip=0.0)
    jax.tree.map(lambda x, y: np.testing.assert_array_equal(np.asarray(x), np.asarray(y)), plain, zero)


def test_solve_batch_accuracy_against_conic_reference():
    """A wider sweep, vmapped: 48 random 5-contact problems (some contacts inactive, mu 0.3 .. 1.2).

    The default Newton solve reaches the exact optimum at 1e-3 relative. Projected gradient with 150 iterations
    (the default before Newton) keeps the objective gap below 1e-4 of the problem's own scale |S w|^2 (it can
    exceed 1e-3 *relative* on problems whose optimum is tiny); with 600 it reaches 1e-3 relative too."""
    rng = np.random.default_rng(99)
    probs = [_random_problem(rng, 5) for _ in range(48)]
    batch = [jnp.asarray(np.stack(x)) for x in zip(*probs)]
    e_newton = np.asarray(_vsolver(CFG)(*batch).error, np.float64)
    e150 = np.asarray(_vsolver(wrench.WrenchConfig(method="apg", iterations=150))(*batch).error, np.float64)
    e600 = np.asarray(_vsolver(wrench.WrenchConfig(method="apg", iterations=600))(*batch).error, np.float64)
    for j, prob in enumerate(probs):
        p, n, a, mu, w, c = _as_f64(prob)
        lo, _ = _polyhedral_optimum(p, n, a, mu, w, c, outer=True, m=256)
        hi, _ = _polyhedral_optimum(p, n, a, mu, w, c, outer=False, m=256)
        sw2 = np.sum((S @ w) ** 2)
        assert lo - 1e-4 * sw2 <= e150[j] <= hi + 1e-4 * sw2, (j, e150[j], lo, hi, sw2)
        assert lo * (1 - 1e-3) <= e600[j] <= hi * (1 + 1e-3), (j, e600[j], lo, hi)
        assert lo * (1 - 1e-3) <= e_newton[j] <= hi * (1 + 1e-3), (j, e_newton[j], lo, hi)


def test_solve_unmet_residual_and_inactive_contacts():
    rng = np.random.default_rng(5)
    for _ in range(6):
        prob = _random_problem(rng, 5, p_inactive=0.5)
        p, n, a, mu, w, c = _as_f64(prob)
        res = _solve(*_as_jax(prob))
        forces = np.asarray(res.forces, np.float64)
        assert np.all(np.asarray(res.forces)[~a] == 0.0)  # exactly zero, not just small
        r = _grasp_matrix_np(p, c) @ forces.ravel() - w
        np.testing.assert_allclose(np.asarray(res.residual), r, rtol=1e-4, atol=1e-5 * np.abs(w).max())
        unmet = np.linalg.norm(S @ r) / np.linalg.norm(S @ w)
        np.testing.assert_allclose(float(res.unmet), unmet, rtol=1e-4, atol=1e-6)
        assert 0.0 <= float(res.unmet) <= 1.0 + 1e-5  # f = 0 is feasible, so never worse than no contact


def test_solve_no_active_contact_leaves_everything_unmet():
    rng = np.random.default_rng(6)
    p, n, a, mu, w, c = _random_problem(rng, 3)
    a = np.zeros(3, bool)
    res = _solve(*_as_jax((p, n, a, mu, w, c)))
    np.testing.assert_array_equal(np.asarray(res.forces), 0.0)
    np.testing.assert_allclose(float(res.unmet), 1.0, rtol=1e-6)
    np.testing.assert_allclose(float(res.error), np.sum((S @ w.astype(np.float64)) ** 2), rtol=1e-5)


@pytest.fixture(scope="module")
def grad_problems():
    """Smooth optima: every active contact carries a clearly non-zero force, or the residual is clearly
    non-zero, so the error is differentiable (checked by the finite differences themselves)."""
    rng = np.random.default_rng(0)
    out = []
    while len(out) < 4:
        prob = _random_problem(rng, 4, p_inactive=0.0)  # one shape: one compile of each gradient
        res = _solve(*_as_jax(prob))
        fn = np.sum(np.asarray(res.forces) * prob[1], -1)
        if float(res.unmet) > 0.05 and (np.all(fn > 0.05) or float(res.unmet) > 0.3):
            out.append(prob)
    return out


@pytest.mark.parametrize("i", range(4))
def test_grad_of_wrench_error_matches_finite_differences(grad_problems, i):
    prob = _as_jax(grad_problems[i])
    p, n, a, mu, w, c = prob
    k = p.shape[0]
    gw = np.asarray(_grad_w(*prob), np.float64)
    gp = np.asarray(_grad_p(*prob), np.float64)
    eps_w, eps_p = 1e-3, 1e-4
    fd_w = np.zeros(6)
    for j in range(6):
        e = jnp.zeros(6, jnp.float32).at[j].set(eps_w)
        fd_w[j] = (float(_error_jit(p, n, a, mu, w + e, c)) - float(_error_jit(p, n, a, mu, w - e, c))) / (2 * eps_w)
    fd_p = np.zeros((k, 3))
    for kk in range(k):
        for j in range(3):
            e = jnp.zeros((k, 3), jnp.float32).at[kk, j].set(eps_p)
            fd_p[kk, j] = (
                float(_error_jit(p + e, n, a, mu, w, c)) - float(_error_jit(p - e, n, a, mu, w, c))
            ) / (2 * eps_p)
    np.testing.assert_allclose(gw, fd_w, rtol=2e-2, atol=2e-2 * np.abs(fd_w).max())
    np.testing.assert_allclose(gp, fd_p, rtol=2e-2, atol=2e-2 * np.abs(fd_p).max())
    assert np.abs(fd_w).max() > 1e-2 and np.abs(fd_p).max() > 1e-2  # not a vacuous comparison


def test_grad_of_converged_error_matches_envelope_theorem(grad_problems):
    """At the optimum the constraints do not depend on w or on the points, so dE*/dw = -2 S^2 r and
    dE*/dp_k = f_k x (2 r_tau / L^2) (r = G f - w): an analytic reference for the unrolled gradient (with
    iterations enough to converge the derivative of the unrolled map too), for both methods."""
    for cfg in CONVERGED:
        _check_envelope(grad_problems, cfg)


def _check_envelope(grad_problems, cfg):

    def err(p, n, a, mu, w, c):
        return wrench.solve(p, n, a, mu, w, c, cfg).error

    g = jax.jit(jax.grad(err, argnums=(0, 4)))
    for prob in grad_problems:
        prob = _as_jax(prob)
        gp, gw = (np.asarray(x, np.float64) for x in g(*prob))
        res = _solve(*prob, cfg=cfg)
        r = np.asarray(res.residual, np.float64)
        f = np.asarray(res.forces, np.float64)
        env_w = -2 * S2 * r
        env_p = np.cross(f, 2 * r[3:] / L**2)
        np.testing.assert_allclose(gw, env_w, rtol=2e-2, atol=2e-2 * np.abs(env_w).max())
        np.testing.assert_allclose(gp, env_p, rtol=2e-2, atol=2e-2 * np.abs(env_p).max())


def test_vmapped_solve_equals_looped_solve():
    rng = np.random.default_rng(11)
    probs = [_random_problem(rng, 4) for _ in range(8)]
    batch = [jnp.asarray(np.stack(x)) for x in zip(*probs)]
    out = _vsolver(CFG)(*batch)
    # float32: the batched and the single program round differently (seen: 1.5e-5 relative on an error of 0.03 N^2
    # under XLA's optimisation level 0); a wrong batching rule would differ at O(1)
    for j, prob in enumerate(probs):
        one = _solve(*_as_jax(prob))
        scale = max(float(np.abs(np.asarray(one.forces)).max()), 1e-3)
        np.testing.assert_allclose(np.asarray(out.forces[j]), np.asarray(one.forces), rtol=0, atol=1e-4 * scale)
        np.testing.assert_allclose(float(out.error[j]), float(one.error), rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(float(out.unmet[j]), float(one.unmet), rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(np.asarray(out.residual[j]), np.asarray(one.residual), rtol=1e-4, atol=1e-4)


def test_float64_wrench_under_x64_gives_the_float32_solution():
    """With jax x64 on, float32 contacts and a float64 required wrench/centre (as jnp.zeros gives there) solve in
    float32 to the same forces as all-float32 input (the scan carry once failed on the mixed dtypes)."""
    pts = jnp.array([[0.0, -0.01, 0.0], [0.0, 0.01, 0.0], [0.02, 0.01, 0.0]], jnp.float32)
    nrm = jnp.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, -1.0, 0.0]], jnp.float32)
    act = jnp.array([True, True, True])
    w = [0.0, 0.0, 3.4, 0.0, 0.0, 0.05]
    ref = wrench.solve(pts, nrm, act, 0.8, jnp.asarray(w, jnp.float32), jnp.zeros(3, jnp.float32))
    with jax.enable_x64(True):
        out = wrench.solve(pts, nrm, act, 0.8, jnp.asarray(w, jnp.float64), jnp.zeros(3, jnp.float64))
        assert out.forces.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(out.forces), np.asarray(ref.forces), rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------ least friction (scipy LP)
@pytest.mark.parametrize("lever,half_width,finger_x", [(0.02, 0.0125, (0.0, 0.03)), (0.01, 0.02, (0.0, 0.02)),
                                                        (0.035, 0.015, (0.01, 0.04, 0.06))])
def test_least_friction_of_an_offset_thumb_is_its_lever_over_the_width(lever, half_width, finger_x):
    """A thumb at x = -lever on the -y face against fingers at x >= 0 on the +y face (CoM at the origin): every
    squeeze turns the tool about z (least when the fingers press at the nearest, min x), and only friction along x
    on the two faces (2 half_width apart) can turn it back, so a held tool needs mu > (lever + min x) / (2
    half_width) however hard the contacts press; the weight makes any finite squeeze need a little more."""
    points = np.array([[-lever, -half_width, 0.002]] + [[x, half_width, 0.002] for x in finger_x])
    normals = np.array([[0.0, 1.0, 0.0]] + [[0.0, -1.0, 0.0]] * len(finger_x))
    lo, hi = wrench.least_friction(points, normals, [0.0, 0.0, 3.4, 0.0, 0.0, 0.0], np.zeros(3))
    expect = (lever + min(finger_x)) / (2 * half_width)
    assert lo <= expect * (1 + 1e-3) and hi >= expect * (1 - 1e-3)
    assert hi - lo < 2e-3 * expect  # the 64-facet pyramids bracket it to 0.12 %


def test_least_friction_zero_for_a_support_from_below_and_inf_for_one_side():
    up = wrench.least_friction([[0.0, 0.0, -0.005]], [[0.0, 0.0, 1.0]], [0.0, 0.0, 3.4, 0.0, 0.0, 0.0], np.zeros(3))
    assert up == (0.0, 0.0)
    pinch = wrench.least_friction([[-0.01, 0.01, 0.0], [0.01, 0.01, 0.0]], [[0.0, -1.0, 0.0]] * 2,
                                  [0.0, 0.0, 3.4, 0.0, 0.0, 0.0], np.zeros(3))
    assert pinch[0] >= 1e6 and pinch[1] == float("inf")  # no friction coefficient suffices
    opposed = wrench.least_friction([[0.0, -0.01, 0.0], [0.0, 0.01, 0.0]], [[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]],
                                    [0.0, 0.0, 3.4, 0.0, 0.0, 0.0], np.zeros(3))
    assert opposed[1] < 1e-6  # a collinear pinch through the CoM holds with any friction, pressed hard enough
    # one contact at the CoM, asked for 1 N sideways and 0.0004 N up: mu* = 2500, beyond the first guesses
    lo, hi = wrench.least_friction([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [1.0, 0.0, 4e-4, 0.0, 0.0, 0.0],
                                   np.zeros(3))
    assert lo <= 2500.0 * (1 + 1e-3) and hi >= 2500.0 * (1 - 1e-3) and hi - lo < 5.0, (lo, hi)
    with pytest.raises(ValueError, match="least_friction"):
        wrench.least_friction(np.full((1, 3), np.nan), [[0.0, 0.0, 1.0]], np.zeros(6), np.zeros(3))
    with pytest.raises(ValueError, match="facets"):
        wrench.least_friction([[0.0, 0.0, -0.005]], [[0.0, 0.0, 1.0]], np.zeros(6), np.zeros(3), facets=2)



def _motor_limited_optimum(points, normals, active, mu, w, center, jac, offset, limit, weight, outer, m=256):
    """min |S(G f - w)|^2 + rho |f|^2 + (weight / L^2) |relu(|J^T f + offset| - limit)|^2 with each active f_k in
    the m-sided polyhedral cone (f = E lam, lam >= 0). The excess term is min over |u| <= limit of
    |J^T f + offset - u|^2, so the whole is a bounded least-squares problem in (lam >= 0, u), solved exactly by
    scipy's BVLS. Returns (value, forces (K, 3))."""
    from scipy.optimize import lsq_linear

    k, n_j = len(points), len(limit)
    e = np.zeros((3 * k, k * m))
    for i in range(k):
        if active[i]:
            e[3 * i : 3 * i + 3, i * m : (i + 1) * m] = _cone_generators(normals[i], mu, m, outer)
    t = jac.transpose(2, 0, 1).reshape(n_j, 3 * k) @ e
    sw = np.sqrt(weight) / L
    mat = np.block([[S @ _grasp_matrix_np(points, center) @ e, np.zeros((6, n_j))],
                    [np.sqrt(RHO) * e, np.zeros((3 * k, n_j))],
                    [sw * t, -sw * np.eye(n_j)]])
    rhs = np.concatenate([S @ w, np.zeros(3 * k), -sw * offset])
    res = lsq_linear(mat, rhs, bounds=(np.r_[np.zeros(k * m), -limit], np.r_[np.full(k * m, np.inf), limit]),
                     method="bvls", tol=1e-14, max_iter=20 * k * m)
    return 2 * res.cost, (e @ res.x[: k * m]).reshape(k, 3)


@pytest.mark.parametrize("i", range(3))
def test_solve_with_motor_limits_matches_the_polyhedral_reference(scipy_problems, i):
    """`motors`: random 'finger' Jacobians whose limits bind at the unlimited solution (60% of its peak torque).
    The solve's value lies within the optima over the circumscribed and inscribed 256-sided cones, its
    forces are theirs, its joint torques exceed the limits less than the unlimited solve's, and a limit no
    force reaches leaves the plain solve unchanged."""
    prob = scipy_problems[i]
    p, n, a, mu, w, c = _as_f64(prob)
    rng = np.random.default_rng(100 + i)
    jac = rng.normal(0, 0.05, (len(p), 3, 6))
    offset = rng.normal(0, 0.02, 6)
    cfg = wrench.WrenchConfig(method="apg", iterations=4000)
    free = np.asarray(wrench.solve(*_as_jax(prob), cfg).forces, np.float64)
    tau_free = np.einsum("kij,ki->j", jac, free) + offset
    limit = np.full(6, 0.6 * np.abs(tau_free).max())
    weight = 1.0
    lo, _ = _motor_limited_optimum(p, n, a, mu, w, c, jac, offset, limit, weight, outer=True)
    hi, f_ref = _motor_limited_optimum(p, n, a, mu, w, c, jac, offset, limit, weight, outer=False)
    assert lo <= hi * (1 + 1e-9) and hi - lo <= 1e-3 * hi  # the bracket is tight
    motors = wrench.MotorLimits(jnp.asarray(jac, jnp.float32), jnp.asarray(offset, jnp.float32),
                                jnp.asarray(limit, jnp.float32), weight)
    res = wrench.solve(*_as_jax(prob), cfg, motors=motors)
    assert lo * (1 - 2e-3) - 1e-6 <= float(res.error) <= hi * (1 + 2e-3) + 1e-6, (float(res.error), lo, hi)
    forces = np.asarray(res.forces, np.float64)
    np.testing.assert_allclose(forces, f_ref, atol=0.05 * max(np.abs(f_ref).max(), 0.1))
    assert np.all(_cone_violation(forces[a], n[a], mu) <= 1e-5 * max(np.abs(forces).max(), 1e-3))
    excess = lambda f: np.maximum(np.abs(np.einsum("kij,ki->j", jac, f) + offset) - limit, 0).max()  # noqa: E731
    assert excess(forces) < excess(free)
    loose = motors.replace(limit=jnp.full(6, 10 * np.abs(tau_free).max(), jnp.float32))
    np.testing.assert_allclose(np.asarray(wrench.solve(*_as_jax(prob), cfg, motors=loose).forces), free,
                               atol=1e-4 * max(np.abs(free).max(), 1.0))


def test_solve_motor_limits_need_the_projected_gradient_method(scipy_problems):
    jac = jnp.zeros((len(scipy_problems[0][0]), 3, 2))
    motors = wrench.MotorLimits(jac, jnp.zeros(2), jnp.ones(2))
    with pytest.raises(ValueError, match="method 'apg'"):
        wrench.solve(*_as_jax(scipy_problems[0]), CFG, motors=motors)

# ---------------------------------------------------------------------------------------- hold_margin (the oracle)
def _squeeze(w=0.03, weight=3.0):
    """Two contacts at x = +-w pressing inwards along x, lifting `weight` newtons; each contact's 'joints' are its
    three force components (J = identity blocks), so joint torques are the contact forces."""
    points = np.array([[w, 0.0, 0.0], [-w, 0.0, 0.0]])
    normals = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    jac = np.zeros((2, 3, 6))
    jac[0, :, :3], jac[1, :, 3:] = np.eye(3), np.eye(3)
    return points, normals, np.array([0.0, 0.0, weight, 0.0, 0.0, 0.0]), jac


@pytest.mark.parametrize("mu", [0.3, 0.5, 1.0, 2.0])
def test_hold_margin_of_a_squeeze_is_its_closed_form(mu):
    """Each contact carries half the weight W by friction, so it must press with N >= W / (2 mu) (mu cos(pi/F) for
    the inscribed pyramid: the lift direction is one of its facets' normals); the least peak 'torque' is then
    max(N, W / 2), over the limit."""
    points, normals, w6, jac = _squeeze()
    limit, facets = 2.5, 16
    m = wrench.hold_margin(points, normals, mu, w6, np.zeros(3), jac, np.full(6, limit), facets=facets)
    w = w6[2]
    np.testing.assert_allclose(m.torque_ratio_outer, max(w / (2 * mu), w / 2) / limit, rtol=1e-6)
    inner_mu = mu * np.cos(np.pi / facets)
    np.testing.assert_allclose(m.torque_ratio_inner, max(w / (2 * inner_mu), w / 2) / limit, rtol=1e-6)
    assert m.possible == (m.torque_ratio_inner <= 1) and m.impossible == (m.torque_ratio_outer > 1)
    free = wrench.hold_margin(points, normals, mu, w6, np.zeros(3))  # no motors: the cones decide alone
    assert free.torque_ratio_outer == 0.0 and free.torque_ratio_inner == 0.0


def test_hold_margin_one_sided_contacts_cannot_hold():
    points = np.array([[0.03, 0.0, 0.0], [0.03, 0.02, 0.0]])
    normals = np.array([[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    m = wrench.hold_margin(points, normals, 1.0, [0.0, 0.0, 3.0, 0.0, 0.0, 0.0], np.zeros(3))
    assert m.torque_ratio_outer == np.inf and m.torque_ratio_inner == np.inf and m.forces is None and m.impossible


@pytest.mark.parametrize("seed", range(4))
def test_hold_margin_brackets_the_exact_cone_optimum(seed):
    """Random three-contact grasps with random 'finger' Jacobians: the exact-cone problem, solved by an independent
    method (scipy SLSQP on the second-order cones), lies between the outer and the inner pyramid's ratio, and the
    inner solution's forces supply the wrench inside the exact cones at the ratio reported."""
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    normals = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) + rng.normal(0, 0.1, (3, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = -0.03 * normals + rng.normal(0, 0.005, (3, 3))
    w6 = np.r_[rng.normal(0, 1.0, 2), 3.0, rng.normal(0, 0.02, 3)]
    jac = rng.normal(0, 0.05, (3, 3, 8))
    limit, bias, mu = rng.uniform(1.0, 3.0, 8), rng.normal(0, 0.05, 8), 0.8
    m = wrench.hold_margin(points, normals, mu, w6, np.zeros(3), jac, limit, bias, facets=32)
    assert np.isfinite(m.torque_ratio_inner) and m.torque_ratio_outer <= m.torque_ratio_inner + 1e-9
    f = m.forces
    np.testing.assert_allclose(wrench.grasp_matrix(points, np.zeros(3), xp=np) @ f.ravel(), w6, atol=1e-7)
    fn = np.sum(f * normals, 1)
    ft = np.linalg.norm(f - fn[:, None] * normals, axis=1)
    assert np.all(ft <= mu * fn + 1e-7)
    tau = np.einsum("kij,ki->j", jac, f) + bias
    np.testing.assert_allclose(np.max(np.abs(tau) / limit), m.torque_ratio_inner, rtol=1e-6, atol=1e-9)
    g = wrench.grasp_matrix(points, np.zeros(3), xp=np)
    jt = jac.transpose(2, 0, 1).reshape(8, 9)
    cons = [{"type": "eq", "fun": lambda x: g @ x[:9] - w6}]
    for k in range(3):
        n = normals[k]
        cons.append({"type": "ineq", "fun": lambda x, k=k, n=n: mu * (x[3 * k:3 * k + 3] @ n)
                     - np.linalg.norm(x[3 * k:3 * k + 3] - (x[3 * k:3 * k + 3] @ n) * n)})
    cons += [{"type": "ineq", "fun": lambda x: x[9] * limit - (jt @ x[:9] + bias)},
             {"type": "ineq", "fun": lambda x: x[9] * limit + (jt @ x[:9] + bias)}]
    x0 = np.r_[f.ravel(), m.torque_ratio_inner]
    ref = minimize(lambda x: x[9], x0, constraints=cons, method="SLSQP", options=dict(ftol=1e-12, maxiter=500))
    assert ref.success, ref.message
    assert m.torque_ratio_outer - 1e-6 <= ref.x[9] <= m.torque_ratio_inner + 1e-6


def test_hold_margin_names_bad_inputs():
    points, normals, w6, jac = _squeeze()
    with pytest.raises(ValueError, match="mu"):
        wrench.hold_margin(points, normals, 0.0, w6, np.zeros(3))
    with pytest.raises(ValueError, match="wrench must"):
        wrench.hold_margin(points, normals, 1.0, [np.nan] * 6, np.zeros(3))
    with pytest.raises(ValueError, match="jacobians"):
        wrench.hold_margin(points, normals, 1.0, w6, np.zeros(3), jac[:, :2], np.ones(6))
    with pytest.raises(ValueError, match="torque_limit"):
        wrench.hold_margin(points, normals, 1.0, w6, np.zeros(3), jac, -np.ones(6))
    with pytest.raises(ValueError, match="points and normals"):
        wrench.hold_margin(points[:1], normals, 1.0, w6, np.zeros(3))


# ------------------------------------------------------------------ forces as delivered: assess and saturate
_assess = jax.jit(wrench.assess, static_argnames=("cfg",))
_saturate = jax.jit(wrench.saturate)


@pytest.mark.parametrize("i", range(4))
def test_assess_is_the_objective_of_given_forces(scipy_problems, i):
    """`assess` of a solve's forces gives the solve's own residual, unmet fraction and error (no grip, no prefer),
    and its residual is the numpy sum of forces and moments, its error |S r|^2 + rho |f|^2 from them."""
    prob = scipy_problems[i]
    p, n, a, mu, w, c = _as_jax(prob)
    res = _solve(p, n, a, mu, w, c)
    got = _assess(res.forces, p, a, w, c)
    np.testing.assert_allclose(np.asarray(got.residual), np.asarray(res.residual), atol=1e-5 * (1 + np.abs(w).max()))
    np.testing.assert_allclose(float(got.unmet), float(res.unmet), atol=tol.WRENCH_ATOL)
    np.testing.assert_allclose(float(got.error), float(res.error), rtol=1e-4, atol=1e-7)
    pf, nf, af, _, wf, cf = _as_f64(prob)
    forces = np.asarray(res.forces, np.float64) * af[:, None]
    r = _grasp_matrix_np(pf, cf) @ forces.ravel() - wf
    np.testing.assert_allclose(np.asarray(got.residual, np.float64), r, atol=1e-4 * (1 + np.abs(wf).max()))
    np.testing.assert_allclose(float(got.error), np.sum((S @ r) ** 2) + RHO * np.sum(forces**2), rtol=1e-4)


def _saturate_np(forces, jac, limit, link_joints):
    """The reference: torques summed contact by contact, each contact scaled by its own joints' worst ratio."""
    tau = np.zeros(jac.shape[2])
    for k in range(len(forces)):
        tau += jac[k].T @ forces[k]
    out = forces.copy()
    for k in range(len(forces)):
        worst = max([abs(tau[j]) / limit[j] for j in range(len(tau)) if link_joints[k, j]], default=0.0)
        out[k] = forces[k] * min(1.0, 1.0 / worst) if worst > 0 else forces[k]
    return out, tau


def test_saturate_scales_each_link_by_its_worst_joint():
    """Against the numpy reference on random forces and Jacobians (three links: two on one finger sharing its
    joints, one alone); a finger within its limits is untouched; a lone link's torques end within the limits,
    its direction kept; limits no force reaches leave every force unchanged."""
    rng = np.random.default_rng(7)
    link_joints = np.zeros((3, 7), bool)
    link_joints[0, :3] = True  # the medial link: the finger's first three joints
    link_joints[1, :4] = True  # the distal link: all four
    link_joints[2, 4:] = True  # another finger
    for _ in range(20):
        jac = rng.normal(size=(3, 3, 7)) * 0.03 * link_joints[:, None, :]
        forces = rng.normal(size=(3, 3)) * 40.0
        limit = rng.uniform(0.5, 3.0, size=7)
        got = np.asarray(_saturate(jnp.asarray(forces, jnp.float32), jnp.asarray(jac, jnp.float32),
                                   jnp.asarray(limit, jnp.float32), jnp.asarray(link_joints)), np.float64)
        ref, tau = _saturate_np(forces, jac, limit, link_joints)
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
        tau_alone = jac[2].T @ got[2]
        assert np.all(np.abs(tau_alone[4:]) <= limit[4:] * (1 + 1e-4))
        if np.all(np.abs(tau[4:]) <= limit[4:]):
            np.testing.assert_array_equal(got[2], forces[2].astype(np.float32))
        cosine = np.sum(got * forces, -1) / (np.linalg.norm(got, axis=-1) * np.linalg.norm(forces, axis=-1))
        np.testing.assert_allclose(cosine, 1.0, atol=1e-5)
    free = np.asarray(_saturate(jnp.asarray(forces, jnp.float32), jnp.asarray(jac, jnp.float32),
                                jnp.full(7, 1e6, jnp.float32), jnp.asarray(link_joints)))
    np.testing.assert_array_equal(free, forces.astype(np.float32))
