"""The learned physics term inside the surrogate (`Surrogate(learned=...)`, `reward.with_risk`): the DP table, the
surrogate's step and the corpus's offline returns (`learned.returns`) agree on it; a hazard of zero leaves the
analytic reward as it was; it is finite for every valid episode (fuzz); weights of another model, or none, are
refused by name.

The agreement and the expectimax backup hold for any model: they run on the small test hand (`models/testhand`:
27 grasps, 10 actions; tests/conftest.py); the fuzz is the shipped model's, over its corpus distribution."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tolerances as tol
from hazards import fitted as _fitted
from gsp_jax.planning import dp, evaluation, lookahead, policies
from gsp_jax.model import scenario
from gsp_jax.surrogate import learned, reward
from gsp_jax.learning.env import GraspEnv
from gsp_jax.model import load as model_lib
from gsp_jax.physics import corpus
from gsp_jax.surrogate.reward import RewardConfig
from gsp_jax.surrogate.step import Surrogate

T = 3  # waypoints of the episodes here (the first three of drawn ones)


def _episodes(n: int, seed: int = 3) -> list[scenario.Episode]:
    return [e.head(T) for e in corpus.draw(corpus.Distribution(), seed, n).values()]


@pytest.fixture(scope="module")
def case(small_sur, small_episodes):
    """One episode of the small hand where sequences hold in the analytic surrogate (1.5 times the mass, the centre
    of mass 1 cm off), a surrogate with an untrained hazard (fall chances spread over (0, 1), most below
    `risk_falls`), and its DP table with and without the term."""
    sur = small_sur
    with_term = sur.replace(reward=RewardConfig(risk_falls=0.95), learned=_fitted(sur.model.digest, space=sur.space))
    ep = small_episodes["mass1.5m0_comy+1cm"].head(T)
    build = jax.jit(dp.build_table)
    return with_term, ep, build(with_term, ep), build(with_term.analytic, ep)


def test_the_table_the_step_and_the_offline_returns_agree_on_the_learned_term(case):
    with_term, ep, table, plain = case
    cfg, space = with_term.reward_config, with_term.space
    keys = jax.random.split(jax.random.PRNGKey(0), 6)
    seqs = [np.asarray(evaluation.four_tips(space, T))]
    seqs += [np.asarray(dp.random_sequence(plain, ep.start_grasp, k, cfg.r_min, 0.5)) for k in keys]
    step = jax.jit(with_term.step)
    checked = 0
    for actions in seqs:
        grasp, grasps_along = ep.start_grasp, []  # the new grasp of each transition
        for a in actions:
            grasp = space.apply(grasp, a)[0]
            grasps_along.append(grasp)
        x = np.asarray(learned.inputs(corpus.features(with_term, ep, jnp.asarray(actions)), jnp.stack(grasps_along),
                                      space))[None]  # the analytic features and the new grasps: the network's inputs
        p = np.asarray(learned.hazard(with_term.learned, x))
        offline, feasible = learned.returns(x, p, cfg)
        in_table = np.asarray(dp.sequence_rewards(table, ep.start_grasp, jnp.asarray(actions)))
        table_return = float(dp.sequence_return(table, ep.start_grasp, jnp.asarray(actions)))
        state, stepped, risks, alive = with_term.reset(ep), [], [], []
        for a in actions:
            alive.append(not bool(state.done))
            state, r, _ = step(state, jnp.int32(a))
            stepped.append(float(r))
            risks.append(float(state.terms.fall_risk))
        step_return = float(reward.expected_return(jnp.asarray(stepped), jnp.asarray(risks), jnp.asarray(alive)))
        if np.all(np.abs(p - cfg.risk_falls) > 1e-3):  # a discrete outcome only where its margin is clear
            assert bool(feasible[0]) == bool(np.all(in_table > cfg.r_min)), (actions, p)
            np.testing.assert_allclose(table_return, offline[0], atol=T * tol.REWARD_ATOL)
            np.testing.assert_allclose(step_return, offline[0], atol=T * tol.REWARD_ATOL)
            scored = dp.sequence_scores(table, ep.start_grasp, jnp.asarray(actions))  # one replay for all three
            np.testing.assert_allclose(scored[0], in_table, atol=1e-6)
            np.testing.assert_allclose(scored[1], table_return, atol=1e-5)
            np.testing.assert_allclose(scored[2], np.prod(np.where(alive, 1 - np.asarray(risks), 1.0)), atol=1e-5)
            checked += 1
    assert checked >= 4
    # the term costs: a step's expected reward is at most its analytic one
    assert np.all(np.asarray(table.reward) <= np.asarray(plain.reward) + tol.REWARD_ATOL)
    # a hazard of (almost) zero leaves the analytic table as it was
    zero = jax.jit(dp.build_table)(with_term.replace(learned=_fitted(with_term.model.digest, -60.0,
                                                                     space=with_term.space)), ep)
    np.testing.assert_allclose(np.asarray(zero.reward), np.asarray(plain.reward), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(zero.terminal), np.asarray(plain.terminal))


def test_the_learned_term_is_finite_for_every_valid_episode(table_ik):
    """Fuzz: drawn episodes at the distribution's corners and inside it, and the shipped model's extremes; every
    table entry finite, and the run's learned fall chances in [0, 1]."""
    sur = Surrogate(ik_config=table_ik, learned=False)
    with_term = sur.replace(learned=_fitted(sur.model.digest, seed=1))
    d = corpus.Distribution()

    def corner(lo):
        return {f: ((v[0], v[0] + 0.02 * (v[1] - v[0])) if lo else (v[1] - 0.02 * (v[1] - v[0]), v[1]))
                for f, v in vars(d).items()}

    eps = _episodes(2, seed=11)
    for seed, lo in ((5, True), (6, False)):
        eps += [e.head(T) for e in corpus.draw(corpus.Distribution(**corner(lo)), seed, 2, sur.model).values()]
    tables = jax.jit(dp.build_tables)(with_term, scenario.stack(eps))
    assert np.all(np.isfinite(np.asarray(tables.reward)))
    assert np.all(np.asarray(tables.reward) >= with_term.reward_config.r_min)


