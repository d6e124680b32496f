"""The world gap (gsp_jax.physics.world): named levels, draws within their ranges, refusals by name, the nominal
world bit for bit, and a drawn world applied to both backends' models alike (issue 85)."""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax import physics  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.physics import world  # noqa: E402
from gsp_jax.planning import evaluation, policies  # noqa: E402
from gsp_jax.surrogate.step import Surrogate  # noqa: E402


@pytest.fixture(scope="module")
def phys():
    return physics.Physics(Surrogate(learned=False), physics.PhysicsConfig().replace(hold=0.3))


@pytest.mark.parametrize("field, value", [("mass", 0.95), ("friction", -0.1), ("com", 0.05), ("com", float("nan")),
                                          ("delay", 2.5), ("delay", -1), ("joint_noise", 0.5), ("mass", True)])
def test_a_gap_outside_its_physical_range_is_refused_by_name(field, value):
    with pytest.raises(ValueError, match=f"Gap.{field}"):
        world.Gap().replace(**{field: value})
    with pytest.raises(ValueError, match="unknown level 'tiny'"):
        world.Gap.named("tiny")


@pytest.mark.parametrize("level", sorted(world.LEVELS))
def test_draws_are_finite_and_within_their_documented_ranges(level):
    gap = world.Gap.named(level)
    n, L, J = 512, 6, 16
    w = jax.device_get(world.draw(gap, jax.random.PRNGKey(3), n, L, J))
    for name in world.RELATIVE:
        x = np.asarray(getattr(w, name))
        half = getattr(gap, name)
        assert np.all(np.isfinite(x)) and np.all(x >= 1 - half - 1e-6) and np.all(x <= 1 + half + 1e-6), name
        if half:  # the range is used, not a corner of it
            assert np.ptp(x) > half, name
    assert np.asarray(w.inertia).shape == (n, 3) and np.all(np.abs(w.com) <= gap.com + 1e-9)
    assert set(np.unique(w.delay)) == set(range(gap.delay + 1))
    np.testing.assert_array_equal(w.noise, np.broadcast_to([gap.pose_noise, gap.angle_noise, gap.joint_noise],
                                                           (n, 3)).astype(np.float32))
    if level == "nominal":  # exactly the nominal world
        one = jax.device_get(world.nominal(L, J))
        jax.tree.map(lambda a, b: np.testing.assert_array_equal(a, np.broadcast_to(b, a.shape)), w, one)
    again = jax.device_get(world.draw(gap, jax.random.PRNGKey(3), n, L, J))  # one key, one world
    jax.tree.map(np.testing.assert_array_equal, w, again)


def _episodes(n_steps=3):
    eps = list(scenario.episode_set("eval").values())[:2]
    return scenario.stack([e.head(n_steps) for e in eps])


def test_the_nominal_world_is_todays_check_bit_for_bit(phys):
    """C MuJoCo, four tips on two short episodes: world=None and the nominal level's draw give identical runs."""
    eps = _episodes()
    policy = policies.SequencePolicy(jnp.asarray(evaluation.four_tips(phys.space, eps.n_steps)))
    w = world.draw(world.Gap.named("nominal"), jax.random.PRNGKey(0), 2, phys.scene.n_touch,
                   len(phys.scene.hand_dof))
    a = phys.simulate_batch(policy, eps, backend="c", cores=1)
    b = phys.simulate_batch(policy, eps, backend="c", cores=1, world=w)
    jax.tree.map(lambda x, y: np.testing.assert_array_equal(np.asarray(x), np.asarray(y)), a, b)
    gap = world.Gap.named("wide").replace(delay=0, pose_noise=0.0, angle_noise=0.0, joint_noise=0.0)
    wide = world.draw(gap, jax.random.PRNGKey(0), 2, phys.scene.n_touch, len(phys.scene.hand_dof))
    c = phys.simulate_batch(policy, eps, backend="c", cores=1, world=wide)
    assert not np.array_equal(np.asarray(a.qpos), np.asarray(c.qpos))  # another world, another run


