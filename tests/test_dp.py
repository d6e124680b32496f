"""Tests of gsp_jax.planning.dp: the table against the surrogate it discretises, the Bellman backup against brute-force
enumeration of every action sequence, the optimal sequence against a rollout of the surrogate, batching, the
IK count, and the open-loop replay (`sequence_return`).

Every property here holds for any model, so everything runs on the small test hand (`models/testhand`: 27 grasps,
10 actions; tests/conftest.py), on reduced episodes of T = 5 waypoints (its nominal lift's first five, and the first
five of one with 1.5 times the mass and the centre of mass 1 cm off), so the brute force enumerates 10^5 = 100,000
sequences per start grasp in numpy (the paper's hand: 17^5 = 1,419,857). Every
compiled function is built once per module (fixtures below) and reused with fixed shapes: the single-episode
solve (both episodes), the batched solve, one vmapped surrogate step over a batch of N_BATCH, the vmapped
discrete state and the vmapped reset at that batch size.
"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import tolerances as tol  # noqa: E402
from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.model import grasps, scenario  # noqa: E402
from gsp_jax.solvers import ik  # noqa: E402
from gsp_jax.surrogate import step as surrogate  # noqa: E402
from gsp_jax.surrogate.reward import RewardConfig  # noqa: E402

T = 5  # waypoints of the reduced episodes
N_BATCH = 20  # batch of every vmapped surrogate call (one compile each)
EVALB = "mass1.5m0_comy+1cm"
TOL = dict(rtol=1e-5, atol=1e-5)  # float32 sums of a few rewards of magnitude <= 200 (the same rewards summed)
# two computations of the table (batched vs unbatched IK and wrench solves): tests/tolerances.py


def _reduce(ep: scenario.Episode, n: int = T) -> scenario.Episode:
    return ep.head(n)


def _np(tree):
    return jax.tree.map(np.asarray, tree)


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def sur(small_sur):
    """This module's surrogate: the small test hand's (its properties do not depend on the model)."""
    return small_sur


@pytest.fixture(scope="module")
def episodes(small_episodes):
    return {
        "nominal": _reduce(small_episodes["nominal"]),
        "evalB": _reduce(small_episodes[EVALB]),
    }


@pytest.fixture(scope="module")
def fns(sur):
    """Every compiled function of this module, compiled lazily on first use and then reused."""
    return dict(
        solve=jax.jit(lambda e: dp.solve(sur, e)),
        vsolve=jax.jit(jax.vmap(lambda e: dp.solve(sur, e))),
        backup=jax.jit(dp.backup),
        sequence_return=jax.jit(dp.sequence_return),
        vdiscrete=jax.jit(jax.vmap(sur.discrete_state, (None, 0, 0))),
        vreset=jax.jit(jax.vmap(sur.reset)),
        vstep=jax.jit(jax.vmap(sur.step)),
    )


@pytest.fixture(scope="module")
def solved(fns, episodes):
    """name -> (Table, Solution) as numpy arrays; each table is built exactly once per module."""
    return {name: _np(fns["solve"](ep)) for name, ep in episodes.items()}


# ------------------------------------------------------------------------------------------ references
def _replay(table, start: int, actions) -> tuple[float, np.ndarray, np.ndarray]:
    """Independent numpy replay of one open-loop sequence: (return, rewards (T,), alive (T,)); rewards after a
    terminal transition count 0. float64 accumulation."""
    g, alive, rewards, alive_t = int(start), True, [], []
    for t, a in enumerate(np.asarray(actions)):
        alive_t.append(alive)
        rewards.append(float(table.reward[g, a, t]) if alive else 0.0)
        alive = alive and not bool(table.terminal[g, a, t])
        g = int(table.next_grasp[g, a])
    return float(np.sum(rewards)), np.asarray(rewards), np.asarray(alive_t)


def _brute_force(table, start: int) -> tuple[float, np.ndarray]:
    """The best return over every one of the A^T action sequences from `start` (float64), and its sequence.
    Sequence n takes action (n // A^(T-1-t)) % A at step t."""
    n_g, n_a, n_t = table.reward.shape
    n = np.arange(n_a**n_t, dtype=np.int64)
    g = np.full(n.shape, start, np.int64)
    alive = np.ones(n.shape, bool)
    total = np.zeros(n.shape, np.float64)
    reward = table.reward.astype(np.float64)
    for t in range(n_t):
        a = (n // n_a ** (n_t - 1 - t)) % n_a
        total += np.where(alive, reward[g, a, t], 0.0)
        alive &= ~table.terminal[g, a, t]
        g = table.next_grasp[g, a].astype(np.int64)
    best = int(np.argmax(total))
    seq = np.asarray([(best // n_a ** (n_t - 1 - t)) % n_a for t in range(n_t)])
    return float(total[best]), seq


def _starts(table, value, episode_start: int, n_alive: int = 2) -> list[int]:
    """The episode's start grasp, grasp 0 (no contacts at all), and a few grasps that survive the first step."""
    rng = np.random.default_rng(7)
    alive = np.flatnonzero(value[:, 0] > table.reward.min())
    others = rng.choice(alive[alive != episode_start], n_alive, replace=False).tolist()
    return [episode_start, 0, *others]


# ------------------------------------------------------------------------------------------ 1. brute force
@pytest.mark.parametrize("name", ["nominal", "evalB"])
def test_backup_equals_brute_force_over_every_sequence(name, solved, episodes, fns):
    """The DP's value from a start grasp equals the best return over all A^T open-loop sequences (for a
    deterministic problem the best open-loop sequence is optimal), and the DP's own sequence attains it."""
    table, sol = solved[name]
    g0 = int(episodes[name].start_grasp)
    assert sol.grasps[0] == g0
    np.testing.assert_allclose(sol.ret, sol.value[g0, 0], rtol=0, atol=0)
    for start in _starts(table, sol.value, g0):
        best, best_seq = _brute_force(table, start)
        s = sol if start == g0 else _np(fns["backup"](jax.tree.map(jnp.asarray, table), jnp.int32(start)))
        np.testing.assert_allclose(s.ret, best, **TOL, err_msg=f"start {start}: DP {s.ret}, brute force {best}")
        np.testing.assert_allclose(sol.value[start, 0], best, **TOL, err_msg=f"value[{start}, 0]")
        ret, rewards, alive = _replay(table, start, s.actions)
        np.testing.assert_allclose(ret, best, **TOL, err_msg=f"start {start}: DP sequence {s.actions} scores {ret}")
        np.testing.assert_allclose(s.rewards, rewards, **TOL)
        np.testing.assert_array_equal(s.alive, alive)
        # the reported grasp path is the table's transitions from the start (frozen after the episode ends)
        g = start
        for t in range(T):
            if alive[t]:
                g = int(table.next_grasp[g, s.actions[t]])
            assert s.grasps[t + 1] == g, f"start {start}: grasps {s.grasps}"
    # the test is not vacuous: the nominal start survives, grasp 0 (no contact) cannot hold the tool
    if name == "nominal":
        assert sol.ret > table.reward.min()


# ------------------------------------------------------------------------------------------ 2. table vs surrogate
def _triples(table, rng):
    """N_BATCH (g, a, t): random ones plus a redundant action, a failing (R_MIN) transition before the last
    step, a last-step transition and a change that fails only through its change term (its new grasp, kept by
    the null action, survives), so every branch of the table is compared."""
    n_g, n_a, n_t = table.reward.shape
    r_min = table.reward.min()
    g = rng.integers(0, n_g, N_BATCH)
    a = rng.integers(0, n_a, N_BATCH)
    t = rng.integers(0, n_t, N_BATCH)
    # a surviving, non-redundant transition in the middle of the episode
    gs, as_, ts = np.nonzero((table.reward > r_min) & (table.next_grasp != np.arange(n_g)[:, None])[..., None])
    mid = np.flatnonzero(ts < n_t - 1)[0]
    g[0], a[0], t[0] = gs[mid], as_[mid], ts[mid]
    # a redundant action (leaves the grasp unchanged) from a grasp that survives it
    same = (table.next_grasp == np.arange(n_g)[:, None]) & (np.arange(n_a) != grasps.NULL)
    gr, ar, tr = np.nonzero((table.reward > r_min) & same[..., None])
    g[1], a[1], t[1] = gr[0], ar[0], tr[0]
    # a failing transition before the last step
    gf, af, tf = np.nonzero((table.reward == r_min) & (np.arange(n_t) < n_t - 1))
    g[2], a[2], t[2] = gf[0], af[0], tf[0]
    # the last step (always terminal) by a transition that does not fail: terminal only because it is the last
    gl, al = np.nonzero(table.reward[:, :, n_t - 1] > r_min)
    g[3], a[3], t[3] = gl[0], al[0], n_t - 1
    # a change that fails although its new grasp survives at that waypoint
    kept = table.reward[table.next_grasp, grasps.NULL, :]  # (G, A, T): the null action from the new grasp
    gc, ac, tc = np.nonzero((table.reward == r_min) & (kept > r_min) & (np.arange(n_t) < n_t - 1))
    g[4], a[4], t[4] = gc[0], ac[0], tc[0]
    return g, a, t


def test_table_matches_surrogate_step(solved, episodes, sur, fns):
    """reward / next grasp / done of `sur.step` from the DP state (g, t) equal the table's entries."""
    table, _ = solved["nominal"]
    ep = episodes["nominal"]
    g, a, t = _triples(table, np.random.default_rng(0))
    states = fns["vdiscrete"](ep, jnp.asarray(g, jnp.int32), jnp.asarray(t, jnp.int32))
    out, reward, done = _np(fns["vstep"](states, jnp.asarray(a, jnp.int32)))
    tol.assert_close_with_rare_ties(reward, table.reward[g, a, t], tol.REWARD_ATOL, "reward")
    np.testing.assert_array_equal(out.grasp, table.next_grasp[g, a])
    np.testing.assert_array_equal(done, table.terminal[g, a, t])
    np.testing.assert_array_equal(out.t, t + 1)
    # the sample covers a failing step, a surviving one, a redundant one and the last step
    assert np.any(reward == sur.reward_config.r_min) and np.any(reward > sur.reward_config.r_min)
    assert np.any(out.terms.redundant == 1) and np.any((t == T - 1) & (reward > sur.reward_config.r_min))
    # the redundancy flag enters the table's reward exactly as in the step: a non-null action that keeps the grasp
    np.testing.assert_array_equal(out.terms.redundant == 1, (table.next_grasp[g, a] == g) & (a != grasps.NULL))
    # the sample covers a grasp change that fails only through its change term (the shared grasp drops the tool)
    assert np.any(out.terms.unmet[:, 3] > sur.reward_config.fall_unmet)


def test_no_change_is_priced_on_the_start_support(solved, sur):
    """At waypoint 0 the tool rests on its start support: a change there is rewarded as its new grasp kept by the
    null action (plus the redundant flag), while later some changes fail that their new grasps survive."""
    table, _ = solved["nominal"]
    n_g, n_a, _ = table.reward.shape
    cfg = sur.reward_config
    redundant = (table.next_grasp == np.arange(n_g)[:, None]) & (np.arange(n_a) != grasps.NULL)
    kept = table.reward[table.next_grasp, grasps.NULL, :]  # (G, A, T)
    r0 = table.reward[..., 0]
    alive = kept[..., 0] > cfg.r_min
    want = np.where(alive, kept[..., 0] - cfg.w_redundant * redundant, cfg.r_min)
    np.testing.assert_allclose(r0, want, atol=1e-6)
    assert np.any((table.reward[..., 1:] == cfg.r_min) & (kept[..., 1:] > cfg.r_min))


# ------------------------------------------------------------------------------------------ 3. rollout
def test_optimal_sequence_value_equals_surrogate_rollout(solved, episodes, sur, fns):
    """Replaying the DP's optimal actions in the surrogate, from `sur.reset` of the episode (with its start grasp
    set to each of N_BATCH grasps), sums to the DP's value, with the same per-step rewards, grasps and end."""
    table, sol = solved["nominal"]
    ep = episodes["nominal"]
    g0 = int(ep.start_grasp)
    rng = np.random.default_rng(3)
    surviving = np.flatnonzero(sol.value[:, 0] > sur.reward_config.r_min)
    failing = np.setdiff1d(np.arange(table.reward.shape[0]), surviving)
    n_fail = min(5, len(failing))  # the small hand's nominal lift: 3 grasps fail at once (no thumb and no index)
    assert n_fail >= 1 and len(surviving) - 1 >= N_BATCH - 1 - n_fail
    starts = np.concatenate([[g0], rng.choice(surviving[surviving != g0], N_BATCH - 1 - n_fail, replace=False),
                             rng.choice(failing, n_fail, replace=False)])
    tab = jax.tree.map(jnp.asarray, table)
    sols = [sol if s == g0 else _np(fns["backup"](tab, jnp.int32(s))) for s in starts]
    batch = scenario.stack([ep.replace(start_grasp=jnp.asarray(s, jnp.int32)) for s in starts])
    state = fns["vreset"](batch)
    np.testing.assert_array_equal(np.asarray(state.grasp), starts)
    total = np.zeros(N_BATCH)
    ended = np.zeros(N_BATCH, bool)
    for t in range(T):
        actions = np.asarray([s.actions[t] for s in sols], np.int32)
        np.testing.assert_array_equal(~ended, [s.alive[t] for s in sols], err_msg=f"step {t}: episode end")
        state, reward, done = fns["vstep"](state, jnp.asarray(actions))
        reward = np.where(ended, 0.0, np.asarray(reward))  # stop when done
        tol.assert_close_with_rare_ties(reward, [s.rewards[t] for s in sols], tol.REWARD_ATOL, f"step {t}")
        np.testing.assert_array_equal(np.where(ended, -1, np.asarray(state.grasp)),
                                      [-1 if e else s.grasps[t + 1] for e, s in zip(ended, sols)])
        total += reward
        ended |= np.asarray(done)
    assert ended.all()  # the last step ends every episode
    tol.assert_close_with_rare_ties(total, [s.ret for s in sols], tol.REWARD_ATOL, "return")
    tol.assert_close_with_rare_ties(total, sol.value[starts, 0], tol.REWARD_ATOL, "value")


# ------------------------------------------------------------------------------------------ 4. Bellman
@pytest.mark.parametrize("name", ["nominal", "evalB"])
def test_bellman_equation_holds_everywhere(name, solved, sur):
    """value[g, t] = max_a reward + (0 if terminal else value[next, t + 1]) for every (g, t), value[:, T] = 0,
    and the policy attains the max. In particular a failing (R_MIN) action is chosen only when no surviving
    action from that (g, t) has a better total."""
    table, sol = solved[name]
    n_g, n_a, n_t = table.reward.shape
    assert sol.value.shape == (n_g, n_t + 1) and sol.policy.shape == (n_g, n_t)
    np.testing.assert_array_equal(sol.value[:, n_t], 0.0)
    reward = table.reward.astype(np.float64)
    v = sol.value.astype(np.float64)
    q = reward + np.where(table.terminal, 0.0, v[table.next_grasp][:, :, 1:])  # (G, A, T): v[next, t + 1]
    np.testing.assert_allclose(v[:, :n_t], q.max(axis=1), **TOL)
    chosen = np.take_along_axis(q, sol.policy[:, None, :], axis=1)[:, 0]
    np.testing.assert_allclose(chosen, v[:, :n_t], **TOL)
    r_min = sur.reward_config.r_min
    fails = np.take_along_axis(reward, sol.policy[:, None, :], axis=1)[:, 0] == r_min  # (G, T)
    surviving_q = np.where(reward > r_min, q, -np.inf).max(axis=1)  # best surviving action per (g, t)
    assert np.all(surviving_q[fails] <= r_min + 1e-4)
    # non-vacuous: both choices occur, and from some (g, t) the DP avoids an immediate failure
    assert fails.any() and (~fails).any()


def _clear_steps(table, sol) -> int:
    """Steps of the optimal sequence, from the start, whose choice is clear: the best action's value beats every
    action that leads to another grasp by more than RETURN_ATOL (so another float32 computation chooses alike)."""
    for t, (g, a) in enumerate(zip(sol.grasps[:-1], sol.actions)):
        if not sol.alive[t]:
            return t
        nxt = table.next_grasp[g]
        q = table.reward[g, :, t] + np.where(table.terminal[g, :, t], 0.0, sol.value[nxt, t + 1])
        others = q[nxt != nxt[a]]
        if others.size and q[a] - others.max() <= tol.RETURN_ATOL:
            return t
    return len(sol.actions)


# ------------------------------------------------------------------------------------------ 5. batching
def test_batched_solve_equals_separate_solves(solved, episodes, fns):
    """`vmap(solve)` over a stacked batch gives each episode's own table and solution."""
    batch = scenario.stack([episodes["nominal"], episodes["evalB"]])
    tables, sols = _np(fns["vsolve"](batch))
    for i, name in enumerate(["nominal", "evalB"]):
        table, sol = solved[name]
        np.testing.assert_array_equal(tables.next_grasp[i], table.next_grasp)
        tol.assert_close_with_rare_ties(tables.terminal[i], table.terminal, 0, f"{name} terminal", tol.FLIP_FRACTION)
        tol.assert_close_with_rare_ties(tables.reward[i], table.reward, tol.REWARD_ATOL, f"{name} reward")
        tol.assert_close_with_rare_ties(
            tables.ik_error[i], table.ik_error, tol.REWARD_ATOL * RewardConfig().ik_scale, f"{name} IK error"
        )
        tol.assert_close_with_rare_ties(sols.value[i], sol.value, tol.RETURN_ATOL, f"{name} value")
        np.testing.assert_allclose(sols.ret[i], sol.ret, atol=tol.RETURN_ATOL)
        # the sequences agree up to the first choice that is a tie (best and runner-up within RETURN_ATOL)
        n = _clear_steps(table, sol)
        assert n >= 1, "the first choice is a tie"
        np.testing.assert_array_equal(sols.actions[i][:n], sol.actions[:n])
        np.testing.assert_array_equal(sols.grasps[i][: n + 1], sol.grasps[: n + 1])
        np.testing.assert_array_equal(sols.alive[i][:n], sol.alive[:n])
    # the two episodes differ (mass and CoM), so a batch that mixed them up would fail above
    assert not np.allclose(solved["nominal"][0].reward, solved["evalB"][0].reward)


# ------------------------------------------------------------------------------------------ 6. IK count
def _ik_problems(jaxpr, iterations: int, n_joints: int) -> int:
    """Number of IK problems in a jaxpr: every `scan` of `iterations` + 1 steps is an IK solve (the iteration count
    is set to a value nothing else uses; trip 0 evaluates the start); its first carry is q with shape (*batch, J),
    so it solves prod(batch) problems. Recurses into sub-jaxprs (jit, cond, custom derivatives)."""
    count = 0
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan" and eqn.params["length"] == iterations + 1:
            q = eqn.outvars[0].aval
            assert q.shape[-1] == n_joints, f"IK scan carry {q.shape}"
            count += int(np.prod(q.shape[:-1]))
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    count += _ik_problems(inner, iterations, n_joints)
    return count


def test_table_costs_g_times_t_ik_solves(sur, episodes, solved):
    """The table needs G x T IK solves (each grasp at each waypoint), not 3 x G x A x T as stepping would; each
    solve runs from the IK's 1 + len(extra_starts) start configurations.

    Why the jaxpr: a Python counter around `ik.solve` only counts traces (a vmapped call traces once and sees
    unbatched shapes), so instead the traced program is inspected. The IK is a `lax.scan` of a fixed iteration
    count; with the count set to 37 (the wrench solver uses 150) every 37-step scan is an IK call, and its carry
    q has shape (*batch, J): the number of problems is the product of the batch dims (the table in `ik.solve`'s
    vmapped form, `IKConfig.lanes=False`: the batch-last form's carry is (J, batch)). The counter is checked on
    `sur.reset` (1 solve) and `sur.step` (3 solves: the new grasp at the current pose and at the next waypoint, and
    the shared grasp through a change; 2 without the change term) first, so a broken counter cannot pass."""
    iters = 37
    assert iters not in (sur.ik_config.iterations, sur.wrench_config.iterations)
    sur37 = surrogate.Surrogate(sur.hand, ik_config=ik.IKConfig(iterations=iters, lanes=False), learned=False)
    per = 1 + len(sur37.ik_config.extra_starts)  # each IK problem runs from every start configuration
    ep = episodes["nominal"]
    n_g, n_j = sur.space.n_grasps, sur.hand.n_joints
    count = lambda f, *args: _ik_problems(jax.make_jaxpr(f)(*args).jaxpr, iters, n_j)  # noqa: E731
    assert count(sur37.reset, ep) == per
    state = jax.eval_shape(sur37.reset, ep)  # abstract: tracing needs no IK to run
    assert sur37.reward_config.prices_changes and count(sur37.step, state, jnp.int32(3)) == 3 * per
    off = surrogate.Surrogate(sur.hand, RewardConfig(w_wrench_change=0.0, change_falls=False),
                              ik_config=ik.IKConfig(iterations=iters), learned=False)
    assert count(off.step, state, jnp.int32(3)) == 2 * per
    assert count(lambda e: dp.build_table(sur37, e), ep) == n_g * T * per
    full = scenario.make_episode(model=sur.hand)
    assert count(lambda e: dp.build_table(sur37, e), full) == n_g * scenario.N_WAYPOINTS * per
    # and one IK error per (grasp, waypoint) comes out
    table, _ = solved["nominal"]
    assert table.ik_error.shape == (n_g, T)
    assert table.reward.shape == (n_g, sur.n_actions, T) and table.next_grasp.shape == (n_g, sur.n_actions)


def test_the_surrogate_and_a_table_are_step_models(solved, episodes, sur):
    """`Surrogate` and `TableModel` are `protocols.StepModel`s (the table's `step_every` its steps vmapped), the
    policies `Policy`s; what is neither is refused by name."""
    from gsp_jax.planning import policies
    from gsp_jax.surrogate import protocols

    table, _ = solved["evalB"]
    model = dp.TableModel(jax.tree.map(jnp.asarray, table), sur.space)
    policy = policies.TablePolicy(jnp.zeros((sur.space.n_grasps, T), jnp.int32))
    assert isinstance(sur, protocols.StepModel) and isinstance(model, protocols.StepModel)
    assert isinstance(policy, protocols.Policy) and not isinstance(policy, protocols.StepModel)
    state = dp.table_state(episodes["evalB"], model.table, 17, 1)
    every, rewards, done = model.step_every(state)
    for a in (0, 3, sur.n_actions - 1):
        one, r, d = model.step(state, jnp.int32(a))
        assert int(every.grasp[a]) == int(one.grasp) and float(rewards[a]) == float(r) and bool(done[a]) == bool(d)
    with pytest.raises(TypeError, match=r"model: a step model needs reset, step, step_every .*got TablePolicy"):
        protocols.checked(policy)
    with pytest.raises(TypeError, match=r"policy: a policy needs `act\(state\)`.*got TableModel"):
        protocols.checked(model, model)


# ------------------------------------------------------------------------------------------ 7. sequence_return
def test_sequence_return(solved, episodes, fns):
    """`sequence_return` of the optimal actions in their own table is the optimum; in general it equals the
    independent numpy replay; and the nominal optimum replayed in another episode's table (the DP baseline)
    never beats that episode's own DP optimum."""
    for name, (table, sol) in solved.items():
        tab = jax.tree.map(jnp.asarray, table)
        start = episodes[name].start_grasp
        np.testing.assert_allclose(fns["sequence_return"](tab, start, jnp.asarray(sol.actions)), sol.ret, **TOL)
        # random sequences from random starts, against the numpy replay (covers ended episodes: R_MIN is common)
        rng = np.random.default_rng(11)
        for _ in range(10):
            g, acts = int(rng.integers(0, table.reward.shape[0])), rng.integers(0, table.reward.shape[1], T)
            got = fns["sequence_return"](tab, jnp.int32(g), jnp.asarray(acts, jnp.int32))
            np.testing.assert_allclose(got, _replay(table, g, acts)[0], **TOL)
            assert got <= sol.value[g, 0] + 1e-5  # no sequence beats the optimum
    nominal_actions = jnp.asarray(solved["nominal"][1].actions)
    table_b, sol_b = solved["evalB"]
    baseline = fns["sequence_return"](jax.tree.map(jnp.asarray, table_b), episodes["evalB"].start_grasp,
                                      nominal_actions)
    np.testing.assert_allclose(baseline, _replay(table_b, int(episodes["evalB"].start_grasp), nominal_actions)[0],
                               **TOL)
    assert baseline <= sol_b.ret + 1e-5
