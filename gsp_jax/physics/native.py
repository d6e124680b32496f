"""The contact controller's tick in native code (numba), for the C backend: the control law of
`controller.Controller.control`, `Physics.tick` and `Physics.check`, written once more over plain arrays, so a tick
of a few episodes has no fixed cost per call (an XLA call's is that of hundreds of small kernels, whatever the
batch: docs/performance.md). It runs without Python's lock, in the threads that step the episodes.

Must equal the JAX tick, `runner.Physics.tick` and `Physics.check` (its reference); checked by
`tests/test_native.py::test_native_tick_is_the_jax_tick_on_recorded_states` (whole runs:
`::test_native_and_jax_controllers_give_the_same_outcomes`). It reads the same flat controller states
(`c_backend._Flat` layout, float32) and observations, and writes the same output rows [ctrl (nu) | external
wrench (6) | angle, position error, fell of the tick before]. The continuous arithmetic runs in float64 (the JAX
controller's float32 differs from it in the last bits); the timeline (time, phases, load fractions, the reference
spline's interval) runs in float32 exactly as the JAX tick does, so both switch phase at the same tick. The small
helpers below (`_reference`, `_rotation_error`, `_solve3`, `_status`) are checked through the tick.

A tick (`_control`) is a few steps, each a function of its own (`_read_state`, `_phase`, `_targets`, `_on_tool`,
`_loads`, `_tracking`, `_tool_wrench`, `_contacts`, `_torques`, `_write`), passed only the groups of `Constants` and
the views of `Scratch` it reads: a call passes its arguments word by word, so a step passed every constant and
working array would cost the tick ~10% (measured); passed its own, nothing measurable, and it compiles no slower than
one long function did.

    ctl = native.Tick(phys)                          # the constants of one `Physics` (or its spec)
    ctl(j, rows, cs, obs, episodes, out)             # tick j of the episodes `rows`: cs updated in place
"""
from __future__ import annotations

import glob
import math
import os
from typing import NamedTuple

import jax
import mujoco
import numba as nb
import numpy as np
from jax.flatten_util import ravel_pytree
from llvmlite import binding as llvm

from gsp_jax.physics import world as world_lib
from gsp_jax.physics import controller as controller_lib
from gsp_jax.physics.controller import MIN_GRADIENT, PATH_TIMES, STRENGTH_RANGE, ControllerState
from gsp_jax.physics.spec import HasSpec, PhysicsSpec, of

F32 = np.float32


def _mujoco_library() -> str:
    """The path of the MuJoCo C library the `mujoco` package loads (its own copy, in the package's folder)."""
    folder = os.path.dirname(mujoco.__file__)
    for pattern in ("libmujoco.so*", "libmujoco*.dylib", "mujoco.dll"):
        found = sorted(glob.glob(os.path.join(folder, pattern)))
        if found:
            return found[0]
    raise ImportError(f"gsp_jax.physics.native: no MuJoCo library in {folder}")


llvm.load_library_permanently(_mujoco_library())  # its symbols, for native code to call by name
# MuJoCo's C functions, called by name from native code (pointers passed as integers: `MjModel._address`)
_mj_step = nb.types.ExternalFunction("mj_step", nb.types.void(nb.types.uint64, nb.types.uint64))
_mju_copy = nb.types.ExternalFunction("mju_copy", nb.types.void(nb.types.uint64, nb.types.uint64, nb.types.intc))
# the columns of `addresses`: where one episode's model, data and the arrays a tick reads and writes live
MODEL, DATA, QPOS, QVEL, QFRC_BIAS, CTRL, XFRC_TOOL, GEOM_POS = range(8)


def addresses(models, datas, tool_body: int) -> np.ndarray:
    """(E, 8) uint64: each episode's mjModel, mjData and arrays (the columns MODEL ... GEOM_POS). The arrays
    of a model and its data stay where they are for their lifetime: keep `models` and `datas` alive."""
    return np.array([[m._address, d._address, d.qpos.ctypes.data, d.qvel.ctypes.data, d.qfrc_bias.ctypes.data,
                      d.ctrl.ctypes.data, d.xfrc_applied[tool_body].ctypes.data, m.geom_pos.ctypes.data]
                     for m, d in zip(models, datas)], np.uint64)


class Hand(NamedTuple):
    """The hand's kinematic tree and contact links (`HandModel`): B bodies, J joints, L contact links, K options a
    link."""

    body_parent: np.ndarray  # (B,) int64
    body_pos: np.ndarray  # (B, 3)
    body_mat: np.ndarray  # (B, 3, 3)
    body_joint: np.ndarray  # (B,) int64, -1: none
    joint_pos: np.ndarray  # (J, 3)
    joint_axis: np.ndarray  # (J, 3)
    joint_moves_body: np.ndarray  # (B, J)
    link_body: np.ndarray  # (L,) int64
    link_site: np.ndarray  # (L, 3)
    link_axis: np.ndarray  # (L, 3)
    link_half: np.ndarray  # (L,)
    link_radius: np.ndarray  # (L,)
    link_finger: np.ndarray  # (L,) int64
    link_is_tip: np.ndarray  # (L,) bool
    n_fingers: int
    targets: np.ndarray  # (L, K, 3) the links' centre-line targets per option, tool frame
    normals: np.ndarray  # (L, K, 3) inward normals per option, tool frame
    box_pos: np.ndarray  # (NB, 3) the tool's boxes (`HandModel.tool_box_*`), tool frame
    box_half: np.ndarray  # (NB, 3)
    box_mat: np.ndarray  # (NB, 3, 3)
    round_kind: np.ndarray  # (NR,) int64, its round primitives: an index into `ROUNDS`
    round_pos: np.ndarray  # (NR, 3) tool frame
    round_mat: np.ndarray  # (NR, 3, 3)
    round_size: np.ndarray  # (NR, 3)


ROUNDS = ("sphere", "capsule", "cylinder", "ellipsoid")  # `Hand.round_kind`'s codes (`ik.round_sdf`'s kinds)


class Scene(NamedTuple):
    """The MuJoCo scene's indices and ranges (`Scene`)."""

    hand_qpos: np.ndarray  # (J,) int64
    hand_dof: np.ndarray  # (J,) int64
    hand_act: np.ndarray  # (J,) int64
    tool_qpos: int
    tool_dof: int
    nq: int
    nv: int
    nu: int
    tool_corners: np.ndarray  # (C, 3) tool frame
    ctrl_low: np.ndarray  # (J,)
    ctrl_high: np.ndarray  # (J,)
    gravity: np.ndarray  # (3,)


class Timeline(NamedTuple):
    """The timeline (`PhysicsConfig.timeline`), float32 as in the JAX tick."""

    timestep: np.float32
    unload: np.float32
    move: np.float32
    load_step: np.float32  # timestep / load
    unload_step: np.float32  # timestep / unload
    path_times: np.ndarray  # (N_PATH,) float32
    touch_tol: float
    reach_tol: float
    ramp: np.float32
    n_segment: int


class Gains(NamedTuple):
    """The controller's tool feedback and force solve (`PhysicsConfig.controller`, the wrench solve's config)."""

    kp: float
    kd: float
    feedback_limit: float
    feedback_floor: float
    tool_radius: float
    rotation_step: float
    grip_force: float
    friction_margin: float
    measured: bool  # `frames` == "measured"
    iterations: int
    rho: float
    torque_length: float
    pose_filter: float  # 1: off
    strength_rate: float  # 0: off
    strength_leak: float
    strength_deadband: float


class Fingers(NamedTuple):
    """The fingers' tracking gains (`PhysicsConfig.fingers`)."""

    finger_kp: float
    finger_kd: float
    held_ratio: float
    free_stiffness: float
    free_damping: float
    posture_kp: float


class Outcome(NamedTuple):
    """When a tool has fallen (`PhysicsConfig.outcome`)."""

    fall_angle: float
    fall_distance: float
    fall_height: float


class Offsets(NamedTuple):
    """Where each field of the controller state starts in its flat row (`c_backend._Flat`, `state_offsets`)."""

    options: int
    previous: int
    changed: int
    start: int
    path: int
    park: int
    anchor: int
    anchored: int
    load: int
    f_with: int
    f_without: int
    q_rest: int
    strength: int
    estimate: int


class Constants(NamedTuple):
    """Everything a tick reads besides its episodes and states (numpy arrays and numbers), in groups: a step of the
    tick is passed the groups it reads."""

    hand: Hand
    scene: Scene
    timeline: Timeline
    controller: Gains
    fingers: Fingers
    outcome: Outcome
    state: Offsets


class Episodes(NamedTuple):
    """The fields of E episodes a tick reads (numpy; `Tick.episodes` makes them from an `Episode` batch); inside
    native code, also one episode's (`_row`: its rows, dt, mass, friction and hold_time numbers)."""

    waypoints: np.ndarray  # (E, T, 3) float32
    quats: np.ndarray  # (E, T, 4) float32
    dt: np.ndarray  # (E,) float32
    w_ext: np.ndarray  # (E, 6) float32
    mass: np.ndarray  # (E,) float32
    inertia: np.ndarray  # (E, 3) float32
    com: np.ndarray  # (E, 3) float32
    friction: np.ndarray  # (E,) float32
    hold_time: np.ndarray  # (E,) float32: when the hold starts [s]


N_VEC3 = 27  # Scratch.v3's 3-vectors (named where used; `_status` uses rows 0..6 as `_control` does)
# Links.blocks: the links' (L, 3) 3-vectors of a tick
ANCHOR, PARK, F_WITH, F_WITHOUT, TARGET, X_REF, V_REF, NORMAL, NORMAL_T, X, V, F_TRACK, POINTS, F_A, F_B = range(15)
N_BLOCKS = 15
# Links.flags: the links' (L,) flags of a tick
CHANGED, ANCHORED, UNLOADING, TRAVELLING, MOVING, TRACKED, HELD, ACTIVE, ACTIVE_B = range(9)
N_FLAGS = 9
OPTIONS, PREVIOUS, CURRENT = range(3)  # Links.options: the links' (L,) options


