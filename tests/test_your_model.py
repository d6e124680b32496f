"""Your hand, your tool: a model written outside the package -- a three-finger hand (the shipped hand without its ring
finger, every geom renamed) and a round-handled tool of its own (not named "wrench", a capsule and a sphere, its own
mass) -- goes surrogate -> DP -> physics with nothing read from the shipped files; every convention a file breaks is
named by `check_model`, and what was made for one model is refused by another."""
from __future__ import annotations

import pathlib
import re
import shutil

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from gsp_jax.planning import dp, evaluation, policies
from gsp_jax.model import grasps, hand as hand_lib, load as model_lib, scenario
from gsp_jax.solvers import ik
from gsp_jax.surrogate import learned
from gsp_jax import physics
from gsp_jax.surrogate.step import Surrogate

TOOL = """<mujoco model="screwdriver">
  <default><default class="t">
    <geom contype="2" conaffinity="1" condim="3" friction="1.0 0.01 0.001" solref="0.004 1" solimp="0.95 0.99 0.001"/>
    <site type="sphere" size="0.003" group="4"/>
  </default></default>
  <custom><numeric name="gsp_start_options" data="1 1 0 1 0"/></custom>
  <worldbody>
    <body name="screwdriver" pos="0 0 0.02" childclass="t">
      <freejoint/>
      <geom name="grip" type="capsule" fromto="-0.07 0 0  0.06 0 0" size="0.0125" mass="0.2"/>
      <geom name="knob" type="sphere" pos="0.075 0 0" size="0.016" mass="0.05"/>
      <site name="opt_thumb_distal_1" pos="0.015 -0.0125 0" zaxis="0 1 0"/>
      <site name="opt_thumb_distal_2" pos="0.03 -0.0125 0" zaxis="0 1 0"/>
      <site name="opt_index_distal_1" pos="0.03 0.0125 0" zaxis="0 -1 0"/>
      <site name="opt_index_medial_1" pos="0.035 0.0125 0" zaxis="0 -1 0"/>
      <site name="opt_middle_distal_1" pos="0.0 0.0125 0" zaxis="0 -1 0"/>
      <site name="opt_middle_distal_2" pos="-0.03 0.0125 0" zaxis="0 -1 0"/>
      <site name="opt_middle_medial_1" pos="0.0 0.0125 0" zaxis="0 -1 0"/>
    </body>
  </worldbody>
</mujoco>"""

SCENE = """<mujoco model="user_scene">
  <include file="hand3.xml"/>
  <include file="tool.xml"/>
  <option timestep="0.002" gravity="0 0 -9.81" cone="elliptic" impratio="10"/>
  <worldbody><geom name="floor" type="plane" size="0.3 0.3 0.01" contype="3" conaffinity="3" condim="3"/></worldbody>
</mujoco>"""


def three_finger_hand() -> str:
    """The shipped hand without its ring finger, every geom renamed (so nothing can find a link by its name)."""
    spec = mujoco.MjSpec.from_file(str(hand_lib.MODELS_DIR / "hand.xml"))
    spec.delete(spec.body("ring_knuckle"))
    for a in list(spec.actuators):
        if a.target.startswith("ring"):
            spec.delete(a)
    texts = {t.name: t for t in spec.texts}
    texts["gsp_contact_links"].data = "thumb_distal index_distal index_medial middle_distal middle_medial"
    texts["gsp_touch_tool"].data = "thumb_medial thumb_distal index_medial index_distal middle_medial middle_distal"
    start = next(n for n in spec.numerics if n.name == "gsp_ik_start")
    start.data, start.size = list(start.data)[:12], 12
    for i, g in enumerate(spec.geoms):
        g.name = f"part{i}"
    return spec.to_xml()


@pytest.fixture(scope="module")
def user_scene(tmp_path_factory) -> pathlib.Path:
    folder = tmp_path_factory.mktemp("my_model")
    (folder / "hand3.xml").write_text(three_finger_hand())
    (folder / "tool.xml").write_text(TOOL)
    (folder / "scene.xml").write_text(SCENE)
    return folder / "scene.xml"


@pytest.fixture(scope="module")
def user_model(user_scene) -> model_lib.Model:
    return model_lib.load_model(user_scene)


