"""Forward kinematics (gsp_jax.model.kinematics) against MuJoCo's own mj_kinematics / mj_jac on the same model file, and
the batch-last copy of its chain (`ik_lanes.chain`) against it."""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from gsp_jax.model import hand as hand_lib
from gsp_jax.solvers import ik_lanes
from gsp_jax.model import kinematics

N_CONFIGS = 20
TOL = 1e-5  # float32 FK vs float64 MuJoCo [m] / [-]
CAPSULE, SPHERE = int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_SPHERE)


@pytest.fixture(scope="module")
def qs(hand, random_q):
    return random_q(hand, np.random.default_rng(20240601), N_CONFIGS)


@pytest.fixture(scope="module")
def fk(hand):
    """Jitted, vmapped FK outputs: body poses, contact segments, sphere centres and the chain's axes/anchors."""

    def one(q):
        pos, mat, axes, anchors = kinematics.chain(hand, q)
        centre, direction = kinematics.contact_segments(hand, q)
        return dict(
            pos=pos, mat=mat, axes=axes, anchors=anchors, centre=centre, direction=direction,
            spheres=kinematics.sphere_centers(hand, q),
        )

    return jax.jit(jax.vmap(one))


@pytest.fixture(scope="module")
def out(fk, qs):
    return jax.tree.map(np.asarray, fk(jnp.asarray(qs)))


@pytest.fixture(scope="module")
def mj_states(mjmodel, hand, qs):
    """One MjData per configuration after mj_kinematics (+ mj_comPos for Jacobians)."""
    datas = []
    for q in qs:
        d = mujoco.MjData(mjmodel)
        d.qpos[hand.qpos_adr] = q.astype(np.float64)
        mujoco.mj_kinematics(mjmodel, d)
        mujoco.mj_comPos(mjmodel, d)
        datas.append(d)
    return datas


def _body_id(m, name):
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
    assert i >= 0, name
    return i


def test_random_configs_are_within_limits_and_varied(hand, qs):
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    assert np.all(qs >= lo) and np.all(qs <= hi)
    assert np.all(np.ptp(qs, axis=0) > 0.2 * (hi - lo))  # the sample exercises every joint


def test_body_poses_match_mujoco(hand, mjmodel, qs, out, mj_states):
    ids = [_body_id(mjmodel, n) for n in hand.body_names]
    for i, d in enumerate(mj_states):
        np.testing.assert_allclose(out["pos"][i], d.xpos[ids], atol=TOL, err_msg=f"config {i}")
        np.testing.assert_allclose(out["mat"][i], d.xmat[ids].reshape(-1, 3, 3), atol=TOL, err_msg=f"config {i}")


def test_body_poses_function_equals_chain(hand, qs, out):
    pos, mat = kinematics.body_poses(hand, jnp.asarray(qs[0]))
    np.testing.assert_allclose(pos, out["pos"][0], atol=1e-7)
    np.testing.assert_allclose(mat, out["mat"][0], atol=1e-7)


def test_body_poses_move_with_q(hand, mjmodel, mj_states, out):
    """Guard against a trivially passing comparison: the configurations really move the fingertips."""
    tips = [hand.body_names.index(n) for n in hand.body_names if n.endswith("distal")]
    spread = np.ptp(out["pos"][:, tips], axis=0)
    assert np.all(np.max(spread, axis=-1) > 0.03)


def test_joint_axes_and_anchors_match_mujoco(hand, mjmodel, out, mj_states):
    jids = [mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, n) for n in hand.joint_names]
    assert all(j >= 0 for j in jids)
    for i, d in enumerate(mj_states):
        np.testing.assert_allclose(out["axes"][i], d.xaxis[jids], atol=TOL)
        np.testing.assert_allclose(out["anchors"][i], d.xanchor[jids], atol=TOL)


