"""Tests of gsp_jax.physics: the contact controller in MJX and in C MuJoCo.

MJX on a 2-core CPU is slow (about a minute to compile an episode runner), so one batch of short episodes (the first 5
waypoints of the lift, then 0.5 s of hold) runs once per module in each backend and every
test reads it; the single-episode runner is compiled once more for the batched-vs-single comparison.
"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from flax import struct  # noqa: E402
from mujoco import mjx  # noqa: E402

from gsp_jax import physics  # noqa: E402
from gsp_jax.planning import policies  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.physics import controller as ctl  # noqa: E402
from gsp_jax.surrogate.step import Surrogate  # noqa: E402

T = 5
CONFIG = physics.PhysicsConfig().replace(hold=0.5)
TILT = 10.0  # [deg] the largest tilt the tests allow while the tool is held
ROWS = ("four 2m0 +1Nm", "four 0.5m0 +1Nm", "index alone", "pinch one side", "change every waypoint")


def _short(ep: scenario.Episode) -> scenario.Episode:
    """The episode's first T waypoints (the start of its lift: 4.5 mm in 1 s)."""
    return ep.head(T)


@pytest.fixture(scope="module")
def phys():
    return physics.Physics(Surrogate(learned=False), CONFIG)


@pytest.fixture(scope="module")
def batch(phys):
    """The rows of `ROWS`: four fingertips (ring added at t = 0, then kept) on a 2 m0 (its CoM 1 cm off) and a 0.5 m0
    tool under +1 N m; the index tip alone; index and middle tips on the same side (no opposing contact); four tips
    with a change at every waypoint (the middle tip slides M2 <-> M1), no torque. (Under -1 N m at these low heights
    the grasp throws the tool when the torque comes on: see the README's physics section.)"""
    sp = phys.space
    nominal = scenario.make_episode()
    heavy = scenario.make_episode(mass_factor=2.0, com_y_cm=1.0)  # its CoM 1 cm off: both backends must move it
    light = scenario.make_episode(mass_factor=0.5)
    eps = [_short(heavy), _short(light),
           _short(nominal.replace(start_grasp=sp.encode([0, 1, 0, 0, 0, 0]))),
           _short(nominal.replace(start_grasp=sp.encode([0, 1, 0, 1, 0, 0]))),
           _short(nominal.replace(w_ext=jnp.zeros_like(nominal.w_ext)))]
    ring, keep = sp.action("ring_distal", 1), sp.action("index_distal", 1)
    m1, m2 = sp.action("middle_distal", 1), sp.action("middle_distal", 2)
    acts = jnp.asarray([[ring] + [keep] * (T - 1)] * 2 + [[keep] * T] * 2 + [[ring, keep, m2, m1, m2]], jnp.int32)
    return scenario.stack(eps), policies.SequencePolicy(acts), eps


@pytest.fixture(scope="module")
def runs(phys, batch):
    episodes, policy, _ = batch
    return {b: jax.device_get(phys.simulate_batch(policy, episodes, policy_axis=0, backend=b))
            for b in physics.BACKENDS}


@pytest.mark.parametrize("backend", physics.BACKENDS)
def test_four_fingertips_hold_and_changes_keep_the_tool(runs, backend):
    """Four tips hold a 2 m0 and a 0.5 m0 tool under +1 N m; a change at every waypoint keeps the tool within TILT
    during the lift and holds it."""
    res = runs[backend]
    for row in (0, 1, 4):
        assert not res.fell[row], (ROWS[row], float(res.fall_time[row]))
        assert res.angle_error[row] < 5.0, (ROWS[row], float(res.angle_error[row]))
        assert res.max_angle[row] < TILT, (ROWS[row], float(res.max_angle[row]))
        assert res.position_error[row] < 0.005, (ROWS[row], float(res.position_error[row]))


def test_a_tip_added_at_the_lowest_start_arrives_before_the_pedestals_sink():
    """The lowest start (path -6 mm: the tool 1.4 mm above the table): the ring tip added at waypoint 0 must touch
    the tool before the pedestals sink at 0.25 s, since the three-tip start grasp alone cannot hold it (it needs
    mu > 0.8: `wrench.least_friction`). A free link pulled along the damped least-squares step (`free_stiffness`)
    arrives and the tool is held; with a hundredth of that pull the tip is late and the tool touches the table
    (C MuJoCo, 3 waypoints)."""
    env = Surrogate(learned=False)
    ep = scenario.make_episode(shift_mm=-6.0, torque=0.0).head(3)
    policy = policies.SequencePolicy(jnp.full((1, 3), env.space.action("ring_distal", 1), jnp.int32))
    touched, fell = {}, {}
    for name, stiffness in (("default", CONFIG.fingers.free_stiffness), ("weak", CONFIG.fingers.free_stiffness / 100)):
        phys = physics.Physics(env, CONFIG.replace(free_stiffness=stiffness))
        res = jax.device_get(phys.simulate_batch(policy, scenario.stack([ep]), policy_axis=0, backend="c"))
        m, d = phys.model, mujoco.MjData(phys.model)
        d.qpos[:] = res.qpos[0, phys.n_segment - 1]  # the last tick before the pedestals sink
        mujoco.mj_forward(m, d)
        ring = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "ring_distal")
        touched[name] = any({m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]} == {ring, phys.scene.tool_body}
                            for c in d.contact[: d.ncon])
        fell[name] = bool(res.fell[0]) and float(res.fall_time[0])
    assert touched == {"default": True, "weak": False} and not fell["default"] and 0.25 < fell["weak"] < 0.4, (
        touched, fell)