def test_a_users_scene_follows_the_conventions(user_scene, user_model):
    assert model_lib.check_model(user_scene) == []
    h, space = user_model.hand, user_model.space
    assert user_model.name == "my_model0" and user_model.path == user_scene.resolve()
    assert h.tool_name == "screwdriver" and h.tool_round_type == ("capsule", "sphere") and len(h.tool_box_half) == 0
    assert space.n_options == (3, 2, 2, 3, 2) and space.n_grasps == 72 and space.n_actions == 13
    assert h.finger_names == ("thumb", "index", "middle") and h.n_joints == 12
    # the tool's inertial properties are the file's (MuJoCo's, from the geoms' masses), not the wrench's constants
    m = mujoco.MjModel.from_xml_path(str(user_scene))
    b = hand_lib.tool_body(m)
    assert h.tool_mass == pytest.approx(0.25) and np.allclose(h.tool_com, m.body_ipos[b])
    assert h.tool_com[0] > 0.01  # the knob pulls the centre of mass towards +x
    ep = scenario.make_episode(model=user_model, mass_factor=2.0)
    assert float(ep.mass) == pytest.approx(0.5) and np.allclose(ep.inertia, 2 * m.body_inertia[b], rtol=1e-6)
    assert np.allclose(ep.com, h.tool_com, atol=1e-7) and float(ep.waypoints[0, 2]) == pytest.approx(0.02)
    assert np.asarray(space.decode(ep.start_grasp)).tolist() == [1, 1, 0, 1, 0]
    assert (scenario.make_episode(model=user_model, start={"thumb_distal": 2}).start_grasp
            == space.encode([2, 0, 0, 0, 0]))
    absolute = scenario.make_episode(model=user_model, mass=0.3, inertia=(1e-4, 2e-4, 2e-4), com=(0.01, 0, 0),
                                     torque=0.5, torque_axis=(1, 1, 0))
    assert float(absolute.mass) == pytest.approx(0.3) and np.allclose(absolute.com, (0.01, 0, 0))
    assert np.allclose(absolute.w_ext[3:], 0.5 * np.array([1, 1, 0]) / np.sqrt(2), atol=1e-6)


def test_supports_come_from_the_tools_shape(user_model):
    """No support sites: two supports near either end of the tool's length, each at the bottom of the geoms above
    it (here the capsule grip's: the sphere knob is past the second one)."""
    h = user_model.hand
    assert h.support_top.shape == (2, 3)
    lo, hi = h.tool_bounds()
    assert np.allclose(h.support_top[:, 2], -0.0125) and np.allclose(h.support_top[:, 1], 0.0)
    assert lo[0] < h.support_top[0, 0] < h.support_top[1, 0] < hi[0]


@pytest.fixture
def shipped_files_unreadable(monkeypatch):
    """Every way the library reads a model file raises for the shipped folder: a silent fallback to the shipped
    wrench fails the test that uses this."""
    shipped = str(hand_lib.MODELS_DIR.resolve())

    def guard(fn):
        def guarded(path=hand_lib.SCENE_XML, *args, **kwargs):
            if str(pathlib.Path(str(path)).resolve()).startswith(shipped):
                raise AssertionError(f"read a shipped model file: {path}")
            return fn(path, *args, **kwargs)
        return guarded

    monkeypatch.setattr(hand_lib, "load_mjmodel", guard(hand_lib.load_mjmodel))
    monkeypatch.setattr(model_lib, "load_hand", guard(model_lib.load_hand))
    monkeypatch.setattr(mujoco.MjSpec, "from_file", staticmethod(guard(mujoco.MjSpec.from_file)))
    monkeypatch.setattr(model_lib, "DEFAULT", "no-default-here")  # load_model(None) fails instead of giving the
    # wrench (even where the process has loaded the wrench already)


def test_surrogate_dp_physics_on_a_users_model(user_model, shipped_files_unreadable, table_ik):
    """The user's model end to end, with the shipped files unreadable: DP finds a sequence that holds in the
    surrogate, and C MuJoCo -- its physics built from the user's scene, contact pairs from the file's conventions,
    not geom names -- holds it too."""
    sur = Surrogate(user_model, ik_config=table_ik)
    assert sur.model is user_model
    ep = scenario.make_episode(model=user_model, torque=0.3).head(4)
    table = jax.jit(dp.build_table)(sur, ep)
    sol = dp.backup(table, ep.start_grasp)
    assert float(sol.ret) > sur.reward_config.r_min and sur.explain(ep, np.asarray(sol.actions)) is None
    phys = physics.Physics(sur)
    m = phys.model
    names = {m.body(b).name for b in range(m.nbody)}
    assert "screwdriver" in names and "wrench" not in names and "ring_knuckle" not in names  # no shipped file read
    # every contact pair of a finger with the tool: the six touch_tool bodies' capsules, 4 spheres each, x 2 geoms
    assert phys.scene.finger_tool_pairs.size == 2 * 6 * 4
    res = phys.simulate_batch(policies.TablePolicy(sol.policy, sur.space), scenario.stack([ep]), backend="c")
    assert not bool(res.fell[0]), float(res.fall_time[0])
    with pytest.raises(Exception):  # the guard itself works: the default model is now unreachable
        Surrogate()


