"""A model: one hand, one tool and their grasp space, loaded once from an MJCF scene and carried everywhere.

`load_model(name_or_path)` is the one door: a shipped model by name (`SHIPPED`: ``wrench``, the default, ``hammer``,
``allegro``, ``screwdriver``, ``five`` and ``five-tips`` (a grasp space beyond the DP table, and its fingertips);
``testhand``, a small model for the tests) or any scene file that follows the conventions
of `docs/your-model.md`. The surrogate, the physics scene (both backends), episodes, policies, DP tables and their
cache, the environments and every ``python -m experiments`` command (``--model NAME_OR_PATH``) are built from it, and
nothing falls back to the shipped files: what was made for one model (an episode, a table, a policy) is refused by
another with an error naming both.

`check_model(path)` lists, in plain words, every convention a scene file breaks (an empty list: none); every
loading path runs it first (`require`), so a broken file is refused before MuJoCo or XLA sees it.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import pathlib

import mujoco
import numpy as np

from gsp_jax.model import grasps, hand as hand_lib

SHIPPED = {"wrench": hand_lib.MODELS_DIR / "scene.xml",  # the paper's tool and our four-fingered hand
           "hammer": hand_lib.MODELS_DIR / "hammer" / "scene.xml",  # round handle, heavy head: CoM far off the grip
           "allegro": hand_lib.MODELS_DIR / "allegro" / "scene.xml",  # the Allegro hand's kinematics, the wrench
           "screwdriver": hand_lib.MODELS_DIR / "screwdriver" / "scene.xml",  # a round grip 2 cm across
           "five": hand_lib.MODELS_DIR / "five" / "scene.xml",  # five fingers, ten contact links: 18,432 grasps
           "five-tips": hand_lib.MODELS_DIR / "five" / "tips.xml",  # the same hand, its five fingertips: 576 grasps
           "testhand": hand_lib.MODELS_DIR / "testhand" / "scene.xml"}  # a test model: 3 two-hinge fingers, a bar
DEFAULT = "wrench"


class ModelError(ValueError):
    """A scene file breaks the model conventions, or something made for one model met another."""


@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """A hand + tool scene: where it came from, its content hash, its constant arrays and its grasp space."""

    name: str  # a shipped name, or the scene file's stem
    path: pathlib.Path  # the scene file
    digest: str  # hash of the compiled scene's content (includes resolved), 16 hex digits
    hand: hand_lib.HandModel

    @property
    def space(self) -> grasps.GraspSpace:
        return grasps.space_of(self.hand)

    @property
    def mjmodel(self) -> mujoco.MjModel:
        return hand_lib.load_mjmodel(self.path)

    @property
    def label(self) -> str:
        """How messages name it: 'hammer (models/hammer/scene.xml, 1a2b...)'."""
        return f"{self.name!r} ({self.path}, {self.digest})"

    def describe(self) -> str:
        """A few lines for a person: links, options, grasps, actions, tool."""
        h, s = self.hand, self.space
        return (f"model {self.name}: {self.path}\n  hand: {h.n_joints} joints, fingers {', '.join(h.finger_names)}\n"
                f"  contact links: {', '.join(f'{n} ({k - 1})' for n, k in zip(h.link_names, h.n_options))}\n"
                f"  grasps {s.n_grasps}, actions {s.n_actions}\n  tool {h.tool_name!r}: {h.tool_mass:g} kg, "
                f"{len(h.tool_box_half)} boxes, {len(h.tool_round_type)} round geoms {list(h.tool_round_type)}")

    def expect(self, other: "Model | str", what: str) -> None:
        """Raise `ModelError` if `what` was made for a model of digest `other` (a Model or a digest)."""
        digest = other.digest if isinstance(other, Model) else str(other)
        if digest != self.digest:
            made = other.label if isinstance(other, Model) else f"a model of digest {digest}"
            raise ModelError(f"{what} was made for {made}, not for {self.label}")


def resolve(name_or_path) -> pathlib.Path:
    """The scene file of a shipped name or a path (a folder means its scene.xml)."""
    if isinstance(name_or_path, str) and name_or_path in SHIPPED:
        return SHIPPED[name_or_path]
    path = pathlib.Path(name_or_path).expanduser()
    if path.is_dir():
        path = path / "scene.xml"
    if not path.is_file():
        raise ModelError(f"model: {str(name_or_path)!r} is neither a shipped model ({', '.join(SHIPPED)}) nor a scene "
                         "file")
    return path.resolve()


def load_model(name_or_path=None) -> Model:
    """The `Model` of a shipped name or a scene file (None: the shipped default, ``wrench``; a `Model` or a loaded
    `HandModel` is returned as its `Model`). One object per file in a process. There is no process-wide model:
    whatever is built for another model is given it (`Surrogate(model)`, `scenario.episode_set(name, model)`, ...)."""
    if isinstance(name_or_path, Model):
        return name_or_path
    if isinstance(name_or_path, hand_lib.HandModel):
        return of_hand(name_or_path)
    return _load(str(resolve(DEFAULT if name_or_path is None else name_or_path)))


@functools.lru_cache(maxsize=8)
def load_hand(path: str | pathlib.Path = hand_lib.SCENE_XML) -> hand_lib.HandModel:
    """The `HandModel` of a scene file (one object per path), the file checked first (`require`: a `ModelError`
    listing every convention it breaks). `load_model` is the door that also names and digests the file."""
    require(path)
    hand = dataclasses.replace(hand_lib.from_mjmodel(hand_lib.load_mjmodel(path)), source=str(path))
    if len(hand.q_start) != hand.n_joints:
        raise ValueError(f"model: gsp_ik_start has {len(hand.q_start)} values for {hand.n_joints} joints")
    return hand


def default_space() -> grasps.GraspSpace:
    """The grasp space of the shipped default model (`load_model()`: the wrench)."""
    return load_model().space


@functools.lru_cache(maxsize=16)
def _load(path: str) -> Model:
    shipped = {str(p.resolve()): n for n, p in SHIPPED.items()}
    name = shipped.get(str(pathlib.Path(path).resolve()), pathlib.Path(path).parent.name
                       if pathlib.Path(path).stem == "scene" else pathlib.Path(path).stem)
    return Model(name, pathlib.Path(path), digest(path), load_hand(path))


def of_hand(hand: hand_lib.HandModel) -> Model:
    """The `Model` a `HandModel` was loaded from (its `source`); one built otherwise has none."""
    if not hand.source:
        raise ModelError("model: this HandModel was not loaded from a scene file (hand.source is empty); load it with "
                         "gsp_jax.load_model(path)")
    model = _load(str(resolve(hand.source)))
    return model if model.hand is hand else dataclasses.replace(model, hand=hand)


@functools.lru_cache(maxsize=16)
def digest(path) -> str:
    """16 hex digits of sha256 over the scene as MuJoCo reads it (its includes resolved, comments dropped)."""
    xml = mujoco.MjSpec.from_file(str(path)).to_xml()
    return hashlib.sha256(xml.encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------------------- checks

def require(path) -> None:
    """Raise `ModelError` listing every convention the scene file at `path` breaks (`check_model`)."""
    problems = check_model(path)
    if problems:
        raise ModelError(f"model {path} breaks {len(problems)} convention(s) (see docs/your-model.md):\n  - "
                         + "\n  - ".join(problems))


def missing_files(path) -> list[str]:
    """The asset files (meshes, textures, height fields, skins) the scene at `path` and its includes name but that
    do not exist, as the paths MuJoCo would open (relative to the scene's folder, through meshdir / texturedir /
    assetdir): all of them at once, where MuJoCo's compiler stops at the first. [] where the file does not parse."""
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception:  # noqa: BLE001 -- a file that does not parse: MuJoCo's compile message says why
        return []
    root = pathlib.Path(path).resolve().parent
    named = [(spec.meshdir, m.file) for m in spec.meshes] + [(spec.texturedir, t.file) for t in spec.textures] + \
        [(spec.meshdir, h.file) for h in spec.hfields] + [(spec.meshdir, k.file) for k in spec.skins]
    out = []
    for folder, file in named:
        if file and not (root / (folder or "") / file).exists() and not (root / file).exists():
            out.append(str(pathlib.Path(folder or "") / file))
    return list(dict.fromkeys(out))


