"""The model files -> the constant arrays the surrogate's kernels need.

`models/scene.xml` (hand + wrench + table) is the one source of geometry. This module reads it once with the
MuJoCo compiler and exposes, as plain numpy arrays (compile-time constants for XLA):

* the hand's kinematic tree (bodies, hinge joints, limits, the IK start configuration),
* the contact links (site on each link, its radius) and their candidate contacts on the tool (sites
  ``opt_<link>_<k>``, whose z axis is the inward contact normal),
* the hand's collision capsules, turned into chains of spheres (for the surrogate's distance checks),
* the tool's collision boxes, and gravity.

A new hand or tool is a new model file that follows the conventions written at the top of `models/hand.xml`
and `models/wrench.xml`; nothing here names a finger.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import pathlib

import mujoco
import numpy as np

_PACKAGE = pathlib.Path(__file__).resolve().parent
# The model files: `models/` of the source tree, which an installed wheel carries as package data gsp_jax/models/.
MODELS_DIR = _PACKAGE / "models" if (_PACKAGE / "models" / "scene.xml").is_file() else _PACKAGE.parent / "models"
SCENE_XML = MODELS_DIR / "scene.xml"
TOOL_BODY = "wrench"
PALM_BODY = "palm"
SPHERE_SPACING = 1.5  # centre spacing of a capsule's spheres, in radii (gaps stay well under the collision margin)
SELF_COLLISION_MIN_DEPTH = 3  # self-collision: capsules of bodies this deep below the palm (medial, distal)


@dataclasses.dataclass(frozen=True, eq=False)
class HandModel:
    """Constant arrays describing hand, contact options and tool. B bodies, J joints, L links, S spheres.

    Frozen and hashable by identity, so it can be closed over (or passed as a static argument) under `jit`.
    """

    # kinematic tree of the hand, bodies in MuJoCo order (parents before children)
    body_names: tuple[str, ...]
    body_parent: np.ndarray  # (B,) int, index into these bodies; -1: attached to the world
    body_pos: np.ndarray  # (B, 3) position in the parent frame [m]
    body_mat: np.ndarray  # (B, 3, 3) orientation in the parent frame
    body_joint: np.ndarray  # (B,) int, index of the body's hinge joint; -1: none (fixed)
    joint_moves_body: np.ndarray  # (B, J) float, 1 where joint j is on body b or one of its ancestors
    joint_names: tuple[str, ...]
    joint_axis: np.ndarray  # (J, 3) hinge axis in the body frame
    joint_pos: np.ndarray  # (J, 3) hinge anchor in the body frame [m]
    joint_range: np.ndarray  # (J, 2) limits [rad]
    joint_torque_limit: np.ndarray  # (J,) the joint's motor's symmetric torque limit |ctrlrange| x gear [N m]
    q_start: np.ndarray  # (J,) fixed IK start configuration [rad]
    qpos_adr: np.ndarray  # (J,) the joints' addresses in the scene's qpos
    # contact links and their options
    link_names: tuple[str, ...]
    link_body: np.ndarray  # (L,) int, body of each contact link
    link_site: np.ndarray  # (L, 3) centre of the link's contact segment, body frame [m]
    link_axis: np.ndarray  # (L, 3) unit direction of the contact segment, body frame
    link_half: np.ndarray  # (L,) half-length of the contact segment (0: a fingertip sphere) [m]
    link_radius: np.ndarray  # (L,) link radius around the segment [m]
    n_options: tuple[int, ...]  # (L,) options per link, "not in contact" (option 0) included
    option_pos: np.ndarray  # (L, K, 3) candidate contact point on the tool, tool frame; row 0 unused [m]
    option_normal: np.ndarray  # (L, K, 3) inward unit normal at that point, tool frame; row 0 unused
    # collision spheres of the hand (each capsule -> a chain of spheres)
    sphere_body: np.ndarray  # (S,) int
    sphere_pos: np.ndarray  # (S, 3) centre in the body frame [m]
    sphere_radius: np.ndarray  # (S,) [m]
    sphere_finger: np.ndarray  # (S,) int, finger index (first body below the palm)
    sphere_link: np.ndarray  # (S,) int, contact link owning the sphere's body; -1: none
    capsule_body: np.ndarray  # (C,) int, body of each self-collision capsule (medial and distal links)
    capsule_ends: np.ndarray  # (C, 2, 3) the capsule's segment end points in the body frame [m]
    capsule_radius: np.ndarray  # (C,) [m]
    self_pairs: np.ndarray  # (P, 2) int, capsule pairs on different fingers checked for self-collision
    finger_names: tuple[str, ...]
    # tool collision boxes, in the tool frame
    tool_box_pos: np.ndarray  # (NB, 3) [m]
    tool_box_mat: np.ndarray  # (NB, 3, 3) box axes as columns
    tool_box_half: np.ndarray  # (NB, 3) half sizes [m]
    tool_mass: float  # nominal tool mass of the model file [kg]
    gravity: np.ndarray  # (3,) [m/s^2]

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_links(self) -> int:
        return len(self.link_names)

    def tool_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The tool's axis-aligned bounding box in the tool frame, (3,) lower and upper corners [m]."""
        signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T  # (8, 3) corners
        corners = self.tool_box_pos[:, None] + np.einsum("bij,bcj->bci", self.tool_box_mat, signs * self.tool_box_half[:, None])
        return corners.reshape(-1, 3).min(0), corners.reshape(-1, 3).max(0)


