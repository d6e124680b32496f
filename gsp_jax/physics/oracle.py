"""The feasibility oracle of the physics check: could *any* controller hold the tool through a grasp sequence?

A fall means something only beside that question. At each point of an episode the oracle takes the grasp's
contacts as the surrogate's IK realises them at the waypoint's tool pose (the discrete state's configuration), the
wrench the contacts must supply there, and asks `wrench.hold_margin`: are there contact forces inside the friction
cones that supply it with every joint torque |J^T f + g(q)| inside the motors' limits (read from the physics
model's actuators; g(q): the fingers' own gravity)? The points checked, for a sequence of T grasps:

  waypoint t < T   the grasp in force at t, and, when the decision at t changes a link, the links that stay (they
                   carry the tool while it moves), at the poses of waypoints t and t + 1; except t = 0: in the
                   first segment the start pedestals carry the tool (`scene`), so its change needs no grip;
  hold             the last grasp at the final pose under gravity and the episode's external wrench.

The wrench is quasi-static plus the reference motion's inertia: m (a_ref - g) and no torque while lifting; in the
hold -m g - w_ext (force and torque about the CoM). A sequence is *impossible* where some point's outer bound
exceeds 1 (certain: no forces exist there) and *possible* where every point's inner bound is <= 1.

`Oracle.simulated` asks the same questions at the configurations the physics run *reached* (`runner.Result.qpos`
at the waypoints' ticks and at the hold's start): each link of the grasp touches the simulated tool where its centre
line comes nearest its option's contact point, with the option's face normal turned by the simulated tool pose. It
separates "this grasp cannot hold the tool" from "the hand reached a configuration that cannot" (the IK's contacts
sit 2 mm below the handle's edge; the simulated ones where the fingers are).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from gsp_jax.model import kinematics
from gsp_jax.solvers import wrench
from gsp_jax.physics.controller import reference_motion
from gsp_jax.physics.scene import Scene
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate.step import Surrogate


@dataclasses.dataclass(frozen=True)
class Verdict:
    """The oracle's answer for a grasp sequence on one episode."""

    points: tuple[str, ...]  # what each check is ("t3", "t3 change", "hold")
    ratio_outer: np.ndarray  # (P,) least peak torque / limit, pyramids containing the cones (inf: cones fail)
    ratio_inner: np.ndarray  # (P,) the same with pyramids inside the cones

    @property
    def impossible(self) -> bool:
        """Certain: at some point no forces in the cones hold the tool within the motor limits."""
        return bool(np.any(self.ratio_outer > 1.0))

    @property
    def possible(self) -> bool:
        """Certain: at every point forces inside the cones hold the tool within the motor limits."""
        return bool(np.all(self.ratio_inner <= 1.0))

    @property
    def worst(self) -> tuple[str, float]:
        """The hardest point and its outer ratio."""
        i = int(np.argmax(np.where(np.isnan(self.ratio_outer), -np.inf, self.ratio_outer)))  # nan: after a fall
        return self.points[i], float(self.ratio_outer[i])


