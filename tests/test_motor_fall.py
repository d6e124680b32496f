"""Tests of the surrogate's motor check: a final wrench beyond what the hand's motors can give is a fall
(`RewardConfig.motor_fall_unmet`, `Surrogate.motor_unmet`), judged against an independent reference, the linear
programme of the physics' feasibility oracle (`wrench.hold_margin`: scipy HiGHS, friction pyramids that bracket the
cones, every joint torque within its motor's limit); the batched programs (the DP table, `Surrogate.transitions`)
solving it for the last step's rows only, against every step's check computed and zeroed before the last; and
`dp.longest_surviving` against brute-force enumeration.
"""
from __future__ import annotations

import dataclasses
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.model import kinematics, scenario  # noqa: E402
from gsp_jax.core import platform  # noqa: E402
from gsp_jax.surrogate import reward, step as surrogate  # noqa: E402
from gsp_jax.solvers import wrench  # noqa: E402

N_GRASPS = 48  # grasps of the nominal final pose compared with the LP
SCALES = (0.5, 8.0)  # the external torque times these: grasps that clearly hold the first, clearly not the second


@pytest.fixture(scope="module")
def sur(table_ik):
    return surrogate.Surrogate(ik_config=table_ik, learned=False)


@pytest.fixture(scope="module")
def final_pose_problems(sur):
    """Grasps realised at the nominal episode's final pose, their contacts' Jacobians and the final wrench."""
    ep = scenario.make_episode()
    pos, quat = ep.waypoints[-1], ep.quats[-1]
    rng = np.random.default_rng(0)
    grasp_ids = jnp.asarray(rng.choice(sur.space.n_grasps, N_GRASPS, replace=False), jnp.int32)
    contacts = jax.jit(jax.vmap(sur.realise, (0, None, None)))(grasp_ids, pos, quat)
    jac = jax.vmap(lambda q, p: kinematics.closest_on_links_and_jacobians(sur.hand, q, p)[1])(
        contacts.ik.q, contacts.points)
    com = pos + kinematics.quat_to_mat(quat) @ ep.com
    return ep, pos, quat, contacts, np.asarray(jac), np.asarray(com)


def _lp_ratios(sur, ep, contacts, jac, com, required):
    """(outer, inner) least peak joint torque / limit with which each grasp's realised contacts hold `required`."""
    out = []
    mu = float(ep.friction)
    for g in range(N_GRASPS):
        act = np.asarray(contacts.realised[g])
        if act.sum() == 0:
            out.append((np.inf, np.inf))
            continue
        m = wrench.hold_margin(np.asarray(contacts.points[g])[act], np.asarray(contacts.normals[g])[act], mu,
                               np.asarray(required), com, jac[g][act], np.asarray(sur.torque_limit))
        out.append((m.torque_ratio_outer, m.torque_ratio_inner))
    return np.asarray(out)


@pytest.mark.parametrize("scale", SCALES)
def test_motor_fall_agrees_with_the_oracle_lp(sur, final_pose_problems, scale):
    """Among grasps whose cones can supply the wrench (the LP's ratio finite: the motors decide): where the LP says
    forces within the motors' limits exist with a margin (inner ratio <= 0.8), the motor check leaves little unmet
    (no fall); where it says none exist even at 2.5x the limits (outer ratio >= 2.5), it leaves more than the fall
    threshold unmet. Grasps between the two are not compared (the check's penalty solve and saturation are a
    first-order model, the LP the exact bound); nor are those whose cones alone cannot (the wrench terms judge them)."""
    ep, pos, quat, contacts, jac, com = final_pose_problems
    ep = dataclasses.replace(ep, w_ext=ep.w_ext * scale)
    required = jnp.concatenate([-ep.mass * sur.gravity, jnp.zeros(3)]) - ep.w_ext
    init = jnp.zeros((N_GRASPS,) + contacts.points.shape[1:], jnp.float32)
    unmet = np.asarray(jax.jit(jax.vmap(lambda c, f: sur.motor_unmet(c, ep, pos, quat, f, required)))(contacts, init))
    ratios = _lp_ratios(sur, ep, contacts, jac, com, required)
    finite = np.isfinite(ratios[:, 0]) & (ratios[:, 0] < 1e3)
    holds, cannot = finite & (ratios[:, 1] <= 0.8), finite & (ratios[:, 0] >= 2.5)
    assert holds.sum() + cannot.sum() >= 2, (scale, ratios)  # the comparison is not empty
    threshold = sur.reward_config.motor_fall_unmet
    assert np.all(unmet[holds] < threshold - 0.1), (unmet[holds], ratios[holds])
    assert np.all(unmet[cannot] > threshold + 0.1), (unmet[cannot], ratios[cannot])


