"""The physics scene: the MuJoCo model of the hand, the tool and the table as the physics check simulates it, the
index arrays both backends (MJX and C MuJoCo) need, the per-episode model fields, and the observation and outcome
of a simulated state.

Contact model: MJX (mujoco-mjx 3.17) misses tilted capsule-box contacts that C MuJoCo finds, so the physics model
replaces every hand capsule, for contact, by `SPHERES_PER_CAPSULE` spheres along its axis (sphere-box and
sphere-plane are exact in MJX) and lists the contacts explicitly: tool x table, tool x the spheres of the hand's
`touch_tool` bodies (friction = the episode's), the `touch_table` bodies' spheres x table, tool x start supports
(`HandModel.touch_tool`, `touch_table`, `support_top`: conventions of the model file, no geom names). The
physics step is the scene file's (`<option timestep>`), the pairs with the table take the table geom's sliding
friction. The surrogate's geometry (the same model file) is unchanged.

The start: the tool rests at waypoint 0 on small pedestals (the model's start supports: support by contact, standing
in for the table the scene starts it on: at the table's height the fingertips cannot reach the side faces); they
sink away after the first segment (at `pedestal_speed`: the fingers take the weight over a few tens of
milliseconds), and from then on the fingers alone hold the tool.
"""
from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from mujoco import mjx

from gsp_jax.model import hand as hand_lib
from gsp_jax.model import kinematics, scenario
from gsp_jax.physics import world as world_lib
from gsp_jax.physics.config import PhysicsConfig
from gsp_jax.model.scenario import Episode

AWAY = -1.0  # [m] the start supports are moved this far down when they drop away
SUPPORT = "gsp_support"  # the start supports' geom names: gsp_support1, gsp_support2, ...
SPHERES_PER_CAPSULE = 4  # contact spheres along each hand capsule (MJX misses tilted capsule-box contacts)
REVISION = 2  # the simulated physics of unchanged settings: raised when it changes (2, 2026-12-07: the episodes'
# centres of mass reach C MuJoCo; before, C MuJoCo kept every tool's at its origin). Corpora record it
COM_PROBE = 1e-6  # [m] the tool's centre of mass is compiled this far off its place (`physics_model`: why)


def _named_spec(path) -> mujoco.MjSpec:
    """The scene's spec with every unnamed geom named ``gsp_geom<i>`` (contact pairs name their geoms)."""
    spec = mujoco.MjSpec.from_file(str(path))
    for i, g in enumerate(spec.geoms):
        if not g.name:
            g.name = f"gsp_geom{i}"
    return spec