def _tool_rates(phys, qpos: np.ndarray) -> np.ndarray:
    """(K-1, 3) the tool's angular velocity (its free joint's, MuJoCo's `mj_differentiatePos`) between successive
    configurations qpos (K, nq), in float64."""
    m, v, tick = phys.model, phys.scene.tool_dof, phys.timestep
    qvel = np.zeros(m.nv)
    rates = np.zeros((len(qpos) - 1, 3))
    for k in range(len(qpos) - 1):
        mujoco.mj_differentiatePos(m, qvel, tick, qpos[k], qpos[k + 1])
        rates[k] = qvel[v + 3 : v + 6]
    return rates


def test_the_tool_loop_is_stable_at_the_control_rate():
    """Four tips on a light (0.25 m0) and a heavy (2.5 m0) tool, the reduced lift (first T waypoints) and 1 s under
    the +1 N m torque (C MuJoCo): both held, and the tool's angular velocity about none of its axes alternates tick
    to tick: the energy of the rates' tick-to-tick differences over that of their sums (the part at the control
    rate's Nyquist frequency against the rest), from the pedestals' sinking to the end, < 0.1 (the settings this
    tells apart: docs/physics.md, "The tool loop at the control rate")."""
    config = CONFIG.replace(hold=1.0)
    phys = physics.Physics(Surrogate(learned=False), config)
    masses = (0.25, 2.5)
    eps = [_short(scenario.make_episode(mass_factor=f)) for f in masses]
    ring, keep = phys.space.action("ring_distal", 1), phys.space.action("index_distal", 1)
    policy = policies.SequencePolicy(jnp.asarray([[ring] + [keep] * (T - 1)] * len(masses), jnp.int32))
    res = jax.device_get(phys.simulate_batch(policy, scenario.stack(eps), policy_axis=0, backend="c"))
    assert not np.any(res.fell), (masses, res.fall_time)
    for i, f in enumerate(masses):
        rates = _tool_rates(phys, np.asarray(res.qpos[i, phys.n_segment:], np.float64))
        alternating = np.sum((rates[1:] - rates[:-1]) ** 2, 0) / np.sum((rates[1:] + rates[:-1]) ** 2, 0)
        assert np.all(alternating < 0.1), (f, alternating)


@pytest.mark.parametrize("backend", physics.BACKENDS)
def test_one_fingertip_and_a_one_sided_pinch_drop_the_tool(runs, backend):
    """Without an opposing contact the tool falls once the start pedestals sink away (after 0.25 s)."""
    res = runs[backend]
    for row in (2, 3):
        assert res.fell[row] and res.angle_error[row] == physics.FALLEN_ERROR, ROWS[row]
        assert 0.25 < res.fall_time[row] < 0.75, (ROWS[row], float(res.fall_time[row]))


def test_mjx_and_c_mujoco_agree(runs):
    """The same controller stepped by MJX and by C MuJoCo: the same outcome in every row, hold angles within 2
    degrees and tool paths within 2 mm where held."""
    a, b = runs["mjx"], runs["c"]
    np.testing.assert_array_equal(a.fell, b.fell)
    np.testing.assert_array_equal(a.grasps, b.grasps)
    held = ~np.asarray(a.fell)
    np.testing.assert_allclose(a.angle_error[held], b.angle_error[held], atol=2.0)
    np.testing.assert_allclose(a.position_error[held], b.position_error[held], atol=0.002)


def test_no_nan_and_falls_freeze(phys, runs):
    for res in runs.values():
        assert np.all(np.isfinite(res.qpos)) and np.all(np.isfinite(res.angle))
        k = int(round(float(res.fall_time[2]) / phys.timestep))
        np.testing.assert_array_equal(res.qpos[2, k:], np.broadcast_to(res.qpos[2, k - 1], res.qpos[2, k:].shape))
        assert res.qpos.shape == (5, phys.n_ticks(T), phys.model.nq)


def test_batched_equals_single(phys, batch, runs):
    """Row 1 run alone equals its row in the batch up to float reassociation (which contact dynamics amplify a
    little): tool path within 1 mm, angle within 2 degrees at every tick, the same grasps and outcome."""
    _, policy, eps = batch
    one = jax.device_get(jax.jit(phys.simulate)(policies.SequencePolicy(policy.actions[1]), eps[1]))
    res, a = runs["mjx"], phys.scene.tool_qpos
    np.testing.assert_allclose(one.qpos[:, a : a + 3], res.qpos[1, :, a : a + 3], atol=1e-3)
    np.testing.assert_allclose(one.angle, res.angle[1], atol=2.0)
    assert bool(one.fell) == bool(res.fell[1])
    np.testing.assert_array_equal(one.grasps, res.grasps[1])


