"""The native controller tick (`gsp_jax.physics.native`) against the JAX controller it was written from, and its
kinematic chain and force solve against `kinematics` and `wrench.solve`, the references they were written from.

Tick by tick on recorded states: the C backend runs episodes with the JAX controller (`controller="jax"`), and
at every tick the native tick reads the same controller state and observation; its motor commands, external
wrench, next controller state and status must agree within the precision of the JAX controller's float32
arithmetic (the native one runs in float64). Outcomes: the same episodes with either controller hold or fall
alike and end at the same hold error.
"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax.planning import evaluation, policies  # noqa: E402
from gsp_jax.model import kinematics, scenario  # noqa: E402
from gsp_jax import physics  # noqa: E402
from gsp_jax.solvers import wrench  # noqa: E402
from gsp_jax.physics import c_backend, native  # noqa: E402
from gsp_jax.surrogate.step import Surrogate  # noqa: E402
import tolerances as tol  # noqa: E402

T = 4
CONFIG = physics.PhysicsConfig().replace(hold=0.25)


@pytest.fixture(scope="module")
def phys():
    return physics.Physics(Surrogate(learned=False), CONFIG)


@pytest.fixture(scope="module")
def phys_paper():
    """The paper's controller, its options' face normals (`PhysicsConfig.named("paper")`)."""
    return physics.Physics(Surrogate(learned=False), physics.PhysicsConfig.named("paper", hold=0.25))


@pytest.fixture(scope="module")
def phys_robust():
    """The robust controller (`PhysicsConfig.named("robust")`: the pose filter, the motors' strengths estimated),
    its estimates moved at every tick (no deadband: `controller.STRENGTH_DEADBAND` 0 while the module's tests run)."""
    from gsp_jax.physics import controller

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(controller, "STRENGTH_DEADBAND", 0.0)
        yield physics.Physics(Surrogate(learned=False), physics.PhysicsConfig.named("robust", hold=0.25))


PHYS = {"measured": "phys", "paper": "phys_paper", "robust": "phys_robust"}


@pytest.fixture(scope="module")
def episodes():
    """Three evaluation episodes (their first T waypoints) and a fourth with the CoM off-centre under a torque."""
    eps = [e.head(T) for e in list(scenario.eval_set_a().values())[:3]]
    eps.append(scenario.make_episode(mass_factor=1.5, com_y_cm=1.0).head(T))
    return scenario.stack(eps)


def _four_tips_then_changes(phys):
    """Four tips reached at the first waypoints, then the middle tip moved and moved back: every phase of a grasp
    change (unload, travel, arrive, load) in T segments."""
    sp = phys.space
    acts = np.asarray(evaluation.four_tips(sp, T)).copy()
    acts[-2:] = [sp.action("middle_distal", 2), sp.action("middle_distal", 1)]
    return policies.SequencePolicy(jnp.asarray(acts), sp)


def test_native_state_layout_is_the_flat_controller_state(phys, episodes):
    """`native.state_offsets` finds each field of a `ControllerState` where `ravel_pytree` puts it."""
    _, cs = jax.vmap(phys.start)(episodes)
    one = jax.tree.map(lambda x: np.asarray(x)[0], cs)
    flat = np.asarray(jax.flatten_util.ravel_pytree(jax.tree.map(lambda x: np.asarray(x, np.float32), one))[0])
    offsets = native.state_offsets(one)
    for name, start in offsets.items():
        value = np.asarray(getattr(one, name), np.float32).ravel()
        np.testing.assert_array_equal(flat[start:start + value.size], value, err_msg=name)


@pytest.mark.parametrize("controller", ["paper", "measured", "robust"])
def test_native_tick_is_the_jax_tick_on_recorded_states(controller, request, episodes):
    """At every tick of four short episodes (JAX controller, C MuJoCo), the native tick from the same state and
    observation gives the JAX tick's motor commands (within 1e-4 N m), external wrench (1e-5 N), next controller state
    (within 1e-3 in force units: the warm-started force solves carry float32 rounding) and status: the angle
    within three float32 steps of its arccos near 0 (`tolerances.STATUS_ANGLE_ATOL_DEG`, 0.069 deg), the same
    falls. For the named controllers (the default's measured frames: the tool's surface normals at the touching
    links; the paper's face normals; the robust one's filtered pose and strength estimates)."""
    phys = request.getfixturevalue(PHYS[controller])
    policy = _four_tips_then_changes(phys)
    run = c_backend._Lockstep(phys, [(policy, None)], episodes, 1, None, controller="jax")
    tick = c_backend.native_tick(phys)
    n, nu, nq = len(episodes.mass), phys.model.nu, phys.model.nq
    rows, worst = np.arange(n), {"ctrl": 0.0, "ext": 0.0, "cs": 0.0, "angle": 0.0}
    changing = 0
    for k in range(T + phys.n_hold):
        run.decide(k)
        eng = run.engine
        for i in range(phys.n_segment):
            j = k * phys.n_segment + i
            cs_native, out_native = run.cs.copy(), np.zeros_like(run.out)
            tick(j, rows, cs_native, eng.obs, run.ep_native, out_native)
            cs, out = run.pr.tick(run.cs, eng.obs, eng.seen, run.ep_flat, j)
            run.cs, out = np.array(cs), np.asarray(out)
            changed = tick.constants.state.changed
            changing += int(np.sum(run.cs[:, changed:changed + phys.hand.n_links]))
            worst["ctrl"] = max(worst["ctrl"], np.abs(out_native[:, :nu] - out[:, :nu]).max())
            worst["ext"] = max(worst["ext"], np.abs(out_native[:, nu:nu + 6] - out[:, nu:nu + 6]).max())
            worst["cs"] = max(worst["cs"], np.abs(cs_native - run.cs).max())
            if j > 0:
                worst["angle"] = max(worst["angle"], np.abs(out_native[:, nu + 6] - out[:, nu + 6]).max())
                np.testing.assert_array_equal(out_native[:, -1], out[:, -1], err_msg=f"fell at tick {j}")
                run.record(rows, j - 1, out[:, nu + 6:], eng.obs[:, :nq])
            alive = rows[~run.fell]
            if alive.size:
                eng.step(tick.constants, alive, out, float(phys.scene.pedestal_drop(j * phys.timestep, xp=np)),
                         np.zeros(64))
    assert changing > 0  # grasp changes were under way
    if controller == "robust":  # the estimates moved (the strengths) and filtered (the pose)
        off, J = tick.constants.state, len(phys.scene.hand_dof)
        assert np.abs(run.cs[:, off.strength:off.strength + J] - 1).max() > 1e-3
    assert worst["ctrl"] < 1e-4 and worst["ext"] < 1e-5 and worst["cs"] < 1e-3, worst
    assert worst["angle"] < tol.STATUS_ANGLE_ATOL_DEG, worst
    assert not np.any(run.fell)


@pytest.mark.parametrize("controller", ["paper", "measured", "robust"])
def test_native_and_jax_controllers_give_the_same_outcomes(controller, request, episodes):
    """The whole lockstep with either tick: the same falls, hold errors within 0.02 deg (the physics
    carries the last-bit differences forward: measured 6e-4 deg on the 27 evaluation episodes, full length)."""
    phys = request.getfixturevalue(PHYS[controller])
    policy = _four_tips_then_changes(phys)
    res = {c: c_backend.simulate(phys, [(policy, None)], episodes, controller=c)[0] for c in c_backend.CONTROLLERS}
    np.testing.assert_array_equal(res["native"].fell, res["jax"].fell)
    np.testing.assert_array_equal(res["native"].grasps, res["jax"].grasps)
    np.testing.assert_allclose(res["native"].angle_error, res["jax"].angle_error, atol=0.02)
    assert not np.any(res["native"].fell)
    with pytest.raises(ValueError, match="controller"):
        c_backend.simulate(phys, [(policy, None)], episodes, controller="python")


@pytest.mark.parametrize("model", ["wrench", "screwdriver"])
def test_native_measured_normal_is_the_jax_one(model, rng):
    """`native._measured_normal` (float64) against `Controller.measured_normals` (float32), the tool at a random
    pose: at random points around it, boxes (the wrench) and round primitives (the screwdriver's cylinders), the
    tool surface's unit inward normal within 1e-4 (float32 rounding of the distance's square root near the
    surface), the nominal one for links not touching; at points exactly on its surface, where the SDF gradient can
    vanish, a unit normal still (the nominal one where it does)."""
    from gsp_jax.model import load as model_lib

    phys_m = physics.Physics(Surrogate(model_lib.load_model(model), learned=False))
    hand, ctl = phys_m.hand, phys_m.spec.controller
    K = c_backend.native_tick(phys_m).constants.hand
    lo, hi = np.asarray(hand.tool_bounds(), np.float64)
    scratch = [np.zeros(3) for _ in range(4)]

    def both(local, p, mat, touching):
        x = (p + local @ mat.T).astype(np.float32)
        nominal = np.tile(np.float32([0.0, 0.0, 1.0]), (len(x), 1))
        want = np.asarray(ctl.measured_normals(jnp.asarray(x), jnp.asarray(p, jnp.float32),
                                               jnp.asarray(mat, jnp.float32), jnp.asarray(nominal),
                                               jnp.asarray(touching)), np.float64)
        got = nominal.astype(np.float64)
        for k in np.flatnonzero(touching):
            native._measured_normal(K, p, mat, x[k].astype(np.float64), got[k], *scratch)
        assert np.all(np.isfinite(got)) and np.all(np.isfinite(want))
        return got, want, nominal

    q = rng.normal(size=4)
    mat = np.asarray(kinematics.quat_to_mat(jnp.asarray(q / np.linalg.norm(q), jnp.float32)), np.float64)
    touching = np.arange(200) % 5 > 0  # and some links not touching: their nominal normal
    got, want, nominal = both(rng.uniform(lo - 0.02, hi + 0.02, size=(200, 3)), rng.uniform(-0.1, 0.1, 3), mat,
                              touching)
    np.testing.assert_allclose(np.linalg.norm(got[touching], axis=-1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(got[~touching], nominal[~touching])
    np.testing.assert_array_equal(want[~touching], nominal[~touching])
    assert np.abs(got - want).max() < 1e-4, np.abs(got - want).max()
    # points exactly on the surface (box face centres, round primitives' sides), where the SDF gradient can vanish
    # (it does at the wrench's face centres in float32): a unit normal still, the tool's or the nominal one
    cand = [np.asarray(c) + np.asarray(r)[:, a] * h[a] * sgn
            for c, r, h in zip(hand.tool_box_pos, hand.tool_box_mat, hand.tool_box_half)
            for a in range(3) for sgn in (-1.0, 1.0)]
    cand += [np.asarray(c) + np.asarray(r)[:, 0] * s[0]
             for c, r, s in zip(hand.tool_round_pos, hand.tool_round_mat, hand.tool_round_size)]
    got, want, _ = both(np.array(cand, np.float64).reshape(-1, 3), np.zeros(3), np.eye(3), np.ones(len(cand), bool))
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(want, axis=-1), 1.0, atol=1e-6)


def test_native_chain_and_links_are_kinematics(phys, rng):
    """`native._chain` and `native._links` (float64) against `kinematics.chain` and
    `kinematics.closest_on_links_and_jacobians` (float32, themselves checked against MuJoCo in
    tests/test_kinematics.py) at random joint angles within the limits and random points near the links: body poses,
    joint axes and anchors, the links' nearest points and their Jacobians within 1e-6 [m], [-], [m/rad] (float32
    rounding of a few 3x3 products: ~1e-7 seen)."""
    hand = phys.hand
    K = c_backend.native_tick(phys).constants
    S = native.scratch(K)
    n_b, n_j, n_l = len(hand.body_parent), hand.n_joints, hand.n_links
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    qs = rng.uniform(lo, hi, size=(8, n_j)).astype(np.float32)

    def reference(q, near):
        return kinematics.chain(hand, q), kinematics.closest_on_links_and_jacobians(hand, q, near)

    ref = jax.jit(reference)
    for q in qs:
        (pos_w, mat_w, axes_w, anchors_w), (x_w, jac_w) = ref(jnp.asarray(q), jnp.zeros((n_l, 3)))
        near = (np.asarray(x_w, np.float64) + rng.normal(0.0, 0.02, (n_l, 3))).astype(np.float32)
        _, (x_w, jac_w) = ref(jnp.asarray(q), jnp.asarray(near))
        pos, mat = np.zeros((n_b, 3)), np.zeros((n_b, 3, 3))
        axes, anchors = np.zeros((n_j, 3)), np.zeros((n_j, 3))
        native._chain(K.hand, q.astype(np.float64), pos, mat, axes, anchors, np.zeros((3, 3)), np.zeros((3, 3)))
        for name, got, want in (("pos", pos, pos_w), ("mat", mat, mat_w), ("axes", axes, axes_w),
                                ("anchors", anchors, anchors_w)):
            np.testing.assert_allclose(got, np.asarray(want), atol=1e-6, err_msg=name)
        x, jac = np.zeros((n_l, 3)), np.zeros((n_l, 3, n_j))
        native._links(K.hand, q.astype(np.float64), near.astype(np.float64), x, jac, pos, mat, axes, anchors, S)
        np.testing.assert_allclose(x, np.asarray(x_w), atol=1e-6, err_msg="closest points")
        np.testing.assert_allclose(jac, np.asarray(jac_w), atol=1e-6, err_msg="Jacobians")


def test_native_force_solve_is_the_wrench_solve(phys, rng):
    """`native._solve` (float64) against `wrench.solve` ("apg", the controller's config, `Controller._forces`'
    preferred grip and warm start; float32) on random grasps of 2 to 4 active contacts of L around a tool-sized
    centre, random wrenches, friction and warm starts: the same fixed iterations, so the same forces within 2e-4 N
    (float32 rounding carried through `force_iterations` momentum steps: ~4e-5 N seen, on forces of 1-5 N; one
    iteration fewer moves them ~1.6e-3 N)."""
    K = c_backend.native_tick(phys).constants
    S = native.scratch(K)
    ctl = phys.controller
    n_l = phys.hand.n_links
    grip = K.controller.grip_force

    @jax.jit
    def reference(points, normals, active, mu, required, center, init):
        return wrench.solve(points, normals, active, mu, required, center, ctl.wrench_config, init,
                            grip * normals).forces

    worst = 0.0
    for _ in range(16):
        center = rng.normal(0.0, 0.02, 3)
        points = center + rng.normal(0.0, 0.03, (n_l, 3))
        normals = center - points + rng.normal(0.0, 0.01, (n_l, 3))  # inward, roughly
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        active = np.zeros(n_l, bool)
        active[rng.choice(n_l, rng.integers(2, 5), replace=False)] = True
        mu = float(rng.uniform(0.3, 1.0))
        required = np.concatenate([rng.normal(0.0, 3.0, 3), rng.normal(0.0, 0.1, 3)])
        init = rng.normal(0.0, 2.0, (n_l, 3))
        points, normals, required, center, init = (np.asarray(x, np.float32)
                                                    for x in (points, normals, required, center, init))
        mu = np.float32(mu)
        want = np.asarray(reference(points, normals, active, mu, required, center, init))
        got = np.zeros((n_l, 3))
        f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
        native._solve(K.controller, f64(points), f64(normals), active, float(mu), f64(required), f64(center),
                      f64(init), got, S)
        assert np.all(got[~active] == 0)
        worst = max(worst, np.abs(got - want).max())
    assert worst < 2e-4, worst


def test_warm_up_compiles_the_native_code_in_the_background(phys):
    """`c_backend.warm_up` (the demo's: numba's compile beside XLA's) runs a real C MuJoCo episode in another
    thread: its future gives None, and the lockstep's native entry points are compiled for the types a run passes."""
    future = c_backend.warm_up(phys)
    assert future.result(timeout=600) is None
    for entry in (native.segment, native.status_rows):
        assert entry.signatures, entry.__name__
