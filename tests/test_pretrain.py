"""Tests of gsp_jax.learning.pretrain: reachability against a brute-force BFS, Q-values against the DP backup, the
behaviour-cloning data set against the DP solution it is drawn from, and behaviour cloning itself.

The nominal episode's full table (all 16 waypoints) is built once per module; the BFS also runs on synthetic
tables over the real grasp space with many terminal transitions (no IK).
"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.learning import pretrain  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.ppo import networks as nets  # noqa: E402


def _np(tree):
    return jax.tree.map(np.asarray, tree)


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def nominal(sur, solve_each):
    """The nominal episode (stacked, N = 1), its table (built once), and the table's DP solution (numpy)."""
    episodes = scenario.stack([scenario.make_episode()])
    tables, sols = solve_each(sur, episodes)
    table, sol = (jax.tree.map(lambda x: x[0], tree) for tree in (tables, sols))
    return dict(episodes=episodes, tables=tables, table=_np(table), sol=_np(sol), start=int(episodes.start_grasp[0]))


@pytest.fixture(scope="module")
def dataset(sur, nominal):
    return pretrain.dp_dataset(sur, nominal["episodes"], nominal["tables"])


def _synthetic_table(space, n_t, p_terminal, seed) -> dp.Table:
    """Random rewards, the real grasp space's transitions, each (g, a, t) terminal with probability p_terminal
    (and every transition of the last step)."""
    rng = np.random.default_rng(seed)
    g_n, a_n = space.n_grasps, space.n_actions
    nxt = np.asarray(space.apply(jnp.arange(g_n)[:, None], jnp.arange(a_n)[None])[0], np.int32)
    terminal = rng.random((g_n, a_n, n_t)) < p_terminal
    terminal[:, :, -1] = True
    return dp.Table(
        reward=rng.normal(size=(g_n, a_n, n_t)).astype(np.float32),
        next_grasp=nxt,
        terminal=terminal,
        ik_error=np.zeros((g_n, n_t), np.float32),
        q=np.zeros((g_n, n_t, 16), np.float32),  # joint angles (J = 16)
    )


def _bfs(table, start: int) -> np.ndarray:
    """(G, T) bool by breadth-first search in plain Python: layer t + 1 holds next_grasp[g, a] for every g of
    layer t and every action a whose transition at t does not end the episode."""
    g_n, a_n, n_t = np.shape(table.reward)
    nxt, term = np.asarray(table.next_grasp), np.asarray(table.terminal)
    reach = np.zeros((g_n, n_t), bool)
    layer = {start}
    for t in range(n_t):
        for g in layer:
            reach[g, t] = True
        layer = {int(nxt[g, a]) for g in layer for a in range(a_n) if not term[g, a, t]}
    return reach


# ------------------------------------------------------------------------------------------ 1. reachable
@pytest.mark.parametrize("p_terminal,seed", [(0.6, 0), (0.85, 1), (0.95, 3)])
def test_reachable_matches_bfs_on_synthetic_tables(sur, p_terminal, seed):
    """pretrain.reachable equals a brute-force BFS on random tables with many terminal transitions, from two
    start grasps."""
    table = _synthetic_table(sur.space, 6, p_terminal, seed)
    jt = jax.tree.map(jnp.asarray, table)
    for start in (0, 157):
        want = _bfs(table, start)
        got = np.asarray(pretrain.reachable(jt, jnp.int32(start)))
        assert got.shape == want.shape
        np.testing.assert_array_equal(got, want, err_msg=f"p_terminal {p_terminal}, start {start}")
        # non-vacuous: the start is alone at t = 0, and the sets are neither empty nor full later on
        assert want[:, 0].sum() == 1 and 0 < want[:, 1:].sum() < want[:, 1:].size


def test_reachable_matches_bfs_on_the_nominal_table(nominal):
    """On the nominal episode's real table (collisions and falls as terminals), reachable equals the BFS."""
    want = _bfs(nominal["table"], nominal["start"])
    got = np.asarray(pretrain.reachable(jax.tree.map(jnp.asarray, nominal["table"]), jnp.int32(nominal["start"])))
    np.testing.assert_array_equal(got, want)
    assert 0 < want.sum() < want.size  # some grasps unreachable (terminal transitions cut them off)


