"""`import_hand(src, ...)`: the steps in order -> `Imported`, the edited spec and its change list, which writes itself.

`Imported.write(out_dir)` writes ``out_dir/hand.xml`` (its header comment: the source, the changes, what the user
must still add) and copies the mesh and texture files it uses to ``out_dir/assets/``. The optional edits that need
the finished hand are here too: the contact links and their sites (`contact_sites`) and the IK start (`ik_start`,
one angle per joint [rad]).
"""
from __future__ import annotations

import dataclasses
import os
import pathlib
import shutil

import mujoco
import numpy as np

from gsp_jax.importer.motors import (_compile, equality_notes, facing_lines, joint_dynamics, motors, palm_pose,
                                     read_keys, self_contacts, strip_prefix, write_keys)
from gsp_jax.importer.spec import HandImportError, _fmt, _named
from gsp_jax.importer.steps import (Replacement, _hand_bodies, _load, _to_replace, check_files, check_joints,
                                    choose_palm, drop_unused_meshes, mesh_files, name_joints, pin_inertia,
                                    remove_tendons, remove_visual, replace_geoms, reroot, reset_option, skeleton)
from gsp_jax.model import hand as hand_lib

_OBJ = mujoco.mjtObj
_GEOM = mujoco.mjtGeom


@dataclasses.dataclass(frozen=True, eq=False)
class Imported:
    """An imported hand: the edited spec, the change list, the replacements made and where the source was."""

    spec: mujoco.MjSpec
    changes: list[str]
    source: pathlib.Path
    palm: str
    replacements: tuple[Replacement, ...] = ()

    def next_steps(self) -> list[str]:
        """What the user must still add before the hand is a model (docs/your-model.md); what the file already has
        is left out."""
        m = self.spec.compile()
        palm = m.body(self.palm).id
        leaves = [_named(m, _OBJ.mjOBJ_BODY, b) for b in _hand_bodies(m, palm)
                  if not any(m.body_parentid[c] == b for c in range(m.nbody))]
        joints = [_named(m, _OBJ.mjOBJ_JOINT, j) for j in range(m.njnt)]
        links = hand_lib._text(m, "gsp_contact_links", "").split()
        start = hand_lib._numeric(m, "gsp_ik_start")
        out = []
        if not links:
            out.append(f"custom text gsp_contact_links: the contact links in grasp order (e.g. the fingertip bodies: "
                       f"{' '.join(leaves)})")
        if not links or any(hand_lib._site(m, f"contact_{n}") < 0 for n in links):
            out.append("a sphere or capsule site contact_<link> on each contact link's body (the part that touches)")
        if start is None or len(start) != len(joints):
            out.append(f"custom numeric gsp_ik_start: the IK's start, {len(joints)} angles in joint order: "
                       f"{' '.join(joints)}")
        return out + ["a scene.xml beside hand.xml: <include file=\"hand.xml\"/>, the tool (the one free body, its "
                      "sites opt_<link>_<k>), a table (one plane in the worldbody) and the scene's <option "
                      "timestep=...>", "then: python -m experiments check-model scene.xml"]

    def header(self) -> str:
        """The written file's header comment's text: source, changes, what is left to do."""
        lines = [f"gsp_jax hand imported from {self.source} by gsp_jax.importer (python -m experiments import-hand)",
                 "", "Changes:"]
        lines += [f"  * {c}" for c in self.changes]
        if self.replacements:
            lines += ["", "Over-cover: how far a fitted capsule or sphere reaches beyond the geoms it replaced (the "
                      "largest distance from a point of its surface to the nearest of them)."]
        lines += ["", "Still to add (docs/your-model.md):"] + [f"  * {s}" for s in self.next_steps()]
        return "\n".join(_wrap(line, 116) for line in lines).replace("--", "- -")

    def write(self, out_dir) -> pathlib.Path:
        """Write ``out_dir/hand.xml`` (the header comment, then the spec) and copy every mesh and texture file it
        uses to ``out_dir/assets/``; returns the path of hand.xml."""
        out_dir = pathlib.Path(out_dir)
        assets = out_dir / "assets"
        spec = self.spec.copy()
        sources = mesh_files(self.spec)
        taken: set[str] = set()
        copies = []
        for kind in ("meshes", "textures"):
            for e in getattr(spec, kind):
                if not e.file:
                    continue
                src = sources[e.name or e.file]
                if not src.is_file():
                    raise HandImportError(f"{kind[:-1]} {e.name!r}: file {str(src)!r} is missing")
                dest = _unique_file(src.name, taken)
                copies.append((src, dest))
                e.file = dest
        spec.compiler.meshdir = spec.compiler.texturedir = "assets"
        spec.meshdir = spec.texturedir = "assets"
        out_dir.mkdir(parents=True, exist_ok=True)
        if copies:
            assets.mkdir(exist_ok=True)
        for src, dest in copies:
            if src.resolve() != (assets / dest).resolve():
                shutil.copyfile(src, assets / dest)
        spec.modelfiledir = str(out_dir.resolve()) + os.sep  # to_xml compiles: the copies are read from there
        xml = spec.to_xml()
        path = out_dir / "hand.xml"
        path.write_text(f"<!--\n{_indent(self.header())}\n-->\n{xml}")
        return path


