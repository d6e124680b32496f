"""A scene file -> the constant arrays the surrogate's kernels need.

A scene (hand + tool + table, e.g. `models/scene.xml`) is the one source of geometry. This module reads it once
with the MuJoCo compiler and exposes, as plain numpy arrays (compile-time constants for XLA):

* the hand's kinematic tree (bodies, hinge joints, limits, the IK start configuration),
* the contact links (site on each link, its radius) and their candidate contacts on the tool (sites
  ``opt_<link>_<k>``, whose z axis is the inward contact normal),
* the hand's collision capsules, turned into chains of spheres (for the surrogate's distance checks),
* the tool (the scene's one free body, any name): its collision primitives, mass, inertia, centre of mass, rest
  pose, start supports and start grasp; the waypoints' reach box, and gravity.

A new hand or tool is a new model file that follows the conventions of `docs/your-model.md` (written also at the
top of `models/hand.xml` and `models/wrench.xml`); `gsp_jax.check_model` lists every convention a file breaks,
and `load` runs it first. Nothing here names a finger, a body or a geom.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import pathlib

import mujoco
import numpy as np

_PACKAGE = pathlib.Path(__file__).resolve().parents[1]  # gsp_jax/
# The model files: `models/` of the source tree, which an installed wheel carries as package data gsp_jax/models/.
MODELS_DIR = _PACKAGE / "models" if (_PACKAGE / "models" / "scene.xml").is_file() else _PACKAGE.parent / "models"
SCENE_XML = MODELS_DIR / "scene.xml"
_G = mujoco.mjtGeom
ROUND_GEOMS = {int(_G.mjGEOM_SPHERE): "sphere", int(_G.mjGEOM_CAPSULE): "capsule", int(_G.mjGEOM_CYLINDER): "cylinder",
               int(_G.mjGEOM_ELLIPSOID): "ellipsoid"}
TOOL_GEOMS = {int(_G.mjGEOM_BOX): "box", **ROUND_GEOMS}  # the primitives a tool may be made of
WORKSPACE = ((-0.05, -0.05, 0.005), (0.05, 0.05, 0.10))  # default reach box of the waypoints, table frame [m]
TASK_TORQUE = 1.0  # default final external torque of a model's episodes [N m] (the paper's; gsp_torque sets it)
SUPPORT_HALF = (0.012, 0.008, 0.004)  # half sizes of a start support derived from the tool's shape [m]
SPHERE_SPACING = 1.5  # centre spacing of a capsule's spheres, in radii (gaps stay well under the collision margin)
SELF_COLLISION_MIN_DEPTH = 3  # self-collision: capsules of bodies this deep below the palm (medial, distal)
# The hand joints' own dynamics the physics controller is tuned for (models/hand.xml; `check_model` measures a file's
# against the controller's stable range, `import-hand` writes these):
JOINT_DAMPING = 0.1  # [N m s/rad]
JOINT_ARMATURE = 0.002  # [kg m^2]
JOINT_FRICTIONLOSS = 0.001  # [N m]


def collides(mj_model: mujoco.MjModel, g: int) -> bool:
    """Whether geom `g` collides with anything (contype or conaffinity set); the others are visual only."""
    return bool(mj_model.geom_contype[g] or mj_model.geom_conaffinity[g])


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
    finger_names: tuple[str, ...]  # (F,) each finger's label: its first body's name up to "_" (labels only)
    joint_finger: np.ndarray  # (J,) int, finger of each joint
    link_finger: np.ndarray  # (L,) int, finger of each contact link
    link_is_tip: np.ndarray  # (L,) bool, the deepest contact link of its finger (where it parks)
    start_options: tuple[int, ...]  # (L,) the default start grasp (custom numeric gsp_start_options; default: tips)
    tip_options: tuple[int, ...]  # (L,) every tip link on its first option, the rest off: the constant all-tips grasp
    touch_tool: tuple[str, ...]  # hand bodies whose geoms touch the tool in physics (custom text gsp_touch_tool)
    touch_table: tuple[str, ...]  # hand bodies whose geoms touch the table in physics (gsp_touch_table)
    workspace: np.ndarray  # (2, 3) the waypoints' reach box, table frame, lower and upper corner [m]
    torque: float  # the magnitude of the final external torque of the model's episodes [N m] (gsp_torque)
    # the tool: its collision boxes and round primitives, in the tool frame
    tool_name: str  # the tool body's name
    tool_box_pos: np.ndarray  # (NB, 3) [m]
    tool_box_mat: np.ndarray  # (NB, 3, 3) box axes as columns
    tool_box_half: np.ndarray  # (NB, 3) half sizes [m]
    tool_round_type: tuple[str, ...]  # (NR,) "sphere", "capsule", "cylinder" or "ellipsoid"
    tool_round_pos: np.ndarray  # (NR, 3) [m]
    tool_round_mat: np.ndarray  # (NR, 3, 3) axes as columns (capsule and cylinder along z)
    tool_round_size: np.ndarray  # (NR, 3) MuJoCo's geom size: radius (and half-length), or the 3 semi-axes [m]
    tool_mass: float  # nominal tool mass of the model file [kg]
    tool_inertia: np.ndarray  # (3,) nominal principal moments of inertia about the CoM [kg m^2]
    tool_com: np.ndarray  # (3,) nominal centre of mass, tool frame [m]
    tool_rest: np.ndarray  # (3,) the tool frame's position in the file (at rest on the table) [m]
    support_top: np.ndarray  # (P, 3) top centre of each start support, tool frame [m]
    support_half: np.ndarray  # (P, 3) half sizes of each support (a box) [m]
    gravity: np.ndarray  # (3,) [m/s^2]
    source: str = ""  # the scene file it was loaded from (`load`); "" if built from a compiled model alone

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_links(self) -> int:
        return len(self.link_names)

    def tool_hull(self) -> np.ndarray:
        """(8 (NB + NR), 3) the corners of each tool geom's box (boxes exact, round primitives their enclosing
        box), tool frame [m]: the lowest of them bounds the tool's lowest point from below."""
        return geom_corners(self.tool_box_pos, self.tool_box_mat, self.tool_box_half, self.tool_round_type,
                            self.tool_round_pos, self.tool_round_mat, self.tool_round_size).reshape(-1, 3)

    def tool_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The tool's axis-aligned bounding box in the tool frame, (3,) lower and upper corners [m]."""
        corners = self.tool_hull()
        return corners.min(0), corners.max(0)


