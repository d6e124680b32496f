"""The contact controller: object-level impedance on the observed tool, the wrench spread over the active
contacts by the friction-cone force solve, fingers in Cartesian impedance through J^T, and grasp changes of one
link at a time. Pure JAX, one episode (vmap for batches), backend-neutral: it reads an `Observation` and returns
motor commands, so MJX and C MuJoCo step the same controller. It is the reference of its numba copy,
`physics.native` (this control law, `Physics.tick` and `Physics.check` over plain arrays), which must equal it;
checked by `tests/test_native.py::test_native_tick_is_the_jax_tick_on_recorded_states`.

Per control tick, with the tool observed at pose (p, R), velocity (v, w), and the reference motion (p_r, v_r, a_r)
of the episode's waypoints (a cubic Hermite spline through them):

  tool wrench   F = m (a_r - g) + m [kp (c_r - c) + kd (v_r - v_c)] - s f_ext          (c: centre of mass)
                T = I' kp e_R - I'' kd w + w x I w - s tau_ext                       (e_R: rotation error vector)
                kp, kd from `tool_freq` / `tool_damping`; I' = I + m r^2 with r `rotation_radius` (`tool_radius`, or
                the tool's own as `radius_from` says: half its longest side by default, or its largest radius of
                gyration; a thin tool's inertia about its long axis alone would leave it free to roll);
                I'' = I' but per principal axis at most `rotation_step` / (tick kd) I (damping stable at the
                control rate); the feedback force and torque capped at `feedback_limit` tool weights, at least
                `feedback_floor` (times r for the torque); s the external wrench's ramp (0 while lifting, 1 in the
                hold);
  contacts      the grasp's contact points on the *observed* tool (where each link touches); forces f in the
                friction cones (`friction_margin` of mu) that supply (F, T), with `grip_force` newtons along every
                normal as the solve's preferred forces, so the grip lives in the grasp matrix's null space and
                inside the cones (`wrench.solve(prefer=...)`, warm-started from the last tick). The normals:
                with `frames="measured"` (the default) a touching link's is the tool surface's at the link's
                centre-line point, as observed (`measured_normals`: MuJoCo's sphere-primitive normal, tilted where
                a fingertip rests on an edge); with "nominal" (the paper's controller) its option's face normal;
  fingers       tau = sum_l J_l^T (f_l + K_l (x*_l - x_l) + D (v*_l - J_l dq)) + bias + posture, with J_l the
                Jacobian of link l's centre-line point nearest its target x*_l at the *measured* joint angles: no IK
                while the tool is held. Targets are fixed to the observed tool: a touching link's where it touches
                (K stiff along the normal, `held_stiffness_ratio` across); an arriving link's its option's nominal
                point (contact point minus the link radius along the normal); a free finger's parking point. A link
                that touches nothing gets K_l = k_free (J_l J_l^T + lam^2 I)^-1: a joint-space spring of
                `free_stiffness` on the damped least-squares step, which also moves a near-straight finger's tip
                along the finger.

A grasp change (a decision that changes one link's option) runs inside its segment:

  unload  (`unload` s) the link's load fraction goes to 0: the force is the blend s f_with + (1 - s) f_without
          of the solves with and without it, so the links that stay carry the whole wrench before it lets go;
  move    (`move` s) the link travels a path fixed to the tool: back off its contact by `standoff` along the
          normal, across (sideways first when the new normal differs), to `standoff` off the new contact, in
          (slowly: the last leg gets the most time); a link that is removed stops at its first point and parks
          there;
  load    once the link touches (within `touch_tol` of the surface and `reach_tol` of its point), its target
          becomes where it touches and its load fraction rises to 1 in `load` s.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.model import grasps, kinematics
from gsp_jax.solvers import ik, wrench
from gsp_jax.model.hand import HandModel
from gsp_jax.physics.config import PhysicsConfig
from gsp_jax.physics.scene import Observation
from gsp_jax.model.scenario import Episode

N_PATH = 5  # points of a moving link's path
MIN_GRADIENT = 0.5  # below this norm the tool's SDF gradient gives no normal (a point on its surface: it is 0 there,
# 1 outside, >= 1 inside a box); the measured frames then keep the option's normal
STRENGTH_RANGE = (0.5, 1.5)  # the motors' strength estimates stay within these factors of the model's
STRENGTH_LEAK = 2.0  # [1/s] the estimates' pull back to the model's strength (1)
STRENGTH_DEADBAND = 0.6  # pose feedback below this many tool weights does not move the estimates (a held tool's
# feedback in the model stays below it: estimates that chase it drop heavy tools)
PATH_TIMES = np.array([0.0, 0.15, 0.4, 0.65, 1.0], np.float32)  # when (fraction of `move`) the path reaches each
# point: the last leg, onto the tool, gets the most time (a slow arrival does not kick the tool)


@struct.dataclass
class Motion:
    """The tool's reference motion at one time."""

    pos: jax.Array  # (3,) tool frame origin [m]
    vel: jax.Array  # (3,) [m/s]
    acc: jax.Array  # (3,) [m/s^2]
    quat: jax.Array  # (4,) orientation (w, x, y, z)


