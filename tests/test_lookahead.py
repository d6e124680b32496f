"""Lookahead (Algorithm 2) against a plain recursive search, DP at full depth, and the rollout cost-improvement
property; on the surrogate itself (continuous states) and on DP tables (exact for discrete states).

Every property here holds for any model, so the module runs on the small test hand (`models/testhand`: 27 grasps,
10 actions; tests/conftest.py) and its evaluation-like episodes: every search, every table and every enumeration
over its states is a tenth of the paper's hand's (288 grasps, 17 actions)."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tolerances as tol
from gsp_jax.planning import lookahead, policies
from gsp_jax.planners import registry as planners
from gsp_jax.model import scenario
from gsp_jax.planning.dp import TableModel, table_state
from gsp_jax.surrogate.observation import observation_size
from gsp_jax.ppo import networks as nets


PICKS = ("shift+4mm_-0.3Nm", "shift-6mm_+0.3Nm", "mass2m0_comy+1cm", "mass0.5m0_comy-1cm")  # tests/conftest.py


def _eval_episodes(episodes, n_steps):
    return scenario.stack([episodes[name].head(n_steps) for name in PICKS])


@pytest.fixture(scope="module")
def sur(small_sur):
    """This module's surrogate: the small test hand's (the lookahead's properties do not depend on the model)."""
    return small_sur


@pytest.fixture(scope="module")
def solved(sur, solve_each, small_episodes):
    """4 evaluation-like episodes (heights and torques, masses and centres of mass) cut to 6 waypoints, with their DP
    tables and solutions."""
    eps = _eval_episodes(small_episodes, 6)
    tables, sols = solve_each(sur, eps)
    return eps, tables, sols


@pytest.fixture(scope="module")
def discrete(sur):
    """The surrogate's discrete (grasp, waypoint) state, jitted: op by op its IK compiles for ~10 s on a CPU."""
    return jax.jit(sur.discrete_state, static_argnums=2)


@pytest.fixture(scope="module")
def network(sur):
    """A small PPO actor-critic with random weights (a deterministic policy that is neither DP nor trivial)."""
    networks = nets.make_networks(observation_size(sur.space, 6, sur.hand.n_joints), sur.n_actions,
                                  nets.NetworkConfig(hidden=(32, 32)))
    return policies.NetworkPolicy(networks.init(jax.random.PRNGKey(3)), networks, sur.space)


@pytest.fixture(scope="module")
def stepped(sur, solved, network):
    """depth -> (the cached lookahead policy on episode 0, its decisions [(plan, the surrogate's step under the
    plan's action, that step's reward)], the return of the plans' rewards, the final state): the episode run
    decision by decision, each plan's child taken; computed once per depth and shared."""
    eps, tables, _ = solved
    ep, cache = _pick(eps, 0), {}

    def run(depth):
        if depth not in cache:
            policy = lookahead.Lookahead(network, sur, depth=depth, inner=TableModel(_pick(tables, 0), sur.space))
            plan, step = jax.jit(policy.search), jax.jit(sur.step)
            s, ret, decisions = sur.reset(ep), 0.0, []
            while len(decisions) < ep.n_steps and not bool(s.done):
                p = plan(s)
                stepped_state, r, _ = step(s, p.action)
                decisions.append((p, stepped_state, r))
                s, ret = p.child, ret + float(p.reward)
            cache[depth] = policy, decisions, ret, s
        return cache[depth]

    return run


def _pick(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _reference_q(step, act, value, state, depth, horizon, n_actions):
    """Plain recursive Algorithm 2 (no sharing, no vmap): q[a] for every one of the `n_actions` first actions."""
    step, act = jax.jit(step), jax.jit(act)

    def rollout(s):
        ret, i = 0.0, 0
        while (horizon is None or i < horizon) and not bool(s.done):
            s, r, _ = step(s, act(s))
            ret, i = ret + float(r), i + 1
        if value is not None and not bool(s.done):
            ret += float(value(s))
        return ret

    def best(s, d):
        if d == 0:
            return rollout(s)
        return max(q_of(s, d))

    def q_of(s, d):
        out = []
        for a in range(n_actions):
            child, r, _ = step(s, jnp.int32(a))
            out.append(float(r) + best(child, d - 1))
        return out

    return np.array(q_of(state, depth))


def test_search_on_the_surrogate_matches_a_recursive_search_from_a_continuous_state(sur, solved, discrete):
    """From an off-waypoint state (tool 2-3 mm and a few degrees off, moving): the vmapped search with shared
    rollouts gives the same Q-values (one per action) and action as a plain recursive search stepping the surrogate
    (depth 1 here, the continuous root's children; deeper levels are exercised on tables below)."""
    eps, _, sols = solved
    ep = _pick(eps, 2).head(5)
    state = discrete(ep, sols.grasps[2, 1], 1)
    tilt = jnp.array([np.cos(0.03), 0.0, np.sin(0.03), 0.0], jnp.float32)  # 3.4 deg about y
    state = state.replace(
        tool_pos=state.tool_pos + jnp.array([0.002, -0.003, 0.001]),
        tool_quat=tilt,
        tool_vel=jnp.array([0.01, 0.0, 0.02, 0.1, 0.0, 0.0]),
    )
    base = policies.SequencePolicy(sols.actions[0, :5])
    plan = jax.jit(lambda s: lookahead.search(sur, s, base, depth=1))(state)
    ref = _reference_q(sur.step, base.act, None, state, 1, None, sur.n_actions)
    # two float32 computations of the surrogate's rewards (vmapped in the search, single steps here): their
    # precision, tests/tolerances.py
    tol.assert_close_with_rare_ties(np.asarray(plan.q), ref, tol.REWARD_ATOL, "q")
    assert ref[int(plan.action)] >= ref.max() - 2 * tol.REWARD_ATOL  # the best action (up to float ties)
    assert float(plan.value) == pytest.approx(ref.max(), abs=tol.REWARD_ATOL)


def test_cached_successors_give_the_surrogates_plan(sur, solved, network, discrete):
    """The search with the tree's interior and rollouts on the episode's table (`inner`) against the search that
    steps the surrogate everywhere, from an off-waypoint continuous state (depth 2, one rollout step and the
    critic): the same Q-values (within the float32 reward tolerance) and plan. Below the root every state is a
    discrete (grasp, waypoint) state, where the table is exact; only the root's steps need the surrogate."""
    eps, tables, sols = solved
    ep, table = _pick(eps, 3), _pick(tables, 3)
    depth, horizon = 2, 1
    state = discrete(ep, sols.grasps[3, 1], 1)
    state = state.replace(tool_pos=state.tool_pos + jnp.array([0.002, -0.003, 0.001]),
                          tool_vel=jnp.array([0.01, 0.0, 0.02, 0.1, 0.0, 0.0]))
    value = network.value
    full = jax.jit(lambda s: lookahead.search(sur, s, network, depth, horizon, value))(state)
    cached = jax.jit(lambda s, m: lookahead.search(sur, s, network, depth, horizon, value, inner=m))(
        state, TableModel(table, sur.space))
    tol.assert_close_with_rare_ties(np.asarray(cached.q), np.asarray(full.q), tol.REWARD_ATOL, "q")
    q = np.sort(np.asarray(full.q))
    assert q[-1] - q[-2] > 2 * tol.REWARD_ATOL and q[0] == sur.reward_config.r_min  # measured: -5.270 vs -5.320
    assert int(cached.action) == int(full.action)  # a clear best action: both plans take it
    policy = policies.Lookahead(network, sur, depth, horizon, network, inner=TableModel(table, sur.space))
    assert int(jax.jit(policy.act)(state)) == int(cached.action)


def test_experiments_cached_lookahead_is_one_policy_per_episode_table(sur, solved, network):
    """`planners.make` (Fig. 4a/4b): the cached L1 carries every episode's table with in_axes 0 (hashable, as the
    physics runner keys its programs by them), and vmapped over the episodes it acts as a per-episode Lookahead
    whose interior is that episode's table."""
    from gsp_jax.planning import evaluation

    eps, tables, sols = solved
    ctx = evaluation.Context(sur, "test", [f"e{i}" for i in range(4)], eps, tables, sols, sols.actions[0], network, "x")
    policy, axis = planners.make(ctx, "L1")
    assert hash(axis) == hash(policies.Lookahead(None, None, depth=1, inner=0))
    states = jax.jit(jax.vmap(lambda e, g: sur.discrete_state(e, g, 2)))(eps, sols.grasps[:, 2])
    plans = jax.jit(jax.vmap(lambda pol, s: pol.search(s), in_axes=(axis, 0)))(policy, states)
    own_plan = jax.jit(lambda m, s: policies.Lookahead(network, sur, depth=1, inner=m).search(s))  # one compile
    clear = 0
    for i in range(4):
        ref = own_plan(TableModel(_pick(tables, i), sur.space), _pick(states, i))
        tol.assert_close_with_rare_ties(np.asarray(plans.q[i]), np.asarray(ref.q), tol.REWARD_ATOL, f"q {i}")
        q = np.sort(np.asarray(ref.q))
        if q[-1] - q[-2] > 2 * tol.REWARD_ATOL:  # batched and single float32 steps may order exact ties apart
            assert int(plans.action[i]) == int(ref.action)
            clear += 1
    assert clear >= 1  # measured: all 4 have a clear best action
    plain, none_axis = planners.make(ctx, "L1", cached=False)
    assert none_axis is None and plain.inner is None


def test_search_with_truncated_rollouts_and_a_critic_matches_a_recursive_search(sur, solved, network):
    """m = 1 rollout steps plus the critic's value at the cut-off, on a DP table; and the best path's score."""
    eps, tables, sols = solved
    model = TableModel(_pick(tables, 0), sur.space)
    state = table_state(_pick(eps, 0), model.table, sols.grasps[0, 2], 2)
    plan = jax.jit(lambda s, m: lookahead.search(m, s, network, depth=2, horizon=1, value=network.value))(state, model)
    ref = _reference_q(model.step, network.act, network.value, state, 2, 1, sur.n_actions)
    np.testing.assert_allclose(np.asarray(plan.q), ref, rtol=1e-4, atol=1e-4)
    assert int(plan.path[0]) == int(plan.action) and ref[int(plan.action)] >= ref.max() - 1e-4


def _enumerated_q(table, actions, g, t, horizon):
    """Depth-2 Q-values of (g, t) by brute-force enumeration of the table in numpy (independent of the search):
    every action pair, then the open-loop `actions` for `horizon` steps (None: to the end) from the leaf."""
    reward, nxt, term = (np.asarray(x) for x in (table.reward, table.next_grasp, table.terminal))
    n_t = reward.shape[2]

    @functools.lru_cache(maxsize=None)
    def roll(g, t):
        ret, i = 0.0, 0
        while t < n_t and (horizon is None or i < horizon):
            a = actions[t]
            ret, done, g, t, i = ret + reward[g, a, t], term[g, a, t], nxt[g, a], t + 1, i + 1
            if done:
                break
        return ret

    n_a = reward.shape[1]
    q = np.full(n_a, -np.inf)
    for a1 in range(n_a):
        r1, g1 = reward[g, a1, t], nxt[g, a1]
        if term[g, a1, t]:
            q[a1] = r1  # ended: absorbing, nothing more
            continue
        for a2 in range(n_a):
            r2, g2 = reward[g1, a2, t + 1], nxt[g1, a2]
            q[a1] = max(q[a1], r1 + r2 + (0.0 if term[g1, a2, t + 1] else roll(g2, t + 2)))
    return q


@pytest.fixture(scope="module")
def long_episode(sur, solve_each, small_episodes):
    """One evaluation episode cut to 12 waypoints, with its DP table and solution: mid-episode there are many
    roots where a grasp fails on one step but holds on the next, i.e. the same grasp ends some paths and lives on
    in others (the case that shared rollouts must keep apart)."""
    ep = small_episodes[PICKS[0]].head(12)
    table, sol = _pick(solve_each(sur, scenario.stack([ep])), 0)
    return ep, table, sol


@pytest.mark.parametrize("horizon", [None, 1])
def test_depth_2_search_equals_brute_force_enumeration_from_every_grasp(sur, long_episode, horizon):
    """From every grasp at every waypoint that has two more after it, with an open-loop DP sequence as base: the
    search's Q-values (one per action) equal a plain enumeration of every action pair plus rollouts."""
    ep, table, sol = long_episode
    model = TableModel(table, sur.space)
    actions = np.asarray(sol.actions)
    base = policies.SequencePolicy(jnp.asarray(actions))
    g, t = np.meshgrid(np.arange(sur.space.n_grasps), np.arange(ep.n_steps - 2), indexing="ij")
    g, t = g.ravel(), t.ravel()
    search = jax.jit(jax.vmap(lambda g, t: lookahead.search(model, table_state(ep, table, g, t), base, 2, horizon).q))
    q = np.asarray(search(jnp.asarray(g, jnp.int32), jnp.asarray(t, jnp.int32)))
    ref = np.stack([_enumerated_q(table, actions, gi, ti, horizon) for gi, ti in zip(g, t)])
    np.testing.assert_allclose(q, ref, rtol=1e-5, atol=1e-4)


def test_full_depth_lookahead_is_dp_optimal_from_every_start_grasp(sur, solve_each, small_episodes):
    """l = T: the complete tree is the whole problem, so running the lookahead policy from any grasp at
    waypoint 0 earns the DP optimal value of that grasp (3-waypoint episodes, A^3 paths per decision)."""
    eps = jax.tree.map(lambda x: x[1:3], _eval_episodes(small_episodes, 3))
    tables, sols = solve_each(sur, eps)
    base = policies.SequencePolicy(jnp.zeros(3, jnp.int32))

    def run(ep, table, g):
        model = TableModel(table, sur.space)
        return lookahead.rollout(model, policies.Lookahead(base, model, depth=3), table_state(ep, table, g, 0))[0]

    grasps = jnp.arange(sur.space.n_grasps, dtype=jnp.int32)
    ret = jax.jit(jax.vmap(jax.vmap(run, (None, None, 0)), (0, 0, None)))(eps, tables, grasps)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(sols.value[:, :, 0]), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("base_name,depth", [("dp-baseline", 1), ("network", 1), ("dp-baseline", 2), ("network", 2)])
def test_lookahead_never_earns_less_than_its_base_policy_from_any_state(sur, solved, network, base_name, depth):
    """Cost improvement of rollout (deterministic model): from every discrete state (grasp, waypoint) of the
    evaluation episodes, running L1 (and L2) over a base policy earns at least what the base policy earns (and
    never more than DP optimal); it strictly improves at many of the states where the base is not optimal."""
    eps, tables, sols = solved
    base = policies.SequencePolicy(sols.actions[0]) if base_name == "dp-baseline" else network
    n_g, n_t = sur.space.n_grasps, eps.waypoints.shape[1]

    def returns(ep, table, g, t):
        model = TableModel(table, sur.space)
        start = table_state(ep, table, g, t)
        base_ret = lookahead.rollout(model, base, start)[0]
        l1_ret = lookahead.rollout(model, policies.Lookahead(base, model, depth=depth), start)[0]
        return base_ret, l1_ret

    g, t = jnp.meshgrid(jnp.arange(n_g, dtype=jnp.int32), jnp.arange(n_t, dtype=jnp.int32), indexing="ij")
    per_state = jax.vmap(returns, (None, None, 0, 0))
    base_ret, l1_ret = jax.jit(jax.vmap(per_state, (0, 0, None, None)))(eps, tables, g.ravel(), t.ravel())
    base_ret, l1_ret = np.asarray(base_ret), np.asarray(l1_ret)
    assert np.all(l1_ret >= base_ret - 1e-4), f"L{depth} below its base at {np.sum(l1_ret < base_ret - 1e-4)} states"
    # never above the DP optimum of the state
    dp_value = np.asarray(sols.value[:, :, :n_t]).reshape(len(base_ret), -1)
    assert np.all(l1_ret <= dp_value + 1e-4)
    # and it does improve, at many of the states where there is room
    room = dp_value > base_ret + 1e-3
    improved = np.mean(l1_ret[room] > base_ret[room] + 1e-3)
    print(f"L{depth} over {base_name}: improves {improved:.2f} of {room.sum()} improvable states")
    assert room.sum() > 100 and improved > 0.25


def test_vmapped_search_equals_looped_search(sur, solved, network):
    eps, tables, sols = solved
    model = TableModel(_pick(tables, 1), sur.space)
    ep = _pick(eps, 1)
    states = jax.vmap(lambda g, t: table_state(ep, model.table, g, t))(jnp.array([0, 7, 15, 26]),
                                                                       jnp.array([0, 2, 3, 5]))
    search = jax.jit(lambda s: lookahead.search(model, s, network, depth=2))
    batched = jax.vmap(lambda s: lookahead.search(model, s, network, depth=2))(states)
    for i in range(4):
        one = search(_pick(states, i))
        np.testing.assert_allclose(np.asarray(batched.q[i]), np.asarray(one.q), rtol=1e-5, atol=1e-5)
        assert int(batched.action[i]) == int(one.action)


def test_lookahead_from_a_finished_state_and_bad_arguments(sur, solved):
    eps, tables, sols = solved
    model = TableModel(_pick(tables, 0), sur.space)
    done = table_state(_pick(eps, 0), model.table, 0, 6).replace(done=jnp.array(True))
    plan = lookahead.search(model, done, policies.SequencePolicy(sols.actions[0]), depth=1)
    np.testing.assert_array_equal(np.asarray(plan.q), 0.0)
    with pytest.raises(ValueError, match="depth"):
        lookahead.search(model, done, policies.SequencePolicy(sols.actions[0]), depth=0)
    with pytest.raises(ValueError, match="horizon"):
        lookahead.search(model, done, policies.SequencePolicy(sols.actions[0]), depth=1, horizon=-1)
    # the model is a step model (`protocols.StepModel`), the base a policy: dispatched by the protocol, checked
    with pytest.raises(TypeError, match="model: a step model needs .*got SequencePolicy"):
        lookahead.search(policies.SequencePolicy(sols.actions[0]), done, policies.SequencePolicy(sols.actions[0]))
    with pytest.raises(TypeError, match="policy: a policy needs .*got TableModel"):
        lookahead.search(model, done, model)


def test_a_rollout_is_one_trajectory(sur, solved):
    """`rollout.rollout` (the one walker): DP optimal's policy in its table walks the DP's optimal sequence -- its
    actions, grasps, rewards and alive steps, and its return, the optimum; cut after 2 steps it keeps the first two
    and fills the rest (null action, reward 0, not alive), the final state at waypoint 2."""
    from gsp_jax.model.grasps import NULL
    from gsp_jax.planning import rollout

    eps, tables, sols = solved
    ep, sol = _pick(eps, 0), _pick(sols, 0)
    model = TableModel(_pick(tables, 0), sur.space)
    walk = jax.jit(lambda s, n: rollout.rollout(model, policies.TablePolicy(sol.policy), s, n), static_argnums=1)
    traj = walk(model.reset(ep), None)
    alive = np.asarray(sol.alive)
    np.testing.assert_array_equal(np.asarray(traj.alive), alive)
    np.testing.assert_array_equal(np.asarray(traj.actions)[alive], np.asarray(sol.actions)[alive])
    np.testing.assert_array_equal(np.asarray(traj.grasps)[alive], np.asarray(sol.grasps)[1:][alive])
    np.testing.assert_allclose(np.asarray(traj.rewards), np.asarray(sol.rewards), atol=tol.REWARD_ATOL)
    np.testing.assert_allclose(float(traj.ret), float(sol.ret), atol=tol.REWARD_ATOL * 6)
    assert bool(traj.final.done) and float(traj.hold) == 1.0 and np.all(np.asarray(traj.reach) == 1.0)
    cut = walk(model.reset(ep), 2)
    assert cut.actions.shape == (2,) and int(cut.final.t) == 2 and bool(np.all(cut.alive))
    np.testing.assert_allclose(float(cut.ret), float(np.sum(np.asarray(sol.rewards)[:2])), atol=tol.REWARD_ATOL * 2)
    if not alive.all():  # the steps after the end keep the fill
        n = int(alive.sum())
        assert np.all(np.asarray(traj.actions)[n:] == NULL) and np.all(np.asarray(traj.rewards)[n:] == 0.0)


def test_shared_rollouts_cover_every_leaf(sur, hand):
    """The distinct leaf grasps of a depth-l tree: 11 (l = 1) and 51 (l = 2) for the paper's hand, i.e. the grasps
    within l link changes (options per link 3, 3, 2, 4, 2, 2); 7 and 19 for the small hand's (3, 3, 3)."""
    from gsp_jax.model import grasps

    paper = grasps.space_of(hand)
    assert lookahead._ball_size(paper, 1) == 1 + 10
    assert lookahead._ball_size(paper, 2) == 1 + 10 + 40
    assert lookahead._ball_size(sur.space, 1) == 1 + 6
    assert lookahead._ball_size(sur.space, 2) == 1 + 6 + 12


def test_per_decision_latency_times_the_planners_own_decisions(sur, solved, network, stepped):
    """`table1 --per-decision` times one decision at a time on the planner's own episode: DP optimal earns each
    episode's DP optimum, and the cached L1 earns what the same policy earns run plan by plan (`stepped`, which the
    rollout test below checks against the jitted `rollout_planned`); every step of every episode is a decision."""
    from experiments.paper.table1 import decisions as bench_latency
    from gsp_jax.planning import evaluation

    eps, tables, sols = solved
    one = jax.tree.map(lambda x: x[:1], (eps, tables, sols))
    ctx = evaluation.Context(sur, "test", ["e0"], *one, sols.actions[0], network, "x")
    result = bench_latency.run(ctx, ["dp-opt", "L1"], cached=True)
    opt, l1 = result["policies"]["dp-opt"], result["policies"]["L1"]
    np.testing.assert_allclose(opt["returns"], np.asarray(sols.ret[:1]), atol=tol.REWARD_ATOL * 6)
    _, _, ret, _ = stepped(1)
    np.testing.assert_allclose(l1["returns"][0], ret, atol=tol.REWARD_ATOL * 6)
    assert opt["decisions"] == int(np.sum(sols.alive[0])) and l1["decisions"] <= 6
    assert 0 < opt["decision_median_s"] <= opt["decision_p99_s"] and opt["setup_median_s"] > 0


def test_table1_dp_optimal_earns_its_dp_optimum_by_replaying_its_own_table(sur, solved, network):
    """`online.episode_planner`'s DP optimal (Table 1's) solves the unseen episode inside the timed call and runs its
    policy in that table (from its start the surrogate visits only the table's states: `test_env` checks the two step
    for step):
    the episode earns exactly the DP optimum of the episode."""
    from gsp_jax.planning import evaluation
    from gsp_jax.planners import online

    eps, tables, sols = solved
    one = jax.tree.map(lambda x: x[:1], (eps, tables, sols))
    ctx = evaluation.Context(sur, "test", ["e0"], *one, sols.actions[0], network, "x")
    ret = jax.jit(online.episode_planner(ctx, "dp-opt"))(_pick(eps, 0))
    np.testing.assert_allclose(float(ret), float(sols.ret[0]), atol=tol.REWARD_ATOL * 6)


def test_table1_lookahead_in_the_table_runs_the_cached_episode(sur, solved, network, stepped):
    """`online.episode_planner`'s L1 (Table 1's) searching in the unseen episode's table, root included
    (`lookahead="table"`, the default), runs the episode that the cached L1 runs with the root's actions stepped in the
    surrogate (from its start the surrogate visits only the table's states): the same return, to the tolerance of a few
    rewards."""
    from gsp_jax.planning import evaluation
    from gsp_jax.planners import online

    eps, tables, sols = solved
    one = jax.tree.map(lambda x: x[:1], (eps, tables, sols))
    ctx = evaluation.Context(sur, "test", ["e0"], *one, sols.actions[0], network, "x")
    _, decisions, ret, _ = stepped(1)
    got = jax.jit(online.episode_planner(ctx, "L1", lookahead="table"))(_pick(eps, 0))
    np.testing.assert_allclose(float(got), ret, atol=tol.REWARD_ATOL * len(decisions))
    with pytest.raises(ValueError, match="lookahead"):
        online.episode_planner(ctx, "L1", lookahead="tables")


@pytest.mark.parametrize("depth", [1, 2])
def test_rollout_planned_runs_the_episode_that_stepping_the_surrogate_runs(sur, solved, stepped, depth):
    """Moving on to each search's own root child instead of stepping the surrogate again gives the same episode.
    Decision by decision: the plan's child and reward are the surrogate's step under the plan's action (the same
    grasp, waypoint and end; the reward to its float32 tolerance, the child coming from the root's vmapped step).
    Whole episode: the jitted `rollout_planned` earns that return and ends there, compared only because every
    decision's best Q-value leads the runner-up by more than the return's tolerance."""
    eps, _, _ = solved
    ep = _pick(eps, 0)
    policy, decisions, ret, s = stepped(depth)
    for n, (p, stepped_state, r) in enumerate(decisions):
        for f in ("grasp", "t", "done"):
            np.testing.assert_array_equal(np.asarray(getattr(p.child, f)), np.asarray(getattr(stepped_state, f)))
        np.testing.assert_allclose(float(p.reward), float(r), atol=tol.REWARD_ATOL)
        q = np.sort(np.asarray(p.q))
        assert q[-1] - q[-2] > tol.REWARD_ATOL * ep.n_steps, f"decision {n}: margin {q[-1] - q[-2]:.2e}"
    n = len(decisions)
    assert n >= 2  # the episode went somewhere
    planned, final = jax.jit(lambda e: lookahead.rollout_planned(policy, sur.reset(e)))(ep)
    np.testing.assert_allclose(float(planned), ret, atol=tol.REWARD_ATOL * ep.n_steps)
    for f in ("grasp", "t", "done"):
        np.testing.assert_array_equal(np.asarray(getattr(final, f)), np.asarray(getattr(s, f)))
