"""The import's steps after the geoms: motors, joint dynamics, names, keyframes, the palm's pose; change lines.

`motors` gives every hinge exactly one torque motor (gear 1, ctrlrange ±limit [N m]; the limit from its actuators'
force ranges, the joint's actuatorfrcrange or the `torque_limit` given); `joint_dynamics` sets the hinges' damping,
armature and friction loss to the values the physics controller is tuned for; `equality_notes`; `strip_prefix`
strips a name prefix that makes the finger names collide; `read_keys` / `write_keys` carry the keyframes whose
controls were 0 over by joint name; `palm_pose` sets the palm's pose (pos [m], quat w x y z) and `facing_lines`
says where its palmar side faces; `self_contacts` lists the body pairs touching at qpos0.
"""
from __future__ import annotations

import dataclasses
import os

import mujoco
import numpy as np

from gsp_jax.importer.spec import (_LISTED, HandImportError, _enum_word, _fmt, _named, _rename, by_id, delete,
                                   inventory)
from gsp_jax.importer.steps import _hand_bodies, _set_pose, _unique
from gsp_jax.model import hand as hand_lib

_OBJ = mujoco.mjtObj
_TRN = mujoco.mjtTrn
UNIT_GAIN_TOL = 1e-6  # a motor's gain counts as 1 within this


def describe_actuator(m: mujoco.MjModel, a: int) -> str:
    """An actuator in words: 'position servo (kp 3)', 'velocity servo (kv 1)', 'motor (gain 2)', 'general ...'."""
    gain, bias = m.actuator_gainprm[a], m.actuator_biasprm[a]
    fixed = m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED and m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE
    if fixed and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_AFFINE:
        if abs(bias[1] + gain[0]) < 1e-12 and bias[1] != 0:
            return f"position servo (kp {gain[0]:g}{f', kv {-bias[2]:g}' if bias[2] else ''})"
        if bias[1] == 0 and abs(bias[2] + gain[0]) < 1e-12:
            return f"velocity servo (kv {gain[0]:g})"
    if fixed and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE:
        return "motor" if abs(gain[0] - 1) < UNIT_GAIN_TOL else f"motor (gain {gain[0]:g})"
    return (f"general actuator (gain {_enum_word(mujoco.mjtGain, m.actuator_gaintype[a])}, bias "
            f"{_enum_word(mujoco.mjtBias, m.actuator_biastype[a])}, dynamics "
            f"{_enum_word(mujoco.mjtDyn, m.actuator_dyntype[a])})")


def is_plain_motor(m: mujoco.MjModel, a: int) -> bool:
    """A joint torque motor as the conventions want it: joint transmission, fixed gain 1, no bias, no dynamics,
    no damping or armature of its own, a control range around 0 and no tighter force limit."""
    lo, hi = m.actuator_ctrlrange[a]
    force_ok = not m.actuator_forcelimited[a] or max(-lo, hi) <= np.abs(m.actuator_forcerange[a]).min()
    return bool(m.actuator_trntype[a] == _TRN.mjTRN_JOINT and m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE
                and m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
                and abs(m.actuator_gainprm[a, 0] - 1) < UNIT_GAIN_TOL
                and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE
                and m.actuator_ctrllimited[a] and lo < 0 < hi and force_ok
                and not np.any(m.actuator_damping[a]) and not m.actuator_armature[a])


def actuator_limit(m: mujoco.MjModel, a: int) -> tuple[float | None, str]:
    """The largest force actuator `a` gives along its transmission, and where it comes from: its force range's
    bound (max |lo|, |hi|) times |gear| if force-limited; for a fixed-gain actuator without bias also its control
    bound times |gain| times |gear| (the smaller of the two); None if neither."""
    gear = abs(float(m.actuator_gear[a, 0]))
    cands = []
    if m.actuator_forcelimited[a]:
        bound = float(np.abs(m.actuator_forcerange[a]).max())
        cands.append((bound * gear, f"its forcerange ±{bound:g} x gear {gear:g}"))
    if (m.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED and m.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE
            and m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE and m.actuator_ctrllimited[a]):
        bound, gain = float(np.abs(m.actuator_ctrlrange[a]).max()), abs(float(m.actuator_gainprm[a, 0]))
        cands.append((bound * gain * gear, f"its ctrlrange ±{bound:g} x gain {gain:g} x gear {gear:g}"))
    return min(cands) if cands else (None, "")