def _unique_file(name: str, taken: set[str]) -> str:
    stem, suffix = os.path.splitext(name)
    out, k = name, 2
    while out in taken:
        out, k = f"{stem}_{k}{suffix}", k + 1
    taken.add(out)
    return out


def _indent(text: str) -> str:
    return "\n".join(("  " + line) if line else "" for line in text.splitlines())


def _wrap(line: str, width: int) -> str:
    """Wrap one line at spaces to `width` characters, continuation lines indented under the text."""
    if len(line) <= width:
        return line
    lead = line[:len(line) - len(line.lstrip(" "))]
    indent = " " * (len(line) - len(line.lstrip(" *")) + 2)
    out, cur = [], lead
    for word in line.strip().split(" "):
        if cur.strip() and len(cur) + 1 + len(word) > width:
            out.append(cur)
            cur = indent + word
        else:
            cur = f"{cur} {word}" if cur.strip() else cur + word
    out.append(cur)
    return "\n".join(out)


def _changing_bodies(spec: mujoco.MjSpec, m: mujoco.MjModel, palm: int, drop_visual: bool
                     ) -> tuple[list[int], list[str]]:
    """The bodies whose geoms change (their inertia is pinned first) and the change line for compiler settings that
    would recompute every body's inertia from its geoms (then every body's is pinned)."""
    bodies = set(_to_replace(m, palm))
    if drop_visual:
        bodies |= {int(m.geom_bodyid[g]) for g in range(m.ngeom) if not hand_lib.collides(m, g)}
    if spec.compiler.inertiafromgeom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE or \
            spec.compiler.settotalmass > 0:
        spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO
        spec.compiler.settotalmass = -1
        return list(range(1, m.nbody)), ["compiler: inertiafromgeom 'true' / settotalmass dropped (they recompute "
                                         "every body's inertia); every body's inertia written as its <inertial>"]
    return sorted(bodies), []


BARE_MASS = 0.005  # [kg] a moving body left with no geom and no mass (`mass_from_collision`): a knuckle's few grams
BARE_RADIUS = 0.01  # [m] ... its inertia: a solid ball of this radius


def mass_from_collision(spec: mujoco.MjSpec) -> list[str]:
    """Bodies left without mass (their mass came from visual geoms that were dropped, their colliding geoms set to
    mass 0, as Menagerie's Allegro's are) take it from their colliding geoms' volume at those geoms' density; a
    moving body left with no geom at all gets `BARE_MASS` (MuJoCo compiles no moving body without mass). The
    change lines."""
    lines = []
    for body in spec.bodies:
        if body.name == "world" or body.explicitinertial or not body.geoms:
            continue
        geoms = [g for g in body.geoms if g.contype or g.conaffinity]
        if geoms and all(g.mass == 0 for g in body.geoms):
            for g in geoms:
                g.mass = float("nan")  # MuJoCo's unset value: the mass comes from the density
            lines.append(f"body {body.name!r}: no mass left (it came from its visual geoms); now from its colliding "
                         f"geoms' volume at density {', '.join(sorted({f'{g.density:g}' for g in geoms}))} kg/m^3")
    for body in spec.bodies:  # moving bodies left with no geom at all: MuJoCo refuses a moving body without mass
        if body.name == "world" or body.explicitinertial or body.geoms or not body.joints:
            continue
        body.mass, body.ipos, body.iquat = BARE_MASS, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
        body.inertia = np.full(3, 0.4 * BARE_MASS * BARE_RADIUS**2)
        body.fullinertia = np.full(6, np.nan)
        body.explicitinertial = True
        lines.append(f"body {body.name!r}: no mass left (its only geoms were visual, their mesh files missing) and it "
                     f"moves: given {BARE_MASS * 1e3:g} g at its origin, the inertia of a ball "
                     f"{BARE_RADIUS * 1e3:g} mm in radius (MuJoCo refuses a moving body without mass); write its "
                     "<inertial> if you know it")
    return lines


