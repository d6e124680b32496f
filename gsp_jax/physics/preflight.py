"""Before the first plan: what a model will do in physics, checked in seconds and said in plain words.

`check-model` runs these after the conventions (`gsp_jax.model.load.check_model`), on a model that loads:

* `joint_dynamics`: the hand's joints against the controller's gains. The controller's finger impedance acts
  explicitly at every physics step; with light links, no armature and little damping its discrete-time loop grows
  instead of settling (a finger kicks the tool away on the first tick). The linearised loop at the IK start is one
  matrix; how much one step takes off its fastest mode says whether it settles (`finger_step`).
* `clearance`: the tool's lowest point above the table at the start of the nominal lift and of the lowest
  standard episode (`scenario.HEIGHT_SHIFTS_MM`): a tool that starts on or in the table is not resting on its
  supports.
* `reach`: each contact link alone on each of its options at the first and last waypoint of the nominal lift, the
  IK's distance to the option [m]; `start_reach` the start grasp's links at waypoint 0.
* `hand_overlaps`: the start grasp's hand over the lift in MuJoCo with every hand geom colliding: body pairs that
  pass through each other (or the table) deeper than at rest. The physics simulates only the tool's and the
  fingertips' contacts, so a pose with a thumb inside the palm would plan and hold there; a real hand cannot take it.
* `dry_run`: the start grasp held for the first `DRY_SEGMENTS` decisions of the nominal lift without the external
  torque, in C MuJoCo: the tool neither falls nor leaves its path by more than `THROWN` [m]. (Held longer, a start
  grasp may well drop the tool: the planners change it from waypoint 0 on.)
"""
from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from gsp_jax.model import grasps, hand as hand_lib, kinematics, scenario
from gsp_jax.physics.config import PhysicsConfig
from gsp_jax.solvers import ik
from gsp_jax.surrogate.step import Surrogate

THROWN = 0.005  # [m] the start grasp's tool leaving its path by more than this in the dry run is a problem
OVERLAP = 0.01  # [m] hand bodies passing through each other (or the table) this much deeper than at rest: a problem
# (capsules `import-hand` fits over-cover a finger's meshes by up to ~1 cm, so neighbours' capsules may overlap that)
CLEARANCE = 0.001  # [m] the least gap between the tool and the table at the start of a standard episode
DRY_SEGMENTS = 1  # decisions (`scenario.DT` each) the dry run judges
FINGER_STEP = 0.5  # the most of the fingers' fastest mode one physics step of the controller may take off (above 1
# it overshoots every step, above 2 it grows); the shipped hands: 0.12-0.14


def finger_step(m: mujoco.MjModel, config: PhysicsConfig = PhysicsConfig()) -> tuple[float, list[str]]:
    """(how much of the fingers' fastest mode one physics step takes off, the hand joints most in that mode).

    The hand of scene `m` (`gsp_jax.model.load.hand_joints`) at its IK start (`gsp_ik_start`, else qpos0), every contact
    link tracked at the controller's full gains (its worst case; without contact sites, every fingertip body):
    stiffness K = finger_kp sum_l J_l^T J_l + free_stiffness I and damping D = finger_kd sum_l J_l^T J_l [joint
    space: N m/rad, N m s/rad], J_l the (3, J) Jacobian of link l's point. MuJoCo's step: the joints' own damping B
    implicit, the controller's torque explicit, mass matrix M (armature included), timestep h:
    v' = (M + h B)^-1 ((M - h D) v - h K q), q' = q + h v', the step matrix A. The figure: max |1 - eig(A)| (0: a
    step changes nothing; above 1 the fastest mode overshoots every step; above 2 it grows)."""
    from gsp_jax.model import load as model_lib

    f, joints = config.fingers, model_lib.hand_joints(m)
    d = mujoco.MjData(m)
    start = hand_lib._numeric(m, "gsp_ik_start")
    if start is not None and len(start) == len(joints):
        d.qpos[m.jnt_qposadr[joints]] = start
    mujoco.mj_forward(m, d)
    dofs = m.jnt_dofadr[joints]
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    mass = full[np.ix_(dofs, dofs)]
    links = hand_lib._text(m, "gsp_contact_links", "").split()
    sites = [s for n in links if (s := hand_lib._site(m, f"contact_{n}")) >= 0]
    root = m.body_rootid[m.jnt_bodyid[joints[0]]]
    tips = [b for b in range(1, m.nbody) if m.body_rootid[b] == root and not np.any(m.body_parentid[1:] == b)]
    jtj = np.zeros((len(dofs), len(dofs)))
    for i in sites or tips:
        jac = np.zeros((3, m.nv))
        (mujoco.mj_jacSite if sites else mujoco.mj_jacBody)(m, d, jac, None, i)
        jtj += jac[:, dofs].T @ jac[:, dofs]
    n, h = len(dofs), m.opt.timestep
    stiff = f.finger_kp * jtj + f.free_stiffness * np.eye(n)
    inv = np.linalg.inv(mass + h * np.diag(m.dof_damping[dofs]))
    vv, vq = inv @ (mass - h * f.finger_kd * jtj), -h * inv @ stiff
    eig, vec = np.linalg.eig(np.block([[vv, vq], [h * vv, np.eye(n) + h * vq]]))  # (v, q) -> (v', q')
    worst = int(np.argmax(np.abs(1.0 - eig)))
    share = np.abs(vec[n:, worst]) + h * np.abs(vec[:n, worst])
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, joints[j]) for j in np.argsort(-share)[:3]]
    return float(np.abs(1.0 - eig[worst])), names


