"""The named contact controllers (`PhysicsConfig.named`): the contact frames the links have against the paper's
nominal ones, on tools the paper's controller drops though holding forces exist (the oracle's "controller" falls).
"""
from __future__ import annotations

import dataclasses
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax import physics  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.physics.controller import STRENGTH_RANGE  # noqa: E402
from gsp_jax.physics.oracle import Oracle  # noqa: E402
from gsp_jax.planning import evaluation, policies  # noqa: E402
from gsp_jax.surrogate.step import Surrogate  # noqa: E402

# two stress episodes whose four fingertips rest on the handle's top edge (MuJoCo's normals tilted ~15 deg from the
# faces'): a heavy tool that creeps down through the fingers as the pedestals sink (2.55 m0), and a light one turned
# out of the hand as the external torque ramps on (+0.4 N m)
EDGE = ("stress084", "stress000")


def test_named_controllers_and_their_errors():
    """`named` sets each controller's fields and `controller_name` reads them back; unknown names and frames are
    refused by name."""
    assert physics.PhysicsConfig().controller_name == "measured"
    assert physics.PhysicsConfig.named("measured") == physics.PhysicsConfig()
    paper = physics.PhysicsConfig.named("paper", hold=0.5)
    assert paper.controller_name == "paper" and paper.value("hold") == 0.5
    assert paper.value("frames") == "nominal" and paper.value("friction_margin") == 0.7
    assert paper.value("tool_radius") == 0.05 and physics.PhysicsConfig().value("tool_radius") is None
    assert paper.value("rotation_step") == 1.0 and physics.PhysicsConfig().value("rotation_step") == 0.3
    assert paper.replace(grip_force=1.0).controller_name is None
    with pytest.raises(ValueError, match="controller must be one of"):
        physics.PhysicsConfig.named("mpc")
    with pytest.raises(ValueError, match=r"PhysicsConfig\.controller\.frames must be one of .* got 'faces'"):
        physics.PhysicsConfig().replace(frames="faces")
    for bad in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match=r"PhysicsConfig\.controller\.tool_radius must be > 0"):
            physics.PhysicsConfig().replace(tool_radius=bad)


def test_rotation_radius_is_the_tools_own():
    """The default controller's rotational gains act at half the tool's longest side, read from the model's tool
    geoms (the wrench: handle and head 19 cm end to end; a tool scaled up in the file gets the larger radius); a
    config's radius overrides it (the paper's 5 cm)."""
    from gsp_jax.physics.controller import rotation_radius

    hand = Surrogate(learned=False).hand
    assert rotation_radius(hand, physics.PhysicsConfig()) == pytest.approx(0.095, abs=1e-6)
    assert rotation_radius(hand, physics.PhysicsConfig.named("paper")) == 0.05
    longer = dataclasses.replace(hand, tool_box_pos=hand.tool_box_pos * 2, tool_box_half=hand.tool_box_half * 2)
    assert rotation_radius(longer, physics.PhysicsConfig()) == pytest.approx(0.19, abs=1e-6)


def test_the_robust_controllers_rotation_radius_is_the_tools_radius_of_gyration():
    """`radius_from="gyration"` (the robust controller's): the model's tool's largest radius of gyration, from its
    mass and principal inertia in the file (the wrench: sqrt(1.12e-3 kg m^2 / 0.35 kg) = 5.66 cm, about a 19 cm
    bar's L / sqrt(12)), not its extent: four times the inertia at the same mass doubles it, a longer box leaves it;
    a config's radius still overrides it; any other rule is refused by name."""
    from gsp_jax.physics.controller import rotation_radius

    hand = Surrogate(learned=False).hand
    robust = physics.PhysicsConfig.named("robust")
    assert robust.value("radius_from") == "gyration"
    assert rotation_radius(hand, robust) == pytest.approx(np.sqrt(1.12e-3 / 0.35), rel=1e-6)
    assert rotation_radius(hand, robust) == pytest.approx(0.19 / np.sqrt(12), rel=0.05)
    heavier = dataclasses.replace(hand, tool_inertia=hand.tool_inertia * 4)
    assert rotation_radius(heavier, robust) == pytest.approx(2 * rotation_radius(hand, robust), rel=1e-6)
    longer = dataclasses.replace(hand, tool_box_pos=hand.tool_box_pos * 2, tool_box_half=hand.tool_box_half * 2)
    assert rotation_radius(longer, robust) == rotation_radius(hand, robust)
    assert rotation_radius(hand, robust.replace(tool_radius=0.03)) == 0.03
    with pytest.raises(ValueError, match=r"PhysicsConfig\.controller\.radius_from must be one of .*, got 'mass'"):
        physics.PhysicsConfig().replace(radius_from="mass")


