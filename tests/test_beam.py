"""Tests of gsp_jax.planning.beam, the beam search over grasp changes (the planners `search`, `search-L1`): as wide as
the grasp space it is DP (its value and its plan's, in the table); narrower, it is the same search run on the DP table
by an independent numpy implementation (the forward beam, then the backup over the kept states); its rewards are the
table's; batched equals one at a time; a full layer counts what it leaves out; bad sizes are refused by name.

The properties hold for any model: the small test hand (27 grasps, 10 actions; tests/conftest.py), episodes of T = 5
waypoints, with the analytic surrogate and with an untrained hazard network as the learned term (expectimax: a
path's worth is its return plus its chance to hold times what follows)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tolerances as tol
from hazards import fitted
from gsp_jax.model import grasps, scenario
from gsp_jax.planning import beam, dp, evaluation, rollout
from gsp_jax.surrogate.reward import RewardConfig
from gsp_jax.surrogate.step import Surrogate

T = 5
NARROW = 2  # grasps a narrow beam keeps: well below the 27 grasps, so it prunes


@pytest.fixture(scope="module")
def case(small_sur, small_episodes, solve_each):
    """(surrogates {name: Surrogate}, episodes stacked, {name: (tables, solutions)}): the analytic surrogate and one
    with an untrained hazard (fall chances spread over (0, 1), most below `risk_falls`)."""
    sur = small_sur
    with_term = sur.replace(reward=RewardConfig(risk_falls=0.95), learned=fitted(sur.model.digest, space=sur.space))
    eps = scenario.stack([small_episodes[n].head(T) for n in ("nominal", "mass1.5m0_comy+1cm")])
    surs = {"analytic": sur, "learned": with_term}
    return surs, eps, {k: solve_each(s, eps) for k, s in surs.items()}


def _one(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _reference(table: dp.Table, start: int, width: int, cap: float) -> float:
    """The same search on a DP table (numpy): forwards, per waypoint each successor's best parent by f = return so
    far + chance to hold so far x (T - t - 1) x max(the successor's null-action reward, -cap), the `width` best
    successors kept (ties: the lower grasp); backwards, the Bellman backup over the kept states. Its value."""
    r, nxt, term = (np.asarray(x, np.float64) for x in (table.reward, table.next_grasp, table.terminal))
    nxt, term = nxt.astype(int), term.astype(bool)
    risk = np.zeros_like(r) if table.fall_risk is None else np.asarray(table.fall_risk, np.float64)
    n_g, _, n_t = r.shape
    g, acc, reach, kept = np.array([start]), np.zeros(1), np.ones(1), [np.array([start])]
    for t in range(n_t - 1):
        gp, a2 = nxt[g], acc[:, None] + reach[:, None] * r[g, :, t]
        r2 = reach[:, None] * (1 - risk[g, :, t])
        h = (n_t - t - 1) * np.maximum(r[gp, grasps.NULL, t], -cap)
        f = np.where(term[g, :, t], -np.inf, a2 + r2 * h).ravel()
        gp, a2, r2 = gp.ravel(), a2.ravel(), r2.ravel()
        best = {}
        for i in np.flatnonzero(np.isfinite(f)):
            if gp[i] not in best or f[i] > f[best[gp[i]]]:
                best[gp[i]] = i
        order = sorted(best, key=lambda x: (-f[best[x]], x))[:width]
        if not order:
            break
        g = np.array(order)
        acc, reach = a2[[best[x] for x in order]], r2[[best[x] for x in order]]
        kept.append(g)
    value = np.full(n_g, -np.inf)
    for t in range(len(kept) - 1, -1, -1):
        g = kept[t]
        into = value[nxt[g]]
        q = np.where(term[g, :, t], r[g, :, t], r[g, :, t] + (1 - risk[g, :, t]) * np.where(np.isfinite(into), into, 0))
        q = np.where(term[g, :, t] | np.isfinite(into), q, -np.inf)
        value = np.full(n_g, -np.inf)
        value[g] = q.max(1)
    return float(value[start])


@pytest.mark.parametrize("name", ["analytic", "learned"])
def test_a_search_as_wide_as_the_grasp_space_is_dp(case, name):
    surs, eps, solved = case
    sur, (tables, sols) = surs[name], solved[name]
    n_g = sur.space.n_grasps
    found = beam.plan_batch(sur, eps, beam.BeamConfig(width=n_g, expand=n_g, fresh=n_g))
    np.testing.assert_allclose(np.asarray(found.ret), np.asarray(sols.ret), atol=tol.RETURN_ATOL)
    replayed = jax.vmap(dp.sequence_return)(tables, eps.start_grasp, found.actions)  # its plan, in the table
    np.testing.assert_allclose(np.asarray(replayed), np.asarray(sols.ret), atol=tol.RETURN_ATOL)
    assert int(jnp.sum(found.dropped)) == 0
    assert np.all(np.asarray(found.realised) <= 2 * n_g * T)  # each (grasp, waypoint) realised at most twice


def test_a_narrow_search_is_the_same_search_on_the_table(case):
    surs, eps, solved = case  # with the learned term: the analytic surrogate is its case of no fall chances
    sur, (tables, sols) = surs["learned"], solved["learned"]
    found = beam.plan_batch(sur, eps, beam.BeamConfig(width=NARROW))
    cap = sur.reward_config.max_step_cost
    for i in range(eps.mass.shape[0]):
        table, start = _one(tables, i), int(eps.start_grasp[i])
        np.testing.assert_allclose(float(found.ret[i]), _reference(table, start, NARROW, cap), atol=tol.RETURN_ATOL)
        assert float(found.ret[i]) <= float(sols.ret[i]) + tol.RETURN_ATOL  # never above the optimum
        # the plan's rewards and fall chances are the table's, and its return is its value
        actions = found.actions[i]
        rewards, ret, _ = dp.sequence_scores(table, start, actions)
        alive = np.asarray(found.alive[i])
        np.testing.assert_allclose(np.asarray(found.rewards[i])[alive], np.asarray(rewards)[alive],
                                   atol=tol.REWARD_ATOL)
        np.testing.assert_allclose(float(ret), float(found.ret[i]), atol=tol.RETURN_ATOL)
        along = np.asarray(table.next_grasp)[np.asarray(found.grasps[i][:-1]), np.asarray(actions)]
        np.testing.assert_array_equal(np.asarray(found.grasps[i][1:])[alive], along[alive])
    assert np.all(np.asarray(found.realised) < sur.space.n_grasps * T)  # fewer IK problems than the table's


def test_batched_equals_one_at_a_time_and_a_full_layer_counts_what_it_leaves(case):
    surs, eps, solved = case
    sur = surs["analytic"]
    tight = beam.BeamConfig(width=4, expand=sur.every_sizes[1], fresh=sur.every_sizes[1])
    batched = beam.plan_batch(sur, eps, tight)
    for i in range(eps.mass.shape[0]):
        one = beam.plan(sur, _one(eps, i), tight)
        np.testing.assert_allclose(float(one.ret), float(batched.ret[i]), atol=tol.RETURN_ATOL)
        np.testing.assert_array_equal(np.asarray(one.actions), np.asarray(batched.actions[i]))
        # what it kept it scored right: the plan's value is the plan's return in the table
        table = _one(solved["analytic"][0], i)
        np.testing.assert_allclose(float(dp.sequence_return(table, eps.start_grasp[i], one.actions)), float(one.ret),
                                   atol=tol.RETURN_ATOL)
    assert int(jnp.sum(batched.dropped)) > 0  # 4 grasps' successors do not fit one grasp's room


@pytest.mark.parametrize("field, value, match", [
    ("width", 0, "BeamConfig.width: a positive int, got 0"),
    ("width", 2.5, "BeamConfig.width: a positive int, got 2.5"),
    ("fresh", True, "BeamConfig.fresh: a positive int, got True"),
    ("expand", 2, "BeamConfig.expand: at least the"),
])
def test_bad_sizes_are_refused_by_name(small_sur, field, value, match):
    with pytest.raises(ValueError, match=match):
        beam.BeamConfig(**{field: value}).sizes(small_sur)


def test_a_space_beyond_the_table_is_planned_with_the_surrogate_s_own_rewards(table_ik):
    """The shipped five-fingered model with ten contact links (18,432 grasps: no table is built): the search plans an
    episode's first waypoints, and its plan's rewards are the surrogate's own, stepped one decision at a time."""
    sur = Surrogate("five", ik_config=table_ik)
    assert sur.space.n_grasps >= 10_000 and sur.learned is None
    ep = scenario.make_episode(model=sur.model).head(3)
    found = beam.plan(sur, ep, beam.BeamConfig(width=2))
    step, state, rewards = jax.jit(sur.step), sur.reset(ep), []
    for a, alive in zip(np.asarray(found.actions), np.asarray(found.alive)):
        if alive:
            state, r, _ = step(state, jnp.int32(a))
            rewards.append(float(r))
    assert rewards and rewards[0] > sur.reward_config.r_min  # a plan that holds at least its first step
    np.testing.assert_allclose(rewards, np.asarray(found.rewards)[:len(rewards)], atol=tol.REWARD_ATOL)
    assert int(found.grasps[len(rewards)]) == int(state.grasp)


@pytest.mark.parametrize("name", ["analytic", "learned"])
def test_a_sequence_is_scored_alike_with_and_without_a_table(case, name):
    """`rollout.sequence_scores` (the surrogate's steps, what `envelope` scores with where no table is built) against
    `dp.sequence_scores` (the table): rewards, expected return and chance to hold of the constant-tips sequence and of
    random ones, feasible and failing."""
    surs, eps, solved = case
    sur, tables = surs[name], solved[name][0]
    space, r_min = sur.space, sur.reward_config.r_min
    score = jax.jit(jax.vmap(lambda ep, a: rollout.sequence_scores(sur, ep, a)))
    for i in range(eps.mass.shape[0]):
        table, ep = _one(tables, i), _one(eps, i)
        keys = jax.random.split(jax.random.PRNGKey(i), 6)
        seqs = [jnp.asarray(evaluation.four_tips(space, T))]
        seqs += [dp.random_sequence(table, ep.start_grasp, k, r_min, hold) for k, hold in zip(keys, [0.0, 0.5] * 3)]
        seqs += [jnp.asarray(evaluation.one_tip(space, T))]  # drops the tool: ends early
        actions = jnp.stack(seqs)
        got = score(jax.tree.map(lambda x: jnp.broadcast_to(x, (len(seqs),) + x.shape), ep), actions)
        want = jax.vmap(dp.sequence_scores, (None, None, 0))(table, ep.start_grasp, actions)
        for g, w in zip(got, want):
            np.testing.assert_allclose(np.asarray(g), np.asarray(w), atol=T * tol.REWARD_ATOL)