def _text(model: mujoco.MjModel, name: str) -> str:
    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, name)
    if i < 0:
        raise ValueError(f"model: custom text {name!r} is missing")
    data = model.text_data
    raw = data.tobytes() if hasattr(data, "tobytes") else bytes(data, "latin1") if isinstance(data, str) else bytes(data)
    return raw[model.text_adr[i] : model.text_adr[i] + model.text_size[i]].split(b"\0")[0].decode()


def _quat_to_mat(q: np.ndarray) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, dtype=np.float64))
    return m.reshape(3, 3)


def _capsule_spheres(half_len: float, radius: float) -> np.ndarray:
    """Offsets along the capsule's local z of a chain of spheres covering it (spacing <= SPHERE_SPACING radii)."""
    n = max(2, int(math.ceil(2 * half_len / (SPHERE_SPACING * radius))) + 1)
    return np.linspace(-half_len, half_len, n)


@dataclasses.dataclass(frozen=True)
class _Tree:
    """The hand's kinematic tree as MuJoCo ids: the bodies below the palm and their hinge joints."""

    model: mujoco.MjModel
    palm: int
    bodies: list[int]  # (B,) MuJoCo body ids, parents before children
    index: dict[int, int]  # MuJoCo body id -> index into `bodies`
    joints: list[int]  # (J,) MuJoCo joint ids
    body_joint: np.ndarray  # (B,) index of each body's joint, -1 none
    fingers: list[int]  # MuJoCo body ids of the bodies just below the palm

    def depth(self, b: int) -> int:
        return 0 if b == self.palm else 1 + self.depth(self.model.body_parentid[b])

    def finger_of(self, b: int) -> int:
        """Index into `fingers` of the finger body `b` belongs to."""
        while self.model.body_parentid[b] != self.palm and b != self.palm:
            b = self.model.body_parentid[b]
        return self.fingers.index(b)

    def joint_moves_body(self) -> np.ndarray:
        """(B, J) 1 where joint j is on body b or one of its ancestors."""
        moves = np.zeros((len(self.bodies), len(self.joints)))
        for bi, b in enumerate(self.bodies):
            while b in self.index:
                if self.body_joint[self.index[b]] >= 0:
                    moves[bi, self.body_joint[self.index[b]]] = 1.0
                b = self.model.body_parentid[b]
        return moves


def _tree(model: mujoco.MjModel, palm: int) -> _Tree:
    """The bodies below the palm, each with at most one hinge joint."""

    def root_below_world(b: int) -> int:
        while model.body_parentid[b] != 0:
            b = model.body_parentid[b]
        return b

    bodies = [b for b in range(1, model.nbody) if root_below_world(b) == palm]
    index = {b: i for i, b in enumerate(bodies)}
    joints = [j for j in range(model.njnt) if model.jnt_bodyid[j] in index]
    for j in joints:
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
            raise ValueError(f"model: hand joint {model.joint(j).name!r} is not a hinge")
    body_joint = np.full(len(bodies), -1)
    for ji, j in enumerate(joints):
        bi = index[model.jnt_bodyid[j]]
        if body_joint[bi] >= 0:
            raise ValueError(f"model: body {model.body(model.jnt_bodyid[j]).name!r} has more than one joint")
        body_joint[bi] = ji
    tree = _Tree(model, palm, bodies, index, joints, body_joint, [])
    fingers = set()
    for b in bodies:
        if b != palm:
            while model.body_parentid[b] != palm:
                b = model.body_parentid[b]
            fingers.add(b)
    return dataclasses.replace(tree, fingers=sorted(fingers))


