"""The DP policies through the common policy interface, rolled out in the surrogate itself."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tolerances as tol
from gsp_jax import dp, policies, scenario, surrogate


@pytest.fixture(scope="module")
def env():
    return surrogate.Surrogate()


@pytest.fixture(scope="module")
def solved(env):
    eps = scenario.stack([scenario.make_episode().head(4), scenario.make_episode(shift_mm=6, torque=-1.0).head(4)])
    tables, sols = jax.jit(jax.vmap(lambda e: dp.solve(env, e)))(eps)
    return eps, tables, sols


def test_dp_optimal_policy_rollout_earns_the_dp_value(env, solved):
    """TablePolicy(DP policy) stepped through the surrogate (not the table) earns the DP return, to the precision
    of the float32 solvers along two paths (tests/tolerances.py: a DP optimal return to RETURN_ATOL)."""
    eps, _, sols = solved
    ret, final = jax.jit(jax.vmap(lambda e, p: policies.rollout(env, policies.TablePolicy(p), e)))(eps, sols.policy)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(sols.ret), rtol=0, atol=tol.RETURN_ATOL)
    assert bool(jnp.all(final.done))


def test_dp_baseline_replays_a_sequence_and_never_beats_dp_optimal(env, solved):
    """SequencePolicy(nominal's optimal actions) on the other episode: its surrogate return equals the table
    replay (dp.sequence_return) and is at most that episode's DP optimum."""
    eps, tables, sols = solved
    other = jax.tree.map(lambda x: x[1], eps)
    table = jax.tree.map(lambda x: x[1], tables)
    base = policies.SequencePolicy(sols.actions[0])
    ret, _ = jax.jit(lambda e: policies.rollout(env, base, e))(other)
    replay = dp.sequence_return(table, other.start_grasp, sols.actions[0])
    np.testing.assert_allclose(float(ret), float(replay), rtol=0, atol=tol.RETURN_ATOL)
    assert float(ret) <= float(sols.ret[1]) + tol.RETURN_ATOL


def test_network_policy_acts_the_same_in_the_surrogate_and_the_table_env(env, solved):
    """The PPO actor as a policy (NetworkPolicy, after BC on the DP data set): its return stepped through the
    surrogate itself equals its greedy return in the table-backed GraspEnv, and BC makes it DP-optimal here."""
    from gsp_jax import pretrain
    from gsp_jax.env import GraspEnv
    from gsp_jax.ppo import networks as nets
    from gsp_jax.ppo import train as ppo

    eps, tables, sols = solved
    table_env = GraspEnv(env, eps, tables, auto_reset=False)
    networks = nets.make_networks(table_env.observation_size, table_env.action_size, nets.NetworkConfig(hidden=(64, 64)))
    data = pretrain.dp_dataset(env, eps, tables)
    params, _ = pretrain.pretrain(networks, data, pretrain.BCConfig(epochs=150, batch_size=64), jax.random.PRNGKey(0), progress=False)
    policy = policies.NetworkPolicy(params, networks, env.space)
    ret, _ = jax.jit(jax.vmap(lambda e: policies.rollout(env, policy, e)))(eps)
    greedy = jax.jit(lambda p: ppo.greedy_returns(table_env, networks, p))(params)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(greedy), rtol=0, atol=tol.RETURN_ATOL)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(sols.ret), rtol=0, atol=tol.RETURN_ATOL)
