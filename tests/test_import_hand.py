"""`gsp_jax.importer` (`python -m experiments import-hand`): a published-style MJCF hand (box and mesh collision
geoms, a visual mesh, position servos, a tendon-coupled joint pair, damping 0.03 without armature) -> a hand file
that follows the conventions. The tests build their own small hand; MuJoCo and numpy only (no JAX compile)."""
from __future__ import annotations

import pathlib
import re

import mujoco
import numpy as np
import pytest

from gsp_jax import importer
from gsp_jax.model import hand as hand_lib
from gsp_jax.model import load as model_lib

TIP_OBJ = """# a stretched diamond (convex), 6 vertices, 8 faces [m]
v 0.007 0 0.008
v 0 0.006 0.008
v -0.007 0 0.008
v 0 -0.006 0.008
v 0 0 0.022
v 0 0 0
f 1 2 5
f 2 3 5
f 3 4 5
f 4 1 5
f 2 1 6
f 3 2 6
f 4 3 6
f 1 4 6
"""
SHELL_OBJ = """# a tetrahedron (visual only)
v 0.009 0 0
v -0.009 0.008 0
v -0.009 -0.008 0
v 0 0 0.012
f 1 2 4
f 2 3 4
f 3 1 4
f 1 3 2
"""
JOINTS = ("index_j1", "index_j2", "middle_j1", "middle_j2", "thumb_j1", "thumb_j2")
HOME = dict(index_j1=0.1, index_j2=0.2, middle_j1=0.3, middle_j2=0.4, thumb_j1=0.05, thumb_j2=0.15)
# the torque limits the motors must get: forcerange x gear, the tendon's forcerange x |coef|, the torque_limit given
LIMITS = dict(index_j1=0.6, index_j2=1.2, middle_j1=0.8, middle_j2=0.4, thumb_j1=0.6, thumb_j2=0.5)
TORQUE_LIMIT = 0.5