def geom_corners(box_pos, box_mat, box_half, round_type, round_pos, round_mat, round_size) -> np.ndarray:
    """(G, 8, 3) the corners of each tool geom's box, boxes first, then round primitives' enclosing boxes [m]."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    pos = np.concatenate([box_pos, round_pos]).reshape(-1, 3)
    mat = np.concatenate([box_mat, round_mat]).reshape(-1, 3, 3)
    half = np.concatenate([box_half, enclosing_half(round_type, round_size)]).reshape(-1, 1, 3)
    return pos[:, None] + np.einsum("bij,bcj->bci", mat, signs * half)


def enclosing_half(kinds, size: np.ndarray) -> np.ndarray:
    """(N, 3) half sizes, in the geom's frame, of the boxes enclosing round primitives of MuJoCo `size` (N, 3)."""
    out = []
    for kind, (a, b, c) in zip(kinds, np.asarray(size).reshape(-1, 3)):
        out.append({"sphere": (a, a, a), "capsule": (a, a, b + a), "cylinder": (a, a, b), "ellipsoid": (a, b, c)}[kind])
    return np.asarray(out, np.float64).reshape(-1, 3)


def _text(mj_model: mujoco.MjModel, name: str, default: str | None = None) -> str:
    i = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_TEXT, name)
    if i < 0:
        if default is not None:
            return default
        raise ValueError(f"model: custom text {name!r} is missing")
    data = mj_model.text_data
    raw = (data.tobytes() if hasattr(data, "tobytes")
           else bytes(data, "latin1") if isinstance(data, str) else bytes(data))
    return raw[mj_model.text_adr[i] : mj_model.text_adr[i] + mj_model.text_size[i]].split(b"\0")[0].decode()


def _numeric(mj_model: mujoco.MjModel, name: str) -> np.ndarray | None:
    """A custom numeric's values, or None if the file has none of that name."""
    if mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_NUMERIC, name) < 0:
        return None
    return np.asarray(mj_model.numeric(name).data, dtype=np.float64)


def _site(mj_model: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, name)


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


def table_geom(mj_model: mujoco.MjModel) -> int:
    """The table: the world's one plane geom."""
    planes = [g for g in range(mj_model.ngeom)
              if mj_model.geom_bodyid[g] == 0 and int(mj_model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE)]
    if len(planes) != 1:
        raise ValueError(f"model: the scene needs one plane geom in the worldbody (the table); found {len(planes)}")
    return planes[0]