def test_measured_frames_hold_edge_contacts_the_paper_controller_drops():
    """Four fingertips on the handle's edge, full episodes in C MuJoCo: the oracle finds holding forces in the
    friction cones at every point of the sequence; the paper's controller (nominal face normals, 70% of mu) drops
    both tools, the measured frames hold both within 3 deg (measured: 0.85 and 1.1 deg; the falls are not marginal:
    at 0.42 s and 4.5 s of 5 s)."""
    sur = Surrogate(learned=False)
    stress = scenario.episode_set("stress")
    eps = [stress[next(n for n in stress if n.startswith(p))] for p in EDGE]
    seq = evaluation.four_tips(sur.space, eps[0].n_steps)
    oracle = Oracle(sur, physics.Physics(sur).scene)
    for e in eps:
        g = [int(e.start_grasp)]
        for a in seq:
            g.append(int(sur.space.transitions[g[-1], a]))
        assert oracle.sequence(e, np.asarray(g[1:])).possible
    batch = scenario.stack(eps)
    policy = policies.SequencePolicy(jnp.asarray(seq), sur.space)
    res = {c: physics.Physics(sur, physics.PhysicsConfig.named(c)).simulate_batch(policy, batch, backend="c")
           for c in ("paper", "measured")}
    assert np.all(np.asarray(res["paper"].fell))
    assert not np.any(np.asarray(res["measured"].fell))
    assert np.all(np.asarray(res["measured"].angle_error) < 3.0)