def hand_xml(prefix: str = "", arm: bool = False) -> str:
    """The small hand: a palm box and three fingers of two links (index: box + mesh tip, its distal link with an
    explicit inertial; middle: two boxes + box and a sphere pad, its joints driven through a fixed tendon; thumb:
    a cylinder + box, its last joint's servo without force range). With `arm`, the palm hangs below an arm body
    with a wrist hinge (and its servo)."""
    p = prefix
    wrist = ("<body name=\"{p}arm\" pos=\"0 0 0.35\" euler=\"0 0.3 0\">\n"
             "      <joint name=\"{p}wrist\" axis=\"0 1 0\" range=\"-1 1\"/>\n"
             "      <geom name=\"{p}arm\" type=\"box\" size=\"0.03 0.03 0.05\"/>\n") if arm else ""
    palm_pose = 'pos="0 0 -0.12" euler="0.2 0 0.1"' if arm else 'pos="0 0 0.2"'
    wrist_act = '<position name="{p}wrist_act" joint="{p}wrist" forcerange="-5 5" ctrlrange="-1 1"/>' if arm else ""
    qpos = ("0.25 " if arm else "") + " ".join(str(HOME[j]) for j in JOINTS)
    xml = f"""<mujoco model="toy_hand">
  <compiler angle="radian" meshdir="meshes" autolimits="true"/>
  <option timestep="0.001" iterations="5" integrator="implicitfast"/>
  <asset>
    <mesh name="tip" file="tip.obj"/>
    <mesh name="shell" file="shell.obj"/>
  </asset>
  <default>
    <joint damping="0.03" axis="1 0 0" range="-0.3 1.6"/>
    <geom contype="1" conaffinity="1" condim="4" friction="0.8 0.02 0.001" solref="0.01 1" solimp="0.9 0.95 0.001"
          margin="0.0005" density="800"/>
    <position kp="3" ctrlrange="-0.3 1.6" forcerange="-0.6 0.6"/>
    <default class="visual">
      <geom type="mesh" contype="0" conaffinity="0" density="0" group="2"/>
    </default>
  </default>
  <worldbody>
    {wrist}
    <body name="{{p}}palm" {palm_pose}>
      <geom name="{{p}}palm" type="box" size="0.04 0.05 0.01"/>
      <body name="{{p}}index_prox" pos="0.025 0.05 0">
        <joint name="{{p}}index_j1"/>
        <geom name="{{p}}index_prox" type="box" size="0.008 0.02 0.007" pos="0 0.02 0"/>
        <geom name="{{p}}index_shell" class="visual" mesh="shell" pos="0 0.02 0.007"/>
        <body name="{{p}}index_dist" pos="0 0.04 0">
          <inertial pos="0 0.01 0" mass="0.02" diaginertia="2e-6 1e-6 2e-6"/>
          <joint name="{{p}}index_j2"/>
          <geom name="{{p}}index_tip" type="mesh" mesh="tip" euler="-1.5708 0 0"/>
        </body>
      </body>
      <body name="{{p}}middle_prox" pos="0 0.05 0">
        <joint name="{{p}}middle_j1"/>
        <geom name="{{p}}middle_a" type="box" size="0.008 0.012 0.007" pos="0 0.012 0"/>
        <geom name="{{p}}middle_b" type="box" size="0.006 0.01 0.005" pos="0.002 0.03 0.001" euler="0 0 0.2"
              friction="0.5 0.02 0.001"/>
        <body name="{{p}}middle_dist" pos="0 0.042 0">
          <joint name="{{p}}middle_j2"/>
          <geom name="{{p}}middle_dist" type="box" size="0.007 0.015 0.006" pos="0 0.015 0"/>
          <geom name="{{p}}middle_pad" type="sphere" size="0.007" pos="0 0.03 0"/>
        </body>
      </body>
      <body name="{{p}}thumb_base" pos="-0.03 0.0 -0.01" euler="0 0 0.8">
        <joint name="{{p}}thumb_j1" axis="0 0 1" range="-0.8 0.8"/>
        <geom name="{{p}}thumb_base" type="cylinder" size="0.009 0.012" pos="0 0.012 0" euler="1.5708 0 0"/>
        <body name="{{p}}thumb_dist" pos="0 0.03 0">
          <joint name="{{p}}thumb_j2"/>
          <geom name="{{p}}thumb_dist" type="box" size="0.008 0.018 0.007" pos="0 0.018 0"/>
        </body>
      </body>
    </body>
    {"</body>" if arm else ""}
  </worldbody>
  <contact>
    <exclude body1="{{p}}palm" body2="{{p}}thumb_dist"/>
  </contact>
  <tendon>
    <fixed name="{{p}}middle_couple">
      <joint joint="{{p}}middle_j1" coef="1"/>
      <joint joint="{{p}}middle_j2" coef="0.5"/>
    </fixed>
  </tendon>
  <equality>
    <joint name="{{p}}thumb_follow" joint1="{{p}}thumb_j2" joint2="{{p}}thumb_j1" polycoef="0 0.1 0 0 0"
           active="false"/>
  </equality>
  <actuator>
    {wrist_act}
    <position name="{{p}}index_a1" joint="{{p}}index_j1"/>
    <position name="{{p}}index_a2" joint="{{p}}index_j2" gear="2" ctrlrange="-0.15 0.8"/>
    <position name="{{p}}middle_act" tendon="{{p}}middle_couple" ctrlrange="-0.5 2" forcerange="-0.8 0.8"/>
    <position name="{{p}}thumb_a1" joint="{{p}}thumb_j1" ctrlrange="-0.8 0.8"/>
    <position name="{{p}}thumb_a2" joint="{{p}}thumb_j2" forcelimited="false"/>
  </actuator>
  <sensor>
    <jointpos name="{{p}}index_j1_pos" joint="{{p}}index_j1"/>
    <actuatorfrc name="{{p}}index_a1_frc" actuator="{{p}}index_a1"/>
    <actuatorfrc name="{{p}}middle_act_frc" actuator="{{p}}middle_act"/>
  </sensor>
  <keyframe>
    <key name="home" qpos="{qpos}"/>
    <key name="grip" qpos="{qpos}" ctrl="{"0 " if arm else ""}0.5 0.2 1 0 0.3"/>
  </keyframe>
</mujoco>
"""
    return xml.replace("{p}", p)


def write_hand(folder: pathlib.Path, prefix: str = "", arm: bool = False) -> pathlib.Path:
    """The small hand's file and its meshes (meshes/tip.obj, meshes/shell.obj) in `folder`; its path."""
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    (folder / "meshes" / "tip.obj").write_text(TIP_OBJ)
    (folder / "meshes" / "shell.obj").write_text(SHELL_OBJ)
    path = folder / "toy_hand.xml"
    path.write_text(hand_xml(prefix, arm))
    return path


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """The small hand imported (torque limit 0.5 N m for its one servo without force range) and written."""
    folder = tmp_path_factory.mktemp("toy")
    src = write_hand(folder / "src")
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT)
    return src, result, result.write(folder / "out")


def _compiled(path) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(path))


def _posed(m: mujoco.MjModel, angles: dict[str, float]) -> mujoco.MjData:
    d = mujoco.MjData(m)
    for name, q in angles.items():
        d.qpos[m.jnt_qposadr[m.joint(name).id]] = q
    mujoco.mj_kinematics(m, d)
    return d