def tool_body(mj_model: mujoco.MjModel) -> int:
    """The tool: the scene's one body with a free joint (any name)."""
    free = sorted({int(mj_model.jnt_bodyid[j]) for j in range(mj_model.njnt)
                   if mj_model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE})
    if len(free) != 1:
        names = [mj_model.body(b).name for b in free]
        raise ValueError(f"model: the tool must be the scene's one free body (a body with <freejoint/>); found "
                         f"{len(free)}{': ' + ', '.join(map(repr, names)) if names else ''}")
    return free[0]


def contact_links(mj_model: mujoco.MjModel) -> tuple[str, ...]:
    """The contact links in the grasp encoding's order (custom text ``gsp_contact_links``)."""
    names = tuple(_text(mj_model, "gsp_contact_links").split())
    if not names:
        raise ValueError("model: custom text 'gsp_contact_links' names no link")
    return names


def hand_root(mj_model: mujoco.MjModel) -> int:
    """The hand's root (its palm): the world's child body that holds the contact links' sites."""
    sites = [s for n in contact_links(mj_model) if (s := _site(mj_model, f"contact_{n}")) >= 0]
    if not sites:
        raise ValueError("model: no contact link has its site 'contact_<link>'")
    return int(mj_model.body_rootid[mj_model.site_bodyid[sites[0]]])


def hinged_root(mj_model: mujoco.MjModel, exclude=()) -> int | None:
    """The world's child (not one of `exclude`) with the most hinge joints below it, the first such in MuJoCo's
    order; None if no body has a hinge. A hand's palm before its contact links are named."""
    hinges = np.bincount([mj_model.body_rootid[mj_model.jnt_bodyid[j]] for j in range(mj_model.njnt)
                          if mj_model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE], minlength=mj_model.nbody)
    hinges[[0, *exclude]] = 0
    return int(np.argmax(hinges)) if hinges.max() > 0 else None


def _tree(mj_model: mujoco.MjModel, palm: int) -> _Tree:
    """The bodies below the palm, each with at most one hinge joint."""
    bodies = [b for b in range(1, mj_model.nbody) if mj_model.body_rootid[b] == palm]
    index = {b: i for i, b in enumerate(bodies)}
    joints = [j for j in range(mj_model.njnt) if mj_model.jnt_bodyid[j] in index]
    for j in joints:
        if mj_model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
            raise ValueError(f"model: hand joint {mj_model.joint(j).name!r} is not a hinge")
    body_joint = np.full(len(bodies), -1)
    for ji, j in enumerate(joints):
        bi = index[mj_model.jnt_bodyid[j]]
        if body_joint[bi] >= 0:
            raise ValueError(f"model: body {mj_model.body(mj_model.jnt_bodyid[j]).name!r} has more than one joint")
        body_joint[bi] = ji
    tree = _Tree(mj_model, palm, bodies, index, joints, body_joint, [])
    fingers = set()
    for b in bodies:
        if b != palm:
            while mj_model.body_parentid[b] != palm:
                b = mj_model.body_parentid[b]
            fingers.add(b)
    return dataclasses.replace(tree, fingers=sorted(fingers))


def _links(mj_model: mujoco.MjModel, tree: _Tree, tool: int) -> dict:
    """The contact links (sites ``contact_<link>``) and their candidate contacts on the tool (``opt_<link>_<k>``)."""
    names = contact_links(mj_model)
    body, site, axis, half, radius, n_options, opts = [], [], [], [], [], [], []
    for name in names:
        s = _site(mj_model, f"contact_{name}")
        if s < 0:
            raise ValueError(f"model: site 'contact_{name}' is missing")
        body.append(tree.index[mj_model.site_bodyid[s]])
        site.append(mj_model.site_pos[s].copy())
        axis.append(_quat_to_mat(mj_model.site_quat[s])[:, 2])
        capsule = mj_model.site_type[s] == mujoco.mjtGeom.mjGEOM_CAPSULE
        half.append(float(mj_model.site_size[s][1]) if capsule else 0.0)
        radius.append(float(mj_model.site_size[s][0]))
        k, link_opts = 1, []
        while (o := _site(mj_model, f"opt_{name}_{k}")) >= 0:
            if mj_model.site_bodyid[o] != tool:
                raise ValueError(f"model: site 'opt_{name}_{k}' is not on the tool body {mj_model.body(tool).name!r}")
            link_opts.append((mj_model.site_pos[o].copy(), _quat_to_mat(mj_model.site_quat[o])[:, 2]))
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
    link_finger = np.array([tree.finger_of(tree.bodies[b]) for b in body], np.int32)
    depth = np.array([tree.depth(tree.bodies[b]) for b in body])
    is_tip = np.array([depth[li] == depth[link_finger == link_finger[li]].max() for li in range(len(names))])
    return dict(link_names=names, link_body=np.array(body), link_site=np.array(site), link_axis=np.array(axis),
                link_half=np.array(half), link_radius=np.array(radius), n_options=tuple(n_options),
                option_pos=option_pos, option_normal=option_normal, link_finger=link_finger, link_is_tip=is_tip)