def physics_model(hand: hand_lib.HandModel, config: PhysicsConfig = PhysicsConfig()) -> mujoco.MjModel:
    """The physics model of the scene a hand was loaded from (`hand.source`): contact spheres for the hand's capsules
    and spheres, and an explicit contact list (see the module docstring): the tool with the table, with the geoms
    of the hand's `touch_tool` bodies (friction set per episode) and with its start supports; the geoms of the
    `touch_table` bodies with the table. The scene file's timestep; solver settings from `config.sim`; the
    joints' damping integrated explicitly (`mjDSBL_EULERDAMP`: Euler's implicit damping re-solves the accelerations
    from the constraint forces, which an unconverged float32 MJX solve leaves as a new contact's whole response;
    docs/physics.md)."""
    if not hand.source:
        raise ValueError("physics: the hand was not loaded from a scene file (hand.source is empty): load it with "
                         "gsp_jax.load_model(path)")
    spec = _named_spec(hand.source)
    base = spec.compile()
    name = lambda obj, i: mujoco.mj_id2name(base, obj, i)  # noqa: E731
    tool = hand_lib.tool_body(base)
    tool_geoms = [name(mujoco.mjtObj.mjOBJ_GEOM, g) for g in hand_lib.tool_geoms(base, tool)]
    tool_geom0 = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_GEOM, tool_geoms[0])
    table_id = hand_lib.table_geom(base)
    table, table_mu = name(mujoco.mjtObj.mjOBJ_GEOM, table_id), float(base.geom_friction[table_id, 0])
    to_tool, to_table = [], []
    for g in range(base.ngeom):
        if int(base.geom_type[g]) not in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_SPHERE)) or \
                base.body_rootid[base.geom_bodyid[g]] == tool or base.geom_bodyid[g] == 0 or \
                not hand_lib.collides(base, g):
            continue
        gname, bname = name(mujoco.mjtObj.mjOBJ_GEOM, g), name(mujoco.mjtObj.mjOBJ_BODY, base.geom_bodyid[g])
        radius, half = base.geom_size[g][:2]
        if int(base.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_SPHERE):
            half = 0.0
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, base.geom_quat[g])
        axis = mat.reshape(3, 3)[:, 2]
        body = spec.body(bname)
        n_s = SPHERES_PER_CAPSULE if half > 0 else 1
        for k, z in enumerate(np.linspace(-half, half, n_s) if n_s > 1 else [0.0]):
            sname = f"{gname}_sphere{k}"
            body.add_geom(name=sname, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius, 0, 0],
                          pos=base.geom_pos[g] + axis * z, contype=0, conaffinity=0, density=0.0, group=3)
            if bname in hand.touch_tool:
                to_tool.append(sname)
            if bname in hand.touch_table:
                to_table.append(sname)
    supports = [f"{SUPPORT}{k + 1}" for k in range(len(hand.support_top))]
    for sname, top, half in zip(supports, hand.support_top, hand.support_half):
        spec.worldbody.add_geom(name=sname, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half), pos=[top[0], top[1], AWAY],
                                rgba=[0.45, 0.35, 0.25, 1])
    for g in spec.geoms:
        g.contype, g.conaffinity = 0, 0
    solref, solimp = base.geom_solref[tool_geom0].copy(), base.geom_solimp[tool_geom0].copy()
    fric = lambda mu: [mu, mu, 0.005, 0.0001, 0.0001]  # noqa: E731
    for tg in tool_geoms:
        spec.add_pair(name=f"{tg}-{table}", geomname1=tg, geomname2=table, condim=3,
                      friction=fric(table_mu), solref=solref, solimp=solimp)
        for s in to_tool:  # friction set per episode (Scene.mjx_model_for / c_model_for)
            spec.add_pair(name=f"{tg}-{s}", geomname1=tg, geomname2=s, condim=3, friction=fric(scenario.FRICTION0),
                          solref=solref, solimp=solimp)
    for k, sname in enumerate(supports):
        tg = tool_geoms[_support_geom(hand, base, tool, k)]
        spec.add_pair(name=f"{tg}-{sname}", geomname1=tg, geomname2=sname, condim=3,
                      friction=fric(table_mu), solref=solref, solimp=solimp)
    for s in to_table:
        spec.add_pair(name=f"{s}-{table}", geomname1=s, geomname2=table, condim=3,
                      friction=fric(table_mu), solref=solref, solimp=solimp)
    # each episode sets the tool's centre of mass (`Scene.c_model`); a body compiled with its centre of mass at its
    # origin is "simple" to MuJoCo, which then skips body_ipos in its kinematics and leaves the coupling of the
    # tool's translation and rotation out of the sparse mass matrix: a centre of mass set later would be ignored.
    # Compiled COM_PROBE off its compiled place, the tool keeps MuJoCo's general path (the episode's value replaces it)
    body = spec.body(name(mujoco.mjtObj.mjOBJ_BODY, tool))
    body.explicitinertial, body.mass = True, float(base.body_mass[tool])
    body.inertia, body.iquat = base.body_inertia[tool].copy(), base.body_iquat[tool].copy()
    body.ipos = base.body_ipos[tool] + np.array([0.0, 0.0, COM_PROBE])
    model = spec.compile()
    sim = config.sim
    model.opt.iterations, model.opt.ls_iterations = sim.solver_iterations, sim.ls_iterations
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    model.opt.noslip_iterations = sim.noslip_iterations
    return model