def _world_points(m: mujoco.MjModel, d: mujoco.MjData, g: int) -> np.ndarray:
    """A box's 8 corners or a mesh's (compiled) vertices, in the world [m]."""
    if int(m.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_BOX):
        local = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * m.geom_size[g]
    else:
        mesh = m.geom_dataid[g]
        local = m.mesh_vert[m.mesh_vertadr[mesh]:m.mesh_vertadr[mesh] + m.mesh_vertnum[mesh]]
    return d.geom_xpos[g] + local @ d.geom_xmat[g].reshape(3, 3).T


def _round_geoms(m: mujoco.MjModel, d: mujoco.MjData, body: int) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """The body's colliding capsules and spheres: (segment start, segment end, radius), in the world [m]."""
    out = []
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != body or not hand_lib.collides(m, g):
            continue
        half = m.geom_size[g][1] if int(m.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_CAPSULE) else 0.0
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        out.append((d.geom_xpos[g] - half * axis, d.geom_xpos[g] + half * axis, float(m.geom_size[g][0])))
    return out


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Brute force: each point's (N, 3) distance from the segment a-b [m]."""
    ab = b - a
    u = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-30), 0.0, 1.0)
    return np.linalg.norm(p - (a + u[:, None] * ab), axis=1)


def test_the_fitted_geoms_cover_every_original_point(imported):
    """Compiled at the same joint angles, every box corner and mesh vertex of the original lies within a capsule
    or sphere of its body in the written file (1e-6 m), and no fitted radius exceeds the largest distance of the
    body's points from their centroid."""
    src, result, out = imported
    m0, m1 = _compiled(src), _compiled(out)
    d0, d1 = _posed(m0, HOME), _posed(m1, HOME)
    checked = 0
    for b0 in range(1, m0.nbody):
        if m0.body(b0).name == "palm":
            continue
        geoms = [g for g in range(m0.ngeom) if m0.geom_bodyid[g] == b0 and hand_lib.collides(m0, g)
                 and int(m0.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_MESH))]
        if not geoms:
            continue
        points = np.concatenate([_world_points(m0, d0, g) for g in geoms])
        rounds = _round_geoms(m1, d1, m1.body(m0.body(b0).name).id)
        inside = np.min([_segment_distance(points, a, b) - r for a, b, r in rounds], axis=0)
        assert inside.max() <= 1e-6, (m0.body(b0).name, inside.max())
        reach = np.linalg.norm(points - points.mean(0), axis=1).max()
        fitted = [r for r in result.replacements if r.body == m0.body(b0).name]
        assert fitted and all(r.fit.radius <= reach + 1e-9 for r in fitted), (m0.body(b0).name, fitted, reach)
        checked += len(points)
    assert checked >= 5 * 8 + 6  # the boxes' corners and the tip's vertices


def test_geoms_below_the_palm_are_capsules_or_spheres_and_keep_their_contact_attributes(imported):
    _, result, out = imported
    m = _compiled(out)
    palm = m.body("palm").id
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != palm and hand_lib.collides(m, g):
            assert int(m.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_SPHERE)), \
                m.geom(g).name
            assert m.geom_condim[g] == 4 and m.geom_margin[g] == pytest.approx(0.0005)
            np.testing.assert_allclose(m.geom_solref[g], [0.01, 1])
            np.testing.assert_allclose(m.geom_solimp[g][:3], [0.9, 0.95, 0.001])
    assert m.geom("palm").type == mujoco.mjtGeom.mjGEOM_BOX  # the palm's own geoms stay
    assert m.geom("middle_pad").type == mujoco.mjtGeom.mjGEOM_SPHERE  # an existing sphere stays
    assert m.geom("index_prox").type == mujoco.mjtGeom.mjGEOM_CAPSULE  # a body's only geom keeps its name
    np.testing.assert_allclose(m.geom("middle_prox_capsule").friction, [0.8, 0.02, 0.001])  # the first geom's
    assert any("middle_prox" in c and "differ in friction" in c for c in result.changes)
    assert len(result.replacements) == 6  # index_prox, index_dist, middle_prox, middle_dist, thumb_base, thumb_dist
    assert all(r.over_cover >= 0 and r.n_points >= 6 for r in result.replacements)


