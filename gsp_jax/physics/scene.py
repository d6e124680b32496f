"""The physics scene: the MuJoCo model of the hand, the tool and the table as the physics check simulates it, the
index arrays both backends (MJX and C MuJoCo) need, the per-episode model fields, and the observation and outcome
of a simulated state.

Contact model: MJX (mujoco-mjx 3.17) misses tilted capsule-box contacts that C MuJoCo finds, so the physics model
replaces every hand capsule, for contact, by `spheres_per_capsule` spheres along its axis (sphere-box and
sphere-plane are exact in MJX) and lists the contacts explicitly: tool x table, tool x medial/distal-link spheres
(friction = the episode's), distal spheres x table, tool x start pedestals. The surrogate's geometry (the same
model file) is unchanged.

The start: the tool rests at waypoint 0 on two small pedestals (support by contact, standing in for the table the
scene starts it on: at the table's height the fingertips cannot reach the side faces); they sink away after the
first segment (at at `pedestal_speed`: the fingers take the weight over a few tens of milliseconds), and from
then on the fingers alone hold the tool.
"""
from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from gsp_jax import hand as hand_lib
from gsp_jax import kinematics, scenario
from gsp_jax.physics.config import PhysicsConfig
from gsp_jax.scenario import Episode

TOOL_BODY = hand_lib.TOOL_BODY
TABLE_GEOM = "table"
# Start supports: name -> (tool geom it carries, x of its centre in the tool frame [m], half sizes [m]); clear of
# every candidate contact of the fingers (the head's sides, the handle's sides and underside at x = 0).
PEDESTALS = {"pedestal_head": ("head", 0.075, (0.012, 0.012, 0.004)),
             "pedestal_handle": ("handle", -0.07, (0.012, 0.008, 0.004))}
AWAY = -1.0  # [m] pedestals are moved this far down when they drop away


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
        spec.worldbody.add_geom(name=pname, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half), pos=[x, 0, AWAY],
                                rgba=[0.45, 0.35, 0.25, 1])
    for g in spec.geoms:
        g.contype, g.conaffinity = 0, 0
    solref, solimp = base.geom_solref[tool_geom0].copy(), base.geom_solimp[tool_geom0].copy()
    fric = lambda mu: [mu, mu, 0.005, 0.0001, 0.0001]  # noqa: E731
    for tg in tool_geoms:
        spec.add_pair(name=f"{tg}-{TABLE_GEOM}", geomname1=tg, geomname2=TABLE_GEOM, condim=3,
                      friction=fric(config.table_friction), solref=solref, solimp=solimp)
        for s in to_tool:  # friction set per episode (Scene.mjx_model_for / c_model_for)
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
    if not config.implicit_damping:
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    model.opt.noslip_iterations = config.noslip_iterations
    return model


@struct.dataclass
class Observation:
    """What the controller and the policy see of a simulated state (one episode; vmap adds leading axes)."""

    q: jax.Array  # (J,) hand joint angles [rad]
    dq: jax.Array  # (J,) hand joint velocities [rad/s]
    tool_pos: jax.Array  # (3,) tool frame origin, world [m]
    tool_quat: jax.Array  # (4,) tool orientation (w, x, y, z)
    tool_vel: jax.Array  # (6,) linear velocity (world) [m/s] and angular velocity (tool frame) [rad/s]
    bias: jax.Array  # (J,) the hand joints' gravity + Coriolis forces (MuJoCo qfrc_bias) [N m]


@struct.dataclass
class EpisodeFields:
    """The model fields an episode sets (one episode): tool mass, inertia, CoM, finger-tool friction, pedestals."""

    mass: jax.Array  # ()
    inertia: jax.Array  # (3,)
    com: jax.Array  # (3,)
    friction: jax.Array  # ()
    pedestal_pos: jax.Array  # (P, 3) pedestal centres holding the tool at waypoint 0