@struct.dataclass
class ControllerState:
    """What the controller remembers between ticks (one episode). L links."""

    options: jax.Array  # (L,) int32, the reference grasp's options (after the segment's decision)
    previous: jax.Array  # (L,) int32, the options before it
    changed: jax.Array  # (L,) bool, the link this segment changes
    start: jax.Array  # () [s] when the segment started
    path: jax.Array  # (N_PATH, 3) the changed link's path, tool frame [m]
    park: jax.Array  # (L, 3) where each link waits when it holds nothing, tool frame [m]
    anchor: jax.Array  # (L, 3) where each touching link touches: its centre line, tool frame [m]
    anchored: jax.Array  # (L,) bool, the link touches at `anchor` (else it heads for its option's nominal point)
    load: jax.Array  # (L,) the share of the wrench each link may carry, in [0, 1]
    f_with: jax.Array  # (L, 3) last tick's forces with the changed link (warm start) [N]
    f_without: jax.Array  # (L, 3) ... and without it
    q_rest: jax.Array  # (J,) posture the spare degrees of freedom are pulled to [rad]
    strength: jax.Array  # (J,) each motor's estimated torque per command, relative to the model's (`strength_rate`)
    estimate: jax.Array  # (7 + J,) the filtered tool pose (position [m], quaternion) and joint angles [rad]
    # (`pose_filter`)


def reference_motion(episode: Episode, time: jax.Array) -> Motion:
    """The waypoints as a C1 cubic Hermite spline in time (tangents by central differences, one-sided at the
    ends), still after the last waypoint; orientation normalised-linear between waypoint quaternions."""
    wp, dt, T = episode.waypoints, episode.dt, episode.n_steps
    s = jnp.clip(time / dt, 0.0, T - 1.0)
    i = jnp.minimum(jnp.floor(s).astype(jnp.int32), T - 2)
    u = s - i
    tangent = lambda j: (wp[jnp.minimum(j + 1, T - 1)] - wp[jnp.maximum(j - 1, 0)]) / (  # noqa: E731
        (jnp.minimum(j + 1, T - 1) - jnp.maximum(j - 1, 0)) * dt) * dt
    p0, p1, m0, m1 = wp[i], wp[i + 1], tangent(i), tangent(i + 1)
    h = jnp.stack([2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2])
    dh = jnp.stack([6 * u**2 - 6 * u, 3 * u**2 - 4 * u + 1, -6 * u**2 + 6 * u, 3 * u**2 - 2 * u])
    ddh = jnp.stack([12 * u - 6, 6 * u - 4, -12 * u + 6, 6 * u - 2])
    basis = jnp.stack([p0, m0, p1, m1])  # (4, 3)
    moving = time < (T - 1) * dt
    qa, qb = episode.quats[i], episode.quats[i + 1]
    qb = jnp.where(jnp.dot(qa, qb) < 0, -qb, qb)
    quat = (1 - u) * qa + u * qb
    return Motion(pos=h @ basis, vel=jnp.where(moving, dh @ basis / dt, 0.0),
                  acc=jnp.where(moving, ddh @ basis / dt**2, 0.0), quat=quat / jnp.linalg.norm(quat))


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return jnp.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                      w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def rotation_error(q_ref: jax.Array, q: jax.Array) -> jax.Array:
    """(3,) world-frame rotation vector that turns orientation q into q_ref [rad]."""
    e = quat_mul(q_ref, q * jnp.array([1.0, -1.0, -1.0, -1.0]))
    e = jnp.where(e[0] < 0, -e, e)
    v = e[1:]
    n = jnp.sqrt(jnp.sum(v**2) + 1e-18)
    return 2 * jnp.arctan2(n, e[0]) * v / n