def test_the_bodies_keep_their_mass_and_inertia(imported):
    src, _, out = imported
    m0, m1 = _compiled(src), _compiled(out)
    for b in range(1, m0.nbody):
        b1 = m1.body(m0.body(b).name).id
        assert m1.body_mass[b1] == pytest.approx(m0.body_mass[b], rel=1e-5), m0.body(b).name
        np.testing.assert_allclose(m1.body_inertia[b1], m0.body_inertia[b], rtol=1e-4)
        np.testing.assert_allclose(m1.body_ipos[b1], m0.body_ipos[b], atol=1e-7)
    assert m1.body_mass[m1.body("index_dist").id] == pytest.approx(0.02)  # the explicit <inertial> kept


def test_every_hinge_gets_one_torque_motor_of_the_actuators_limit(imported):
    """Servos become motors (gear 1, ctrlrange ±forcerange·gear), the tendon's servo one motor per joint (±its
    forcerange·|coef|), the servo without force range the torque limit given; a control is the joint's torque."""
    _, result, out = imported
    m = _compiled(out)
    assert m.nu == m.njnt == len(JOINTS)
    for a in range(m.nu):
        assert m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
        assert m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED and m.actuator_gainprm[a, 0] == 1
        assert m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE
        assert m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE
        assert m.actuator_gear[a, 0] == 1 and m.actuator_ctrllimited[a]
    driven = {m.joint(m.actuator_trnid[a, 0]).name: a for a in range(m.nu)}
    assert sorted(driven) == sorted(JOINTS)
    for joint, limit in LIMITS.items():
        np.testing.assert_allclose(m.actuator_ctrlrange[driven[joint]], [-limit, limit], err_msg=joint)
    assert m.actuator(driven["index_j1"]).name == "index_a1"  # converted in place: name and sensor kept
    assert m.sensor("index_a1_frc").id >= 0 and m.ntendon == 1
    assert any("middle_act" in c and "tendon" in c for c in result.changes)
    d = mujoco.MjData(m)
    d.ctrl[:] = np.linspace(-0.3, 0.3, m.nu)
    mujoco.mj_forward(m, d)
    for a in range(m.nu):
        assert d.qfrc_actuator[m.jnt_dofadr[m.actuator_trnid[a, 0]]] == pytest.approx(d.ctrl[a], abs=1e-12)


def test_joint_dynamics_and_the_option_are_set(imported):
    _, result, out = imported
    m = _compiled(out)
    np.testing.assert_allclose(m.dof_damping, hand_lib.JOINT_DAMPING)
    np.testing.assert_allclose(m.dof_armature, hand_lib.JOINT_ARMATURE)
    np.testing.assert_allclose(m.dof_frictionloss, hand_lib.JOINT_FRICTIONLOSS)
    text = "\n".join(result.changes)
    assert f"damping 0.03 -> {hand_lib.JOINT_DAMPING:g}" in text and "armature 0 ->" in text
    assert m.opt.iterations == mujoco.MjModel.from_xml_string("<mujoco/>").opt.iterations
    assert "<option> dropped" in text and "iterations 5" in text
    assert "equality 'thumb_follow'" in text  # a coupling kept, and said so
    np.testing.assert_allclose(m.jnt_range[m.joint("thumb_j1").id], [-0.8, 0.8])  # ranges untouched


def test_keyframes_without_controls_stay(imported):
    _, result, out = imported
    m = _compiled(out)
    assert m.nkey == 1 and m.key(0).name == "home"
    for joint, q in HOME.items():
        assert m.key_qpos[0, m.jnt_qposadr[m.joint(joint).id]] == pytest.approx(q)
    assert any("keyframe 'grip' removed" in c for c in result.changes)


def test_the_written_file_compiles_from_its_folder_with_its_meshes(imported):
    _, result, out = imported
    assert (out.parent / "assets" / "shell.obj").is_file()  # the visual mesh, kept
    assert not (out.parent / "assets" / "tip.obj").exists()  # the collision mesh, replaced by a capsule
    m = _compiled(out)
    visual = [g for g in range(m.ngeom) if not hand_lib.collides(m, g)]
    assert [m.geom(g).name for g in visual] == ["index_shell"]
    assert int(m.geom_type[visual[0]]) == int(mujoco.mjtGeom.mjGEOM_MESH)
    head = out.read_text().split("-->")[0]
    assert str(result.source) in head and "gsp_contact_links" in head and "--" not in head[4:]
    for change in result.changes:
        assert change.split()[0] in " ".join(head.split())


def test_visual_geoms_go_with_drop_visual(tmp_path):
    src = write_hand(tmp_path / "src")
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT, drop_visual=True)
    out = result.write(tmp_path / "out")
    m = _compiled(out)
    assert all(hand_lib.collides(m, g) for g in range(m.ngeom)) and m.nmesh == 0
    assert not (tmp_path / "out" / "assets").exists()