@pytest.mark.parametrize("name", ["measured", "paper", "robust"])
def test_controller_is_finite_on_fuzzed_states(name):
    """Fuzz: the control law (`Controller.control`, both named controllers) on 48 random states of random valid
    episodes (the stress distribution with another seed: mass 0.25-3 m0, friction 0.3-2, torques to 2 N m, CoM
    offsets), each state its episode's start perturbed (joints +-0.3 rad and +-3 rad/s, tool +-5 mm and +-15 deg,
    +-0.3 m/s and +-5 rad/s), at a random time from the lift to the hold, in a random grasp change of one link
    (any phase: unloading, moving, loading) or none, under a random part of the external wrench: every joint torque
    finite and within the motors' limits, every number of the next state finite."""
    from gsp_jax.physics.controller import reference_motion

    sur = Surrogate(learned=False)
    phys = physics.Physics(sur, physics.PhysicsConfig.named(name))
    ctl, rng = phys.controller, np.random.default_rng(84)
    episodes = list(scenario.stress_set(12, seed=rng.integers(2**31), prefix="fuzz").values())
    rows = []
    for _ in range(48):
        ep = episodes[rng.integers(len(episodes))]
        qpos, cs = phys.start(ep)
        obs = phys.scene.observe(qpos, jnp.zeros(phys.model.nv), jnp.zeros(phys.model.nv))
        q = obs.q + rng.uniform(-0.3, 0.3, obs.q.shape)
        axis = rng.normal(size=3)
        turn = np.deg2rad(rng.uniform(-15, 15)) / 2 * axis / np.linalg.norm(axis)
        quat = np.asarray(obs.tool_quat)
        dq = np.r_[np.cos(np.linalg.norm(turn)), np.sin(np.linalg.norm(turn)) * turn / (np.linalg.norm(turn) + 1e-12)]
        w1, v1, w2, v2 = dq[0], dq[1:], quat[0], quat[1:]
        quat = np.r_[w1 * w2 - v1 @ v2, w1 * v2 + w2 * v1 + np.cross(v1, v2)]
        obs = obs.replace(q=jnp.asarray(q, jnp.float32), dq=jnp.asarray(rng.uniform(-3, 3, q.shape), jnp.float32),
                          tool_pos=obs.tool_pos + rng.uniform(-0.005, 0.005, 3).astype(np.float32),
                          tool_quat=jnp.asarray(quat, jnp.float32),
                          tool_vel=jnp.asarray(np.r_[rng.uniform(-0.3, 0.3, 3), rng.uniform(-5, 5, 3)], jnp.float32))
        k = int(rng.integers(ep.n_steps + phys.n_hold))
        grasp = ep.start_grasp
        if rng.uniform() < 0.7:  # a grasp change of one link this segment
            grasp = sur.space.transitions[int(grasp), int(rng.integers(1, sur.space.n_actions))]
        start = float(phys.segment_start(k))
        cs = ctl.begin_segment(cs, obs, jnp.int32(grasp), start)
        cs = cs.replace(load=jnp.asarray(rng.uniform(0, 1, cs.load.shape), jnp.float32))
        time = start + rng.uniform(0, scenario.DT)
        ext = rng.uniform(0, 1) * ep.w_ext
        rows.append((cs, obs, ep, jnp.float32(time), jnp.asarray(ext, jnp.float32)))
    cs, obs, ep, time, ext = jax.tree.map(lambda *x: jnp.stack(x), *rows)

    def one(cs, obs, ep, time, ext):
        return ctl.control(cs, obs, ep, reference_motion(ep, time), time, ext)

    tau, nxt = jax.jit(jax.vmap(one))(cs, obs, ep, time, ext)
    tau = np.asarray(tau)
    low, high = phys.scene.ctrl_range
    assert np.all(np.isfinite(tau))
    assert np.all((tau >= low - 1e-6) & (tau <= high + 1e-6))
    for field, value in vars(nxt).items():
        assert np.all(np.isfinite(np.asarray(value))), field
    low_s, high_s = STRENGTH_RANGE
    assert np.all((np.asarray(nxt.strength) >= low_s) & (np.asarray(nxt.strength) <= high_s))


def test_a_models_tuning_is_its_own(tmp_path):
    """`tuning`: a model's controller tuning beside its scene, read back by every command's config
    (`Run.physics_config`) for that model and refused, by name, for another (a changed file: another digest); the
    paper's controller is never tuned; fields outside `TUNABLE` or out of range are refused by name."""
    import shutil

    from experiments.common import Run
    from experiments.physics.calibrate import parse_grid
    from gsp_jax.model import load as model_lib
    from gsp_jax.physics import tuning

    shutil.copytree(model_lib.load_model("testhand").path.parent, tmp_path / "hand")
    model = model_lib.load_model(tmp_path / "hand" / "scene.xml")
    assert tuning.load(model) == {} and Run(model=model).physics_config() == physics.PhysicsConfig()
    path = tuning.save(model, {"rotation_step": 0.5, "grip_force": 6.0}, {"falls": 3})
    assert path == tmp_path / "hand" / "scene.controller.json"
    assert tuning.load(model) == {"rotation_step": 0.5, "grip_force": 6.0}
    config = Run(model=model).physics_config(hold=0.5)
    assert config == physics.PhysicsConfig().replace(rotation_step=0.5, grip_force=6.0, hold=0.5)
    assert Run(model=model, controller="paper").physics_config() == physics.PhysicsConfig.named("paper")
    with pytest.raises(ValueError, match="never tuned"):
        tuning.save(model, {"grip_force": 6.0}, controller="paper")
    for fields, match in (({"finger_kp": 100.0}, "'finger_kp' is not a tunable"),
                          ({"grip_force": -1.0}, "grip_force must be a finite number > 0, got -1.0"),
                          ({"rotation_step": float("nan")}, "rotation_step must be a finite number > 0")):
        with pytest.raises(ValueError, match=match):
            tuning.save(model, fields)
    shutil.copytree(tmp_path / "hand", tmp_path / "b" / "hand")  # the file beside a heavier bar: another model
    bar = tmp_path / "b" / "hand" / "bar.xml"
    bar.write_text(bar.read_text().replace('mass="0.25"', 'mass="0.3"'))
    other = model_lib.load_model(tmp_path / "b" / "hand" / "scene.xml")
    assert other.name == model.name and other.digest != model.digest
    with pytest.raises(ValueError, match="made for model .* not for"):
        tuning.load(other)
    (tmp_path / "hand" / "scene.controller.json").write_text("{")
    with pytest.raises(ValueError, match="not a controller tuning"):
        tuning.load(model)
    assert parse_grid("grip_force=4,8;rotation_step=0.3") == [{"grip_force": 4.0, "rotation_step": 0.3},
                                                              {"grip_force": 8.0, "rotation_step": 0.3}]
    for bad in ("finger_kp=1", "grip_force=a", "grip_force=0", ""):
        with pytest.raises(SystemExit):
            parse_grid(bad)