def _tendon_joints(m: mujoco.MjModel, t: int) -> list[tuple[int, float]] | None:
    """A fixed tendon's (joint id, coef) list; None for a spatial tendon."""
    adr, num = m.tendon_adr[t], m.tendon_num[t]
    if any(m.wrap_type[w] != mujoco.mjtWrap.mjWRAP_JOINT for w in range(adr, adr + num)):
        return None
    return [(int(m.wrap_objid[w]), float(m.wrap_prm[w])) for w in range(adr, adr + num)]


@dataclasses.dataclass(frozen=True)
class _Drive:
    """One actuator's pull on one joint."""

    actuator: int
    limit: float | None  # [N m] on the joint
    why: str
    one_to_one: bool  # a joint actuator (not through a tendon)


def _drives(m: mujoco.MjModel, hinges: list[int]) -> tuple[dict[int, list[_Drive]], list[str]]:
    """Joint -> the actuators that drive it; and notes on actuators that drive no hand hinge."""
    drives: dict[int, list[_Drive]] = {j: [] for j in hinges}
    notes = []
    for a in range(m.nu):
        trn, target = int(m.actuator_trntype[a]), int(m.actuator_trnid[a, 0])
        limit, why = actuator_limit(m, a)
        if trn in (_TRN.mjTRN_JOINT, _TRN.mjTRN_JOINTINPARENT) and target in drives:
            drives[target].append(_Drive(a, limit, why, True))
        elif trn == _TRN.mjTRN_TENDON and (joints := _tendon_joints(m, target)) is not None:
            for j, coef in joints:
                if j in drives:
                    lim = None if limit is None else limit * abs(coef)
                    drives[j].append(_Drive(a, lim, f"{why} x |coef| {abs(coef):g}" if why else "", False))
        else:
            notes.append(f"actuator {_named(m, _OBJ.mjOBJ_ACTUATOR, a)!r} ({describe_actuator(m, a)} on a "
                         f"{_enum_word(_TRN, trn)}) drives no hand hinge directly: removed")
    return drives, notes


def _joint_limit(m: mujoco.MjModel, j: int, drives: list[_Drive], torque_limit: float | None
                 ) -> tuple[float | None, str]:
    """A joint's motor limit [N m] and where it comes from: the largest of its actuators' limits, else the joint's
    own actuatorfrcrange, else `torque_limit`; capped by the joint's actuatorfrcrange."""
    known = [d for d in drives if d.limit is not None]
    if known:
        best = max(known, key=lambda d: d.limit)
        limit, why = best.limit, f"{_named(m, _OBJ.mjOBJ_ACTUATOR, best.actuator)!r}: {best.why}"
    elif m.jnt_actfrclimited[j]:
        limit, why = None, ""
    elif torque_limit is not None:
        limit, why = float(torque_limit), "the torque_limit given"
    else:
        return None, ""
    if m.jnt_actfrclimited[j]:
        bound = float(np.abs(m.jnt_actfrcrange[j]).max())
        if limit is None or bound < limit:
            limit, why = bound, f"the joint's actuatorfrcrange ±{bound:g}"
    return limit, why


def _set_motor(a, joint: str, limit: float, main) -> None:
    """Make spec actuator `a` a torque motor on `joint`: gear 1, ctrlrange ±limit, no force limit [N m]."""
    a.set_to_motor()
    a.classname = main
    a.inheritrange = 0.0
    a.trntype = _TRN.mjTRN_JOINT
    a.target, a.refsite, a.slidersite = joint, "", ""
    a.gear = [1.0, 0, 0, 0, 0, 0]
    a.ctrllimited, a.ctrlrange = mujoco.mjtLimited.mjLIMITED_TRUE, [-limit, limit]
    a.forcelimited, a.forcerange = mujoco.mjtLimited.mjLIMITED_FALSE, [0.0, 0.0]
    a.actlimited, a.actrange = mujoco.mjtLimited.mjLIMITED_FALSE, [0.0, 0.0]
    a.damping, a.armature = np.zeros_like(np.asarray(a.damping)), 0.0
    a.gainprm = np.r_[1.0, np.zeros(len(a.gainprm) - 1)]
    a.biasprm = np.zeros(len(a.biasprm))
    a.dynprm = np.r_[1.0, np.zeros(len(a.dynprm) - 1)]


