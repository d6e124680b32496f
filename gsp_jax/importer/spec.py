"""Bookkeeping on a `mujoco.MjSpec` for the importer, and the importer's error `HandImportError`.

`delete` removes spec elements together with every actuator, sensor, equality, tendon, exclude and contact pair that
names them (MuJoCo's own delete leaves those behind); `inventory` counts the named elements of each kind and `_lost`
says in words what a step dropped; `_rename` renames every element and every reference to it (tendons rebuilt);
`by_id` maps compiled ids to spec elements. `_fmt`, `_enum_word` and `_named` put numbers, enum values and compiled
elements into the words of the change lines. No geometry here: names and references only.
"""
from __future__ import annotations

import collections

import mujoco
import numpy as np

_OBJ = mujoco.mjtObj
_TRN = mujoco.mjtTrn
_TMP = "__gsp_import_old__"  # a tendon's name while it is rebuilt under its new one
_TENDON_FIELDS = ("actfrclimited", "actfrcrange", "armature", "damping", "frictionloss", "group", "limited", "margin",
                  "material", "range", "rgba", "solimp_friction", "solimp_limit", "solref_friction", "solref_limit",
                  "springlength", "springyield", "stiffness", "userdata", "width")


class HandImportError(ValueError):
    """The hand file cannot be imported as asked; the message names the field and value and what to do."""


def _kind_of(e) -> int | None:
    """The mjtObj kind of a spec element that other elements can name (None for the others)."""
    kinds = {mujoco.MjsBody: _OBJ.mjOBJ_BODY, mujoco.MjsJoint: _OBJ.mjOBJ_JOINT, mujoco.MjsGeom: _OBJ.mjOBJ_GEOM,
             mujoco.MjsSite: _OBJ.mjOBJ_SITE, mujoco.MjsTendon: _OBJ.mjOBJ_TENDON,
             mujoco.MjsActuator: _OBJ.mjOBJ_ACTUATOR, mujoco.MjsCamera: _OBJ.mjOBJ_CAMERA}
    return next((int(k) for t, k in kinds.items() if isinstance(e, t)), None)


def _norm_kind(kind) -> int:
    return int(_OBJ.mjOBJ_BODY) if int(kind) == int(_OBJ.mjOBJ_XBODY) else int(kind)


_TRN_KIND = {int(_TRN.mjTRN_JOINT): _OBJ.mjOBJ_JOINT, int(_TRN.mjTRN_JOINTINPARENT): _OBJ.mjOBJ_JOINT,
             int(_TRN.mjTRN_TENDON): _OBJ.mjOBJ_TENDON, int(_TRN.mjTRN_SITE): _OBJ.mjOBJ_SITE,
             int(_TRN.mjTRN_BODY): _OBJ.mjOBJ_BODY, int(_TRN.mjTRN_SLIDERCRANK): _OBJ.mjOBJ_SITE}


def _wraps(t) -> list[tuple[int, str, float, float, str]]:
    """A tendon's path: (mjtWrap type, target name ('' if gone or none), coef, divisor, side site name)."""
    out = []
    for w in t.path:
        target = "" if w.target is None else getattr(w.target, "name", "")
        side = "" if w.sidesite is None else getattr(w.sidesite, "name", w.sidesite if isinstance(w.sidesite, str)
                                                     else "")
        coef, divisor = (float(v) if v is not None else 0.0 for v in (w.coef, w.divisor))
        out.append((int(w.type), target, coef, divisor, side))
    return out