def test_a_training_run_is_not_resumed_for_another_model(user_model, tmp_path):
    """A PPO run's checkpoint folder records its model; the same folder with another model is refused naming it."""
    import types

    from gsp_jax.ppo import networks as nets, train as ppo

    def trainer(model):
        return types.SimpleNamespace(env=types.SimpleNamespace(surrogate=Surrogate(model)), config=ppo.PPOConfig(),
                                     networks=types.SimpleNamespace(config=nets.NetworkConfig()))

    ppo._manager(tmp_path, trainer(user_model), 0).close()
    with pytest.raises(ValueError, match=r"different model .*'my_model0'.*'wrench'"):
        ppo._manager(tmp_path, trainer("wrench"), 0)


def test_what_was_made_for_another_model_is_refused(user_model, tmp_path):
    sur = Surrogate(user_model)
    with pytest.raises(model_lib.ModelError, match=r"'wrench'.*not for 'my_model0'"):
        policies.load_network_policy(sur, policies.SHIPPED_POLICY)  # the shipped PPO policy is the wrench's
    with pytest.raises(FileNotFoundError, match="no PPO policy ships for 'my_model0'"):
        policies.load_network_policy(sur)  # nothing ships for a model of your own: no fallback to the wrench's
    path = tmp_path / "eps.json"
    scenario.save(path, {"n": scenario.make_episode()})  # the wrench's
    with pytest.raises(model_lib.ModelError, match=r"made for model 'wrench'.*not for 'my_model0'"):
        scenario.load(path, user_model)
    assert set(scenario.load(path)) == {"n"}
    with pytest.raises(ValueError, match=r"288 rows for the model's 72 grasps"):
        policies.TablePolicy(jnp.zeros((288, 16), jnp.int32), sur.space)
    with pytest.raises(ValueError, match=r"13 is not in \[0, 13\)"):
        policies.SequencePolicy(jnp.full(16, 13, jnp.int32), sur.space)
    bare = hand_lib.from_mjmodel(user_model.mjmodel)  # a HandModel with no scene file behind it
    with pytest.raises(ValueError, match="not loaded from a scene file"):
        physics.Physics(Surrogate(bare))


def _write(folder: pathlib.Path, tool: str, hand: str | None = None) -> pathlib.Path:
    (folder / "hand3.xml").write_text(hand or three_finger_hand())
    (folder / "tool.xml").write_text(tool)
    (folder / "scene.xml").write_text(SCENE)
    return folder / "scene.xml"


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('<site name="opt_index_medial_1" pos="0.035 0.0125 0" zaxis="0 -1 0"/>', ""),
     "link 'index_medial' has no contact option on the tool: add site 'opt_index_medial_1'"),
    (lambda t: t.replace("<freejoint/>", ""), "the tool must be the scene's one free body"),
    (lambda t: t.replace('type="sphere" pos="0.075 0 0" size="0.016"', 'type="mesh" mesh="knob" pos="0.075 0 0"')
     .replace("<worldbody>",
              '<asset><mesh name="knob" vertex="0 0 0  0.02 0 0  0 0.02 0  0 0 0.02"/></asset><worldbody>'),
     "tool geom 'knob' is a mesh: a tool geom must be one of box, capsule, cylinder, ellipsoid, sphere"),
    (lambda t: t.replace('name="opt_middle_medial_1"', 'name="opt_pinky_distal_1"'),
     "site 'opt_pinky_distal_1' names no contact link"),
    (lambda t: t.replace('data="1 1 0 1 0"', 'data="1 1 0 1"'), "gsp_start_options"),
])
def test_check_model_names_what_is_broken(tmp_path, edit, message):
    scene = _write(tmp_path, edit(TOOL))
    problems = model_lib.check_model(scene)
    assert any(message in p for p in problems), problems
    with pytest.raises(model_lib.ModelError, match="breaks"):
        model_lib.load_model(scene)


def test_check_model_names_the_hands_problems(tmp_path):
    hand = three_finger_hand().replace('name="contact_index_medial"', 'name="contact_elsewhere"')
    hand = hand.replace('<geom name="part1" class="link" size="0.012 0.0075"',
                        '<geom name="part1" class="link" type="box" size="0.012 0.012 0.0075"')
    problems = model_lib.check_model(_write(tmp_path, TOOL, hand))
    assert any("link 'index_medial' has no site 'contact_index_medial'" in p for p in problems), problems
    assert any("hand geom 'part1' (body 'thumb_knuckle') is a box: below the palm a hand geom that collides must be a "
               "capsule or a sphere" in p for p in problems), problems