def _support_geom(hand, base: mujoco.MjModel, tool: int, k: int) -> int:
    """Index (into the tool's collision geoms) of the geom support k carries: the one whose box, at the support's
    top centre, is nearest above it."""
    hull = hand.tool_hull().reshape(-1, 8, 3)  # boxes first, then round geoms: the order of `tool_geoms`
    order = [g for g in hand_lib.tool_geoms(base, tool) if int(base.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_BOX)]
    order += [g for g in hand_lib.tool_geoms(base, tool) if int(base.geom_type[g]) in hand_lib.ROUND_GEOMS]
    top = hand.support_top[k]
    lo, hi = hull.min(1), hull.max(1)
    inside = np.all((lo[:, :2] <= top[:2] + 1e-9) & (hi[:, :2] >= top[:2] - 1e-9), -1)
    gap = np.where(inside, np.abs(lo[:, 2] - top[2]), np.inf)
    best = int(np.argmin(gap)) if np.isfinite(gap).any() else 0
    return hand_lib.tool_geoms(base, tool).index(order[best])


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
    """The model fields an episode sets (one episode): tool mass, inertia, CoM, finger-tool friction, pedestals, and
    the world's factors on the model's own values (`world.World`; exactly 1 in the nominal world, so the model's
    values are kept bit for bit). K finger-tool contact pairs, J hand joints."""

    mass: jax.Array  # ()
    inertia: jax.Array  # (3,)
    com: jax.Array  # (3,)
    friction: jax.Array  # ()
    pedestal_pos: jax.Array  # (P, 3) pedestal centres holding the tool at waypoint 0
    pair_friction: jax.Array  # (K,) factor on `friction`, per finger-tool pair
    pair_softness: jax.Array  # (K,) factor on the pair's contact time constant (solref[0])
    damping: jax.Array  # (J,) factor on each hand joint's damping
    armature: jax.Array  # (J,) factor on each hand joint's armature
    strength: jax.Array  # (J,) factor on each hand motor's gear (torque per command)