@functools.lru_cache(maxsize=16)
def _check(path: str) -> tuple[str, ...]:
    try:
        m = hand_lib.load_mjmodel(path)
    except Exception as e:  # noqa: BLE001 -- MuJoCo's own message, passed on
        missing = missing_files(path)
        if missing:
            folder = pathlib.Path(path).resolve().parent
            return (f"{len(missing)} file(s) the scene names are missing (relative to {folder}): "
                    f"{', '.join(missing)}; get them beside the file, or drop the visual meshes (`import-hand "
                    f"--drop-visual`)",)
        return (f"MuJoCo cannot compile the file: {e}".strip(),)
    problems = [*_check_tool(m), *_check_table(m)]
    links = _check_links(m, problems)
    palm = _palm(m, links)
    if palm is None:
        problems.append("no hand found: no body under the world carries hinge joints")
    else:
        problems += _check_hand(m, palm)
    if not problems:
        try:
            hand_lib.from_mjmodel(m)
        except ValueError as e:
            problems.append(str(e).removeprefix("model: "))
    return tuple(problems)


def check_model(path) -> list[str]:
    """Every model convention the scene file at `path` breaks, in plain words ([] when it follows them all): the
    tool (one free body of supported primitives, with mass), the table (a plane), the contact links (site
    ``contact_<link>``, at least one option ``opt_<link>_<k>`` on the tool), the hand (hinges, a motor each,
    capsule or sphere geoms, the IK start) and the optional conventions (start options, touch lists, reach box,
    supports)."""
    return list(_check(str(path)))


