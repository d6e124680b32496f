"""The feasibility oracle (`gsp_jax.physics.oracle`): its verdicts on grasps whose answer is known, its torque rows
against MuJoCo's own Jacobians, and its errors. (`wrench.hold_margin`, the LP under it, is tested against closed
forms and an exact-cone reference in test_wrench.py.)"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax import physics  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.physics.oracle import Oracle  # noqa: E402
from gsp_jax.surrogate.step import Surrogate  # noqa: E402


@pytest.fixture(scope="module")
def oracle():
    sur = Surrogate(learned=False)
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


def _ik_configuration(oracle, grasp, ep, t):
    """(nq,) the physics model's configuration with the hand at `grasp`'s IK solution at waypoint t and the tool
    at waypoint t's pose."""
    scene = oracle.scene
    q = oracle.realise(grasp, ep, t)[0]
    qpos = np.asarray(scene.model.qpos0, float).copy()
    qpos[scene.hand_qpos] = q
    a = scene.tool_qpos
    qpos[a : a + 3], qpos[a + 3 : a + 7] = np.asarray(ep.waypoints[t]), np.asarray(ep.quats[t])
    return qpos


def test_reached_configuration_reads_the_contacts_off_the_hand(oracle):
    """At the IK's own configuration, the oracle on the reached configuration (contacts where the links' centre lines
    come nearest their options, on the faces) agrees with the IK's: the same Jacobians, contacts within the IK's 5 mm
    acceptance, and four tips' torque ratios within 10% (the points differ by those millimetres); one tip cannot
    hold at either. Moving the tool 2 cm along the faces' normals (y) moves every contact with its face, and the
    torque rows are `mj_jac` at the links' points of the new configuration."""
    sp, ep, scene = oracle.space, scenario.make_episode(mass_factor=1.5), oracle.scene
    four, index = sp.encode([1, 1, 0, 1, 0, 1]), sp.encode([0, 1, 0, 0, 0, 0])
    for t, hold in ((6, False), (15, True)):
        qpos = _ik_configuration(oracle, four, ep, t)
        _, pts_ik, _, realised, _, jac_ik = oracle.realise(four, ep, t)
        _, pts, nrm, carried, jac, _ = oracle.at_configuration(four, qpos)
        np.testing.assert_array_equal(carried, realised)
        np.testing.assert_allclose(jac[carried], jac_ik[carried], atol=1e-5)
        assert np.linalg.norm(pts - pts_ik, axis=-1)[carried].max() < 5e-3
        ik, reached = oracle.check(four, ep, t, hold=hold), oracle.check_at(four, ep, qpos, None if hold else t)
        assert reached.possible and reached.torque_ratio_outer == pytest.approx(ik.torque_ratio_outer, rel=0.1)
        assert oracle.check_at(index, ep, _ik_configuration(oracle, index, ep, t), t).impossible
    qpos = _ik_configuration(oracle, four, ep, 6)
    moved = qpos.copy()
    moved[scene.tool_qpos + 1] += 0.02
    _, pts0, _, carried, _, _ = oracle.at_configuration(four, qpos)
    q, pts1, _, _, jac1, _ = oracle.at_configuration(four, moved)
    np.testing.assert_allclose((pts1 - pts0)[carried][:, 1], 0.02, atol=1e-6)  # on the faces, which moved
    m, d = scene.model, mujoco.MjData(scene.model)
    d.qpos[:] = moved
    mujoco.mj_forward(m, d)
    jacp = np.zeros((3, m.nv))
    for link in np.flatnonzero(carried):  # the Jacobian at the link's own point (centre line) is mj_jac there
        body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, oracle.hand.body_names[oracle.hand.link_body[link]])
        x, jx = oracle._links_at(q.astype(np.float32), pts1.astype(np.float32))
        mujoco.mj_jac(m, d, jacp, None, np.asarray(x[link], float), body)
        np.testing.assert_allclose(jac1[link], jacp[:, scene.hand_dof], atol=2e-5)


def test_reached_verdict_checks_each_decision_up_to_the_fall(oracle):
    """`Oracle.simulated` on a made-up run (the IK configuration of each waypoint held for a segment's ticks): each
    point is `check_at` of the grasp then in force; points from the fall on read nan and decide nothing."""
    sp, ep = oracle.space, scenario.make_episode()
    four, three = sp.encode([1, 1, 0, 1, 0, 1]), sp.encode([1, 1, 0, 1, 0, 0])
    T, n = ep.n_steps, 3
    grasps = [four] * 8 + [three] * 8
    rows = [_ik_configuration(oracle, grasps[t - 1], ep, min(t, T - 1)) for t in range(1, T + 1)]
    qpos = np.repeat(np.stack(rows), n, axis=0)  # tick t * n - 1 is row t - 1
    v = oracle.simulated(ep, grasps, qpos, n)
    assert v.points[0] == "t1" and v.points[-1] == "hold" and len(v.points) == T
    for t in (1, 9, T):
        m = oracle.check_at(grasps[t - 1], ep, rows[t - 1], None if t == T else t)
        assert v.ratio_outer[t - 1] == pytest.approx(m.torque_ratio_outer, rel=1e-9)
    cut = oracle.simulated(ep, grasps, qpos, n, fall_tick=5 * n)
    assert np.all(np.isfinite(cut.ratio_outer[:5])) and np.all(np.isnan(cut.ratio_outer[5:]))
    assert cut.worst[0] in cut.points[:5] and not cut.possible


def test_oracle_names_bad_input(oracle):
    ep = scenario.make_episode()
    with pytest.raises(ValueError, match="grasps must have"):
        oracle.sequence(ep, [0, 1, 2])
    with pytest.raises(ValueError, match="qpos must be a finite"):
        oracle.check_at(0, ep, np.full(3, np.nan))
    with pytest.raises(ValueError, match="qpos must be"):
        oracle.simulated(ep, [0] * ep.n_steps, np.zeros((4, oracle.scene.model.nq)), 10)


def test_envelope_summary_counts_regret_and_classes():
    """`gsp_jax.physics.envelope.summarise` on a hand-made pool: a planner's regret counts the episodes where it fell
    and another sequence held; the falls' classes are counted; the AUC is the hold-above-fall probability."""
    from gsp_jax.physics import envelope

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
    assert "predicted_hold" not in out["pool"]  # without the learned term
    hold = np.array([[0.9, 0.2, 0.5], [0.4, 0.6, 0.8], [0.7, 0.1, 0.3]])  # >= 0.5: (0,0) (0,2) (1,1) (1,2) (2,0)
    pool = envelope.summarise(kinds, fell, angle, feasible, returns, classes, hold=hold)["pool"]
    assert pool["predicted_hold"] == 5 and pool["predicted_hold_share"] == pytest.approx(3 / 5)


def test_the_envelope_oracle_process_judges_the_callers_model():
    """`envelope.classify`'s worker processes start with the library's default model; they are handed the caller's
    (`--model`), so a hammer's falls are judged on the hammer's hand, not silently on the shipped wrench."""
    from gsp_jax.model import load as model_lib
    from gsp_jax.physics import envelope

    hammer = model_lib.load_model("hammer")
    try:
        envelope._start_worker(str(hammer.path))
        assert envelope._ORACLE.surrogate.model.name == "hammer"
    finally:
        envelope._ORACLE = None
    assert model_lib.load_model().name == model_lib.DEFAULT  # the worker's model is its own, not the process's