def test_the_predictive_hold_is_never_worse_and_holds_what_the_default_drops():
    """The predictive hold (`PhysicsConfig.named("predictive")`, C MuJoCo): its rollout under its own settings is
    the default controller's run bit for bit (the snapshot continues it), so per episode it holds whatever the
    default holds, with no larger angle error; on four stress episodes the default drops in the hold and one it
    holds (four tips) it holds at least one more (measured: all four, both on AVX-512 and under SSE4.2, held
    angles 0.6-1.2 deg)."""
    sur = Surrogate(learned=False)
    stress = scenario.episode_set("stress")
    names = [next(n for n in stress if n.startswith(p)) for p in ("stress037", "stress043", "stress074", "stress102",
                                                                  "stress000")]
    batch = scenario.stack([stress[n] for n in names])
    policy = policies.SequencePolicy(jnp.asarray(evaluation.four_tips(sur.space, batch.n_steps)), sur.space)
    base = physics.Physics(sur).simulate_batch(policy, batch, backend="c")
    phys = physics.Physics(sur, physics.PhysicsConfig.named("predictive"))
    (res,), (chosen,) = phys.simulate_predictive([(policy, None)], batch)
    fell, base_fell = np.asarray(res.fell), np.asarray(base.fell)
    assert not np.any(fell & ~base_fell)
    kept = chosen == 0
    np.testing.assert_array_equal(np.asarray(res.angle_error)[kept], np.asarray(base.angle_error)[kept])
    held = ~fell & ~base_fell
    assert np.all(np.asarray(res.angle_error)[held] <= np.asarray(base.angle_error)[held])
    assert base_fell.sum() >= 3 and fell.sum() < base_fell.sum(), (base_fell, fell, chosen)
    np.testing.assert_array_equal(np.asarray(phys.simulate_batch(policy, batch, backend="c").fell), fell)
    with pytest.raises(ValueError, match=r"controller\.predictive: .*needs backend='c', got backend='mjx'"):
        phys.simulate_batch(policy, batch, backend="mjx")


def test_the_predictive_holds_candidates_scale_the_runs_own_settings():
    """Each candidate is the run's own config (tuned or not) with a few gains scaled, the predictive layer off in the
    rollouts, the damping bound and the friction fraction at most 1; the first is the run's own."""
    from gsp_jax.physics import predictive
    from gsp_jax.physics.controller import rotation_radius

    hand = Surrogate(learned=False).hand
    config = physics.PhysicsConfig.named("predictive", grip_force=6.0, rotation_step=0.5)
    got = predictive.candidate_configs(config, hand)
    assert len(got) == len(predictive.CANDIDATES) and got[0] == config.replace(predictive=False)
    assert not any(c.value("predictive") for c in got)
    assert sorted(c.value("grip_force") for c in got) == [3.0] + [6.0] * 6 + [9.0, 12.0]
    assert max(c.value("rotation_step") for c in got) == 1.0 and max(c.value("friction_margin") for c in got) <= 1
    radii = [c.value("tool_radius") for c in got if c.value("tool_radius") is not None]
    assert radii == [pytest.approx(1.5 * rotation_radius(hand, config))]
    with pytest.raises(ValueError, match=r"PhysicsConfig\.controller\.predictive must be a bool, got 1"):
        physics.PhysicsConfig().replace(predictive=1)


