"""The physics check: the scene in MuJoCo MJX, a contact controller that realises reference grasps, and an
episode runner (open or closed loop) batched over episodes and policies.

    phys = Physics()                                     # MJX model built from models/scene.xml
    result = phys.simulate(policy, episode)              # one episode: pure, jit- and vmap-able
    results = phys.simulate_batch(policies, episodes)    # many episodes (x policies) as one XLA kernel

Timeline of an episode (times in `PhysicsConfig`):

  start   the tool rests at waypoint 0 on two small pedestals (support by contact, standing in for the table the
          scene starts it on: at the table's height the fingertips cannot reach the side faces), the hand in the
          start grasp realised there by IK; the pedestals drop away after the first decision's segment, and from
          then on the fingers alone hold the tool (touching the table counts as a fall from then on);
  t = 0 .. T-1   at waypoint t the policy observes the *simulated* state (joint angles, tool pose and velocity:
          the surrogate's `State`) and picks an action; the new reference grasp is realised by IK at waypoint t
          (or the observed pose, `targets_at`) and at waypoint t+1, and the controller blends to it while
          tracking the tool's reference motion to waypoint t+1 (the last decision re-grasps at the final pose);
  hold    the episode's external wrench ramps on at the final pose (`xfrc_applied` at the tool's CoM); the
          tool's angle and position errors are averaged over the hold.

Every phase is made of segments of `segment` seconds (T decision segments, then `hold` / `segment` hold
segments), so the program is one `lax.scan` over segments around one `lax.scan` over control ticks: a single
copy of `mjx.step`, of the IK and of the policy, which keeps the compile time down.

A tool that touches the table, moves `fall_distance` from its reference or turns more than `fall_angle` has
fallen: its angle error is 180 degrees and its simulation freezes there (a dropped tool never reaches the
solver as NaN).

The contact controller (per control tick, joint torques clipped to the motors' range):

  tau = kp (q_ref - q) - kd dq + sum_l J_l(q)^T f_l

  * q_ref: IK joint targets of the reference grasp, from waypoint t to waypoint t+1, linear over the segment (the
    IK puts each active link's surface on its contact point). `targets_at="observed"` starts them from the
    observed tool pose instead, as a tracking controller would; measured on the nominal episode (C MuJoCo, same
    controller), that made even a held four-fingertip grasp drop the tool mid-lift: the IK from the fixed start
    configuration jumps with small pose errors, and the finger targets with it. The policy still acts on the
    observed state, so the loop is closed at the level of grasps;
  * f_l: inverse dynamics of the tool: the wrench solve's contact forces (inside the friction cones) for
    m (a_ref - g) while moving, and for -m g - w_ext during the hold (the task's wrench is known, as when
    tightening a bolt; `feedforward_external=False` leaves it to the grasp's passive stiffness), plus `squeeze`
    newtons along each contact normal projected onto the grasp matrix's null space (internal force: grips
    without changing the net wrench);
  * J_l: the Jacobian of the link point closest to its contact point;
  * a grasp change (one link per decision, as the action space allows: add, remove or slide) is a transition
    of `transition` seconds in three equal phases: *unload* -- the forces go over to the links the old and new
    grasps share (their own wrench solve), while the other joint targets blend to the new IK; *move* -- the
    changing link's finger travels from its old to its new joint targets, unloaded and lifted `lift` metres off
    the tool along the contact normal at mid-move (a bump in joint space); *load* -- the forces blend
    to the new grasp's. A slide that dragged a loaded fingertip across the tool would push the tool with friction.

Why these gains: kp = 10 N m/rad gives ~1 N per mm of fingertip error at a 10 cm lever, enough to reach a contact
within a segment without the PD term swamping the feed-forward grip forces (a few N); kd = 0.05 N m s/rad damps
the 16 light fingers at the 10 ms control period; the 10 N squeeze is ~3x the nominal tool weight. The motors
(the model's ctrlrange, 3 N m) are sized so that a thumb at full reach can add that squeeze to the weight-bearing
forces: with 1.5 N m the thumb saturated, the forces no longer balanced, and even four fingertips let the tool
tilt onto the table (measured in C MuJoCo, same controller).

Contact model: MJX (mujoco-mjx 3.17) misses tilted capsule-box contacts that C MuJoCo finds, so the physics
model replaces every hand capsule, for contact, by `spheres_per_capsule` spheres along its axis (sphere-box and
sphere-plane are exact in MJX) and lists the contacts explicitly: tool x table, tool x medial/distal-link spheres
(friction = the episode's), distal spheres x table, tool x start pedestals. The surrogate's geometry (the same
model file) is unchanged.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from gsp_jax import hand as hand_lib
from gsp_jax import ik, kinematics, scenario, wrench
from gsp_jax.scenario import Episode
from gsp_jax.surrogate import RewardTerms, State, Surrogate

TOOL_BODY = "wrench"
TABLE_GEOM = "table"
# Start supports: name -> (tool geom it carries, x of its centre in the tool frame [m], half sizes [m]); clear of
# every candidate contact of the fingers (the head's sides, the handle's sides and underside at x = 0).
PEDESTALS = {"pedestal_head": ("head", 0.075, (0.012, 0.012, 0.004)),
             "pedestal_handle": ("handle", -0.07, (0.012, 0.008, 0.004))}


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """Simulation, controller and outcome settings: one place for each."""

    # simulation
    timestep: float = 0.002  # [s] physics step
    control_every: int = 5  # physics steps per control tick (10 ms)
    solver_iterations: int = 20  # Newton iterations per step (MJX stops earlier when converged)
    ls_iterations: int = 20  # line-search iterations
    spheres_per_capsule: int = 4  # contact spheres replacing each hand capsule
    tool_contact_links: tuple[str, ...] = ("medial", "distal")  # hand capsules (name suffixes) that touch the tool
    table_friction: float = 0.6
    # timeline
    segment: float = scenario.DT  # [s] between waypoints (episodes must have this dt)
    transition: float = 0.15  # [s] grasp change: unload, move, load (a third each)
    lift: float = 0.004  # [m] how far a moving link lifts off the tool mid-move
    hold: float = 1.0  # [s] under the external wrench at the final pose, rounded to whole segments
    ramp: float = 0.1  # [s] for the external wrench to reach its full value
    # controller
    targets_at: str = "reference"  # IK of each decision's start: "reference" (waypoint t) or "observed" tool pose
    kp: float = 10.0  # [N m/rad]
    kd: float = 0.05  # [N m s/rad]
    squeeze: float = 10.0  # [N] internal grip force per contact
    feedforward_external: bool = True  # the hold's forces also resist the known w_ext (False: gravity only)
    # outcome
    fall_angle: float = 90.0  # [deg] tool rotation from its reference beyond which it counts as fallen
    fall_distance: float = 0.03  # [m] tool position error beyond which it counts as fallen
    table_margin: float = 0.0005  # [m] lowest tool point below this height: touching the table
    fallen_error: float = 180.0  # [deg] the angle error reported for a fallen tool

    @property
    def tick(self) -> float:
        return self.timestep * self.control_every

    def ticks(self, seconds: float) -> int:
        return max(1, int(round(seconds / self.tick)))

    def __post_init__(self):
        if self.transition > self.segment:
            raise ValueError(f"PhysicsConfig.transition must be <= segment ({self.segment}), got {self.transition}")
        for name in ("timestep", "segment", "hold", "transition", "ramp", "kp", "fall_angle"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"PhysicsConfig.{name} must be > 0, got {value!r}")
        for name in ("control_every", "solver_iterations", "ls_iterations", "spheres_per_capsule"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"PhysicsConfig.{name} must be an int >= 1, got {value!r}")
        if self.targets_at not in ("reference", "observed"):
            raise ValueError(f"PhysicsConfig.targets_at must be 'reference' or 'observed', got {self.targets_at!r}")
        if self.kd < 0 or self.squeeze < 0:
            raise ValueError(f"PhysicsConfig kd and squeeze must be >= 0, got {self.kd}, {self.squeeze}")


def physics_model(path=hand_lib.SCENE_XML, config: PhysicsConfig = PhysicsConfig()) -> mujoco.MjModel:
    """The physics model of a scene file: contact spheres for the hand capsules and an explicit contact list
    (see the module docstring); solver settings from `config`."""
    base = hand_lib.load_mjmodel(path)
    spec = mujoco.MjSpec.from_file(str(path))
    name = lambda obj, i: mujoco.mj_id2name(base, obj, i)  # noqa: E731
    tool = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_BODY, TOOL_BODY)
    tool_geoms = [name(mujoco.mjtObj.mjOBJ_GEOM, g) for g in range(base.ngeom) if base.geom_bodyid[g] == tool]
    tool_geom0 = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_GEOM, tool_geoms[0])
    to_tool, to_table = [], []
    for g in range(base.ngeom):
        if base.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE:
            continue
        gname, bname = name(mujoco.mjtObj.mjOBJ_GEOM, g), name(mujoco.mjtObj.mjOBJ_BODY, base.geom_bodyid[g])
        radius, half = base.geom_size[g][:2]
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, base.geom_quat[g])
        axis = mat.reshape(3, 3)[:, 2]
        body = spec.body(bname)
        n_s = config.spheres_per_capsule
        for k, z in enumerate(np.linspace(-half, half, n_s) if n_s > 1 else [0.0]):
            sname = f"{gname}_sphere{k}"
            body.add_geom(name=sname, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius, 0, 0],
                          pos=base.geom_pos[g] + axis * z, contype=0, conaffinity=0, density=0.0, group=3)
            if gname.endswith(config.tool_contact_links):
                to_tool.append(sname)
            if gname.endswith("distal"):
                to_table.append(sname)
    for pname, (tg, x, half) in PEDESTALS.items():
        spec.worldbody.add_geom(name=pname, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half), pos=[x, 0, -1.0],
                                rgba=[0.45, 0.35, 0.25, 1])
    for g in spec.geoms:
        g.contype, g.conaffinity = 0, 0
    solref, solimp = base.geom_solref[tool_geom0].copy(), base.geom_solimp[tool_geom0].copy()
    fric = lambda mu: [mu, mu, 0.005, 0.0001, 0.0001]  # noqa: E731
    for tg in tool_geoms:
        spec.add_pair(name=f"{tg}-{TABLE_GEOM}", geomname1=tg, geomname2=TABLE_GEOM, condim=3,
                      friction=fric(config.table_friction), solref=solref, solimp=solimp)
        for s in to_tool:  # friction set per episode (Physics.model_for)
            spec.add_pair(name=f"{tg}-{s}", geomname1=tg, geomname2=s, condim=3, friction=fric(scenario.FRICTION0),
                          solref=solref, solimp=solimp)
    for pname, (tg, _, _) in PEDESTALS.items():
        spec.add_pair(name=f"{tg}-{pname}", geomname1=tg, geomname2=pname, condim=3,
                      friction=fric(config.table_friction), solref=solref, solimp=solimp)
    for s in to_table:
        spec.add_pair(name=f"{s}-{TABLE_GEOM}", geomname1=s, geomname2=TABLE_GEOM, condim=3,
                      friction=fric(config.table_friction), solref=solref, solimp=solimp)
    model = spec.compile()
    model.opt.timestep = config.timestep
    model.opt.iterations, model.opt.ls_iterations = config.solver_iterations, config.ls_iterations
    return model


@struct.dataclass
class Reference:
    """What the controller tracks over one segment: start (waypoint t, or the observed pose) and end (waypoint
    t+1)."""

    q0: jax.Array  # (J,) joint targets at the segment's start [rad]
    q1: jax.Array  # (J,) ... and end
    p0: jax.Array  # (L, 3) contact points, world [m]
    p1: jax.Array  # (L, 3)
    f0: jax.Array  # (L, 3) feed-forward forces on the tool, world [N]
    f1: jax.Array  # (L, 3)
    f_hold: jax.Array  # (L, 3) forces for -m g - w_ext at the end pose (used by the hold after the last decision)
    f_mid: jax.Array  # (L, 3) forces with only the links the previous and this grasp share (during a change)
    active: jax.Array  # (L,) bool, links the reference grasp puts in contact
    changed: jax.Array  # (L,) bool, the link whose option this decision changed
    moving: jax.Array  # (J,) bool, the joints that move the changed link
    q_lift: jax.Array  # (J,) joint offset that lifts the changed link `lift` off the tool (added mid-move)

    def at(self, phase: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(q, p, f) at phase in [0, 1] of the segment."""
        lerp = lambda a, b: (1 - phase) * a + phase * b  # noqa: E731
        return lerp(self.q0, self.q1), lerp(self.p0, self.p1), lerp(self.f0, self.f1)