def test_weights_of_another_model_or_none_are_refused_by_name(tmp_path):
    from experiments import cli

    wrench = model_lib.load_model("wrench")
    with pytest.raises(learned.LearnedTermError, match=r"fitted for another model .*not 'hammer'"):
        Surrogate("hammer", learned=_fitted(wrench.digest))
    path = learned.save(_fitted(wrench.digest), tmp_path / "w.npz")
    with pytest.raises(learned.LearnedTermError, match=r"fitted for another model .*not 'hammer'"):
        Surrogate("hammer", learned=path)
    assert Surrogate("wrench", learned=path).learned_tag == learned.tag(_fitted(wrench.digest))
    with pytest.raises(learned.LearnedTermError, match=r"fitted on inputs \['t', .*'lateral'\], not \['t', "):
        Surrogate("wrench", learned=_fitted(wrench.digest).replace(features=learned.FEATURES))  # no grasp inputs
    if not learned.path_of(model_lib.load_model("hammer")).exists():
        with pytest.raises(learned.LearnedTermError, match=r"model 'hammer' has no learned physics term .*calibrate "
                                                           r"--learn --model"):
            Surrogate("hammer", learned=True)
        with pytest.raises(SystemExit, match=r"--learned: model 'hammer' has no learned physics term"):
            cli.main(["dp", "--model", "hammer", "--learned"])
    assert model_lib.load_model().name == model_lib.DEFAULT  # a command's --model leaves no process-wide model


def test_dp_and_lookahead_back_up_the_learned_term_as_expectimax(case):
    """With the term each step is a chance node (a fall of chance p ends the run at r_min): the DP's optimal value
    from the start grasp equals the best expected return over every action sequence, enumerated
    (`dp.sequence_return`, itself checked against every fall time in tests/test_reward.py); the full-depth lookahead
    on the episode's table finds that value; the PPO environment's running return is the expected one; a zero
    hazard leaves them the plain sums (tests/test_dp.py)."""
    with_term, ep, table, _ = case
    space = with_term.space
    assert table.fall_risk is not None and float(jnp.max(jnp.where(table.terminal, 0.0, table.fall_risk))) > 0.1
    sol = dp.backup(table, ep.start_grasp)
    n_a = space.n_actions
    every = jnp.stack(jnp.meshgrid(*[jnp.arange(n_a, dtype=jnp.int32)] * T, indexing="ij"), -1).reshape(-1, T)
    enumerated = jax.jit(jax.vmap(dp.sequence_return, (None, None, 0)))(table, ep.start_grasp, every)
    np.testing.assert_allclose(float(sol.ret), float(jnp.max(enumerated)), atol=T * tol.REWARD_ATOL)
    np.testing.assert_allclose(float(dp.sequence_return(table, ep.start_grasp, sol.actions)), float(sol.ret),
                               atol=T * tol.REWARD_ATOL)
    # the plain sum of the same rewards is another number where the term has a chance of a fall
    assert abs(float(jnp.sum(sol.rewards)) - float(sol.ret)) > 10 * T * tol.REWARD_ATOL
    model = dp.TableModel(table, space)
    plan = lookahead.search(model, model.reset(ep), policies.SequencePolicy(sol.actions), depth=T)
    np.testing.assert_allclose(float(plan.value), float(sol.ret), atol=T * tol.REWARD_ATOL)
    env = GraspEnv(with_term, scenario.stack([ep]), tables=jax.tree.map(lambda x: x[None], table), auto_reset=False)
    state = env.reset_to(0)
    for a in sol.actions:
        state = env.step(state, a)
    np.testing.assert_allclose(float(state.info["return"]), float(sol.ret), atol=T * tol.REWARD_ATOL)