def _name(m, obj, i) -> str:
    return mujoco.mj_id2name(m, obj, i) or f"#{i}"


def _check_tool(m) -> list[str]:
    try:
        tool = hand_lib.tool_body(m)
    except ValueError as e:
        return [str(e).removeprefix("model: ")]
    out = []
    geoms = hand_lib.tool_geoms(m, tool)
    if not geoms:
        out.append(f"tool body {_name(m, mujoco.mjtObj.mjOBJ_BODY, tool)!r} has no collision geom")
    for g in geoms:
        if int(m.geom_type[g]) not in hand_lib.TOOL_GEOMS:
            kind = mujoco.mjtGeom(m.geom_type[g]).name.removeprefix("mjGEOM_").lower()
            out.append(f"tool geom {_name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r} is a {kind}: a tool geom must be one of "
                       f"{', '.join(sorted(hand_lib.TOOL_GEOMS.values()))}")
    if not m.body_mass[tool] > 0:
        out.append(f"tool body {_name(m, mujoco.mjtObj.mjOBJ_BODY, tool)!r} has no mass "
                   "(give it an <inertial> or geoms with density)")
    return out


def _check_table(m) -> list[str]:
    try:
        hand_lib.table_geom(m)
    except ValueError as e:
        return [str(e).removeprefix("model: ")]
    return []


