"""The import's steps on the spec up to the new geoms, each editing it in place and returning its change lines.

Reading the file (`_load`) and compiling its kinematics without reading any mesh (`skeleton`); choosing the palm
(`choose_palm`) and making it the world's child at its qpos0 pose, dropping what is above it (`reroot`); checking the
joints (hinges only) and naming the unnamed ones; resetting the hand's <option>; the mesh files (`mesh_files`,
`check_files`); pinning the inertia of bodies whose geoms change (`pin_inertia`); replacing each body's colliding
boxes, meshes, cylinders and ellipsoids by a fitted capsule or sphere (`replace_geoms` -> `Replacement`s, the fit in
the body's frame [m]); removing visual geoms and the meshes no geom uses.
"""
from __future__ import annotations

import collections
import dataclasses
import pathlib

import mujoco
import numpy as np

from gsp_jax.importer.fitting import Fit, fit_round
from gsp_jax.importer.geom_points import geom_distance, geom_points, over_cover
from gsp_jax.importer.spec import HandImportError, _enum_word, _fmt, _lost, _named, by_id, delete, inventory
from gsp_jax.model import hand as hand_lib

_OBJ = mujoco.mjtObj
_GEOM = mujoco.mjtGeom
SEARCH_SPACING = 0.002  # [m] the spacing of a fitted geom's surface samples while choosing among the candidate fits
SEARCH_TOLERANCE = 0.0005  # [m] candidates this close to the least over-cover count as equal: the smallest volume
_ROUND = (int(_GEOM.mjGEOM_CAPSULE), int(_GEOM.mjGEOM_SPHERE))
_CONTACT_FIELDS = ("contype", "conaffinity", "condim", "friction", "solref", "solimp", "margin", "gap", "priority",
                   "solmix")


def _load(src: pathlib.Path) -> mujoco.MjSpec:
    if not src.is_file():
        raise HandImportError(f"src: no such file {str(src)!r}")
    try:
        return mujoco.MjSpec.from_file(str(src))
    except Exception as e:  # noqa: BLE001 -- MuJoCo's own parse error, passed on without its trace
        raise HandImportError(f"src: MuJoCo cannot read {str(src)!r}: {e}") from None


def skeleton(spec: mujoco.MjSpec) -> mujoco.MjModel:
    """The spec's kinematics compiled without any geom, mesh, material or texture (so without reading a file):
    the same bodies, joints, actuators and keyframes, each body at least a tiny mass."""
    s = spec.copy()
    delete(s, list(s.geoms))
    for kind in ("skins", "meshes", "hfields", "materials", "textures"):
        for e in list(getattr(s, kind)):
            s.delete(e)
    for e in (*s.sites, *s.tendons):
        e.material = ""
    s.compiler.boundmass, s.compiler.boundinertia = 1e-6, 1e-12
    try:
        return s.compile()
    except Exception as e:  # noqa: BLE001
        raise HandImportError(f"MuJoCo cannot compile the hand's bodies and joints: {e}") from None


def _subtree_hinges(m: mujoco.MjModel, root: int) -> int:
    bodies = {b for b in range(m.nbody) if hand_lib._is_below(m, b, root)}
    return sum(1 for j in range(m.njnt) if m.jnt_bodyid[j] in bodies and m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE)


def choose_palm(spec: mujoco.MjSpec, sk: mujoco.MjModel, palm: str | None) -> str:
    """The palm's name: `palm` (checked), or the world's child with the most hinge joints below it (named 'palm'
    if it had no name)."""
    children = [b for b in range(1, sk.nbody) if sk.body_parentid[b] == 0]
    if palm is not None:
        b = mujoco.mj_name2id(sk, _OBJ.mjOBJ_BODY, palm)
        if b < 0:
            roots = ", ".join(repr(_named(sk, _OBJ.mjOBJ_BODY, c)) for c in children)
            raise HandImportError(f"palm: no body named {palm!r} in the file (the world's children: {roots})")
        if _subtree_hinges(sk, b) - sum(sk.jnt_bodyid == b) == 0:
            raise HandImportError(f"palm: body {palm!r} has no hinge joint below it")
        return palm
    if not children:
        raise HandImportError("src: the worldbody holds no body (no hand)")
    best = hand_lib.hinged_root(sk)
    if best is None:
        raise HandImportError("src: no body of the file has hinge joints below it (no hand)")
    name = mujoco.mj_id2name(sk, _OBJ.mjOBJ_BODY, best)
    if not name:
        spec.worldbody.bodies[children.index(best)].name = name = "palm"
    return name