def joint_dynamics(m: mujoco.MjModel, config: PhysicsConfig = PhysicsConfig()) -> list[str]:
    """The problem (a list of at most one line) if one physics step takes more than `FINGER_STEP` off the
    fingers' fastest mode (`finger_step`)."""
    step, worst = finger_step(m, config)
    if step <= FINGER_STEP:
        return []
    ids = [m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in worst]
    return [f"the hand's joints are too light for the controller's finger gains at this timestep: one physics step "
            f"takes {step:.0%} off the fingers' fastest mode (at most {FINGER_STEP:.0%}; joints {', '.join(worst)}: "
            f"armature "
            f"{', '.join(f'{m.dof_armature[i]:g}' for i in ids)} kg m^2, damping "
            f"{', '.join(f'{m.dof_damping[i]:g}' for i in ids)} N m s/rad): give every hand joint armature and damping "
            f"(the shipped hands': {hand_lib.JOINT_ARMATURE:g} and {hand_lib.JOINT_DAMPING:g}; import-hand sets them)"]


def clearance(sur: Surrogate) -> list[str]:
    """Problems with the tool's gap to the table at the start of the nominal lift and the lowest standard one."""
    lowest = float(sur.hand.tool_hull()[:, 2].min() + sur.hand.tool_rest[2])
    shift = scenario.fit(sur.model).shift(min(scenario.HEIGHT_SHIFTS_MM)) * 1e-3
    if lowest + shift >= CLEARANCE - 1e-7:  # a tool exactly CLEARANCE clear passes (0.1 um of rounding)
        return []
    where = "in" if lowest < 0 else "on" if lowest < CLEARANCE else f"{lowest * 1e3:.1f} mm above"
    raise_mm = max(np.ceil(np.round((CLEARANCE - lowest - shift) * 1e4, 6)), 1) / 10  # whole tenths: never "0.0"
    return [f"the tool starts {where} the table (its lowest point at z = {lowest * 1e3:.1f} mm): the standard "
            f"episodes start the lift up to {-shift * 1e3:g} mm lower, so raise the tool body in the file by at least "
            f"{raise_mm:.1f} mm, onto its supports"]


@dataclasses.dataclass(frozen=True)
class Reach:
    """Each contact link alone on each option at the lift's first and last waypoint: the IK's distance [m]."""

    links: tuple[str, ...]
    error: np.ndarray  # (L, K, 2) [m]; NaN where a link has fewer options (row k = 0 unused)
    tolerance: float  # [m] within this the link reaches (the reward's contact_tol)

    def unreachable(self) -> list[tuple[str, int]]:
        """(link, option) pairs reached at neither waypoint."""
        return [(n, k) for li, n in enumerate(self.links) for k in range(1, self.error.shape[1])
                if np.isfinite(self.error[li, k]).all() and (self.error[li, k] > self.tolerance).all()]

    def table(self) -> str:
        """One row per link and option: the error at waypoint 0 and the last [mm]."""
        rows = ["link            option  first [mm]  last [mm]", "-" * 45]
        for li, n in enumerate(self.links):
            for k in range(1, self.error.shape[1]):
                e = self.error[li, k]
                if np.isfinite(e).all():
                    ok = e <= self.tolerance
                    mark = "" if ok.all() else "  last only" if ok[1] else "  first only" if ok[0] else "  unreached"
                    rows.append(f"{n:<15} {k:>6}  {e[0] * 1e3:>10.1f}  {e[1] * 1e3:>9.1f}{mark}")
        return "\n".join(rows)