def test_reference_motion_interpolates_the_waypoints():
    """The spline passes through every waypoint; its velocity and acceleration are the derivatives of its path
    (central differences), and it stays at the last waypoint afterwards."""
    ep = scenario.make_episode()
    f = jax.jit(ctl.reference_motion)
    for t in range(ep.n_steps):
        np.testing.assert_allclose(f(ep, t * ep.dt).pos, ep.waypoints[t], atol=1e-6)
    h = 1e-3
    for time in (0.3, 1.1, 2.45, 3.6):
        m, a, b = f(ep, time), f(ep, time - h), f(ep, time + h)
        np.testing.assert_allclose(m.vel, (b.pos - a.pos) / (2 * h), atol=2e-4)
        np.testing.assert_allclose(m.acc, (b.vel - a.vel) / (2 * h), atol=2e-2)
    end = f(ep, 10.0)
    np.testing.assert_allclose(end.pos, ep.waypoints[-1], atol=1e-6)
    assert float(jnp.abs(end.vel).max()) == 0.0


def test_rotation_error_matches_mujoco():
    rng = np.random.default_rng(0)
    for _ in range(5):
        q1, q2 = (x / np.linalg.norm(x) for x in rng.normal(size=(2, 4)))
        rel, vel = np.zeros(4), np.zeros(3)
        mujoco.mju_mulQuat(rel, q1, np.array([q2[0], -q2[1], -q2[2], -q2[3]]))
        mujoco.mju_quat2Vel(vel, rel, 1.0)  # the rotation taking q2 to q1, in the world frame
        np.testing.assert_allclose(ctl.rotation_error(jnp.asarray(q1), jnp.asarray(q2)), vel, atol=1e-5)


def test_mjx_finds_the_fingertip_contacts_c_mujoco_finds(phys):
    """The reason for the contact spheres: at the four-tip grasp, MJX's contacts equal C MuJoCo's (mujoco-mjx 3.17
    missed tilted capsule-box contacts entirely)."""
    sur, sp, scene = phys.surrogate, phys.space, phys.scene
    ep = scenario.make_episode()
    c = sur.realise(sp.encode([1, 1, 0, 1, 0, 1]), ep.waypoints[0], ep.quats[0])
    fields = scene.episode_fields(ep)
    mx = scene.mjx_model(fields, 0.0)
    d = mjx.make_data(mx).replace(qpos=scene.initial_qpos(ep, c.ik.q))
    d = jax.jit(mjx.forward)(mx, d)
    m = scene.c_model(jax.device_get(fields))
    cd = mujoco.MjData(m)
    cd.qpos[:] = np.asarray(d.qpos)
    mujoco.mj_forward(m, cd)
    c_dist = sorted(float(x.dist) for x in cd.contact[: cd.ncon])
    dist = np.asarray(d._impl.contact.dist)
    mjx_dist = sorted(float(x) for x in dist[dist < 0])
    assert len(c_dist) >= 4 and len(mjx_dist) == len([x for x in c_dist if x < 0])
    np.testing.assert_allclose(mjx_dist, [x for x in c_dist if x < 0], atol=1e-4)


def test_bad_episodes_errors_name_the_field(phys):
    ep = scenario.stack([scenario.make_episode()])
    pol = policies.SequencePolicy(jnp.zeros(16, jnp.int32))
    with pytest.raises(ValueError, match="episode.dt"):
        phys.simulate_batch(pol, ep.replace(dt=ep.dt * 2))
    with pytest.raises(ValueError, match=r"episodes\[0\]\.mass: -0\.35 kg \(must be within 100x"):
        phys.simulate_batch(pol, ep.replace(mass=-ep.mass))
    with pytest.raises(ValueError, match="backend"):
        phys.simulate_batch(pol, ep, backend="bullet")


def test_pedestal_drop_in_numpy_is_the_jax_value():
    """The C backend computes the pedestals' drop per tick in numpy float32: bit for bit the jax.numpy value."""
    phys = physics.Physics(Surrogate(learned=False), CONFIG)
    ticks = np.arange(0, phys.n_ticks(16), 7)
    ours = [float(phys.scene.pedestal_drop(j * phys.timestep, xp=np)) for j in ticks]
    theirs = [float(phys.scene.pedestal_drop(j * phys.timestep)) for j in ticks]
    assert ours == theirs and min(ours) < 0.0 and max(ours) == 0.0