def test_the_gpu_form_of_the_motor_check_unrolls_its_solve_to_the_same_result(sur, final_pose_problems,
                                                                             monkeypatch):
    """Traced for a GPU, the motor check's solve runs `MOTOR_GPU_UNROLL` iterations per loop trip (a CPU's keeps
    `wrench_config.unroll`), with the same unmet fractions (the GPU's other kernel forms round apart in float32)."""
    ep, pos, quat, contacts, _, _ = final_pose_problems
    required = jnp.concatenate([-ep.mass * sur.gravity, jnp.zeros(3)]) - ep.w_ext
    init = jnp.zeros((N_GRASPS,) + contacts.points.shape[1:], jnp.float32)

    def check(c, f):
        return sur.motor_unmet(c, ep, pos, quat, f, required)

    def unrolls():
        jaxpr = jax.make_jaxpr(jax.vmap(check))(contacts, init).jaxpr
        return {e.params["unroll"] for e in jaxpr.eqns if e.primitive.name == "scan"
                and e.params["length"] == sur.reward_config.motor_iterations}

    cpu = np.asarray(jax.jit(jax.vmap(check))(contacts, init))
    assert unrolls() == {sur.wrench_config.unroll}
    monkeypatch.setattr(platform, "current", lambda: "gpu")
    assert unrolls() == {surrogate.MOTOR_GPU_UNROLL} != {1}
    gpu = np.asarray(jax.jit(jax.vmap(check))(contacts, init))
    np.testing.assert_allclose(gpu, cpu, atol=1e-4)


def test_a_torque_beyond_the_motors_is_a_fall_and_said_so(sur, solve_each):
    """The nominal lift's first four waypoints with a 1e9 N m final torque: no sequence holds it in the surrogate
    (its DP optimum is r_min), explained as beyond the motors at the final step; with the check off (inf) the same
    plan of the nominal episode ran to its end (the probe of issue 50: planned as held). Four waypoints: the final
    step's motor check is the same program part as at sixteen, the tables a quarter of the work."""
    ep = scenario.make_episode(torque=1e9).head(MOTOR_T + 1)
    table, sol = jax.tree.map(lambda x: x[0], solve_each(sur, scenario.stack([ep])))
    r_min = sur.reward_config.r_min
    assert float(sol.ret) <= r_min
    longest = dp.longest_surviving(table, ep.start_grasp, r_min)
    assert float(longest.ret) == ep.n_steps - 1  # every step but the last can be held
    why = sur.explain(ep, np.asarray(longest.actions))
    assert why.startswith(f"t={ep.n_steps - 1}:") and "beyond the hand's motors" in why, why
    nominal = scenario.make_episode().head(MOTOR_T + 1)
    nominal_plan = np.asarray(solve_each(sur, scenario.stack([nominal]))[1].actions[0])
    off = sur.replace(reward=dataclasses.replace(sur.reward_config, motor_fall_unmet=float("inf")))
    assert off.explain(ep, nominal_plan) is None  # without the check the plan holds 1e9 N m
    assert "beyond the hand's motors" in sur.explain(ep, nominal_plan)


def _motor_problems(jaxpr, iterations: int, in_cond: bool | None = None) -> int:
    """Number of motor-check solves in a jaxpr: every `scan` of `iterations` steps (a count nothing else uses) is
    one, its first carry the forces (*batch, 3K), so it solves prod(batch) problems; sub-jaxprs included. `in_cond`
    True / False: only those inside / outside a `cond`'s branches (None: all)."""
    count = 0
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan" and eqn.params["length"] == iterations and in_cond is not True:
            count += int(np.prod(eqn.outvars[0].aval.shape[:-1]))
        below = in_cond
        if eqn.primitive.name == "cond":
            if in_cond is False:
                continue
            below = None  # inside a cond's branches: every scan there counts
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    count += _motor_problems(inner, iterations, below)
    return count


MOTOR_T = 3  # waypoints of the episode the batched programs are compared on (the nominal lift's first three)


@pytest.fixture(scope="module")
def motor_episode():
    return scenario.make_episode().head(MOTOR_T)


def _every_step_checked(sur, ep, contacts):
    """The reference arrival terms (G, T): every (grasp, waypoint)'s motor check solved (`motor_check` of each
    step's `MotorProblem`), then zeroed before the last step and added by `reward.with_motor`."""
    n_t = ep.n_steps
    ts = jnp.arange(n_t, dtype=jnp.int32)
    nxt = jax.tree.map(lambda x: x[:, jnp.minimum(ts + 1, n_t - 1)], contacts)
    each = lambda now, nx, t: sur.score_deferred(ep, t, ep.waypoints[t], ep.quats[t], now, nx, False)  # noqa: E731
    terms, problem = jax.vmap(jax.vmap(each, (0, 0, 0)), (0, 0, None))(contacts, nxt, ts)
    motor = jax.vmap(jax.vmap(lambda p: sur.motor_check(ep, p)))(problem)  # (G, T): every step's
    return reward.with_motor(sur.reward_config, terms, jnp.where(ts == n_t - 1, motor, 0.0)), motor