def _check_links(m, problems: list[str]):
    """Check the contact links and their options; the link names if the hand can be checked further."""
    if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TEXT, "gsp_contact_links") < 0:
        problems.append("custom text 'gsp_contact_links' is missing: <custom><text name=\"gsp_contact_links\" "
                        "data=\"link1 link2 ...\"/></custom> lists the contact links in grasp order, each with a site "
                        "'contact_<link>' on its body and options 'opt_<link>_<k>' on the tool")
        return []
    links = hand_lib._text(m, "gsp_contact_links").split()
    if not links:
        problems.append("custom text 'gsp_contact_links' names no link")
        return []
    try:
        tool = hand_lib.tool_body(m)
    except ValueError:
        tool = -1
    for link in links:
        s = hand_lib._site(m, f"contact_{link}")
        if s < 0:
            problems.append(f"link {link!r} has no site 'contact_{link}' (a sphere or capsule site on the link's body)")
        elif int(m.site_type[s]) not in (int(mujoco.mjtGeom.mjGEOM_SPHERE), int(mujoco.mjtGeom.mjGEOM_CAPSULE)):
            problems.append(f"site 'contact_{link}' must be a sphere or capsule site")
        elif m.site_bodyid[s] in (0, tool):
            problems.append(f"site 'contact_{link}' must be on a body of the hand, not the world or the tool")
        if hand_lib._site(m, f"opt_{link}_1") < 0:
            problems.append(f"link {link!r} has no contact option on the tool: add site 'opt_{link}_1' (its z axis the "
                            "inward normal) to the tool body")
        k = 1
        while (o := hand_lib._site(m, f"opt_{link}_{k}")) >= 0:
            if m.site_bodyid[o] != tool:
                problems.append(f"site 'opt_{link}_{k}' is not on the tool body")
            k += 1
    for s in range(m.nsite):
        name = _name(m, mujoco.mjtObj.mjOBJ_SITE, s)
        if name.startswith("opt_") and name[4:].rsplit("_", 1)[0] not in links:
            problems.append(f"site {name!r} names no contact link (gsp_contact_links: {' '.join(links)})")
    placed = [s for n in links if (s := hand_lib._site(m, f"contact_{n}")) >= 0 and m.site_bodyid[s] not in (0, tool)]
    if len({int(m.body_rootid[m.site_bodyid[s]]) for s in placed}) > 1:
        problems.append("the contact links' sites are on more than one hand (bodies under different world children)")
    return links


def hand_joints(m: mujoco.MjModel) -> list[int]:
    """The ids of the hand's joints in scene `m` (below `_palm`: the contact links' root, else the world child with
    the most hinges)."""
    palm = _palm(m, hand_lib._text(m, "gsp_contact_links", "").split())
    return [] if palm is None else [j for j in range(m.njnt) if m.body_rootid[m.jnt_bodyid[j]] == palm]


def _palm(m, links) -> int | None:
    """The hand's root: the world child holding the first placed contact site, else the one (not the tool's) with
    the most hinge joints below it; None if no body has a hinge."""
    try:
        tool = hand_lib.tool_body(m)
    except ValueError:
        tool = -1
    for link in links or ():
        s = hand_lib._site(m, f"contact_{link}")
        if s >= 0 and m.site_bodyid[s] not in (0, tool):
            return int(m.body_rootid[m.site_bodyid[s]])
    return hand_lib.hinged_root(m, exclude=[tool] if tool >= 0 else [])


def _check_hand(m, palm: int) -> list[str]:
    out = []
    bodies = [b for b in range(1, m.nbody) if m.body_rootid[b] == palm]
    joints = [j for j in range(m.njnt) if m.jnt_bodyid[j] in bodies]
    for j in joints:
        if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
            out.append(f"hand joint {_name(m, mujoco.mjtObj.mjOBJ_JOINT, j)!r} is not a hinge")
    per_body = np.bincount(m.jnt_bodyid[joints], minlength=m.nbody) if joints else np.zeros(m.nbody, int)
    out += [f"hand body {_name(m, mujoco.mjtObj.mjOBJ_BODY, b)!r} has {per_body[b]} joints (at most one hinge)"
            for b in bodies if per_body[b] > 1]
    out += _check_actuators(m, joints)
    for g in range(m.ngeom):
        if m.geom_bodyid[g] not in bodies or m.geom_bodyid[g] == palm or not hand_lib.collides(m, g):
            continue
        if int(m.geom_type[g]) not in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_SPHERE)):
            kind = mujoco.mjtGeom(m.geom_type[g]).name.removeprefix("mjGEOM_").lower()
            out.append(f"hand geom {_name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r} (body "
                       f"{_name(m, mujoco.mjtObj.mjOBJ_BODY, m.geom_bodyid[g])!r}) is a {kind}: below the palm a hand "
                       "geom that collides must be a capsule or a sphere (import-hand fits them)")
    start = hand_lib._numeric(m, "gsp_ik_start")
    if start is None:
        out.append(f"custom numeric 'gsp_ik_start' is missing (the IK's start: {len(joints)} joint angles [rad], "
                   "in the hand's joint order)")
    elif len(start) != len(joints):
        out.append(f"custom numeric 'gsp_ik_start' has {len(start)} values for the hand's {len(joints)} joints")
    return out