def test_contact_segments_match_mujoco_sites(hand, mjmodel, out, mj_states):
    sids = [mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_SITE, f"contact_{n}") for n in hand.link_names]
    assert all(s >= 0 for s in sids)
    for i, d in enumerate(mj_states):
        np.testing.assert_allclose(out["centre"][i], d.site_xpos[sids], atol=TOL)
        site_z = d.site_xmat[sids].reshape(-1, 3, 3)[:, :, 2]
        np.testing.assert_allclose(out["direction"][i], site_z, atol=TOL)
        np.testing.assert_allclose(np.linalg.norm(out["direction"][i], axis=-1), 1.0, atol=1e-6)


def test_contact_link_half_lengths_and_radii_match_sites(hand, mjmodel):
    for li, n in enumerate(hand.link_names):
        s = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_SITE, f"contact_{n}")
        assert hand.link_radius[li] == pytest.approx(mjmodel.site_size[s][0])
        if int(mjmodel.site_type[s]) == CAPSULE:
            assert hand.link_half[li] == pytest.approx(mjmodel.site_size[s][1])
        else:
            assert hand.link_half[li] == 0.0


def test_closest_on_links_is_the_segment_projection(hand, out, qs, rng):
    """closest_on_links against a brute-force search over points sampled along each segment."""
    q = jnp.asarray(qs[3])
    centre, direction = out["centre"][3], out["direction"][3]
    pts = centre + rng.normal(scale=0.03, size=centre.shape)
    got = np.asarray(kinematics.closest_on_links(hand, q, jnp.asarray(pts, jnp.float32)))
    for li in range(hand.n_links):
        s = np.linspace(-hand.link_half[li], hand.link_half[li], 20001)
        cand = centre[li] + s[:, None] * direction[li]
        best = cand[np.argmin(np.linalg.norm(cand - pts[li], axis=-1))]
        np.testing.assert_allclose(got[li], best, atol=2e-6)


def _sphere_geoms(hand, mjmodel):
    """For each hand sphere, the MuJoCo collision geom (capsule or sphere) of its body that contains it."""
    body_ids = [_body_id(mjmodel, n) for n in hand.body_names]
    geoms = []
    for b in hand.sphere_body:
        gs = [
            g for g in range(mjmodel.ngeom)
            if mjmodel.geom_bodyid[g] == body_ids[b]
            and int(mjmodel.geom_type[g]) in (CAPSULE, SPHERE)
        ]
        assert len(gs) == 1, f"body {hand.body_names[b]} has geoms {gs}"
        geoms.append(gs[0])
    return np.array(geoms)


def test_sphere_centers_lie_on_capsule_axes(hand, mjmodel, out, mj_states):
    geoms = _sphere_geoms(hand, mjmodel)
    np.testing.assert_allclose(hand.sphere_radius, mjmodel.geom_size[geoms, 0], rtol=1e-12)
    for i, d in enumerate(mj_states):
        c = out["spheres"][i]
        rel = c - d.geom_xpos[geoms]
        z = d.geom_xmat[geoms].reshape(-1, 3, 3)[:, :, 2]
        along = np.sum(rel * z, -1)
        perp = rel - along[:, None] * z
        half = np.where(mjmodel.geom_type[geoms] == CAPSULE, mjmodel.geom_size[geoms, 1], 0.0)
        np.testing.assert_allclose(np.linalg.norm(perp, axis=-1), 0.0, atol=TOL)  # on the axis
        assert np.all(np.abs(along) <= half + TOL)  # within the segment


def test_spheres_cover_each_capsule_end_to_end(hand, mjmodel, out, mj_states):
    """Every capsule's chain of spheres starts and ends at the capsule's end points, gaps under the radius."""
    geoms = _sphere_geoms(hand, mjmodel)
    d = mj_states[0]
    c = out["spheres"][0]
    for g in np.unique(geoms):
        sel = geoms == g
        z = d.geom_xmat[g].reshape(3, 3)[:, 2]
        along = np.sort((c[sel] - d.geom_xpos[g]) @ z)
        if int(mjmodel.geom_type[g]) == CAPSULE:
            h, r = mjmodel.geom_size[g][1], mjmodel.geom_size[g][0]
            assert along[0] == pytest.approx(-h, abs=TOL) and along[-1] == pytest.approx(h, abs=TOL)
            assert np.max(np.diff(along)) <= 1.5 * r + TOL