def _collision(mj_model: mujoco.MjModel, tree: _Tree, link_body: np.ndarray) -> dict:
    """The hand's collision geoms as chains of spheres, and the capsules checked for self-collision."""
    body_link = {b: li for li, b in enumerate(link_body)}
    sph_body, sph_pos, sph_rad, sph_finger, sph_link = [], [], [], [], []
    cap_body, cap_ends, cap_rad, cap_finger = [], [], [], []
    for g in range(mj_model.ngeom):
        b = mj_model.geom_bodyid[g]
        if b not in tree.index or b == tree.palm or not collides(mj_model, g):
            continue
        gtype = mj_model.geom_type[g]
        mat = _quat_to_mat(mj_model.geom_quat[g])
        if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            r, h = mj_model.geom_size[g][:2]
            offsets = _capsule_spheres(h, r)
            if tree.depth(b) >= SELF_COLLISION_MIN_DEPTH:
                cap_body.append(tree.index[b])
                cap_ends.append([mj_model.geom_pos[g] - mat[:, 2] * h, mj_model.geom_pos[g] + mat[:, 2] * h])
                cap_rad.append(r)
                cap_finger.append(tree.finger_of(b))
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            r, offsets = mj_model.geom_size[g][0], np.zeros(1)
        else:
            raise ValueError(f"model: hand geom {_geom_label(mj_model, g)} must be a capsule or sphere")
        for z in offsets:
            sph_body.append(tree.index[b])
            sph_pos.append(mj_model.geom_pos[g] + mat[:, 2] * z)
            sph_rad.append(r)
            sph_finger.append(tree.finger_of(b))
            sph_link.append(body_link.get(tree.index[b], -1))
    pairs = np.array(
        [(i, j) for i in range(len(cap_body)) for j in range(i + 1, len(cap_body)) if cap_finger[i] != cap_finger[j]]
    ).reshape(-1, 2)
    return dict(sphere_body=np.array(sph_body), sphere_pos=np.array(sph_pos), sphere_radius=np.array(sph_rad),
                sphere_finger=np.array(sph_finger), sphere_link=np.array(sph_link),
                capsule_body=np.array(cap_body, np.int64), capsule_ends=np.array(cap_ends).reshape(-1, 2, 3),
                capsule_radius=np.array(cap_rad), self_pairs=pairs)


def _geom_label(mj_model: mujoco.MjModel, g: int) -> str:
    name = mj_model.geom(g).name
    return repr(name) if name else f"#{g} (unnamed, on body {mj_model.body(mj_model.geom_bodyid[g]).name!r})"


def tool_geoms(mj_model: mujoco.MjModel, tool: int) -> list[int]:
    """The tool's collision geoms: those of its body that collide with something (contype or conaffinity)."""
    return [g for g in range(mj_model.ngeom) if mj_model.geom_bodyid[g] == tool and collides(mj_model, g)]