def _links(model: mujoco.MjModel, tree: _Tree, tool: int) -> dict:
    """The contact links (sites ``contact_<link>``) and their candidate contacts on the tool (``opt_<link>_<k>``)."""
    names = tuple(_text(model, "gsp_contact_links").split())
    body, site, axis, half, radius, n_options, opts = [], [], [], [], [], [], []
    for name in names:
        s = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"contact_{name}")
        if s < 0:
            raise ValueError(f"model: site 'contact_{name}' is missing")
        body.append(tree.index[model.site_bodyid[s]])
        site.append(model.site_pos[s].copy())
        axis.append(_quat_to_mat(model.site_quat[s])[:, 2])
        capsule = model.site_type[s] == mujoco.mjtGeom.mjGEOM_CAPSULE
        half.append(float(model.site_size[s][1]) if capsule else 0.0)
        radius.append(float(model.site_size[s][0]))
        k, link_opts = 1, []
        while (o := mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"opt_{name}_{k}")) >= 0:
            if model.site_bodyid[o] != tool:
                raise ValueError(f"model: site 'opt_{name}_{k}' is not on the tool body {TOOL_BODY!r}")
            link_opts.append((model.site_pos[o].copy(), _quat_to_mat(model.site_quat[o])[:, 2]))
            k += 1
        if not link_opts:
            raise ValueError(f"model: link {name!r} has no candidate contact 'opt_{name}_1'")
        n_options.append(k)
        opts.append(link_opts)
    option_pos = np.zeros((len(names), max(n_options), 3))
    option_normal = np.zeros((len(names), max(n_options), 3))
    for li, link_opts in enumerate(opts):
        for k, (p, n) in enumerate(link_opts, start=1):
            option_pos[li, k], option_normal[li, k] = p, n / np.linalg.norm(n)
    return dict(link_names=names, link_body=np.array(body), link_site=np.array(site), link_axis=np.array(axis),
                link_half=np.array(half), link_radius=np.array(radius), n_options=tuple(n_options),
                option_pos=option_pos, option_normal=option_normal)


def _collision(model: mujoco.MjModel, tree: _Tree, link_body: np.ndarray) -> dict:
    """The hand's collision geoms as chains of spheres, and the capsules checked for self-collision."""
    body_link = {b: li for li, b in enumerate(link_body)}
    sph_body, sph_pos, sph_rad, sph_finger, sph_link = [], [], [], [], []
    cap_body, cap_ends, cap_rad, cap_finger = [], [], [], []
    for g in range(model.ngeom):
        b = model.geom_bodyid[g]
        if b not in tree.index or b == tree.palm:
            continue
        gtype = model.geom_type[g]
        mat = _quat_to_mat(model.geom_quat[g])
        if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            r, h = model.geom_size[g][:2]
            offsets = _capsule_spheres(h, r)
            if tree.depth(b) >= SELF_COLLISION_MIN_DEPTH:
                cap_body.append(tree.index[b])
                cap_ends.append([model.geom_pos[g] - mat[:, 2] * h, model.geom_pos[g] + mat[:, 2] * h])
                cap_rad.append(r)
                cap_finger.append(tree.finger_of(b))
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            r, offsets = model.geom_size[g][0], np.zeros(1)
        else:
            raise ValueError(f"model: hand geom {model.geom(g).name!r} must be a capsule or sphere")
        for z in offsets:
            sph_body.append(tree.index[b])
            sph_pos.append(model.geom_pos[g] + mat[:, 2] * z)
            sph_rad.append(r)
            sph_finger.append(tree.finger_of(b))
            sph_link.append(body_link.get(tree.index[b], -1))
    pairs = np.array(
        [(i, j) for i in range(len(cap_body)) for j in range(i + 1, len(cap_body)) if cap_finger[i] != cap_finger[j]]
    )
    return dict(sphere_body=np.array(sph_body), sphere_pos=np.array(sph_pos), sphere_radius=np.array(sph_rad),
                sphere_finger=np.array(sph_finger), sphere_link=np.array(sph_link), capsule_body=np.array(cap_body),
                capsule_ends=np.array(cap_ends), capsule_radius=np.array(cap_rad), self_pairs=pairs)