def test_c_engine_steps_each_episode_as_its_own_model(phys):
    """`c_backend.Engine` (one model copy a episode, stepped from native code through MuJoCo's C API) steps every
    episode bit for bit as `mujoco.mj_step` on that episode's own model (`Scene.c_model`, pedestals set per
    tick) does from Python, under the same motor commands and external wrench; its state rows restore it."""
    from gsp_jax.physics import c_backend, native

    eps = scenario.stack([scenario.make_episode(mass_factor=2.0, com_y_cm=1.0),
                          scenario.make_episode(shift_mm=-6, friction=0.5, mass_factor=0.5)])
    fields = jax.device_get(jax.vmap(phys.scene.episode_fields)(eps))
    qpos0 = np.asarray(jax.vmap(phys.start)(eps)[0], np.float64)
    rng = np.random.default_rng(0)
    lo, hi = phys.scene.model.actuator_ctrlrange.T
    nu = phys.model.nu
    out = np.zeros((40, 2, nu + 9), np.float32)
    out[:, :, :nu] = rng.uniform(0.3 * lo, 0.3 * hi, (40, 2, nu))
    out[:, :, nu:nu + 6] = rng.normal(0.0, 0.2, (40, 2, 6))
    constants = c_backend.native_tick(phys).constants
    eng = c_backend.Engine(phys.scene, fields, qpos0)
    buf = np.zeros(max(phys.model.nq, phys.model.nv, nu, 6))
    trace, states = [], []
    for j in range(40):
        states.append((eng.state(), eng.obs.copy()))
        eng.step(constants, np.arange(2), out[j], -0.001 * j, buf)
        trace.append(eng.obs.copy())
    for e in range(2):
        m = phys.scene.c_model(jax.tree.map(lambda x: x[e], fields))
        d = mujoco.MjData(m)
        d.qpos[:] = qpos0[e]
        mujoco.mj_forward(m, d)
        for j in range(40):
            phys.scene.c_pedestals(m, jax.tree.map(lambda x: x[e], fields), -0.001 * j)
            d.ctrl[:], d.xfrc_applied[phys.scene.tool_body] = out[j, e, :nu], out[j, e, nu:nu + 6]
            mujoco.mj_step(m, d)
            ref = np.concatenate([d.qpos, d.qvel, d.qfrc_bias]).astype(np.float32)
            np.testing.assert_array_equal(trace[j][e], ref)
    eng.restore(*states[10])  # back to tick 10: the same steps again
    for j in range(10, 40):
        eng.step(constants, np.arange(2), out[j], -0.001 * j, buf)
        np.testing.assert_array_equal(eng.obs, trace[j])
    assert native.addresses(eng.models, eng.datas, phys.scene.tool_body).shape == (2, 8)


def test_the_episodes_centre_of_mass_moves_the_tool_in_c_mujoco(phys):
    """An episode's CoM offset (`EpisodeFields.com`, set on a copy of the compiled model) is the tool's in C MuJoCo:
    its inertial frame sits at the offset (MuJoCo's kinematics: xipos = xpos + R com) and, spinning in free flight
    clear of everything, its centre of mass gains g t of velocity as a rigid body's must (Newton, the reference).
    A tool compiled with its CoM at its origin is 'simple' to MuJoCo, which skips both (they held before 2026-12-07:
    the offsets were ignored, 1.9 cm off here)."""
    scene, b = phys.scene, phys.scene.tool_body
    fields = jax.device_get(scene.episode_fields(scenario.make_episode()))
    com = np.array([0.02, -0.01, 0.005], np.float32)
    m = scene.c_model(fields.replace(com=com))
    d = mujoco.MjData(m)
    d.qpos[scene.tool_qpos + 2] += 1.0  # a metre above the hand
    d.qvel[scene.tool_dof + 3:scene.tool_dof + 6] = [3.0, -2.0, 5.0]  # [rad/s], the tool's frame
    mujoco.mj_forward(m, d)
    mujoco.mj_subtreeVel(m, d)
    v0 = d.subtree_linvel[b].copy()
    n = 100
    for _ in range(n):
        mujoco.mj_step(m, d)
    mujoco.mj_forward(m, d)
    mujoco.mj_subtreeVel(m, d)
    assert not any(b in (m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]) for c in d.contact[:d.ncon])
    np.testing.assert_allclose(d.xipos[b] - d.xpos[b], d.xmat[b].reshape(3, 3) @ com, atol=1e-9)
    gained = d.subtree_linvel[b] - v0
    np.testing.assert_allclose(gained, m.opt.gravity * n * m.opt.timestep, atol=2e-3)  # explicit Euler's error: ~4e-4


def test_c_lockstep_of_several_policies_is_each_policy_alone(phys, batch, runs):
    """`simulate_many` in C MuJoCo runs two policies' episodes in one lockstep: each policy's result is the one it
    gets alone (`simulate_batch`), bit for bit, on 1 core and on 2, as one chunk or as two side by side (each
    episode's controller and physics are its own: no arithmetic is shared between rows)."""
    episodes, policy, _ = batch
    keep = policies.SequencePolicy(jnp.full((5, T), phys.space.action("index_distal", 1), jnp.int32))
    both = [jax.device_get(phys.simulate_many([(policy, 0), (keep, 0)], episodes, backend="c", cores=c, workers=w))
            for c, w in ((1, 1), (2, 1), (2, 2))]
    alone = runs["c"]
    for run in both:
        for f in ("qpos", "angle", "fell", "grasps", "angle_error"):
            np.testing.assert_array_equal(getattr(run[0], f), getattr(alone, f), err_msg=f)
            np.testing.assert_array_equal(getattr(run[1], f), getattr(both[0][1], f), err_msg=f)
    assert not np.array_equal(both[0][1].grasps, alone.grasps)  # the second group ran its own policy