def _set_pose(e, pos, quat) -> None:
    e.pos = np.asarray(pos, np.float64)
    e.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
    e.quat = np.asarray(quat, np.float64) / np.linalg.norm(quat)


def reroot(spec: mujoco.MjSpec, sk: mujoco.MjModel, palm: str) -> list[str]:
    """Make the palm the world's child at its pose in the file's reference configuration (qpos0) and drop what is
    above it (its ancestors' joints, geoms, sites and other children, and what names them), the palm's own joints,
    the world's other bodies, geoms and sites. `sk`: the spec's `skeleton`. Returns the change lines."""
    d = mujoco.MjData(sk)
    d.qpos[:] = sk.qpos0
    mujoco.mj_kinematics(sk, d)
    b = sk.body(palm).id
    pos, quat = d.xpos[b].copy(), d.xquat[b].copy()
    before = inventory(spec)
    pb = spec.body(palm)
    chain = []
    a = pb.parent
    while a is not spec.worldbody:
        chain.append(a)
        a = a.parent
    doomed = list(pb.joints)
    for a in chain:
        doomed += [*a.joints, *a.geoms, *a.sites, *a.cameras, *a.lights]
        doomed += [c for c in a.bodies if not any(c is x for x in (*chain, pb))]
    root = chain[-1] if chain else pb
    world = spec.worldbody
    doomed += [c for c in world.bodies if c is not root] + [*world.geoms, *world.sites]
    doomed += [x for x in spec.excludes if any(n in {c.name for c in chain} for n in (x.bodyname1, x.bodyname2))]
    delete(spec, doomed)
    for a in reversed(chain):
        frame = a.to_frame()
        _set_pose(frame, np.zeros(3), [1.0, 0.0, 0.0, 0.0])
    _set_pose(spec.body(palm), pos, quat)
    lost = _lost(before, inventory(spec))
    out = []
    if chain:
        out.append(f"palm {palm!r}: made the world's child at its pose in the file's reference configuration "
                   f"(qpos0): pos {_fmt(pos)} m, quat {_fmt(quat)}; the bodies above it "
                   f"({', '.join(repr(a.name) for a in reversed(chain))}) are gone")
    if lost:
        out.append("dropped (above the palm, the palm's own joints, the world's other bodies and geoms, and what "
                   "names them): " + "; ".join(lost))
    return out


def _hand_bodies(m: mujoco.MjModel, palm: int) -> list[int]:
    """The bodies below the palm (not the palm), in MuJoCo order."""
    return [b for b in range(1, m.nbody) if b != palm and hand_lib._is_below(m, b, palm)]


def check_joints(m: mujoco.MjModel, palm: int) -> list[str]:
    """Raise `HandImportError` for a joint below the palm that is not a hinge; notes for bodies with more than one
    hinge (the conventions allow one per body)."""
    bad = [j for j in range(m.njnt) if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE]
    if bad:
        kinds = ", ".join(f"{_named(m, _OBJ.mjOBJ_JOINT, j)!r} ({_enum_word(mujoco.mjtJoint, m.jnt_type[j])} on body "
                          f"{_named(m, _OBJ.mjOBJ_BODY, m.jnt_bodyid[j])!r})" for j in bad)
        raise HandImportError(f"joints {kinds}: every joint below the palm must be a hinge (a slide, ball or free "
                              "joint has no place in the hand's kinematics)")
    counts = collections.Counter(int(b) for b in m.jnt_bodyid)
    return [f"NOTE: body {_named(m, _OBJ.mjOBJ_BODY, b)!r} has {n} hinges; the conventions allow one per body: "
            "split it into a chain of bodies by hand" for b, n in counts.items() if n > 1]


_OPTION_ENUMS = {"cone": mujoco.mjtCone, "integrator": mujoco.mjtIntegrator, "solver": mujoco.mjtSolver,
                 "jacobian": mujoco.mjtJacobian}
_OPTION_FLAGS = {"disableflags": mujoco.mjtDisableBit, "enableflags": mujoco.mjtEnableBit}


def _option_words(field: str, value) -> str:
    """An <option> field's value in words: enum names, flag names, numbers."""
    if field in _OPTION_ENUMS:
        return _enum_word(_OPTION_ENUMS[field], value)
    if field in _OPTION_FLAGS:
        bits = [n.split("_", 1)[1].lower() for n, b in _OPTION_FLAGS[field].__members__.items()
                if int(value) & int(b) and not n.endswith("NFLAG") and bin(int(b)).count("1") == 1]
        return "+".join(bits) or "none"
    return _fmt(value)