def motors(spec: mujoco.MjSpec, m: mujoco.MjModel, hinges: list[int], torque_limit: float | None) -> list[str]:
    """Give every hinge exactly one torque motor (gear 1, ctrlrange ±limit): a joint's only joint actuator is made
    that motor in place (its name and the sensors on it kept), the others (servos through tendons, extra ones, ones
    on sites or bodies) are removed, and joints left without become a new motor '<joint>_motor'. `m`: the spec
    compiled; `hinges`: the hand's joints. Raises `HandImportError` naming every joint whose limit is unknown."""
    drives, lines = _drives(m, hinges)
    limits, missing = {}, {}
    for j in hinges:
        limit, why = _joint_limit(m, j, drives[j], torque_limit)
        if limit is None or not limit > 0:
            reason = "; ".join(f"{describe_actuator(m, d.actuator)} without forcerange" for d in drives[j])
            missing.setdefault(reason or "no actuator", []).append(_named(m, _OBJ.mjOBJ_JOINT, j))
        limits[j] = (limit, why)
    if missing:
        what = "; ".join(f"joints {', '.join(js)} ({len(js)}): {why}" for why, js in missing.items())
        raise HandImportError(f"torque_limit: the motor limits are unknown for {what}: give the torque limit [N m] "
                              "(torque_limit=...; on the command line --torque-limit N_M), or a forcerange to those "
                              "actuators")
    keep, convert = {}, {}
    for j in hinges:
        sole = [d for d in drives[j] if d.one_to_one]
        if len(sole) == 1 and len(drives[j]) == 1 and is_plain_motor(m, sole[0].actuator):
            keep[j] = sole[0].actuator
        elif len(sole) == 1:
            convert[j] = sole[0].actuator
    used = set(keep.values()) | set(convert.values())
    names = {a: _named(m, _OBJ.mjOBJ_ACTUATOR, a) for a in range(m.nu)}
    specs = by_id(spec.actuators)
    main = spec.default
    for j, a in convert.items():
        limit, why = limits[j]
        joint = _named(m, _OBJ.mjOBJ_JOINT, j)
        lines.append(f"actuator {names[a]!r} ({describe_actuator(m, a)} on joint {joint!r}) -> motor, ctrlrange "
                     f"±{limit:.4g} N m ({why})")
        _set_motor(specs[a], joint, limit, main)
    removed = [a for a in range(m.nu) if a not in used]
    before = inventory(spec)
    delete(spec, [specs[a] for a in removed])
    for a in removed:
        joints = sorted({_named(m, _OBJ.mjOBJ_JOINT, j) for j in hinges if any(d.actuator == a for d in drives[j])})
        tendon = m.actuator_trntype[a] == _TRN.mjTRN_TENDON
        via = f" through tendon {_named(m, _OBJ.mjOBJ_TENDON, m.actuator_trnid[a, 0])!r}" if tendon else ""
        if joints:
            lines.append(f"actuator {names[a]!r} ({describe_actuator(m, a)}{via}) removed; its joints "
                         f"{', '.join(map(repr, joints))} get motors of their own")
    sensors = before["sensors"] - inventory(spec)["sensors"]
    if sensors:
        lines.append(f"sensors on removed actuators, removed: {', '.join(sorted(n or '(unnamed)' for n in sensors))}")
    taken = {a.name for a in spec.actuators if a.name}
    for j in hinges:
        if j in keep or j in convert:
            continue
        limit, why = limits[j]
        joint = _named(m, _OBJ.mjOBJ_JOINT, j)
        a = spec.add_actuator()
        a.name = _unique(f"{joint}_motor", taken)
        _set_motor(a, joint, limit, main)
        lines.append(f"joint {joint!r}: new motor {a.name!r}, ctrlrange ±{limit:.4g} N m ({why})")
    return lines