def test_a_drawn_world_sets_both_backends_models_as_drawn(phys):
    """The world's factors land on the right fields: the C model (float64) and the MJX model (float32) of one
    episode agree with each other and with the nominal model's values times the draw."""
    scene = phys.scene
    eps = _episodes()
    gap = world.Gap.named("wide").replace(delay=0, pose_noise=0.0, angle_noise=0.0, joint_noise=0.0)
    w = world.draw(gap, jax.random.PRNGKey(1), 2, scene.n_touch, len(scene.hand_dof))
    fields = jax.device_get(jax.vmap(scene.episode_fields)(eps, w))
    one = jax.tree.map(lambda x: np.asarray(x)[1], fields)
    w1 = jax.tree.map(lambda x: np.asarray(x)[1], jax.device_get(w))
    m, base, mx = scene.c_model(one), scene.model, scene.mjx_model(one, jnp.float32(0.0))
    b, pairs, dof, act = scene.tool_body, scene.finger_tool_pairs, scene.hand_dof, scene.hand_act
    np.testing.assert_allclose(m.body_mass[b], float(eps.mass[1]) * float(w1.mass), rtol=1e-6)
    np.testing.assert_allclose(m.body_inertia[b], np.asarray(eps.inertia[1]) * w1.inertia, rtol=1e-6)
    np.testing.assert_allclose(m.body_ipos[b], np.asarray(eps.com[1]) + w1.com, atol=1e-7)
    np.testing.assert_allclose(m.pair_friction[pairs, 0], float(eps.friction[1]) * w1.friction[scene.pair_link],
                               rtol=1e-6)
    np.testing.assert_allclose(m.pair_solref[pairs, 0], base.pair_solref[pairs, 0] * w1.softness[scene.pair_link],
                               rtol=1e-6)
    np.testing.assert_allclose(m.dof_damping[dof], base.dof_damping[dof] * w1.damping, rtol=1e-6)
    np.testing.assert_allclose(m.dof_armature[dof], base.dof_armature[dof] * w1.armature, rtol=1e-6)
    np.testing.assert_allclose(m.actuator_gear[act, 0], base.actuator_gear[act, 0] * w1.strength, rtol=1e-6)
    assert len(set(scene.pair_link.tolist())) > 1  # the links' frictions differ, not one factor for all
    for name in ("body_mass", "body_inertia", "body_ipos", "pair_friction", "pair_solref", "dof_damping",
                 "dof_armature", "actuator_gear"):
        np.testing.assert_allclose(np.asarray(getattr(mx, name)), getattr(m, name), rtol=1e-6, atol=1e-7,
                                   err_msg=name)
    assert not np.allclose(m.dof_damping[dof], base.dof_damping[dof])  # the draw moved them


def test_a_world_that_does_not_fit_its_episodes_or_its_ranges_is_refused_by_name(phys):
    scene, eps = phys.scene, _episodes()
    policy = policies.SequencePolicy(jnp.asarray(evaluation.four_tips(phys.space, eps.n_steps)))
    w = world.draw(world.Gap.named("gap"), jax.random.PRNGKey(0), 2, scene.n_touch, len(scene.hand_dof))
    with pytest.raises(ValueError, match="world.friction: shape"):
        phys.simulate_batch(policy, eps, backend="c", world=w.replace(friction=w.friction[:, :1]))
    with pytest.raises(ValueError, match="world.damping: factors"):
        phys.simulate_batch(policy, eps, backend="c", world=w.replace(damping=-w.damping))
    with pytest.raises(ValueError, match=r"world.noise: stds in \[0, "):
        phys.simulate_batch(policy, eps, backend="c", world=w.replace(noise=w.noise * 100))