def name_joints(spec: mujoco.MjSpec, m: mujoco.MjModel, hinges: list[int]) -> list[str]:
    """Name the unnamed hand hinges '<body>_joint' (a motor names its joint). `m`: the spec compiled. Change
    lines."""
    specs, taken = by_id(spec.joints), {j.name for j in spec.joints if j.name}
    out = []
    for j in hinges:
        if not mujoco.mj_id2name(m, _OBJ.mjOBJ_JOINT, j):
            body = mujoco.mj_id2name(m, _OBJ.mjOBJ_BODY, m.jnt_bodyid[j]) or f"body{m.jnt_bodyid[j]}"
            specs[j].name = _unique(f"{body}_joint", taken)
            out.append(f"joint #{j} (body {body!r}) had no name: named {specs[j].name!r} (its motor names it)")
    return out


def reset_option(spec: mujoco.MjSpec) -> list[str]:
    """Reset the hand's <option> to MuJoCo's defaults (the scene's <option> sets the physics); the change line."""
    default = mujoco.MjSpec().option
    diffs = []
    for f in dir(default):
        if f.startswith("_"):
            continue
        old, new = getattr(spec.option, f), getattr(default, f)
        if callable(old):
            continue
        if not np.array_equal(np.asarray(old), np.asarray(new)):
            diffs.append(f"{f} {_option_words(f, old)}")
            setattr(spec.option, f, new)
    if not diffs:
        return []
    return [f"<option> dropped ({', '.join(diffs)}): the scene's <option> sets the physics, and an included hand's "
            "option would override MuJoCo's defaults there"]


def mesh_files(spec: mujoco.MjSpec) -> dict[str, pathlib.Path]:
    """Each mesh's (and texture's) file, resolved as MuJoCo resolves it: name -> path (files that may not exist)."""
    base = pathlib.Path(spec.modelfiledir or ".")
    out = {}
    for kind, folder in (("meshes", spec.compiler.meshdir), ("textures", spec.compiler.texturedir)):
        for e in getattr(spec, kind):
            if e.file:
                f = pathlib.Path(e.file)
                out[e.name or e.file] = f if f.is_absolute() else base / (folder or "") / f
    return out


def check_files(spec: mujoco.MjSpec, drop_visual: bool, palm: str | None = None, drop_missing: bool = False
                ) -> list[str]:
    """Raise `HandImportError` naming a mesh file that is missing where it is needed; with `drop_visual`, delete the
    visual geoms whose mesh files are missing (their meshes go with the other unused ones); with `drop_missing`, the
    collision geoms too (their bodies then collide with nothing there). `palm`: the palm body's name (its geoms are
    kept as they are, not fitted). The change lines."""
    paths = mesh_files(spec)
    missing = {x.name: paths[x.name or x.file] for x in spec.meshes
               if x.file and not paths[x.name or x.file].is_file()}
    out = []
    for name, path in missing.items():
        users = [g for g in spec.geoms if g.type == _GEOM.mjGEOM_MESH and g.meshname == name]
        colliding = [g for g in users if g.contype or g.conaffinity]
        dropped = bool(colliding and drop_missing)
        if dropped:
            bodies = sorted({g.parent.name for g in colliding})
            out.append(f"mesh {name!r}: file {str(path)!r} is missing; its collision geoms ({len(colliding)}) removed "
                       f"(drop_missing): {'body' if len(bodies) == 1 else 'bodies'} {', '.join(map(repr, bodies))} "
                       f"collide{'s' if len(bodies) == 1 else ''} with nothing there now")
            for g in colliding:
                spec.delete(g)
            users = [g for g in users if g not in colliding]
            colliding = []
        if colliding:
            g = colliding[0]
            why = ("the palm's geoms are kept as they are: MuJoCo needs the file to compile it; or replace the geom "
                   "by a box or capsule in the file" if g.parent.name == palm else
                   "its capsule is fitted to the mesh's vertices")
            raise HandImportError(f"mesh {name!r}: file {str(path)!r} is missing, and collision geom "
                                  f"{g.name or '(unnamed)'!r} (body {g.parent.name!r}) needs it ({why}); put the "
                                  "file there, or remove such geoms (drop_missing=True; on the command line "
                                  "--drop-missing)")
        if users and not drop_visual:
            raise HandImportError(f"mesh {name!r}: file {str(path)!r} is missing (used by the visual geoms "
                                  f"{', '.join(repr(g.name or '(unnamed)') for g in users)}); put the file there, or "
                                  "drop the visual geoms (drop_visual=True; on the command line --drop-visual)")
        for g in users:
            spec.delete(g)
        spec.delete(spec.mesh(name))
        if users or not dropped:
            out.append(f"mesh {name!r}: file {str(path)!r} is missing; removed with its visual geoms ({len(users)})")
    return out


