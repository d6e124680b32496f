"""The batch-last IK (gsp_jax.solvers.ik_lanes) against `ik.solve` vmapped: the normal equations at random
configurations, the solved grasps of a table's problems, leading batch axes, and the table built either way.

Two float32 computations of the same solve in another order of arithmetic: compared with the tolerances of
tests/tolerances.py (the precision the solvers reach), allowing rare ties where Levenberg-Marquardt's accept/reject
test goes the other way (as between two CPUs).
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tolerances as tol
from gsp_jax.model import load as model_lib
from gsp_jax.planning import dp
from gsp_jax.solvers import ik, ik_lanes
from gsp_jax.model import kinematics, scenario
from gsp_jax.surrogate.step import Surrogate

CFG = ik.IKConfig()
FAST = {"xla_backend_optimization_level": 0}


@pytest.fixture(scope="module")
def problems(hand):
    """192 IK problems of the nominal episode's table (every 3rd grasp at 4 waypoints) and random configurations:
    active (N, L), targets (N, L, 3), tool poses (N, 3), (N, 3, 3), q (N, J)."""
    space = model_lib.default_space()
    ep = scenario.make_episode()
    g, t = np.meshgrid(np.arange(0, space.n_grasps, 6), [0, 5, 10, 15], indexing="ij")
    g, t = jnp.asarray(g.ravel(), jnp.int32), jnp.asarray(t.ravel())
    mat = jax.vmap(kinematics.quat_to_mat)(ep.quats[t])
    pos = ep.waypoints[t]
    active, targets, _ = jax.vmap(lambda g, p, m: ik.grasp_targets(hand, space.decode(g), p, m))(g, pos, mat)
    q = jnp.asarray(hand.q_start)[None] + 0.3 * jax.random.normal(jax.random.PRNGKey(0), (len(g), hand.n_joints))
    return active, targets, pos, mat, jnp.clip(q, *jnp.asarray(hand.joint_range.T)[:, None])


def test_normal_equations_match_the_reference(hand, problems):
    """J^T J, J^T r and both costs of the batch-last evaluation against `ik.residuals_and_jacobian` per problem
    (closed-form Jacobian, itself checked against autodiff in test_ik.py): relative to each problem's largest entry,
    within 1e-4 (float32 rounding of sums of ~200 rows; the median is ~1e-7) except at rare ties (a sphere exactly
    between two boxes, or on the hinge's kink)."""
    active, targets, pos, mat, q = problems
    n = hand.n_joints
    upper = np.triu_indices(n)

    def reference(q, a, t, p, m):
        r, jac = ik.residuals_and_jacobian(hand, CFG, q, a, t, p, m)
        return (jac.T @ jac)[upper], jac.T @ r, jnp.sum(r**2), jnp.sum(r[:-n] ** 2)

    def lanes(q, a, t, p, m):
        last = lambda x: jnp.moveaxis(x, 0, -1)  # noqa: E731
        out = ik_lanes._Problem(hand, CFG, last(a), last(t), last(p), last(m)).evaluate(last(q))
        return tuple(jnp.moveaxis(x, -1, 0) for x in out)

    with jax.default_matmul_precision("highest"):
        want = jax.jit(jax.vmap(reference))(q, active, targets, pos, mat)
        got = jax.jit(lanes, compiler_options=FAST)(q, active, targets, pos, mat)
    for name, w, g in zip(("J^T J", "J^T r", "cost", "cost without the pull"), want, got):
        w, g = np.asarray(w, np.float64).reshape(len(q), -1), np.asarray(g, np.float64).reshape(len(q), -1)
        scale = np.max(np.abs(w), axis=1)
        assert np.all(scale > 0), name
        rel = np.max(np.abs(w - g), axis=1) / scale
        tol.assert_close_with_rare_ties(rel, np.zeros_like(rel), 1e-4, name)
        assert np.median(rel) < 1e-5, (name, np.median(rel))


def test_cholesky_solve_matches_float64(hand):
    """The unrolled batch-last Cholesky step against numpy's float64 solve of (A + lam I) x = b."""
    n, m = hand.n_joints, 64
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(1), 3)
    x = jax.random.normal(k1, (m, n, 2 * n)) * 0.1
    a = np.asarray(x @ jnp.swapaxes(x, 1, 2), np.float64)  # (m, n, n) positive semidefinite
    lam = np.asarray(10.0 ** jax.random.uniform(k2, (m,), minval=-6, maxval=-1), np.float64)
    b = np.asarray(jax.random.normal(k3, (m, n)), np.float64)
    upper = np.triu_indices(n)
    packed = jnp.asarray(np.moveaxis(a[:, upper[0], upper[1]], 0, -1), jnp.float32)
    got = np.asarray(jax.jit(ik_lanes._cholesky_solve)(packed, jnp.asarray(lam, jnp.float32),
                                                       jnp.asarray(b.T, jnp.float32))).T
    want = np.linalg.solve(a + lam[:, None, None] * np.eye(n), b[..., None])[..., 0]
    # float32 against float64: the error scales with the condition number (up to ~1e5 here)
    cond = np.linalg.cond(a + lam[:, None, None] * np.eye(n))
    err = np.linalg.norm(got - want, axis=1) / np.linalg.norm(want, axis=1)
    assert np.all(err < 1e-6 * cond), np.max(err / cond)


