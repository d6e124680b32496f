"""Tests of the surrogate's motor check: a final wrench beyond what the hand's motors can give is a fall
(`RewardConfig.motor_fall_unmet`, `Surrogate.motor_unmet`), judged against an independent reference, the linear
programme of the physics' feasibility oracle (`wrench.hold_margin`: scipy HiGHS, friction pyramids that bracket the
cones, every joint torque within its motor's limit); and `dp.longest_surviving` against brute-force enumeration.
"""
from __future__ import annotations

import dataclasses
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax import dp, kinematics, scenario, surrogate, wrench  # noqa: E402

N_GRASPS = 48  # grasps of the nominal final pose compared with the LP
SCALES = (0.5, 8.0)  # the external torque times these: grasps that clearly hold the first, clearly not the second


@pytest.fixture(scope="module")
def sur(table_ik):
    return surrogate.Surrogate(ik_config=table_ik)


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


def test_a_torque_beyond_the_motors_is_a_fall_and_said_so(sur, solve_each):
    """The nominal episode with a 1e9 N m final torque: no sequence holds it in the surrogate (its DP optimum is
    r_min), explained as beyond the motors at the final step; with the check off (inf) the same plan of the nominal
    episode ran to its end (the probe of issue 50: planned as held)."""
    ep = scenario.make_episode(torque=1e9)
    table, sol = jax.tree.map(lambda x: x[0], solve_each(sur, scenario.stack([ep])))
    r_min = sur.reward_config.r_min
    assert float(sol.ret) <= r_min
    longest = dp.longest_surviving(table, ep.start_grasp, r_min)
    assert float(longest.ret) == ep.n_steps - 1  # every step but the last can be held
    why = sur.explain(ep, np.asarray(longest.actions))
    assert why.startswith(f"t={ep.n_steps - 1}:") and "beyond the hand's motors" in why, why
    nominal_plan = np.asarray(solve_each(sur, scenario.stack([scenario.make_episode()]))[1].actions[0])
    off = sur.replace(reward=dataclasses.replace(sur.reward_config, motor_fall_unmet=float("inf")))
    assert off.explain(ep, nominal_plan) is None  # without the check the plan holds 1e9 N m
    assert "beyond the hand's motors" in sur.explain(ep, nominal_plan)


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