def _tool(model: mujoco.MjModel, tool: int) -> dict:
    """The tool's collision boxes (its frame) and nominal mass."""
    boxes = [g for g in range(model.ngeom) if model.geom_bodyid[g] == tool]
    for g in boxes:
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_BOX:
            raise ValueError(f"model: tool geom {model.geom(g).name!r} must be a box")
    return dict(tool_box_pos=np.array([model.geom_pos[g] for g in boxes]),
                tool_box_mat=np.array([_quat_to_mat(model.geom_quat[g]) for g in boxes]),
                tool_box_half=np.array([model.geom_size[g] for g in boxes]), tool_mass=float(model.body_mass[tool]))


def _torque_limits(model: mujoco.MjModel, joints) -> np.ndarray:
    """(J,) each hand joint's motor limit [N m]: min(-lo, hi) of the ctrlrange of the one motor that drives it,
    times its gear."""
    limit = {}
    for a in range(model.nu):
        if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            lo, hi = model.actuator_ctrlrange[a] if model.actuator_ctrllimited[a] else (-np.inf, np.inf)
            limit[int(model.actuator_trnid[a, 0])] = min(-lo, hi) * abs(model.actuator_gear[a, 0])
    missing = [model.joint(j).name for j in joints if not limit.get(int(j), 0) > 0]
    if missing:
        raise ValueError(f"model: hand joints {missing} need a motor with a control range around 0")
    return np.array([limit[int(j)] for j in joints])


def from_mjmodel(model: mujoco.MjModel) -> HandModel:
    """Extract a `HandModel` from a compiled scene (hand + tool body named ``wrench``)."""
    palm = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, PALM_BODY)
    tool = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, TOOL_BODY)
    if palm < 0 or tool < 0:
        raise ValueError(f"model: needs bodies {PALM_BODY!r} and {TOOL_BODY!r}")
    tree = _tree(model, palm)
    links = _links(model, tree, tool)
    bodies, joints = tree.bodies, tree.joints
    return HandModel(
        joint_moves_body=tree.joint_moves_body(),
        body_names=tuple(model.body(b).name for b in bodies),
        body_parent=np.array([tree.index.get(model.body_parentid[b], -1) for b in bodies]),
        body_pos=np.array([model.body_pos[b] for b in bodies]),
        body_mat=np.array([_quat_to_mat(model.body_quat[b]) for b in bodies]),
        body_joint=tree.body_joint,
        joint_names=tuple(model.joint(j).name for j in joints),
        joint_axis=np.array([model.jnt_axis[j] for j in joints]),
        joint_pos=np.array([model.jnt_pos[j] for j in joints]),
        joint_range=np.array([model.jnt_range[j] for j in joints]),
        joint_torque_limit=_torque_limits(model, joints),
        q_start=np.asarray(model.numeric("gsp_ik_start").data, dtype=np.float64),
        qpos_adr=np.array([model.jnt_qposadr[j] for j in joints]),
        finger_names=tuple(model.body(f).name.split("_")[0] for f in tree.fingers),
        gravity=np.array(model.opt.gravity),
        **links, **_collision(model, tree, links["link_body"]), **_tool(model, tool),
    )


@functools.lru_cache(maxsize=8)
def load_mjmodel(path: str | pathlib.Path = SCENE_XML) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(path))


@functools.lru_cache(maxsize=8)
def load(path: str | pathlib.Path = SCENE_XML) -> HandModel:
    """The `HandModel` of a scene file (cached: one object per path)."""
    hand = from_mjmodel(load_mjmodel(path))
    if len(hand.q_start) != hand.n_joints:
        raise ValueError(f"model: gsp_ik_start has {len(hand.q_start)} values for {hand.n_joints} joints")
    return hand