@struct.dataclass
class _Opaque:
    """A policy that hides its base's `act_table`: the C lockstep decides it by the JAX decision at every segment."""

    base: object

    def act(self, state):
        return self.base.act(state)


def test_c_lockstep_decides_table_policies_in_numpy_as_jax_does(phys, batch, runs):
    """A policy that reads only its grasp and waypoint (`act_table`: sequences, DP tables) is decided in numpy by
    the C lockstep, and a segment whose grasp stays the same restarts the controller's timeline in numpy
    (`native.keep_grasp`) without a JAX call: the same run, bit for bit, as the JAX decision at every segment (the
    batch's sequences keep the grasp at some segments and change it at others, in the hold none does)."""
    from gsp_jax.physics import c_backend

    episodes, policy, _ = batch
    kept = np.asarray(phys.space.transitions)[np.asarray(runs["c"].grasps)[:, :-1], np.asarray(policy.actions)[:, 1:]]
    assert np.any(kept == np.asarray(runs["c"].grasps)[:, :-1]) and np.any(kept != runs["c"].grasps[:, :-1])
    table = c_backend.action_table(policy, 0, T, phys.space.n_grasps, T)
    assert table is not None and c_backend.action_table(_Opaque(policy), _Opaque(0), T, phys.space.n_grasps, T) is None
    jax_run = jax.device_get(phys.simulate_batch(_Opaque(policy), episodes, policy_axis=_Opaque(0), backend="c"))
    from_table = c_backend.simulate(phys, [(c_backend.ActionTable(np.array(table)), 0)], episodes)[0]
    for f in ("qpos", "angle", "fell", "actions", "grasps", "angle_error"):
        np.testing.assert_array_equal(getattr(runs["c"], f), getattr(jax_run, f), err_msg=f)
        np.testing.assert_array_equal(getattr(from_table, f), getattr(jax_run, f), err_msg=f)
    start = jax.jit(lambda k: jnp.asarray(k * phys.n_segment * phys.timestep, jnp.float32))  # as `Physics.decide`
    for k in range(40):
        assert phys.segment_start(k) == start(k), k


def test_c_pool_keeps_at_most_its_size_the_episode_used_longest_ago_dropped_first(phys):
    """`c_backend.Pool`: a pair given back is taken again for the same episode (its fields' key), a new one is made
    for another episode, and beyond `most` pairs the episode given back longest ago loses its pairs first."""
    from gsp_jax.physics import c_backend

    fields = jax.device_get(phys.scene.episode_fields(scenario.make_episode()))
    other = jax.device_get(phys.scene.episode_fields(scenario.make_episode(mass_factor=2.0)))
    pool, a, b = c_backend.Pool(most=2), c_backend.Pool.key(fields), c_backend.Pool.key(other)
    assert a != b
    m, d = pool.take(phys.scene, a, lambda: fields)
    assert m.body_mass[phys.scene.tool_body] == pytest.approx(float(fields.mass))
    pool.give(a, m, d)
    assert pool.take(phys.scene, a, lambda: fields) == (m, d)  # the same objects again
    assert pool.take(phys.scene, b, lambda: other)[0] is not m
    pool.give(a, m, d)
    pool.give(b, "model b1", "data b1")
    pool.give(b, "model b2", "data b2")  # three kept: episode a's pair (given back longest ago) goes
    assert pool._count == 2 and a not in pool._free and len(pool._free[b]) == 2


def test_c_pool_past_its_size_keeps_no_episode_without_a_pair(phys):
    """`c_backend.Pool` beyond `most`: an episode whose last pair was taken (and not yet given back) leaves the pool,
    so the pairs dropped first are always kept ones (the pool once kept such an episode first in line and failed to
    drop from it)."""
    from gsp_jax.physics import c_backend

    pool, a, b = c_backend.Pool(most=2), b"episode a", b"episode b"
    pool.give(a, "model a1", "data a1")
    pool.give(b, "model b1", "data b1")
    assert pool.take(phys.scene, a, lambda: None) == ("model a1", "data a1")  # a's last pair: a is not kept
    assert a not in pool._free
    pool.give(b, "model b2", "data b2")
    pool.give(b, "model b3", "data b3")  # three pairs kept: one of b's goes
    assert pool._count == 2 and list(pool._free) == [b] and len(pool._free[b]) == 2
    pool.give(a, "model a1", "data a1")  # a given back last: b, given back longest ago, loses a pair
    assert pool._count == 2 and list(pool._free) == [b, a] and len(pool._free[b]) == 1