def _tool(mj_model: mujoco.MjModel, tool: int) -> dict:
    """The tool's collision primitives (its frame), nominal inertial properties, rest pose and start supports."""
    geoms = tool_geoms(mj_model, tool)
    for g in geoms:
        if int(mj_model.geom_type[g]) not in TOOL_GEOMS:
            raise ValueError(f"model: tool geom {_geom_label(mj_model, g)} must be one of "
                             f"{sorted(TOOL_GEOMS.values())}")
    boxes = [g for g in geoms if mj_model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]
    rounds = [g for g in geoms if int(mj_model.geom_type[g]) in ROUND_GEOMS]
    out = dict(tool_name=mj_model.body(tool).name,
               tool_box_pos=np.array([mj_model.geom_pos[g] for g in boxes]).reshape(-1, 3),
               tool_box_mat=np.array([_quat_to_mat(mj_model.geom_quat[g]) for g in boxes]).reshape(-1, 3, 3),
               tool_box_half=np.array([mj_model.geom_size[g] for g in boxes]).reshape(-1, 3),
               tool_round_type=tuple(ROUND_GEOMS[int(mj_model.geom_type[g])] for g in rounds),
               tool_round_pos=np.array([mj_model.geom_pos[g] for g in rounds]).reshape(-1, 3),
               tool_round_mat=np.array([_quat_to_mat(mj_model.geom_quat[g]) for g in rounds]).reshape(-1, 3, 3),
               tool_round_size=np.array([mj_model.geom_size[g] for g in rounds]).reshape(-1, 3),
               tool_mass=float(mj_model.body_mass[tool]), tool_inertia=np.array(mj_model.body_inertia[tool]),
               tool_com=np.array(mj_model.body_ipos[tool]), tool_rest=np.array(mj_model.body_pos[tool]))
    return {**out, **_supports(mj_model, tool, out)}


def _supports(mj_model: mujoco.MjModel, tool: int, shape: dict) -> dict:
    """The start supports: the tool's box sites ``support_<k>`` (top centre, half sizes) if it has any; else two,
    under the tool's lowest point near either end of its longest horizontal extent (from its geoms' boxes)."""
    k, top, half = 1, [], []
    while (s := _site(mj_model, f"support_{k}")) >= 0:
        if mj_model.site_bodyid[s] != tool or mj_model.site_type[s] != mujoco.mjtGeom.mjGEOM_BOX:
            raise ValueError(f"model: site 'support_{k}' must be a box site on the tool body")
        top.append(mj_model.site_pos[s].copy())
        half.append(mj_model.site_size[s].copy())
        k += 1
    if top:
        return dict(support_top=np.array(top), support_half=np.array(half))
    corners = geom_corners(*(shape[f"tool_{k}"] for k in ("box_pos", "box_mat", "box_half", "round_type", "round_pos",
                                                           "round_mat", "round_size")))  # (G, 8, 3)
    lo, hi = corners.min(1), corners.max(1)  # (G, 3) each geom's box
    axis = 0 if np.ptp(corners[..., 0]) >= np.ptp(corners[..., 1]) else 1
    a0, a1 = lo[:, axis].min(), hi[:, axis].max()
    top = []
    for x in (a0 + 0.2 * (a1 - a0), a1 - 0.2 * (a1 - a0)):
        over = (lo[:, axis] <= x) & (hi[:, axis] >= x)
        p = np.zeros(3)
        p[axis], p[1 - axis] = x, 0.5 * (lo[over, 1 - axis].min() + hi[over, 1 - axis].max())
        p[2] = lo[over, 2].min()
        top.append(p)
    half = np.tile(np.array(SUPPORT_HALF)[[axis, 1 - axis, 2]], (2, 1))  # the long side along the tool
    return dict(support_top=np.array(top), support_half=half)


def _torque_limits(mj_model: mujoco.MjModel, joints) -> np.ndarray:
    """(J,) each hand joint's motor limit [N m]: min(-lo, hi) of the ctrlrange of the one motor that drives it,
    times its gear."""
    limit = {}
    for a in range(mj_model.nu):
        if mj_model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            lo, hi = mj_model.actuator_ctrlrange[a] if mj_model.actuator_ctrllimited[a] else (-np.inf, np.inf)
            limit[int(mj_model.actuator_trnid[a, 0])] = min(-lo, hi) * abs(mj_model.actuator_gear[a, 0])
    missing = [mj_model.joint(j).name for j in joints if not limit.get(int(j), 0) > 0]
    if missing:
        raise ValueError(f"model: hand joints {missing} need a motor with a control range around 0")
    return np.array([limit[int(j)] for j in joints])


def _bodies_text(mj_model: mujoco.MjModel, name: str, default: list[int], tree: _Tree) -> tuple[str, ...]:
    """Hand body names from custom text `name`, or the `default` bodies."""
    names = _text(mj_model, name, "").split()
    for n in names:
        b = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, n)
        if b not in tree.index:
            raise ValueError(f"model: custom text {name!r} names {n!r}, which is not a body of the hand")
    return tuple(names) if names else tuple(mj_model.body(b).name for b in default)