class Links(NamedTuple):
    """One thread's working arrays of the links for a tick, named by the constants above."""

    blocks: np.ndarray  # (N_BLOCKS, L, 3) float64: ANCHOR ... F_B
    flags: np.ndarray  # (N_FLAGS, L) bool: CHANGED ... ACTIVE_B
    options: np.ndarray  # (3, L) int64: OPTIONS, PREVIOUS, CURRENT
    load: np.ndarray  # (L,) float32: the load fractions
    busy: np.ndarray  # (n_fingers,) bool: a finger with a link on an option or changing


class Scratch(NamedTuple):
    """One thread's working arrays for a tick and a step, so that neither allocates: made once a thread by
    `scratch`, float64 unless named. The tick's steps (`_control`) name their views of v3, m3, f and `links`; the
    helpers they call have fields of their own (a tick runs `_status`, then `_control`: they share v3's first rows,
    m3[0] and q4)."""

    v3: np.ndarray  # (N_VEC3, 3): 3-vectors
    m3: np.ndarray  # (3, 3, 3): 3x3 matrices
    f: np.ndarray  # (5 J + 15,): J-, 6- and 3-vectors
    q4: np.ndarray  # (2, 4): the tool's quaternion and the reference's
    links: Links
    jac: np.ndarray  # (L, 3, J)
    joints: np.ndarray  # (2, J, 3): the joints' world axes and anchors (`_chain`)
    body_pos: np.ndarray  # (B, 3): the bodies' positions (`_chain`)
    body_mat: np.ndarray  # (B, 3, 3): the bodies' rotations (`_chain`)
    kin_v: np.ndarray  # (4, 3): `_links`' centre, axis and two temporaries
    kin_m: np.ndarray  # (2, 3, 3): `_chain`'s rotations
    adj: np.ndarray  # (3, 3): `_solve3`'s cofactor rows
    gg: np.ndarray  # (6, 6): `_solve`'s G G^T
    lever: np.ndarray  # (2, L, 3): `_solve`'s scaled levers and preferred forces
    apg: np.ndarray  # (3, 3 L): `_solve`'s iterate, the one before and the extrapolated point
    buf: np.ndarray  # (max(nq, nv, nu, 6),): `_step_row`'s copies in and out of MuJoCo


def scratch(K: Constants) -> Scratch:
    """A `Scratch` for the hand and scene of `K` (one a thread: a tick writes all of it)."""
    H, sc = K.hand, K.scene
    J, L, B = sc.hand_qpos.shape[0], H.link_body.shape[0], H.body_parent.shape[0]
    links = Links(blocks=np.zeros((N_BLOCKS, L, 3)), flags=np.zeros((N_FLAGS, L), np.bool_),
                  options=np.zeros((3, L), np.int64), load=np.zeros(L, F32), busy=np.zeros(H.n_fingers, np.bool_))
    return Scratch(v3=np.zeros((N_VEC3, 3)), m3=np.zeros((3, 3, 3)), f=np.zeros(5 * J + 15), q4=np.zeros((2, 4)),
                   links=links, jac=np.zeros((L, 3, J)), joints=np.zeros((2, J, 3)), body_pos=np.zeros((B, 3)),
                   body_mat=np.zeros((B, 3, 3)), kin_v=np.zeros((4, 3)), kin_m=np.zeros((2, 3, 3)),
                   adj=np.zeros((3, 3)), gg=np.zeros((6, 6)), lever=np.zeros((2, L, 3)), apg=np.zeros((3, 3 * L)),
                   buf=np.zeros(max(sc.nq, sc.nv, sc.nu, 6)))


def state_offsets(one_state: ControllerState) -> dict[str, int]:
    """Where each field of a `ControllerState` starts in its flat row (`ravel_pytree` order)."""
    names = list(ControllerState.__dataclass_fields__)
    marked = one_state.replace(**{n: np.full(np.shape(getattr(one_state, n)), i, np.float32)
                                  for i, n in enumerate(names)})
    flat = np.asarray(ravel_pytree(marked)[0])
    return {n: int(np.flatnonzero(flat == i)[0]) for i, n in enumerate(names)}


class Tick:
    """The native tick of one `runner.Physics` (its hand, scene and config: a `Physics` or its `spec`)."""

    def __init__(self, phys: PhysicsSpec | HasSpec):
        self.spec = spec = of(phys)
        hand, scene, cfg, ctl = spec.hand, spec.scene, spec.config, spec.controller
        tl, c, fi, out = cfg.timeline, cfg.controller, cfg.fingers, cfg.outcome
        kp, kd = c.tool_gains
        # the controller state's layout, as `c_backend` flattens it (its shapes only: nothing runs)
        m = spec.mj_model
        rest = scene.observe(m.qpos0, np.zeros(m.nv), np.zeros(m.nv))
        zeros = jax.eval_shape(ctl.start, spec.nominal(), np.zeros(hand.n_joints, np.float32), rest)
        offsets = state_offsets(jax.tree.map(lambda x: np.zeros(x.shape, x.dtype), zeros))
        f64 = lambda x: np.ascontiguousarray(x, np.float64)  # noqa: E731
        i64 = lambda x: np.ascontiguousarray(x, np.int64)  # noqa: E731
        self.constants = Constants(
            hand=Hand(
                body_parent=i64(hand.body_parent), body_pos=f64(hand.body_pos), body_mat=f64(hand.body_mat),
                body_joint=i64(hand.body_joint), joint_pos=f64(hand.joint_pos), joint_axis=f64(hand.joint_axis),
                joint_moves_body=f64(hand.joint_moves_body), link_body=i64(hand.link_body),
                link_site=f64(hand.link_site), link_axis=f64(hand.link_axis), link_half=f64(hand.link_half),
                link_radius=f64(hand.link_radius), link_finger=i64(hand.link_finger),
                link_is_tip=np.ascontiguousarray(hand.link_is_tip, np.bool_), n_fingers=len(hand.finger_names),
                targets=f64(ctl.targets_tool), normals=f64(hand.option_normal),
                box_pos=f64(hand.tool_box_pos).reshape(-1, 3), box_half=f64(hand.tool_box_half).reshape(-1, 3),
                box_mat=f64(hand.tool_box_mat).reshape(-1, 3, 3),
                round_kind=i64([ROUNDS.index(k) for k in hand.tool_round_type]),
                round_pos=f64(hand.tool_round_pos).reshape(-1, 3), round_mat=f64(hand.tool_round_mat).reshape(-1, 3, 3),
                round_size=f64(hand.tool_round_size).reshape(-1, 3)),
            scene=Scene(
                hand_qpos=i64(scene.hand_qpos), hand_dof=i64(scene.hand_dof), hand_act=i64(scene.hand_act),
                tool_qpos=scene.tool_qpos, tool_dof=scene.tool_dof, nq=m.nq, nv=m.nv, nu=m.nu,
                tool_corners=f64(scene.tool_corners), ctrl_low=f64(scene.ctrl_range[0]),
                ctrl_high=f64(scene.ctrl_range[1]), gravity=f64(np.asarray(hand.gravity, np.float32))),
            timeline=Timeline(
                timestep=F32(spec.timestep), unload=F32(tl.unload), move=F32(tl.move),
                load_step=F32(spec.timestep / tl.load), unload_step=F32(spec.timestep / tl.unload),
                path_times=np.ascontiguousarray(PATH_TIMES, np.float32), touch_tol=float(F32(tl.touch_tol)),
                reach_tol=float(F32(tl.reach_tol)), ramp=F32(tl.ramp), n_segment=spec.n_segment),
            controller=Gains(
                kp=float(F32(kp)), kd=float(F32(kd)), feedback_limit=float(c.feedback_limit),
                feedback_floor=float(c.feedback_floor), tool_radius=float(ctl.tool_radius),
                rotation_step=float(c.rotation_step), grip_force=float(c.grip_force),
                friction_margin=float(c.friction_margin), measured=c.frames == "measured",
                iterations=int(c.force_iterations),
                rho=float(ctl.wrench_config.force_penalty), torque_length=float(ctl.wrench_config.torque_length),
                pose_filter=float(c.pose_filter), strength_rate=float(c.strength_rate),
                strength_leak=float(controller_lib.STRENGTH_LEAK),
                strength_deadband=float(controller_lib.STRENGTH_DEADBAND)),
            fingers=Fingers(
                finger_kp=float(fi.finger_kp), finger_kd=float(fi.finger_kd),
                held_ratio=float(fi.held_stiffness_ratio), free_stiffness=float(fi.free_stiffness),
                free_damping=float(fi.free_damping), posture_kp=float(fi.posture_kp)),
            outcome=Outcome(fall_angle=float(out.fall_angle), fall_distance=float(out.fall_distance),
                            fall_height=float(out.fall_height)),
            state=Offsets(**offsets))

    def episodes(self, episodes) -> Episodes:
        """The `Episodes` of an `Episode` batch (leading axis)."""
        f32 = lambda x: np.ascontiguousarray(np.asarray(x), np.float32)  # noqa: E731
        n = np.shape(episodes.mass)[0]
        hold = np.full(n, F32(self.spec.hold_time(episodes.n_steps)), np.float32)
        return Episodes(waypoints=f32(episodes.waypoints), quats=f32(episodes.quats), dt=f32(episodes.dt),
                        w_ext=f32(episodes.w_ext), mass=f32(episodes.mass), inertia=f32(episodes.inertia),
                        com=f32(episodes.com), friction=f32(episodes.friction), hold_time=hold)

    def __call__(self, j: int, rows: np.ndarray, cs: np.ndarray, obs: np.ndarray, episodes: Episodes,
                 out: np.ndarray, work: Scratch | None = None, seen: np.ndarray | None = None) -> None:
        """Control tick j of the episodes `rows` (int64 indices into every array's leading axis): their states
        cs (E, C) float32 updated in place, out (E, nu + 9) float32 written, from observations obs (E, nq + 2 nv)
        float32 (the status) and what the controller observes, `seen` (the same layout; default obs). Rows not in
        `rows` are left as they are. `work`: the calling thread's `Scratch` (default: a new one)."""
        tick_rows(np.int64(j), rows, cs, obs, obs if seen is None else seen, episodes, self.constants, out,
                  scratch(self.constants) if work is None else work)