def _references(spec: mujoco.MjSpec) -> list[tuple[object, list[tuple[int, str]]]]:
    """Every element that names others, with the (mjtObj kind, name) it names; a tendon whose path lost an element
    names (-1, '')."""
    out = []
    for a in spec.actuators:
        kind = _TRN_KIND.get(int(a.trntype))
        refs = [(int(kind), a.target)] if kind is not None else []
        refs += [(int(_OBJ.mjOBJ_SITE), n) for n in (a.refsite, a.slidersite) if n]
        out.append((a, refs))
    for s in spec.sensors:
        refs = [(_norm_kind(k), n) for k, n in ((s.objtype, s.objname), (s.reftype, s.refname)) if n]
        out.append((s, refs))
    for e in spec.equalities:
        out.append((e, [(_norm_kind(e.objtype), n) for n in (e.name1, e.name2) if n]))
    kinds = {int(mujoco.mjtWrap.mjWRAP_JOINT): _OBJ.mjOBJ_JOINT, int(mujoco.mjtWrap.mjWRAP_SITE): _OBJ.mjOBJ_SITE,
             int(mujoco.mjtWrap.mjWRAP_SPHERE): _OBJ.mjOBJ_GEOM, int(mujoco.mjtWrap.mjWRAP_CYLINDER): _OBJ.mjOBJ_GEOM}
    for t in spec.tendons:
        refs = []
        for kind, target, _, _, side in _wraps(t):
            if kind in kinds:
                refs.append((int(kinds[kind]), target) if target else (-1, ""))
            if side:
                refs.append((int(_OBJ.mjOBJ_SITE), side))
        out.append((t, refs))
    out += [(x, [(int(_OBJ.mjOBJ_BODY), x.bodyname1), (int(_OBJ.mjOBJ_BODY), x.bodyname2)]) for x in spec.excludes]
    out += [(p, [(int(_OBJ.mjOBJ_GEOM), p.geomname1), (int(_OBJ.mjOBJ_GEOM), p.geomname2)]) for p in spec.pairs]
    return out


def _tree_names(e) -> set[tuple[int, str]]:
    """(kind, name) of a tree element and, for a body, of everything below it."""
    kind = _kind_of(e)
    out = {(kind, e.name)} if kind is not None and e.name else set()
    if isinstance(e, mujoco.MjsBody):
        for obj in (_OBJ.mjOBJ_BODY, _OBJ.mjOBJ_JOINT, _OBJ.mjOBJ_GEOM, _OBJ.mjOBJ_SITE, _OBJ.mjOBJ_CAMERA):
            out |= {(int(obj), x.name) for x in e.find_all(obj) if x.name}
    return out


def _inside(e, bodies: list) -> bool:
    """Whether tree element e lies in (or is) one of `bodies`."""
    b = e if isinstance(e, mujoco.MjsBody) else e.parent
    while b is not None:
        if any(b is x for x in bodies):
            return True
        parent = b.parent
        if parent is b or parent is None or b.name == "world":
            return False
        b = parent
    return False


def delete(spec: mujoco.MjSpec, doomed: list) -> None:
    """Delete spec elements and, transitively, every actuator, sensor, equality, tendon, exclude and contact pair
    that names one of them (MuJoCo's own delete leaves those behind for joints, geoms and sites)."""
    doomed = list(doomed)
    names = set().union(*(_tree_names(e) for e in doomed)) if doomed else set()
    grew = True
    while grew:
        grew = False
        for e, refs in _references(spec):
            if any(e is d for d in doomed):
                continue
            if any(r in names or r[0] == -1 for r in refs):
                doomed.append(e)
                names |= _tree_names(e)
                grew = True
    bodies = [e for e in doomed if isinstance(e, mujoco.MjsBody)]
    tree = (mujoco.MjsBody, mujoco.MjsJoint, mujoco.MjsGeom, mujoco.MjsSite, mujoco.MjsCamera, mujoco.MjsLight)
    for e in [e for e in doomed if not isinstance(e, tree)]:
        spec.delete(e)
    for e in [e for e in doomed if isinstance(e, tree) and not isinstance(e, mujoco.MjsBody)]:
        if not _inside(e, bodies):
            spec.delete(e)
    for b in bodies:
        if not _inside(b.parent, bodies):
            spec.delete(b)


_LISTED = ("bodies", "joints", "geoms", "sites", "actuators", "sensors", "tendons", "equalities", "excludes", "pairs")


def inventory(spec: mujoco.MjSpec) -> dict[str, collections.Counter]:
    """The named elements of each kind (unnamed ones counted under ''); excludes as 'body1-body2'."""
    out = {}
    for kind in _LISTED:
        items = getattr(spec, kind)
        if kind == "excludes":
            out[kind] = collections.Counter(f"{x.bodyname1}-{x.bodyname2}" for x in items)
        else:
            out[kind] = collections.Counter(x.name for x in items if not (kind == "bodies" and x.name == "world"))
    return out


