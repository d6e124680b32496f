"""A published MJCF hand -> a hand file that follows the model conventions (docs/your-model.md).

`import_hand(src, ...)` reads a hand file (e.g. MuJoCo Menagerie's LEAP or Shadow hand: box and mesh collision
geoms, position servos, tendons, a forearm and wrist) and edits its `mujoco.MjSpec` into a hand the project can
load, listing every change in plain words:

* the palm (the world's child with the most hinges below it, or a named body deeper in the tree) becomes the
  world's child at its pose in the file's zero configuration; what is above it (forearm, wrist joints and their
  geoms, actuators, sensors, excludes) and what else the world holds is dropped;
* every colliding geom below the palm that is not a capsule or a sphere is replaced by a fitted capsule (or
  sphere) that covers it, one per body (or one per geom), its contact attributes kept and the body's inertia pinned.
  The fit covers points whose convex hull contains the geoms (box corners, mesh vertices, polytopes around cylinders
  and ellipsoids): for each of the points' three principal directions, the axis line through the centre of the
  smallest circle around their projection, radii from that circle's (the smallest possible) up to the points'
  largest distance from their centroid, each with the shortest segment that covers every point; of those, the one
  with the least *over-cover* (the largest distance from a point of its surface to the replaced geoms: how far it
  reaches beyond them), the smallest by volume among those within `SEARCH_TOLERANCE` of it;
* every actuator that is not a plain joint torque motor becomes a `<motor>` on its joint (a tendon actuator one per
  joint of the tendon), with the actuator's force limit as its control range; every hinge gets exactly one motor;
* the hinges' damping, armature and friction loss become the values the physics controller is tuned for
  (`gsp_jax.hand.JOINT_DAMPING`, ...);
* a common name prefix that makes the finger names collide ("rh_") is stripped, the hand's `<option>` is dropped
  (the scene sets the physics), keyframes whose controls no longer fit are dropped.

`Imported.write(out_dir)` writes ``out_dir/hand.xml`` (its header comment: the changes, the source, what the user
must still add) and copies the mesh files it still uses to ``out_dir/assets/``. The model layer: numpy and MuJoCo
only. Lengths are in metres, angles in radians, torques in N m unless a name says otherwise.
"""
from __future__ import annotations

import collections
import dataclasses
import math
import os
import pathlib
import shutil

import mujoco
import numpy as np

from gsp_jax import hand as hand_lib

_OBJ = mujoco.mjtObj
_GEOM = mujoco.mjtGeom
_TRN = mujoco.mjtTrn
SPHERE_RATIO = 0.25  # a fitted capsule whose segment is shorter than this many radii becomes a sphere
COVER_PAD = 1e-9  # [m] added to a fitted radius, so rounding never leaves a point outside
CIRCLE_SIDES = 64  # a cylinder's rims: the vertices of this regular polygon around each (it contains the rim)
SPHERE_GRID = (24, 48)  # an ellipsoid: latitudes x longitudes of the polytope around it
SURFACE_SPACING = 0.0005  # [m] spacing of the samples of replaced ellipsoids (over-cover)
CAPSULE_SPACING = 0.001  # [m] spacing of the samples of a fitted geom's surface (over-cover)
SEARCH_SPACING = 0.002  # [m] the same, coarser, while choosing among the candidate fits
SEARCH_TOLERANCE = 0.0005  # [m] candidates this close to the least over-cover count as equal: the smallest volume
UNIT_GAIN_TOL = 1e-6  # a motor's gain counts as 1 within this
_TMP = "__gsp_import_old__"  # a tendon's name while it is rebuilt under its new one
_ROUND = (int(_GEOM.mjGEOM_CAPSULE), int(_GEOM.mjGEOM_SPHERE))
_TENDON_FIELDS = ("actfrclimited", "actfrcrange", "armature", "damping", "frictionloss", "group", "limited", "margin",
                  "material", "range", "rgba", "solimp_friction", "solimp_limit", "solref_friction", "solref_limit",
                  "springlength", "springyield", "stiffness", "userdata", "width")
_CONTACT_FIELDS = ("contype", "conaffinity", "condim", "friction", "solref", "solimp", "margin", "gap", "priority",
                   "solmix")


class HandImportError(ValueError):
    """The hand file cannot be imported as asked; the message names the field and value and what to do."""