def test_c_branches_on_a_pool_past_its_size_are_the_runs_without_it(phys, batch, runs, monkeypatch):
    """L1-physics' pattern on a pool of 3 pairs: each episode's snapshot branched twice (two rows of each episode, one
    after the other), three times over: take, give, take again, drop the pairs beyond 3 (with an episode's last pair
    out in a branch while others are given back). Every branch is the uninterrupted run without a pool, bit for bit,
    and the pool never keeps more than its size."""
    from gsp_jax.physics import c_backend

    episodes, policy, _ = batch
    snap = c_backend.simulate(phys, [(policy, 0)], episodes, until=2)
    rows = np.repeat(np.arange(5), 2)
    pick = lambda tree: jax.tree.map(lambda x: np.asarray(x)[rows], tree)  # noqa: E731
    fields = jax.device_get(jax.vmap(phys.scene.episode_fields)(episodes))
    assert len({c_backend.Pool.key(jax.tree.map(lambda x: x[e], fields)) for e in range(5)}) >= 3
    pool = c_backend.Pool(most=3)
    monkeypatch.setitem(phys._kept, "c-pool", pool)
    ref = pick(runs["c"])
    for outcomes in (False, True, False):
        out, = c_backend.simulate(phys, [(pick(policy), 0)], pick(episodes), start=snap.take(rows), outcomes=outcomes)
        if outcomes:
            for got, want in zip(out, (ref.fell, ref.angle_error, ref.actions)):
                np.testing.assert_array_equal(got, want)
        else:
            for f in ("qpos", "angle", "fell", "fall_time", "actions", "grasps", "angle_error"):
                np.testing.assert_array_equal(getattr(out, f), getattr(ref, f), err_msg=f)
        assert pool._count == sum(map(len, pool._free.values())) == 3 and all(pool._free.values())


def test_c_continuation_from_a_snapshot_is_the_original_run(phys, batch, runs):
    """`c_backend.simulate(..., until=2)` stops at the start of segment 2 with a `Snapshot` (MuJoCo's state rows,
    the observation, the controller states, the traces so far); continued from it (`start=`) the run is the
    uninterrupted one bit for bit, and so are its outcomes alone (`outcomes=True`), run on engines used before.
    Branched from it under another policy (the middle tip kept from segment 2 on instead of changed), the rows share
    the past and part from segment 2 on."""
    from gsp_jax.physics import c_backend

    episodes, policy, _ = batch
    snap = c_backend.simulate(phys, [(policy, 0)], episodes, until=2)
    assert snap.segment == 2 and snap.state.shape[0] == 5 and not np.any(snap.actions[:, 2:])
    cont, ref = c_backend.simulate(phys, [(policy, 0)], episodes, start=snap)[0], runs["c"]
    for f in ("qpos", "angle", "fell", "fall_time", "actions", "grasps", "angle_error", "position_error"):
        np.testing.assert_array_equal(getattr(cont, f), getattr(ref, f), err_msg=f)
    # a branch's outcomes alone (`outcomes=True`, what L1-physics reads) are the full result's, bit for bit, from
    # the models and datas the continuation above left in the pool (`c_backend.Pool`: used, not new)
    assert phys._kept["c-pool"]._count >= 5
    (fell, error, actions), = c_backend.simulate(phys, [(policy, 0)], episodes, start=snap, outcomes=True)
    for got, want in ((fell, ref.fell), (error, ref.angle_error), (actions, ref.actions)):
        np.testing.assert_array_equal(got, want)
    acts = np.array(policy.actions)
    acts[4, 2:] = acts[4, 1]  # keep the grasp of segment 1 (the original changes the middle tip at every waypoint)
    other = c_backend.simulate(phys, [(policies.SequencePolicy(jnp.asarray(acts)), 0)], episodes, start=snap)[0]
    k2 = 2 * phys.n_segment
    np.testing.assert_array_equal(other.qpos[:, :k2], ref.qpos[:, :k2])
    np.testing.assert_array_equal(other.qpos[:4], ref.qpos[:4])  # the other rows' actions are the same
    assert other.grasps[4, 2] != ref.grasps[4, 2] and not np.array_equal(other.qpos[4, k2:], ref.qpos[4, k2:])
    with pytest.raises(ValueError, match="start"):
        c_backend.simulate(phys, [(policy, 0)], episodes, start=snap.take([0, 1]))
    with pytest.raises(ValueError, match="until"):
        c_backend.simulate(phys, [(policy, 0)], episodes, start=snap, until=1)