def joint_dynamics(spec: mujoco.MjSpec, m: mujoco.MjModel, hinges: list[int]) -> list[str]:
    """Set every hand hinge's damping, armature and friction loss to `hand_lib.JOINT_DAMPING`, `JOINT_ARMATURE`,
    `JOINT_FRICTIONLOSS` (and its higher-order damping to 0); one change line per group of equal old values."""
    new = (hand_lib.JOINT_DAMPING, hand_lib.JOINT_ARMATURE, hand_lib.JOINT_FRICTIONLOSS)
    groups: dict[tuple, list[str]] = {}
    specs = by_id(spec.joints)
    for j in hinges:
        dof = m.jnt_dofadr[j]
        poly = float(np.abs(m.dof_dampingpoly[dof]).max()) if hasattr(m, "dof_dampingpoly") else 0.0
        old = (float(m.dof_damping[dof]), float(m.dof_armature[dof]), float(m.dof_frictionloss[dof]), poly)
        e = specs[j]
        damping = np.zeros_like(np.asarray(e.damping, np.float64))
        damping[0] = new[0]
        e.damping, e.armature, e.frictionloss = damping, new[1], new[2]
        if old != (*new, 0.0):
            groups.setdefault(old, []).append(_named(m, _OBJ.mjOBJ_JOINT, j))
    springs = [_named(m, _OBJ.mjOBJ_JOINT, j) for j in hinges if m.jnt_stiffness[j]]
    lines = [f"NOTE: joints {', '.join(springs)} have springs (stiffness): kept; the physics controller was tuned "
             "without them"] if springs else []
    for old, joints in groups.items():
        parts = [f"{n} {o:g} -> {v:g}" for n, o, v in zip(("damping", "armature", "frictionloss"), old, new) if o != v]
        parts += [f"higher-order damping {old[3]:g} -> 0"] if old[3] else []
        lines.append(f"joints {', '.join(joints)} ({len(joints)}): {', '.join(parts)} (the values the physics "
                     "controller is tuned for)")
    return lines


def equality_notes(m: mujoco.MjModel) -> list[str]:
    """The equality constraints and the tendon springs kept (couplings and forces the surrogate does not model)."""
    stiff = [float(np.ravel(m.tendon_stiffness[t])[0]) for t in range(m.ntendon)]
    out = [f"kept: tendon {_named(m, _OBJ.mjOBJ_TENDON, t)!r}, a spring of {k:g} N/m: the physics keeps its force on "
           "the joints, which neither the surrogate nor the controller's gravity compensation knows; remove it (its "
           "<spatial> or <fixed>; all of them: --drop-tendons) if the real hand's motors cancel it"
           for t, k in enumerate(stiff) if k > 0]
    for e in range(m.neq):
        kind = _enum_word(mujoco.mjtEq, m.eq_type[e])
        objs = {"joint": _OBJ.mjOBJ_JOINT, "tendon": _OBJ.mjOBJ_TENDON}.get(kind)
        between = (f" between {kind}s {_named(m, objs, m.eq_obj1id[e])!r} and {_named(m, objs, m.eq_obj2id[e])!r}"
                   if objs is not None else "")
        out.append(f"kept: equality {_named(m, _OBJ.mjOBJ_EQUALITY, e)!r} ({kind}{between}); the physics keeps the "
                   "coupling, the surrogate treats every joint as independent")
    return out


def _same(name: str) -> str:
    return name


