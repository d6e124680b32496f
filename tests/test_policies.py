"""The DP policies through the common policy interface, rolled out in the surrogate itself (`lookahead.rollout`)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tolerances as tol
from gsp_jax.planning import dp, lookahead, policies
from gsp_jax.model import scenario


@pytest.fixture(scope="module")
def solved(sur, solve_each):
    eps = scenario.stack([scenario.make_episode().head(4), scenario.make_episode(shift_mm=6, torque=-1.0).head(4)])
    tables, sols = solve_each(sur, eps)
    return eps, tables, sols


def test_dp_optimal_policy_rollout_earns_the_dp_value(sur, solved):
    """TablePolicy(DP policy) stepped through the surrogate (not the table) earns the DP return, to the precision
    of the float32 solvers along two paths (tests/tolerances.py: a DP optimal return to RETURN_ATOL)."""
    eps, _, sols = solved
    run = jax.vmap(lambda e, p: lookahead.rollout(sur, policies.TablePolicy(p), sur.reset(e)))
    ret, final = jax.jit(run)(eps, sols.policy)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(sols.ret), rtol=0, atol=tol.RETURN_ATOL)
    assert bool(jnp.all(final.done))


def test_dp_baseline_replays_a_sequence_and_never_beats_dp_optimal(sur, solved):
    """SequencePolicy(nominal's optimal actions) on the other episode: its surrogate return equals the table
    replay (dp.sequence_return) and is at most that episode's DP optimum."""
    eps, tables, sols = solved
    other = jax.tree.map(lambda x: x[1], eps)
    table = jax.tree.map(lambda x: x[1], tables)
    base = policies.SequencePolicy(sols.actions[0])
    ret, _ = jax.jit(lambda e: lookahead.rollout(sur, base, sur.reset(e)))(other)
    replay = dp.sequence_return(table, other.start_grasp, sols.actions[0])
    np.testing.assert_allclose(float(ret), float(replay), rtol=0, atol=tol.RETURN_ATOL)
    assert float(ret) <= float(sols.ret[1]) + tol.RETURN_ATOL


def test_network_policy_acts_the_same_in_the_surrogate_and_the_table_env(sur, solved):
    """The PPO actor as a policy (NetworkPolicy, after BC on the DP data set): its return stepped through the
    surrogate itself equals its greedy return in the table-backed GraspEnv, and BC makes it DP-optimal here."""
    from gsp_jax.learning import pretrain
    from gsp_jax.learning.env import GraspEnv
    from gsp_jax.ppo import networks as nets
    from gsp_jax.ppo import train as ppo

    eps, tables, sols = solved
    table_env = GraspEnv(sur, eps, tables, auto_reset=False)
    networks = nets.make_networks(table_env.observation_size, table_env.action_size,
                                  nets.NetworkConfig(hidden=(64, 64)))
    data = pretrain.dp_dataset(sur, eps, tables)
    params, _ = pretrain.pretrain(networks, data, pretrain.BCConfig(epochs=150, batch_size=64), jax.random.PRNGKey(0),
                                  progress=False)
    policy = policies.NetworkPolicy(params, networks, sur.space)
    ret, _ = jax.jit(jax.vmap(lambda e: lookahead.rollout(sur, policy, sur.reset(e))))(eps)
    greedy = jax.jit(lambda p: ppo.greedy_returns(table_env, networks, p))(params)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(greedy), rtol=0, atol=tol.RETURN_ATOL)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(sols.ret), rtol=0, atol=tol.RETURN_ATOL)


def _early_end(table, start_grasp, first_action):
    """(T,) actions: `first_action`, then from the grasp it leads to the first action whose transition at waypoint 1
    fails (collision or fall), then null actions: an episode that ends before its last step."""
    g1 = int(table.next_grasp[start_grasp, first_action])
    fails = np.flatnonzero(np.asarray(table.terminal[g1, :, 1]))
    assert len(fails), "no failing action at waypoint 1 to end the episode early"
    return np.array([first_action, fails[0]] + [0] * (table.reward.shape[2] - 2), np.int32)


@pytest.mark.parametrize("kind,ahead", [("dp-base", 1), ("ends-early", 1), ("dp-opt", 1), ("dp-opt", 3), ("network", 1),
                                        ("network", 3)])
def test_batched_rollout_runs_the_episode_that_stepping_runs(sur, solved, kind, ahead):
    """`rollout_batched` (the chain of decisions, then every transition in one vmapped batch) against stepping the
    surrogate one decision at a time: the same actions, rewards to REWARD_ATOL, return, final grasp, waypoint, joint
    angles (Q_ATOL) and end. Open loop (DP baseline on the other episode; a sequence that fails at its second step)
    and closed loop (the DP policy over (grasp, t); a network acting on the continuous observation, compared only
    because its best logit leads the runner-up by more than twice what the joint angles' tolerance can move it); the
    closed-loop ones also with `ahead` = 3, each batch realising every state three decisions can reach (4 steps: a
    whole block, then a part of one)."""
    from gsp_jax.surrogate.observation import observation, observation_size
    from gsp_jax.ppo import networks as nets

    eps, tables, sols = solved
    ep, table = jax.tree.map(lambda x: x[1], (eps, tables))
    if kind == "network":
        networks = nets.make_networks(observation_size(sur.space, ep.n_steps, sur.hand.n_joints), sur.n_actions,
                                      nets.NetworkConfig(hidden=(32, 32)))
        # an initialisation whose greedy episode runs all four steps (most fall at the first) with clear margins
        policy = policies.NetworkPolicy(networks.init(jax.random.PRNGKey(19)), networks, sur.space)
    else:
        policy = {"dp-base": policies.SequencePolicy(sols.actions[0]), "dp-opt": policies.TablePolicy(sols.policy[1]),
                  "ends-early": policies.SequencePolicy(_early_end(table, int(ep.start_grasp),
                                                                   int(sols.actions[1][0])))}[kind]
    step, act = jax.jit(sur.step), jax.jit(lambda p, s: p.act(s))
    s, ret, n = jax.jit(sur.reset)(ep), 0.0, 0
    while not bool(s.done):
        if kind == "network":  # the greedy action must not hinge on last bits: its lead over the runner-up exceeds
            # what moving every observation component by Q_ATOL (the joint angles' tolerance) can take from it
            obs = observation(sur.space, s)
            logits = np.asarray(networks.logits(policy.params, obs))
            first, second = np.argsort(logits)[::-1][:2]
            jac = np.asarray(jax.jacfwd(lambda o: networks.logits(policy.params, o))(obs))
            reach = 2 * np.abs(jac[first] - jac[second]).sum() * tol.Q_ATOL
            assert logits[first] - logits[second] > reach, f"decision {n}: margin {logits[first] - logits[second]:.2e}"
        s, r, _ = step(s, act(policy, s))
        ret, n = ret + float(r), n + 1
    assert n == (2 if kind == "ends-early" else ep.n_steps)
    batched, final = jax.jit(lambda p, e: policies.rollout_batched(sur, p, e, ahead))(policy, ep)
    np.testing.assert_allclose(float(batched), ret, rtol=0, atol=tol.REWARD_ATOL * n)
    for f in ("grasp", "t", "done"):
        np.testing.assert_array_equal(np.asarray(getattr(final, f)), np.asarray(getattr(s, f)), err_msg=f)
    np.testing.assert_allclose(np.asarray(final.q), np.asarray(s.q), rtol=0, atol=tol.Q_ATOL)
