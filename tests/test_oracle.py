"""The feasibility oracle (`gsp_jax.physics.oracle`): its verdicts on grasps whose answer is known, its torque rows
against MuJoCo's own Jacobians, and its errors. (`wrench.hold_margin`, the LP under it, is tested against closed
forms and an exact-cone reference in test_wrench.py.)"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax import physics, scenario  # noqa: E402
from gsp_jax.physics.oracle import Oracle  # noqa: E402
from gsp_jax.surrogate import Surrogate  # noqa: E402


@pytest.fixture(scope="module")
def oracle():
    sur = Surrogate()
    return Oracle(sur, physics.Scene(sur.hand))


def test_four_tips_can_hold_and_one_tip_cannot(oracle):
    sp, ep = oracle.space, scenario.make_episode()
    four, index = sp.encode([1, 1, 0, 1, 0, 1]), sp.encode([0, 1, 0, 0, 0, 0])
    assert oracle.check(four, ep, 8).possible and oracle.check(four, ep, 15, hold=True).possible
    one = oracle.check(index, ep, 8)
    assert one.impossible and one.torque_ratio_outer == np.inf
    v = oracle.sequence(ep, [four] * ep.n_steps)
    assert v.possible and not v.impossible and v.points[-1] == "hold" and len(v.points) == ep.n_steps
    drop = oracle.sequence(ep, [four] * 8 + [index] * 8)  # letting go of all but the index tip at t = 8
    assert drop.impossible and drop.worst[0].startswith("t8")


def test_the_motor_limits_decide_for_a_heavy_tool(oracle):
    """A 20 m0 tool: four tips' cones can supply its weight, the motors cannot; the ratio is the peak torque over
    the limit, so doubling the limits halves it."""
    sp, ep = oracle.space, scenario.make_episode(mass_factor=20.0)
    four = sp.encode([1, 1, 0, 1, 0, 1])
    m = oracle.check(four, ep, 15, hold=True)
    assert m.impossible and np.isfinite(m.torque_ratio_outer)
    limit = oracle.torque_limit
    try:
        oracle.torque_limit = 2 * limit
        m2 = oracle.check(four, ep, 15, hold=True)
    finally:
        oracle.torque_limit = limit
    np.testing.assert_allclose(m2.torque_ratio_outer, m.torque_ratio_outer / 2, rtol=1e-5)


def test_torque_rows_are_mujocos_jacobians(oracle):
    """The Jacobians whose transposes map contact forces to joint torques equal `mj_jac` on the physics model at
    the realised configuration and the same link points."""
    sp, ep, scene = oracle.space, scenario.make_episode(mass_factor=1.5), oracle.scene
    q, _, _, realised, x, jac = oracle.realise(sp.encode([1, 1, 0, 1, 0, 1]), ep, 6)
    m, d = scene.model, mujoco.MjData(scene.model)
    d.qpos[scene.hand_qpos] = q
    mujoco.mj_forward(m, d)
    jacp = np.zeros((3, m.nv))
    assert realised.sum() == 4
    for link in np.flatnonzero(realised):
        body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, oracle.hand.body_names[oracle.hand.link_body[link]])
        mujoco.mj_jac(m, d, jacp, None, x[link], body)
        np.testing.assert_allclose(jac[link], jacp[:, scene.hand_dof], atol=2e-5)


def test_gravity_torques_are_the_fingers_weight(oracle):
    """At rest, the bias is the fingers' gravity: zero without gravity, and the torques scale with it."""
    q = np.asarray(oracle.hand.q_start)
    g = oracle.gravity_torques(q)
    assert np.abs(g).max() > 0
    model = oracle.scene.model
    saved = model.opt.gravity.copy()
    try:
        model.opt.gravity[:] = 2 * saved
        np.testing.assert_allclose(oracle.gravity_torques(q), 2 * g, rtol=1e-6, atol=1e-9)
    finally:
        model.opt.gravity[:] = saved


def test_oracle_names_bad_input(oracle):
    ep = scenario.make_episode()
    with pytest.raises(ValueError, match="grasps must have"):
        oracle.sequence(ep, [0, 1, 2])


def test_envelope_summary_counts_regret_and_classes():
    """`experiments.envelope.summarise` on a hand-made pool: a planner's regret counts the episodes where it fell and
    another sequence held; the falls' classes are counted; the AUC is the hold-above-fall probability."""
    from experiments import envelope

    kinds = ["four-tips", "dp-opt", "random0"]
    fell = np.array([[0, 1, 1], [1, 1, 0], [0, 1, 1]], bool)  # episode 1: everything fell
    angle = np.where(fell, 180.0, [[1.0, 0, 0], [0, 0, 2.0], [3.0, 0, 0]])
    returns = np.array([[-1.0, -5, -4], [-6, -5, -1], [-2, -7, -3]])
    feasible = np.ones_like(fell)
    classes = {(0, 1): "necessary", (0, 2): "controller", (1, 0): "controller", (1, 1): "necessary",
               (2, 1): "necessary", (2, 2): "undetermined"}
    out = envelope.summarise(kinds, fell, angle, feasible, returns, classes)
    assert out["kinds"]["four-tips"] == dict(out["kinds"]["four-tips"], falls=2, necessary=1, controller=1, regret=1,
                                             regret_episodes=[2])
    assert out["kinds"]["dp-opt"]["regret"] == 1 and out["kinds"]["dp-opt"]["regret_episodes"] == [0]
    assert out["kinds"]["random0"]["undetermined"] == 1
    holds, falls = returns[~fell], returns[fell]
    brute = np.mean([[h > f for f in falls] for h in holds])
    assert out["pool"]["auc_pooled"] == pytest.approx(brute)
    assert out["pool"]["feasible_hold_share"] == pytest.approx(3 / 9)