def test_a_missing_visual_mesh_names_its_file_and_suggests_drop_visual(tmp_path):
    src = write_hand(tmp_path / "src")
    (tmp_path / "src" / "meshes" / "shell.obj").unlink()
    with pytest.raises(ValueError, match="shell.obj") as err:
        importer.import_hand(src, torque_limit=TORQUE_LIMIT)
    assert "--drop-visual" in str(err.value)
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT, drop_visual=True)
    assert _compiled(result.write(tmp_path / "out")).nmesh == 0


def test_a_missing_collision_mesh_is_an_error_naming_it(tmp_path):
    """... and names --drop-missing; with it the geom is removed, said so, and the hand compiles with that body
    colliding with nothing (issue 83: the Sharpa Wave's pinky metacarpal, an STL file not at hand)."""
    src = write_hand(tmp_path / "src")
    (tmp_path / "src" / "meshes" / "tip.obj").unlink()
    with pytest.raises(importer.HandImportError, match="tip.obj.*index_tip") as err:
        importer.import_hand(src, torque_limit=TORQUE_LIMIT, drop_visual=True)
    assert "--drop-missing" in str(err.value)
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT, drop_visual=True, drop_missing=True)
    said = [c for c in result.changes if "tip.obj" in c]
    assert len(said) == 1 and "body 'index_dist' collides with nothing" in said[0], result.changes
    m = _compiled(result.write(tmp_path / "out"))
    tip = m.body("index_dist").id
    assert not any(m.geom_bodyid[g] == tip and hand_lib.collides(m, g) for g in range(m.ngeom))


def test_a_servo_without_force_range_needs_the_torque_limit(tmp_path):
    src = write_hand(tmp_path / "src")
    with pytest.raises(ValueError) as err:
        importer.import_hand(src)
    message = str(err.value)
    assert "thumb_j2" in message and "--torque-limit" in message and "position servo" in message
    assert "index_j1" not in message  # its servo has a force range


def test_per_geom_fits_one_capsule_per_geom(tmp_path):
    src = write_hand(tmp_path / "src")
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT, per_geom=True)
    m = _compiled(result.write(tmp_path / "out"))
    body = m.body("middle_prox").id
    assert len([g for g in range(m.ngeom) if m.geom_bodyid[g] == body and hand_lib.collides(m, g)]) == 2
    np.testing.assert_allclose(m.geom("middle_b").friction, [0.5, 0.02, 0.001])  # each geom's own
    # a tip's contact site goes on the geom that reaches farthest (the pad), not on the phalanx's largest capsule
    tips = importer.import_hand(src, torque_limit=TORQUE_LIMIT, per_geom=True,
                                contact_links=["thumb_dist", "index_dist", "middle_dist"])
    site = _compiled(tips.write(tmp_path / "tips")).site("contact_middle_dist")
    np.testing.assert_allclose(site.pos, [0.0, 0.03, 0.0], atol=1e-9)
    assert site.size[0] == pytest.approx(0.007)


def test_a_palm_deeper_in_the_tree_becomes_the_worlds_child_at_its_pose(tmp_path):
    """--palm: the palm takes its world pose at the file's zero configuration; the arm, the wrist joint and its
    servo are dropped (and said so); the keyframe keeps the hand's joint angles."""
    src = write_hand(tmp_path / "src", arm=True)
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT, palm="palm")
    out = result.write(tmp_path / "out")
    m0, m1 = _compiled(src), _compiled(out)
    d0, d1 = _posed(m0, {}), _posed(m1, {})
    assert m1.body_parentid[m1.body("palm").id] == 0 and m1.njnt == len(JOINTS) and m1.nu == len(JOINTS)
    np.testing.assert_allclose(d1.xpos[m1.body("palm").id], d0.xpos[m0.body("palm").id], atol=1e-6)
    np.testing.assert_allclose(d1.xmat[m1.body("palm").id], d0.xmat[m0.body("palm").id], atol=1e-5)  # 6 digits
    assert mujoco.mj_name2id(m1, mujoco.mjtObj.mjOBJ_BODY, "arm") < 0
    text = "\n".join(result.changes)
    assert "'arm'" in text and "wrist" in text and "wrist_act" in text
    for joint, q in HOME.items():
        assert m1.key_qpos[0, m1.jnt_qposadr[m1.joint(joint).id]] == pytest.approx(q)