def _conventions(mj_model: mujoco.MjModel, tree: _Tree, links: dict) -> dict:
    """Start grasp, the all-tips grasp, the bodies that touch the tool and the table, the reach box."""
    n_links = len(links["link_names"])
    tips = tuple(int(t) for t in links["link_is_tip"])
    start = _numeric(mj_model, "gsp_start_options")
    if start is None:
        start = np.array(tips)
    if (len(start) != n_links or np.any(start != np.round(start)) or np.any(start < 0)
            or np.any(start >= links["n_options"])):
        raise ValueError(f"model: gsp_start_options {start.tolist()} must give each of the {n_links} links an option "
                         f"in [0, n_options) = {list(links['n_options'])}")
    below = {b for b in tree.bodies for lb in links["link_body"] if _is_below(mj_model, b, tree.bodies[lb])}
    leaves = [b for b in tree.bodies if b != tree.palm and not any(mj_model.body_parentid[c] == b for c in tree.bodies)]
    box = _numeric(mj_model, "gsp_workspace")
    box = np.array(WORKSPACE).ravel() if box is None else box
    if box.size != 6 or np.any(box[:3] >= box[3:]):
        raise ValueError(f"model: gsp_workspace {box.tolist()} must be 6 values, lower corner below upper corner")
    torque = _numeric(mj_model, "gsp_torque")
    torque = np.array([TASK_TORQUE]) if torque is None else torque
    if torque.size != 1 or not 0 < torque[0] < np.inf:
        raise ValueError(f"model: gsp_torque {torque.tolist()} must be one positive value [N m]")
    return dict(start_options=tuple(int(o) for o in start), tip_options=tips, torque=float(torque[0]),
                touch_tool=_bodies_text(mj_model, "gsp_touch_tool", sorted(below), tree),
                touch_table=_bodies_text(mj_model, "gsp_touch_table", leaves, tree), workspace=box.reshape(2, 3))


def _is_below(mj_model: mujoco.MjModel, b: int, ancestor: int) -> bool:
    while b > 0:
        if b == ancestor:
            return True
        b = mj_model.body_parentid[b]
    return False


def from_mjmodel(mj_model: mujoco.MjModel) -> HandModel:
    """Extract a `HandModel` from a compiled scene (hand + one free body, the tool); raise ValueError naming the
    first convention it breaks (`gsp_jax.check_model` lists them all)."""
    tool = tool_body(mj_model)
    palm = hand_root(mj_model)
    tree = _tree(mj_model, palm)
    links = _links(mj_model, tree, tool)
    bodies, joints = tree.bodies, tree.joints
    q_start = _numeric(mj_model, "gsp_ik_start")
    if q_start is None:
        raise ValueError("model: custom numeric 'gsp_ik_start' is missing")
    return HandModel(
        joint_moves_body=tree.joint_moves_body(),
        body_names=tuple(mj_model.body(b).name for b in bodies),
        body_parent=np.array([tree.index.get(mj_model.body_parentid[b], -1) for b in bodies]),
        body_pos=np.array([mj_model.body_pos[b] for b in bodies]),
        body_mat=np.array([_quat_to_mat(mj_model.body_quat[b]) for b in bodies]),
        body_joint=tree.body_joint,
        joint_names=tuple(mj_model.joint(j).name for j in joints),
        joint_axis=np.array([mj_model.jnt_axis[j] for j in joints]),
        joint_pos=np.array([mj_model.jnt_pos[j] for j in joints]),
        joint_range=np.array([mj_model.jnt_range[j] for j in joints]),
        joint_torque_limit=_torque_limits(mj_model, joints),
        q_start=q_start,
        qpos_adr=np.array([mj_model.jnt_qposadr[j] for j in joints]),
        finger_names=tuple(mj_model.body(f).name.split("_")[0] for f in tree.fingers),
        joint_finger=np.array([tree.finger_of(int(mj_model.jnt_bodyid[j])) for j in joints], np.int32),
        gravity=np.array(mj_model.opt.gravity),
        **links, **_collision(mj_model, tree, links["link_body"]), **_tool(mj_model, tool),
        **_conventions(mj_model, tree, links),
    )


@functools.lru_cache(maxsize=8)
def load_mjmodel(path: str | pathlib.Path = SCENE_XML) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(path))