def test_every_hand_collision_geom_has_spheres(hand, mjmodel):
    body_ids = {_body_id(mjmodel, n) for n in hand.body_names if n != "palm"}
    capsules = {
        g for g in range(mjmodel.ngeom)
        if mjmodel.geom_bodyid[g] in body_ids and int(mjmodel.geom_type[g]) == CAPSULE
    }
    assert capsules == set(_sphere_geoms(hand, mjmodel).tolist())


@pytest.fixture(scope="module")
def point_setup(hand):
    rng = np.random.default_rng(7)
    n_b = len(hand.body_names)
    body = np.concatenate([np.arange(n_b), rng.integers(0, n_b, size=15)])
    local = rng.normal(scale=0.02, size=(len(body), 3)).astype(np.float32)
    return body, local


def test_point_jacobian_matches_jacfwd(hand, qs, point_setup):
    body, local = point_setup

    @jax.jit
    def both(q):
        _, _, axes, anchors = kinematics.chain(hand, q)
        pts = kinematics.local_points(hand, q, body, local)
        closed = kinematics.point_jacobian(hand, axes, anchors, body, pts)
        auto = jax.jacfwd(lambda q: kinematics.local_points(hand, q, body, local))(q)
        return closed, auto

    for q in qs[:8]:
        closed, auto = both(jnp.asarray(q))
        assert closed.shape == (len(body), 3, hand.n_joints)
        np.testing.assert_allclose(closed, auto, atol=1e-5)
        assert np.max(np.abs(auto)) > 0.05  # non-trivial Jacobians


def test_direction_jacobian_is_the_direction_times_the_point_jacobian(hand, qs, point_setup):
    """The wrench-twist form (`direction_jacobian`) against the point Jacobian contracted with the direction
    and against autodiff of dirs . points, with the directions held fixed."""
    body, local = point_setup
    dirs = jnp.asarray(np.random.default_rng(4).normal(size=(len(body), 3)), jnp.float32)

    @jax.jit
    def three(q):
        _, _, axes, anchors = kinematics.chain(hand, q)
        pts = kinematics.local_points(hand, q, body, local)
        rows = kinematics.direction_jacobian(hand, kinematics.joint_twists(axes, anchors), body, pts, dirs)
        via_points = jnp.einsum("ni,nij->nj", dirs, kinematics.point_jacobian(hand, axes, anchors, body, pts))
        auto = jax.jacfwd(lambda q: jnp.sum(dirs * kinematics.local_points(hand, q, body, local), -1))(q)
        return rows, via_points, auto

    for q in qs[:8]:
        rows, via_points, auto = three(jnp.asarray(q))
        assert rows.shape == (len(body), hand.n_joints)
        np.testing.assert_allclose(rows, via_points, atol=1e-5)
        np.testing.assert_allclose(rows, auto, atol=1e-5)
        assert np.max(np.abs(auto)) > 0.05


def test_point_jacobian_matches_mujoco_mj_jac(hand, mjmodel, qs, mj_states, point_setup):
    body, local = point_setup
    ids = [_body_id(mjmodel, n) for n in hand.body_names]
    jids = [mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, n) for n in hand.joint_names]
    dofs = mjmodel.jnt_dofadr[jids]
    for i in range(4):
        q = jnp.asarray(qs[i])
        _, _, axes, anchors = kinematics.chain(hand, q)
        pts = np.asarray(kinematics.local_points(hand, q, body, local))
        jac = np.asarray(kinematics.point_jacobian(hand, axes, anchors, body, jnp.asarray(pts)))
        d = mj_states[i]
        for n in range(len(body)):
            jacp = np.zeros((3, mjmodel.nv))
            mujoco.mj_jac(mjmodel, d, jacp, None, pts[n].astype(np.float64), ids[body[n]])
            np.testing.assert_allclose(jac[n], jacp[:, dofs], atol=1e-5)