# ------------------------------------------------------------------------------------------ small math
_jit = nb.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")


@_jit
def _quat_to_mat(q, m):
    w, x, y, z = q[0], q[1], q[2], q[3]
    m[0, 0], m[0, 1], m[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    m[1, 0], m[1, 1], m[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    m[2, 0], m[2, 1], m[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@_jit
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@_jit
def _norm3(v):
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@_jit
def _clip_norm(v, top):
    """v * min(1, top / (|v| + 1e-9)) in place."""
    s = min(1.0, top / (_norm3(v) + 1e-9))
    for i in range(3):
        v[i] *= s


@_jit
def _rotation_error(q_ref, q, out):
    """World-frame rotation vector (3,) that turns orientation q into q_ref [rad]."""
    w1, x1, y1, z1 = q_ref[0], q_ref[1], q_ref[2], q_ref[3]
    w2, x2, y2, z2 = q[0], -q[1], -q[2], -q[3]
    e0 = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    e1 = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    e2 = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    e3 = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    if e0 < 0:
        e0, e1, e2, e3 = -e0, -e1, -e2, -e3
    n = math.sqrt(e1 * e1 + e2 * e2 + e3 * e3 + 1e-18)
    s = 2 * math.atan2(n, e0) / n
    out[0], out[1], out[2] = s * e1, s * e2, s * e3


@_jit
def _reference(wp, quats, dt, time, pos, vel, acc, quat):
    """`controller.reference_motion` at float32 `time`: pos, vel, acc (3,), quat (4,) written."""
    T = wp.shape[0]
    s = min(max(time / dt, F32(0.0)), F32(T - 1))
    i = min(int(math.floor(s)), T - 2)
    u32 = s - F32(i)
    u = float(u32)
    moving = time < F32(T - 1) * dt
    d = float(dt)
    h0, h1, h2, h3 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    g0, g1, g2, g3 = 6 * u**2 - 6 * u, 3 * u**2 - 4 * u + 1, -6 * u**2 + 6 * u, 3 * u**2 - 2 * u
    a0, a1, a2, a3 = 12 * u - 6, 6 * u - 4, -12 * u + 6, 6 * u - 2
    for c in range(3):
        lo0, hi0 = max(i - 1, 0), min(i + 1, T - 1)
        lo1, hi1 = max(i, 0), min(i + 2, T - 1)
        m0 = (float(wp[hi0, c]) - float(wp[lo0, c])) / ((hi0 - lo0) * d) * d
        m1 = (float(wp[hi1, c]) - float(wp[lo1, c])) / ((hi1 - lo1) * d) * d
        p0, p1 = float(wp[i, c]), float(wp[i + 1, c])
        pos[c] = h0 * p0 + h1 * m0 + h2 * p1 + h3 * m1
        vel[c] = (g0 * p0 + g1 * m0 + g2 * p1 + g3 * m1) / d if moving else 0.0
        acc[c] = (a0 * p0 + a1 * m0 + a2 * p1 + a3 * m1) / d**2 if moving else 0.0
    dot = 0.0
    for c in range(4):
        dot += float(quats[i, c]) * float(quats[i + 1, c])
    sign = -1.0 if dot < 0 else 1.0
    n = 0.0
    for c in range(4):
        quat[c] = (1 - u) * float(quats[i, c]) + u * sign * float(quats[i + 1, c])
        n += quat[c] * quat[c]
    n = math.sqrt(n)
    for c in range(4):
        quat[c] /= n


# ------------------------------------------------------------------------------------------ kinematics
@_jit
def _chain(H, q, pos, mat, axes, anchors, r, rot):
    """Body poses pos (B, 3), mat (B, 3, 3) and the joints' world axes, anchors (J, 3) at joint angles q.
    r, rot: (3, 3) scratch. Must equal `kinematics.chain` (its reference); checked by
    `tests/test_native.py::test_native_chain_and_links_are_kinematics`."""
    B = H.body_parent.shape[0]
    for b in range(B):
        pa = H.body_parent[b]
        if pa < 0:
            for i in range(3):
                pos[b, i] = H.body_pos[b, i]
                for k in range(3):
                    r[i, k] = H.body_mat[b, i, k]
        else:
            for i in range(3):
                pos[b, i] = pos[pa, i] + mat[pa, i, 0] * H.body_pos[b, 0] + mat[pa, i, 1] * H.body_pos[b, 1] \
                    + mat[pa, i, 2] * H.body_pos[b, 2]
                for k in range(3):
                    r[i, k] = mat[pa, i, 0] * H.body_mat[b, 0, k] + mat[pa, i, 1] * H.body_mat[b, 1, k] \
                        + mat[pa, i, 2] * H.body_mat[b, 2, k]
        j = H.body_joint[b]
        if j < 0:
            for i in range(3):
                for k in range(3):
                    mat[b, i, k] = r[i, k]
            continue
        ax, an = H.joint_axis[j], H.joint_pos[j]
        for i in range(3):
            anchors[j, i] = pos[b, i] + r[i, 0] * an[0] + r[i, 1] * an[1] + r[i, 2] * an[2]
            axes[j, i] = r[i, 0] * ax[0] + r[i, 1] * ax[1] + r[i, 2] * ax[2]
        s, c1 = math.sin(q[j]), 1 - math.cos(q[j])
        x, y, z = ax[0], ax[1], ax[2]  # Rodrigues: I + s [a]x + (1 - cos) [a]x^2
        # [a]x^2 = a a^T - |a|^2 I
        n2 = x * x + y * y + z * z
        rot[0, 0], rot[0, 1], rot[0, 2] = 1.0 + c1 * (x * x - n2), -s * z + c1 * x * y, s * y + c1 * x * z
        rot[1, 0], rot[1, 1], rot[1, 2] = s * z + c1 * x * y, 1.0 + c1 * (y * y - n2), -s * x + c1 * y * z
        rot[2, 0], rot[2, 1], rot[2, 2] = -s * y + c1 * x * z, s * x + c1 * y * z, 1.0 + c1 * (z * z - n2)
        for i in range(3):
            for k in range(3):
                mat[b, i, k] = r[i, 0] * rot[0, k] + r[i, 1] * rot[1, k] + r[i, 2] * rot[2, k]
        for i in range(3):
            pos[b, i] = anchors[j, i] - (mat[b, i, 0] * an[0] + mat[b, i, 1] * an[1] + mat[b, i, 2] * an[2])


@_jit
def _links(H, q, near, x, jac, pos, mat, axes, anchors, S):
    """The links' centre-line points x (L, 3) nearest the world points `near` (L, 3), and their Jacobians
    jac (L, 3, J). S: `Scratch` (its kin_v, kin_m). Must equal `kinematics.closest_on_links_and_jacobians` (its
    reference); checked by `tests/test_native.py::test_native_chain_and_links_are_kinematics`."""
    _chain(H, q, pos, mat, axes, anchors, S.kin_m[0], S.kin_m[1])
    L, J = H.link_body.shape[0], q.shape[0]
    centre, axis, d, c = S.kin_v[0], S.kin_v[1], S.kin_v[2], S.kin_v[3]
    for lk in range(L):
        b = H.link_body[lk]
        for i in range(3):
            centre[i] = pos[b, i] + mat[b, i, 0] * H.link_site[lk, 0] + mat[b, i, 1] * H.link_site[lk, 1] \
                + mat[b, i, 2] * H.link_site[lk, 2]
            axis[i] = mat[b, i, 0] * H.link_axis[lk, 0] + mat[b, i, 1] * H.link_axis[lk, 1] \
                + mat[b, i, 2] * H.link_axis[lk, 2]
        s = 0.0
        for i in range(3):
            s += (near[lk, i] - centre[i]) * axis[i]
        half = H.link_half[lk]
        s = min(max(s, -half), half)
        for i in range(3):
            x[lk, i] = centre[i] + s * axis[i]
        for jj in range(J):
            if H.joint_moves_body[b, jj] == 0.0:
                for i in range(3):
                    jac[lk, i, jj] = 0.0
                continue
            for i in range(3):
                d[i] = x[lk, i] - anchors[jj, i]
            _cross(axes[jj], d, c)
            for i in range(3):
                jac[lk, i, jj] = c[i] * H.joint_moves_body[b, jj]


# ------------------------------------------------------------------------------------------ force solve
@_jit
def _project(x, normals, mu, mask):
    """Each contact's force x[3k:3k+3] projected onto its friction cone, 0 if masked. Must equal
    `wrench.project_cone` (its reference); checked within `_solve` by
    `tests/test_native.py::test_native_force_solve_is_the_wrench_solve`."""
    for k in range(normals.shape[0]):
        if not mask[k]:
            x[3 * k], x[3 * k + 1], x[3 * k + 2] = 0.0, 0.0, 0.0
            continue
        n0, n1, n2 = normals[k, 0], normals[k, 1], normals[k, 2]
        f0, f1, f2 = x[3 * k], x[3 * k + 1], x[3 * k + 2]
        fn = f0 * n0 + f1 * n1 + f2 * n2
        t0, t1, t2 = f0 - fn * n0, f1 - fn * n1, f2 - fn * n2
        tn = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2 + 1e-30)
        if tn <= mu * fn:
            continue
        if mu * tn <= -fn:
            x[3 * k], x[3 * k + 1], x[3 * k + 2] = 0.0, 0.0, 0.0
            continue
        fb = (fn + mu * tn) / (1.0 + mu * mu)
        s = mu * fb / tn
        x[3 * k], x[3 * k + 1], x[3 * k + 2] = fb * n0 + s * t0, fb * n1 + s * t1, fb * n2 + s * t2


@_jit
def _solve(C, points, normals, active, mu, wrench, center, init, forces, S, lip=-1.0):
    """`wrench.solve` ("apg", `Controller._forces`): cone forces (L, 3) on the `active` links supplying `wrench`
    (6,) about `center`, pulled towards `grip_force` along each normal, from `init` (L, 3); written to forces.
    Must equal `wrench.solve` (its reference); checked by
    `tests/test_native.py::test_native_force_solve_is_the_wrench_solve`.

    The grasp matrix's products are written per contact (its force rows are identities, its torque rows cross
    products with the contact's lever r_k): G y = (sum y_k, sum r_k x y_k) and (G^T e)_k = e_f + e_t x r_k,
    with the torque rows scaled by 1 / torque_length as in `wrench._solve`. `lip` > 0: the step's Lipschitz
    constant, if known (it depends on the active contacts' positions only); the one used is returned. S: `Scratch`
    (its gg, lever and apg)."""
    L = points.shape[0]
    s = 1.0 / C.torque_length
    r, target = S.lever[0], S.lever[1]  # the scaled levers of the active contacts, the preferred forces
    x, x_prev = S.apg[0], S.apg[1]
    r[:] = 0.0
    for k in range(L):
        if active[k]:
            for i in range(3):
                r[k, i] = (points[k, i] - center[i]) * s
    if lip <= 0.0:
        lip = _lipschitz(r, active, S.gg) + C.rho
    target[:] = 0.0
    x[:] = 0.0
    for k in range(L):
        if active[k]:
            for i in range(3):
                target[k, i] = C.grip_force * normals[k, i]
                x[3 * k + i] = init[k, i]
    _project(x, normals, mu, active)
    x_prev[:] = x
    _iterate(C, normals, active, mu, wrench, s, lip, S)
    for k in range(L):
        for i in range(3):
            forces[k, i] = x[3 * k + i]
    return lip


@_jit
def _lipschitz(r, active, gg):
    """The largest eigenvalue of G G^T = sum_k [[I, R_k^T], [R_k, R_k R_k^T]], R_k = [r_k]x, over the `active`
    contacts' scaled levers r (L, 3). gg: (6, 6) scratch."""
    gg[:] = 0.0
    for k in range(r.shape[0]):
        if not active[k]:
            continue
        r0, r1, r2 = r[k, 0], r[k, 1], r[k, 2]
        n2 = r0 * r0 + r1 * r1 + r2 * r2
        gg[0, 0] += 1.0
        gg[1, 1] += 1.0
        gg[2, 2] += 1.0
        # R^T = -R: the force-torque block
        gg[0, 4] += r2
        gg[0, 5] -= r1
        gg[1, 3] -= r2
        gg[1, 5] += r0
        gg[2, 3] += r1
        gg[2, 4] -= r0
        # R R^T = |r|^2 I - r r^T
        gg[3, 3] += n2 - r0 * r0
        gg[4, 4] += n2 - r1 * r1
        gg[5, 5] += n2 - r2 * r2
        gg[3, 4] -= r0 * r1
        gg[3, 5] -= r0 * r2
        gg[4, 5] -= r1 * r2
    for i in range(6):
        for j in range(i):
            gg[i, j] = gg[j, i]
    return np.linalg.eigvalsh(gg)[-1]


@_jit
def _iterate(C, normals, active, mu, wrench, s, lip, S):
    """`_solve`'s accelerated projected gradient steps (C.iterations) from S.apg's iterate x (= the one before,
    x_prev), with the levers and preferred forces of S.lever and the torque rows scaled by s; x updated."""
    L = normals.shape[0]
    r, target = S.lever[0], S.lever[1]
    x, x_prev, y = S.apg[0], S.apg[1], S.apg[2]
    b0, b1, b2 = wrench[0], wrench[1], wrench[2]
    b3, b4, b5 = wrench[3] * s, wrench[4] * s, wrench[5] * s
    rho = C.rho
    ks = math.sqrt(lip / rho)
    beta = (ks - 1.0) / (ks + 1.0)
    y[:] = 0.0
    for _ in range(C.iterations):
        e0, e1, e2, e3, e4, e5 = -b0, -b1, -b2, -b3, -b4, -b5  # G y - b
        for k in range(L):
            if not active[k]:
                continue
            y0 = x[3 * k] + beta * (x[3 * k] - x_prev[3 * k])
            y1 = x[3 * k + 1] + beta * (x[3 * k + 1] - x_prev[3 * k + 1])
            y2 = x[3 * k + 2] + beta * (x[3 * k + 2] - x_prev[3 * k + 2])
            y[3 * k], y[3 * k + 1], y[3 * k + 2] = y0, y1, y2
            r0, r1, r2 = r[k, 0], r[k, 1], r[k, 2]
            e0 += y0
            e1 += y1
            e2 += y2
            e3 += r1 * y2 - r2 * y1
            e4 += r2 * y0 - r0 * y2
            e5 += r0 * y1 - r1 * y0
        for k in range(L):
            if not active[k]:
                continue
            r0, r1, r2 = r[k, 0], r[k, 1], r[k, 2]
            g0 = e0 + (e4 * r2 - e5 * r1) + rho * (y[3 * k] - target[k, 0])
            g1 = e1 + (e5 * r0 - e3 * r2) + rho * (y[3 * k + 1] - target[k, 1])
            g2 = e2 + (e3 * r1 - e4 * r0) + rho * (y[3 * k + 2] - target[k, 2])
            x_prev[3 * k], x_prev[3 * k + 1], x_prev[3 * k + 2] = x[3 * k], x[3 * k + 1], x[3 * k + 2]
            x[3 * k] = y[3 * k] - g0 / lip
            x[3 * k + 1] = y[3 * k + 1] - g1 / lip
            x[3 * k + 2] = y[3 * k + 2] - g2 / lip
        _project(x, normals, mu, active)


# ------------------------------------------------------------------------------------------ one tick
@_jit
def _row(episodes, r):
    """Episode r of `episodes` as `Episodes` of one episode (its rows; dt, mass, friction, hold_time numbers)."""
    return Episodes(waypoints=episodes.waypoints[r], quats=episodes.quats[r], dt=episodes.dt[r],
                    w_ext=episodes.w_ext[r], mass=episodes.mass[r], inertia=episodes.inertia[r], com=episodes.com[r],
                    friction=episodes.friction[r], hold_time=episodes.hold_time[r])


@_jit
def _tool(sc, obs, p, quat, vel, w_body, mat):
    """The tool's pose and velocity in an observation row (`Scene.observe`; sc: `Scene`): p, quat (normalised),
    vel, w_body (tool frame), mat written; whether the state is finite (`Scene.status`)."""
    nq = sc.nq
    a0, v0 = sc.tool_qpos, nq + sc.tool_dof
    qn = 0.0
    for i in range(4):
        quat[i] = obs[a0 + 3 + i]
        qn += quat[i] * quat[i]
    qn = math.sqrt(qn)
    for i in range(4):
        quat[i] /= qn
    for i in range(3):
        p[i], vel[i], w_body[i] = obs[a0 + i], obs[v0 + i], obs[v0 + 3 + i]
    _quat_to_mat(quat, mat)
    finite = True
    for i in range(nq + sc.nv):
        if not math.isfinite(obs[i]):
            finite = False
    for i in range(4):
        if not math.isfinite(quat[i]):
            finite = False
    return finite


@_jit
def _status(K, j, obs, ep, out, S):
    """`Physics.check` after tick j of one episode (`_row`): out[0:3] = angle error [deg], position error [m],
    fell (0/1). S: `Scratch` (v3's rows 0..6, m3[0], q4, as `_control`)."""
    sc, tl, oc = K.scene, K.timeline, K.outcome
    v3 = S.v3
    p, quat, vel, w_body, mat = v3[0], S.q4[0], v3[1], v3[2], S.m3[0]
    finite = _tool(sc, obs, p, quat, vel, w_body, mat)
    ref_pos, ref_vel, ref_acc, ref_quat = v3[4], v3[5], v3[6], S.q4[1]
    _reference(ep.waypoints, ep.quats, ep.dt, F32(j + 1) * tl.timestep, ref_pos, ref_vel, ref_acc, ref_quat)
    dot = abs(quat[0] * ref_quat[0] + quat[1] * ref_quat[1] + quat[2] * ref_quat[2] + quat[3] * ref_quat[3])
    angle = math.degrees(2 * math.acos(min(max(dot, 0.0), 1.0)))
    perr = math.sqrt((p[0] - ref_pos[0]) ** 2 + (p[1] - ref_pos[1]) ** 2 + (p[2] - ref_pos[2]) ** 2)
    lowest = np.inf
    for c in range(sc.tool_corners.shape[0]):
        z = mat[2, 0] * sc.tool_corners[c, 0] + mat[2, 1] * sc.tool_corners[c, 1] + mat[2, 2] * sc.tool_corners[c, 2]
        lowest = min(lowest, z)
    lowest += p[2]
    fell = (not finite) or (j >= tl.n_segment and lowest < oc.fall_height) or perr > oc.fall_distance \
        or angle > oc.fall_angle
    out[0] = angle if finite else 0.0
    out[1] = perr if finite else 0.0
    out[2] = 1.0 if fell else 0.0


@_jit
def _control(K, j, cs, obs, ep, out, S):
    """`Physics.tick` j of one episode (`_row`): out[:nu] motor commands, out[nu:nu + 6] the tool's external
    wrench; its controller state cs (flat, float32) updated in place. S: `Scratch`; the steps below are passed the
    groups of K they read and S's views (the tool's pose and the reference: v3's rows 0..6, m3[0], q4; the links':
    S.links, by name)."""
    sc, tl, C, W = K.scene, K.timeline, K.controller, S.links
    nq, nv, J = sc.nq, sc.nv, sc.hand_qpos.shape[0]
    v3, f = S.v3, S.f
    q, dq, bias = f[0:J], f[J:2 * J], f[2 * J:3 * J]
    for i in range(J):
        q[i], dq[i], bias[i] = obs[sc.hand_qpos[i]], obs[nq + sc.hand_dof[i]], obs[nq + nv + sc.hand_dof[i]]
    p, quat, vel, w_body, mat = v3[0], S.q4[0], v3[1], v3[2], S.m3[0]
    _tool(sc, obs, p, quat, vel, w_body, mat)
    if C.pose_filter < 1.0:
        _filter(K.state, C.pose_filter, tl.timestep, cs, p, quat, vel, w_body, mat, q, dq)
    omega = v3[3]
    for i in range(3):
        omega[i] = mat[i, 0] * w_body[0] + mat[i, 1] * w_body[1] + mat[i, 2] * w_body[2]

    # ---- Physics.tick: the external wrench and the reference at this tick
    ts = tl.timestep
    time = F32(j) * ts
    held = (F32(j + 1) * ts - ep.hold_time) / tl.ramp
    ramp = float(min(max(held, F32(0.0)), F32(1.0)))
    ext = f[4 * J:4 * J + 6]
    for i in range(6):
        ext[i] = float(F32(ramp) * ep.w_ext[i])
    _reference(ep.waypoints, ep.quats, ep.dt, time, v3[4], v3[5], v3[6], S.q4[1])

    # ---- the controller (`Controller.control`)
    _read_state(K.state, cs, W)
    before_move, in_move = _phase(K.state, tl, cs, time, v3[7])
    _targets(K.hand, before_move, in_move, v3[7], W)
    _on_tool(K.hand, p, mat, vel, omega, W, v3)
    x, jac = W.blocks[X], S.jac
    _links(K.hand, q, W.blocks[X_REF], x, jac, S.body_pos, S.body_mat, S.joints[0], S.joints[1], S)
    v = W.blocks[V]
    for lk in range(x.shape[0]):
        for i in range(3):
            acc = 0.0
            for jj in range(J):
                acc += jac[lk, i, jj] * dq[jj]
            v[lk, i] = acc
    _loads(K.hand, tl, p, mat, W, v3[10])
    _tracking(K.fingers, jac, W, v3, S.m3[2], S.adj)
    required = f[4 * J + 6:4 * J + 12]
    _tool_wrench(C, sc.gravity, ts, ep, ext, v3, S.m3, S.q4, f[4 * J + 6:4 * J + 15])

    # ---- the force solves on the observed tool, blended over the changed link's load
    mu, share = _contacts(K.hand, C, ep.friction, p, mat, v3, W)
    pts, nrm, com_w, flags = W.blocks[POINTS], W.blocks[NORMAL], v3[24], W.flags
    f_with, f_without, f_a, f_b = W.blocks[F_WITH], W.blocks[F_WITHOUT], W.blocks[F_A], W.blocks[F_B]
    lip = _solve(C, pts, nrm, flags[ACTIVE], mu, required, com_w, f_with, f_a, S)
    same = True  # no link changing: both solves have one grasp matrix
    for lk in range(x.shape[0]):
        same = same and flags[ACTIVE, lk] == flags[ACTIVE_B, lk]
    if same and _same_bits(f_with, f_without):  # one problem from one start: the first solve's forces, bit for bit
        for lk in range(x.shape[0]):
            for i in range(3):
                f_b[lk, i] = f_a[lk, i]
    else:
        _solve(C, pts, nrm, flags[ACTIVE_B], mu, required, com_w, f_without, f_b, S, lip if same else -1.0)
    _torques(K.fingers, K.state, sc, cs, f, share, jac, W)
    if C.strength_rate > 0:
        _strengths(C, K.state, sc, cs, f, jac, W, float(ep.mass) * _norm3(sc.gravity), float(ts), S.m3[2], v3[9],
                   S.adj)
    for jj in range(J):
        f[3 * J + jj] = min(max(f[3 * J + jj] / cs[K.state.strength + jj], sc.ctrl_low[jj]), sc.ctrl_high[jj])
    _write(K.state, sc, cs, f, W, out)


@_jit
def _read_state(off, cs, W):
    """The controller state's fields the tick reads, from its flat row cs (offsets off) into the links' views W."""
    options, previous = W.options[OPTIONS], W.options[PREVIOUS]
    changed, anchored, load = W.flags[CHANGED], W.flags[ANCHORED], W.load
    anchor, park, f_with, f_without = W.blocks[ANCHOR], W.blocks[PARK], W.blocks[F_WITH], W.blocks[F_WITHOUT]
    for lk in range(load.shape[0]):
        options[lk] = int(round(cs[off.options + lk]))
        previous[lk] = int(round(cs[off.previous + lk]))
        changed[lk] = cs[off.changed + lk] > 0.5
        anchored[lk] = cs[off.anchored + lk] > 0.5
        load[lk] = cs[off.load + lk]
        for i in range(3):
            anchor[lk, i] = cs[off.anchor + 3 * lk + i]
            park[lk, i] = cs[off.park + 3 * lk + i]
            f_with[lk, i] = cs[off.f_with + 3 * lk + i]
            f_without[lk, i] = cs[off.f_without + 3 * lk + i]


@_jit
def _phase(off, tl, cs, time, on_path):
    """`Controller._phase` (float32) at float32 `time`: the changing link's point on its path (tool frame) written
    to on_path (3,); (before the move, in the move)."""
    tau_s = time - cs[off.start]
    u = min(max((tau_s - tl.unload) / tl.move, F32(0.0)), F32(1.0))
    times = tl.path_times
    npath = times.shape[0]
    seg = 0
    for i in range(npath):
        if times[i] <= u:
            seg = i
    seg = min(max(seg, 0), npath - 2)
    w = min(max((u - times[seg]) / (times[seg + 1] - times[seg]), F32(0.0)), F32(1.0))
    w = w * w * (F32(3) - F32(2) * w)
    wd = float(w)
    for i in range(3):
        on_path[i] = (1 - wd) * cs[off.path + 3 * seg + i] + wd * cs[off.path + 3 * (seg + 1) + i]
    return tau_s < tl.unload, u < F32(1.0)


@_jit
def _targets(H, before_move, in_move, on_path, W):
    """Each link's option now, its phase flags, its target (tool frame) and whether it is tracked."""
    options, previous, current = W.options[OPTIONS], W.options[PREVIOUS], W.options[CURRENT]
    fl, anchor, park, tgt, busy = W.flags, W.blocks[ANCHOR], W.blocks[PARK], W.blocks[TARGET], W.busy
    busy[:] = False
    for lk in range(current.shape[0]):
        changed = fl[CHANGED, lk]
        fl[UNLOADING, lk] = changed and before_move
        fl[TRAVELLING, lk] = changed and in_move
        fl[MOVING, lk] = changed and (not before_move) and in_move
        current[lk] = previous[lk] if fl[UNLOADING, lk] else options[lk]
        fl[ANCHORED, lk] = fl[ANCHORED, lk] and not fl[MOVING, lk]
        for i in range(3):
            if fl[ANCHORED, lk]:
                tgt[lk, i] = anchor[lk, i]
            elif changed:
                tgt[lk, i] = on_path[i]
            elif current[lk] > 0:
                tgt[lk, i] = H.targets[lk, current[lk], i]
            else:
                tgt[lk, i] = park[lk, i]
        if current[lk] > 0 or changed:
            busy[H.link_finger[lk]] = True
    for lk in range(current.shape[0]):
        fl[TRACKED, lk] = current[lk] > 0 or fl[CHANGED, lk] or ((not busy[H.link_finger[lk]]) and H.link_is_tip[lk])


@_jit
def _on_tool(H, p, mat, vel, omega, W, v3):
    """The targets fixed to the observed tool (pose p, mat; velocity vel, omega): their points, velocities and
    normals (world and tool frame). v3's rows 8, 9: scratch."""
    current, tgt = W.options[CURRENT], W.blocks[TARGET]
    x_ref, v_ref, nrm, nrm_t = W.blocks[X_REF], W.blocks[V_REF], W.blocks[NORMAL], W.blocks[NORMAL_T]
    d, c = v3[8], v3[9]
    for lk in range(current.shape[0]):
        for i in range(3):
            x_ref[lk, i] = p[i] + mat[i, 0] * tgt[lk, 0] + mat[i, 1] * tgt[lk, 1] + mat[i, 2] * tgt[lk, 2]
            nrm_t[lk, i] = H.normals[lk, current[lk], i]
        for i in range(3):
            nrm[lk, i] = mat[i, 0] * nrm_t[lk, 0] + mat[i, 1] * nrm_t[lk, 1] + mat[i, 2] * nrm_t[lk, 2]
            d[i] = x_ref[lk, i] - p[i]
        _cross(omega, d, c)
        for i in range(3):
            v_ref[lk, i] = vel[i] + c[i]


@_jit
def _loads(H, tl, p, mat, W, here):
    """The load fractions: down when a link is to let go, up once an arriving link touches (where it touches:
    its anchor); which links hold the tool. here (3,): scratch."""
    current, load, fl = W.options[CURRENT], W.load, W.flags
    x_ref, x, nrm, nrm_t = W.blocks[X_REF], W.blocks[X], W.blocks[NORMAL], W.blocks[NORMAL_T]
    anchor = W.blocks[ANCHOR]
    for lk in range(current.shape[0]):
        cur = current[lk]
        want = cur > 0 and not fl[UNLOADING, lk] and not fl[TRAVELLING, lk]
        gap = 0.0
        for i in range(3):
            gap += (x_ref[lk, i] - x[lk, i]) * nrm[lk, i]
        across = 0.0
        for i in range(3):
            across += (x_ref[lk, i] - x[lk, i] - gap * nrm[lk, i]) ** 2
        touching = gap < tl.touch_tol and math.sqrt(across) < tl.reach_tol
        arrive = cur > 0 and not fl[ANCHORED, lk] and not fl[TRAVELLING, lk] and touching
        if arrive:  # where it touches: its point now (tool frame) moved onto the option's contact level
            for i in range(3):
                here[i] = mat[0, i] * (x[lk, 0] - p[0]) + mat[1, i] * (x[lk, 1] - p[1]) + mat[2, i] * (x[lk, 2] - p[2])
            lev = 0.0
            for i in range(3):
                lev += (here[i] - H.targets[lk, cur, i]) * nrm_t[lk, i]
            for i in range(3):
                anchor[lk, i] = here[i] - lev * nrm_t[lk, i]
        fl[ANCHORED, lk] = fl[ANCHORED, lk] or arrive
        up = min(load[lk] + tl.load_step, F32(1.0)) if fl[ANCHORED, lk] else load[lk]
        load[lk] = up if want else max(load[lk] - tl.unload_step, F32(0.0))
        fl[HELD, lk] = fl[ANCHORED, lk] and cur > 0


@_jit
def _tracking(Fi, jac, W, v3, jjt, adj):
    """The tracked links' tracking forces (`Controller._tracking`; Fi: `Fingers`): an impedance on a held link
    (stiffer along its normal), damped least squares on a free one. v3's rows 8, 11, 12, jjt (3, 3), adj (3, 3):
    scratch."""
    x_ref, v_ref, x, v, nrm = W.blocks[X_REF], W.blocks[V_REF], W.blocks[X], W.blocks[V], W.blocks[NORMAL]
    fl, f_track = W.flags, W.blocks[F_TRACK]
    f_track[:] = 0.0
    err, derr, d = v3[11], v3[12], v3[8]
    ratio = Fi.held_ratio
    for lk in range(x.shape[0]):
        if not fl[TRACKED, lk]:
            continue
        en, dn = 0.0, 0.0
        for i in range(3):
            err[i], derr[i] = x_ref[lk, i] - x[lk, i], v_ref[lk, i] - v[lk, i]
            en += err[i] * nrm[lk, i]
            dn += derr[i] * nrm[lk, i]
        if fl[HELD, lk]:
            for i in range(3):
                e_n, d_n = en * nrm[lk, i], dn * nrm[lk, i]
                f_track[lk, i] = Fi.finger_kp * (e_n + ratio * (err[i] - e_n)) \
                    + Fi.finger_kd * (d_n + ratio * (derr[i] - d_n))
        else:
            for i in range(3):
                for k in range(3):
                    acc = 0.0
                    for jj in range(jac.shape[2]):
                        acc += jac[lk, i, jj] * jac[lk, k, jj]
                    jjt[i, k] = acc + (Fi.free_damping**2 if i == k else 0.0)
            _solve3(jjt, err, d, adj[0], adj[1], adj[2])
            for i in range(3):
                f_track[lk, i] = Fi.free_stiffness * d[i] + Fi.finger_kd * derr[i]


@_jit
def _tool_wrench(C, g, ts, ep, ext, v3, m3, q4, required):
    """The wrench the contacts are to put on the tool (`Controller.tool_wrench`; C: `Gains`, g: gravity, ts: the
    timestep): the reference's motion and pose feedback (capped) less the external wrench ext (6,), written to
    required[:6], the feedback's force before its cap to required[6:9]; the CoM's offset (world frame) to v3[13].
    The tool's pose and the reference as in `_control`; v3's rows 9, 13..22, m3[1]: scratch."""
    p, quat, vel, omega, mat = v3[0], q4[0], v3[1], v3[3], m3[0]
    ref_pos, ref_vel, ref_acc, ref_quat = v3[4], v3[5], v3[6], q4[1]
    com_t, inertia_d, c = ep.com, ep.inertia, v3[9]
    m = float(ep.mass)
    r_com = v3[13]
    for i in range(3):
        r_com[i] = mat[i, 0] * com_t[0] + mat[i, 1] * com_t[1] + mat[i, 2] * com_t[2]
    mat_ref = m3[1]
    _quat_to_mat(ref_quat, mat_ref)
    _cross(omega, r_com, c)
    weight = m * _norm3(g)
    feedback = v3[14]
    for i in range(3):
        com_ref = ref_pos[i] + mat_ref[i, 0] * com_t[0] + mat_ref[i, 1] * com_t[1] + mat_ref[i, 2] * com_t[2]
        feedback[i] = m * (C.kp * (com_ref - (p[i] + r_com[i])) + C.kd * (ref_vel[i] - (vel[i] + c[i])))
    stiff, damp = v3[15], v3[16]
    for i in range(3):
        stiff[i] = float(inertia_d[i]) + m * C.tool_radius**2
        damp[i] = min(stiff[i], C.rotation_step / (float(ts) * C.kd) * float(inertia_d[i]))
    err_r = v3[17]
    _rotation_error(ref_quat, quat, err_r)
    # world-frame products: (mat diag(s) mat^T) v
    turn, inertia_w = v3[18], v3[19]
    lo_s, lo_d, lo_i = v3[20], v3[21], v3[22]  # in the tool frame
    for k in range(3):
        lo_s[k] = C.kp * (mat[0, k] * err_r[0] + mat[1, k] * err_r[1] + mat[2, k] * err_r[2])
        lo_i[k] = mat[0, k] * omega[0] + mat[1, k] * omega[1] + mat[2, k] * omega[2]
        lo_d[k] = C.kd * lo_i[k]
    for i in range(3):
        turn[i] = 0.0
        inertia_w[i] = 0.0
        for k in range(3):
            turn[i] += mat[i, k] * (stiff[k] * lo_s[k] - damp[k] * lo_d[k])
            inertia_w[i] += mat[i, k] * (float(inertia_d[k]) * lo_i[k])
    cap = max(C.feedback_limit * weight, C.feedback_floor)
    for i in range(3):
        required[6 + i] = feedback[i]  # before its cap: `_strengths` reads it
    _clip_norm(feedback, cap)
    _clip_norm(turn, cap * C.tool_radius)
    _cross(omega, inertia_w, c)
    for i in range(3):
        required[i] = m * (ref_acc[i] - g[i]) + feedback[i] - ext[i]
        required[3 + i] = turn[i] + c[i] - ext[3 + i]


@_jit
def _contacts(H, C, friction, p, mat, v3, W):
    """The force solves' problem on the observed tool: the contact points, the CoM (world, v3[24]; its offset
    v3[13] from `_tool_wrench`), the links active with and without the changed one; (the friction coefficient,
    the changed link's load). v3's rows 9, 23, 25, 26: scratch."""
    current, load, fl = W.options[CURRENT], W.load, W.flags
    anchor, nrm_t, pts = W.blocks[ANCHOR], W.blocks[NORMAL_T], W.blocks[POINTS]
    surface, r_com = v3[23], v3[13]
    for lk in range(current.shape[0]):
        cur = current[lk]
        for i in range(3):
            surface[i] = (anchor[lk, i] if fl[ANCHORED, lk] else H.targets[lk, cur, i]) \
                + H.link_radius[lk] * nrm_t[lk, i]
        for i in range(3):
            pts[lk, i] = p[i] + mat[i, 0] * surface[0] + mat[i, 1] * surface[1] + mat[i, 2] * surface[2]
    if C.measured:  # a touching link's normal: the tool surface's at its centre-line point
        x, nrm = W.blocks[X], W.blocks[NORMAL]
        for lk in range(current.shape[0]):
            if fl[ANCHORED, lk] and current[lk] > 0:
                _measured_normal(H, p, mat, x[lk], nrm[lk], v3[23], v3[9], v3[25], v3[26])
    mu = C.friction_margin * float(friction)
    com_w = v3[24]
    for i in range(3):
        com_w[i] = p[i] + r_com[i]
    share = F32(0.0)
    for lk in range(current.shape[0]):
        fl[ACTIVE, lk] = current[lk] > 0 and load[lk] > 0
        fl[ACTIVE_B, lk] = fl[ACTIVE, lk] and not fl[CHANGED, lk]
        if fl[CHANGED, lk]:
            share += load[lk]
    return mu, share


@_jit
def _measured_normal(H, p, mat, x, nrm, here, g, rel, gr):
    """`Controller.measured_normals` of one touching link at world point x (3,), the tool at p, mat: nrm (3,)
    overwritten by the tool surface's inward normal there, unless the SDF gradient vanishes (then left as it is).
    here, g, rel, gr (3,): scratch."""
    for i in range(3):
        here[i] = mat[0, i] * (x[0] - p[0]) + mat[1, i] * (x[1] - p[1]) + mat[2, i] * (x[2] - p[2])
    _outward(H, here, g, rel, gr)
    n = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
    if n > MIN_GRADIENT:
        for i in range(3):
            nrm[i] = -(mat[i, 0] * g[0] + mat[i, 1] * g[1] + mat[i, 2] * g[2]) / n


@_jit
def _round(kind, size, x, y, z, g):
    """`ik.round_sdf` of one point (x, y, z) in a round primitive's frame (kind: `ROUNDS` index): the distance,
    its gradient written to g (3,)."""
    a, b, c = size[0], size[1], size[2]
    eps = 1e-12
    if kind <= 1:  # sphere, capsule
        dz = z - min(max(z, -b), b) if kind == 1 else z
        r = math.sqrt(x * x + y * y + dz * dz + eps)
        g[0], g[1], g[2] = x / r, y / r, dz / r
        return r - a
    if kind == 2:  # cylinder
        rho = math.sqrt(x * x + y * y + eps)
        dr, dzz = rho - a, abs(z) - b
        o_r, o_z = max(dr, 0.0), max(dzz, 0.0)
        outside = math.sqrt(o_r * o_r + o_z * o_z + eps)
        side = dr >= dzz
        w_r = o_r / outside if outside > 1e-6 else (1.0 if side else 0.0)
        w_z = o_z / outside if outside > 1e-6 else (0.0 if side else 1.0)
        sz = 1.0 if z > 0 else -1.0 if z < 0 else 0.0
        g[0], g[1], g[2] = w_r * x / rho, w_r * y / rho, w_z * sz
        return outside + min(max(dr, dzz), 0.0)
    k0 = math.sqrt((x / a) ** 2 + (y / b) ** 2 + (z / c) ** 2 + eps)  # ellipsoid
    nx, ny, nz = x / a**2, y / b**2, z / c**2
    n = math.sqrt(nx * nx + ny * ny + nz * nz + eps)
    g[0], g[1], g[2] = nx / n, ny / n, nz / n
    return (k0 - 1.0) * min(a, b, c)


@_jit
def _outward(H, h, g, rel, gr):
    """The tool's surface normal (outward, tool frame) at the tool-frame point h (3,) written to g (3,): the
    gradient of its signed distance, as `ik.box_sdf_and_grad` (the nearest box, the first of equals; a round
    primitive where strictly nearer). rel, gr (3,): scratch."""
    best = np.inf
    for b in range(H.box_pos.shape[0]):
        R = H.box_mat[b]
        for i in range(3):
            rel[i] = R[0, i] * (h[0] - H.box_pos[b, 0]) + R[1, i] * (h[1] - H.box_pos[b, 1]) \
                + R[2, i] * (h[2] - H.box_pos[b, 2])
        deepest, o2 = -np.inf, 0.0
        for i in range(3):
            d = abs(rel[i]) - H.box_half[b, i]
            deepest = max(deepest, d)
            o2 += max(d, 0.0) ** 2
        outside = math.sqrt(o2 + 1e-12)
        dist = outside + min(deepest, 0.0)
        if dist < best:
            best = dist
            for i in range(3):
                d = abs(rel[i]) - H.box_half[b, i]
                face = 1.0 if (d == deepest and deepest < 0.0) else 0.0
                sg = 1.0 if rel[i] > 0 else -1.0 if rel[i] < 0 else 0.0
                gr[i] = sg * (max(d, 0.0) / outside + face)
            for i in range(3):
                g[i] = R[i, 0] * gr[0] + R[i, 1] * gr[1] + R[i, 2] * gr[2]
    for r in range(H.round_pos.shape[0]):
        R = H.round_mat[r]
        for i in range(3):
            rel[i] = R[0, i] * (h[0] - H.round_pos[r, 0]) + R[1, i] * (h[1] - H.round_pos[r, 1]) \
                + R[2, i] * (h[2] - H.round_pos[r, 2])
        dist = _round(H.round_kind[r], H.round_size[r], rel[0], rel[1], rel[2], gr)
        if dist < best:
            best = dist
            for i in range(3):
                g[i] = R[i, 0] * gr[0] + R[i, 1] * gr[1] + R[i, 2] * gr[2]


@_jit
def _torques(Fi, off, sc, cs, f, share, jac, W):
    """The motor torques (f's (J,) tau) before the motors' strengths and range: the two solves' forces blended over
    the changed link's load `share`, and the tracking forces, through the Jacobians; the posture term (rest: cs at
    off.q_rest), the joints' bias."""
    J = jac.shape[2]
    q, bias, tau = f[0:J], f[2 * J:3 * J], f[3 * J:4 * J]
    f_a, f_b, f_track = W.blocks[F_A], W.blocks[F_B], W.blocks[F_TRACK]
    sh = float(share)
    for jj in range(J):
        acc = 0.0
        for lk in range(jac.shape[0]):
            for i in range(3):
                acc += jac[lk, i, jj] * (sh * f_a[lk, i] + (1 - sh) * f_b[lk, i] + f_track[lk, i])
        tau[jj] = acc + Fi.posture_kp * (cs[off.q_rest + jj] - q[jj]) + bias[jj]


@_jit
def _filter(off, a, ts, cs, p, quat, vel, w_body, mat, q, dq):
    """`Controller._filtered` (gain a, timestep ts): the estimate in cs (at off.estimate) carried one tick by the
    measured velocities and moved a of the way to the observed p, quat (normalised), q; written to cs and over p,
    quat, mat and q."""
    e = off.estimate
    for i in range(3):
        pred = F32(cs[e + i] + F32(vel[i] * ts))
        p[i] = F32(pred + F32(a * F32(p[i] - pred)))
        cs[e + i] = p[i]
    w, x, y, z = cs[e + 3], cs[e + 4], cs[e + 5], cs[e + 6]
    hx, hy, hz = F32(0.5 * ts * w_body[0]), F32(0.5 * ts * w_body[1]), F32(0.5 * ts * w_body[2])
    pw = w - x * hx - y * hy - z * hz
    px = w * hx + x + y * hz - z * hy
    py = w * hy - x * hz + y + z * hx
    pz = w * hz + x * hy - y * hx + z
    sg = 1.0 if pw * quat[0] + px * quat[1] + py * quat[2] + pz * quat[3] >= 0 else -1.0
    qw, qx = pw + a * (sg * quat[0] - pw), px + a * (sg * quat[1] - px)
    qy, qz = py + a * (sg * quat[2] - py), pz + a * (sg * quat[3] - pz)
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    quat[0], quat[1], quat[2], quat[3] = qw / n, qx / n, qy / n, qz / n
    for i in range(4):
        cs[e + 3 + i] = quat[i]
    _quat_to_mat(quat, mat)
    for i in range(q.shape[0]):
        pred = F32(cs[e + 7 + i] + F32(dq[i] * ts))
        q[i] = F32(pred + F32(a * F32(q[i] - pred)))
        cs[e + 7 + i] = q[i]


@_jit
def _strengths(C, off, sc, cs, f, jac, W, weight, ts, jjt, pull, adj):
    """`Controller._strengths`: the motors' strength estimates in cs (at off.strength) moved by this tick's pose
    feedback (f's uncapped feedback force), from f's tau (before the strengths). jjt (3, 3), pull (3,), adj (3, 3)
    and f's last J numbers (the gradient): scratch."""
    J = jac.shape[2]
    tau, fb, grad = f[3 * J:4 * J], f[4 * J + 12:4 * J + 15], f[4 * J + 15:5 * J + 15]
    size = math.sqrt(fb[0] * fb[0] + fb[1] * fb[1] + fb[2] * fb[2])
    keep = max(0.0, 1.0 - C.strength_deadband * weight / (size + 1e-9))
    for lk in range(jac.shape[0]):
        if W.flags[CHANGED, lk]:
            keep = 0.0
    step = keep * C.strength_rate * ts / (weight * weight)
    grad[:] = 0.0
    if step > 0.0:  # grad_j = tau_j sum_l J_l[:, j] . (J_l J_l^T)^-1 fb (one solve a link: J_l J_l^T is symmetric)
        for lk in range(jac.shape[0]):
            if not W.flags[ACTIVE, lk]:
                continue
            for a in range(3):
                for b in range(3):
                    acc = 1e-4 if a == b else 0.0
                    for k in range(J):
                        acc += jac[lk, a, k] * jac[lk, b, k]
                    jjt[a, b] = acc
            _solve3(jjt, fb, pull, adj[0], adj[1], adj[2])
            for jj in range(J):
                grad[jj] += jac[lk, 0, jj] * pull[0] + jac[lk, 1, jj] * pull[1] + jac[lk, 2, jj] * pull[2]
    for jj in range(J):
        old = cs[off.strength + jj]
        new = old - step * grad[jj] * tau[jj]
        new += C.strength_leak * ts * (1.0 - new)
        out = tau[jj] / old
        if out >= sc.ctrl_high[jj] or out <= sc.ctrl_low[jj]:
            new = max(new, old)
        cs[off.strength + jj] = min(max(new, STRENGTH_RANGE[0]), STRENGTH_RANGE[1])


@_jit
def _write(off, sc, cs, f, W, out):
    """The tick's outputs (motor commands, the external wrench: f's tau and ext) to out, the next controller state
    to cs."""
    J, nu = sc.hand_qpos.shape[0], sc.nu
    tau, ext = f[3 * J:4 * J], f[4 * J:4 * J + 6]
    load, anchored = W.load, W.flags[ANCHORED]
    anchor, f_a, f_b = W.blocks[ANCHOR], W.blocks[F_A], W.blocks[F_B]
    for i in range(nu):
        out[i] = 0.0
    for jj in range(J):
        out[sc.hand_act[jj]] = tau[jj]
    for i in range(6):
        out[nu + i] = ext[i]
    for lk in range(load.shape[0]):
        cs[off.load + lk] = load[lk]
        cs[off.anchored + lk] = 1.0 if anchored[lk] else 0.0
        for i in range(3):
            cs[off.anchor + 3 * lk + i] = anchor[lk, i]
            cs[off.f_with + 3 * lk + i] = f_a[lk, i]
            cs[off.f_without + 3 * lk + i] = f_b[lk, i]


@_jit
def _same_bits(a, b):
    """Whether float arrays a and b (L, 3) hold the same numbers bit for bit (a NaN never matches)."""
    for lk in range(a.shape[0]):
        for i in range(3):
            x, y = a[lk, i], b[lk, i]
            if x != y or math.copysign(1.0, x) != math.copysign(1.0, y):
                return False
    return True


@_jit
def _solve3(m, v, x, c0, c1, c2):
    """x (3,) with m x = v, by the adjugate (`controller._solve3`); c0, c1, c2 (3,) scratch."""
    _cross(m[1], m[2], c0)
    _cross(m[2], m[0], c1)
    _cross(m[0], m[1], c2)
    det = m[0, 0] * c0[0] + m[0, 1] * c0[1] + m[0, 2] * c0[2]
    for i in range(3):
        x[i] = (c0[i] * v[0] + c1[i] * v[1] + c2[i] * v[2]) / det


@_jit
def tick_rows(j, rows, cs, obs, seen, episodes, K, out, S):
    """`Tick.__call__`: the JAX tick's work for the episodes `rows` (the status of tick j - 1 from obs, then tick j
    from what the controller observes, seen)."""
    nu = K.scene.nu
    for r in rows:
        ep = _row(episodes, r)
        _status(K, j - 1, obs[r], ep, out[r, nu + 6:], S)
        _control(K, j, cs[r], seen[r], ep, out[r], S)


@_jit
def status_rows(j, rows, obs, episodes, K, out, S):
    """`Physics.check` after tick j of the episodes `rows`: out (E, 3) [angle, position error, fell]."""
    for r in rows:
        _status(K, j, obs[r], _row(episodes, r), out[r], S)


# ------------------------------------------------------------------------------------------ the engine
class Models(NamedTuple):
    """The C models of E episodes as native code steps them (`Engine`)."""

    addresses: np.ndarray  # (E, 8) uint64: `addresses`
    pedestals: np.ndarray  # (E, P, 3) float64: the pedestals' positions at drop 0
    geoms: np.ndarray  # (P,) int64: the pedestals' geoms
    delay: np.ndarray  # (E,) int64: control ticks a motor command waits before it acts (the world's; 0: none)
    pending: np.ndarray  # (E, D, nu) float64: the commands issued, a ring of D > max(delay) ticks (zeros at first;
    # written for every row, a delay or not)
    noise: np.ndarray  # (E, 3) float32: the world's observation noise stds (`world.World.noise`; zeros: none)
    key: np.ndarray  # (E, 2) uint32: each episode's noise key
    seen: np.ndarray  # (E, nq + 2 nv) float32: what the controller observes after the last step (the observation
    # with `world.seen`'s noise; without noise in any row, the observation array itself)
    noisy: np.ndarray  # (E,) bool: seen[r] is written after each step (every row, where `seen` is a copy)


class Trace(NamedTuple):
    """What a run records of its E episodes, K control ticks (`segment` writes it)."""

    fell: np.ndarray  # (E,) bool
    fall_tick: np.ndarray  # (E,) int32: the tick of the first fall, -1 if none
    angle: np.ndarray  # (E, K) float32 [deg] after each tick
    perr: np.ndarray  # (E, K) float32 [m]
    qpos: np.ndarray  # (E, K, nq) float32


@_jit
def _step_row(K, models, r, out, drop, obs, buf, j):
    """Episode r's pedestals `drop` metres down, motor commands out[:nu] (issued at tick j; they act `delay[r]`
    ticks later, zero torque before the first arrives) and external wrench out[nu:nu + 6] in, one `mj_step`, its
    observation row obs[r] (qpos, qvel, qfrc_bias; float32) read back. buf: float64 scratch."""
    nq, nv, nu = K.scene.nq, K.scene.nv, K.scene.nu
    addr, pedestals, geoms = models.addresses, models.pedestals, models.geoms
    place = buf.ctypes.data
    for g in range(geoms.shape[0]):
        buf[0], buf[1], buf[2] = pedestals[r, g, 0], pedestals[r, g, 1], pedestals[r, g, 2] + drop
        _mju_copy(addr[r, GEOM_POS] + np.uint64(24 * geoms[g]), place, np.intc(3))
    d = models.delay[r]
    ring = models.pending.shape[1]
    for i in range(nu):  # every row keeps its last commands issued (a snapshot's, for a branch in another world)
        models.pending[r, j % ring, i] = out[i]
    if d > 0:  # the command of tick j - d acts now (a slot not yet written holds zeros)
        for i in range(nu):
            buf[i] = models.pending[r, (j - d) % ring, i]
    else:
        for i in range(nu):
            buf[i] = out[i]
    _mju_copy(addr[r, CTRL], place, np.intc(nu))
    for i in range(6):
        buf[i] = out[nu + i]
    _mju_copy(addr[r, XFRC_TOOL], place, np.intc(6))
    _mj_step(addr[r, MODEL], addr[r, DATA])
    _mju_copy(place, addr[r, QPOS], np.intc(nq))
    for i in range(nq):
        obs[r, i] = buf[i]
    _mju_copy(place, addr[r, QVEL], np.intc(nv))
    for i in range(nv):
        obs[r, nq + i] = buf[i]
    _mju_copy(place, addr[r, QFRC_BIAS], np.intc(nv))
    for i in range(nv):
        obs[r, nq + nv + i] = buf[i]
    if models.noisy[r]:
        _seen_row(K.scene, models, r, obs, j + 1)


_MASK = np.uint64(0xFFFFFFFF)
_MUL = (np.uint64(world_lib.HASH_MUL[0]), np.uint64(world_lib.HASH_MUL[1]))
_S8, _S15, _S16 = np.uint64(8), np.uint64(15), np.uint64(16)


@_jit
def _mix(x):
    """`world._mix` in uint64 arithmetic kept to 32 bits."""
    x = x ^ (x >> _S16)
    x = (x * _MUL[0]) & _MASK
    x = x ^ (x >> _S15)
    x = (x * _MUL[1]) & _MASK
    return x ^ (x >> _S16)


@_jit
def _unit_noise(k0, k1, j, component):
    """`world.unit_noise` of one component at tick j (k0, k1: the episode's key as uint64)."""
    base = (((np.uint64(j) * np.uint64(world_lib.COMPONENTS) + np.uint64(component)) & _MASK) * np.uint64(4)) & _MASK
    total = F32(0.0)
    for m in range(4):
        h = _mix(_mix(_mix((base + np.uint64(m)) & _MASK) ^ k0) ^ k1)
        total = F32(total + F32(h >> _S8) * F32(world_lib.UNIT))
    return F32(F32(total - F32(2.0)) * F32(world_lib.SQRT3))


@_jit
def _seen_row(sc, models, r, obs, j):
    """`world.seen` of episode r's observation obs[r] at control tick j into models.seen[r] (sc: `Scene`)."""
    seen, s = models.seen, models.noise[r]
    k0, k1 = np.uint64(models.key[r, 0]), np.uint64(models.key[r, 1])
    for i in range(obs.shape[1]):
        seen[r, i] = obs[r, i]
    a0 = sc.tool_qpos
    for i in range(3):
        seen[r, a0 + i] = F32(obs[r, a0 + i] + F32(s[0] * _unit_noise(k0, k1, j, i)))
    for i in range(sc.hand_qpos.shape[0]):
        c = sc.hand_qpos[i]
        seen[r, c] = F32(obs[r, c] + F32(s[2] * _unit_noise(k0, k1, j, 6 + i)))
    if s[1] != 0:  # the rotation vector r to first order: q + q (0, r) / 2, normalised
        qn = F32(0.0)
        for i in range(4):
            qn = F32(qn + F32(obs[r, a0 + 3 + i] * obs[r, a0 + 3 + i]))
        qn = F32(math.sqrt(qn))
        w, x = F32(obs[r, a0 + 3] / qn), F32(obs[r, a0 + 4] / qn)
        y, z = F32(obs[r, a0 + 5] / qn), F32(obs[r, a0 + 6] / qn)
        r0 = F32(s[1] * _unit_noise(k0, k1, j, 3))
        r1 = F32(s[1] * _unit_noise(k0, k1, j, 4))
        r2 = F32(s[1] * _unit_noise(k0, k1, j, 5))
        half = F32(0.5)
        q0 = F32(w + F32(half * F32(F32(F32(-x * r0) - F32(y * r1)) - F32(z * r2))))
        q1 = F32(x + F32(half * F32(F32(F32(w * r0) + F32(y * r2)) - F32(z * r1))))
        q2 = F32(y + F32(half * F32(F32(F32(w * r1) + F32(z * r0)) - F32(x * r2))))
        q3 = F32(z + F32(half * F32(F32(F32(w * r2) + F32(x * r1)) - F32(y * r0))))
        n = F32(math.sqrt(F32(F32(F32(q0 * q0) + F32(q1 * q1)) + F32(F32(q2 * q2) + F32(q3 * q3)))))
        seen[r, a0 + 3], seen[r, a0 + 4] = F32(q0 / n), F32(q1 / n)
        seen[r, a0 + 5], seen[r, a0 + 6] = F32(q2 / n), F32(q3 / n)


@_jit
def seen_rows(K, models, rows, obs, j):
    """`_seen_row` of the episodes `rows` at control tick j (a run's first observation, or a restored one)."""
    for r in rows:
        if models.noisy[r]:
            _seen_row(K.scene, models, r, obs, j)


@_jit
def step_rows(K, models, rows, out, drop, obs, buf, j):
    """Episodes `rows` one physics step each under their rows of out (E, nu + 6 + ...) issued at tick j
    (`_step_row`)."""
    for r in rows:
        _step_row(K, models, r, out[r], drop, obs, buf, j)


@_jit
def segment(K, j0, drops, rows, cs, obs, episodes, models, trace, out, S):
    """Control ticks j0 .. j0 + len(drops) - 1 of the episodes `rows`, each tick: the status of the tick before
    recorded in `trace` (`Trace`: angle, perr, qpos at tick j - 1; fell, fall_tick at the first fall), then, for
    an episode that has not fallen, the controller's tick j and one physics step of its model (`Models`) with the
    pedestals drops[j - j0] metres down. The C backend's segment between two decisions, in one call without
    Python. S: the thread's `Scratch`. Returns the physics steps taken."""
    nq, nu = K.scene.nq, K.scene.nu
    fell, fall_tick = trace.fell, trace.fall_tick
    steps = 0
    for r in rows:  # a row's ticks one after another (its model and data stay in the cache): rows are independent
        ep = _row(episodes, r)
        for i in range(drops.shape[0]):
            j = j0 + i
            if j > 0:
                st = out[r, nu + 6:]
                _status(K, j - 1, obs[r], ep, st, S)
                if st[2] > 0.5 and not fell[r]:
                    fell[r], fall_tick[r] = True, j - 1
                trace.angle[r, j - 1], trace.perr[r, j - 1] = st[0], st[1]
                for c in range(nq):
                    trace.qpos[r, j - 1, c] = obs[r, c]
            if fell[r]:
                continue
            _control(K, j, cs[r], models.seen[r], ep, out[r], S)
            _step_row(K, models, r, out[r], drops[i], obs, S.buf, j)
            steps += 1
    return steps


# ------------------------------------------------------------------------------------------ a decision
def keep_grasp(K: Constants, rows, cs: np.ndarray, start: np.float32) -> None:
    """`Controller.begin_segment` for the episodes `rows` whose reference grasp stays the same at a segment that
    starts at `start` [s] (float32): no link moves, so only the timeline's fields change (previous options = the
    current ones, nothing changed, the segment's start). cs (E, C) float32 flat controller states, updated in
    place. Must equal `Controller.begin_segment` there (its reference), bit for bit; checked by
    `tests/test_physics.py::test_c_lockstep_decides_table_policies_in_numpy_as_jax_does`."""
    L, off = K.hand.link_body.shape[0], K.state
    cs[rows, off.previous:off.previous + L] = cs[rows, off.options:off.options + L]
    cs[rows, off.changed:off.changed + L] = 0.0
    cs[rows, off.start] = start