def test_check_model_command_exits_nonzero(tmp_path, capsys):
    from experiments.common import Run
    from experiments.diagnostics import check_model

    scene = _write(tmp_path, TOOL.replace("<freejoint/>", ""))
    with pytest.raises(SystemExit) as e:
        check_model.main(type("Args", (), {"scene": str(scene)}), Run())
    assert e.value.code == 1 and "one free body" in capsys.readouterr().out


def test_shipped_models_follow_the_conventions():
    for name in model_lib.SHIPPED:
        assert model_lib.check_model(model_lib.SHIPPED[name]) == [], name
    for name, path in policies.SHIPPED_POLICIES.items():  # each shipped policy is tagged for its model as it is now
        assert policies.model_tag(path)["digest"] == model_lib.load_model(name).digest, name
    for name, path in policies.SHIPPED_LEARNED_POLICIES.items():  # and trained with the model's learned term as it is
        model = model_lib.load_model(name)
        made = policies.model_tag(path)
        assert made["digest"] == model.digest, name
        assert made["learned"] == learned.tag(learned.load(learned.path_of(model), model)), name


def test_the_learned_term_finds_the_policy_trained_with_it(sur, tmp_path):
    """With the learned term the evaluation loads the policy `train --learned` wrote under the results folder it is
    given, else the shipped one trained with the term; without it, the analytic one; a policy trained under another
    reward than the surrogate's is loaded and said to be."""
    with_term = sur.replace(learned=True)
    assert evaluation.trained_policy(with_term, tmp_path) == tmp_path / "train-learned/dp/seed0/policy"
    assert evaluation.trained_policy(sur, "results") == pathlib.Path("results/train/dp/seed0/policy")
    assert policies.shipped_policy(with_term) == policies.SHIPPED_LEARNED_POLICIES["wrench"]
    assert policies.shipped_policy(sur) == policies.SHIPPED_POLICY
    _, source = evaluation.load_rl(with_term, results=tmp_path)  # no policy trained there: the shipped one
    assert source.endswith("ppo_dp_learned") and "trained" not in source  # trained with these very weights
    trained = evaluation.trained_policy(sur, tmp_path)
    shipped = policies.SHIPPED_LEARNED_POLICIES["wrench"]  # copied there with its model tag, as `train` writes it
    shutil.copytree(shipped, trained)
    shutil.copy(shipped.parent / f"{shipped.name}.model.json", trained.parent / f"{trained.name}.model.json")
    _, source = evaluation.load_rl(sur, results=tmp_path)  # the trained one, before the shipped one
    assert source.startswith(str(trained)) and source.endswith("(trained with the learned term)")
    _, source = evaluation.load_rl(sur)
    assert source.endswith("ppo_dp_seed0") and "trained" not in source
    _, source = evaluation.load_rl(with_term, policies.SHIPPED_POLICY)
    assert source.endswith("(trained without the learned term)")
    _, source = evaluation.load_rl(sur, policies.SHIPPED_LEARNED_POLICIES["wrench"])
    assert source.endswith("(trained with the learned term)")