def test_the_robust_controllers_settings_and_their_errors():
    """`robust` is the default with the pose filter and the strength estimates on; a filter gain outside (0, 1] and
    negative rates are refused by name."""
    robust = physics.PhysicsConfig.named("robust")
    assert robust.controller_name == "robust"
    assert robust.value("pose_filter") < 1 and robust.value("strength_rate") > 0
    assert physics.PhysicsConfig().value("pose_filter") == 1 and physics.PhysicsConfig().value("strength_rate") == 0
    for name, bad in (("pose_filter", 0.0), ("pose_filter", 1.5), ("strength_rate", -0.1),
                      ("strength_rate", float("nan"))):
        with pytest.raises(ValueError, match=rf"PhysicsConfig\.controller\.{name} must be"):
            physics.PhysicsConfig().replace(**{name: bad})


def _moving_tool(ticks, dt, rng, noise):
    """Observations of a tool turning at a constant body rate and moving at a constant velocity, joints at
    constant rates, (ticks,) each; the pose and joint angles with Gaussian noise of stds `noise` [m, rad, rad]."""
    from gsp_jax.physics.controller import quat_mul

    v, w, dq = np.array([0.02, -0.01, 0.03]), np.array([0.5, -0.3, 0.8]), rng.uniform(-1, 1, 16)
    t = np.arange(1, ticks + 1) * dt
    half = 0.5 * np.linalg.norm(w) * t
    turn = np.c_[np.cos(half), np.sin(half)[:, None] * w / np.linalg.norm(w)]
    quat0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    quat = np.asarray(jax.vmap(lambda b: quat_mul(jnp.asarray(quat0, jnp.float32), b))(jnp.asarray(turn, jnp.float32)))
    pos, q = np.array([0.0, 0.01, 0.05]) + t[:, None] * v, 0.3 + t[:, None] * dq
    small = rng.normal(size=(ticks, 3)) * noise[1] / 2
    kick = np.c_[np.ones(ticks), small] / np.linalg.norm(np.c_[np.ones(ticks), small], axis=1, keepdims=True)
    noisy = np.asarray(jax.vmap(quat_mul)(jnp.asarray(quat, jnp.float32), jnp.asarray(kick, jnp.float32)))
    seen = dict(tool_pos=pos + rng.normal(size=pos.shape) * noise[0], tool_quat=noisy,
                q=q + rng.normal(size=q.shape) * noise[2], dq=np.broadcast_to(dq, q.shape),
                tool_vel=np.broadcast_to(np.r_[v, w], (ticks, 6)), bias=np.zeros_like(q))
    start = (pos[0] - v * dt, quat0, q[0] - dq * dt)  # the estimate a tick before the first observation
    return {k: jnp.asarray(x, jnp.float32) for k, x in seen.items()}, pos, quat, q, start


@pytest.mark.parametrize("noisy", [False, True])
def test_the_pose_filter_follows_a_moving_tool_and_cuts_its_noise_as_an_exponential_filter_does(noisy):
    """`Controller._filtered` (gain a = the robust controller's 0.1) over 4,000 ticks of a tool moving and turning at
    constant rates: without noise the estimate is the pose within float32 rounding (the measured velocities carry
    it); with white noise of std s on the position, orientation and joint angles, the estimate's error has the std
    of an exponential filter's, s sqrt(a / (2 - a)) (0.23 s), within 15%."""
    from gsp_jax.physics.controller import rotation_error
    from gsp_jax.physics.scene import Observation

    phys = physics.Physics(Surrogate(learned=False), physics.PhysicsConfig.named("robust"))
    ctl, a, ticks = phys.controller, phys.config.controller.pose_filter, 4000
    noise = (0.001, 0.01, 0.005) if noisy else (0.0, 0.0, 0.0)
    seen, pos, quat, q, start = _moving_tool(ticks, ctl.timestep, np.random.default_rng(3), noise)
    _, cs = phys.start(list(scenario.eval_set_a().values())[0])
    cs = cs.replace(estimate=jnp.asarray(np.concatenate(start), jnp.float32))

    def step(cs, obs):
        obs, est = ctl._filtered(cs, Observation(**obs))
        return cs.replace(estimate=est), (obs.tool_pos, obs.tool_quat, obs.q)

    _, (p_est, q_est, j_est) = jax.lax.scan(step, cs, seen)
    err_p = np.asarray(p_est) - pos
    err_r = np.asarray(jax.vmap(rotation_error)(jnp.asarray(quat, jnp.float32), q_est))
    err_j = np.asarray(j_est) - q
    if not noisy:
        assert np.abs(err_p).max() < 2e-6 and np.abs(err_r).max() < 2e-5 and np.abs(err_j).max() < 2e-5
        return
    expect = np.sqrt(a / (2 - a))
    for err, s in ((err_p, noise[0]), (err_r, noise[1]), (err_j, noise[2])):
        ratio = np.std(err[500:]) / s
        assert abs(ratio - expect) < 0.15 * expect, (ratio, expect)