class Scene:
    """The physics model and its index arrays, shared by the MJX and the C MuJoCo backend."""

    def __init__(self, hand: hand_lib.HandModel, config: PhysicsConfig = PhysicsConfig()):
        self.hand, self.config = hand, config
        self.model = m = physics_model(hand, config)
        self.tool_body = hand_lib.tool_body(m)
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
        n_sup = len(hand.support_top)
        self.pedestal_geoms = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{SUPPORT}{k + 1}")
                                        for k in range(n_sup)])
        others = {hand_lib.table_geom(m), *self.pedestal_geoms.tolist()}
        self.finger_tool_pairs = np.array(
            [p for p in range(m.npair)
             if self.tool_body in (m.geom_bodyid[m.pair_geom1[p]], m.geom_bodyid[m.pair_geom2[p]])
             and not others & {int(m.pair_geom1[p]), int(m.pair_geom2[p])}])
        touch = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b): i for i, b in enumerate(hand.touch_tool)}
        hand_geom = lambda p: m.pair_geom2[p] if m.geom_bodyid[m.pair_geom1[p]] == self.tool_body \
            else m.pair_geom1[p]  # noqa: E731
        self.pair_link = np.array([touch[int(m.geom_bodyid[hand_geom(p)])] for p in self.finger_tool_pairs], np.int32)
        self.n_touch = len(hand.touch_tool)  # L: the hand's bodies that touch the tool (a world's friction per body)
        self.support_top = hand.support_top.astype(np.float32)  # (P, 3) tool frame
        self.support_drop = (hand.support_half[:, 2]).astype(np.float32)  # (P,) centre below the top
        self.tool_corners = hand.tool_hull().astype(np.float32)  # (8 G, 3) the geoms' box corners, tool frame
        self.timestep = float(m.opt.timestep)  # [s] the physics step, which is the control period

        try:
            self._mx, self._mx_error = mjx.put_model(m), None
        except NotImplementedError as e:  # MJX collides fewer primitive pairs than C MuJoCo (a cylinder and a box)
            self._mx, self._mx_error = None, str(e)

    @property
    def mx(self) -> mjx.Model:
        """The MJX model; a scene with a primitive pair MJX cannot collide gets a ValueError naming it."""
        if self._mx is None:
            raise ValueError(f"physics: MJX cannot simulate this scene ({self._mx_error}); use the C MuJoCo backend "
                             "(backend='c', the default of the physics check)")
        return self._mx

    # ------------------------------------------------------------------------------------------ episodes
    def episode_fields(self, episode: Episode, world: "world_lib.World | None" = None) -> EpisodeFields:
        """The model fields of one episode in `world` (`gsp_jax.physics.world`; None: the nominal world) (pure JAX;
        vmap over episodes)."""
        if world is None:
            world = world_lib.nominal(self.n_touch, len(self.hand_dof))
        mat0 = kinematics.quat_to_mat(episode.quats[0])
        ped = []
        for top, drop in zip(self.support_top, self.support_drop):
            p = mat0 @ top + episode.waypoints[0]
            ped.append(jnp.stack([p[0], p[1], p[2] - drop]))
        link = jnp.asarray(self.pair_link)
        return EpisodeFields(mass=episode.mass * world.mass, inertia=episode.inertia * world.inertia,
                             com=episode.com + world.com, friction=jnp.asarray(episode.friction, jnp.float32),
                             pedestal_pos=jnp.stack(ped), pair_friction=world.friction[link],
                             pair_softness=world.softness[link], damping=world.damping, armature=world.armature,
                             strength=world.strength)

    def pedestal_drop(self, time, xp=jnp) -> jax.Array:
        """How far [m] (<= 0) the pedestals have sunk at `time`: in place for the first segment, then sinking at
        `pedestal_speed`, so the fingers take the tool's weight over a few tens of milliseconds. float32; `xp` is
        jax.numpy (traceable) or numpy (the same value without a JAX dispatch: the C backend asks every tick)."""
        f32 = xp.float32
        return -xp.minimum(f32(self.config.sim.pedestal_speed) * xp.maximum(f32(time - scenario.DT), f32(0.0)),
                           f32(-AWAY))

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
            pair_friction=mx.pair_friction.at[self.finger_tool_pairs, :2].set(
                (fields.friction * fields.pair_friction)[:, None]),
            pair_solref=mx.pair_solref.at[self.finger_tool_pairs, 0].multiply(fields.pair_softness),
            dof_damping=mx.dof_damping.at[self.hand_dof].multiply(fields.damping),
            dof_armature=mx.dof_armature.at[self.hand_dof].multiply(fields.armature),
            actuator_gear=mx.actuator_gear.at[self.hand_act, 0].multiply(fields.strength),
        )

    def c_model(self, fields: EpisodeFields) -> mujoco.MjModel:
        """A C MuJoCo model (a copy) with one episode's fields (numpy, one episode), pedestals in place."""
        m, b = copy.copy(self.model), self.tool_body
        self.c_pedestals(m, fields, 0.0)
        m.body_mass[b], m.body_inertia[b], m.body_ipos[b] = fields.mass, fields.inertia, fields.com
        f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731  (as the MJX model computes them)
        m.pair_friction[self.finger_tool_pairs, :2] = (f32(fields.friction) * f32(fields.pair_friction))[:, None]
        m.pair_solref[self.finger_tool_pairs, 0] *= fields.pair_softness
        m.dof_damping[self.hand_dof] *= fields.damping
        m.dof_armature[self.hand_dof] *= fields.armature
        m.actuator_gear[self.hand_act, 0] *= fields.strength
        return m

    def c_pedestals(self, mj_model: mujoco.MjModel, fields: EpisodeFields, drop: float) -> None:
        """Set the pedestals of a C model `drop` (<= 0) metres below their start (in place)."""
        mj_model.geom_pos[self.pedestal_geoms] = self.pedestal_positions(fields, drop)

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
                           tool_quat=quat / jnp.linalg.norm(quat), tool_vel=qvel[v : v + 6],
                           bias=qfrc_bias[self.hand_dof])

    def status(self, obs: Observation, ref_pos, ref_quat, lifted) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(angle error [deg], position error [m], fallen?) of the tool against a reference pose; the table
        counts once `lifted`. A non-finite state counts as fallen (and reads 0 error)."""
        c = self.config.outcome
        cos = jnp.clip(jnp.abs(jnp.dot(obs.tool_quat, ref_quat)), 0.0, 1.0)
        angle = jnp.degrees(2 * jnp.arccos(cos))
        perr = jnp.linalg.norm(obs.tool_pos - ref_pos)
        lowest = jnp.min((self.tool_corners @ kinematics.quat_to_mat(obs.tool_quat).T)[:, 2]) + obs.tool_pos[2]
        finite = jnp.all(jnp.isfinite(jnp.concatenate([obs.q, obs.dq, obs.tool_pos, obs.tool_quat, obs.tool_vel])))
        fell = ~finite | (lifted & (lowest < c.fall_height)) | (perr > c.fall_distance) | (angle > c.fall_angle)
        return jnp.where(finite, angle, 0.0), jnp.where(finite, perr, 0.0), fell