def contact_sites(spec: mujoco.MjSpec, m: mujoco.MjModel, palm: int, links) -> list[str]:
    """Write custom text ``gsp_contact_links`` and a site ``contact_<link>`` on each link body (`links`: body names
    in grasp order): on a finger's deepest link (its tip) a sphere at the far end of the body's colliding capsule or
    sphere that reaches farthest from its joint, with its radius; on another link a capsule site along its largest.
    The change lines."""
    links = list(links)
    hand = set(_hand_bodies(m, palm))
    lines, depth, finger = [], {}, {}
    for name in links:
        b = mujoco.mj_name2id(m, _OBJ.mjOBJ_BODY, name)
        if b < 0 or b not in hand or b == palm:
            raise HandImportError(f"contact_links: {name!r} is not a body of the hand below its palm")
        chain = [b]
        while m.body_parentid[chain[-1]] != palm:
            chain.append(int(m.body_parentid[chain[-1]]))
        depth[name], finger[name] = len(chain), chain[-1]
    if len(set(links)) != len(links):
        raise HandImportError(f"contact_links: {links} names a body twice")
    for name in links:
        b = m.body(name).id
        round_ = [g for g in range(m.ngeom) if m.geom_bodyid[g] == b and hand_lib.collides(m, g)
                  and int(m.geom_type[g]) in (int(_GEOM.mjGEOM_CAPSULE), int(_GEOM.mjGEOM_SPHERE))]
        if not round_:
            raise HandImportError(f"contact_links: body {name!r} has no colliding capsule or sphere to put its "
                                  "contact site on")
        tip = depth[name] == max(depth[n] for n in links if finger[n] == finger[name])

        def far(g) -> float:  # how far the geom reaches from the body's joint (its origin)
            axis = hand_lib._quat_to_mat(m.geom_quat[g])[:, 2]
            half = m.geom_size[g, 1] if int(m.geom_type[g]) == int(_GEOM.mjGEOM_CAPSULE) else 0.0
            return max(float(np.linalg.norm(m.geom_pos[g] + s * half * axis)) for s in (-1.0, 1.0)) + m.geom_size[g, 0]

        # a tip: the geom that reaches farthest (with one capsule per geom, `--per-geom`, the fingertip's, not the
        # phalanx's largest); another link: its largest geom
        g = max(round_, key=far) if tip else max(
            round_, key=lambda g: m.geom_size[g, 0] ** 2 * (4 / 3 * m.geom_size[g, 0] + 2 * m.geom_size[g, 1]))
        r, half = float(m.geom_size[g, 0]), float(m.geom_size[g, 1])
        capsule = int(m.geom_type[g]) == int(_GEOM.mjGEOM_CAPSULE)
        axis = hand_lib._quat_to_mat(m.geom_quat[g])[:, 2]
        body = spec.body(name)
        if tip or not capsule:
            ends = [m.geom_pos[g] + s * half * axis for s in (-1.0, 1.0)] if capsule else [m.geom_pos[g]]
            pos = max(ends, key=lambda e: float(np.linalg.norm(e)))  # the end farther from the body's joint
            body.add_site(name=f"contact_{name}", type=_GEOM.mjGEOM_SPHERE, size=[r, 0, 0], pos=pos)
            lines.append(f"site 'contact_{name}' (a {'tip' if tip else 'link'}): sphere r {r * 1e3:.1f} mm at "
                         f"{_fmt(pos, ' mm', 1e3)} on body {name!r}, the far end of its geom")
        else:
            body.add_site(name=f"contact_{name}", type=_GEOM.mjGEOM_CAPSULE, size=[r, half, 0], pos=m.geom_pos[g],
                          quat=m.geom_quat[g])
            lines.append(f"site 'contact_{name}': capsule r {r * 1e3:.1f} mm, half-length {half * 1e3:.1f} mm along "
                         f"body {name!r}'s geom")
    spec.add_text(name="gsp_contact_links", data=" ".join(links))
    return [f"custom text gsp_contact_links: {' '.join(links)}"] + lines