def test_the_table_solves_the_motor_check_for_the_last_waypoint_only(sur, motor_episode):
    """`dp.grasp_terms` solves the motor check for the last waypoint's G arrivals alone (G solves in its program,
    against G x T for the step vmapped over t), and its terms and table equal the reference that solves every
    step's check and zeroes it before the last, and the surrogate's step vmapped (its `cond` a `select` there)."""
    ep = motor_episode
    contacts = jax.jit(lambda e: dp.realise_all(sur, e))(ep)
    got = jax.jit(lambda e, c: dp.grasp_terms(sur, e, c))(ep, contacts)
    want, every = jax.jit(lambda e, c: _every_step_checked(sur, e, c))(ep, contacts)
    n_t = ep.n_steps
    ts = jnp.arange(n_t)
    nxt = jax.tree.map(lambda x: x[:, jnp.minimum(ts + 1, n_t - 1)], contacts)
    stepped = jax.jit(jax.vmap(jax.vmap(lambda now, nx, t: sur.score(ep, t, ep.waypoints[t], ep.quats[t], now, nx,
                                                                     False), (0, 0, 0)), (0, 0, None)))(
        contacts, nxt, ts)
    threshold = sur.reward_config.motor_fall_unmet
    assert np.any(np.asarray(every[:, :-1]) > threshold)  # checked before the last step, it would drop grasps
    last = np.asarray(got.motor_unmet[:, -1])
    assert 0 < np.sum(last > threshold) < len(last)  # the last step's check drops some grasps and not others
    for ref in (want, stepped):
        np.testing.assert_array_equal(np.asarray(got.fall), np.asarray(ref.fall))
        np.testing.assert_array_equal(np.asarray(got.motor_unmet[:, :-1]), 0.0)
        # 150 APG iterations of one problem in batches of other shapes round apart by ~1e-5 (they converge to 5e-3)
        np.testing.assert_allclose(np.asarray(got.motor_unmet), np.asarray(ref.motor_unmet), atol=1e-4)
        np.testing.assert_allclose(np.asarray(got.reward), np.asarray(ref.reward), rtol=1e-6, atol=1e-6)
    table = jax.jit(lambda e, p, c: dp.table_from_terms(sur, e, p, c))
    new, old = table(ep, got, contacts), table(ep, want, contacts)
    np.testing.assert_array_equal(np.asarray(new.terminal), np.asarray(old.terminal))
    np.testing.assert_allclose(np.asarray(new.reward), np.asarray(old.reward), rtol=1e-6, atol=1e-6)
    iters = 43
    assert iters not in (sur.ik_config.iterations, sur.wrench_config.iterations)
    sur43 = sur.replace(reward=dataclasses.replace(sur.reward_config, motor_iterations=iters))
    count = lambda f, *args: _motor_problems(jax.make_jaxpr(f)(*args).jaxpr, iters)  # noqa: E731
    n_g = sur.space.n_grasps
    assert count(lambda e, c: dp.grasp_terms(sur43, e, c), ep, contacts) == n_g
    assert count(lambda e, c: _every_step_checked(sur43, e, c), ep, contacts) == n_g * n_t  # the counter counts
    assert count(lambda e: dp.build_table(sur43, e), scenario.make_episode()) == n_g


def test_batched_transitions_solve_the_motor_check_for_the_last_step_only(sur, motor_episode):
    """`Surrogate.transitions` (an episode's T steps in one batch: DP baseline's and RL's batched rollouts) equals
    `transition` vmapped over the steps, which solves every step's check (its `cond` a `select`); its program solves
    the check once, for the last step, against T."""
    ep = motor_episode
    n_t = ep.n_steps
    start = int(ep.start_grasp)
    actions = jnp.asarray([0, 3, 0][:n_t], jnp.int32)
    grasps = [start]
    for a in np.asarray(actions)[:-1]:
        grasps.append(int(sur.space.transitions[grasps[-1], a]))
    grasps = jnp.asarray(grasps, jnp.int32)
    ts = jnp.arange(n_t, dtype=jnp.int32)
    got = jax.jit(sur.transitions)(ep, grasps, actions)
    want = jax.jit(jax.vmap(sur.transition, (None, 0, 0, 0)))(ep, grasps, ts, actions)
    assert float(got[0].terms.motor_unmet[-1]) > 0  # the last step's check ran
    np.testing.assert_array_equal(np.asarray(got[0].terms.motor_unmet[:-1]), 0.0)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        if jnp.issubdtype(g.dtype, jnp.floating):  # the motor check's solve: see the test above
            np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-5, atol=1e-4)
        else:
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    iters = 43
    sur43 = sur.replace(reward=dataclasses.replace(sur.reward_config, motor_iterations=iters))
    count = lambda f, *args: _motor_problems(jax.make_jaxpr(f)(*args).jaxpr, iters)  # noqa: E731
    assert count(sur43.transitions, ep, grasps, actions) == 1
    assert count(jax.vmap(sur43.transition, (None, 0, 0, 0)), ep, grasps, ts, actions) == n_t


