"""Where to put the palm, and where the IK starts: a search over palm positions for the one whose fingers reach the
tool's options over the lift and whose start grasp is clear over the heights the episodes start at
(`check-model --place`).

    best = placement.search("path/to/scene.xml")[0]      # candidates, best first
    best.pos                                              # (3,) the palm's position [m]: `import-hand --palm-pos`
    best.start                                            # (J,) the IK start there [rad]: `import-hand --ik-start`

Each candidate is the scene with its palm body moved (the tool, the table and the reach box stay) and an IK start
drawn for it (`ik_start`: the IK descends from gsp_ik_start, so a start far from the grasps leaves links short of
options they can reach), loaded as a model of its own and scored by the surrogate's IK (`preflight.reach`: every
link on every option at the lift's first and last waypoint; `preflight.start_band`: the start grasp at the lowest
and highest starts). The search moves the palm along z, then x, then y (coordinate descent, `STEPS`); each
candidate compiles its own IK (the hand's arrays are constants of the program), so a search of a dozen takes
minutes on a CPU.
"""
from __future__ import annotations

import dataclasses
import hashlib
import itertools
import pathlib

import mujoco
import numpy as np

from gsp_jax.model import kinematics
from gsp_jax.model import load as model_lib
from gsp_jax.model import scenario
from gsp_jax.physics import preflight
from gsp_jax.surrogate.step import Surrogate

STEPS = ((2, 0.02), (0, 0.01), (1, 0.01))  # (axis, step [m]): z, then x, then y; each tried one step either way, twice


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One palm position and how the hand fares there."""

    offset: tuple[float, float, float]  # [m] the palm moved by, from the file's position
    pos: tuple[float, float, float]  # [m] the palm's position in the world
    both: int  # options reached at the lift's first and last waypoint
    either: int  # options reached at one of them at least
    options: int  # options in all
    clear: bool  # the start grasp reaches, collides nowhere over the band of start heights, and its hand is whole
    problems: tuple[str, ...]  # what `preflight.start_reach`, `start_band` and `hand_overlaps` say there
    start: tuple[float, ...] = ()  # (J,) the IK start drawn for this palm position (`ik_start`) [rad]

    def score(self) -> tuple:
        return (self.clear, self.both, self.either)


def _moved(path: pathlib.Path, palm: str, offset, start=None) -> tuple[pathlib.Path, tuple[float, ...]]:
    """The scene with its palm moved by `offset` (and its gsp_ik_start set to `start` (J,) where given), written
    beside it (its includes and meshes resolve alike), named by its content (a model is loaded once per path in a
    process); and the palm's new position."""
    spec = mujoco.MjSpec.from_file(str(path))
    body = spec.body(palm)
    body.pos = np.asarray(body.pos, np.float64) + np.asarray(offset, np.float64)
    if start is not None:
        numeric = next(n for n in spec.numerics if n.name == "gsp_ik_start")
        numeric.data = [float(x) for x in start]
    xml = spec.to_xml()
    out = path.with_name(f".{path.stem}.place-{hashlib.sha256(xml.encode()).hexdigest()[:12]}.xml")
    out.write_text(xml)
    return out, tuple(float(x) for x in body.pos)


def evaluate(path, offset=(0.0, 0.0, 0.0), draw_start: bool = True) -> Candidate:
    """`Candidate` of the scene at `path` with its palm moved by `offset` (3,) [m], its IK starting from a start
    drawn there (`ik_start`; `draw_start=False`: the file's)."""
    path = pathlib.Path(model_lib.resolve(path))
    base = model_lib.load_model(path)
    palm = base.hand.body_names[0]
    start = None
    if draw_start:
        moved, _ = _moved(path, palm, offset)
        try:
            start = ik_start(moved).q
        finally:
            moved.unlink(missing_ok=True)
    moved, pos = _moved(path, palm, offset, start)
    try:
        model = model_lib.load_model(moved)
        sur = Surrogate(model, learned=False)
        reach = preflight.reach(sur)
        ok = np.nan_to_num(reach.error, nan=np.inf) <= reach.tolerance  # (L, K, 2)
        valid = np.isfinite(reach.error[..., 0])
        problems = tuple(preflight.start_reach(sur) + preflight.start_band(sur) + preflight.hand_overlaps(sur))
    finally:
        moved.unlink(missing_ok=True)
    return Candidate(offset=tuple(float(x) for x in offset), pos=pos, both=int(np.sum(ok.all(-1) & valid)),
                     either=int(np.sum(ok.any(-1) & valid)), options=int(valid.sum()), clear=not problems,
                     problems=problems, start=tuple(float(x) for x in np.asarray(model.hand.q_start)))