def test_a_delayed_motor_acts_with_the_command_of_d_ticks_before(phys):
    """`c_backend.Engine` with delays (0, 3): the delayed episode steps bit for bit as `mujoco.mj_step` from Python
    does with each tick's motor command applied three ticks later (zero torque before the first arrives), the other
    as without a delay; a snapshot's commands on their way are restored with it."""
    import mujoco

    from gsp_jax.physics import c_backend

    scene = phys.scene
    eps = _episodes()
    fields = jax.device_get(jax.vmap(scene.episode_fields)(eps))
    qpos0 = np.asarray(jax.vmap(phys.start)(eps)[0], np.float64)
    rng = np.random.default_rng(0)
    lo, hi = scene.model.actuator_ctrlrange.T
    nu, n = phys.model.nu, 30
    out = np.zeros((n, 2, nu + 9), np.float32)
    out[:, :, :nu] = rng.uniform(0.3 * lo, 0.3 * hi, (n, 2, nu))
    constants = c_backend.native_tick(phys).constants
    late = world.nominal_batch(2, scene.n_touch, len(scene.hand_dof)).replace(delay=np.array([0, 3]))
    eng = c_backend.Engine(scene, fields, qpos0, world=late)
    buf = np.zeros(max(phys.model.nq, phys.model.nv, nu, 6))
    trace, states = [], []
    for j in range(n):
        states.append((eng.state(), eng.obs.copy(), eng.native.pending.copy()))
        eng.step(constants, np.arange(2), out[j], 0.0, buf, j)
        trace.append(eng.obs.copy())
    for e, delay in ((0, 0), (1, 3)):
        one = jax.tree.map(lambda x: x[e], fields)
        m = scene.c_model(one)
        d = mujoco.MjData(m)
        d.qpos[:] = qpos0[e]
        mujoco.mj_forward(m, d)
        for j in range(n):
            scene.c_pedestals(m, one, 0.0)
            d.ctrl[:] = out[j - delay, e, :nu] if j >= delay else 0.0
            mujoco.mj_step(m, d)
            np.testing.assert_array_equal(trace[j][e], np.concatenate([d.qpos, d.qvel, d.qfrc_bias]).astype(np.float32))
    eng.restore(*states[10])  # back to tick 10 with the commands then on their way: the same steps again
    for j in range(10, n):
        eng.step(constants, np.arange(2), out[j], 0.0, buf, j)
        np.testing.assert_array_equal(eng.obs, trace[j])


def test_mjx_and_c_mujoco_agree_in_a_delayed_and_noisy_world(phys):
    """Four tips on two short episodes, the second with its motor commands 4 ticks late and its observations
    noised (the wide level's stds): MJX and C MuJoCo give the
    same outcomes, held angles within 2 degrees (as without a world, tests/test_physics.py); MJX with the nominal
    world is MJX without one, bit for bit; the world changes the run."""
    scene, eps = phys.scene, _episodes()
    policy = policies.SequencePolicy(jnp.asarray(evaluation.four_tips(phys.space, eps.n_steps)))
    w = world.draw(world.Gap(), jax.random.PRNGKey(0), 2, scene.n_touch, len(scene.hand_dof))
    noise = jnp.array([[0.0, 0.0, 0.0], [0.002, 0.02, 0.01]], jnp.float32)  # the wide level's, second episode
    late = w.replace(delay=jnp.array([0, 4], jnp.int32), noise=noise, key=jnp.array([[0, 0], [7, 9]], jnp.uint32))
    runs = {b: jax.device_get(phys.simulate_batch(policy, eps, backend=b, world=late)) for b in ("mjx", "c")}
    np.testing.assert_array_equal(runs["mjx"].fell, runs["c"].fell)
    held = ~np.asarray(runs["c"].fell)
    np.testing.assert_allclose(runs["mjx"].angle_error[held], runs["c"].angle_error[held], atol=2.0)
    plain = jax.device_get(phys.simulate_batch(policy, eps, backend="mjx"))
    nominal = jax.device_get(phys.simulate_batch(policy, eps, backend="mjx", world=w))
    jax.tree.map(lambda x, y: np.testing.assert_array_equal(np.asarray(x), np.asarray(y)), plain, nominal)
    assert np.array_equal(plain.qpos[0], runs["mjx"].qpos[0]) and not np.array_equal(plain.qpos[1], runs["mjx"].qpos[1])
    with pytest.raises(ValueError, match=r"world.delay: control ticks in \[0, 20\]"):
        phys.simulate_batch(policy, eps, backend="c", world=w.replace(delay=jnp.array([0, 21], jnp.int32)))


def test_observation_noise_is_one_function_of_key_tick_and_component_in_jax_and_native_code():
    """`world.unit_noise` (JAX) and `native._unit_noise` (the native controller's) give the same float32 bits;
    over 64 components x 2000 ticks the noise has zero mean and unit variance (within 4 standard errors), stays
    within its bound (2 sqrt 3), and a tick's noise is uncorrelated with the next's."""
    from gsp_jax.physics import native

    key = np.array([12345, 678910], np.uint32)
    ticks, comps = np.arange(2000), np.arange(world.COMPONENTS)
    jx = np.asarray(jax.jit(jax.vmap(lambda j: world.unit_noise(key, j, jnp.arange(world.COMPONENTS,
                                                                                       dtype=jnp.uint32))))(ticks))
    k0, k1 = np.uint64(key[0]), np.uint64(key[1])
    for j in (0, 1, 1999):
        nb = np.array([native._unit_noise(k0, k1, np.int64(j), np.int64(c)) for c in comps], np.float32)
        np.testing.assert_array_equal(nb, jx[j])
    n = jx.size
    assert abs(jx.mean()) < 4 / np.sqrt(n) and abs(jx.var() - 1.0) < 4 * np.sqrt(2.0 / n)
    assert np.abs(jx).max() <= 2 * np.sqrt(3) + 1e-6
    assert abs(np.corrcoef(jx[:-1].ravel(), jx[1:].ravel())[0, 1]) < 4 / np.sqrt(n)
    other = np.asarray(world.unit_noise(key + 1, 5, jnp.arange(world.COMPONENTS, dtype=jnp.uint32)))
    assert not np.array_equal(other, jx[5])  # another key, another noise