def _lost(before: dict, after: dict) -> list[str]:
    """Plain words for what `before` has and `after` lacks, kind by kind."""
    parts = []
    for kind in _LISTED:
        gone = before[kind] - after[kind]
        named = sorted(n for n in gone.elements() if n)
        if gone:
            what = ", ".join(named[:12]) + (f" and {len(named) - 12} more" if len(named) > 12 else "")
            unnamed = gone[""]
            text = what + (f"{' and ' if named else ''}{unnamed} unnamed" if unnamed else "")
            parts.append(f"{kind} ({sum(gone.values())}): {text}")
    return parts


def _rename(spec: mujoco.MjSpec, fn) -> None:
    """Rename every body, joint, geom, site, camera, light, tendon, actuator, sensor, equality and exclude by `fn`
    (old name -> new name), and every reference to them; tendons are rebuilt (a tendon's path keeps the names it
    was built with)."""
    paths = [(t, _wraps(t)) for t in spec.tendons]
    for kind in (*_LISTED, "cameras", "lights"):
        for e in getattr(spec, kind):
            if e.name and not (kind == "bodies" and e.name == "world"):
                e.name = fn(e.name)
    for a in spec.actuators:
        a.target, a.refsite, a.slidersite = fn(a.target), fn(a.refsite), fn(a.slidersite)
    for s in spec.sensors:
        s.objname, s.refname = fn(s.objname), fn(s.refname)
    for e in spec.equalities:
        e.name1, e.name2 = fn(e.name1), fn(e.name2)
    for x in spec.excludes:
        x.bodyname1, x.bodyname2 = fn(x.bodyname1), fn(x.bodyname2)
    for p in spec.pairs:
        p.geomname1, p.geomname2 = fn(p.geomname1), fn(p.geomname2)
    for t, wraps in paths:
        _rebuild_tendon(spec, t, [(k, fn(n), c, d, fn(s)) for k, n, c, d, s in wraps])


def _rebuild_tendon(spec: mujoco.MjSpec, t, wraps) -> None:
    """Replace tendon t by a copy (same name, fields) whose path is `wraps` (`_wraps`' tuples)."""
    name = t.name
    t.name = _TMP + name
    new = spec.add_tendon()
    for f in _TENDON_FIELDS:
        if hasattr(t, f):
            setattr(new, f, getattr(t, f))
    new.name = name
    W = mujoco.mjtWrap
    for kind, target, coef, divisor, side in wraps:
        if kind == W.mjWRAP_JOINT:
            new.wrap_joint(target, coef)
        elif kind == W.mjWRAP_SITE:
            new.wrap_site(target)
        elif kind in (W.mjWRAP_SPHERE, W.mjWRAP_CYLINDER):
            new.wrap_geom(target, side)
        elif kind == W.mjWRAP_PULLEY:
            new.wrap_pulley(divisor)
    spec.delete(t)


def by_id(items) -> dict[int, object]:
    """Spec elements by their compiled id (valid right after `spec.compile()`)."""
    return {e.id: e for e in items}


def _named(m: mujoco.MjModel, obj, i: int) -> str:
    return mujoco.mj_id2name(m, obj, i) or f"#{i}"


def _enum_word(enum, value) -> str:
    """An enum value's name without its prefix, in lower case: mjJNT_SLIDE -> 'slide'."""
    return enum(int(value)).name.split("_", 1)[1].lower()


def _fmt(x, unit: str = "", scale: float = 1.0, digits: int = 4) -> str:
    """Numbers for a person: `digits` significant digits, rounding noise (below 1e-9 of the largest) shown as 0."""
    vals = np.atleast_1d(np.asarray(x, np.float64)) * scale
    vals = np.where(np.abs(vals) <= 1e-9 * max(float(np.abs(vals).max()), 1e-300), 0.0, vals)
    text = " ".join(f"{v:.{digits}g}" for v in vals)
    return f"({text}){unit}" if len(vals) > 1 else f"{text}{unit}"