def reach(sur: Surrogate, episode: scenario.Episode | None = None) -> Reach:
    """`Reach` of every (link, option) on `episode` (default: the model's nominal lift) by the surrogate's IK."""
    hand, space = sur.hand, sur.space
    episode = scenario.make_episode(model=sur.model) if episode is None else episode
    K = max(hand.n_options)
    options = np.zeros((hand.n_links, K, hand.n_links), np.int32)
    for li in range(hand.n_links):
        for k in range(1, hand.n_options[li]):
            options[li, k, li] = k
    ends = np.array([0, episode.n_steps - 1])
    grasps_ = np.repeat(np.asarray(space.encode(options.reshape(-1, hand.n_links)))[:, None], 2, axis=1)  # (L K, 2)
    pos = np.broadcast_to(np.asarray(episode.waypoints)[ends], grasps_.shape + (3,))
    quat = np.broadcast_to(np.asarray(episode.quats)[ends], grasps_.shape + (4,))
    realise = jax.jit(lambda g, p, q: sur.realise_many(g, p, q, lanes=False).ik.link_error)
    err = np.asarray(realise(jnp.asarray(grasps_), jnp.asarray(pos), jnp.asarray(quat)))
    err = err.reshape(hand.n_links, K, 2, hand.n_links)
    own = np.stack([err[li, :, :, li] for li in range(hand.n_links)])  # (L, K, 2)
    valid = np.arange(K)[None, :] < np.array(hand.n_options)[:, None]
    own = np.where(valid[..., None], own, np.nan)
    own[:, 0] = np.nan
    return Reach(hand.link_names, own, float(sur.reward_config.contact_tol))


def start_reach(sur: Surrogate) -> list[str]:
    """Problems with the start grasp at waypoint 0 of the nominal lift: links the IK leaves off their options."""
    episode = scenario.make_episode(model=sur.model)
    c = sur.realise(episode.start_grasp, episode.waypoints[0], episode.quats[0])
    err, active = np.asarray(c.ik.link_error), np.asarray(sur.space.decode(episode.start_grasp)) > 0
    tol = float(sur.reward_config.contact_tol)
    opts = sur.hand.start_options
    return [f"the start grasp's link {n!r} does not reach its option {opts[li]} at the start of the lift: the IK "
            f"leaves it {err[li] * 1e3:.1f} mm away (> {tol * 1e3:g} mm); move the option, the palm or gsp_ik_start"
            for li, n in enumerate(sur.hand.link_names) if active[li] and err[li] > tol]


def start_band(sur: Surrogate) -> list[str]:
    """Problems with the start grasp over the heights the episodes start at: the lowest and highest starts any set
    or corpus draws (`scenario.fit`'s shifts), where the IK's start grasp collides, naming the bodies and depths."""
    f, out = scenario.fit(sur.model), []
    for mm in (f.shift(-scenario.DOWN_REACH * 1e3), f.shift(scenario.UP_REACH * 1e3)):
        episode = scenario.make_episode(model=sur.model, shift_mm=mm)
        pos, quat = episode.waypoints[0], episode.quats[0]
        c = sur.realise(episode.start_grasp, pos, quat)
        if bool(c.ik.collision):
            hits = ik.collisions(sur.hand, c.ik.q, pos, kinematics.quat_to_mat(quat), sur.ik_config.collision_tol)
            out.append(f"the start grasp collides where the episodes start {abs(mm):.3g} mm "
                       f"{'lower' if mm < 0 else 'higher'} than the file's rest (the sets and the corpus reach "
                       f"there): {'; '.join(hits)}; move the palm, the options or gsp_ik_start")
    return out