def pin_inertia(spec: mujoco.MjSpec, m: mujoco.MjModel, bodies: list[int]) -> list[str]:
    """Give each of `bodies` (compiled ids of `m`, compiled from `spec`) that has no explicit <inertial> the mass,
    centre of mass and inertia MuJoCo computed from its geoms, so replacing its geoms keeps them. Change lines."""
    out = []
    specs = by_id(spec.bodies)
    for b in bodies:
        e = specs[b]
        if e.explicitinertial:
            continue
        e.mass, e.ipos, e.iquat = float(m.body_mass[b]), m.body_ipos[b].copy(), m.body_iquat[b].copy()
        e.inertia = m.body_inertia[b].copy()
        e.fullinertia = np.full(6, np.nan)
        e.explicitinertial = True
        out.append(f"body {_named(m, _OBJ.mjOBJ_BODY, b)!r}: its mass {m.body_mass[b] * 1e3:.4g} g and inertia, "
                   "computed from its geoms, written as its <inertial> (so the new geoms keep them)")
    return out


@dataclasses.dataclass(frozen=True)
class Replacement:
    """A fitted round geom and the geoms it replaced."""

    body: str
    name: str  # the new geom's name
    replaced: tuple[str, ...]  # the replaced geoms' labels
    fit: Fit  # in the body's frame [m]
    n_points: int  # the points it covers (box corners, mesh vertices, ...)
    over_cover: float  # `over_cover` [m]

    def describe(self) -> str:
        f = self.fit
        shape = (f"sphere r {f.radius * 1e3:.2f} mm at {_fmt(f.ends[0], ' mm', 1e3)}" if f.kind == "sphere" else
                 f"capsule r {f.radius * 1e3:.2f} mm, segment {f.length * 1e3:.2f} mm from {_fmt(f.ends[0], '', 1e3)}"
                 f" to {_fmt(f.ends[1], ' mm', 1e3)}")
        return (f"body {self.body!r}: {', '.join(self.replaced)} -> {shape} ({self.name!r}, body frame), covering "
                f"all {self.n_points} points; over-cover {self.over_cover * 1e3:.2f} mm")


def _geom_label(m: mujoco.MjModel, g: int) -> str:
    kind = _enum_word(_GEOM, m.geom_type[g])
    name = mujoco.mj_id2name(m, _OBJ.mjOBJ_GEOM, g)
    label = f"{kind} {name!r}" if name else kind
    if kind == "mesh":
        label += f" (asset {mujoco.mj_id2name(m, _OBJ.mjOBJ_MESH, m.geom_dataid[g])!r})"
    return label


def _to_replace(m: mujoco.MjModel, palm: int) -> dict[int, list[int]]:
    """Body -> its colliding geoms that are not capsules or spheres, for the bodies below the palm."""
    out: dict[int, list[int]] = {}
    for b in _hand_bodies(m, palm):
        for g in range(m.ngeom):
            if m.geom_bodyid[g] == b and hand_lib.collides(m, g) and int(m.geom_type[g]) not in _ROUND:
                kind = int(m.geom_type[g])
                if kind in (_GEOM.mjGEOM_PLANE, _GEOM.mjGEOM_HFIELD, _GEOM.mjGEOM_SDF):
                    raise HandImportError(f"geom {_geom_label(m, g)} (body {_named(m, _OBJ.mjOBJ_BODY, b)!r}): a "
                                          f"{_enum_word(_GEOM, kind)} cannot be covered by a capsule; remove it or "
                                          "make it a box or mesh")
                out.setdefault(b, []).append(g)
    return out


def _unique(name: str, taken: set[str]) -> str:
    out, k = name, 2
    while out in taken:
        out, k = f"{name}{k}", k + 1
    taken.add(out)
    return out