@pytest.fixture(scope="module")
def solved(hand, problems):
    """The problems solved both ways, default config: (reference, batch-last) IKResults (N, ...)."""
    active, targets, pos, mat, _ = problems
    ref = jax.jit(jax.vmap(lambda a, t, p, m: ik.solve(hand, a, t, p, m, CFG)), compiler_options=FAST)
    lanes = jax.jit(lambda a, t, p, m: ik_lanes.solve(hand, a, t, p, m, CFG), compiler_options=FAST)
    return ref(active, targets, pos, mat), lanes(active, targets, pos, mat)


def test_solve_matches_vmapped_solve(hand, solved, problems):
    """The same grasps: the IK error within IK_ATOL, the worst penetration within it too, joint angles of
    converged problems within Q_ATOL, and the realised contacts and collision flags equal, all but rare ties."""
    (want, got), active = solved, np.asarray(problems[0])
    ok = tol.assert_close_with_rare_ties(got.error, want.error, tol.IK_ATOL, "IK error")
    same_pen = tol.assert_close_with_rare_ties(got.penetration, want.penetration, tol.IK_ATOL, "penetration")
    converged = ok & (np.asarray(want.error) < 1e-3)
    dq = np.max(np.abs(np.asarray(got.q) - np.asarray(want.q)), axis=1)
    # a few dozen converged problems: the tie allowance of so small a sample (two starts converging to equally good
    # solutions of the redundant hand can swap on a rounding tie: q 0.16 rad apart at the same IK error)
    tol.assert_close_with_rare_ties(dq[converged], np.zeros(converged.sum()), tol.Q_ATOL, "q of converged problems",
                                    tie_fraction=tol.small_sample_tie_fraction(int(converged.sum())))
    tol_link = 0.005  # the surrogate's contact_tol: compare the realised flags where clear of it
    clear = np.all(np.abs(np.asarray(want.link_error) - tol_link) > 1e-4, axis=1)
    same = np.all((np.asarray(got.link_error) < tol_link) == (np.asarray(want.link_error) < tol_link), axis=1)
    assert np.mean(~same[ok & clear]) <= tol.TIE_FRACTION
    clear_c = np.abs(np.asarray(want.penetration) - CFG.collision_tol) > 1e-4
    # compared where the penetration itself agrees (a tie there moves the flag with it) and is clear of the threshold
    agree = ok & same_pen & clear_c
    assert np.array_equal(np.asarray(got.collision)[agree], np.asarray(want.collision)[agree])
    # the result's other fields are those of its q
    assert np.all(np.asarray(got.link_error)[~active] == 0)
    assert np.allclose(np.asarray(got.error), np.max(np.asarray(got.link_error), axis=1))


def test_leading_axes_and_one_start(hand, problems):
    """Any leading batch axes come back as they went in, a config without extra starts solves each problem once
    (the result equals the first start's), a batch solved in chunks is solved problem by problem as in one, and a
    bad chunk size is named."""
    active, targets, pos, mat, _ = problems
    single = dataclasses.replace(CFG, extra_starts=(), iterations=10)
    solve = jax.jit(lambda a, t, p, m: ik_lanes.solve(hand, a, t, p, m, single), compiler_options=FAST)
    flat = solve(active[:12], targets[:12], pos[:12], mat[:12])
    shaped = solve(*(x[:12].reshape((3, 4) + x.shape[1:]) for x in (active, targets, pos, mat)))
    for f, s in zip(jax.tree.leaves(flat), jax.tree.leaves(shaped)):
        assert s.shape == (3, 4) + f.shape[1:]
        np.testing.assert_array_equal(np.asarray(s).reshape(f.shape), np.asarray(f))
    ref = jax.jit(jax.vmap(lambda a, t, p, m: ik.solve(hand, a, t, p, m, single)), compiler_options=FAST)
    tol.assert_close_with_rare_ties(flat.error, ref(active[:12], targets[:12], pos[:12], mat[:12]).error,
                                    tol.IK_ATOL, "one start", tie_fraction=0.0)
    # in chunks of 5 (three chunks, the last padded): each problem's result as in one chunk
    chunked = jax.jit(lambda a, t, p, m: ik_lanes.solve(hand, a, t, p, m, dataclasses.replace(single, lanes_chunk=5)),
                      compiler_options=FAST)(active[:12], targets[:12], pos[:12], mat[:12])
    assert chunked.q.shape == flat.q.shape
    tol.assert_close_with_rare_ties(chunked.error, flat.error, tol.IK_ATOL, "chunked", tie_fraction=0.0)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="IKConfig.lanes_chunk"):
            ik_lanes.solve(hand, active[:2], targets[:2], pos[:2], mat[:2],
                           dataclasses.replace(single, lanes_chunk=bad))


def test_table_is_the_same_either_way(hand):
    """`dp.build_table` with the batch-last IK (the CPU default) and with `ik.solve` vmapped: the same rewards
    and terminal flags to the tolerances of two float32 computations, and the same DP optimum."""
    ep = scenario.make_episode().head(4)
    lanes = Surrogate(hand, ik_config=dataclasses.replace(CFG, lanes=True), learned=False)
    vmap = Surrogate(hand, ik_config=dataclasses.replace(CFG, lanes=False), learned=False)
    a, sa = jax.jit(lambda e: dp.solve(lanes, e))(ep)
    b, sb = jax.jit(lambda e: dp.solve(vmap, e))(ep)
    ok = tol.assert_close_with_rare_ties(a.reward, b.reward, tol.REWARD_ATOL, "table reward")
    assert np.mean(np.asarray(a.terminal) != np.asarray(b.terminal)) <= tol.FLIP_FRACTION
    assert ok.mean() > 0.95
    np.testing.assert_allclose(float(sa.ret), float(sb.ret), atol=tol.RETURN_ATOL)