def ik_start(spec: mujoco.MjSpec, m: mujoco.MjModel, hinges: list[int], start) -> list[str]:
    """Write custom numeric ``gsp_ik_start`` (one angle per hand joint [rad], clipped to nothing: checked against
    the joints' ranges). The change lines."""
    q = np.asarray(start, np.float64)
    names = [_named(m, _OBJ.mjOBJ_JOINT, j) for j in hinges]
    if q.shape != (len(hinges),) or not np.all(np.isfinite(q)):
        raise HandImportError(f"ik_start: {np.ravel(q).tolist()} must be {len(hinges)} finite angles [rad], one per "
                              f"joint: {' '.join(names)}")
    lo, hi = m.jnt_range[hinges].T
    out = [f"{n} {v:g} not in [{a:g}, {b:g}]" for n, v, a, b, lim in zip(names, q, lo, hi, m.jnt_limited[hinges])
           if lim and not a <= v <= b]
    if out:
        raise HandImportError(f"ik_start: outside the joint ranges: {'; '.join(out)}")
    spec.add_numeric(name="gsp_ik_start", data=q.tolist(), size=len(q))
    return [f"custom numeric gsp_ik_start: {' '.join(f'{v:g}' for v in q)}"]


def import_hand(src, *, torque_limit: float | None = None, palm: str | None = None, palm_pos=None, palm_quat=None,
                drop_visual: bool = False, per_geom: bool = False, contact_links=None, start=None,
                drop_missing: bool = False, drop_tendons: bool = False) -> Imported:
    """A published MJCF hand file -> an `Imported` hand that follows the conventions (the module's docstring lists
    the edits). `torque_limit` [N m]: the motor limit of joints whose actuators give none (no forcerange); `palm`:
    the hand's root body (default: the world's child with the most hinges below it); `palm_pos` (3,) [m] /
    `palm_quat` (4,) w x y z: the palm's pose in the world; `drop_visual`: remove the visual geoms; `drop_missing`:
    remove the collision geoms whose mesh files are missing (reported; they collide with nothing then);
    `drop_tendons`: remove every tendon (a tendon-driven hand's paths and springs: its joints get motors);
    `per_geom`: one capsule per replaced geom instead of one per body; `contact_links` (body names, grasp order):
    write them and their contact sites (`contact_sites`); `start` (J,) [rad]: the IK start (`ik_start`). Raises
    `HandImportError` (a ValueError) naming the field."""
    if torque_limit is not None and not (np.isfinite(torque_limit) and torque_limit > 0):
        raise HandImportError(f"torque_limit: {torque_limit!r} must be a positive number [N m]")
    src = pathlib.Path(src).expanduser().resolve()
    spec = _load(src)
    sk = skeleton(spec)
    keys = read_keys(sk)
    for k in list(spec.keys):
        spec.delete(k)
    palm = choose_palm(spec, sk, palm)
    changes = reroot(spec, sk, palm)
    rename, lines = strip_prefix(spec, palm)
    palm = rename(palm)
    changes += lines + reset_option(spec) + (remove_tendons(spec) if drop_tendons else [])
    changes += check_files(spec, drop_visual, palm, drop_missing)
    changes += mass_from_collision(spec)
    m = _compile(spec, "after moving the palm")
    pid = m.body(palm).id
    hinges = [j for j in range(m.njnt) if hand_lib._is_below(m, int(m.jnt_bodyid[j]), pid)]
    notes = check_joints(m, pid)
    lines = name_joints(spec, m, hinges)
    if lines:
        changes += lines
        m = _compile(spec, "after naming its joints")
    contacts = self_contacts(m)
    motor_lines = motors(spec, m, hinges, torque_limit)  # before the slow fits: a missing torque limit stops here
    bodies, lines = _changing_bodies(spec, m, pid, drop_visual)
    changes += lines + pin_inertia(spec, m, bodies)
    replacements, lines = replace_geoms(spec, m, pid, per_geom)
    changes += lines + (remove_visual(spec, m) if drop_visual else []) + drop_unused_meshes(spec)
    changes += motor_lines + joint_dynamics(spec, m, hinges) + equality_notes(m)
    changes += palm_pose(spec, palm, palm_pos, palm_quat)
    edited = _compile(spec, "after its edits")
    if contact_links:
        changes += contact_sites(spec, edited, edited.body(palm).id, [rename(n) for n in contact_links])
    if start is not None:
        changes += ik_start(spec, edited, [edited.joint(_named(m, _OBJ.mjOBJ_JOINT, j)).id for j in hinges], start)
    changes += write_keys(spec, _compile(spec, "after its edits"), keys, rename)
    m = _compile(spec, "with its keyframes")
    new = self_contacts(m) - contacts
    if new:
        pairs = ", ".join("-".join(p) for p in sorted(new))
        changes.append(f"NOTE: at qpos0 the new geoms touch between bodies {pairs} (add <contact><exclude> pairs if "
                       "they should not)")
    changes += notes + facing_lines(m, pid, palm_pos is None and palm_quat is None)
    return Imported(spec, changes, src, palm, tuple(replacements))