def replace_geoms(spec: mujoco.MjSpec, m: mujoco.MjModel, palm: int, per_geom: bool
                  ) -> tuple[list[Replacement], list[str]]:
    """Replace the colliding non-round geoms below the palm by fitted capsules or spheres (one per body, or one per
    geom), each with the contact attributes, group, colour and material of the first geom it replaces. `m`: the
    spec compiled (its ids). The replacements and the change lines."""
    out, lines = [], []
    taken = {g.name for g in spec.geoms if g.name}
    geom_specs, body_specs = by_id(spec.geoms), by_id(spec.bodies)
    for b, geoms in _to_replace(m, palm).items():
        groups = [[g] for g in geoms] if per_geom else [geoms]
        body = body_specs[b]
        bname = _named(m, _OBJ.mjOBJ_BODY, b)
        for group in groups:
            pts = np.concatenate([geom_points(m, g) for g in group])
            coarse = [geom_distance(m, g, SEARCH_SPACING) for g in group]
            fit = fit_round(pts, lambda f: over_cover(coarse, f, SEARCH_SPACING), SEARCH_TOLERANCE)
            first = geom_specs[group[0]]
            only = mujoco.mj_id2name(m, _OBJ.mjOBJ_GEOM, group[0]) if len(group) == 1 else None
            new = body.add_geom()
            new.classname = spec.default
            new.meshname = new.hfieldname = ""  # a primitive that names a mesh is fitted to it by MuJoCo
            for f in (*_CONTACT_FIELDS, "group", "rgba", "material", "density"):
                setattr(new, f, getattr(first, f))
            new.type = _GEOM.mjGEOM_SPHERE if fit.kind == "sphere" else _GEOM.mjGEOM_CAPSULE
            if fit.kind == "sphere":
                new.pos, new.size = fit.ends[0], [fit.radius, 0.0, 0.0]
            else:
                new.fromto, new.size = np.concatenate(fit.ends), [fit.radius, 0.0, 0.0]
            differ = [f for f in _CONTACT_FIELDS if any(not np.array_equal(np.asarray(getattr(first, f)),
                                                                           np.asarray(getattr(geom_specs[g], f)))
                                                        for g in group[1:])]
            labels = tuple(_geom_label(m, g) for g in group)
            rep = Replacement(bname, "", labels, fit, len(pts), over_cover([geom_distance(m, g) for g in group], fit))
            for g in group:
                spec.delete(geom_specs[g])
            taken.discard(only)
            body_name = mujoco.mj_id2name(m, _OBJ.mjOBJ_BODY, b)
            new.name = _unique(only or f"{body_name}_{fit.kind}", taken) if only or body_name else ""
            rep = dataclasses.replace(rep, name=new.name)
            out.append(rep)
            lines.append(rep.describe())
            if differ:
                lines.append(f"NOTE: body {bname!r}: its replaced geoms differ in {', '.join(differ)}; the new geom "
                             f"takes those of {labels[0]} (per_geom keeps each geom's own)")
    return out, lines


def remove_tendons(spec: mujoco.MjSpec) -> list[str]:
    """Delete every tendon, spatial and fixed (their paths and springs), and what names one: the actuators that pull
    them, sensors, equalities. A tendon-driven hand's joints then take a motor each (`motors`). The change line."""
    tendons = list(spec.tendons)
    if not tendons:
        return []
    names = ", ".join(t.name or "(unnamed)" for t in tendons[:6]) + (", ..." if len(tendons) > 6 else "")
    delete(spec, tendons)
    return [f"tendons removed: {len(tendons)} ({names}), with their springs and what names them (actuators, "
            "sensors, equalities): each joint is driven by a motor of its own"]


def remove_visual(spec: mujoco.MjSpec, m: mujoco.MjModel) -> list[str]:
    """Delete every geom that collides with nothing (visual only), but those a tendon wraps around (part of the
    tendon's path: a spatial tendon names them). `m`: the spec compiled (its tendons' wraps). The change line."""
    wrap = {int(mujoco.mjtWrap.mjWRAP_SPHERE), int(mujoco.mjtWrap.mjWRAP_CYLINDER)}
    wrapped = {mujoco.mj_id2name(m, _OBJ.mjOBJ_GEOM, int(m.wrap_objid[i])) for i in range(m.nwrap)
               if int(m.wrap_type[i]) in wrap}
    visual = [g for g in spec.geoms if not (g.contype or g.conaffinity)]
    gone = [g for g in visual if not (g.name and g.name in wrapped)]
    if not gone:
        return []
    for g in gone:
        spec.delete(g)
    kept = len(visual) - len(gone)
    return [f"visual geoms (contype = conaffinity = 0) removed: {len(gone)}"
            + (f" (kept {kept} that tendons wrap around)" if kept else "")]


def drop_unused_meshes(spec: mujoco.MjSpec) -> list[str]:
    """Delete the meshes no geom uses. The change line."""
    used = {g.meshname for g in spec.geoms if g.type == _GEOM.mjGEOM_MESH}
    gone = [x for x in spec.meshes if x.name not in used]
    for x in gone:
        spec.delete(x)
    return [f"mesh assets no geom uses any more, removed: {', '.join(x.name for x in gone)}"] if gone else []