def _solve3(m: jax.Array, v: jax.Array) -> jax.Array:
    """x (..., 3) with m x = v for 3x3 matrices m (..., 3, 3), by the adjugate (Cramer's rule): written out, so
    XLA fuses it (a batched LAPACK solve is a library call of its own, a large share of a controller tick on a CPU:
    docs/physics.md, "Cost")."""
    c0 = jnp.cross(m[..., 1, :], m[..., 2, :])
    c1 = jnp.cross(m[..., 2, :], m[..., 0, :])
    c2 = jnp.cross(m[..., 0, :], m[..., 1, :])
    det = jnp.sum(m[..., 0, :] * c0, -1, keepdims=True)
    return (c0 * v[..., :1] + c1 * v[..., 1:2] + c2 * v[..., 2:]) / det


def rotation_radius(hand: HandModel, config: PhysicsConfig) -> float:
    """The radius [m] the tool's rotational gains act at (`ControllerConfig.tool_radius`): the config's, or where
    that is None the tool's own (`ControllerConfig.radius_from`): "extent", half the longest side of its bounding
    box in its frame (`HandModel.tool_bounds`), the lever its contacts have about its centre; "gyration", the
    model's tool's largest radius of gyration sqrt(I_max / m) (a bar of length L: L / sqrt(12))."""
    c = config.controller
    if c.tool_radius is not None:
        return float(c.tool_radius)
    if c.radius_from == "gyration":
        return float(np.sqrt(np.max(hand.tool_inertia) / hand.tool_mass))
    low, high = hand.tool_bounds()
    return float(np.max(high - low) / 2)


def _smooth(u: jax.Array) -> jax.Array:
    return u * u * (3 - 2 * u)


