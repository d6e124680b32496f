"""The points of a collision geom and distances to it, to fit round geoms and to score the fits.

`geom_points(model, g)`: (N, 3) points, in the frame of geom g's body, whose convex hull contains the compiled geom
(a box's corners, a mesh's vertices, a polygon prism around a cylinder, a polytope around an ellipsoid) [m].
`geom_distance(model, g)`: a function of points (N, 3) in that frame giving their distance (N,) from the solid geom
[m]. `fit_surface(fit)`: (N, 3) samples of a fitted capsule's or sphere's surface, and `over_cover`: how far a fit
reaches beyond the geoms it replaces (the largest distance from its surface to the nearest of them) [m].
"""
from __future__ import annotations

import math

import mujoco
import numpy as np

from gsp_jax.importer.fitting import Fit
from gsp_jax.importer.spec import HandImportError, _enum_word
from gsp_jax.model import hand as hand_lib

_GEOM = mujoco.mjtGeom
CIRCLE_SIDES = 64  # a cylinder's rims: the vertices of this regular polygon around each (it contains the rim)
SPHERE_GRID = (24, 48)  # an ellipsoid: latitudes x longitudes of the polytope around it
SURFACE_SPACING = 0.0005  # [m] spacing of the samples of replaced ellipsoids (over-cover)
CAPSULE_SPACING = 0.001  # [m] spacing of the samples of a fitted geom's surface (over-cover)


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


def _local_points(kind: int, size: np.ndarray, mj_model: mujoco.MjModel, mesh: int) -> np.ndarray:
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
        adr, n = mj_model.mesh_vertadr[mesh], mj_model.mesh_vertnum[mesh]
        return np.asarray(mj_model.mesh_vert[adr:adr + n], np.float64)
    raise HandImportError(f"geom type {_enum_word(_GEOM, kind)} cannot be fitted")


def geom_points(mj_model: mujoco.MjModel, g: int) -> np.ndarray:
    """(N, 3) points, in the frame of geom g's body, whose convex hull contains the compiled geom [m]: a box's
    corners, a mesh's vertices, a polygon prism around a cylinder, a polytope around an ellipsoid."""
    local = _local_points(int(mj_model.geom_type[g]), mj_model.geom_size[g], mj_model, int(mj_model.geom_dataid[g]))
    return mj_model.geom_pos[g] + local @ hand_lib._quat_to_mat(mj_model.geom_quat[g]).T


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


def geom_distance(mj_model: mujoco.MjModel, g: int, spacing: float | None = None):
    """A function of points x (N, 3), in the frame of geom g's body, giving their distance (N,) from the solid geom
    [m]: exact for boxes, cylinders and (`spacing` None) meshes (to the mesh's triangles: only points outside it are
    asked); for an ellipsoid, and for a mesh given a `spacing`, the distance to the nearest of its surface samples
    about `spacing` apart (too large by at most about `spacing` / 2; `SURFACE_SPACING` for an ellipsoid)."""
    kind, size = int(mj_model.geom_type[g]), mj_model.geom_size[g].copy()
    pos, mat = mj_model.geom_pos[g].copy(), hand_lib._quat_to_mat(mj_model.geom_quat[g])
    if kind == _GEOM.mjGEOM_BOX:
        return lambda x: np.linalg.norm(np.maximum(np.abs((x - pos) @ mat) - size, 0.0), axis=1)
    if kind == _GEOM.mjGEOM_CYLINDER:
        def cylinder(x):
            local = (x - pos) @ mat
            dr = np.maximum(np.linalg.norm(local[:, :2], axis=1) - size[0], 0.0)
            return np.hypot(dr, np.maximum(np.abs(local[:, 2]) - size[1], 0.0))
        return cylinder
    if kind == _GEOM.mjGEOM_MESH:
        mesh = int(mj_model.geom_dataid[g])
        vert = np.asarray(mj_model.mesh_vert[mj_model.mesh_vertadr[mesh]:][:mj_model.mesh_vertnum[mesh]], np.float64)
        face = np.asarray(mj_model.mesh_face[mj_model.mesh_faceadr[mesh]:][:mj_model.mesh_facenum[mesh]])
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