def test_physics_lookahead_takes_the_branch_that_does_best_in_physics(phys):
    """`verified.PhysicsLookahead` (L1-physics) on two short episodes: at each decision the surrogate lookahead's k
    best root actions and each base's own action are branched in C MuJoCo from the current state under each base
    policy, and the best branch's first action is taken (held, then the least angle error, then the surrogate's
    Q). As the branch taken is continued by a candidate of the next decision, the outcomes taken never get worse
    and the episode ends as the last one taken. With one candidate (k = 1, no base actions) that is the root's own
    action: the run equals the root policy's, bit for bit (compared where the root's best Q leads its runner-up by
    more than the float32 reward tolerance, so both programs' argmax agree)."""
    from gsp_jax.physics import verified
    import tolerances as tol

    sp = phys.space
    nominal = scenario.make_episode()
    eps = scenario.stack([_short(nominal).head(3), _short(scenario.make_episode(mass_factor=0.5)).head(3)])
    keep = policies.SequencePolicy(jnp.full((3,), sp.action("index_distal", 1), jnp.int32))
    change = policies.SequencePolicy(jnp.tile(jnp.full((3,), sp.action("middle_distal", 2), jnp.int32), (2, 1)))
    root = policies.Lookahead(keep, phys.surrogate, depth=1, horizon=1)
    two = verified.PhysicsLookahead(root, None, ((keep, None), (change, 0)), k=2, cores=2)  # change: per episode
    res2 = phys.simulate_batch(two, eps, backend="c")
    assert len(two.decisions) == 2 * 3 and all(d.candidates.shape == (2, 3) for d in two.decisions)
    for e in range(2):
        taken = []
        for d in (d for d in two.decisions if d.episode == e):
            qk = d.q[d.candidates[0, :2]]
            assert qk[0] == d.q.max() and qk[0] >= qk[1]  # the surrogate's two best, best first, under both bases
            np.testing.assert_array_equal(d.candidates[:, :2], d.candidates[[1, 0], :2])
            assert d.candidates[0, 2] == keep.actions[d.segment] and d.candidates[1, 2] == change.actions[e, d.segment]
            if d.fell is None:  # not branched: the tool had fallen before this decision
                assert res2.fell[e] and res2.fall_time[e] <= d.segment * phys.segment
                continue
            c, f, a = d.candidates.ravel(), d.fell.ravel(), d.angle_error.ravel()
            pick = np.lexsort((-d.q[c], a, f))[0]
            assert d.chosen == c[pick] and d.base == pick // 3
            taken.append((f[pick], a[pick]))
        assert all(later <= before for before, later in zip(taken, taken[1:])), taken  # (fell, angle) never worse
        assert taken[-1] == (res2.fell[e], res2.angle_error[e])  # the last branch taken is the episode, bit for bit
    assert [d.chosen for d in two.decisions if d.episode == 0] == list(res2.actions[0])
    # branches whose outcome an earlier branch gave are not run again, and bases that read only their grasp and
    # waypoint run as one group decided in numpy (`_run_tabled`): neither changes anything, bit for bit, against
    # every branch run, each base's own group decided by JAX at every segment (the bases' tables hidden)
    every = verified.PhysicsLookahead(root, None, ((_Opaque(keep), None), (_Opaque(change), _Opaque(0))), k=2,
                                      cores=2, reuse=False)
    assert verified._tables(two, phys, eps) is not None and verified._tables(every, phys, eps) is None
    res_every = phys.simulate_batch(every, eps, backend="c")
    assert sum(d.branches for d in two.decisions) < sum(d.branches for d in every.decisions)
    for a, b in zip(two.decisions, every.decisions):
        assert (a.chosen, a.base) == (b.chosen, b.base)
        np.testing.assert_array_equal(a.angle_error, b.angle_error)
    np.testing.assert_array_equal(res2.qpos, res_every.qpos)
    one = verified.PhysicsLookahead(root, None, ((keep, None),), k=1, base_actions=False, cores=2)
    res1, alone = phys.simulate_batch(one, eps, backend="c"), phys.simulate_batch(root, eps, backend="c")
    assert all(d.fell is None and d.base == -1 for d in one.decisions)  # one candidate: nothing to branch
    for d in one.decisions:  # each argmax clear of the two programs' last bits
        assert np.diff(np.sort(d.q)[-2:])[0] > 2 * tol.REWARD_ATOL, (d.segment, np.sort(d.q)[-2:])
    np.testing.assert_array_equal(res1.actions, alone.actions)
    np.testing.assert_array_equal(res1.qpos, alone.qpos)
    with pytest.raises(ValueError, match="backend"):
        phys.simulate_batch(one, eps, backend="mjx")
    with pytest.raises(ValueError, match="k"):
        verified.PhysicsLookahead(root, None, ((keep, None),), k=0)
    with pytest.raises(ValueError, match="bases"):
        verified.PhysicsLookahead(root, None, keep)