class Oracle:
    """The feasibility oracle for one hand model and its physics scene (numpy/scipy around jitted kinematics)."""

    def __init__(self, surrogate: Surrogate, scene: Scene, facets: int = 16):
        self.surrogate, self.scene, self.facets = surrogate, scene, facets
        self.hand, self.space = surrogate.hand, surrogate.space
        m = scene.model
        gear = m.actuator_gear[scene.hand_act, 0]
        lo, hi = (np.asarray(r, float) for r in scene.ctrl_range)
        self.torque_limit = np.minimum(-lo, hi) * np.abs(gear)  # (J,) [N m] the motors' symmetric limit
        if not np.all(self.torque_limit > 0):
            raise ValueError(f"Oracle: every hand motor needs a control range around 0, got {scene.ctrl_range}")
        self._data = mujoco.MjData(m)
        self._cache: dict = {}  # per episode: (grasp, t, links, hold) -> HoldMargin
        hand = self.hand

        def contacts(grasp, pos, quat):
            c = surrogate.realise(grasp, pos, quat)
            x, jac = kinematics.closest_on_links_and_jacobians(hand, c.ik.q, c.points)
            return c.ik.q, c.points, c.normals, c.realised, x, jac

        self._contacts = jax.jit(contacts)
        self._links_at = jax.jit(lambda q, near: kinematics.closest_on_links_and_jacobians(hand, q, near))

    def gravity_torques(self, q: np.ndarray) -> np.ndarray:
        """(J,) the hand joints' gravity torques at joint angles q, at rest (MuJoCo's qfrc_bias) [N m]."""
        d, s = self._data, self.scene
        d.qpos[:] = s.model.qpos0
        d.qpos[s.hand_qpos] = q
        d.qvel[:] = 0.0
        mujoco.mj_forward(s.model, d)
        return d.qfrc_bias[s.hand_dof].copy()

    def realise(self, grasp: int, episode: Episode, t: int):
        """(q (J,), contact points (L, 3), normals (L, 3), realised (L,), link points (L, 3), Jacobians (L, 3, J))
        of `grasp` realised by IK at waypoint t's tool pose (numpy)."""
        out = self._contacts(jnp.int32(grasp), episode.waypoints[t], episode.quats[t])
        return tuple(np.asarray(x, np.float64) if np.asarray(x).dtype != bool else np.asarray(x) for x in out)

    def required(self, episode: Episode, t: int | None) -> tuple[np.ndarray, np.ndarray]:
        """(wrench (6,) the contacts must supply, centre (3,) its torque is about: the CoM) at waypoint t, or in the
        hold (t None)."""
        g, m = np.asarray(self.hand.gravity, float), float(episode.mass)
        T = episode.n_steps
        k = T - 1 if t is None else t
        ref = reference_motion(episode, jnp.float32(k * float(episode.dt)))
        mat = np.asarray(kinematics.quat_to_mat(episode.quats[k]), float)
        centre = np.asarray(episode.waypoints[k], float) + mat @ np.asarray(episode.com, float)
        if t is None:
            ext = np.asarray(episode.w_ext, float)
            return np.r_[-m * g - ext[:3], -ext[3:]], centre
        return np.r_[m * (np.asarray(ref.acc, float) - g), np.zeros(3)], centre

    def at_configuration(self, grasp: int, qpos: np.ndarray):
        """(q (J,), contact points (L, 3), normals (L, 3), carried (L,), Jacobians (L, 3, J), CoM frame (pos (3,),
        rotation (3, 3))) of `grasp`'s links on the tool at a simulated configuration `qpos` (nq,) (numpy)."""
        s, hand = self.scene, self.hand
        qpos = np.asarray(qpos, np.float64)
        if qpos.shape != (s.model.nq,) or not np.all(np.isfinite(qpos)):
            raise ValueError(f"Oracle: qpos must be a finite ({s.model.nq},) configuration, got shape {qpos.shape}")
        q = qpos[s.hand_qpos]
        pos, quat = qpos[s.tool_qpos : s.tool_qpos + 3], qpos[s.tool_qpos + 3 : s.tool_qpos + 7]
        mat = np.asarray(kinematics.quat_to_mat(jnp.asarray(quat / np.linalg.norm(quat))), np.float64)
        opts = np.asarray(self.space.decode(int(grasp)))
        L = hand.n_links
        option_pts = np.asarray(hand.option_pos, np.float64)[np.arange(L), opts]  # (L, 3) tool frame
        normals_tool = np.asarray(hand.option_normal, np.float64)[np.arange(L), opts]
        x, jac = self._links_at(jnp.asarray(q, jnp.float32), jnp.asarray(pos + option_pts @ mat.T, jnp.float32))
        x, jac = np.asarray(x, np.float64), np.asarray(jac, np.float64)
        normals = normals_tool @ mat.T
        # the link's surface point towards the face, moved along the normal onto the face's plane
        face = pos + option_pts @ mat.T
        radius = np.asarray(hand.link_radius, np.float64)[:, None]
        pts = x + radius * normals
        pts = pts - np.sum((pts - face) * normals, -1, keepdims=True) * normals
        return q, pts, normals, opts > 0, jac, (pos, mat)

    def check_at(self, grasp: int, episode: Episode, qpos: np.ndarray, t: int | None = None,
                 links=None) -> wrench.HoldMargin:
        """The margin of `grasp` at the simulated configuration `qpos` (nq,) for the wrench of waypoint t, or of
        the hold (t None), with only the links `links` (L,) bool carrying force if given."""
        q, pts, nrm, carried, jac, (pos, mat) = self.at_configuration(grasp, qpos)
        carry = carried if links is None else carried & np.asarray(links, bool)
        wr, _ = self.required(episode, t)
        centre = pos + mat @ np.asarray(episode.com, np.float64)
        if not np.any(carry):
            return wrench.HoldMargin(float("inf"), float("inf"), None)
        return wrench.hold_margin(pts[carry], nrm[carry], float(episode.friction), wr, centre, jac[carry],
                                  self.torque_limit, self.gravity_torques(q), self.facets)

    def simulated(self, episode: Episode, grasps, qpos: np.ndarray, ticks_per_segment: int,
                  fall_tick: int | None = None) -> Verdict:
        """The verdict on the grasps (T,) at the configurations a physics run reached: `qpos` (K, nq) after each
        control tick (`runner.Result.qpos`), `ticks_per_segment` ticks a segment (`Physics.n_segment`). Checked at
        the tick before each decision t >= 1 (the grasp in force then, the wrench of waypoint t) and at the hold's
        start (the last grasp, the hold's wrench); a run that fell at tick `fall_tick` is checked only before it
        (points from then on read nan)."""
        grasps = [int(g) for g in np.asarray(grasps).reshape(-1)]
        T, qpos = episode.n_steps, np.asarray(qpos)
        if len(grasps) != T:
            raise ValueError(f"Oracle.simulated: grasps must have the episode's {T} entries, got {len(grasps)}")
        if qpos.ndim != 2 or qpos.shape[0] < T * ticks_per_segment:
            raise ValueError(f"Oracle.simulated: qpos must be (K, nq) with K >= {T * ticks_per_segment} "
                             f"ticks, got shape {qpos.shape}")
        names, outer, inner = [], [], []
        for t in range(1, T + 1):
            tick = t * ticks_per_segment - 1
            hold = t == T
            names.append("hold" if hold else f"t{t}")
            if (fall_tick is not None and tick >= fall_tick) or not np.all(np.isfinite(qpos[tick])):
                outer.append(np.nan), inner.append(np.nan)
                continue
            m = self.check_at(grasps[t - 1], episode, qpos[tick], None if hold else t)
            outer.append(m.torque_ratio_outer), inner.append(m.torque_ratio_inner)
        return Verdict(tuple(names), np.asarray(outer), np.asarray(inner))

    def check(self, grasp: int, episode: Episode, t: int, links=None, hold: bool = False) -> wrench.HoldMargin:
        """The margin of `grasp` at waypoint t (the hold's wrench at the last waypoint with `hold`), with only the
        links `links` (L,) bool carrying force if given."""
        q, pts, nrm, realised, _, jac = self.realise(grasp, episode, t)
        carry = realised if links is None else realised & links
        wr, centre = self.required(episode, None if hold else t)
        if not np.any(carry):
            return wrench.HoldMargin(float("inf"), float("inf"), None)
        return wrench.hold_margin(pts[carry], nrm[carry], float(episode.friction), wr, centre, jac[carry],
                                  self.torque_limit, self.gravity_torques(q), self.facets)

    def sequence(self, episode: Episode, grasps) -> Verdict:
        """The verdict on the grasps (T,) in force after each decision (`runner.Result.grasps`), from the episode's
        start grasp."""
        grasps = [int(g) for g in np.asarray(grasps).reshape(-1)]
        T = episode.n_steps
        if len(grasps) != T:
            raise ValueError(f"Oracle.sequence: grasps must have the episode's {T} entries, got {len(grasps)}")
        names, outer, inner = [], [], []

        def add(name, margin):
            names.append(name)
            outer.append(margin.torque_ratio_outer)
            inner.append(margin.torque_ratio_inner)

        key = b"".join(np.asarray(x).tobytes() for x in jax.tree.leaves(episode))
        cache = self._cache.setdefault(key, {}) if len(self._cache) < 64 else {}

        def check(grasp, t, links=None, hold=False):
            k = (grasp, t, None if links is None else tuple(links), hold)
            if k not in cache:
                cache[k] = self.check(grasp, episode, t, links, hold)
            return cache[k]

        before = int(episode.start_grasp)
        for t, grasp in enumerate(grasps):
            if t == 0:  # on the pedestals
                before = grasp
                continue
            add(f"t{t}", check(grasp, t))
            if grasp != before:  # the links both grasps share carry the tool while the changed link moves
                old, new = np.asarray(self.space.decode(before)), np.asarray(self.space.decode(grasp))
                for tt in (t, min(t + 1, T - 1)):
                    add(f"t{tt} change", check(grasp, tt, links=(old == new) & (new > 0)))
            before = grasp
        add("hold", check(grasps[-1], T - 1, hold=True))
        return Verdict(tuple(names), np.asarray(outer), np.asarray(inner))
