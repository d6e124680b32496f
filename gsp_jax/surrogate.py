"""The surrogate environment: a pure-JAX model of one grasp-sequence decision step.

    state = env.reset(episode)                      # grasp realised at waypoint 0
    state, reward, done = env.step(state, action)   # jit- and vmap-able over states, actions, episodes

A step at waypoint t applies the action to the grasp g (action 0, the null action, keeps it; every other action
sets one contact link to one option), then scores the new grasp g' with the paper's shaped reward (Sec. IV-B):

  (a) wrench_move  wrench error against gravity and the desired tool acceleration, g' realised by IK at the
                   *current* (observed) tool pose,
  (b) ik_next      IK error of g' realised at the *next* desired pose (waypoint t+1),
  (c) wrench_hold  wrench error against gravity with the contacts of that second IK,
  (d) wrench_ext   at the last step only: wrench error against gravity plus the external wrench w_ext,
  (e) redundant    1 if a non-null action left the grasp unchanged (the null action is free),
  (f) wrench_change when the grasp changes: wrench error of the *shared* grasp (g without the link that moves,
                   `GraspSpace.shared`; the contact controller unloads that link, moves it and loads it again)
                   realised at the current pose, against the same moving wrench as (a): the links that stay
                   must carry the tool through the change. 0 for the null action, and 0 at waypoint 0, where
                   the tool still rests on its start support (`supported_steps`).

reward = -(weighted sum), or R_MIN when either IK collides (tool, table, self) or any wrench term leaves more
than `fall_unmet` of its wrench unmet (the tool would fall; (f) counts when `change_falls`), or at the last step
the forces the hand's motors can give leave more than `motor_fall_unmet` of (d) unmet (no grasp holds a wrench
beyond its actuators: `motor_unmet`); R_MIN ends the episode. The wrench solves use `friction_scale` times the tool's friction coefficient (a margin: the physics'
contact controller plans its forces inside 0.7 mu). Every IK starts from the
model's fixed start configuration, so the next joint state is the IK result at the next desired pose (the
paper's transition). Rotational inertia is not modelled here (the paper's trajectories are pure
translations): the contacts must supply m (a - g) and zero torque about the CoM while moving; the MJX physics
check carries the full rigid-body dynamics.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax import grasps, ik, ik_lanes, kinematics, wrench
from gsp_jax import hand as hand_lib, model as model_lib
from gsp_jax.calibration import CALIBRATED
from gsp_jax.scenario import M0, Episode, unstack, validate



@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """Weights and thresholds of the shaped reward (one place for each)."""

    w_wrench_move: float = 1.0  # (a)
    w_ik: float = 1.0  # (b), per `ik_scale` of IK error
    w_wrench_hold: float = 1.0  # (c)
    w_wrench_ext: float = 1.0  # (d)
    w_redundant: float = 0.05  # (e)
    w_wrench_change: float = CALIBRATED["w_wrench_change"]  # (f)
    change_falls: bool = CALIBRATED["change_falls"]  # (f) leaving more than fall_unmet unmet drops the tool (R_MIN)
    supported_steps: int = 1  # (f) is 0 for decisions at waypoints t < this: the tool still rests on its start
    # support (the physics' pedestals stay for the first segment), so no shared grasp has to carry it through a change
    friction_scale: float = CALIBRATED["friction_scale"]  # the wrench solves' friction coefficient, times the tool's
    grip: float = CALIBRATED["grip"]  # [N] every realised contact presses with at least this (`wrench.solve`) ...
    grip_scales_with_mass: bool = CALIBRATED["grip_scales_with_mass"]  # ... times m / m0 (`grip_of`): the wrench
    # problem then stays positively homogeneous in the mass, so a lighter tool is never harder to hold
    squeeze: float = CALIBRATED["squeeze"]  # [N] a soft grip, as the physics' controller squeezes: every
    # realised contact's preferred force is this along its normal (`wrench.solve(prefer=...)`), and the error
    # prices the forces' distance from it instead of their size
    motors: bool = CALIBRATED["motors"]  # price the hand's motors: the solved forces as motors of the
    # model's torque limits deliver them (`wrench.saturate`: a link whose joints would saturate pushes
    # proportionally less), so a grasp whose forces the motors cannot give leaves its wrench unmet
    ik_scale: float = 0.01  # [m]: an IK error of 1 cm costs w_ik
    wrench_scale: float = (M0 * 9.81) ** 2  # [N^2]: wrench errors are divided by (m0 g)^2
    contact_tol: float = 0.005  # [m]: a link within this of its contact point carries force
    fall_unmet: float = CALIBRATED["fall_unmet"]  # unmet fraction of a required wrench above which the tool falls
    motor_fall_unmet: float = 0.3  # ... and of the final wrench (d) under the hand's motors (`RewardTerms.motor_unmet`),
    # above which the tool falls: a weight plus external wrench beyond the actuators is a fall, as in physics (inf: off)
    motor_iterations: int = 150  # iterations of that motor-limited solve (`wrench.solve(method="apg", motors=...)`):
    # fewer leave it unconverged and call holdable grasps falls
    max_step_cost: float = 10.0  # cap on a non-failing step's cost ...
    r_min: float = -200.0  # ... so that failing costs more than any T non-failing steps: r_min < -max_step_cost * T

    def __post_init__(self):
        for name in ("w_wrench_move", "w_ik", "w_wrench_hold", "w_wrench_ext", "w_redundant", "w_wrench_change"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"RewardConfig.{name}: a weight must be >= 0, got {getattr(self, name)}")
        for name in ("ik_scale", "wrench_scale", "contact_tol", "friction_scale", "fall_unmet", "motor_fall_unmet",
                     "max_step_cost"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RewardConfig.{name}: must be > 0, got {getattr(self, name)}")
        if not self.grip >= 0:
            raise ValueError(f"RewardConfig.grip: must be >= 0 [N], got {self.grip}")
        if not self.squeeze >= 0:
            raise ValueError(f"RewardConfig.squeeze: must be >= 0 [N], got {self.squeeze}")
        if not isinstance(self.motors, bool):
            raise ValueError(f"RewardConfig.motors: must be a bool, got {self.motors!r}")
        if not isinstance(self.grip_scales_with_mass, bool):
            raise ValueError(f"RewardConfig.grip_scales_with_mass: must be a bool, got {self.grip_scales_with_mass!r}")
        if not (isinstance(self.motor_iterations, int) and self.motor_iterations >= 1):
            raise ValueError(f"RewardConfig.motor_iterations: must be an int >= 1, got {self.motor_iterations!r}")
        if not (isinstance(self.supported_steps, int) and self.supported_steps >= 0):
            raise ValueError(f"RewardConfig.supported_steps: must be an int >= 0, got {self.supported_steps!r}")
        if not self.r_min < -self.max_step_cost:
            raise ValueError(f"RewardConfig.r_min: must be < -max_step_cost = {-self.max_step_cost}, got {self.r_min}")

    @property
    def max_waypoints(self) -> int:
        """The most waypoints T an episode may have: failing (r_min) costs more than any T held steps."""
        return int(np.ceil(-self.r_min / self.max_step_cost)) - 1


@struct.dataclass
class RewardTerms:
    """The reward of one step, term by term (unweighted, normalised as in `RewardConfig`)."""

    wrench_move: jax.Array  # () (a) / wrench_scale
    ik_next: jax.Array  # () (b) / ik_scale
    wrench_hold: jax.Array  # () (c) / wrench_scale
    wrench_ext: jax.Array  # () (d) / wrench_scale; 0 before the last step
    redundant: jax.Array  # () (e) 0 or 1
    wrench_change: jax.Array  # () (f) / wrench_scale; 0 when the grasp does not change
    unmet: jax.Array  # (4,) unmet wrench fractions of (a), (c), (d), (f)
    motor_unmet: jax.Array  # () unmet fraction of (d) (0 before the last step) with forces within the motors' torque
    # limits: solved with the limits, then each contact scaled down where its joints' limits still bind
    collision: jax.Array  # () bool
    fall: jax.Array  # () bool
    reward: jax.Array  # () the step's reward
    invalid: jax.Array  # () bool, the episode's inputs are out of range (`episode_ok`): reward r_min, done

    @classmethod
    def zeros(cls) -> "RewardTerms":
        z = jnp.zeros((), jnp.float32)
        f = jnp.array(False)
        return cls(z, z, z, z, z, z, jnp.zeros(4, jnp.float32), z, f, f, z, f)


@struct.dataclass
class State:
    """Continuous surrogate state plus the episode input. Shapes for one state (vmap adds axes)."""

    grasp: jax.Array  # () int32, the reference grasp in force
    t: jax.Array  # () int32, index of the current waypoint (T when the episode is over)
    q: jax.Array  # (J,) hand joint angles [rad]
    tool_pos: jax.Array  # (3,) observed tool position [m]
    tool_quat: jax.Array  # (4,) observed tool orientation (w, x, y, z)
    tool_vel: jax.Array  # (6,) observed tool linear [m/s] and angular [rad/s] velocity
    episode: Episode
    done: jax.Array  # () bool
    terms: RewardTerms  # terms of the step that led here (zeros after reset)


@struct.dataclass
class Contacts:
    """A grasp realised by IK at a tool pose."""

    ik: ik.IKResult
    points: jax.Array  # (L, 3) contact points on the tool, world [m]
    normals: jax.Array  # (L, 3) inward normals, world
    realised: jax.Array  # (L,) bool, active and within contact_tol: these links carry force


@jax.tree_util.register_static
class Surrogate:
    """The surrogate model of a hand + tool scene. Stateless: all methods are pure functions of their inputs.
    A static pytree (no leaves), so a policy that holds one (`lookahead.Lookahead`) passes through `jit`. Two
    surrogates of the same hand object and configs are equal (and hash alike), so a program traced for one is
    reused for the other: `jax.jit`'s cache holds one program per (model, shapes, options) in a process."""

    def __init__(
        self,
        hand=None,
        reward: RewardConfig = RewardConfig(),
        ik_config: ik.IKConfig = ik.IKConfig(),
        wrench_config: wrench.WrenchConfig = wrench.WrenchConfig(),
    ):
        """`hand`: the model, as a shipped name, a scene path, a `gsp_jax.model.Model` or a loaded `HandModel`
        (None: the shipped wrench, `gsp_jax.model.DEFAULT`)."""
        self.hand = hand if isinstance(hand, hand_lib.HandModel) else model_lib.load_model(hand).hand
        self.space = grasps.space_of(self.hand)
        self.reward_config, self.ik_config, self.wrench_config = reward, ik_config, wrench_config
        self.gravity = jnp.asarray(self.hand.gravity, jnp.float32)
        self.torque_limit = jnp.asarray(self.hand.joint_torque_limit, jnp.float32)  # (J,)
        self.link_joints = jnp.asarray(self.hand.joint_moves_body[self.hand.link_body] > 0)  # (L, J)

    def _key(self):
        return id(self.hand), self.reward_config, self.ik_config, self.wrench_config

    def __eq__(self, other) -> bool:
        return isinstance(other, Surrogate) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    @property
    def n_actions(self) -> int:
        return self.space.n_actions

    @property
    def model(self) -> model_lib.Model:
        """The `Model` (scene file, digest) the hand was loaded from; ModelError for a hand built otherwise."""
        return model_lib.of_hand(self.hand)

    @property
    def prices_changes(self) -> bool:
        """Whether the change term (f) enters the reward at all (a weight or its fall check)."""
        return self.reward_config.w_wrench_change != 0 or self.reward_config.change_falls

    # ------------------------------------------------------------------------------------------- kernels
    @jax.jit
    def realise(self, grasp: jax.Array, tool_pos: jax.Array, tool_quat: jax.Array) -> Contacts:
        """IK of `grasp` (int) at a tool pose (3,), (4,)."""
        mat = kinematics.quat_to_mat(tool_quat)
        active, points, normals = ik.grasp_targets(self.hand, self.space.decode(grasp), tool_pos, mat)
        res = ik.solve(self.hand, active, points, tool_pos, mat, self.ik_config)
        realised = active & (res.link_error < self.reward_config.contact_tol)
        return Contacts(ik=res, points=points, normals=normals, realised=realised)

    def realise_batch(self, grasp: jax.Array, tool_pos: jax.Array, tool_quat: jax.Array) -> Contacts:
        """`realise` of a whole batch at once in the batch-last form (`ik_lanes`: a CPU runs it several times
        faster than `realise` vmapped): grasps (...), tool poses (..., 3), (..., 4) -> `Contacts` (...)."""
        mat = kinematics.quat_to_mat(tool_quat)
        active, points, normals = jax.vmap(lambda g, p, m: ik.grasp_targets(self.hand, self.space.decode(g), p, m))(
            grasp.reshape(-1), tool_pos.reshape(-1, 3), mat.reshape(-1, 3, 3))
        res = ik_lanes.solve(self.hand, active, points, tool_pos.reshape(-1, 3), mat.reshape(-1, 3, 3), self.ik_config)
        realised = active & (res.link_error < self.reward_config.contact_tol)
        out = Contacts(ik=res, points=points, normals=normals, realised=realised)
        return jax.tree.map(lambda x: x.reshape(grasp.shape + x.shape[1:]), out)

    def wrench_error(
        self, contacts: Contacts, episode: Episode, tool_pos, tool_quat, required: jax.Array
    ) -> wrench.WrenchResult:
        """Wrench solve for `required` (6,) = (force, torque about the CoM) that the contacts must supply."""
        cfg = self.reward_config
        com = tool_pos + kinematics.quat_to_mat(tool_quat) @ episode.com
        mu = episode.friction * cfg.friction_scale
        grip = self.grip_of(episode)
        prefer = None if cfg.squeeze == 0 else cfg.squeeze * contacts.normals
        res = wrench.solve(contacts.points, contacts.normals, contacts.realised, mu, required, com, self.wrench_config,
                           prefer=prefer, grip=grip)
        if cfg.squeeze == 0 and not cfg.motors:
            return res
        forces = res.forces
        if cfg.motors:
            _, jac = kinematics.closest_on_links_and_jacobians(self.hand, contacts.ik.q, contacts.points)
            forces = wrench.saturate(forces, jac, self.torque_limit, self.link_joints)
        reference = (grip + cfg.squeeze) * contacts.normals  # the forces the solve pulls towards
        return wrench.assess(forces, contacts.points, contacts.realised, required, com, self.wrench_config, reference)

    def grip_of(self, episode: Episode) -> jax.Array:
        """() [N] the grip of `episode`'s wrench solves: `RewardConfig.grip`, times m / m0 if it scales with mass."""
        cfg = self.reward_config
        scale = episode.mass / self.hand.tool_mass if cfg.grip_scales_with_mass else jnp.ones((), jnp.float32)
        return jnp.asarray(cfg.grip, jnp.float32) * scale

    def score(
        self, episode: Episode, t: jax.Array, tool_pos, tool_quat, now: Contacts, nxt: Contacts, redundant,
        during: Contacts | None = None, changed=False,
    ) -> RewardTerms:
        """Reward terms of moving, with new grasp contacts `now` (at the current pose) and `nxt` (at waypoint
        t+1), from waypoint t. The previous grasp enters through `redundant`, `changed` (the grasp changes) and
        `during` (the shared grasp's contacts at the current pose; None: no change term)."""
        cfg = self.reward_config
        wp, m = episode.waypoints, episode.mass
        last = episode.n_steps - 1
        t_next = jnp.minimum(t + 1, last)
        zero3 = jnp.zeros(3, jnp.float32)
        move_wrench = self.move_wrench(episode, t)
        pos_n, quat_n = wp[t_next], episode.quats[t_next]
        hold_wrench = jnp.concatenate([-m * self.gravity, zero3])
        # the three (four) wrench solves are independent: one vmapped solve runs them in lock step (the step's
        # depth is one solve's iterations, not three)
        problems = [(now, tool_pos, tool_quat, move_wrench), (nxt, pos_n, quat_n, hold_wrench),
                    (nxt, pos_n, quat_n, hold_wrench - episode.w_ext)]
        if during is not None:
            problems.append((during, tool_pos, tool_quat, move_wrench))
        stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *problems)
        solved = jax.vmap(lambda c, p, q, w: self.wrench_error(c, episode, p, q, w))(*stacked)
        move, hold, ext = (jax.tree.map(lambda x, i=i: x[i], solved) for i in range(3))
        is_last = t >= last
        if np.isfinite(cfg.motor_fall_unmet):
            motor_unmet = self.motor_unmet(nxt, episode, pos_n, quat_n, ext.forces, hold_wrench - episode.w_ext)
            motor_unmet = jnp.where(is_last, motor_unmet, 0.0)
        else:
            motor_unmet = jnp.zeros((), jnp.float32)
        if during is None:
            change_error = change_unmet = jnp.zeros((), jnp.float32)
        else:
            change_error, change_unmet = solved.error[3] / cfg.wrench_scale, solved.unmet[3]
        terms = RewardTerms(
            wrench_move=move.error / cfg.wrench_scale,
            ik_next=nxt.ik.error / cfg.ik_scale,
            wrench_hold=hold.error / cfg.wrench_scale,
            wrench_ext=jnp.where(is_last, ext.error / cfg.wrench_scale, 0.0),
            redundant=jnp.zeros((), jnp.float32),
            wrench_change=jnp.zeros((), jnp.float32),
            unmet=jnp.stack([move.unmet, hold.unmet, jnp.where(is_last, ext.unmet, 0.0), jnp.zeros(())]),
            motor_unmet=motor_unmet,
            collision=now.ik.collision | nxt.ik.collision,
            fall=jnp.array(False),
            reward=jnp.zeros(()),
            invalid=jnp.array(False),
        )
        return self.finish(terms, redundant, changed, change_error, change_unmet, t)

    def finish(self, terms: RewardTerms, redundant, changed, change_error, change_unmet, t) -> RewardTerms:
        """`terms` with the previous grasp's part set -- the redundant flag, and when `changed` at a waypoint `t`
        past the start support (`supported_steps`) the change term (f) (normalised error, unmet fraction) -- and
        the fall flag and reward recomputed. Broadcasts."""
        cfg = self.reward_config
        changed = jnp.asarray(changed, bool) & (jnp.asarray(t) >= cfg.supported_steps)
        shape = terms.wrench_move.shape
        change_error = jnp.broadcast_to(jnp.where(changed, change_error, 0.0), shape)
        change_unmet = jnp.broadcast_to(jnp.where(changed, change_unmet, 0.0), shape)
        unmet = jnp.concatenate([terms.unmet[..., :3], change_unmet[..., None]], axis=-1)
        counted = unmet if cfg.change_falls else unmet[..., :3]
        terms = terms.replace(
            redundant=jnp.broadcast_to(jnp.asarray(redundant, jnp.float32), shape),
            wrench_change=change_error,
            unmet=unmet,
            fall=jnp.any(counted > cfg.fall_unmet, axis=-1) | (terms.motor_unmet > cfg.motor_fall_unmet),
        )
        return terms.replace(reward=self.reward(terms))

    def motor_unmet(self, contacts: Contacts, episode: Episode, tool_pos, tool_quat, init, required) -> jax.Array:
        """() unmet fraction of a wrench `required` (6,) with forces the hand's motors can give at the contacts' IK
        configuration: the wrench solved with the joints' torque limits (`wrench.MotorLimits`, warm-started from
        `init` (L, 3), no grip floor), then each contact scaled down where its joints' limits still bind
        (`wrench.saturate`). Near 1 where no force the motors give supplies the wrench."""
        com = tool_pos + kinematics.quat_to_mat(tool_quat) @ episode.com
        _, jac = kinematics.closest_on_links_and_jacobians(self.hand, contacts.ik.q, contacts.points)
        motors = wrench.MotorLimits(jacobians=jac, offset=jnp.zeros_like(self.torque_limit), limit=self.torque_limit)
        cfg = dataclasses.replace(self.wrench_config, method="apg", iterations=self.reward_config.motor_iterations)
        mu = episode.friction * self.reward_config.friction_scale
        res = wrench.solve(contacts.points, contacts.normals, contacts.realised, mu, required, com, cfg, init=init,
                           motors=motors)
        delivered = wrench.saturate(res.forces, jac, self.torque_limit, self.link_joints)
        return wrench.assess(delivered, contacts.points, contacts.realised, required, com, self.wrench_config).unmet

    def move_wrench(self, episode: Episode, t: jax.Array) -> jax.Array:
        """(6,) wrench the contacts must supply while moving on from waypoint t: m (a - g), with the desired
        acceleration a from the waypoints' finite differences, and no torque about the CoM."""
        wp, last = episode.waypoints, episode.n_steps - 1
        acc = (wp[jnp.minimum(t + 1, last)] - 2 * wp[jnp.minimum(t, last)] + wp[jnp.maximum(t - 1, 0)]) / episode.dt**2
        return jnp.concatenate([episode.mass * (acc - self.gravity), jnp.zeros(3, jnp.float32)])

    def reward(self, terms: RewardTerms) -> jax.Array:
        """The shaped reward from a step's terms (`terms.fall` and `terms.collision` give R_MIN)."""
        cfg = self.reward_config
        cost = (
            cfg.w_wrench_move * terms.wrench_move
            + cfg.w_ik * terms.ik_next
            + cfg.w_wrench_hold * terms.wrench_hold
            + cfg.w_wrench_ext * terms.wrench_ext
            + cfg.w_redundant * terms.redundant
            + cfg.w_wrench_change * terms.wrench_change
        )
        return jnp.where(terms.collision | terms.fall, cfg.r_min, -jnp.minimum(cost, cfg.max_step_cost))

    # ----------------------------------------------------------------------------------------- env API
    def reset(self, episode: Episode) -> State:
        """The episode's start: its start grasp realised at waypoint 0, at rest. Called from Python with a concrete
        episode, it first checks it against the model (`scenario.validate`: an EpisodeError names the field and the
        value); traced (inside `jit` / `vmap`) it cannot raise. Compiled (once per model and episode shapes): it runs
        as one program, not op by op."""
        return self._reset(self.check(episode))

    def check(self, episodes: Episode, name: str = "episode") -> Episode:
        """`episodes` (one, or a stack with leading axis N) checked against this surrogate's model and reward
        (`scenario.validate`; an EpisodeError names the field, e.g. "episodes[3].mass"). Traced inputs (inside
        `jit` / `vmap`) pass unchecked: their steps flag themselves (`RewardTerms.invalid`)."""
        if isinstance(episodes.mass, jax.core.Tracer):
            return episodes
        kw = dict(hand=self.hand, max_waypoints=self.reward_config.max_waypoints)
        if np.ndim(episodes.mass) == 0:
            validate(episodes, name, **kw)
        else:
            for i, ep in enumerate(unstack(episodes)):
                validate(ep, f"{name}s[{i}]", **kw)
        return episodes

    @jax.jit
    def _reset(self, episode: Episode) -> State:
        return self.discrete_state(episode, episode.start_grasp, 0)

    @jax.jit
    def discrete_state(self, episode: Episode, grasp: jax.Array, t: jax.Array) -> State:
        """The DP state (grasp, t): the tool exactly on waypoint t, the grasp realised there by IK. Compiled, like
        `reset`."""
        t = jnp.asarray(t, jnp.int32)
        pos, quat = episode.waypoints[t], episode.quats[t]
        prev = episode.waypoints[jnp.maximum(t - 1, 0)]
        return State(
            grasp=jnp.asarray(grasp, jnp.int32),
            t=t,
            q=self.realise(grasp, pos, quat).ik.q,
            tool_pos=pos,
            tool_quat=quat,
            tool_vel=jnp.concatenate([(pos - prev) / episode.dt, jnp.zeros(3, jnp.float32)]),
            episode=episode,
            done=jnp.array(False),
            terms=RewardTerms.zeros(),
        )

    def step(self, state: State, action: jax.Array) -> tuple[State, jax.Array, jax.Array]:
        """One decision. A finished state is absorbing (reward 0, done). A concrete action outside
        [0, n_actions) raises ValueError; a traced one is clipped into range (`grasps`)."""
        self.space.check_actions(action)
        moved = self._move(state.episode, state.grasp, state.t, state.tool_pos, state.tool_quat, action)
        out = jax.tree.map(lambda old, new: jnp.where(state.done, old, new), state, moved)
        reward = jnp.where(state.done, 0.0, moved.terms.reward)
        return out, reward, out.done

    def explain(self, episode: Episode, actions) -> str | None:
        """Why a sequence fails in the surrogate, in words, or None if it does not: the first step (from the start
        grasp, actions (T,)) that collides or drops the tool, the term and how far off, e.g. "t=0: the hold at the
        next waypoint is 167% unmet (> 30%) with grasp T1 I1 . M1 . .". For a plan whose return is `r_min` or less
        (DP's optimum then says: no sequence holds)."""
        actions = np.asarray(actions, np.int32)
        self.space.check_actions(actions, "actions")
        states, terms = _replay(self, episode, jnp.asarray(actions))
        for t in range(min(len(actions), episode.n_steps)):
            if bool(terms.collision[t]) or bool(terms.fall[t]):
                grasp = self.space.label(int(self.space.transitions[int(states.grasp[t]), actions[t]]))
                if bool(terms.collision[t]):
                    return f"t={t}: the hand collides (with the tool, the table or itself) holding {grasp}"
                unmet, cfg = np.asarray(terms.unmet[t]), self.reward_config
                if float(terms.motor_unmet[t]) > cfg.motor_fall_unmet:
                    return (f"t={t}: {UNMET_TERMS[2]} is beyond the hand's motors: "
                            f"{100 * float(terms.motor_unmet[t]):.0f}% unmet with forces within their torque limits "
                            f"(> {100 * cfg.motor_fall_unmet:.0f}%) with grasp {grasp}")
                k = int(np.argmax(unmet - self.reward_config.fall_unmet > 0))
                return (f"t={t}: {UNMET_TERMS[k]} is {100 * unmet[k]:.0f}% unmet (> {100 * self.reward_config.fall_unmet:.0f}%)"
                        f" with grasp {grasp}")
        return None

    def transition(self, episode: Episode, grasp: jax.Array, t: jax.Array, action: jax.Array):
        """`step(discrete_state(episode, grasp, t), action)` without realising the state it starts from (a step reads
        only the state's grasp, waypoint and tool pose, not its joint angles): (next state, reward, done). `vmap` it
        over the steps of a sequence whose grasps are known in advance (`policies.rollout_batched`)."""
        self.space.check_actions(action)
        t = jnp.asarray(t, jnp.int32)
        moved = self._move(episode, jnp.asarray(grasp, jnp.int32), t, episode.waypoints[t], episode.quats[t], action)
        return moved, moved.terms.reward, moved.done

    @jax.jit
    def _move(self, ep: Episode, grasp, t, tool_pos, tool_quat, action) -> State:
        """The state after `action` from grasp `grasp` at waypoint `t` with the tool at (tool_pos, tool_quat)."""
        new_grasp, redundant = self.space.apply(grasp, action)
        t_next = jnp.minimum(t + 1, ep.n_steps - 1)
        pos_n, quat_n = ep.waypoints[t_next], ep.quats[t_next]
        # the two (three) IK solves are independent: one vmapped solve runs them in lock step
        grasp_in = [new_grasp, new_grasp] + ([self.space.shared(grasp, action)] if self.prices_changes else [])
        pos_in = [tool_pos, pos_n, tool_pos][: len(grasp_in)]
        quat_in = [tool_quat, quat_n, tool_quat][: len(grasp_in)]
        realised = jax.vmap(self.realise)(jnp.stack(grasp_in), jnp.stack(pos_in), jnp.stack(quat_in))
        now, nxt, *rest = (jax.tree.map(lambda x, i=i: x[i], realised) for i in range(len(grasp_in)))
        during = rest[0] if rest else None
        changed = new_grasp != grasp
        terms = self.score(ep, t, tool_pos, tool_quat, now, nxt, redundant, during, changed)
        invalid = ~episode_ok(ep, self.space.n_grasps)  # traced inputs cannot raise: r_min and a flag, never NaN
        terms = terms.replace(invalid=invalid, reward=jnp.where(invalid, self.reward_config.r_min, terms.reward))
        done = terms.collision | terms.fall | (t + 1 >= ep.n_steps) | invalid
        vel = jnp.concatenate([(pos_n - tool_pos) / ep.dt, jnp.zeros(3, jnp.float32)])
        return State(
            grasp=new_grasp,
            t=t + 1,
            q=nxt.ik.q,
            tool_pos=pos_n,
            tool_quat=quat_n,
            tool_vel=vel,
            episode=ep,
            done=done,
            terms=terms,
        )