class Controller:
    """The contact controller of one hand model (see the module docstring). Stateless after construction."""

    def __init__(self, hand: HandModel, space: grasps.GraspSpace, config: PhysicsConfig, ctrl_range, gravity,
                 timestep: float):
        """`ctrl_range`: the motors' (low, high) torques (J,) x 2 [N m]; `gravity` (3,) [m/s^2]; `timestep` [s] the
        control period (the scene's physics step: the controller acts at every step)."""
        self.hand, self.space, self.config, self.timestep = hand, space, config, timestep
        self.ctrl_range = tuple(jnp.asarray(r, jnp.float32) for r in ctrl_range)
        self.gravity = jnp.asarray(gravity, jnp.float32)
        self.finger_names = hand.finger_names
        self.link_finger = np.asarray(hand.link_finger)  # (L,) finger of each contact link
        self.is_tip = np.asarray(hand.link_is_tip)  # (L,) the finger's deepest contact link: where it parks
        radius = hand.link_radius[:, None, None]
        self.targets_tool = (hand.option_pos - radius * hand.option_normal).astype(np.float32)  # (L, K, 3)
        self.wrench_config = wrench.WrenchConfig(method="apg", iterations=config.controller.force_iterations)
        self.tool_radius = rotation_radius(hand, config)  # [m]

    # ----------------------------------------------------------------------------------------- geometry
    def _frame(self, obs: Observation):
        mat = kinematics.quat_to_mat(obs.tool_quat)
        return obs.tool_pos, mat, mat @ obs.tool_vel[3:]  # position, rotation, world angular velocity

    def _links(self, q: jax.Array, near: jax.Array):
        """Link points (L, 3) on the links' centre lines nearest the world points `near` (L, 3) at joint angles q,
        and their Jacobians (L, 3, J). (Forces act there too: the tool holds better than with them at the
        touching point one radius out.)"""
        return kinematics.closest_on_links_and_jacobians(self.hand, q, near)

    def _target(self, options: jax.Array) -> jax.Array:
        """(L, 3) tool-frame targets of the links' centre lines for `options` (L,) (meaningless where 0)."""
        return jnp.asarray(self.targets_tool)[np.arange(self.hand.n_links), options]

    def _normal(self, options: jax.Array) -> jax.Array:
        """(L, 3) tool-frame inward normals of the links' `options` (L,) (meaningless where 0)."""
        return jnp.asarray(self.hand.option_normal, jnp.float32)[np.arange(self.hand.n_links), options]

    def _on_surface(self, here: jax.Array, options: jax.Array) -> jax.Array:
        """Tool-frame points `here` (L, 3) moved along their option's normal onto the nominal contact level: where a
        link touches, keeping where along the surface it touches."""
        n = self._normal(options)
        return here - jnp.sum((here - self._target(options)) * n, -1, keepdims=True) * n

    def _touching(self, target: jax.Array, point: jax.Array, normal: jax.Array) -> jax.Array:
        """(L,) bool: link points `point` (L, 3) touch the surface of their `target`s (L, 3) with inward `normal`s
        (L, 3), all in one frame: within `touch_tol` of it along the normal and `reach_tol` across it."""
        gap = jnp.sum((target - point) * normal, -1)  # > 0: the link is off the surface
        across = jnp.linalg.norm(target - point - gap[..., None] * normal, axis=-1)
        timeline = self.config.timeline
        return (gap < timeline.touch_tol) & (across < timeline.reach_tol)

    # ------------------------------------------------------------------------------------------- phases
    def start(self, episode: Episode, q0: jax.Array, obs: Observation) -> ControllerState:
        """The state at the episode's start: the start grasp's links that touch loaded, every link parked where
        it is."""
        opts = self.space.decode(episode.start_grasp)
        p, mat, _ = self._frame(obs)
        x, _ = self._links(q0, p + self._target(opts) @ mat.T)
        L = self.hand.n_links
        zeros = jnp.zeros((L, 3), jnp.float32)
        here = (x - p) @ mat
        touching = (opts > 0) & self._touching(self._target(opts), here, self._normal(opts))
        return ControllerState(options=opts, previous=opts, changed=jnp.zeros(L, bool), start=jnp.float32(0.0),
                               path=jnp.zeros((N_PATH, 3), jnp.float32), park=here,
                               anchor=self._on_surface(here, opts), anchored=touching,
                               load=touching.astype(jnp.float32), f_with=zeros, f_without=zeros, q_rest=q0,
                               strength=jnp.ones_like(q0),
                               estimate=jnp.concatenate([obs.tool_pos, obs.tool_quat / jnp.linalg.norm(obs.tool_quat),
                                                         obs.q]))

    def begin_segment(self, cs: ControllerState, obs: Observation, grasp: jax.Array,
                      time: jax.Array) -> ControllerState:
        """A new segment at `time` with reference grasp `grasp` (at most one link differs from the current one):
        the changed link's path, and parking points. Where the grasp stays the same, the reference of
        `native.keep_grasp`, which must equal it bit for bit; checked by
        `tests/test_physics.py::test_c_lockstep_decides_table_policies_in_numpy_as_jax_does`."""
        gap, L = self.config.timeline.standoff, self.hand.n_links
        new, old = self.space.decode(grasp), cs.options
        changed = new != old
        link = jnp.argmax(changed)
        p, mat, _ = self._frame(obs)
        park_world = p + cs.park @ mat.T
        x, _ = self._links(obs.q, park_world)
        here = ((x - p) @ mat)[link]  # the link's point now, tool frame
        n_old = jnp.where(old[link] > 0, self._normal(old)[link], 0.0)
        n_new = jnp.where(new[link] > 0, self._normal(new)[link], 0.0)
        a = jnp.where(old[link] > 0, jnp.where(cs.anchored[link], cs.anchor[link], self._target(old)[link]), here)
        a1 = a - gap * n_old
        side = n_new - jnp.dot(n_new, n_old) * n_old  # the new normal's part across the old one
        a2 = a1 - gap * side
        b = jnp.where(new[link] > 0, self._target(new)[link], a1)
        b1 = b - gap * n_new
        path = jnp.where(new[link] > 0, jnp.stack([a, a1, a2, b1, b]), jnp.stack([a, a1, a1, a1, a1]))
        any_change = jnp.any(changed)
        park = jnp.where(any_change & (jnp.arange(L) == link)[:, None] & (new[link] == 0), path[-1], cs.park)
        return cs.replace(options=new, previous=old, changed=changed, start=jnp.asarray(time, jnp.float32),
                          path=jnp.where(any_change, path, cs.path), park=park)

    # -------------------------------------------------------------------------------------------- a tick
    def tool_wrench(self, obs: Observation, episode: Episode, ref: Motion, external: jax.Array,
                    uncapped: bool = False):
        """(6,) force and torque about the CoM the contacts must supply (impedance on the observed pose); with
        `uncapped`, also the pose feedback's force before its cap (3,) [N]."""
        c = self.config.controller
        kp, kd = c.tool_gains
        p, mat, omega = self._frame(obs)
        r_com = mat @ episode.com
        com, com_ref = p + r_com, ref.pos + kinematics.quat_to_mat(ref.quat) @ episode.com
        v_com = obs.tool_vel[:3] + jnp.cross(omega, r_com)
        weight = episode.mass * jnp.linalg.norm(self.gravity)
        feedback = episode.mass * (kp * (com_ref - com) + kd * (ref.vel - v_com))
        inertia, stiff, damp = self._tool_inertia(mat, episode)
        turn = stiff @ (kp * rotation_error(ref.quat, obs.tool_quat)) - damp @ (kd * omega)
        # the feedback is capped: a contact's impact spikes the observed velocity, and an uncapped damping term
        # would turn the spike into grip forces the motors cannot give, throwing the tool out of the hand
        clip = lambda v, top: v * jnp.minimum(1.0, top / (jnp.linalg.norm(v) + 1e-9))  # noqa: E731
        cap = jnp.maximum(c.feedback_limit * weight, c.feedback_floor)
        raw = feedback
        feedback, turn = clip(feedback, cap), clip(turn, cap * self.tool_radius)
        force = episode.mass * (ref.acc - self.gravity) + feedback
        torque = turn + jnp.cross(omega, inertia @ omega)
        wrench = jnp.concatenate([force, torque]) - external
        return (wrench, raw) if uncapped else wrench

    def _tool_inertia(self, mat: jax.Array, episode: Episode) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(3, 3) x 3, world frame: the tool's inertia about its CoM, and the inertias its rotational stiffness and
        damping act on. Stiffness: the tool's plus its mass at `rotation_radius` (as of that mass: the inertia about a
        thin tool's long axis is ~50x smaller, and inertia-normalised gains would leave it free to roll under an
        offset CoM's grip forces). Damping: the same, but about each principal axis at most `rotation_step` /
        (tick kd) times the tool's own inertia there, so one tick's damping takes at most `rotation_step` of the
        tool's angular velocity off (within a tick the tool turns alone, the fingers follow through the contacts'
        compliance, so their reflected inertia does not count: docs/physics.md, "The tool loop at the control
        rate")."""
        c = self.config.controller
        inertia = (mat * episode.inertia) @ mat.T
        stiff = episode.inertia + episode.mass * self.tool_radius**2  # (3,) about the tool's principal axes
        damp = jnp.minimum(stiff, c.rotation_step / (self.timestep * c.tool_gains[1]) * episode.inertia)
        return inertia, (mat * stiff) @ mat.T, (mat * damp) @ mat.T

    def measured_normals(self, x: jax.Array, p: jax.Array, mat: jax.Array, nominal: jax.Array,
                         touching: jax.Array) -> jax.Array:
        """(L, 3) world inward normals: for the `touching` (L,) links the tool surface's at their world points `x`
        (L, 3) (the gradient of the tool's signed distance, `ik.box_sdf_and_grad`, for the tool at p, mat), else
        (and where that gradient vanishes: a point exactly on the surface) the `nominal` ones. The reference of
        `native._measured_normal`; checked by `tests/test_native.py::test_native_measured_normal_is_the_jax_one`."""
        outward = ik.box_sdf_and_grad(x, p, mat, self.hand)[1]
        size = jnp.linalg.norm(outward, axis=-1, keepdims=True)
        use = touching[:, None] & (size > MIN_GRADIENT)
        return jnp.where(use, -outward / jnp.where(use, size, 1.0), nominal)

    def _forces(self, points, normals, active, mu, required, com, init):
        """Cone forces (L, 3) on the links `active` (L,) that supply `required`, pulled towards `grip_force`
        newtons along each normal (the grip: it lives in the grasp matrix's null space, inside the cones). The
        reference of `native._solve`, which must equal it; checked by
        `tests/test_native.py::test_native_force_solve_is_the_wrench_solve`."""
        prefer = self.config.controller.grip_force * normals
        return wrench.solve(points, normals, active, mu, required, com, self.wrench_config, init, prefer).forces

    def _phase(self, cs: ControllerState, time: jax.Array):
        """Where each link is in the segment's grasp change at `time`: (unloading, travelling, moving (L,) bool,
        current (L,) the option each link's force acts at, on_path (L, 3) tool-frame point on the travel path)."""
        c = self.config.timeline
        tau_s = time - cs.start
        unloading = cs.changed & (tau_s < c.unload)
        u = jnp.clip((tau_s - c.unload) / c.move, 0.0, 1.0)
        travelling = cs.changed & (u < 1)
        current = jnp.where(unloading, cs.previous, cs.options)
        times = jnp.asarray(PATH_TIMES)
        seg = jnp.clip(jnp.searchsorted(times, u, side="right") - 1, 0, N_PATH - 2)
        w = _smooth(jnp.clip((u - times[seg]) / (times[seg + 1] - times[seg]), 0.0, 1.0))
        on_path = (1 - w) * cs.path[seg] + w * cs.path[seg + 1]
        moving = cs.changed & (tau_s >= c.unload) & (u < 1)
        return unloading, travelling, moving, current, on_path

    def _targets(self, cs: ControllerState, current, on_path, anchored):
        """Tool-frame targets (L, 3) of the links (contact option, travel path, anchor or parking point) and which
        links are tracked (L,) (those in a grasp or changing, and the tip of a finger otherwise idle)."""
        tgt = jnp.where((current > 0)[:, None], self._target(current), cs.park)
        tgt = jnp.where(cs.changed[:, None], on_path, tgt)
        tgt = jnp.where(anchored[:, None], cs.anchor, tgt)
        busy_link = (current > 0) | cs.changed
        busy = jnp.zeros(len(self.finger_names), bool).at[self.link_finger].max(busy_link)[self.link_finger]
        return tgt, busy_link | (~busy & self.is_tip)

    def _tracking(self, x_ref, v_ref, x, v, jac, nrm, held, tracked):
        """Forces (L, 3) pulling every tracked link to its target; a touching (`held`) link only weakly across the
        surface (there the force solve holds the tool; a stiff pull to a point on a tool that slips would pull the
        tool with it)."""
        c = self.config.fingers
        err, derr = x_ref - x, v_ref - v
        err_n, derr_n = jnp.sum(err * nrm, -1, keepdims=True) * nrm, jnp.sum(derr * nrm, -1, keepdims=True) * nrm
        ratio = c.held_stiffness_ratio
        # a free link (travelling, arriving, parked) is pulled as by a joint-space spring towards the damped
        # least-squares step J^T (J J^T + lam^2)^-1 e: J^T kp e alone is weak along the directions a finger
        # barely moves in (a near-straight finger lowering its tip), and an arriving tip came too late
        jjt = jnp.einsum("lij,lkj->lik", jac, jac) + c.free_damping**2 * jnp.eye(3)
        f_free = c.free_stiffness * _solve3(jjt, err)
        f_track = jnp.where(held, c.finger_kp * (err_n + ratio * (err - err_n)), f_free)
        f_track = f_track + c.finger_kd * jnp.where(held, derr_n + ratio * (derr - derr_n), derr)
        return jnp.where(tracked[:, None], f_track, 0.0)

    def _filtered(self, cs: ControllerState, obs: Observation) -> tuple[Observation, jax.Array]:
        """The observation with its tool pose and joint angles filtered (`pose_filter` a): the last estimate carried
        one tick by the measured velocities (the tool's angular velocity in its frame), then moved a of the way to
        the observed values; (the filtered observation, the new estimate (7 + J,)). The reference of
        `native._filter`."""
        a, ts = jnp.float32(self.config.controller.pose_filter), jnp.float32(self.timestep)
        est = cs.estimate
        pos = est[:3] + obs.tool_vel[:3] * ts
        pos = pos + a * (obs.tool_pos - pos)
        h = jnp.float32(0.5) * ts * obs.tool_vel[3:]
        quat = quat_mul(est[3:7], jnp.concatenate([jnp.ones(1, jnp.float32), h]))
        seen = obs.tool_quat / jnp.linalg.norm(obs.tool_quat)
        seen = jnp.where(jnp.dot(quat, seen) < 0, -seen, seen)
        quat = quat + a * (seen - quat)
        quat = quat / jnp.linalg.norm(quat)
        q = est[7:] + obs.dq * ts
        q = q + a * (obs.q - q)
        return obs.replace(tool_pos=pos, tool_quat=quat, q=q), jnp.concatenate([pos, quat, q])

    def _strengths(self, cs: ControllerState, tau: jax.Array, jac: jax.Array, active: jax.Array,
                   feedback: jax.Array, episode: Episode) -> jax.Array:
        """(J,) the motors' strength estimates after this tick: each moves against the gradient of the pose
        feedback's shortfall, (the force on the tool that joint j's torque tau_j gives through each active link l,
        (J_l J_l^T)^-1 J_l e_j tau_j) . `feedback` (3,) [N] (uncapped), = tau_j e_j^T J_l^T (J_l J_l^T)^-1 feedback
        (J_l J_l^T symmetric: one solve a link), scaled by `strength_rate` / weight^2 and by
        how far the feedback exceeds `STRENGTH_DEADBAND` tool weights; leaking back to 1 at `STRENGTH_LEAK`; frozen
        while a link changes; a motor whose command is at its limit is not asked for more. The reference of
        `native._strengths`."""
        c, ts = self.config.controller, jnp.float32(self.timestep)
        leak, deadband = STRENGTH_LEAK, STRENGTH_DEADBAND
        weight = episode.mass * jnp.linalg.norm(self.gravity)
        jjt = jnp.einsum("lij,lkj->lik", jac, jac) + jnp.float32(1e-4) * jnp.eye(3)  # (L, 3, 3) [m^2]
        pull = _solve3(jjt, jnp.broadcast_to(feedback, (jac.shape[0], 3)))  # (L, 3): (J J^T)^-1 feedback [N/m^2]
        grad = jnp.einsum("l,lij,li->j", active.astype(jnp.float32), jac, pull) * tau  # (J,) [N^2]
        size = jnp.linalg.norm(feedback)
        keep = jnp.maximum(0.0, 1.0 - deadband * weight / (size + 1e-9))
        keep = jnp.where(jnp.any(cs.changed), 0.0, keep)
        old = cs.strength
        new = old - keep * c.strength_rate * ts * grad / (weight * weight)
        new = new + leak * ts * (1.0 - new)
        out = tau / old
        limited = (out >= self.ctrl_range[1]) | (out <= self.ctrl_range[0])
        new = jnp.where(limited, jnp.maximum(new, old), new)
        return jnp.clip(new, *STRENGTH_RANGE)

    def control(self, cs: ControllerState, obs: Observation, episode: Episode, ref: Motion, time: jax.Array,
                external: jax.Array) -> tuple[jax.Array, ControllerState]:
        """Joint torques (J,) for one tick at `time`, and the next state. `external` (6,): the external wrench
        the controller feeds forward (zero while lifting). The reference of `native._control`, which must equal it;
        checked by `tests/test_native.py::test_native_tick_is_the_jax_tick_on_recorded_states`."""
        timeline, tick = self.config.timeline, self.timestep
        with jax.default_matmul_precision("highest"):
            estimate = cs.estimate
            if self.config.controller.pose_filter < 1:
                obs, estimate = self._filtered(cs, obs)
            p, mat, omega = self._frame(obs)
            unloading, travelling, moving, current, on_path = self._phase(cs, time)
            anchored = cs.anchored & ~moving
            tgt, tracked = self._targets(cs, current, on_path, anchored)
            # targets fixed to the observed tool
            x_ref = p + tgt @ mat.T
            v_ref = obs.tool_vel[:3] + jnp.cross(omega, x_ref - p)
            nrm = self._normal(current) @ mat.T
            x, jac = self._links(obs.q, x_ref)
            v = jnp.einsum("lij,j->li", jac, obs.dq)

            # load fractions: down when a link is to let go, up once an arriving link touches
            want = (current > 0) & ~unloading & ~travelling
            arrive = (current > 0) & ~anchored & ~travelling & self._touching(x_ref, x, nrm)
            anchor = jnp.where(arrive[:, None], self._on_surface((x - p) @ mat, current), cs.anchor)
            anchored = anchored | arrive
            up = jnp.where(anchored, jnp.minimum(cs.load + tick / timeline.load, 1.0), cs.load)
            load = jnp.where(want, up, jnp.maximum(cs.load - tick / timeline.unload, 0.0))
            held = (anchored & (current > 0))[:, None]
            f_track = self._tracking(x_ref, v_ref, x, v, jac, nrm, held, tracked)

            # the force solve on the observed tool, blended over the changed link's load
            radius = jnp.asarray(self.hand.link_radius, jnp.float32)[:, None]
            surface = jnp.where(anchored[:, None], anchor, self._target(current)) + radius * (nrm @ mat)
            pts = p + surface @ mat.T
            if self.config.controller.frames == "measured":
                nrm = self.measured_normals(x, p, mat, nrm, held[:, 0])
            required, feedback = self.tool_wrench(obs, episode, ref, external, uncapped=True)
            mu = self.config.controller.friction_margin * episode.friction
            com = p + mat @ episode.com
            active = (current > 0) & (load > 0)
            posture = self.config.fingers.posture_kp * (cs.q_rest - obs.q)
            f_a = self._forces(pts, nrm, active, mu, required, com, cs.f_with)
            f_b = self._forces(pts, nrm, active & ~cs.changed, mu, required, com, cs.f_without)
            share = jnp.sum(load * cs.changed)
            forces = share * f_a + (1 - share) * f_b
            tau = jnp.einsum("lij,li->j", jac, forces + f_track) + posture + obs.bias  # bias: gravity compensation
            strength = cs.strength
            if self.config.controller.strength_rate > 0:
                strength = self._strengths(cs, tau, jac, active, feedback, episode)
                tau = tau / strength
            tau = jnp.clip(tau, *self.ctrl_range)
        return tau, cs.replace(load=load, f_with=f_a, f_without=f_b, anchor=anchor, anchored=anchored,
                               strength=strength, estimate=estimate)