def test_round_primitives_distance_against_mujoco():
    """`ik.round_sdf` (via the tool's SDF) against MuJoCo's own geom distance of a point-sized sphere, outside the
    primitives; its gradient against central differences."""
    xml = """<mujoco><worldbody>
      <geom name="cyl" type="cylinder" size="0.02 0.03" pos="0.1 0 0" euler="0.3 0.2 0.1"/>
      <geom name="cap" type="capsule" size="0.015 0.04" pos="-0.1 0 0" euler="0 1.2 0"/>
      <geom name="sph" type="sphere" size="0.025" pos="0 0.1 0"/>
      <body mocap="true" name="probe"><geom name="p" type="sphere" size="1e-5"/></body>
    </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    for g, kind in ((0, "cylinder"), (1, "capsule"), (2, "sphere")):
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, m.geom_quat[g])
        mat = mat.reshape(3, 3)
        distance = lambda x, g=g, kind=kind: ik.round_sdf(kind, m.geom_size[g], x[0], x[1], x[2])[0]  # noqa: E731
        for _ in range(20):
            p = m.geom_pos[g] + rng.normal(size=3) * 0.05
            d.mocap_pos[0] = p
            mujoco.mj_forward(m, d)
            ref = mujoco.mj_geomDistance(m, d, g, 3, 1.0, None) + 1e-5
            local = jnp.asarray((p - m.geom_pos[g]) @ mat, jnp.float32)
            dist, *grad = ik.round_sdf(kind, m.geom_size[g], *local)
            if ref > 1e-3:
                assert float(dist) == pytest.approx(ref, abs=2e-5), (kind, p)
            np.testing.assert_allclose(np.array([float(x) for x in grad]), np.asarray(jax.grad(distance)(local)),
                                       atol=1e-4)


def test_environments_and_references_of_a_users_model(user_model):
    from gsp_jax.learning import gym_env

    env = gym_env.make(episodes="nominal", backend="surrogate", model=user_model, progress=False)
    assert env.action_space.n == 13 and env.env.surrogate.model is user_model
    with pytest.raises(model_lib.ModelError, match="differs from the surrogate's"):
        gym_env.make(episodes="nominal", backend="surrogate", model="hammer", surrogate=Surrogate(user_model))
    # the all-tips reference from the model's start grasp: the start already has every tip, so it keeps it
    space = user_model.space
    assert space.tip_options == (1, 1, 0, 1, 0) and evaluation.four_tips(space, 4).tolist() == [0, 0, 0, 0]
    wrench_space = model_lib.load_model().space  # the wrench: add the ring tip, then repeat that (redundant) action
    assert evaluation.four_tips(wrench_space, 3).tolist() == [wrench_space.action("ring_distal", 1)] * 3


def test_explain_names_the_first_failing_step(sur):
    """A sequence that must drop the tool (the index tip alone) is explained at its first failing step, a held one
    is not."""
    ep = scenario.make_episode().head(4)
    why = sur.explain(ep, evaluation.one_tip(sur.space, ep.n_steps))
    assert why is not None and why.startswith(("t=0:", "t=1:", "t=2:")) and "unmet" in why, why
    assert sur.explain(ep, evaluation.four_tips(sur.space, ep.n_steps)) is None


def _hand_spec() -> mujoco.MjSpec:
    return mujoco.MjSpec.from_string(three_finger_hand())


def test_check_model_reports_every_problem_of_a_file_at_once(tmp_path, capsys):
    """A file with problems of five kinds -- a position servo, a tendon-driven joint pair, a box below the palm, no IK
    start, a tool without one link's option -- names all of them in one run, each with its fix."""
    from experiments.common import Run
    from experiments.diagnostics import check_model

    spec = _hand_spec()
    servo = next(a for a in spec.actuators if a.target == "index_mcp")
    servo.set_to_position(kp=3.0)
    for a in [a for a in spec.actuators if a.target in ("middle_pip", "middle_dip")]:
        spec.delete(a)
    tendon = spec.add_tendon(name="middle_coupling")
    tendon.wrap_joint("middle_pip", 1.0)
    tendon.wrap_joint("middle_dip", 1.0)
    spec.add_actuator(name="middle_drive", target="middle_coupling", trntype=mujoco.mjtTrn.mjTRN_TENDON,
                      ctrlrange=[-1, 1], ctrllimited=True)
    spec.geom("part1").type = mujoco.mjtGeom.mjGEOM_BOX
    spec.geom("part1").size = [0.012, 0.012, 0.0075]
    spec.delete(next(n for n in spec.numerics if n.name == "gsp_ik_start"))
    tool = TOOL.replace('<site name="opt_index_medial_1" pos="0.035 0.0125 0" zaxis="0 -1 0"/>', "")
    scene = _write(tmp_path, tool, spec.to_xml())
    problems = model_lib.check_model(scene)
    expected = ["actuator 'index_mcp' on hand joint 'index_mcp' is a position servo (kp 3)",
                "drives tendon 'middle_coupling' (joints 'middle_pip', 'middle_dip')",
                "hand joint 'middle_pip' has no motor", "hand geom 'part1' (body 'thumb_knuckle') is a box",
                "custom numeric 'gsp_ik_start' is missing", "link 'index_medial' has no contact option"]
    for text in expected:
        assert any(text in p for p in problems), (text, problems)
    with pytest.raises(SystemExit) as e:
        check_model.main(type("Args", (), {"scene": str(scene), "quick": True, "reach": False}), Run())
    out = capsys.readouterr().out
    assert e.value.code == 1 and all(text in out for text in expected), out


def test_check_model_finds_the_hand_without_contact_links(tmp_path):
    """Without gsp_contact_links (a published hand as it comes) the hand is still checked: its servo is named."""
    spec = _hand_spec()
    spec.delete(next(t for t in spec.texts if t.name == "gsp_contact_links"))
    next(a for a in spec.actuators if a.target == "thumb_mcp").set_to_position(kp=2.0)
    problems = model_lib.check_model(_write(tmp_path, TOOL, spec.to_xml()))
    assert any("'gsp_contact_links' is missing" in p for p in problems), problems
    assert any("on hand joint 'thumb_mcp' is a position servo (kp 2)" in p for p in problems), problems