class Scene:
    """The physics model and its index arrays, shared by the MJX and the C MuJoCo backend."""

    def __init__(self, hand: hand_lib.HandModel, config: PhysicsConfig = PhysicsConfig(), path=None):
        self.hand, self.config = hand, config
        self.model = m = physics_model(path or hand_lib.SCENE_XML, config)
        self.tool_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, TOOL_BODY)
        tool_joint = int(np.flatnonzero(m.jnt_bodyid == self.tool_body)[0])
        self.tool_qpos, self.tool_dof = int(m.jnt_qposadr[tool_joint]), int(m.jnt_dofadr[tool_joint])
        joint_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in hand.joint_names]
        self.hand_qpos = np.array([m.jnt_qposadr[j] for j in joint_ids])
        self.hand_dof = np.array([m.jnt_dofadr[j] for j in joint_ids])
        act_of = {int(m.actuator_trnid[a, 0]): a for a in range(m.nu)}
        missing = [n for n, j in zip(hand.joint_names, joint_ids) if j not in act_of]
        if missing:
            raise ValueError(f"hand joints without a motor in the scene: {missing}")
        self.hand_act = np.array([act_of[j] for j in joint_ids])
        self.ctrl_range = tuple(np.asarray(m.actuator_ctrlrange[self.hand_act].T, np.float32))  # motor limits (J,) x 2
        gname = lambda g: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g)  # noqa: E731
        self.finger_tool_pairs = np.array(
            [p for p in range(m.npair) if self.tool_body in (m.geom_bodyid[m.pair_geom1[p]], m.geom_bodyid[m.pair_geom2[p]])
             and not {TABLE_GEOM, *PEDESTALS} & {gname(m.pair_geom1[p]), gname(m.pair_geom2[p])}])
        box_names = [gname(g) for g in range(m.ngeom) if m.geom_bodyid[g] == self.tool_body]
        self.pedestal_geoms = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in PEDESTALS])
        self.pedestal_specs = [(box_names.index(tg), x, half) for tg, x, half in PEDESTALS.values()]
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float32)
        self.tool_corners = np.concatenate([  # (8 NB, 3) box corners in the tool frame
            hand.tool_box_pos[b] + (corners * hand.tool_box_half[b]) @ hand.tool_box_mat[b].T
            for b in range(len(hand.tool_box_half))]).astype(np.float32)
        self.mx = mjx.put_model(m)

    def joint_inertia(self) -> np.ndarray:
        """(J,) [kg m^2] the hand joints' inertia: the diagonal of the joint-space inertia (armature included, 80-100%
        of it) at the model's reference pose."""
        m = self.model
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        full = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, full)
        return np.diag(full)[self.hand_dof].astype(np.float32)

    # ------------------------------------------------------------------------------------------ episodes
    def episode_fields(self, episode: Episode) -> EpisodeFields:
        """The model fields of one episode (pure JAX; vmap over episodes)."""
        mat0 = kinematics.quat_to_mat(episode.quats[0])
        ped = []
        for box, x, half in self.pedestal_specs:
            corners = (self.tool_corners[8 * box : 8 * box + 8] @ mat0.T) + episode.waypoints[0]
            top = jnp.min(corners[:, 2])
            ped.append(jnp.stack([episode.waypoints[0, 0] + x, episode.waypoints[0, 1], top - half[2]]))
        return EpisodeFields(mass=episode.mass, inertia=episode.inertia, com=episode.com,
                             friction=jnp.asarray(episode.friction, jnp.float32), pedestal_pos=jnp.stack(ped))

    def pedestal_drop(self, time, xp=jnp) -> jax.Array:
        """How far [m] (<= 0) the pedestals have sunk at `time`: in place for the first segment, then sinking at
        `pedestal_speed`, so the fingers take the tool's weight over a few tens of milliseconds. float32; `xp` is
        jax.numpy (traceable) or numpy (the same value without a JAX dispatch: the C backend asks every tick)."""
        c, f32 = self.config, xp.float32
        return -xp.minimum(f32(c.pedestal_speed) * xp.maximum(f32(time - c.segment), f32(0.0)), f32(-AWAY))

    @staticmethod
    def pedestal_positions(fields: EpisodeFields, drop):
        """(P, 3) pedestal centres `drop` (<= 0) metres below their start (jax or numpy arrays)."""
        return fields.pedestal_pos + np.array([0.0, 0.0, 1.0], np.float32) * drop

    def mjx_model(self, fields: EpisodeFields, drop: jax.Array) -> mjx.Model:
        """The MJX model with one episode's fields, the pedestals `drop` (<= 0) metres below their start."""
        mx, b = self.mx, self.tool_body
        return mx.replace(
            geom_pos=mx.geom_pos.at[self.pedestal_geoms].set(self.pedestal_positions(fields, drop)),
            body_mass=mx.body_mass.at[b].set(fields.mass),
            body_inertia=mx.body_inertia.at[b].set(fields.inertia),
            body_ipos=mx.body_ipos.at[b].set(fields.com),
            pair_friction=mx.pair_friction.at[self.finger_tool_pairs, :2].set(fields.friction),
        )

    def c_model(self, fields: EpisodeFields) -> mujoco.MjModel:
        """A C MuJoCo model (a copy) with one episode's fields (numpy, one episode), pedestals in place."""
        m, b = copy.copy(self.model), self.tool_body
        self.c_pedestals(m, fields, 0.0)
        m.body_mass[b], m.body_inertia[b], m.body_ipos[b] = fields.mass, fields.inertia, fields.com
        m.pair_friction[self.finger_tool_pairs, :2] = fields.friction
        return m

    def c_pedestals(self, model: mujoco.MjModel, fields: EpisodeFields, drop: float) -> None:
        """Set the pedestals of a C model `drop` (<= 0) metres below their start (in place)."""
        model.geom_pos[self.pedestal_geoms] = self.pedestal_positions(fields, drop)

    def initial_qpos(self, episode: Episode, q: jax.Array) -> jax.Array:
        """(nq,) hand at joint angles q (J,), tool at rest on waypoint 0."""
        qpos = jnp.asarray(self.model.qpos0, jnp.float32).at[self.hand_qpos].set(q)
        qpos = qpos.at[self.tool_qpos : self.tool_qpos + 3].set(episode.waypoints[0])
        return qpos.at[self.tool_qpos + 3 : self.tool_qpos + 7].set(episode.quats[0])

    # ----------------------------------------------------------------------------------------- states
    def observe(self, qpos: jax.Array, qvel: jax.Array, qfrc_bias: jax.Array) -> Observation:
        """The `Observation` of a simulated state (arrays of either backend; one episode)."""
        a, v = self.tool_qpos, self.tool_dof
        quat = qpos[a + 3 : a + 7]
        return Observation(q=qpos[self.hand_qpos], dq=qvel[self.hand_dof], tool_pos=qpos[a : a + 3],
                           tool_quat=quat / jnp.linalg.norm(quat), tool_vel=qvel[v : v + 6], bias=qfrc_bias[self.hand_dof])

    def status(self, obs: Observation, ref_pos, ref_quat, lifted) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(angle error [deg], position error [m], fallen?) of the tool against a reference pose; the table
        counts once `lifted`. A non-finite state counts as fallen (and reads 0 error)."""
        c = self.config
        cos = jnp.clip(jnp.abs(jnp.dot(obs.tool_quat, ref_quat)), 0.0, 1.0)
        angle = jnp.degrees(2 * jnp.arccos(cos))
        perr = jnp.linalg.norm(obs.tool_pos - ref_pos)
        lowest = jnp.min((self.tool_corners @ kinematics.quat_to_mat(obs.tool_quat).T)[:, 2]) + obs.tool_pos[2]
        finite = jnp.all(jnp.isfinite(jnp.concatenate([obs.q, obs.dq, obs.tool_pos, obs.tool_quat, obs.tool_vel])))
        fell = ~finite | (lifted & (lowest < c.table_margin)) | (perr > c.fall_distance) | (angle > c.fall_angle)
        return jnp.where(finite, angle, 0.0), jnp.where(finite, perr, 0.0), fell