def test_palm_pose_is_set_when_given(tmp_path):
    src = write_hand(tmp_path / "src")
    quat = np.array([0.0, 1.0, 0.0, 0.0])
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT, palm_pos=(0.01, 0.02, 0.15), palm_quat=quat)
    m = _compiled(result.write(tmp_path / "out"))
    np.testing.assert_allclose(m.body_pos[m.body("palm").id], [0.01, 0.02, 0.15])
    np.testing.assert_allclose(np.abs(m.body_quat[m.body("palm").id]), quat)
    assert any("position set" in c for c in result.changes) and any("orientation set" in c for c in result.changes)
    with pytest.raises(ValueError, match="palm_quat"):
        importer.import_hand(src, torque_limit=TORQUE_LIMIT, palm_quat=(0, 0, 0))


def test_a_common_prefix_that_makes_the_fingers_collide_is_stripped(tmp_path):
    src = write_hand(tmp_path / "src", prefix="lh_")
    result = importer.import_hand(src, torque_limit=TORQUE_LIMIT)
    m = _compiled(result.write(tmp_path / "out"))
    assert result.palm == "palm" and "palm" in [m.body(b).name for b in range(m.nbody)]
    assert sorted(m.joint(j).name for j in range(m.njnt)) == sorted(JOINTS)
    assert m.tendon("middle_couple").id >= 0 and m.exclude_signature.size == 1
    assert sorted({m.actuator(a).name for a in range(m.nu)}) == sorted(
        {"index_a1", "index_a2", "thumb_a1", "thumb_a2", "middle_j1_motor", "middle_j2_motor"})
    assert any("'lh_'" in c for c in result.changes)


def test_importing_an_imported_hand_changes_nothing(imported, tmp_path):
    _, _, out = imported
    again = importer.import_hand(out)
    assert not again.replacements
    assert [c for c in again.changes if not c.startswith(("palm ", "NOTE", "kept: equality", "keyframe 'home' kept"))] \
        == []


def test_with_a_tool_and_a_table_the_hand_follows_the_conventions(imported):
    """The user's part (contact links and their sites, the IK start, a tool with options, a table) added to the
    written hand: `check_model` finds nothing about its geoms, actuators (motors) or joints."""
    _, _, out = imported
    spec = mujoco.MjSpec.from_file(str(out))
    spec.add_text(name="gsp_contact_links", data="thumb_dist index_dist middle_dist")
    spec.add_numeric(name="gsp_ik_start", data=[0.0] * len(JOINTS))
    for link, pos in (("thumb_dist", (0, 0.035, 0)), ("index_dist", (0, 0.02, 0)), ("middle_dist", (0, 0.03, 0))):
        spec.body(link).add_site(name=f"contact_{link}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.007, 0, 0],
                                 pos=pos)
    tool = spec.worldbody.add_body(name="block", pos=[0, 0.09, 0.02])
    tool.add_freejoint()
    tool.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, 0.02], mass=0.1)
    for k, link in enumerate(("thumb_dist", "index_dist", "middle_dist")):
        tool.add_site(name=f"opt_{link}_1", pos=[0.02 * (k - 1), 0, 0.02], zaxis=[0, 0, -1])
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0.3, 0.3, 0.01])
    scene = out.parent / "scene.xml"
    scene.write_text(spec.to_xml())
    problems = model_lib.check_model(scene)
    about_the_hand = [p for p in problems if any(w in p for w in ("geom", "actuator", "motor", "joint"))]
    assert about_the_hand == [], problems
    assert mujoco.MjModel.from_xml_path(str(scene)).nbody == 9


def test_fit_round_covers_its_points_and_prefers_the_smaller_geom():
    rng = np.random.default_rng(3)
    rod = rng.normal(size=(200, 3)) * [0.02, 0.003, 0.004]
    fit = importer.fit_round(rod)
    assert fit.kind == "capsule" and importer.segment_distance(rod, fit.ends).max() <= fit.radius
    assert abs(np.diff(fit.ends, axis=0)[0] @ [1, 0, 0]) > 0.9 * fit.length  # along the long axis
    ball = rng.normal(size=(200, 3))
    ball = 0.01 * ball / np.linalg.norm(ball, axis=1, keepdims=True)  # points on a sphere of 1 cm
    fit = importer.fit_round(ball)
    assert fit.kind == "sphere" and fit.radius == pytest.approx(0.01, rel=1e-3)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * [0.005, 0.006, 0.03]
    box = importer.fit_round(corners)
    assert box.radius == pytest.approx(np.hypot(0.005, 0.006), rel=1e-6)  # the smallest radius across the box
    np.testing.assert_allclose(sorted(np.abs(box.ends[:, 2])), [0.03, 0.03], atol=1e-9)