def test_what_the_native_controller_observes_is_world_seen(phys):
    """The C engine's noised observation (`Engine.seen`) after a step is `world.seen` of its observation at the
    next tick: joints and tool position to the float32 bit, the orientation within 2 float32 steps; velocities as
    simulated. A row without noise observes its state; no noise anywhere: the observation itself."""
    from gsp_jax.physics import c_backend

    scene, eps = phys.scene, _episodes()
    fields = jax.device_get(jax.vmap(scene.episode_fields)(eps))
    qpos0 = np.asarray(jax.vmap(phys.start)(eps)[0], np.float64)
    w = world.nominal_batch(2, scene.n_touch, len(scene.hand_dof)).replace(
        noise=np.array([[0.0, 0.0, 0.0], [0.002, 0.02, 0.01]], np.float32), key=np.array([[0, 0], [3, 4]], np.uint32))
    constants = c_backend.native_tick(phys).constants
    eng = c_backend.Engine(scene, fields, qpos0, world=w)
    out = np.zeros((2, phys.model.nu + 9), np.float32)
    buf = np.zeros(max(phys.model.nq, phys.model.nv, phys.model.nu, 6))
    for j in range(5):
        eng.step(constants, np.arange(2), out, 0.0, buf, j)
    nq, nv = phys.model.nq, phys.model.nv
    o = lambda row: scene.observe(row[:nq], row[nq:nq + nv], row[nq + nv:])  # noqa: E731
    np.testing.assert_array_equal(eng.seen[0], eng.obs[0])
    want = jax.device_get(world.seen(o(jnp.asarray(eng.obs[1])), jax.tree.map(lambda x: jnp.asarray(x[1]), w), 5))
    got = o(eng.seen[1])
    np.testing.assert_array_equal(np.asarray(got.q), want.q)
    np.testing.assert_array_equal(np.asarray(got.tool_pos), want.tool_pos)
    np.testing.assert_allclose(np.asarray(got.tool_quat), want.tool_quat, rtol=0, atol=2.5e-7)
    np.testing.assert_array_equal(eng.seen[1, nq:], eng.obs[1, nq:])
    assert np.abs(np.asarray(got.q) - np.asarray(o(eng.obs[1]).q)).max() > 1e-3  # it is noised
    plain = c_backend.Engine(scene, fields, qpos0)
    assert plain.seen is plain.obs


def test_a_noisy_delayed_c_run_continues_from_its_snapshot_bit_for_bit(phys):
    """The noise is a function of the episode's key and the tick, the commands on their way are in the snapshot:
    a C MuJoCo run stopped at segment 2 and continued is the whole run, bit for bit."""
    from gsp_jax.physics import c_backend

    scene, eps = phys.scene, _episodes()
    policy = policies.SequencePolicy(jnp.asarray(evaluation.four_tips(phys.space, eps.n_steps)))
    w = world.draw(world.Gap.named("wide"), jax.random.PRNGKey(5), 2, scene.n_touch, len(scene.hand_dof))
    w = w.replace(delay=jnp.array([2, 3], jnp.int32))
    whole = c_backend.simulate(phys, [(policy, None)], eps, world=w)[0]
    snap = c_backend.simulate(phys, [(policy, None)], eps, world=w, until=2)
    rest = c_backend.simulate(phys, [(policy, None)], eps, world=w, start=snap)[0]
    jax.tree.map(lambda x, y: np.testing.assert_array_equal(np.asarray(x), np.asarray(y)), whole, rest)
    calm = c_backend.simulate(phys, [(policy, None)], eps, world=w.replace(noise=jnp.zeros_like(w.noise)))[0]
    assert not np.array_equal(np.asarray(calm.qpos), np.asarray(whole.qpos))  # the noise moves the run