def test_local_points_match_mujoco(hand, mjmodel, qs, mj_states, point_setup):
    body, local = point_setup
    ids = np.array([_body_id(mjmodel, n) for n in hand.body_names])
    for i in range(4):
        got = np.asarray(kinematics.local_points(hand, jnp.asarray(qs[i]), body, local))
        d = mj_states[i]
        want = d.xpos[ids[body]] + np.einsum("nij,nj->ni", d.xmat[ids[body]].reshape(-1, 3, 3), local)
        np.testing.assert_allclose(got, want, atol=TOL)


def test_vmapped_fk_equals_looped_fk(hand, qs, out):
    one = jax.jit(lambda q: kinematics.body_poses(hand, q))
    for i, q in enumerate(qs):
        pos, mat = one(jnp.asarray(q))
        np.testing.assert_allclose(out["pos"][i], pos, atol=1e-6)
        np.testing.assert_allclose(out["mat"][i], mat, atol=1e-6)


def test_batch_last_chain_equals_chain(hand, qs, out):
    """`ik_lanes.chain` (the batch as the last axis, component by component) against `kinematics.chain`, its
    reference (checked against MuJoCo above), at the random configurations: body poses, joint axes and anchors
    within 1e-6 [m], [-] (two float32 orders of the same products)."""
    ch = jax.jit(lambda q: ik_lanes.chain(hand, q))(jnp.asarray(qs.T))
    n = len(qs)
    vec = lambda v: np.stack([np.broadcast_to(np.asarray(c), (n,)) for c in v], -1)  # noqa: E731  Vec -> (N, 3)
    got = dict(pos=np.stack([vec(p) for p in ch.pos], 1), axes=np.stack([vec(a) for a in ch.axis], 1),
               anchors=np.stack([vec(a) for a in ch.anchor], 1),
               mat=np.stack([np.stack([vec(row) for row in m], -2) for m in ch.mat], 1))
    for name, value in got.items():
        assert value.shape == out[name].shape, name
        np.testing.assert_allclose(value, out[name], atol=1e-6, err_msg=name)


def test_quat_to_mat_matches_mujoco(rng):
    quats = rng.normal(size=(10, 4))
    quats /= np.linalg.norm(quats, axis=-1, keepdims=True)
    got = np.asarray(kinematics.quat_to_mat(jnp.asarray(quats, jnp.float32)))
    for qq, m in zip(quats, got):
        want = np.zeros(9)
        mujoco.mju_quat2Mat(want, qq)
        np.testing.assert_allclose(m, want.reshape(3, 3), atol=1e-6)


def test_scene_loads_in_mjx_and_agrees_with_mujoco(hand):
    """The same model files load in MJX; MJX's own kinematics agree with ours on the hand."""
    from mujoco import mjx

    model = hand_lib.load_mjmodel()
    mx = mjx.put_model(model)
    q = np.asarray(hand.q_start, np.float32) + 0.1
    dx = mjx.make_data(mx).replace(qpos=jnp.asarray(model.qpos0, jnp.float32).at[hand.qpos_adr].set(q))
    dx = jax.jit(mjx.kinematics)(mx, dx)
    body_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in hand.body_names]
    pos, _ = kinematics.body_poses(hand, jnp.asarray(q))
    np.testing.assert_allclose(np.asarray(dx.xpos)[body_ids], np.asarray(pos), atol=1e-5)


@pytest.mark.parametrize("spec, shape_a, shape_b", [
    ("...ij,...j->...i", (5, 3, 3), (5, 3)),
    ("...ij,...jk->...ik", (4, 3, 3), (4, 3, 3)),
    ("...ij,...j->...i", (3, 3), (9, 3)),  # leading axes on one operand only
    ("nj,ji->ni", (7, 3), (3, 3)),
    ("nbj,bji->nbi", (7, 2, 3), (2, 3, 3)),
    ("cij,cej->cei", (8, 3, 3), (8, 2, 3)),
    ("li,lij->lj", (6, 3), (6, 3, 16)),
])
def test_small_einsum_both_forms_match_numpy(spec, shape_a, shape_b):
    """The IK's tiny contractions: the CPU's einsum and the GPU's broadcast-and-sum form against numpy in float64."""
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=shape_a).astype(np.float32), rng.normal(size=shape_b).astype(np.float32)
    ref = np.einsum(spec, a.astype(np.float64), b.astype(np.float64))
    for got in (kinematics.small_einsum(spec, a, b), kinematics._broadcast_einsum(spec, a, b)):
        assert got.shape == ref.shape
        np.testing.assert_allclose(np.asarray(got), ref, atol=2e-6 * max(1.0, np.abs(ref).max()))