def test_min_circle_is_the_smallest_enclosing_circle():
    rng = np.random.default_rng(0)
    for _ in range(20):
        p = rng.normal(size=(rng.integers(3, 40), 2))
        c, r = importer.min_circle(p)
        assert np.linalg.norm(p - c, axis=1).max() <= r * (1 + 1e-9)
        pairs = max(np.linalg.norm(a - b) / 2 for a in p for b in p)
        assert r >= pairs - 1e-12  # no circle is smaller than half the widest pair
        grid = c + 0.01 * rng.normal(size=(50, 2))  # no nearby centre does better
        assert all(np.linalg.norm(p - g, axis=1).max() >= r - 1e-12 for g in grid)


def test_contact_links_and_the_ik_start_are_written_with_their_sites(tmp_path):
    """`contact_links` writes gsp_contact_links and each link's site: a finger's deepest link a sphere at the far end
    of its geom (the end farther from the body's joint), with the geom's radius; a link above it a capsule along its
    geom. `start` writes gsp_ik_start; angles outside the joint ranges and unknown bodies are refused by name."""
    src = write_hand(tmp_path / "src")
    res = importer.import_hand(src, torque_limit=TORQUE_LIMIT, contact_links=["index_prox", "index_dist"],
                               start=[0.1] * len(JOINTS))
    m = _compiled(res.write(tmp_path / "out"))
    assert hand_lib._text(m, "gsp_contact_links") == "index_prox index_dist"
    np.testing.assert_allclose(hand_lib._numeric(m, "gsp_ik_start"), [0.1] * len(JOINTS))
    for link, kind in (("index_dist", mujoco.mjtGeom.mjGEOM_SPHERE), ("index_prox", mujoco.mjtGeom.mjGEOM_CAPSULE)):
        s, b = m.site(f"contact_{link}").id, m.body(link).id
        assert int(m.site_type[s]) == int(kind) and m.site_bodyid[s] == b
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] == b and hand_lib.collides(m, g)]
        g = max(geoms, key=lambda g: m.geom_size[g, 0])
        assert m.site_size[s, 0] == pytest.approx(m.geom_size[g, 0], rel=1e-5)
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE:  # on the geom's axis, at its end farther from the joint
            axis = hand_lib._quat_to_mat(m.geom_quat[g])[:, 2]
            ends = [m.geom_pos[g] + s_ * m.geom_size[g, 1] * axis for s_ in (-1, 1)]
            far = max(ends, key=np.linalg.norm)
            np.testing.assert_allclose(m.site_pos[s], far, atol=1e-6)
    with pytest.raises(importer.HandImportError, match=r"ik_start: outside the joint ranges: index_j1 5"):
        importer.import_hand(src, torque_limit=TORQUE_LIMIT, start=[5.0] + [0.1] * (len(JOINTS) - 1))
    with pytest.raises(importer.HandImportError, match=r"contact_links: 'pinky' is not a body of the hand"):
        importer.import_hand(src, torque_limit=TORQUE_LIMIT, contact_links=["pinky"])


def test_bodies_whose_mass_was_in_dropped_visual_geoms_take_it_from_their_collision_geoms(tmp_path):
    """Menagerie's Allegro keeps its links' mass in the visual meshes (collision boxes mass 0): where the visual
    meshes' files are not at hand and the visual geoms are dropped, each such body's mass comes from its collision
    geoms' volume at their density (with the files, the body's mass and inertia are kept as the file computes
    them)."""
    spec = mujoco.MjSpec.from_file(str(write_hand(tmp_path / "src")))
    body = next(b for b in spec.bodies if b.name == "middle_prox")
    for g in body.geoms:
        g.mass = 0.0
    body.add_geom(name="skin", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="shell", contype=0, conaffinity=0)
    (tmp_path / "src" / "heavy_skin.xml").write_text(spec.to_xml())
    (tmp_path / "src" / "meshes" / "shell.obj").unlink()  # its visual meshes not at hand (as Menagerie's STLs here)
    res = importer.import_hand(tmp_path / "src" / "heavy_skin.xml", torque_limit=TORQUE_LIMIT, drop_visual=True)
    line = next(c for c in res.changes if c.startswith("body 'middle_prox': no mass left"))
    density = float(re.search(r"density ([0-9.]+) kg/m\^3", line).group(1))
    volume = sum(8 * np.prod(g.size) for g in body.geoms if g.type == mujoco.mjtGeom.mjGEOM_BOX)
    assert res.spec.compile().body("middle_prox").mass[0] == pytest.approx(density * volume, rel=1e-6)