def search(path, steps=STEPS, progress: bool = True) -> list[Candidate]:
    """Every palm position tried, best first (clear start, then options reached at both ends, then at one): from
    the file's position, along each (axis, step) of `steps` in turn, one step either way, kept where it scores
    better, again from there while it does (at most twice an axis)."""
    tried: dict[tuple, Candidate] = {}

    def at(offset) -> Candidate:
        key = tuple(round(float(x), 6) for x in offset)
        if key not in tried:
            tried[key] = evaluate(path, key)
            c = tried[key]
            if progress:
                print(f"  palm moved by {np.round(np.asarray(key) * 1e3, 1).tolist()} mm: {c.both} of {c.options} "
                      f"options reached at both ends, {c.either} at one; start {'clear' if c.clear else 'not clear'}",
                      flush=True)
        return tried[key]

    best = at((0.0, 0.0, 0.0))
    for axis, step in steps:
        for _ in range(2):
            moves = [np.add(best.offset, np.eye(3)[axis] * s) for s in (-step, step)]
            better = max((at(m) for m in moves), key=Candidate.score)
            if better.score() <= best.score():
                break
            best = better
    return sorted(tried.values(), key=Candidate.score, reverse=True)


def _chain(mj: mujoco.MjModel, hand, body: int) -> list[int]:
    """The hand joints (indices into `hand.joint_names`) on the bodies from MuJoCo body `body` up to the world,
    nearest first: the joints that move it."""
    index = {name: j for j, name in enumerate(hand.joint_names)}
    chain = []
    while body > 0:
        chain += [index[mj.joint(j).name] for j in range(mj.njnt)
                  if mj.jnt_bodyid[j] == body and mj.joint(j).name in index]
        body = mj.body_parentid[body]
    return chain


def _centres(hand, episode, t: int, links, options) -> np.ndarray:
    """(N, 3) world points where links `links` (N,) sit when touching their `options` (N,) at waypoint `t` of
    `episode`: each option's point less the link's radius along its inward normal [m]."""
    mat = np.asarray(kinematics.quat_to_mat(episode.quats[t]), np.float64)
    local = hand.option_pos[links, options] - hand.option_normal[links, options] * hand.link_radius[links, None]
    return np.asarray(episode.waypoints[t], np.float64) + local @ mat.T


@dataclasses.dataclass(frozen=True)
class Start:
    """An IK start that puts each contact link near an option at mid-lift (`ik_start`)."""

    q: np.ndarray  # (J,) the hand's joint angles [rad]: gsp_ik_start (`import-hand --ik-start`)
    gap: np.ndarray  # (L,) each link's contact centre from its target at mid-lift there [m]
    gap_before: np.ndarray  # (L,) the same from the file's gsp_ik_start [m]