def test_gpu_form_of_the_contractions_gives_the_same_fk_and_ik(hand, qs, monkeypatch):
    """`small_einsum` lowers to a broadcast product on a GPU: forced here on the CPU, the chain (against the CPU form
    and so against MuJoCo) and the IK's residuals and Jacobian agree to float32 rounding."""
    from gsp_jax.model import grasps
    from gsp_jax.solvers import ik

    space = grasps.space_of(hand)
    tool_pos, tool_mat = jnp.array([0.0, 0.0, 0.05]), jnp.eye(3)
    active, targets, _ = ik.grasp_targets(hand, space.decode(jnp.int32(5)), tool_pos, tool_mat)

    def outputs(q):
        return kinematics.chain(hand, q), ik.residuals_and_jacobian(hand, ik.IKConfig(), q, active, targets, tool_pos,
                                                                     tool_mat)

    def hinge_switch(q):  # margin - gap of every collision hinge: the Jacobian's rows switch on where it crosses 0
        cfg = ik.IKConfig()
        geo = ik._geometry(hand, *kinematics.body_poses(hand, q), targets, tool_pos, tool_mat)
        on_active = jnp.where(hand.sphere_link >= 0, active[jnp.maximum(hand.sphere_link, 0)], False)
        tool_margin = jnp.where(on_active, -cfg.contact_slack, cfg.clearance)
        return jnp.concatenate([tool_margin - geo.tool_gap, cfg.table_margin - geo.table_gap,
                                cfg.self_margin - geo.self_gap])

    q = jnp.asarray(qs, jnp.float32)
    # the two forms differ by ~1e-7 m: compare only where no hinge sits that close to switching (measured: 1.1e-4 m)
    assert np.abs(np.asarray(jax.vmap(hinge_switch)(q))).min() > 1e-5
    cpu = jax.jit(jax.vmap(outputs))(q)
    monkeypatch.setattr(kinematics, "small_einsum", kinematics._broadcast_einsum)
    gpu = jax.jit(jax.vmap(outputs))(q)
    for a, b in zip(jax.tree.leaves(cpu), jax.tree.leaves(gpu)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-5, rtol=1e-5)


def test_joint_torque_limits_are_the_models_motors(hand, mjmodel):
    """`HandModel.joint_torque_limit`: each hand joint's motor's control range times its gear, read off MuJoCo's
    actuators by joint name; a joint that no motor drives is refused by name."""
    by_joint = {mjmodel.joint(int(mjmodel.actuator_trnid[a, 0])).name: min(-mjmodel.actuator_ctrlrange[a, 0],
                mjmodel.actuator_ctrlrange[a, 1]) * abs(mjmodel.actuator_gear[a, 0]) for a in range(mjmodel.nu)}
    np.testing.assert_array_equal(hand.joint_torque_limit, [by_joint[n] for n in hand.joint_names])
    broken = hand_lib.load_mjmodel().__copy__()
    j0 = mujoco.mj_name2id(broken, mujoco.mjtObj.mjOBJ_JOINT, hand.joint_names[0])
    j1 = mujoco.mj_name2id(broken, mujoco.mjtObj.mjOBJ_JOINT, hand.joint_names[1])
    a = [a for a in range(broken.nu) if broken.actuator_trnid[a, 0] == j0][0]
    broken.actuator_trnid[a, 0] = j1  # two motors on the second joint, none on the first
    with pytest.raises(ValueError, match=hand.joint_names[0]):
        hand_lib.from_mjmodel(broken)