def _light_scene(folder: pathlib.Path, armature: float, damping: float) -> pathlib.Path:
    spec = _hand_spec()
    for j in spec.joints:
        j.armature, j.damping = armature, [damping, 0.0, 0.0]
    return _write(folder, TOOL, spec.to_xml())


def test_joint_dynamics_against_the_controller_agree_with_c_mujoco(tmp_path, user_scene, table_ik):
    """The joint-dynamics check and C MuJoCo agree: joints without armature (Menagerie's LEAP: damping 0.03) are
    named, and the dry run of the start goes unstable on them; the shipped hand's (armature 0.002, damping 0.1) pass
    both."""
    from gsp_jax.physics import preflight

    light = _light_scene(tmp_path, 0.0, 0.03)
    problems = preflight.joint_dynamics(hand_lib.load_mjmodel(light))
    assert len(problems) == 1 and "too light for the controller's finger gains" in problems[0], problems
    assert preflight.joint_dynamics(hand_lib.load_mjmodel(user_scene)) == []
    step, _ = preflight.finger_step(hand_lib.load_mjmodel(user_scene))
    assert 0 < step < preflight.FINGER_STEP
    bad = preflight.dry_run(Surrogate(model_lib.load_model(light), ik_config=table_ik))
    good = preflight.dry_run(Surrogate(model_lib.load_model(user_scene), ik_config=table_ik))
    assert bad.problems() and (bad.unstable_time >= 0 or bad.fell or bad.max_offset > preflight.THROWN), bad
    assert good.problems() == [] and good.unstable_time < 0 and good.max_offset < preflight.THROWN / 2, good


def test_check_model_names_a_tool_on_the_table_and_options_out_of_reach(tmp_path, user_model, table_ik):
    """A tool placed so the standard episodes start it in the table is named with the height to add (the user's
    tool: its knob, 16 mm across, hangs 4 mm above the table, 2 mm into it 6 mm lower); an option off to the side
    of the tool, beyond the fingers, is named by the reach report, and the options the fingers reach are not."""
    from gsp_jax.physics import preflight

    problems = preflight.clearance(Surrogate(user_model, ik_config=table_ik))
    assert len(problems) == 1 and "starts 4.0 mm above the table" in problems[0] and \
        "raise the tool body in the file by at least 3.0 mm" in problems[0], problems
    raised = model_lib.load_model(_write(tmp_path, TOOL.replace('pos="0 0 0.02"', 'pos="0 0 0.0231"')))
    assert preflight.clearance(Surrogate(raised, ik_config=table_ik)) == []
    far = TOOL.replace('<site name="opt_thumb_distal_2" pos="0.03 -0.0125 0" zaxis="0 1 0"/>',
                       '<site name="opt_thumb_distal_2" pos="0.03 -0.0125 0" zaxis="0 1 0"/>'
                       '<site name="opt_thumb_distal_3" pos="-0.2 0.3 0" zaxis="0 -1 0"/>')
    (tmp_path / "far").mkdir()
    reach = preflight.reach(Surrogate(model_lib.load_model(_write(tmp_path / "far", far)), ik_config=table_ik))
    assert reach.unreachable() == [("thumb_distal", 3)], reach.table()
    assert reach.error[0, 3].min() > 0.1 and reach.error[0, 1].max() < reach.tolerance


def test_check_model_lists_every_missing_file_at_once(tmp_path):
    """A published hand whose meshes are not beside it (issue 83): every missing file is named in one problem, where
    MuJoCo's compiler stops at the first; a file with its meshes present is not reported."""
    (tmp_path / "assets").mkdir()
    (tmp_path / "scene.xml").write_text(
        '<mujoco><compiler meshdir="assets"/><asset><mesh name="a" file="palm.stl"/><mesh name="b" file="tip.obj"/>'
        '<texture name="t" type="2d" file="skin.png"/></asset>'
        '<worldbody><body><geom type="mesh" mesh="a"/></body></worldbody></mujoco>')
    problems = model_lib.check_model(tmp_path / "scene.xml")
    assert len(problems) == 1 and "3 file(s)" in problems[0], problems
    for name in ("assets/palm.stl", "assets/tip.obj", "skin.png"):
        assert name in problems[0], problems
    assert model_lib.missing_files(model_lib.SHIPPED["allegro"]) == []