def test_vmapped_steps_solve_the_motor_check_only_where_a_row_is_last(sur, motor_episode):
    """Steps vmapped over states at several waypoints (a search's or a rollout's batch) solve the motor check under
    one `cond` on whether any row is at the last step (not a `select` that always runs it), also under nested vmaps,
    and equal steps taken one at a time: the check where t is last, 0 elsewhere, 0 for a batch with no last row."""
    ep = motor_episode
    last = ep.n_steps - 1
    grasps = jnp.asarray([3, 5, 7, 9], jnp.int32)
    actions = jnp.asarray([0, 2, 4, 0], jnp.int32)
    vstep = jax.jit(jax.vmap(sur.step))
    for ts in ([0, last, 1, last], [0, 1, 1, 0]):
        states = jax.vmap(sur.discrete_state, (None, 0, 0))(ep, grasps, jnp.asarray(ts, jnp.int32))
        got = vstep(states, actions)
        for i in range(len(ts)):
            one = jax.jit(sur.step)(jax.tree.map(lambda x, i=i: x[i], states), actions[i])
            np.testing.assert_allclose(float(got[0].terms.motor_unmet[i]), float(one[0].terms.motor_unmet), atol=1e-4)
            assert float(got[1][i]) == float(one[1]) and bool(got[2][i]) == bool(one[2])
        assert np.all((np.asarray(got[0].terms.motor_unmet) > 0) == (np.asarray(ts) == last))
    iters = 43
    sur43 = sur.replace(reward=dataclasses.replace(sur.reward_config, motor_iterations=iters))
    nested = jax.tree.map(lambda x: x.reshape((2, 2) + x.shape[1:]), states)
    for f, args in ((jax.vmap(sur43.step), (states, actions)),
                    (jax.vmap(jax.vmap(sur43.step)), (nested, actions.reshape(2, 2)))):
        jaxpr = jax.make_jaxpr(f)(*args).jaxpr
        assert _motor_problems(jaxpr, iters, in_cond=False) == 0
        assert _motor_problems(jaxpr, iters, in_cond=True) == len(ts)


def _brute_force_survival(reward, terminal, next_grasp, start, r_min):
    """The most steps survived (reward > r_min) over every action sequence from `start` (numpy enumeration)."""
    n_g, n_a, n_t = reward.shape
    n = np.arange(n_a**n_t)
    g, alive, total = np.full(n.shape, start), np.ones(n.shape, bool), np.zeros(n.shape)
    for t in range(n_t):
        a = (n // n_a ** (n_t - 1 - t)) % n_a
        total += alive & (reward[g, a, t] > r_min)
        alive &= ~terminal[g, a, t]
        g = next_grasp[g, a]
    return total.max()


@pytest.mark.parametrize("seed", range(4))
def test_longest_surviving_equals_brute_force(seed):
    """Random tables where a third of the entries fail (r_min, terminal): the sequence `longest_surviving` returns
    survives as many steps as the best of every sequence, and its own replay survives that many."""
    rng = np.random.default_rng(seed)
    n_g, n_a, n_t, r_min = 7, 4, 6, -200.0
    fails = rng.random((n_g, n_a, n_t)) < 0.33
    reward = np.where(fails, r_min, -rng.random((n_g, n_a, n_t))).astype(np.float32)
    terminal = fails | (np.arange(n_t) == n_t - 1)[None, None, :]
    next_grasp = rng.integers(0, n_g, (n_g, n_a)).astype(np.int32)
    table = dp.Table(reward=jnp.asarray(reward), next_grasp=jnp.asarray(next_grasp), terminal=jnp.asarray(terminal),
                     ik_error=jnp.zeros((n_g, n_t)), q=jnp.zeros((n_g, n_t, 1)))
    for start in range(n_g):
        sol = dp.longest_surviving(table, start, r_min)
        best = _brute_force_survival(reward, terminal, next_grasp, start, r_min)
        assert float(sol.ret) == best
        g, alive, survived = start, True, 0
        for t, a in enumerate(np.asarray(sol.actions)):
            if alive:
                survived += reward[g, a, t] > r_min
                alive = not terminal[g, a, t]
                g = next_grasp[g, a]
        assert survived == best