def hand_overlaps(sur: Surrogate, tol: float = OVERLAP) -> list[str]:
    """Problems with the hand's own geometry in the start grasp: at the nominal lift's first and last waypoint, the
    IK's pose of the start grasp in MuJoCo with every hand geom colliding with every other (MuJoCo's own filters:
    parent and child, the file's <exclude> pairs) and with the table; a pair of bodies that overlaps more than `tol`
    [m] deeper than at the file's rest (qpos0: fitted capsules often touch at the joints), or a body more than `tol`
    into the table, is named with its depth."""
    m = copy.copy(sur.model.mjmodel)  # its geoms' collision flags are changed below
    hand = sur.hand
    tool = hand_lib.tool_body(m)
    table = [g for g in range(m.ngeom) if m.geom_bodyid[g] == 0 and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    solid = [g for g in range(m.ngeom) if m.geom_bodyid[g] not in (0, tool) and hand_lib.collides(m, g)]
    for g in range(m.ngeom):  # the hand's solid geoms and the table collide with each other only
        on = g in solid or g in table
        m.geom_contype[g], m.geom_conaffinity[g] = (1, 1) if on else (0, 0)
    d = mujoco.MjData(m)

    def depths(q) -> dict[tuple[str, str], float]:
        d.qpos[:] = m.qpos0
        d.qpos[hand.qpos_adr] = q
        mujoco.mj_forward(m, d)
        out: dict[tuple[str, str], float] = {}
        for c in d.contact[: d.ncon]:
            a, b = sorted("table" if g in table else m.body(m.geom_bodyid[g]).name for g in (c.geom1, c.geom2))
            out[(a, b)] = max(out.get((a, b), 0.0), -float(c.dist))
        return out

    rest = depths(m.qpos0[hand.qpos_adr])
    episode = scenario.make_episode(model=sur.model)
    found: dict[tuple[str, str], tuple[float, int]] = {}
    for t in (0, episode.n_steps - 1):
        q = np.asarray(sur.realise(episode.start_grasp, episode.waypoints[t], episode.quats[t]).ik.q)
        for pair, depth in depths(q).items():
            base = 0.0 if "table" in pair else rest.get(pair, 0.0)  # the table is no part of the hand at rest
            if depth - base > tol and depth > found.get(pair, (0.0, 0))[0]:
                found[pair] = (depth, t)
    if not found:
        return []
    worst = sorted(found.items(), key=lambda kv: -kv[1][0])
    said = "; ".join(f"{a} and {b} {d * 1e3:.1f} mm at waypoint {t}" for (a, b), (d, t) in worst[:6])
    return [f"the start grasp's hand passes through itself or the table (by > {tol * 1e3:g} mm more than at rest): "
            f"{said}. The physics simulates only the tool's and the fingertips' contacts, so it would plan and hold "
            "this pose, which the real hand cannot take: turn or move the palm (check-model --place), or change "
            "gsp_ik_start or the options"]


@dataclasses.dataclass(frozen=True)
class DryRun:
    """The start grasp held for the first `DRY_SEGMENTS` decisions of the nominal lift (no external torque) in C
    MuJoCo."""

    fell: bool
    fall_time: float  # [s], -1 if it held
    max_offset: float  # [m] the tool's largest distance from its path
    offset_time: float  # [s] when
    max_angle: float  # [deg] its largest tilt from its path
    unstable_time: float = -1.0  # [s] when MuJoCo found the simulation unstable (and reset it); -1: never

    def problems(self) -> list[str]:
        out = []
        if self.unstable_time >= 0:
            out.append(f"in C MuJoCo the simulation goes unstable {self.unstable_time * 1e3:.0f} ms into the start "
                       "grasp (MuJoCo reset it): see the joint dynamics")
        if self.fell:
            out.append(f"in C MuJoCo the start grasp drops the tool {self.fall_time:.2f} s into the nominal lift (the "
                       "grasp held, no external torque): see the offset, the joint dynamics and the start's reach")
        if self.max_offset > THROWN:
            out.append(f"in C MuJoCo the start grasp pushes the tool {self.max_offset * 1e3:.1f} mm off its path "
                       f"{self.offset_time * 1e3:.0f} ms into the lift (> {THROWN * 1e3:g} mm)")
        return out


def dry_run(sur: Surrogate, config: PhysicsConfig = PhysicsConfig()) -> DryRun:
    """`DryRun` of the model's start grasp (`Surrogate`'s model) on its nominal lift without the external torque."""
    from gsp_jax.physics import c_backend
    from gsp_jax.physics.controller import reference_motion
    from gsp_jax.physics.runner import Physics

    phys = Physics(sur, config)
    episode = scenario.make_episode(model=sur.model, torque=0.0)
    hold = c_backend.OpenLoop(jnp.full(episode.n_steps, grasps.NULL, jnp.int32))
    batch = jax.tree.map(lambda x: x[None], episode)
    log: list = []
    res = c_backend.simulate(phys, [(hold, None)], batch, cores=1, workers=1, engine_log=log)[0]
    res = jax.tree.map(lambda x: np.asarray(x)[0], res)
    clock = np.array([states[0, 0] for _, states, _ in log])  # mjSTATE_INTEGRATION starts with the time
    back = np.flatnonzero(np.diff(clock) < 0)  # MuJoCo resets a diverging simulation to time 0
    times = (np.arange(len(res.angle)) + 1) * phys.timestep
    ref = np.asarray(jax.vmap(lambda t: reference_motion(episode, t).pos)(jnp.asarray(times, jnp.float32)))
    a = phys.scene.tool_qpos
    offset = np.linalg.norm(res.qpos[:, a:a + 3] - ref, axis=1)
    window = DRY_SEGMENTS * phys.n_segment
    fell = bool(res.fell and res.fall_time <= times[window - 1])
    until = max(1, int(np.searchsorted(times, res.fall_time))) if fell else window
    worst = int(np.argmax(offset[:until]))
    return DryRun(fell, float(res.fall_time) if fell else -1.0, float(offset[worst]), float(times[worst]),
                  float(np.max(res.angle[:until])), float(clock[back[0]]) if back.size else -1.0)