def strip_prefix(spec: mujoco.MjSpec, palm: str) -> tuple[object, list[str]]:
    """If the finger names (the palm's child bodies' names up to the first '_') collide, strip the common prefix of
    those bodies' names (up to its last '_') from every name that starts with it. The renaming (old name -> new
    name) and the change lines."""
    firsts = [b.name for b in spec.body(palm).bodies]
    fingers = [n.split("_")[0] for n in firsts]
    if len(set(fingers)) == len(fingers):
        return _same, []
    common = os.path.commonprefix(firsts)
    prefix = common[:common.rfind("_") + 1]
    if not prefix:
        return _same, [f"NOTE: the fingers' names collide ({', '.join(fingers)}: the names of the bodies below the "
                       "palm up to the first '_'); rename those bodies so that each finger has its own"]
    lists = [getattr(spec, k) for k in (*_LISTED, "cameras", "lights")]
    olds = [[e.name for e in items if e.name] for items in lists]
    for names in olds:
        new = [n.removeprefix(prefix) for n in names]
        if len(set(new)) < len(new) or any(not n for n in new):
            return _same, [f"NOTE: the fingers' names collide ({', '.join(fingers)}); stripping the prefix "
                           f"{prefix!r} would make two names equal, so nothing was renamed: rename the bodies below "
                           "the palm"]

    def fn(name: str) -> str:
        return name.removeprefix(prefix) if name and name.startswith(prefix) else name

    n = sum(1 for names in olds for x in names if x.startswith(prefix))
    _rename(spec, fn)
    now = [fn(x).split("_")[0] for x in firsts]
    still = "" if len(set(now)) == len(now) else "; NOTE: they still collide: rename the bodies below the palm"
    return fn, [f"names: the prefix {prefix!r} stripped from {n} names (bodies, joints, geoms, sites, actuators, "
                f"sensors, tendons): the finger names ({', '.join(fingers)}) collided; now {', '.join(now)}{still}"]


@dataclasses.dataclass(frozen=True)
class _Key:
    name: str
    time: float
    qpos: dict[str, np.ndarray]  # joint name -> its qpos
    qvel: dict[str, np.ndarray]  # joint name -> its qvel
    ctrl_zero: bool


def read_keys(m: mujoco.MjModel) -> list[_Key]:
    """The model's keyframes, by joint name."""
    out = []
    for k in range(m.nkey):
        qpos, qvel = {}, {}
        for j in range(m.njnt):
            n = mujoco.mj_id2name(m, _OBJ.mjOBJ_JOINT, j)
            if not n:
                continue
            width = {0: 7, 1: 4}.get(int(m.jnt_type[j]), 1)
            qpos[n] = m.key_qpos[k, m.jnt_qposadr[j]:m.jnt_qposadr[j] + width].copy()
            dw = {0: 6, 1: 3}.get(int(m.jnt_type[j]), 1)
            qvel[n] = m.key_qvel[k, m.jnt_dofadr[j]:m.jnt_dofadr[j] + dw].copy()
        out.append(_Key(mujoco.mj_id2name(m, _OBJ.mjOBJ_KEY, k) or f"#{k}", float(m.key_time[k]), qpos, qvel,
                        not np.any(m.key_ctrl[k]) if m.nu else True))
    return out


def write_keys(spec: mujoco.MjSpec, m: mujoco.MjModel, keys: list[_Key], rename) -> list[str]:
    """Add back the keyframes whose controls were all 0 (they fit any motor; the others set the old actuators'
    targets), their joint angles mapped by name onto `m` (the final model); the change lines."""
    lines = []
    for k in keys:
        if not k.ctrl_zero:
            lines.append(f"keyframe {k.name!r} removed: its ctrl (the old actuators' inputs) does not fit the motors")
            continue
        qpos, qvel = m.qpos0.copy(), np.zeros(m.nv)
        by_new = {rename(n): n for n in k.qpos}
        for j in range(m.njnt):
            old = by_new.get(mujoco.mj_id2name(m, _OBJ.mjOBJ_JOINT, j))
            if old is not None:
                qpos[m.jnt_qposadr[j]] = k.qpos[old][0]
                qvel[m.jnt_dofadr[j]] = k.qvel[old][0]
        key = spec.add_key()
        key.name, key.time, key.qpos, key.qvel = ("" if k.name.startswith("#") else k.name), k.time, qpos, qvel
        key.ctrl = np.zeros(m.nu)
        lines.append(f"keyframe {k.name!r} kept: its joint angles (its ctrl was 0)")
    return lines