def test_strength_estimates_move_along_the_least_squares_force_of_each_joint():
    """`Controller._strengths` against numpy: each joint's estimate moves by rate dt / weight^2 times the part of
    the feedback beyond the deadband dotted with the force its torque gives through each active link (the least
    squares solution of J_l^T f = tau_j e_j, `np.linalg.lstsq`), then leaks towards 1; nothing but the leak below
    the deadband or while a link changes; a motor whose command is at its limit is never asked for more."""
    phys = physics.Physics(Surrogate(learned=False), physics.PhysicsConfig.named("robust"))
    from gsp_jax.physics.controller import STRENGTH_DEADBAND, STRENGTH_LEAK

    ctl, c, rng = phys.controller, phys.config.controller, np.random.default_rng(5)
    ep = list(scenario.eval_set_a().values())[0]
    _, cs = phys.start(ep)
    L, J = phys.hand.n_links, len(cs.q_rest)
    jac = rng.normal(size=(L, 3, J)) * 0.3
    active = rng.uniform(size=L) < 0.5
    tau, old = rng.uniform(-1, 1, J), rng.uniform(0.8, 1.2, J)
    cs = cs.replace(strength=jnp.asarray(old, jnp.float32))
    weight = float(ep.mass) * np.linalg.norm(np.asarray(ctl.gravity))
    dt = ctl.timestep
    leak = lambda s: s + STRENGTH_LEAK * dt * (1 - s)  # noqa: E731

    def run(feedback, cs=cs, tau=tau):
        return np.asarray(ctl._strengths(cs, jnp.asarray(tau, jnp.float32), jnp.asarray(jac, jnp.float32),
                                         jnp.asarray(active), jnp.asarray(feedback, jnp.float32), ep))

    feedback = np.array([0.5, -1.0, 3.0]) * weight
    grad = np.array([sum(np.linalg.lstsq(jac[lk].T, tau[j] * np.eye(J)[j], rcond=None)[0] @ feedback
                         for lk in np.flatnonzero(active)) for j in range(J)])
    beyond = 1 - STRENGTH_DEADBAND * weight / np.linalg.norm(feedback)
    expect = leak(old - beyond * c.strength_rate * dt * grad / weight**2)
    np.testing.assert_allclose(run(feedback), expect, rtol=1e-5, atol=1e-6)
    assert np.abs(expect - leak(old)).max() > 1e-4  # the feedback moved them (30x the tolerance above)
    np.testing.assert_allclose(run(0.5 * STRENGTH_DEADBAND * feedback / np.linalg.norm(feedback) * weight),
                               leak(old), rtol=1e-6)
    changing = cs.replace(changed=cs.changed.at[0].set(True))
    np.testing.assert_allclose(run(feedback, cs=changing), leak(old), rtol=1e-6)
    at_limit = tau.copy()
    at_limit[:] = phys.scene.ctrl_range[1][0] * old * 1.01  # every command beyond the motors' range
    assert np.all(run(feedback, tau=at_limit) >= old - 1e-7)