def test_a_snapshot_continues_bit_for_bit_in_a_lockstep_of_another_delay(phys):
    """The commands a snapshot holds are the last ones issued, by tick: continued in a lockstep whose ring of
    commands is longer (another row waits longer) or shorter (the row alone), a delayed row's run is the whole run,
    bit for bit (how L1-physics branches a snapshot in its own worlds: `verified.planned_worlds`)."""
    from gsp_jax.physics import c_backend

    scene, eps = phys.scene, _episodes()
    policy = policies.SequencePolicy(jnp.asarray(evaluation.four_tips(phys.space, eps.n_steps)))
    w = world.draw(world.Gap.named("gap"), jax.random.PRNGKey(7), 2, scene.n_touch, len(scene.hand_dof))
    w = w.replace(delay=jnp.array([2, 3], jnp.int32))  # a ring of 4
    whole = c_backend.simulate(phys, [(policy, None)], eps, world=w)[0]
    snap = c_backend.simulate(phys, [(policy, None)], eps, world=w, until=2)
    row0 = lambda r: jax.tree.map(lambda x: np.asarray(x)[:1], r)  # noqa: E731
    for rows, delays in (([0], [2]), ([0, 0], [2, 6])):  # a ring of 3, of 7
        wr = world.rows(w, rows)
        wr = wr.replace(delay=np.array(delays, np.int32))
        sub = jax.tree.map(lambda x: np.asarray(x)[rows], eps)
        rest = c_backend.simulate(phys, [(policy, None)], sub, world=wr, start=snap.take(rows))[0]
        jax.tree.map(lambda x, y: np.testing.assert_array_equal(x, y), row0(rest), row0(whole))


def test_a_commands_world_is_drawn_per_episode_from_its_level_and_seed():
    """`--world LEVEL [--world-only FIELD...] [--world-seed N]` (`experiments.common.Run.worlds`): none in the
    nominal world (today's path); the level's gap, or only the named fields of it, drawn per episode from the seed;
    a chunk's rows are the whole set's rows; results and records named for the world; a part of a gap without a
    level refused."""
    from experiments import cli
    from experiments.common import Run

    hand = Surrogate(learned=False).hand
    eps = scenario.stack(list(scenario.episode_set("eval").values())[:6])
    assert Run().worlds(eps, hand) is None and Run().world_name == "nominal"
    run = Run(world="gap", world_only=("strength", "delay"), world_seed=4)
    w = run.worlds(eps, hand)
    assert run.world_name == "gap-strength-delay" and np.asarray(w.strength).shape == (6, hand.n_joints)
    np.testing.assert_array_equal(w.mass, np.ones(6, np.float32))  # the fields not named: the model's
    assert np.ptp(np.asarray(w.strength)) > 0 and np.all(np.abs(np.asarray(w.strength) - 1) <= 0.15 + 1e-6)
    whole = Run(world="gap", world_seed=4).worlds(eps, hand)
    np.testing.assert_array_equal(world.rows(whole, [2, 3]).friction, np.asarray(whole.friction)[2:4])
    assert world.digest(whole) != world.digest(Run(world="gap", world_seed=5).worlds(eps, hand))
    assert world.as_rows(whole)[1]["delay"] == int(np.asarray(whole.delay)[1])
    with pytest.raises(SystemExit, match="needs --world gap or wide"):
        cli.main(["envelope", "--world-only", "mass"])
    for words, refusal in ((["envelope", "--physics-worlds", "2"], "give --physics-lookahead K too"),
                           (["envelope", "--physics-worlds", "2", "--physics-lookahead", "2"], "needs a gap"),
                           (["envelope", "--physics-gap", "gap"], "--physics-gap is for --physics-worlds"),
                           (["envelope", "--physics-worlds", "-1"], "--physics-worlds must be >= 0"),
                           (["corpus", "--world", "gap", "--world-seed", "3"], "--world-seed 3: a corpus's worlds"),
                           (["calibrate", "--world", "gap"], "--world gap is for --learn")):
        with pytest.raises(SystemExit, match=refusal):
            cli.main(words)
    with pytest.raises(ValueError, match="Gap.only: unknown fields"):
        world.Gap.named("gap").only("weight")