def test_a_moving_body_whose_only_geom_was_a_dropped_visual_mesh_gets_a_mass(tmp_path):
    """Issue 83: a body that moves and whose only geom is a visual mesh whose file is missing (a knuckle drawn by a
    mesh, its mass in it) compiled to 'mass and inertia of moving bodies must be larger than mjMINVAL'; with
    --drop-visual it now gets a few grams at its origin, and the change says so and names it."""
    spec = mujoco.MjSpec.from_file(str(write_hand(tmp_path / "src")))
    parent = next(b for b in spec.bodies if b.name == "middle_prox")
    knuckle = parent.add_body(name="knuckle", pos=[0, 0, 0.01])
    knuckle.add_joint(name="knuckle_hinge", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[1, 0, 0], range=[-0.1, 0.1])
    knuckle.add_geom(name="knuckle_skin", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="shell", contype=0, conaffinity=0)
    (tmp_path / "src" / "knuckle.xml").write_text(spec.to_xml())
    (tmp_path / "src" / "meshes" / "shell.obj").unlink()
    res = importer.import_hand(tmp_path / "src" / "knuckle.xml", torque_limit=TORQUE_LIMIT, drop_visual=True)
    line = next(c for c in res.changes if c.startswith("body 'knuckle': no mass left"))
    assert "5 g" in line, line
    m = res.spec.compile()
    assert m.body("knuckle").mass[0] == pytest.approx(0.005) and np.all(m.body("knuckle").inertia > 0)


def test_a_missing_palm_mesh_is_not_said_to_be_fitted(tmp_path):
    """Issue 83: the palm's geoms are kept as the file has them (only the fingers' are fitted): a collision mesh of
    the palm whose file is missing is named with that reason, not as a capsule 'fitted to the mesh's vertices'."""
    spec = mujoco.MjSpec.from_file(str(write_hand(tmp_path / "src")))
    palm = next(b for b in spec.bodies if b.name == "palm")
    palm.add_geom(name="palm_shell", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="shell")
    (tmp_path / "src" / "palm_mesh.xml").write_text(spec.to_xml())
    (tmp_path / "src" / "meshes" / "shell.obj").unlink()
    with pytest.raises(importer.HandImportError, match="shell.obj") as err:
        importer.import_hand(tmp_path / "src" / "palm_mesh.xml", torque_limit=TORQUE_LIMIT, drop_visual=True)
    assert "palm_shell" in str(err.value) and "the palm's geoms are kept" in str(err.value) and \
        "fitted to the mesh" not in str(err.value), err.value


def test_drop_visual_keeps_the_geoms_a_tendon_wraps(tmp_path):
    """Issue 83 (a newcomer's Aero hand): `--drop-visual` removed a visual cylinder a spatial tendon wraps around, and
    MuJoCo could not compile the hand ('geom ... not found in tendon'); it keeps such geoms (and says so), and a
    tendon spring is named as a force the controller does not compensate."""
    src = write_hand(tmp_path / "src")
    text = src.read_text()
    text = text.replace('<geom name="index_prox" type="box"',
                        '<geom name="wrap" type="cylinder" size="0.004 0.004" contype="0" conaffinity="0" '
                        'pos="0 0.02 0.012"/>\n        <site name="s2" pos="0 0.035 0.01"/>\n'
                        '        <geom name="index_prox" type="box"', 1)
    palm = '<geom name="palm" type="box" size="0.04 0.05 0.01"/>'
    text = text.replace(palm, palm + '\n      <site name="s1" pos="0.025 0.04 0.012"/>', 1)
    text = text.replace("</worldbody>", '</worldbody>\n  <tendon><spatial name="spring" stiffness="100">'
                        '<site site="s1"/><geom geom="wrap"/><site site="s2"/></spatial></tendon>', 1)
    assert text.count('name="wrap"') == 1 and text.count('name="s1"') == 1
    (tmp_path / "src" / "tendon.xml").write_text(text)
    result = importer.import_hand(tmp_path / "src" / "tendon.xml", torque_limit=TORQUE_LIMIT, drop_visual=True)
    m = _compiled(result.write(tmp_path / "out"))
    assert m.tendon("spring").id >= 0 and m.geom("wrap").id >= 0
    assert any("kept 1 that tendons wrap around" in c for c in result.changes), result.changes
    assert any("tendon 'spring', a spring of 100 N/m" in c for c in result.changes), result.changes
    gone = importer.import_hand(tmp_path / "src" / "tendon.xml", torque_limit=TORQUE_LIMIT, drop_visual=True,
                                drop_tendons=True)
    m = _compiled(gone.write(tmp_path / "no_tendons"))
    assert m.ntendon == 0 and mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "wrap") < 0  # then a visual geom
    assert m.nu == len([j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE])  # a motor a joint
    assert any(c.startswith("tendons removed: 2") for c in gone.changes), gone.changes