# ------------------------------------------------------------------------------------------ fitting (numpy)

@dataclasses.dataclass(frozen=True)
class Fit:
    """A round geom covering a point set: a capsule between `ends`, or a sphere (both ends its centre) [m]."""

    ends: np.ndarray  # (2, 3) the segment's end points (equal for a sphere), the points' frame [m]
    radius: float  # [m]

    @property
    def kind(self) -> str:
        return "sphere" if np.array_equal(self.ends[0], self.ends[1]) else "capsule"

    @property
    def length(self) -> float:
        """The segment's length [m] (0: a sphere)."""
        return float(np.linalg.norm(self.ends[1] - self.ends[0]))

    @property
    def volume(self) -> float:
        """[m^3]"""
        return math.pi * self.radius ** 2 * self.length + 4.0 / 3.0 * math.pi * self.radius ** 3


def segment_distance(points: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(N,) distance of each point (N, 3) from the segment between ends (2, 3) [m]."""
    a, b = np.asarray(ends, np.float64)
    ab = b - a
    denom = float(ab @ ab)
    u = np.zeros(len(points)) if denom == 0.0 else np.clip((points - a) @ ab / denom, 0.0, 1.0)
    return np.linalg.norm(points - (a + u[:, None] * ab), axis=1)


def principal_axes(points: np.ndarray) -> np.ndarray:
    """(3, 3) the point set's principal directions as columns, largest spread first."""
    centred = points - points.mean(0)
    w, v = np.linalg.eigh(centred.T @ centred)
    return v[:, np.argsort(w)[::-1]]


def _hull2(p: np.ndarray) -> np.ndarray:
    """(K, 2) the convex hull's vertices of 2-D points (N, 2) (Andrew's monotone chain)."""
    pts = np.unique(p, axis=0)
    if len(pts) <= 2:
        return pts

    def half(seq):
        out: list = []
        for q in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (q[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (q[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(q)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _circle2(a, b) -> tuple[np.ndarray, float]:
    return (a + b) / 2, float(np.linalg.norm(a - b)) / 2


def _circle3(a, b, c) -> tuple[np.ndarray, float]:
    """The circle through three 2-D points (the widest pair's circle when they are collinear)."""
    d = 2 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
    if abs(d) < 1e-18:
        return max((_circle2(a, b), _circle2(a, c), _circle2(b, c)), key=lambda cr: cr[1])
    sa, sb, sc = a @ a, b @ b, c @ c
    centre = np.array([sa * (b[1] - c[1]) + sb * (c[1] - a[1]) + sc * (a[1] - b[1]),
                       sa * (c[0] - b[0]) + sb * (a[0] - c[0]) + sc * (b[0] - a[0])]) / d
    return centre, float(np.linalg.norm(a - centre))


def min_circle(p: np.ndarray) -> tuple[np.ndarray, float]:
    """The smallest circle containing 2-D points (N, 2): centre (2,) and radius (Welzl's algorithm, on the convex
    hull, in a fixed random order)."""
    h = _hull2(np.asarray(p, np.float64))
    h = h[np.random.default_rng(0).permutation(len(h))]

    def outside(q, c, r):
        return np.linalg.norm(q - c) > r * (1 + 1e-12) + 1e-15

    c, r = h[0], 0.0
    for i in range(1, len(h)):
        if outside(h[i], c, r):
            c, r = h[i], 0.0
            for j in range(i):
                if outside(h[j], c, r):
                    c, r = _circle2(h[i], h[j])
                    for k in range(j):
                        if outside(h[k], c, r):
                            c, r = _circle3(h[i], h[j], h[k])
    return c, r


def _line(points: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The axis line of direction `axis` (unit, (3,)) nearest to all points (N, 3): through the centre of the
    smallest circle around the points' projection across it. Its point (3,), and each point's coordinate along it
    (N,) and distance from it (N,) [m]."""
    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    c2, _ = min_circle(points @ np.stack([u, v], 1))
    origin = c2[0] * u + c2[1] * v
    rel = points - origin
    t = rel @ axis
    return origin, t, np.linalg.norm(rel - t[:, None] * axis, axis=1)


def fit_along(points: np.ndarray, axis: np.ndarray, radius: float | None = None) -> Fit:
    """The round geom along `axis` (3,) that covers `points` (N, 3), of the given radius (at least, and by default,
    the smallest any line of that direction allows: the smallest circle around the points' projection across the
    axis): its segment is the shortest that puts every point within the radius. A sphere when that segment is
    shorter than `SPHERE_RATIO` radii: about the segment's middle or the points' centroid, whichever is smaller,
    as large as the farthest point."""
    points = np.asarray(points, np.float64)
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    origin, t, d = _line(points, axis)
    r = max(float(d.max()), radius or 0.0)
    s = np.sqrt(np.maximum(r * r - d * d, 0.0))
    lo, hi = float((t + s).min()), float((t - s).max())  # the segment must reach each point's [t - s, t + s]
    if hi - lo >= SPHERE_RATIO * r:
        return Fit(np.stack([origin + lo * axis, origin + hi * axis]), r + COVER_PAD)
    spheres = [(float(np.linalg.norm(points - c, axis=1).max()) + COVER_PAD, c)
               for c in (origin + 0.5 * (lo + hi) * axis, points.mean(0))]
    radius, centre = min(spheres, key=lambda rc: rc[0])
    return Fit(np.stack([centre, centre]), radius)


def candidate_fits(points: np.ndarray, n_radii: int = 13) -> list[Fit]:
    """Round geoms covering the points (N, 3): along each of their three principal directions, radii from the
    smallest possible to the points' largest distance from their centroid (`n_radii` of them, evenly spaced); a
    larger radius shortens the segment."""
    points = np.asarray(points, np.float64)
    reach = float(np.linalg.norm(points - points.mean(0), axis=1).max())
    out = []
    for axis in principal_axes(points).T:
        _, _, d = _line(points, axis)
        r0 = float(d.max())
        out += [fit_along(points, axis, r) for r in np.linspace(r0, max(r0, reach), n_radii)]
    return out


def fit_round(points: np.ndarray, score=None, tolerance: float = 0.0) -> Fit:
    """The best of `candidate_fits` for the points (N, 3): the smallest `score(fit)` (default: the volume); among
    those within `tolerance` of it, the smallest volume. Every point lies within the result's radius of its
    segment (checked)."""
    points = np.asarray(points, np.float64)
    fits = candidate_fits(points)
    scores = np.array([f.volume if score is None else score(f) for f in fits])
    best = min((f for f, sc in zip(fits, scores) if sc <= scores.min() + tolerance), key=lambda f: f.volume)
    worst = float(segment_distance(points, best.ends).max())
    if worst > best.radius + 1e-12:
        raise AssertionError(f"fit_round: a point is {worst - best.radius:.3g} m outside the fitted geom")
    return best


# ------------------------------------------------------------------------------- the points of a geom

def _sphere_grid() -> np.ndarray:
    """(M, 3) unit vectors of a latitude-longitude grid, scaled so that their convex hull contains the unit ball
    (by 1 / cos of the grid's covering radius)."""
    n_lat, n_lon = SPHERE_GRID
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    pts = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1).reshape(-1, 3)
    cover = 0.5 * math.hypot(np.pi / n_lat, 2 * np.pi / n_lon)
    return pts / math.cos(cover)


def _local_points(kind: int, size: np.ndarray, model: mujoco.MjModel, mesh: int) -> np.ndarray:
    """(N, 3) points, in the geom's frame, whose convex hull contains the geom [m]."""
    if kind == _GEOM.mjGEOM_BOX:
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        return signs * size
    if kind == _GEOM.mjGEOM_CYLINDER:
        a = np.linspace(0, 2 * np.pi, CIRCLE_SIDES, endpoint=False)
        rim = size[0] / math.cos(math.pi / CIRCLE_SIDES) * np.stack([np.cos(a), np.sin(a)], 1)
        return np.concatenate([np.c_[rim, np.full(len(a), z)] for z in (-size[1], size[1])])
    if kind == _GEOM.mjGEOM_ELLIPSOID:
        return _sphere_grid() * size
    if kind == _GEOM.mjGEOM_MESH:
        adr, n = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        return np.asarray(model.mesh_vert[adr:adr + n], np.float64)
    raise HandImportError(f"geom type {_enum_word(_GEOM, kind)} cannot be fitted")


def geom_points(model: mujoco.MjModel, g: int) -> np.ndarray:
    """(N, 3) points, in the frame of geom g's body, whose convex hull contains the compiled geom [m]: a box's
    corners, a mesh's vertices, a polygon prism around a cylinder, a polytope around an ellipsoid."""
    local = _local_points(int(model.geom_type[g]), model.geom_size[g], model, int(model.geom_dataid[g]))
    return model.geom_pos[g] + local @ hand_lib._quat_to_mat(model.geom_quat[g]).T


def _segment_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, F) distance of points p (N, 1, 3) from segments a -> b (F, 3) [m]."""
    ab = b - a
    u = np.clip(((p - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + u[..., None] * ab), axis=-1)


def triangle_distance(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N,) distance from each point of x (N, 3) to the nearest of the triangles tri (F, 3, 3) [m] (exact: to a
    triangle's plane where the point projects inside it, else to its nearest edge)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    area = np.linalg.norm(n, axis=1)
    n = n / np.maximum(area, 1e-300)[:, None]
    out = np.empty(len(x))
    step = max(1, 1_000_000 // max(len(tri), 1))
    for s in range(0, len(x), step):
        p = x[s:s + step, None, :]  # (N, 1, 3)
        h = ((p - a) * n).sum(-1)  # (N, F)
        q = p - h[..., None] * n
        inside = np.broadcast_to(area > 1e-18, h.shape).copy()
        for e0, e1 in ((a, b), (b, c), (c, a)):
            inside &= (np.cross(e1 - e0, q - e0) * n).sum(-1) >= 0
        d = np.where(inside, np.abs(h), np.inf)
        for e0, e1 in ((a, b), (b, c), (c, a)):
            d = np.minimum(d, _segment_dist(p, e0, e1))
        out[s:s + step] = d.min(1)
    return out


def _triangle_samples(vert: np.ndarray, face: np.ndarray, spacing: float) -> np.ndarray:
    """(N, 3) points on the triangles (F, 3) of vertices (V, 3), at most about `spacing` apart [m]."""
    tri = vert[face]  # (F, 3, 3)
    k_of = np.ceil(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(1) / spacing).astype(int)
    out = [vert]
    for k in np.unique(k_of[k_of >= 2]):
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = i + j <= k
        w = np.stack([i[keep], j[keep], k - i[keep] - j[keep]], 1) / k  # (S, 3) barycentric weights
        out.append(np.einsum("sk,fkd->fsd", w, tri[k_of == k]).reshape(-1, 3))
    return np.concatenate(out)


def _thin(points: np.ndarray, spacing: float) -> np.ndarray:
    """(M, 3) one of the points (N, 3) in each cube of side `spacing` that holds any."""
    _, first = np.unique(np.floor(points / spacing).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def _nearest(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N,) distance from each point of x (N, 3) to the nearest point of y (M, 3) [m]."""
    out = np.empty(len(x))
    yy = (y * y).sum(1)
    step = max(1, 8_000_000 // max(len(y), 1))
    for s in range(0, len(x), step):
        xs = x[s:s + step]
        d2 = (xs * xs).sum(1)[:, None] + yy[None, :] - 2.0 * xs @ y.T
        out[s:s + step] = np.sqrt(np.maximum(d2.min(1), 0.0))
    return out


def _ellipsoid_surface(size: np.ndarray, spacing: float) -> np.ndarray:
    """(N, 3) points on an ellipsoid's surface (semi-axes `size` (3,)), about `spacing` apart or closer [m]."""
    n = max(8, int(math.ceil(2 * math.pi * float(np.max(size)) / spacing)))
    la, lo = np.meshgrid(np.linspace(-np.pi / 2, np.pi / 2, n // 2 + 1), np.linspace(0, 2 * np.pi, n, endpoint=False),
                         indexing="ij")
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1).reshape(-1, 3) * size


def geom_distance(model: mujoco.MjModel, g: int, spacing: float | None = None):
    """A function of points x (N, 3), in the frame of geom g's body, giving their distance (N,) from the solid geom
    [m]: exact for boxes, cylinders and (`spacing` None) meshes (to the mesh's triangles: only points outside it are
    asked); for an ellipsoid, and for a mesh given a `spacing`, the distance to the nearest of its surface samples
    about `spacing` apart (too large by at most about `spacing` / 2; `SURFACE_SPACING` for an ellipsoid)."""
    kind, size = int(model.geom_type[g]), model.geom_size[g].copy()
    pos, mat = model.geom_pos[g].copy(), hand_lib._quat_to_mat(model.geom_quat[g])
    if kind == _GEOM.mjGEOM_BOX:
        return lambda x: np.linalg.norm(np.maximum(np.abs((x - pos) @ mat) - size, 0.0), axis=1)
    if kind == _GEOM.mjGEOM_CYLINDER:
        def cylinder(x):
            local = (x - pos) @ mat
            dr = np.maximum(np.linalg.norm(local[:, :2], axis=1) - size[0], 0.0)
            return np.hypot(dr, np.maximum(np.abs(local[:, 2]) - size[1], 0.0))
        return cylinder
    if kind == _GEOM.mjGEOM_MESH:
        mesh = int(model.geom_dataid[g])
        vert = np.asarray(model.mesh_vert[model.mesh_vertadr[mesh]:][:model.mesh_vertnum[mesh]], np.float64)
        face = np.asarray(model.mesh_face[model.mesh_faceadr[mesh]:][:model.mesh_facenum[mesh]])
        if spacing is not None:
            samples = pos + _thin(_triangle_samples(vert, face, spacing), spacing) @ mat.T
            return lambda x: _nearest(x, samples)
        tri = (pos + vert @ mat.T)[face]
        return lambda x: triangle_distance(x, tri)
    if kind == _GEOM.mjGEOM_ELLIPSOID:
        samples = pos + _ellipsoid_surface(size, spacing or SURFACE_SPACING) @ mat.T
        return lambda x: np.where((((x - pos) @ mat / size) ** 2).sum(1) <= 1.0, 0.0, _nearest(x, samples))
    raise HandImportError(f"geom type {_enum_word(_GEOM, kind)} has no distance here")


def fit_surface(fit: Fit, spacing: float = CAPSULE_SPACING) -> np.ndarray:
    """(N, 3) points on the surface of a fitted capsule or sphere, about `spacing` apart [m]."""
    a, b = fit.ends
    axis = b - a
    length = float(np.linalg.norm(axis))
    axis = axis / length if length > 0 else np.array([0.0, 0.0, 1.0])
    n = max(64, int(4 * math.pi * fit.radius ** 2 / spacing ** 2))
    k = np.arange(n) + 0.5  # a Fibonacci sphere
    z = 1 - 2 * k / n
    phi = math.pi * (1 + 5 ** 0.5) * k
    unit = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    frame = np.stack([u, np.cross(axis, u), axis], 1)
    sph = unit * fit.radius
    caps = [a + sph[sph[:, 2] <= 0] @ frame.T, b + sph[sph[:, 2] >= 0] @ frame.T]
    if length > 0:
        ring = int(math.ceil(2 * math.pi * fit.radius / spacing))
        ang = np.linspace(0, 2 * np.pi, ring, endpoint=False)
        circle = (np.cos(ang)[:, None] * frame[:, 0] + np.sin(ang)[:, None] * frame[:, 1]) * fit.radius
        ts = np.linspace(0, 1, int(math.ceil(length / spacing)) + 1)
        caps.append((a + ts[:, None, None] * (b - a) + circle[None]).reshape(-1, 3))
    return np.concatenate(caps)


def over_cover(distances, fit: Fit, spacing: float = CAPSULE_SPACING) -> float:
    """How far a fitted geom reaches beyond the geoms it covers [m]: the largest distance from a point of its
    surface (samples `spacing` apart) to the nearest of those geoms; `distances`: their `geom_distance`
    functions."""
    surf = fit_surface(fit, spacing)
    return float(np.min([dist(surf) for dist in distances], axis=0).max())


# ------------------------------------------------------------------------------------ spec bookkeeping

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


# ------------------------------------------------------------------------------------------ the steps

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


def check_files(spec: mujoco.MjSpec, drop_visual: bool) -> list[str]:
    """Raise `HandImportError` naming a mesh file that is missing where it is needed; with `drop_visual`, delete the
    visual geoms whose mesh files are missing (their meshes go with the other unused ones). The change lines."""
    paths = mesh_files(spec)
    missing = {x.name: paths[x.name or x.file] for x in spec.meshes
               if x.file and not paths[x.name or x.file].is_file()}
    out = []
    for name, path in missing.items():
        users = [g for g in spec.geoms if g.type == _GEOM.mjGEOM_MESH and g.meshname == name]
        colliding = [g for g in users if g.contype or g.conaffinity]
        if colliding:
            g = colliding[0]
            raise HandImportError(f"mesh {name!r}: file {str(path)!r} is missing, and collision geom "
                                  f"{g.name or '(unnamed)'!r} (body {g.parent.name!r}) needs it (its capsule is fitted "
                                  "to the mesh's vertices)")
        if users and not drop_visual:
            raise HandImportError(f"mesh {name!r}: file {str(path)!r} is missing (used by the visual geoms "
                                  f"{', '.join(repr(g.name or '(unnamed)') for g in users)}); put the file there, or "
                                  "drop the visual geoms (drop_visual=True; on the command line --drop-visual)")
        for g in users:
            spec.delete(g)
        spec.delete(spec.mesh(name))
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


def remove_visual(spec: mujoco.MjSpec) -> list[str]:
    """Delete every geom that collides with nothing (visual only). The change line."""
    gone = [g for g in spec.geoms if not (g.contype or g.conaffinity)]
    if not gone:
        return []
    for g in gone:
        spec.delete(g)
    return [f"visual geoms (contype = conaffinity = 0) removed: {len(gone)}"]


def drop_unused_meshes(spec: mujoco.MjSpec) -> list[str]:
    """Delete the meshes no geom uses. The change line."""
    used = {g.meshname for g in spec.geoms if g.type == _GEOM.mjGEOM_MESH}
    gone = [x for x in spec.meshes if x.name not in used]
    for x in gone:
        spec.delete(x)
    return [f"mesh assets no geom uses any more, removed: {', '.join(x.name for x in gone)}"] if gone else []


# --------------------------------------------------------------------------------------------- motors

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
    """The equality constraints kept (couplings the surrogate does not model)."""
    out = []
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


# --------------------------------------------------------------------------------------------- the result

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
        lines = [f"gsp_jax hand imported from {self.source} by gsp_jax.hand_import (python -m experiments import-hand)",
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


def mass_from_collision(spec: mujoco.MjSpec) -> list[str]:
    """Bodies left without mass (their mass came from visual geoms that were dropped, their colliding geoms set to
    mass 0, as Menagerie's Allegro's are) take it from their colliding geoms' volume at those geoms' density. The
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
    return lines


def contact_sites(spec: mujoco.MjSpec, m: mujoco.MjModel, palm: int, links) -> list[str]:
    """Write custom text ``gsp_contact_links`` and a site ``contact_<link>`` on each link body (`links`: body names
    in grasp order): on a finger's deepest link (its tip) a sphere at the far end of the body's largest colliding
    capsule or sphere, with its radius; on another link a capsule site along that capsule. The change lines."""
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
        g = max(round_, key=lambda g: m.geom_size[g, 0] ** 2 * (4 / 3 * m.geom_size[g, 0] + 2 * m.geom_size[g, 1]))
        r, half = float(m.geom_size[g, 0]), float(m.geom_size[g, 1])
        capsule = int(m.geom_type[g]) == int(_GEOM.mjGEOM_CAPSULE)
        axis = hand_lib._quat_to_mat(m.geom_quat[g])[:, 2]
        tip = depth[name] == max(depth[n] for n in links if finger[n] == finger[name])
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
                drop_visual: bool = False, per_geom: bool = False, contact_links=None, start=None) -> Imported:
    """A published MJCF hand file -> an `Imported` hand that follows the conventions (the module's docstring lists
    the edits). `torque_limit` [N m]: the motor limit of joints whose actuators give none (no forcerange); `palm`:
    the hand's root body (default: the world's child with the most hinges below it); `palm_pos` (3,) [m] /
    `palm_quat` (4,) w x y z: the palm's pose in the world; `drop_visual`: remove the visual geoms; `per_geom`: one
    capsule per replaced geom instead of one per body; `contact_links` (body names, grasp order): write them and
    their contact sites (`contact_sites`); `start` (J,) [rad]: the IK start (`ik_start`). Raises `HandImportError`
    (a ValueError) naming the field."""
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
    changes += lines + reset_option(spec) + check_files(spec, drop_visual)
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
    changes += lines + (remove_visual(spec) if drop_visual else []) + drop_unused_meshes(spec)
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