def episode_ok(episode: Episode, n_grasps: int) -> jax.Array:
    """() bool, traceable: the episode's inputs are in range -- every field finite, dt, mass, inertia and friction
    positive, the start grasp a grasp of the model. `scenario.validate` checks the same and more from Python, naming
    the field; inside `jit` a step of an episode that fails this gives r_min, done and `RewardTerms.invalid`."""
    leaves = [episode.waypoints, episode.quats, episode.dt, episode.w_ext, episode.mass, episode.inertia, episode.com,
              episode.friction]
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
    positive = (episode.dt > 0) & (episode.mass > 0) & jnp.all(episode.inertia > 0) & (episode.friction > 0)
    return finite & positive & (episode.start_grasp >= 0) & (episode.start_grasp < n_grasps)


UNMET_TERMS = ("the wrench while moving (a)", "the hold at the next waypoint (c)",
               "the external wrench at the final pose (d)", "the shared grasp during the change (f)")


@jax.jit
def _replay(sur: Surrogate, episode: Episode, actions: jax.Array):
    """(the state each step starts from, its terms) along `actions` from the episode's start."""
    def step(state, a):
        nxt, _, _ = sur.step(state, a)
        return nxt, (state, nxt.terms)

    return jax.lax.scan(step, sur.reset(episode), actions)[1]