def test_physics_lookahead_over_worlds_scores_each_candidate_by_the_share_of_worlds_it_holds_in(phys):
    """L1-physics branching over worlds (`gap`, `worlds`): each episode's planned worlds are drawn from the gap
    (apart from one another, the same in any batch); every candidate is branched once per world, and the action taken
    is the one held in the largest share of them, then the least mean angle error, then the surrogate's Q. At the
    first decision a branch is its whole sequence, so each of its outcomes equals that sequence run alone from the
    start in that world (`c_backend.simulate(..., world=)`, bit for bit; the first episode's). Bad options are
    refused by name."""
    from gsp_jax.physics import c_backend, verified, world

    sp = phys.space
    eps = scenario.stack([_short(scenario.make_episode()).head(2),
                          _short(scenario.make_episode(mass_factor=0.5)).head(2)])
    keep = policies.SequencePolicy(jnp.full((2,), sp.action("index_distal", 1), jnp.int32))
    change = policies.SequencePolicy(jnp.tile(jnp.full((2,), sp.action("middle_distal", 2), jnp.int32), (2, 1)))
    root = policies.Lookahead(keep, phys.surrogate, depth=1, horizon=1)
    gap = world.Gap.named("wide")
    hedge = verified.PhysicsLookahead(root, None, ((keep, None), (change, 0)), k=2, cores=2, gap=gap, worlds=2)
    assert hedge.reuse is False and verified.PhysicsLookahead(root, None, ((keep, None),)).reuse is True
    res = phys.simulate_batch(hedge, eps, backend="c")
    planned = verified.planned_worlds(hedge, phys, eps)
    assert np.asarray(planned.mass).shape == (4,) and len(set(np.asarray(planned.mass).tolist())) == 4
    again = verified.planned_worlds(verified.PhysicsLookahead(root, None, ((keep, None),), gap=gap, worlds=2), phys,
                                    jax.tree.map(lambda x: x[::-1], eps))  # the episodes the other way round
    np.testing.assert_array_equal(np.asarray(again.friction)[:2], np.asarray(planned.friction)[2:])
    assert [d.chosen for d in hedge.decisions if d.episode == 0] == list(res.actions[0])
    for d in hedge.decisions:
        if d.fell is None:
            continue
        assert d.fell.shape == d.angle_error.shape == (2, 3, 2)
        c = d.candidates.ravel()
        pick = np.lexsort((-d.q[c], d.angle_error.mean(-1).ravel(), d.fell.mean(-1).ravel()))[0]
        assert (d.chosen, d.base) == (c[pick], pick // 3)
        if d.segment or d.episode:  # the first decision of the first episode against runs from the start
            continue
        for b, base in enumerate((keep, change)):
            for a in {int(x) for x in d.candidates[b]}:
                seq = np.array(base.actions if b == 0 else base.actions[d.episode])
                seq[0] = a
                one = jax.tree.map(lambda x: x[d.episode:d.episode + 1], eps)
                for w in range(2):
                    (fell, err, _), = c_backend.simulate(
                        phys, [(policies.SequencePolicy(jnp.asarray(seq[None])), 0)], one, outcomes=True,
                        world=world.rows(planned, [2 * d.episode + w]))
                    slot = list(d.candidates[b]).index(a)
                    assert (d.fell[b, slot, w], d.angle_error[b, slot, w]) == (fell[0], err[0]), (b, a, w)
    with pytest.raises(ValueError, match="worlds: 2 worlds need a gap"):
        verified.PhysicsLookahead(root, None, ((keep, None),), worlds=2)
    with pytest.raises(ValueError, match="worlds must be an int >= 1"):
        verified.PhysicsLookahead(root, None, ((keep, None),), gap=gap, worlds=0)
    with pytest.raises(ValueError, match="gap must be a world.Gap"):
        verified.PhysicsLookahead(root, None, ((keep, None),), gap="gap")


def test_c_backend_rejects_bad_cores_by_name(phys, batch):
    episodes, policy, _ = batch
    for bad in (0, -2, 1.5):
        with pytest.raises(ValueError, match="cores"):
            phys.simulate_batch(policy, episodes, policy_axis=0, backend="c", cores=bad)


def test_written_out_3x3_solve_matches_numpy():
    """The controller's closed-form 3x3 solve (free links' damped least squares) against numpy's LU solve, on the
    matrices it meets (J J^T + lambda^2 I, positive definite) and on random well-conditioned ones."""
    rng = np.random.default_rng(1)
    jac = rng.normal(0.0, 0.05, (50, 3, 16))
    m = np.einsum("bij,bkj->bik", jac, jac) + 0.02**2 * np.eye(3)
    m = np.concatenate([m, rng.normal(size=(50, 3, 3)) + 3 * np.eye(3)])
    v = rng.normal(size=(100, 3))
    ours = np.asarray(ctl._solve3(jnp.asarray(m, jnp.float32), jnp.asarray(v, jnp.float32)), np.float64)
    ref = np.linalg.solve(m, v[..., None])[..., 0]
    np.testing.assert_allclose(ours, ref, rtol=2e-3, atol=1e-4 * np.abs(ref).max())


def test_feedback_floor(phys):
    """The pose feedback's force is capped at max(feedback_limit x weight, feedback_floor): a floor below the
    limit leaves it, one above it sets the cap."""
    ep = scenario.make_episode(mass_factor=0.5)
    obs = phys.scene.observe(*(jnp.asarray(x, jnp.float32) for x in (phys.scene.model.qpos0, np.zeros(phys.model.nv),
                                                                        np.zeros(phys.model.nv))))
    obs = obs.replace(tool_pos=obs.tool_pos + jnp.array([0.0, 0.0, -0.5]))  # far below its reference
    ref = ctl.reference_motion(ep, jnp.float32(1.0))
    weight = float(ep.mass) * 9.81
    limit = CONFIG.controller.feedback_limit * weight
    assert 1.0 < limit < 5.0
    for floor in (1.0, 5.0):
        c = physics.Physics(phys.surrogate, CONFIG.replace(feedback_floor=floor)).controller
        force = np.asarray(c.tool_wrench(obs, ep, ref, jnp.zeros(6)))[:3]
        feedforward = float(ep.mass) * (np.asarray(ref.acc) - np.asarray(c.gravity))
        cap = max(limit, floor)
        np.testing.assert_allclose(np.linalg.norm(force - feedforward), cap, rtol=1e-4)
