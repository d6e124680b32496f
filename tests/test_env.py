"""Tests of gsp_jax.learning.env (the brax `GraspEnv`); its Gymnasium views are tested in test_gym.py.

Everything runs on a set of three reduced episodes (the first T = 3 waypoints of the nominal lift, of a +6 mm
shift with -1 N m, and of an evaluation-set-B episode), whose DP tables are built once per module. The surrogate
backend (two IK and three wrench solves per step) is compiled once, vmapped over N_ENVS environments, for the
step-for-step comparison with the table backend; every other test uses the cheap table backend.
"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import tolerances as tol  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.learning.env import GraspEnv  # noqa: E402

T = 3  # waypoints of the reduced episodes
N_ENVS = 12  # vmapped environments of the backend comparison
N_STEPS = 10  # steps of the backend comparison (several episodes per environment, auto-reset on)


def _np(tree):
    return jax.tree.map(np.asarray, tree)


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def episodes():
    """Three reduced episodes, stacked (leaves (3, ...))."""
    return scenario.stack(
        [
            scenario.make_episode().head(T),
            scenario.make_episode(shift_mm=6, torque=-1.0).head(T),
            scenario.eval_set_b()["mass1.5m0_comy+1cm"].head(T),
        ]
    )


@pytest.fixture(scope="module")
def solved(sur, episodes, solve_each):
    """The DP tables and solutions of the three episodes, built exactly once for this module (one episode at a time,
    as `gym_env.make_grasp_env` builds test_gym's: the same program)."""
    return solve_each(sur, episodes)


@pytest.fixture(scope="module")
def tables(solved):
    return solved[0]


@pytest.fixture(scope="module")
def solutions(solved):
    """The DP solutions of the three tables (numpy, leaves (N, ...))."""
    return _np(solved[1])


@pytest.fixture(scope="module")
def policy(solutions):
    """(N, G, T) DP-optimal actions per episode: lets rollouts survive past the first step (most random actions
    drop the tool at once)."""
    return solutions.policy


@pytest.fixture(scope="module")
def table_env(sur, episodes, tables):
    return GraspEnv(sur, episodes, tables=tables)


@pytest.fixture(scope="module")
def table_fns(table_env):
    """The table backend's compiled single and vmapped reset/step (compiled once, reused)."""
    return dict(
        reset=jax.jit(table_env.reset),
        reset_to=jax.jit(table_env.reset_to),
        step=jax.jit(table_env.step),
        vreset=jax.jit(jax.vmap(table_env.reset)),
        vstep=jax.jit(jax.vmap(table_env.step)),
    )


def _actions(rng, state, policy, p_optimal=0.6):
    """Per environment: the DP-optimal action of its (episode, grasp, t) with probability p_optimal, else a
    uniformly random one. Computed in numpy from the state, so both backends get the same actions."""
    ep = np.asarray(state.info["episode_index"])
    sim = state.pipeline_state
    g, t = np.asarray(sim.grasp), np.minimum(np.asarray(sim.t), T - 1)
    optimal = policy[ep, g, t]
    random = rng.integers(0, 17, size=ep.shape)
    return np.where(rng.random(ep.shape) < p_optimal, optimal, random).astype(np.int32)


# ------------------------------------------------------------------------------------------ 1. backends
def test_table_backend_equals_surrogate_backend_step_for_step(sur, episodes, table_fns, policy):
    """Two GraspEnvs over the same episodes (tables vs surrogate), same reset keys and actions, auto-reset on:
    rewards, done, episode index, running return, grasp, t and observations agree at every step, across
    several episodes per environment."""
    sur_env = GraspEnv(sur, episodes)  # no tables: IK and wrench solves every step
    assert sur_env.backend == "surrogate"
    vreset_s, vstep_s = jax.jit(jax.vmap(sur_env.reset)), jax.jit(jax.vmap(sur_env.step))
    keys = jax.random.split(jax.random.PRNGKey(5), N_ENVS)
    a, b = table_fns["vreset"](keys), vreset_s(keys)
    rng = np.random.default_rng(0)
    done, times, rewards, visited = [], [], [], set()
    for step in range(N_STEPS + 1):
        msg = f"step {step}"
        # tolerances from the solvers' float32 precision (tests/tolerances.py); a return sums up to T rewards
        tol.assert_close_with_rare_ties(a.reward, b.reward, tol.REWARD_ATOL, msg)
        np.testing.assert_array_equal(a.done, b.done, err_msg=msg)
        np.testing.assert_array_equal(a.info["episode_index"], b.info["episode_index"], err_msg=msg)
        tol.assert_close_with_rare_ties(a.info["return"], b.info["return"], T * tol.REWARD_ATOL, msg)
        tol.assert_close_with_rare_ties(a.metrics["episode_return"], b.metrics["episode_return"], T * tol.REWARD_ATOL,
                                        msg)
        np.testing.assert_array_equal(a.pipeline_state.grasp, b.pipeline_state.grasp, err_msg=msg)
        np.testing.assert_array_equal(a.pipeline_state.t, b.pipeline_state.t, err_msg=msg)
        tol.assert_close_with_rare_ties(a.obs, b.obs, tol.Q_ATOL, msg)  # the joint angles are the imprecise part
        done.append(np.asarray(a.done))
        times.append(np.asarray(a.pipeline_state.t))
        rewards.append(np.asarray(a.reward))
        visited |= set(np.asarray(a.info["episode_index"]).tolist())
        if step < N_STEPS:
            act = jnp.asarray(_actions(rng, a, policy))
            a, b = table_fns["vstep"](a, act), vstep_s(b, act)
    # non-vacuous: episodes ended (auto-reset exercised) and others went on to later waypoints; both failing
    # and surviving steps; every episode of the set was visited
    assert np.sum(done) >= N_ENVS and np.sum(np.asarray(times) == T - 1) >= N_ENVS
    rewards, r_min = np.asarray(rewards[1:]), sur.reward_config.r_min
    assert np.any(rewards == r_min) and np.any(rewards > r_min)
    assert visited == {0, 1, 2}


# ------------------------------------------------------------------------------------------ 2. auto-reset
def test_auto_reset_cycles_episodes_and_reports_the_return(table_env, table_fns, episodes, policy):
    """After an episode ends the next state is episode (i + 1) mod N at t = 0 with its start grasp and a zero
    running return; metrics['episode_return'] at the done step is the sum of that episode's rewards (summed here,
    step by step)."""
    n = table_env.n_episodes
    start = np.asarray(episodes.start_grasp)
    rng = np.random.default_rng(1)
    state = table_fns["reset"](jax.random.PRNGKey(3))
    visited, ended, total = [int(state.info["episode_index"])], 0, 0.0
    for step in range(40):
        ep = int(state.info["episode_index"])
        act = jnp.asarray(_actions(rng, jax.tree.map(lambda x: x[None], state), policy)[0])
        state = table_fns["step"](state, act)
        total += float(state.reward)
        if bool(state.done):
            ended += 1
            np.testing.assert_allclose(float(state.metrics["episode_return"]), total, rtol=1e-6, atol=1e-5)
            assert int(state.info["episode_index"]) == (ep + 1) % n, (
                f"step {step}: {ep} -> {int(state.info['episode_index'])}")
            assert int(state.pipeline_state.t) == 0 and not bool(state.pipeline_state.done)
            assert int(state.pipeline_state.grasp) == start[(ep + 1) % n]
            assert float(state.info["return"]) == 0.0
            np.testing.assert_array_equal(state.obs, table_fns["reset_to"](jnp.int32((ep + 1) % n)).obs)
            visited.append(int(state.info["episode_index"]))
            total = 0.0
        else:
            assert int(state.info["episode_index"]) == ep
            np.testing.assert_allclose(float(state.info["return"]), total, rtol=1e-6, atol=1e-5)
    assert ended >= n + 1 and set(visited) == set(range(n))  # the whole set was cycled


# ------------------------------------------------------------------------------------------ 3. absorbing
def test_without_auto_reset_a_finished_state_is_absorbing(sur, episodes, tables, policy):
    """auto_reset=False: once done, further steps (any action) give reward 0 and leave the state, observation,
    episode index and return unchanged."""
    env = GraspEnv(sur, episodes, tables=tables, auto_reset=False)
    step = jax.jit(env.step)
    for ep in range(env.n_episodes):
        state = env.reset_to(ep)
        g = int(state.pipeline_state.grasp)
        for t in range(T):  # the DP-optimal sequence: survives to the last waypoint
            state = step(state, jnp.int32(policy[ep, g, t]))
            g = int(state.pipeline_state.grasp)
        assert bool(state.done) and int(state.pipeline_state.t) == T
        for a in (0, 7, 15):
            after = step(state, jnp.int32(a))
            assert float(after.reward) == 0.0 and bool(after.done)
            for x, y in zip(jax.tree.leaves(after.pipeline_state), jax.tree.leaves(state.pipeline_state)):
                np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(after.obs, state.obs)
            assert int(after.info["episode_index"]) == ep
            assert float(after.info["return"]) == float(state.info["return"])
    # a failing first step also ends the episode and is absorbing at t = 1
    state = env.reset_to(0)
    failing = int(np.argmin(np.asarray(tables.reward[0, int(episodes.start_grasp[0]), :, 0])))
    state = step(state, jnp.int32(failing))
    assert bool(state.done) and int(state.pipeline_state.t) == 1
    assert float(step(state, jnp.int32(3)).reward) == 0.0


# ------------------------------------------------------------------------------------------ 4. brax API
def test_brax_interface_sizes_and_backends(sur, episodes, table_env, table_fns):
    """observation_size equals the observation's length (both backends), action_size = 17 = the grasp space's
    actions, and backend names the stepping method."""
    sur_env = GraspEnv(sur, episodes)
    state = table_fns["reset"](jax.random.PRNGKey(0))
    abstract = jax.eval_shape(sur_env.reset, jax.random.PRNGKey(0))  # traced only: no IK runs
    assert table_env.observation_size == state.obs.shape[-1] == abstract.obs.shape[-1] == sur_env.observation_size
    assert table_env.action_size == sur_env.action_size == sur.space.n_actions == 17
    assert (table_env.backend, sur_env.backend) == ("table", "surrogate")
    assert table_env.n_episodes == 3 and table_env.n_steps == T
    assert state.obs.dtype == jnp.float32 and state.reward.shape == () and state.done.dtype == jnp.bool_


def test_vmapped_reset_and_step_equal_single_calls(table_fns, policy):
    """jax.vmap(reset) / vmap(step) over a batch give, leaf for leaf, the single-environment calls in a loop."""
    keys = jax.random.split(jax.random.PRNGKey(9), 6)
    batch = table_fns["vreset"](keys)
    singles = [table_fns["reset"](k) for k in keys]
    rng = np.random.default_rng(2)
    for step in range(4):
        for i, s in enumerate(singles):
            for x, y in zip(jax.tree.leaves(jax.tree.map(lambda v: v[i], batch)), jax.tree.leaves(s)):
                np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-6, err_msg=f"step {step}, env {i}")
        act = _actions(rng, batch, policy, p_optimal=0.5)
        batch = table_fns["vstep"](batch, jnp.asarray(act))
        singles = [table_fns["step"](s, jnp.int32(a)) for s, a in zip(singles, act)]
    # the batch is not trivially uniform: the keys picked different episodes
    assert len(set(np.asarray(table_fns["vreset"](keys).info["episode_index"]).tolist())) > 1