def test_check_model_checks_the_start_over_the_height_band(tmp_path, table_ik):
    """Issue 83: a placement whose nominal start is clear but whose start grasp collides at the highest start the
    sets and the corpus use (a handle 6 cm wide: at +14 mm the middle and index tips are pushed into it) is refused
    by check-model, naming the bodies and their depths; the shipped wrench passes. The clearance message never asks
    to raise the tool by 0.0 mm."""
    from gsp_jax.physics import preflight

    folder = hand_lib.MODELS_DIR
    (tmp_path / "hand.xml").write_text((folder / "hand.xml").read_text())
    (tmp_path / "scene.xml").write_text((folder / "scene.xml").read_text())
    wide = (folder / "wrench.xml").read_text().replace('size="0.075 0.0125 0.005"', 'size="0.075 0.03 0.005"')
    (tmp_path / "wrench.xml").write_text(wide)
    sur = Surrogate(model_lib.load_model(tmp_path / "scene.xml"), ik_config=table_ik, learned=False)
    assert preflight.start_reach(sur) == []  # the nominal start reaches and does not collide
    problems = preflight.start_band(sur)
    assert len(problems) == 1 and "14 mm higher" in problems[0], problems
    depths = re.findall(r"(\w+) into the tool (\d+\.\d) mm", problems[0])
    assert depths and all(float(d) > ik.IKConfig().collision_tol * 1e3 for _, d in depths), problems
    assert preflight.start_band(Surrogate(ik_config=table_ik, learned=False)) == []
    exact = (folder / "wrench.xml").read_text().replace('pos="0 0 0.014"', 'pos="0 0 0.013"')  # lowest point 7 mm
    (tmp_path / "wrench.xml").write_text(exact)
    assert preflight.clearance(Surrogate(model_lib.load_model(tmp_path / "scene.xml"), learned=False)) == []


def test_explain_names_the_grip_rule_and_where_the_opposing_contact_should_sit(sur):
    """Issue 83: every realised contact presses with at least the grip: the wrench's start grasp (thumb at x = -2 cm
    against the index and middle tips at 3 and 0 cm) holds without that floor but not with it, and `explain` says so,
    naming the thumb as the contact that opposes the others and its 35 mm from the line through their centroid; a
    sequence that falls without the floor too (the index tip alone) gets no such note."""
    ep = scenario.make_episode().head(4)
    why = sur.explain(ep, np.full(ep.n_steps, grasps.NULL, np.int32))
    assert why is not None and "without the grip floor it holds" in why, why
    assert re.search(r"thumb_distal opposes the others: its option is 35 mm from the line", why), why
    alone = sur.explain(ep, evaluation.one_tip(sur.space, ep.n_steps))
    assert alone is not None and "grip floor" not in alone, alone


def _testhand_with(folder: pathlib.Path, old: str, new: str) -> pathlib.Path:
    """The test hand's scene copied into `folder` with the one occurrence of `old` in its hand.xml replaced by `new`;
    the scene's path."""
    src = hand_lib.MODELS_DIR / "testhand"
    for name in ("scene.xml", "bar.xml"):
        (folder / name).write_text((src / name).read_text())
    hand_xml = (src / "hand.xml").read_text()
    assert hand_xml.count(old) == 1, old
    (folder / "hand.xml").write_text(hand_xml.replace(old, new))
    return folder / "scene.xml"


def test_the_placement_search_finds_a_palm_that_reaches(tmp_path):
    """Issue 83: the test hand with its palm raised 4 cm reaches no option at both ends of the lift and its start
    grasp misses; `placement.search` (along z only, 2 cm steps) moves the palm back down to where every option is
    reached at both ends and the start is clear, and reports the palm's position there."""
    from gsp_jax.physics import placement

    scene = _testhand_with(tmp_path, '<body name="palm" pos="0 0 0.11"', '<body name="palm" pos="0 0 0.15"')
    found = placement.search(scene, steps=((2, 0.02),), progress=False)
    raised = next(c for c in found if c.offset == (0.0, 0.0, 0.0))
    best = found[0]
    assert not raised.clear and raised.both < raised.options, raised
    assert best.clear and best.both == best.options and best.offset[2] < 0, best
    assert best.pos[2] == pytest.approx(0.15 + best.offset[2]) and best.pos[2] <= 0.13 + 1e-9
    assert not list(tmp_path.glob(".*place*")), "the candidates' scene files are left behind"


def test_the_allegro_screwdriver_scene_follows_the_conventions():
    """The hands table's Allegro x screwdriver cell (a scene file beside the shipped models, not a shipped name)."""
    assert model_lib.check_model(hand_lib.MODELS_DIR / "allegro-screwdriver" / "scene.xml") == []