_MOTOR = "<motor joint=\"{j}\" ctrlrange=\"-L L\"/>, L its torque limit [N m]"


def _servo_kind(m, a: int) -> str | None:
    """What a joint actuator is if not a torque motor ('a position servo (kp 3)', ...); None for a motor."""
    if int(m.actuator_biastype[a]) != int(mujoco.mjtBias.mjBIAS_NONE):
        kp, kv = -m.actuator_biasprm[a, 1], -m.actuator_biasprm[a, 2]
        if kp > 0:
            return f"a position servo (kp {kp:g})"
        return f"a velocity servo (kv {kv:g})" if kv > 0 else "an actuator with a bias term"
    if int(m.actuator_gaintype[a]) != int(mujoco.mjtGain.mjGAIN_FIXED) or \
            int(m.actuator_dyntype[a]) != int(mujoco.mjtDyn.mjDYN_NONE):
        return "not a torque motor (its gain or activation dynamics are not a fixed gain)"
    return None


def _check_actuators(m, joints) -> list[str]:
    """One torque motor per hand joint (what the controller commands), its control range its torque limit."""
    out, by_joint = [], {int(j): [] for j in joints}
    for a in range(m.nu):
        aname = _name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
        if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_TENDON:
            t = int(m.actuator_trnid[a, 0])
            moved = [int(m.wrap_objid[w]) for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t])
                     if m.wrap_type[w] == mujoco.mjtWrap.mjWRAP_JOINT and int(m.wrap_objid[w]) in by_joint]
            if moved:
                names = ", ".join(repr(_name(m, mujoco.mjtObj.mjOBJ_JOINT, j)) for j in moved)
                out.append(f"actuator {aname!r} drives tendon {_name(m, mujoco.mjtObj.mjOBJ_TENDON, t)!r} (joints "
                           f"{names}): the controller commands each joint's torque, one motor per joint "
                           "(import-hand replaces it)")
        elif m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and int(m.actuator_trnid[a, 0]) in by_joint:
            by_joint[int(m.actuator_trnid[a, 0])].append(a)
    for j, acts in by_joint.items():
        jname = _name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
        if not acts:
            out.append(f"hand joint {jname!r} has no motor: add {_MOTOR.format(j=jname)}")
            continue
        if len(acts) > 1:
            out.append(f"hand joint {jname!r} has {len(acts)} actuators "
                       f"({', '.join(repr(_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a)) for a in acts)}): one motor each")
        a = acts[0]
        aname, kind = _name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a), _servo_kind(m, a)
        lo, hi = m.actuator_ctrlrange[a]
        if kind is not None:
            out.append(f"actuator {aname!r} on hand joint {jname!r} is {kind}: the controller commands joint torques; "
                       f"replace it by {_MOTOR.format(j=jname)} (import-hand does, from its forcerange)")
        elif not m.actuator_ctrllimited[a]:
            out.append(f"motor {aname!r} (hand joint {jname!r}) has no control range: its ctrlrange is the joint's "
                       "torque limit, -L..L [N m]")
        elif not lo < 0 < hi:
            out.append(f"hand joint {jname!r} has no motor with a control range around 0: motor {aname!r}'s is "
                       f"[{lo:g}, {hi:g}]; a motor's range is its torque limit, -L..L [N m]")
    return out