# ------------------------------------------------------------------------------------------ 2. q_values
def test_q_values_are_consistent_with_the_backup(nominal):
    """Q = q_values(table, backup): equals the Bellman right-hand side computed in float64 numpy, its max over
    actions is the backup's value[:, :T], and the DP policy's action attains the max (ties allowed)."""
    table, sol = nominal["table"], nominal["sol"]
    n_t = table.reward.shape[2]
    q = np.asarray(pretrain.q_values(jax.tree.map(jnp.asarray, table), jax.tree.map(jnp.asarray, sol)))
    v = sol.value.astype(np.float64)
    ref = table.reward + np.where(table.terminal, 0.0, v[table.next_grasp][:, :, 1 : n_t + 1])
    np.testing.assert_allclose(q, ref, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(q.max(axis=1), sol.value[:, :n_t], rtol=1e-6, atol=1e-4)
    chosen = np.take_along_axis(q, sol.policy[:, None, :], axis=1)[:, 0]
    np.testing.assert_allclose(chosen, q.max(axis=1), rtol=0, atol=1e-5)
    unique = (q >= q.max(axis=1, keepdims=True) - 1e-5).sum(axis=1) == 1
    np.testing.assert_array_equal(np.argmax(q, axis=1)[unique], sol.policy[unique])
    alive = sol.value[:, :n_t] > table.reward.min()  # (g, t) from which some sequence holds the tool
    assert unique[alive].mean() > 0.5  # most of them have a single optimal action, so the argmax check bites


# ------------------------------------------------------------------------------------------ 3. dp_dataset
def _decode(sur, obs, n_t):
    """(grasp, t, q) of each observation: the per-link one-hots (grasp), the time one-hot, the joint angles."""
    space = sur.space
    obs = np.asarray(obs)
    options, k = [], 0
    for n in space.n_options:
        block = obs[:, k : k + n]
        assert np.all(block.sum(axis=1) == 1)  # exactly one option per link
        options.append(block.argmax(axis=1))
        k += n
    grasp = np.asarray(space.encode(np.stack(options, axis=1)))
    t_hot = obs[:, k : k + n_t]
    assert np.all(t_hot.sum(axis=1) == 1)
    j = k + n_t + 1
    return grasp, t_hot.argmax(axis=1), obs[:, j : j + sur.hand.n_joints]


def test_dp_dataset_is_the_dp_solution_on_reachable_states(sur, nominal, dataset):
    """The data set's states (grasp and t decoded from the observations) are exactly the BFS-reachable states,
    once each; actions are the DP policy there, values the DP values, the `optimal` mask the actions whose Q
    attains the value; the start state is present with value = the DP return; the observations carry the
    table's joint angles."""
    table, sol, start = nominal["table"], nominal["sol"], nominal["start"]
    n_t = table.reward.shape[2]
    grasp, t, q = _decode(sur, dataset.obs, n_t)
    np.testing.assert_array_equal(t, np.asarray(dataset.t))
    states = set(zip(grasp.tolist(), t.tolist()))
    assert len(states) == dataset.size, "a state appears twice"
    reach = _bfs(table, start)
    assert states == set(zip(*map(lambda x: x.tolist(), np.nonzero(reach)))), "not the reachable states"
    np.testing.assert_array_equal(np.asarray(dataset.action), sol.policy[grasp, t])
    np.testing.assert_allclose(np.asarray(dataset.value), sol.value[grasp, t], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(dataset.episode), 0)
    np.testing.assert_allclose(q, table.q[grasp, t], rtol=0, atol=1e-6)
    v = sol.value.astype(np.float64)
    qv = table.reward + np.where(table.terminal, 0.0, v[table.next_grasp][:, :, 1 : n_t + 1])  # (G, A, T)
    want_opt = qv[grasp, :, t] >= sol.value[grasp, t][:, None] - 1e-6
    np.testing.assert_array_equal(np.asarray(dataset.optimal), want_opt)
    assert np.all(np.take_along_axis(np.asarray(dataset.optimal), np.asarray(dataset.action)[:, None], 1))
    first = np.flatnonzero((grasp == start) & (t == 0))
    assert first.size == 1 and np.sum(t == 0) == 1  # the start is the only state at t = 0
    np.testing.assert_allclose(float(dataset.value[first[0]]), float(sol.ret), rtol=0, atol=1e-6)
    assert float(sol.ret) > -sur.reward_config.max_step_cost * n_t  # the nominal start survives the episode


# ------------------------------------------------------------------------------------------ 4. BC
def test_behaviour_cloning_fits_the_dp_dataset(dataset):
    """pretrain() on the nominal DP data set: exact DP-action accuracy > 95% (greedy actions from the logits,
    counted here) and the critic's value RMSE [reward units] below a tenth of the values' spread (a constant
    predictor's RMSE is the spread); the history's last metrics agree with these."""
    cfg = pretrain.BCConfig(epochs=300, batch_size=128, learning_rate=1e-3, reward_scale=0.1)
    networks = nets.make_networks(dataset.obs.shape[1], 17, nets.NetworkConfig(hidden=(64, 64, 64)))
    params, history = pretrain.pretrain(networks, dataset, cfg, jax.random.PRNGKey(0), progress=False)
    logits = np.asarray(networks.logits(params, dataset.obs))
    accuracy = float(np.mean(np.argmax(logits, axis=1) == np.asarray(dataset.action)))
    value = np.asarray(networks.value(params, dataset.obs)) / cfg.reward_scale
    target = np.asarray(dataset.value)
    rmse, spread = float(np.sqrt(np.mean((value - target) ** 2))), float(np.std(target))
    optimal = float(np.mean(np.take_along_axis(np.asarray(dataset.optimal), np.argmax(logits, axis=1)[:, None], 1)))
    n_opt = np.asarray(dataset.optimal).sum(1)
    print(f"BC accuracy {accuracy:.3f}, optimal {optimal:.3f}, "
          f"states with several optimal actions {np.mean(n_opt > 1):.3f}")
    assert accuracy > 0.95, f"BC accuracy {accuracy:.3f} (any optimal action {optimal:.3f}) on {dataset.size} DP states"
    assert rmse < 0.1 * spread, f"critic RMSE {rmse:.3f} vs value spread (std) {spread:.3f}"
    assert history[-1]["epoch"] == cfg.epochs
    np.testing.assert_allclose(history[-1]["accuracy"], accuracy, atol=1e-6)
    np.testing.assert_allclose(history[-1]["value_rmse"], rmse, rtol=1e-3)
    assert history[0]["accuracy"] < accuracy  # it learned (the first record is after 10 epochs)