# ------------------------------------------------------------------------------------------ 5. bad input
def test_bad_input_raises_naming_the_field(sur, episodes, tables):
    """An unstacked episode set is refused naming episodes.waypoints; tables whose leading axis is not the number
    of episodes naming tables.reward."""
    single = scenario.make_episode().head(T)
    with pytest.raises(ValueError, match=r"episodes\.waypoints"):
        GraspEnv(sur, single)
    two = jax.tree.map(lambda x: x[:2], tables)
    with pytest.raises(ValueError, match=r"tables\.reward"):
        GraspEnv(sur, episodes, tables=two)
    GraspEnv(sur, jax.tree.map(lambda x: x[:2], episodes), tables=two)  # consistent: accepted
    bad_start = episodes.replace(start_grasp=episodes.start_grasp.at[1].set(999))
    with pytest.raises(ValueError, match=r"episodes\.start_grasp\[1\]: 999"):
        GraspEnv(sur, bad_start)


@pytest.mark.parametrize("bad", [-1, 17, 1000])
def test_out_of_range_actions_raise_at_every_python_entry_point(sur, episodes, tables, table_env, bad):
    """A concrete action outside [0, 17) raises a ValueError naming the value: the brax env, the table model, the
    surrogate step and transition, the DP policies given the model's space. Inside jit it is clipped (documented in
    gsp_jax.model.grasps)."""
    from gsp_jax.planning import dp, policies

    state = table_env.reset_to(0)
    msg = rf"action: {bad} is not in \[0, 17\)"
    with pytest.raises(ValueError, match=msg):
        table_env.step(state, bad)
    model = dp.TableModel(jax.tree.map(lambda x: x[0], tables), sur.space)
    with pytest.raises(ValueError, match=msg):
        model.step(state.pipeline_state, np.int32(bad))
    with pytest.raises(ValueError, match=msg):
        sur.step(state.pipeline_state, bad)
    with pytest.raises(ValueError, match=msg):
        sur.transition(state.pipeline_state.episode, state.pipeline_state.grasp, 0, bad)
    with pytest.raises(ValueError, match=rf"SequencePolicy\.actions: {bad} "):
        policies.SequencePolicy(jnp.asarray([0, bad, 2], jnp.int32), sur.space)
    with pytest.raises(ValueError, match=rf"TablePolicy\.table: {bad} "):
        policies.TablePolicy(jnp.full((288, T), bad, jnp.int32), sur.space)
    # traced: clipped into range, the documented behaviour
    clipped = jax.jit(model.step)(state.pipeline_state, jnp.int32(bad))
    expect = model.step(state.pipeline_state, min(max(bad, 0), sur.space.n_actions - 1))
    np.testing.assert_array_equal(clipped[0].grasp, expect[0].grasp)
    assert float(clipped[1]) == float(expect[1])
