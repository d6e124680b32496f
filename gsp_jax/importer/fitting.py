"""Round geoms fitted to point sets (numpy only): the capsule or sphere that covers every point.

Points are (N, 3) arrays in one frame (a body's), lengths in metres. `fit_round(points, score)` chooses among
`candidate_fits`: for each of the points' three principal directions (`principal_axes`), the axis line through the
centre of the smallest circle around their projection (`min_circle`, Welzl's algorithm), radii from that circle's
(the smallest possible) up to the points' largest distance from their centroid, each with the shortest segment that
covers every point (`fit_along`); a segment shorter than `SPHERE_RATIO` radii becomes a sphere. A `Fit` is the
segment's ends (2, 3) and the radius.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

SPHERE_RATIO = 0.25  # a fitted capsule whose segment is shorter than this many radii becomes a sphere
COVER_PAD = 1e-9  # [m] added to a fitted radius, so rounding never leaves a point outside


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