def palm_facing(m: mujoco.MjModel, palm: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Which way the palmar side faces, in the world: (3,) a unit vector, estimated as the fingertips' mean
    displacement when every joint goes from qpos0 to the middle of its range (the flexion side), less its part along
    the fingers; and (3,) the fingers' mean direction (base -> tip). None if the fingers do not move."""
    d = mujoco.MjData(m)
    tips = [b for b in _hand_bodies(m, palm) if not any(m.body_parentid[c] == b for c in range(m.nbody))]
    firsts = [b for b in range(m.nbody) if m.body_parentid[b] == palm]
    if not tips or not firsts:
        return None
    d.qpos[:] = m.qpos0
    mujoco.mj_kinematics(m, d)
    p0, base = d.xpos[tips].copy(), d.xpos[firsts].mean(0)
    mid = np.where(m.jnt_limited, m.jnt_range.mean(1), 0.0)
    for j in range(m.njnt):
        d.qpos[m.jnt_qposadr[j]] = mid[j]
    mujoco.mj_kinematics(m, d)
    along = (p0 - base).mean(0)
    along /= max(np.linalg.norm(along), 1e-12)
    move = (d.xpos[tips] - p0).mean(0)
    side = move - (move @ along) * along
    if np.linalg.norm(side) < 1e-6:
        return None
    return side / np.linalg.norm(side), along


def _axis_words(v: np.ndarray) -> str:
    k = int(np.argmax(np.abs(v)))
    return f"{'+' if v[k] > 0 else '-'}{'xyz'[k]}"


def palm_pose(spec: mujoco.MjSpec, palm: str, pos, quat) -> list[str]:
    """Set the palm's pose in the world (pos (3,) [m], quat (4,) w x y z; None keeps the file's). Change lines."""
    lines = []
    body = spec.body(palm)
    if pos is not None:
        pos = np.asarray(pos, np.float64)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise HandImportError(f"palm_pos: {np.asarray(pos).tolist()} must be 3 finite numbers [m]")
        body.pos = pos
        lines.append(f"palm {palm!r}: position set to {_fmt(pos)} m")
    if quat is not None:
        q = np.asarray(quat, np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or not np.linalg.norm(q) > 0:
            raise HandImportError(f"palm_quat: {np.asarray(quat).tolist()} must be 4 finite numbers (w x y z), not "
                                  "all 0")
        _set_pose(body, body.pos, q)
        lines.append(f"palm {palm!r}: orientation set to quat {_fmt(q / np.linalg.norm(q))}")
    return lines


def facing_lines(m: mujoco.MjModel, palm: int, advise: bool = True) -> list[str]:
    """The palm's pose in the world and where its palmar side faces, in words (`advise`: and how to place it)."""
    name = _named(m, _OBJ.mjOBJ_BODY, palm)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    line = f"palm {name!r} at {_fmt(d.xpos[palm])} m, quat {_fmt(d.xquat[palm])}"
    est = palm_facing(m, palm)
    if est is None:
        line += "; which way its palmar side faces could not be told (the fingertips do not move)"
    else:
        side, along = est
        local = d.xmat[palm].reshape(3, 3).T @ side
        line += (f"; its palmar side faces {_fmt(side, digits=2)} (about world {_axis_words(side)}; palm frame "
                 f"{_axis_words(local)}), its fingers point {_fmt(along, digits=2)} (estimated from where the "
                 "fingertips move when the joints go to the middle of their ranges)")
    if advise:
        line += (". Place it over the tool, its palm facing down (-z, as models/allegro/hand.xml's) or its fingers "
                 "pointing down (as models/hand.xml's): palm_pos / palm_quat")
    return [line]


def self_contacts(m: mujoco.MjModel) -> set[tuple[str, str]]:
    """The body pairs of the hand in contact at qpos0 (by body name)."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    out = set()
    for c in d.contact[:d.ncon]:
        a, b = (_named(m, _OBJ.mjOBJ_BODY, m.geom_bodyid[g]) for g in (c.geom1, c.geom2))
        out.add(tuple(sorted((a, b))))
    return out


def _compile(spec: mujoco.MjSpec, what: str) -> mujoco.MjModel:
    try:
        return spec.compile()
    except Exception as e:  # noqa: BLE001
        raise HandImportError(f"MuJoCo cannot compile the hand {what}: {e}") from None