@struct.dataclass
class Result:
    """One simulated episode. Shapes for one episode (vmap adds leading axes); K control ticks in all."""

    actions: jax.Array  # (T,) int32, the policy's actions
    grasps: jax.Array  # (T,) int32, reference grasp after each decision
    angle_error: jax.Array  # () [deg] mean tool angle error over the hold; `fallen_error` (180) if it fell
    position_error: jax.Array  # () [m] mean tool position error over the hold (meaningless if it fell)
    max_angle: jax.Array  # () [deg] largest angle error before the hold (the lift's quality)
    fell: jax.Array  # () bool: touched the table, dropped, or turned past fall_angle
    fall_time: jax.Array  # () [s] when it fell; -1 if it did not
    angle: jax.Array  # (K,) [deg] angle error at each control tick
    qpos: jax.Array  # (K, nq) the simulated configuration at each control tick (for plots and video)


@struct.dataclass
class _Carry:
    data: mjx.Data
    ref: Reference
    grasp: jax.Array
    fell: jax.Array
    fall_tick: jax.Array
    tick: jax.Array


class Physics:
    """MJX scene + contact controller + episode runner for one hand/tool model. Stateless after construction."""

    def __init__(self, surrogate: Surrogate | None = None, config: PhysicsConfig = PhysicsConfig(), path=None):
        self.surrogate = surrogate or Surrogate()
        self.hand, self.space, self.config = self.surrogate.hand, self.surrogate.space, config
        self.model = physics_model(path or hand_lib.SCENE_XML, config)
        m = self.model
        self.mx = mjx.put_model(m)
        self.tool_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, TOOL_BODY)
        tool_joint = int(np.flatnonzero(m.jnt_bodyid == self.tool_body)[0])
        self.tool_qpos, self.tool_dof = int(m.jnt_qposadr[tool_joint]), int(m.jnt_dofadr[tool_joint])
        joint_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in self.hand.joint_names]
        self.hand_qpos = np.array([m.jnt_qposadr[j] for j in joint_ids])
        self.hand_dof = np.array([m.jnt_dofadr[j] for j in joint_ids])
        act_of = {int(m.actuator_trnid[a, 0]): a for a in range(m.nu)}
        missing = [n for n, j in zip(self.hand.joint_names, joint_ids) if j not in act_of]
        if missing:
            raise ValueError(f"hand joints without a motor in the scene: {missing}")
        self.hand_act = np.array([act_of[j] for j in joint_ids])
        self.ctrl_range = tuple(np.asarray(m.actuator_ctrlrange[self.hand_act].T, np.float32))  # motor limits (J,) x 2
        self.finger_tool_pairs = np.array(
            [p for p in range(m.npair) if self.tool_body in (m.geom_bodyid[m.pair_geom1[p]], m.geom_bodyid[m.pair_geom2[p]])
             and not {TABLE_GEOM, *PEDESTALS} & {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, m.pair_geom1[p]),
                                                 mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, m.pair_geom2[p])}])
        box_names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in range(m.ngeom) if m.geom_bodyid[g] == self.tool_body]
        self.pedestal_geoms = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in PEDESTALS])
        self.pedestal_specs = [(box_names.index(tg), x, half) for tg, x, half in PEDESTALS.values()]
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float32)
        self.tool_corners = np.concatenate([  # (8 NB, 3) box corners in the tool frame
            self.hand.tool_box_pos[b] + (corners * self.hand.tool_box_half[b]) @ self.hand.tool_box_mat[b].T
            for b in range(len(self.hand.tool_box_half))]).astype(np.float32)
        c = config
        self.n_segment = c.ticks(c.segment)  # control ticks per segment
        self.n_hold = max(1, int(round(c.hold / c.segment)))  # hold segments
        self._jitted = {}

    def n_ticks(self, n_steps: int) -> int:
        """Control ticks of an episode with n_steps waypoints (the length of `Result.angle`)."""
        return (n_steps + self.n_hold) * self.n_segment

    def hold_time(self, n_steps: int) -> float:
        """Simulated time at which the hold starts [s]."""
        return n_steps * self.n_segment * self.config.tick

    # ------------------------------------------------------------------------------------------- the world
    def model_for(self, episode: Episode) -> mjx.Model:
        """The MJX model with the episode's tool mass, inertia, centre of mass and finger-tool friction, and the
        pedestals under the tool at waypoint 0 (`supported(model, False)` removes them)."""
        b, mx = self.tool_body, self.mx
        mu = jnp.asarray(episode.friction, jnp.float32)
        mat0 = kinematics.quat_to_mat(episode.quats[0])
        geom_pos = mx.geom_pos
        for gid, (box, x, half) in zip(self.pedestal_geoms, self.pedestal_specs):
            corners = (self.tool_corners[8 * box : 8 * box + 8] @ mat0.T) + episode.waypoints[0]
            top = jnp.min(corners[:, 2])
            geom_pos = geom_pos.at[gid].set(jnp.stack([episode.waypoints[0, 0] + x, episode.waypoints[0, 1], top - half[2]]))
        return mx.replace(
            geom_pos=geom_pos,
            body_mass=mx.body_mass.at[b].set(episode.mass),
            body_inertia=mx.body_inertia.at[b].set(episode.inertia),
            body_ipos=mx.body_ipos.at[b].set(episode.com),
            pair_friction=mx.pair_friction.at[self.finger_tool_pairs, :2].set(mu),
        )

    def supported(self, mx: mjx.Model, on: jax.Array) -> mjx.Model:
        """`mx` with the pedestals in place (on) or 1 m below the table (off)."""
        away = mx.geom_pos.at[self.pedestal_geoms, 2].add(-1.0)
        return mx.replace(geom_pos=jnp.where(on, mx.geom_pos, away))

    def initial_data(self, mx: mjx.Model, episode: Episode, q: jax.Array, pos: jax.Array) -> mjx.Data:
        """Hand at joint angles q (J,), tool at rest at `pos` (3,) in waypoint 0's orientation."""
        d = mjx.make_data(mx)
        qpos = d.qpos.at[self.hand_qpos].set(q)
        qpos = qpos.at[self.tool_qpos : self.tool_qpos + 3].set(pos)
        qpos = qpos.at[self.tool_qpos + 3 : self.tool_qpos + 7].set(episode.quats[0])
        return d.replace(qpos=qpos)

    def tool_pose(self, data: mjx.Data) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Observed tool position (3,), orientation (4,) and velocity (6,: linear world, angular body frame)."""
        a, v = self.tool_qpos, self.tool_dof
        return data.qpos[a : a + 3], data.qpos[a + 3 : a + 7], data.qvel[v : v + 6]

    def observe(self, data: mjx.Data, grasp: jax.Array, t: jax.Array, episode: Episode) -> State:
        """The surrogate `State` of a simulated one: what every policy acts on."""
        pos, quat, vel = self.tool_pose(data)
        return State(grasp=jnp.asarray(grasp, jnp.int32), t=jnp.asarray(t, jnp.int32), q=data.qpos[self.hand_qpos],
                     tool_pos=pos, tool_quat=quat, tool_vel=vel, episode=episode, done=jnp.array(False),
                     terms=RewardTerms.zeros())

    # -------------------------------------------------------------------------------------- the controller
    def grip_forces(self, contacts, episode: Episode, pos, quat, required: jax.Array) -> jax.Array:
        """(L, 3) feed-forward contact forces: the wrench solve for `required` (6,) plus the null-space squeeze."""
        sol = self.surrogate.wrench_error(contacts, episode, pos, quat, required)
        mask = contacts.realised.astype(jnp.float32)
        com = pos + kinematics.quat_to_mat(quat) @ episode.com
        G = wrench.grasp_matrix(contacts.points, com) * jnp.repeat(mask, 3)[None]  # (6, 3L)
        n = (contacts.normals * mask[:, None]).ravel()
        internal = (n - jnp.linalg.pinv(G) @ (G @ n)) * jnp.repeat(mask, 3)
        return sol.forces + self.config.squeeze * internal.reshape(-1, 3)

    def reference(self, episode: Episode, grasp: jax.Array, t: jax.Array, pos, quat, previous=None) -> Reference:
        """References of decision t: `grasp` realised at the pose (pos, quat) and at waypoint t+1; forces
        for the reference acceleration at t (as the surrogate's term (a)) and for gravity at t+1; the change from
        grasp `previous` (default: none)."""
        previous = grasp if previous is None else previous
        changed = self.space.decode(previous) != self.space.decode(grasp)  # (L,)
        moving = jnp.any(changed[:, None] & jnp.asarray(self.hand.joint_moves_body[self.hand.link_body] > 0), axis=0)
        sur, last = self.surrogate, episode.n_steps - 1
        wp = episode.waypoints
        t_next = jnp.minimum(t + 1, last)
        now = sur.realise(grasp, pos, quat)
        nxt = sur.realise(grasp, wp[t_next], episode.quats[t_next])
        move = sur.move_wrench(episode, t)
        f0 = self.grip_forces(now, episode, pos, quat, move)
        weight = jnp.concatenate([-episode.mass * sur.gravity, jnp.zeros(3, jnp.float32)])
        f1 = self.grip_forces(nxt, episode, wp[t_next], episode.quats[t_next], weight)
        expected = episode.w_ext if self.config.feedforward_external else jnp.zeros_like(episode.w_ext)
        f_hold = self.grip_forces(nxt, episode, wp[t_next], episode.quats[t_next], weight - expected)
        shared = now.replace(realised=now.realised & ~changed)
        # lift direction: the changed link's contact normal (the new option's, or the old one's when it lets go)
        mat = kinematics.quat_to_mat(quat)
        _, _, n_old = ik.grasp_targets(self.hand, self.space.decode(previous), pos, mat)
        normal = jnp.sum(jnp.where((self.space.decode(grasp) > 0)[:, None], now.normals, n_old) * changed[:, None], 0)
        _, _, axes, anchors = kinematics.chain(self.hand, now.ik.q)
        link = jnp.argmax(changed)
        points = kinematics.closest_on_links(self.hand, now.ik.q, now.points)
        jac = kinematics.point_jacobian(self.hand, axes, anchors, self.hand.link_body, points)[link]  # (3, J)
        q_lift = jac.T @ jnp.linalg.solve(jac @ jac.T + 1e-6 * jnp.eye(3), -self.config.lift * normal)
        f_mid = self.grip_forces(shared, episode, pos, quat, move)
        return Reference(q0=now.ik.q, q1=nxt.ik.q, p0=now.points, p1=nxt.points, f0=f0, f1=f1, f_hold=f_hold,
                         f_mid=f_mid, active=nxt.realised, changed=changed, moving=moving, q_lift=q_lift * jnp.any(changed))

    def control(self, data: mjx.Data, q_ref: jax.Array, points: jax.Array, forces: jax.Array) -> jax.Array:
        """Motor commands (nu,): PD to q_ref (J,) plus J^T f for forces (L, 3) at the links nearest `points`."""
        c, hand = self.config, self.hand
        q, dq = data.qpos[self.hand_qpos], data.qvel[self.hand_dof]
        _, _, axes, anchors = kinematics.chain(hand, q)
        at = kinematics.closest_on_links(hand, q, points)
        jac = kinematics.point_jacobian(hand, axes, anchors, hand.link_body, at)  # (L, 3, J)
        tau = c.kp * (q_ref - q) - c.kd * dq + jnp.einsum("lij,li->j", jac, forces)
        lo, hi = self.ctrl_range
        return jnp.zeros(self.model.nu, jnp.float32).at[self.hand_act].set(jnp.clip(tau, lo, hi))

    def targets(self, prev: Reference, ref: Reference, i: jax.Array, k: jax.Array, episode: Episode):
        """Controller targets at tick i (of `n_segment`) of segment k, going from `prev` to `ref`: joint targets
        (J,), contact points (L, 3), feed-forward forces (L, 3), the external wrench's weight in [0, 1], and the
        reference tool position (3,) for the fall check."""
        c, n, T = self.config, self.n_segment, episode.n_steps
        decision, t = k < T, jnp.minimum(k, T - 1)
        s = (i + 1).astype(jnp.float32)
        phase, third = s / n, c.transition / 3
        u, mv, ld = (jnp.clip((s * c.tick - j * third) / third, 0.0, 1.0) for j in range(3))  # unload, move, load
        q_new, p_new, f_new = ref.at(phase)
        q_move = (1 - mv) * prev.q1 + mv * q_new + jnp.sin(jnp.pi * mv) * ref.q_lift
        q = jnp.where(ref.moving, q_move, (1 - u) * prev.q1 + u * q_new)
        p = jnp.where((ref.changed & (mv < 1))[:, None] | ~ref.active[:, None], prev.p1, p_new)
        f = jnp.where(ld > 0, (1 - ld) * ref.f_mid + ld * f_new, (1 - u) * prev.f1 + u * ref.f_mid)
        held = jnp.maximum(0.0, ((k - T) * n + s) * c.tick)  # time under the external wrench
        w = jnp.where(decision, 0.0, jnp.minimum(1.0, held / c.ramp))
        f = (1 - w) * f + w * ref.f_hold
        wp = episode.waypoints
        ref_pos = jnp.where(decision, (1 - phase) * wp[t] + phase * wp[jnp.minimum(t + 1, T - 1)], wp[-1])
        return q, p, f, w, ref_pos

    # ------------------------------------------------------------------------------------------ the runner
    def _status(self, data: mjx.Data, ref_pos, ref_quat, lifted=True) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(angle error [deg], position error [m], fallen?) of the tool against a reference pose."""
        c = self.config
        pos, quat, _ = self.tool_pose(data)
        quat = quat / jnp.linalg.norm(quat)
        cos = jnp.clip(jnp.abs(jnp.dot(quat, ref_quat)), 0.0, 1.0)
        angle = jnp.degrees(2 * jnp.arccos(cos))
        perr = jnp.linalg.norm(pos - ref_pos)
        lowest = jnp.min((self.tool_corners @ kinematics.quat_to_mat(quat).T)[:, 2]) + pos[2]
        finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
        fell = ~finite | (lifted & (lowest < c.table_margin)) | (perr > c.fall_distance) | (angle > c.fall_angle)
        return jnp.where(finite, angle, 0.0), jnp.where(finite, perr, 0.0), fell

    def _advance(self, mx, carry: _Carry, q_ref, points, forces, w_ext, ref_pos, ref_quat, lifted):
        """One control tick: command, `control_every` physics steps, the fall check (the table counts once
        `lifted`); a fallen tool freezes."""
        ctrl = self.control(carry.data, q_ref, points, forces)
        xfrc = jnp.zeros((self.model.nbody, 6), jnp.float32).at[self.tool_body].set(w_ext)
        data = carry.data.replace(ctrl=ctrl, xfrc_applied=xfrc)
        data = jax.lax.fori_loop(0, self.config.control_every, lambda _, d: mjx.step(mx, d), data)
        angle, perr, fell_now = self._status(data, ref_pos, ref_quat, lifted)
        fell = carry.fell | fell_now
        finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
        keep = carry.fell | ~finite  # freeze: a fallen tool stays put, a non-finite step is never stored
        data = jax.tree.map(lambda old, new: jnp.where(keep, old, new), carry.data, data)
        fall_tick = jnp.where(fell & ~carry.fell, carry.tick, carry.fall_tick)
        carry = carry.replace(data=data, fell=fell, fall_tick=fall_tick, tick=carry.tick + 1)
        return carry, (angle, perr, data.qpos)

    def simulate(self, policy, episode: Episode) -> Result:
        """One episode of `policy` (anything with `act(State) -> action`) on `episode`; see the module docstring.
        Open loop is `policies.SequencePolicy`; closed loop is any policy that reads the continuous state."""
        c, T, n = self.config, episode.n_steps, self.n_segment
        mx = self.model_for(episode)
        wp, quats = episode.waypoints, episode.quats
        pos0 = wp[0]
        now = self.surrogate.realise(episode.start_grasp, pos0, quats[0])
        weight = jnp.concatenate([-episode.mass * self.surrogate.gravity, jnp.zeros(3, jnp.float32)])
        f = self.grip_forces(now, episode, pos0, quats[0], weight)
        start = Reference(q0=now.ik.q, q1=now.ik.q, p0=now.points, p1=now.points, f0=f, f1=f, f_hold=f, f_mid=f,
                          active=now.realised, changed=jnp.zeros(self.hand.n_links, bool),
                          moving=jnp.zeros(self.hand.n_joints, bool), q_lift=jnp.zeros(self.hand.n_joints))
        data = self.initial_data(mx, episode, start.q1, pos0)
        carry = _Carry(data=data, ref=start, grasp=jnp.asarray(episode.start_grasp, jnp.int32), fell=jnp.array(False),
                       fall_tick=jnp.asarray(-1, jnp.int32), tick=jnp.asarray(0, jnp.int32))

        def segment(carry: _Carry, k):
            decision, t = k < T, jnp.minimum(k, T - 1)
            t1 = jnp.minimum(t + 1, T - 1)
            pos, quat, _ = self.tool_pose(carry.data)
            if c.targets_at == "reference":
                pos, quat = wp[t], quats[t]
            observed = self.observe(carry.data, carry.grasp, t, episode)  # the policy acts only at waypoints
            action = jax.lax.cond(decision, lambda s: jnp.asarray(policy.act(s), jnp.int32), lambda s: jnp.int32(0), observed)
            grasp = jnp.where(decision, self.space.apply(carry.grasp, action)[0], carry.grasp)
            prev = carry.ref
            still = prev.replace(q0=prev.q1, p0=prev.p1, f0=prev.f1, f_mid=prev.f1, changed=jnp.zeros_like(prev.changed),
                                 moving=jnp.zeros_like(prev.moving), q_lift=jnp.zeros_like(prev.q_lift))  # hold: stay
            ref = jax.tree.map(lambda a, b: jnp.where(decision, a, b),
                               self.reference(episode, grasp, t, pos, quat, carry.grasp), still)

            def tick(carry, i):
                q, p, f, w, ref_pos = self.targets(prev, ref, i, k, episode)
                return self._advance(mxk, carry, q, p, f, w * episode.w_ext, ref_pos, quats[t1], k > 0)

            mxk = self.supported(mx, k == 0)
            carry, trace = jax.lax.scan(tick, carry.replace(ref=ref, grasp=grasp), jnp.arange(n))
            return carry, (jnp.where(decision, action, -1), grasp, trace)

        carry, (actions, grasps, trace) = jax.lax.scan(segment, carry, jnp.arange(T + self.n_hold))
        angle, perr, qpos = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), trace)
        n_before = T * n
        fell = carry.fell
        return Result(
            actions=actions[:T],
            grasps=grasps[:T],
            angle_error=jnp.where(fell, c.fallen_error, jnp.mean(angle[n_before:])),
            position_error=jnp.mean(perr[n_before:]),
            max_angle=jnp.where(fell & (carry.fall_tick < n_before), c.fallen_error, jnp.max(angle[:n_before])),
            fell=fell,
            fall_time=jnp.where(fell, (carry.fall_tick + 1).astype(jnp.float32) * c.tick, -1.0),
            angle=angle,
            qpos=qpos,
        )

    def simulate_batch(self, policy, episodes: Episode, policy_axis: int | None = None) -> Result:
        """`simulate` vmapped over a batch of episodes (leading axis), jitted once per structure. With
        policy_axis=0 the policy pytree carries the same batch axis (e.g. one `SequencePolicy` per episode:
        episodes x policies flattened into one batch)."""
        check_episodes(episodes, self.config)
        key = policy_axis
        if key not in self._jitted:
            self._jitted[key] = jax.jit(jax.vmap(self.simulate, in_axes=(policy_axis, 0)))
        return self._jitted[key](policy, episodes)


def check_episodes(episodes: Episode, config: PhysicsConfig) -> None:
    """Clear errors for episodes the physics check cannot run (concrete arrays only)."""
    dt = np.asarray(episodes.dt)
    if not np.allclose(dt, config.segment, rtol=1e-5):
        raise ValueError(f"episode.dt must equal PhysicsConfig.segment = {config.segment} s, got {np.unique(dt)}")
    for name in ("mass", "friction"):
        value = np.asarray(getattr(episodes, name))
        if not np.all(np.isfinite(value) & (value > 0)):
            raise ValueError(f"episode.{name} must be finite and > 0, got {value}")
    inertia = np.asarray(episodes.inertia)
    if not np.all(np.isfinite(inertia) & (inertia > 0)):
        raise ValueError(f"episode.inertia must be finite and > 0, got {inertia}")