def test_the_ik_start_drawn_puts_each_link_near_its_option(tmp_path):
    """Issue 83: the test hand with its IK start flexed the wrong way (every link 15 mm from its start option at
    mid-lift) gets a start from `placement.ik_start` that puts every link's contact centre within 3 mm of where it
    touches its option, by MuJoCo's forward kinematics; the surrogate's own kinematics (JAX) measure the same gaps;
    no link ends further than the file's start left it (+1 mm)."""
    from gsp_jax.model import kinematics
    from gsp_jax.physics import placement

    start_xml = '<numeric name="gsp_ik_start" data="{}"'
    model = model_lib.load_model(_testhand_with(tmp_path, start_xml.format("0.3 0.6   0.3 0.6   0.3 0.6"),
                                                start_xml.format("-0.5 2.2 -0.5 2.2 -0.5 2.2")))
    start = placement.ik_start(model, samples=2000)
    assert np.all(start.gap_before > 0.01) and np.all(start.gap < 0.003), (start.gap_before, start.gap)
    assert np.all(start.gap <= start.gap_before + 1e-3)
    hand = model.hand
    episode = scenario.make_episode(model=model)
    t = episode.n_steps // 2
    mat = np.asarray(kinematics.quat_to_mat(episode.quats[t]))
    opts = np.where(np.asarray(hand.start_options) > 0, hand.start_options, 1)
    li = np.arange(hand.n_links)
    target = (np.asarray(episode.waypoints[t]) + hand.option_pos[li, opts] @ mat.T
              - (hand.option_normal[li, opts] @ mat.T) * hand.link_radius[:, None])
    centre, _ = kinematics.contact_segments(hand, jnp.asarray(start.q))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(centre) - target, axis=1), start.gap, atol=1e-4)


def test_check_model_names_a_hand_that_passes_through_the_table(table_ik):
    """Issue 83: the physics simulates only the tool's and the fingertips' contacts, so a start grasp whose hand
    passes through itself or the table would plan and hold; `preflight.hand_overlaps` finds it in MuJoCo with every
    hand geom colliding. The test hand's start grasp is clean; the same hand with its fingers straight (the IK's pose
    replaced) has each distal capsule in the table by its lowest point's depth below z = 0, as MuJoCo's geometry
    says (radius + half-length - centre height, each capsule hanging straight down)."""
    from gsp_jax.physics import preflight

    model = model_lib.load_model(hand_lib.MODELS_DIR / "testhand" / "scene.xml")
    sur = Surrogate(model, ik_config=table_ik, learned=False)
    assert preflight.hand_overlaps(sur) == []

    class Straight:  # the surrogate with every realised pose replaced by the fingers straight down
        def __getattr__(self, name):
            return getattr(sur, name)

        def realise(self, grasp, pos, quat):
            c = sur.realise(grasp, pos, quat)
            return c.replace(ik=c.ik.replace(q=jnp.zeros_like(c.ik.q)))

    found = preflight.hand_overlaps(Straight())
    assert len(found) == 1, found
    m = model.mjmodel
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    for name in ("thumb_distal", "index_distal", "middle_distal"):
        g = next(g for g in range(m.ngeom) if m.geom_bodyid[g] == m.body(name).id)
        depth = m.geom_size[g, 0] + m.geom_size[g, 1] - d.geom_xpos[g, 2]
        assert depth > preflight.OVERLAP
        said = re.search(rf"(?:table and {name}|{name} and table) (\d+\.\d) mm", found[0])
        assert said and float(said.group(1)) == pytest.approx(depth * 1e3, abs=0.06), (name, depth, found[0])


def test_the_orientation_screen_turns_an_upside_down_palm_back(tmp_path):
    """Issue 83: the test hand with its palm turned upside down (180 degrees about x) reaches few options; the
    orientation screen (forward kinematics over the 24 axis-aligned turns, no IK) finds the file's original
    orientation reaching every option at both ends of the lift, near the original position (within 2 cm), and
    ranks the upside-down one lower."""
    from gsp_jax.physics import placement

    palm = '<body name="palm" pos="0 0 0.11"'
    scene = _testhand_with(tmp_path, palm, palm + ' quat="0 1 0 0"')
    poses = placement.orientations(scene, samples=1500)
    best = poses[0]
    assert best.both == best.options, best
    assert abs(abs(best.quat[0]) - 1.0) < 1e-6, best  # the identity: the original palm, facing down
    assert np.linalg.norm(np.subtract(best.pos, (0.0, 0.0, 0.11))) <= 0.02 + 1e-9, best
    _, own = placement.palm_pose(scene)
    upside_down = [p for p in poses if abs(float(np.dot(p.quat, own))) > 0.999]
    assert not upside_down or upside_down[0].both < best.both, upside_down