def ik_start(model, samples: int = 4000, seed: int = 0) -> Start:
    """A start for the IK from which each contact link begins near its option: the IK descends from the file's
    gsp_ik_start, and a start far from the grasps (a thumb folded the other way) leaves links short of options they
    can reach. For each link, `samples` draws (uniform within the joint limits, one seed) of the joints between the
    palm and it, scored by forward kinematics in MuJoCo: the distance from its contact centre to where it would
    touch its start option (option 1 where the start leaves it off) at the nominal lift's middle waypoint; kept is
    the draw within 1 mm of the nearest that is nearest the file's start (the file's own angles are one of the
    draws). Joints on no link's chain keep the file's angles; a joint shared by links is set by the first of them."""
    model = model_lib.load_model(model)
    hand, mj = model.hand, model.mjmodel
    data = mujoco.MjData(mj)
    episode = scenario.make_episode(model=model)
    options = np.where(np.asarray(hand.start_options) > 0, hand.start_options, 1)
    centre = _centres(hand, episode, episode.n_steps // 2, np.arange(hand.n_links), options)  # (L, 3)
    bodies = np.array([mj.body(name).id for name in hand.link_names])  # MuJoCo's body ids
    rng = np.random.default_rng(seed)

    def gaps(q) -> np.ndarray:
        data.qpos[hand.qpos_adr] = q
        mujoco.mj_kinematics(mj, data)
        at = data.xpos[bodies] + np.einsum("lij,lj->li", data.xmat[bodies].reshape(-1, 3, 3), hand.link_site)
        return np.linalg.norm(at - centre, axis=1)

    q = np.array(hand.q_start, np.float64)
    before = gaps(q)
    taken: set[int] = set()
    for k in range(hand.n_links):
        chain = [j for j in _chain(mj, hand, int(bodies[k])) if j not in taken]
        if not chain:
            continue
        lo, hi = hand.joint_range[chain, 0], hand.joint_range[chain, 1]
        draws = lo + (hi - lo) * rng.random((samples, len(chain)))
        draws[0] = q[chain]  # the file's own angles compete too: no link ends further than it began (+ 1 mm)
        dist = np.empty(samples)
        for s in range(samples):
            trial = q.copy()
            trial[chain] = draws[s]
            dist[s] = gaps(trial)[k]
        near = np.flatnonzero(dist <= dist.min() + 1e-3)
        pick = near[np.argmin(np.linalg.norm(draws[near] - q[chain], axis=1))]
        q[chain] = draws[pick]
        taken.update(chain)
    return Start(q=q.astype(np.float32), gap=gaps(q), gap_before=before)


def _rotations() -> np.ndarray:
    """(24, 3, 3) the rotations that turn the coordinate axes onto the coordinate axes (the cube's)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[np.arange(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    return np.array(out)


@dataclasses.dataclass(frozen=True)
class Pose:
    """A palm pose of the orientation screen (`orientations`)."""

    pos: tuple[float, float, float]  # [m] the palm's position in the world
    quat: tuple[float, float, float, float]  # (w, x, y, z) its orientation
    both: int  # options some joint draw reaches at the lift's first and last waypoint (forward kinematics alone)
    options: int  # options in all


def _links_cloud(model, samples: int, rng) -> list[np.ndarray]:
    """Per contact link (L), its contact centre over `samples` draws of its finger's joints, in the palm's frame
    (S, 3) [m]."""
    hand, mj = model.hand, model.mjmodel
    data = mujoco.MjData(mj)
    palm = mj.body(hand.body_names[0]).id
    clouds = []
    for name, site in zip(hand.link_names, hand.link_site):
        body = mj.body(name).id
        chain = _chain(mj, hand, body)
        q = np.array(hand.q_start, np.float64)
        lo, hi = hand.joint_range[chain, 0], hand.joint_range[chain, 1]
        pts = np.empty((samples, 3))
        for s, draw in enumerate(lo + (hi - lo) * rng.random((samples, len(chain)))):
            q[chain] = draw
            data.qpos[hand.qpos_adr] = q
            mujoco.mj_kinematics(mj, data)
            world = data.xpos[body] + data.xmat[body].reshape(3, 3) @ site
            pts[s] = data.xmat[palm].reshape(3, 3).T @ (world - data.xpos[palm])
        clouds.append(pts)
    return clouds


def orientations(path, samples: int = 3000, grid: float = 0.01, seed: int = 0) -> list[Pose]:
    """Palm poses screened by forward kinematics alone, best first, one per orientation: each of the 24 rotations
    that turn the palm's axes onto the world's, at the position (on a `grid` [m]) where the most options are within
    reach of some draw of their link's finger joints at both the lift's first and last waypoint. Seconds, no IK:
    it finds the orientation (a left hand's thumb may oppose the fingers only with the palm turned otherwise than a
    right hand's); `search` and the IK then settle the position and check collisions. A link reaches an option
    where one of its `samples` draws puts its contact centre within one `grid` cell of the option's (its point less
    the link radius along the normal); palm positions below the lifted tool (its highest waypoint + 1 cm) are not
    counted; among equals, the position nearest the file's palm is kept."""
    model = model_lib.load_model(pathlib.Path(model_lib.resolve(path)))
    hand = model.hand
    rng = np.random.default_rng(seed)
    clouds = _links_cloud(model, samples, rng)
    episode = scenario.make_episode(model=model)
    links = np.array([li for li in range(hand.n_links) for _ in range(1, hand.n_options[li])], np.int32)
    options = np.array([k for li in range(hand.n_links) for k in range(1, hand.n_options[li])], np.int32)
    ends = np.stack([_centres(hand, episode, t, links, options) for t in (0, episode.n_steps - 1)], 1)  # (N, 2, 3)
    here = palm_pose(model)[0] / grid  # the file's palm position, in cells
    above = (float(np.max(np.asarray(episode.waypoints)[:, 2])) + 0.01) / grid  # the palm above the lifted tool
    out = []
    for rot in _rotations():
        votes: dict[tuple, int] = {}
        for li, at in zip(links, ends):
            cells = [set(map(tuple, np.round((c - clouds[li] @ rot.T) / grid).astype(int))) for c in at]
            for cell in cells[0] & cells[1]:  # palm positions that reach the option at both ends
                if cell[2] >= above:
                    votes[cell] = votes.get(cell, 0) + 1
        if not votes:
            continue
        cell, n = max(votes.items(), key=lambda kv: (kv[1], -np.linalg.norm(np.subtract(kv[0], here))))
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, rot.reshape(-1))
        out.append(Pose(pos=tuple(float(x) * grid for x in cell), quat=tuple(float(x) for x in quat), both=n,
                        options=len(links)))
    return sorted(out, key=lambda p: -p.both)


def palm_pose(model) -> tuple[np.ndarray, np.ndarray]:
    """The file's palm position (3,) [m] and orientation (4,) (w, x, y, z) in the world."""
    model = model_lib.load_model(model)
    data = mujoco.MjData(model.mjmodel)
    mujoco.mj_kinematics(model.mjmodel, data)
    palm = model.mjmodel.body(model.hand.body_names[0]).id
    return data.xpos[palm].copy(), data.xquat[palm].copy()
