"""The surrogate: a pure-JAX model of one grasp-sequence decision step.

    state = sur.reset(episode)                      # grasp realised at waypoint 0
    state, reward, done = sur.step(state, action)   # jit- and vmap-able over states, actions, episodes

A step at waypoint t applies the action to the grasp g (action 0, the null action, keeps it; every other action sets one
contact link to one option), realises the new grasp g' by IK at the current tool pose and at the next desired pose
(waypoint t+1), and, when the grasp changes, the shared grasp (g without the link that moves) at the current pose; it
solves the wrench problems of those contacts and scores them with the shaped reward of `gsp_jax.surrogate.reward` (its
terms (a)-(f), `RewardConfig`). A step that collides or drops the tool gets `r_min` and ends the episode. Every IK
starts from the model's fixed start configuration, so the next joint state is the IK result at the next desired pose
(the paper's transition). Rotational inertia is not modelled here (the paper's trajectories are pure translations): the
contacts must supply m (a - g) and zero torque about the CoM while moving; the MJX physics check carries the full
rigid-body dynamics.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.model import grasps, kinematics
from gsp_jax.solvers import ik, ik_lanes, wrench
from gsp_jax.core import platform
from gsp_jax.model import hand as hand_lib, load as model_lib
from gsp_jax.surrogate import learned as learned_lib, reward as reward_lib
from gsp_jax.surrogate.reward import RewardConfig, RewardTerms
from gsp_jax.model.scenario import Episode, unstack, validate


MOTOR_GPU_UNROLL = 10  # the motor check's solve: iterations per loop trip on a GPU (`WrenchConfig.unroll`; the same
# result), where each trip of XLA's loop costs a sync on the device; a CPU keeps `wrench_config.unroll`


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


@struct.dataclass
class MotorProblem:
    """The motor check's inputs of one step (`Surrogate.motor_check`): the new grasp's contacts at waypoint t+1 and
    the final wrench (d), whose solve's forces warm-start it."""

    contacts: Contacts
    tool_pos: jax.Array  # (3,) [m]
    tool_quat: jax.Array  # (4,)
    init: jax.Array  # (L, 3) [N] the forces of the wrench solve (d)
    required: jax.Array  # (6,) the wrench (d): gravity plus the external wrench


@jax.tree_util.register_static
class Surrogate:
    """The surrogate model of a hand + tool scene. Stateless: all methods are pure functions of their inputs.
    A static pytree (no leaves), so a policy that holds one (`lookahead.Lookahead`) passes through `jit`. Two
    surrogates of the same hand object and configs are equal (and hash alike), so a program traced for one is
    reused for the other: `jax.jit`'s cache holds one program per (model, shapes, options) in a process."""

    def __init__(
        self,
        hand=None,
        reward: RewardConfig | None = None,
        ik_config: ik.IKConfig = ik.IKConfig(),
        wrench_config: wrench.WrenchConfig = wrench.WrenchConfig(),
        learned=None,
    ):
        """`hand`: the model, as a shipped name, a scene path, a `gsp_jax.model.load.Model` or a loaded `HandModel`
        (None: the shipped wrench, `gsp_jax.model.load.DEFAULT`). `reward`: None, `RewardConfig()` (its calibrated
        defaults read when it is built). `learned`: the learned physics term
        (`gsp_jax.surrogate.reward.with_risk`): None (the default) the model's own weights where its scene has them
        (`learned.path_of`: the shipped wrench, hammer and Allegro do), else off; False off (the paper's surrogate);
        True the model's own weights (refused where there are none); a `learned.Fitted` or a weights file. Weights
        of another model are refused."""
        self.hand = hand if isinstance(hand, hand_lib.HandModel) else model_lib.load_model(hand).hand
        self.space = grasps.space_of(self.hand)
        reward = RewardConfig() if reward is None else reward
        self.reward_config, self.ik_config, self.wrench_config = reward, ik_config, wrench_config
        self.learned = learned_lib.resolve(learned, self.model)
        self.learned_tag = "" if self.learned is None else learned_lib.tag(self.learned)
        self.gravity = jnp.asarray(self.hand.gravity, jnp.float32)
        self.torque_limit = jnp.asarray(self.hand.joint_torque_limit, jnp.float32)  # (J,)
        self.link_joints = jnp.asarray(self.hand.joint_moves_body[self.hand.link_body] > 0)  # (L, J)

    def _key(self):
        return id(self.hand), self.reward_config, self.ik_config, self.wrench_config, self.learned_tag

    @functools.cached_property
    def analytic(self) -> "Surrogate":
        """This surrogate without the learned physics term (itself where it has none)."""
        return self if self.learned is None else self.replace(learned=False)

    def replace(self, **changes) -> "Surrogate":
        """This surrogate with some of `reward`, `ik_config`, `wrench_config`, `learned` (as `__init__` takes them)
        replaced; the rest, the learned term included, kept."""
        kept = dict(reward=self.reward_config, ik_config=self.ik_config, wrench_config=self.wrench_config,
                    learned=False if self.learned is None else self.learned)
        return Surrogate(self.hand, **(kept | changes))

    def links(self, grasp: jax.Array) -> jax.Array:
        """(...) int32: the links in contact in grasps (...) (option 0 is off)."""
        return jnp.sum(self.space.decode(grasp) > 0, -1)

    def with_learned(self, episode: Episode, t, new_grasp, changed, terms: RewardTerms) -> RewardTerms:
        """`terms` (analytic, leaves broadcasting with t, new_grasp, changed) with the learned physics term where the
        surrogate has one (`reward.with_risk`), else unchanged."""
        if self.learned is None:
            return terms
        x = learned_lib.inputs(learned_lib.transition_features(terms, t, changed, self.links(new_grasp),
                                                               learned_lib.episode_features(episode)),
                               new_grasp, self.space)
        return reward_lib.with_risk(self.reward_config, terms, learned_lib.hazard(self.learned, x))

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

    def realise_many(self, grasp: jax.Array, tool_pos: jax.Array, tool_quat: jax.Array,
                     lanes: bool | None = None) -> Contacts:
        """`realise` of a batch: grasps (...), tool poses (..., 3), (..., 4) -> `Contacts` (...). In the batch-last
        form (`realise_batch`) where `ik_config.lanes` says so (None: on a CPU), else `realise` vmapped; both agree
        to float32 rounding. `lanes` (not None) overrides `ik_config.lanes`."""
        lanes = self.ik_config.lanes if lanes is None else lanes

        def vmapped():
            realise = self.realise
            for _ in range(grasp.ndim):
                realise = jax.vmap(realise)
            return realise(grasp, tool_pos, tool_quat)

        batched = lambda: self.realise_batch(grasp, tool_pos, tool_quat)  # noqa: E731
        if lanes is not None:
            return (batched if lanes else vmapped)()
        return platform.by_platform(cpu=batched, default=vmapped)

    def wrench_error(
        self, contacts: Contacts, episode: Episode, tool_pos, tool_quat, required: jax.Array
    ) -> wrench.WrenchResult:
        """Wrench solve for `required` (6,) = (force, torque about the CoM) that the contacts must supply."""
        com = tool_pos + kinematics.quat_to_mat(tool_quat) @ episode.com
        return wrench.solve(contacts.points, contacts.normals, contacts.realised, episode.friction, required, com,
                            self.wrench_config, grip=self.grip_of(episode))

    def grip_of(self, episode: Episode) -> jax.Array:
        """() [N] the grip of `episode`'s wrench solves: `RewardConfig.grip`, times m / m0 if it scales with mass."""
        cfg = self.reward_config
        scale = episode.mass / self.hand.tool_mass if cfg.grip_scales_with_mass else jnp.ones((), jnp.float32)
        return jnp.asarray(cfg.grip, jnp.float32) * scale

    def score(
        self, episode: Episode, t: jax.Array, tool_pos, tool_quat, now: Contacts, nxt: Contacts, redundant,
        during: Contacts | None = None, changed=False,
    ) -> RewardTerms:
        """Reward terms of moving, with new grasp contacts `now` (at the current pose) and `nxt` (at waypoint t+1), from
        waypoint t: the wrench problems solved here, the terms assembled by `gsp_jax.surrogate.reward`. The previous
        grasp enters through `redundant`, `changed` (the grasp changes) and `during` (the shared grasp's contacts at the
        current pose; None: no change term). The motor check counts at the last step only (`reward.arrival`): under a
        `cond` (`_only_where`), so a step of one t solves it only there and a batch of steps only where one of its rows
        is a last step; a batch over t solves it for its last step's rows alone through `score_deferred` and
        `motor_check` (`arrival_terms`, `transitions`)."""
        terms, problem = self.score_deferred(episode, t, tool_pos, tool_quat, now, nxt, redundant, during, changed)
        if problem is None:
            return terms
        motor = _only_where(t >= episode.n_steps - 1, self.motor_check, episode, problem)
        return reward_lib.with_motor(self.reward_config, terms, motor)

    def score_deferred(
        self, episode: Episode, t: jax.Array, tool_pos, tool_quat, now: Contacts, nxt: Contacts, redundant,
        during: Contacts | None = None, changed=False,
    ) -> tuple[RewardTerms, MotorProblem | None]:
        """`score` without the motor check: (the terms with `motor_unmet` 0, the check's `MotorProblem`; None
        without the check, `motor_fall_unmet` inf). `reward.with_motor(cfg, terms, motor_check(episode, problem))`
        completes a last step's terms; every other step's are complete."""
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
        problem = None
        if np.isfinite(cfg.motor_fall_unmet):
            problem = MotorProblem(contacts=nxt, tool_pos=pos_n, tool_quat=quat_n, init=ext.forces,
                                   required=hold_wrench - episode.w_ext)
        if during is None:
            change_error = change_unmet = jnp.zeros((), jnp.float32)
        else:
            change_error, change_unmet = reward_lib.wrench_term(cfg, jax.tree.map(lambda x: x[3], solved))
        terms = reward_lib.arrival(cfg, move, hold, ext, nxt.ik.error, now.ik.collision | nxt.ik.collision,
                                   None, is_last)
        return reward_lib.with_previous(cfg, terms, redundant, changed, change_error, change_unmet, t), problem

    def with_last_motor(self, episode: Episode, terms: RewardTerms, problem: MotorProblem | None) -> RewardTerms:
        """The terms of an episode's T steps (leaves with a leading axis T, from `score_deferred`) with the motor
        check solved for the last step alone, 0 before it (`reward.with_motor`); unchanged without the check
        (`problem` None). `vmap` it over further leading axes (`arrival_terms`: the table's G' grasps)."""
        if problem is None:
            return terms
        motor = self.motor_check(episode, jax.tree.map(lambda x: x[-1], problem))
        n_t = terms.wrench_move.shape[0]
        return reward_lib.with_motor(self.reward_config, terms, jnp.zeros(n_t, motor.dtype).at[-1].set(motor))

    # ------------------------------------------------ every transition of an episode at once (the DP table's terms)
    def realise_every(self, episode: Episode) -> Contacts:
        """Every grasp realised by IK at every waypoint of `episode`: leaves (G, T, ...). All G x T solves as one
        batch: on a CPU in the batch-last form (`ik_lanes`, where `ik_config.lanes` allows), elsewhere `realise`
        vmapped (`realise_many`)."""
        shape = (self.space.n_grasps, episode.n_steps)
        grasps_in = jnp.broadcast_to(jnp.arange(self.space.n_grasps, dtype=jnp.int32)[:, None], shape)
        return self.realise_many(grasps_in, jnp.broadcast_to(episode.waypoints, shape + (3,)),
                                 jnp.broadcast_to(episode.quats, shape + (4,)))

    def arrival_terms(self, episode: Episode, contacts: Contacts | None = None) -> RewardTerms:
        """The reward terms (G', T) of arriving in grasp g' by a step from waypoint t, without the previous grasp's
        part (not redundant, no change): the null action's terms from (g', t) (`score`). `contacts`: every grasp
        realised at every waypoint (`realise_every`; None: realised here). The motor check, which counts at the last
        step only, is solved for the last waypoint's G' arrivals alone (`score_deferred`, `with_last_motor`)."""
        contacts = self.realise_every(episode) if contacts is None else contacts
        n_t = episode.n_steps
        ts = jnp.arange(n_t, dtype=jnp.int32)
        nxt = jax.tree.map(lambda x: x[:, jnp.minimum(ts + 1, n_t - 1)], contacts)

        def score(now, nx, t):
            return self.score_deferred(episode, t, episode.waypoints[t], episode.quats[t], now, nx, False)

        terms, problem = jax.vmap(jax.vmap(score, (0, 0, 0)), (0, 0, None))(contacts, nxt, ts)
        return jax.vmap(lambda tm, pb: self.with_last_motor(episode, tm, pb))(terms, problem)  # each grasp's T steps

    def every_transition(self, episode: Episode, arrived: RewardTerms) -> tuple[jax.Array, RewardTerms]:
        """(next grasp (G, A) int32, terms (G, A, T)) of every action a from every grasp g at every waypoint t, from
        the arrival terms of every grasp (`arrival_terms`): each transition reads its new grasp's terms, adds its
        redundant flag and its change term (the shared grasp's moving-wrench term: `reward.of_transitions`), then the
        learned term where the surrogate has one (`with_learned`): the terms `step` gives each (discrete) transition,
        with G x T IK solves in all."""
        n_g, n_t = self.space.n_grasps, episode.n_steps
        grasps_in = jnp.arange(n_g, dtype=jnp.int32)
        ts = jnp.arange(n_t, dtype=jnp.int32)
        actions = jnp.arange(self.space.n_actions, dtype=jnp.int32)
        next_grasp, is_redundant = self.space.apply(grasps_in[:, None], actions[None, :])  # (G, A)
        changed = next_grasp != grasps_in[:, None]  # (G, A)
        shared = self.space.shared(grasps_in[:, None], actions[None, :])  # (G, A)
        terms = reward_lib.of_transitions(self.reward_config, arrived, next_grasp, is_redundant, changed, shared, ts)
        return next_grasp, self.with_learned(episode, ts, next_grasp[..., None], changed[..., None], terms)

    def motor_check(self, episode: Episode, problem: MotorProblem) -> jax.Array:
        """() the motor check of a `MotorProblem` (`motor_unmet`); leaves with leading axes: `vmap` it."""
        return self.motor_unmet(problem.contacts, episode, problem.tool_pos, problem.tool_quat, problem.init,
                                problem.required)

    def motor_unmet(self, contacts: Contacts, episode: Episode, tool_pos, tool_quat, init, required) -> jax.Array:
        """() unmet fraction of a wrench `required` (6,) with forces the hand's motors can give at the contacts' IK
        configuration: the wrench solved with the joints' torque limits (`wrench.MotorLimits`, warm-started from
        `init` (L, 3), no grip floor), then each contact scaled down where its joints' limits still bind
        (`wrench.saturate`). Near 1 where no force the motors give supplies the wrench."""
        com = tool_pos + kinematics.quat_to_mat(tool_quat) @ episode.com
        _, jac = kinematics.closest_on_links_and_jacobians(self.hand, contacts.ik.q, contacts.points)
        motors = wrench.MotorLimits(jacobians=jac, offset=jnp.zeros_like(self.torque_limit), limit=self.torque_limit)
        unroll = platform.by_platform(cpu=lambda: self.wrench_config.unroll, default=lambda: MOTOR_GPU_UNROLL)
        cfg = dataclasses.replace(self.wrench_config, method="apg", iterations=self.reward_config.motor_iterations,
                                  unroll=unroll)
        res = wrench.solve(contacts.points, contacts.normals, contacts.realised, episode.friction, required, com, cfg,
                           init=init, motors=motors)
        delivered = wrench.saturate(res.forces, jac, self.torque_limit, self.link_joints)
        return wrench.assess(delivered, contacts.points, contacts.realised, required, com, self.wrench_config).unmet

    def move_wrench(self, episode: Episode, t: jax.Array) -> jax.Array:
        """(6,) wrench the contacts must supply while moving on from waypoint t: m (a - g), with the desired
        acceleration a from the waypoints' finite differences, and no torque about the CoM."""
        wp, last = episode.waypoints, episode.n_steps - 1
        acc = (wp[jnp.minimum(t + 1, last)] - 2 * wp[jnp.minimum(t, last)] + wp[jnp.maximum(t - 1, 0)]) / episode.dt**2
        return jnp.concatenate([episode.mass * (acc - self.gravity), jnp.zeros(3, jnp.float32)])

    # ------------------------------------------------------------------------------------ step interface
    def reset(self, episode: Episode) -> State:
        """The episode's start: its start grasp realised at waypoint 0, at rest. Called from Python with a concrete
        episode, it first checks it against the model (`scenario.validate`: an EpisodeError names the field and the
        value); traced (inside `jit` / `vmap`) it cannot raise. Compiled (once per model and episode shapes): it runs
        as one program, not op by op."""
        return self._reset(self.validate(episode))

    def validate(self, episodes: Episode, name: str = "episode") -> Episode:
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
        return _absorbing(state, self._move(state.episode, state.grasp, state.t, state.tool_pos, state.tool_quat,
                                            action))

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
                g = int(self.space.transitions[int(states.grasp[t]), actions[t]])
                step = jax.tree.map(lambda x, t=t: x[t], terms)
                why = reward_lib.explain_failure(self.reward_config, step, t, self.space.label(g))
                if bool(terms.collision[t]):
                    return why + self.where_collides(episode, g, t)
                return why + self.grip_note(episode, actions, g, t, step)
        return None

    def grip_note(self, episode: Episode, actions, grasp: int, t: int, terms: RewardTerms) -> str:
        """Where step t (new grasp `grasp`) falls only because every contact must press with at least the grip
        (`grip_of`): '; without the grip floor it holds: ...', naming the net force and torque the contacts' least
        forces leave and, for the contact that opposes the others, how far its option is from the line through their
        centroid along its normal (where it would balance them); '' otherwise (the motors, the learned term, or a
        fall without the grip too)."""
        cfg = self.reward_config
        unmet = np.asarray(terms.unmet)[:4 if cfg.change_falls else 3]
        if cfg.grip <= 0 or float(terms.motor_unmet) > cfg.motor_fall_unmet or not np.any(unmet > cfg.fall_unmet):
            return ""
        free = self.analytic.replace(reward=dataclasses.replace(cfg, grip=0.0))
        if bool(_replay(free, episode, jnp.asarray(actions, jnp.int32))[1].fall[t]):
            return ""
        k = min(t + 1, episode.n_steps - 1)
        c = self.realise(jnp.int32(grasp), episode.waypoints[k], episode.quats[k])
        on = np.flatnonzero(np.asarray(c.realised))
        p, n = np.asarray(c.points, np.float64)[on], np.asarray(c.normals, np.float64)[on]
        g = float(self.grip_of(episode))
        mat = np.asarray(kinematics.quat_to_mat(episode.quats[k]), np.float64)
        com = np.asarray(episode.waypoints[k], np.float64) + mat @ np.asarray(episode.com, np.float64)
        force, torque = g * n.sum(0), g * np.cross(p - com, n).sum(0)
        note = (f"; without the grip floor it holds: each contact must press with at least {g:.1f} N "
                f"(RewardConfig.grip), and these least forces alone leave {np.linalg.norm(force):.1f} N and "
                f"{np.linalg.norm(torque):.3f} N m about the centre of mass that the contacts cannot cancel")
        if len(on) >= 2:
            others = n.sum(0, keepdims=True) - n
            i = int(np.argmin(np.sum(n * others, -1)))  # the contact that opposes the rest most
            rest = np.delete(np.arange(len(on)), i)
            off = p[i] - p[rest].mean(0)
            miss = np.linalg.norm(off - (off @ n[i]) * n[i])
            note += (f"; {self.hand.link_names[on[i]]} opposes the others: its option is {miss * 1e3:.0f} mm from the "
                     "line through their centroid along its normal (an option on that line balances their least "
                     "forces)")
        return note

    def where_collides(self, episode: Episode, grasp: int, t: int) -> str:
        """What collides when `grasp` is realised at waypoints t and t + 1 (a step's two poses), as ': <body> into
        the tool 2.7 mm, ...' naming the bodies and depths (`ik.collisions`), or '' where neither pose collides."""
        found = []
        for k in dict.fromkeys((t, min(t + 1, episode.n_steps - 1))):
            pos, quat = episode.waypoints[k], episode.quats[k]
            q = self.realise(jnp.int32(grasp), pos, quat).ik.q
            hits = ik.collisions(self.hand, q, pos, kinematics.quat_to_mat(quat), self.ik_config.collision_tol)
            found += [f"{text} at waypoint {k}" for text in hits]
        return (": " + "; ".join(found)) if found else ""

    def transition(self, episode: Episode, grasp: jax.Array, t: jax.Array, action: jax.Array):
        """`step(discrete_state(episode, grasp, t), action)` without realising the state it starts from (a step reads
        only the state's grasp, waypoint and tool pose, not its joint angles): (next state, reward, done). `vmap` it
        over the steps of a sequence whose grasps are known in advance (`policies.rollout_batched`)."""
        self.space.check_actions(action)
        t = jnp.asarray(t, jnp.int32)
        moved = self._move(episode, jnp.asarray(grasp, jnp.int32), t, episode.waypoints[t], episode.quats[t], action)
        return moved, moved.terms.reward, moved.done

    def step_every(self, state: State) -> tuple[State, jax.Array, jax.Array]:
        """`step(state, a)` for every action a at once: (next states, rewards, done), each with a leading axis A.
        The same terms, with each distinct grasp realised once: from one grasp the actions reach few distinct
        grasps (a redundant action keeps the grasp, a shared grasp is often another action's new grasp), so this
        solves at most `every_sizes` IK problems (11 + 11 for the shipped hand) where A vmapped steps solve 3 A
        (the lookahead's root expansion: `lookahead.search`)."""
        return _absorbing(state, self._move_every(state.episode, state.grasp, state.t, state.tool_pos,
                                                  state.tool_quat))

    @functools.cached_property
    def every_sizes(self) -> tuple[int, int]:
        """(most distinct grasps realised at the current pose, at the next waypoint) by `step_every` from any grasp:
        the new grasps and shared grasps of every action, and the new grasps (static, from the grasp space)."""
        new = self.space.transitions
        keys = np.concatenate([new, self.space.shared_grasps], 1) if self.reward_config.prices_changes else new
        distinct = lambda x: max(len(np.unique(row)) for row in x)  # noqa: E731
        return distinct(keys), distinct(new)

    @jax.jit
    def _move_every(self, ep: Episode, grasp, t, tool_pos, tool_quat) -> State:
        """`_move` of every action (leading axis A), each distinct grasp realised once at each pose."""
        actions = jnp.arange(self.space.n_actions, dtype=jnp.int32)
        new_grasp, redundant = self.space.apply(grasp, actions)
        t_next = jnp.minimum(t + 1, ep.n_steps - 1)
        pos_n, quat_n = ep.waypoints[t_next], ep.quats[t_next]
        shared = self.space.shared(grasp, actions) if self.reward_config.prices_changes else None
        n_now, n_next = self.every_sizes
        now_keys = new_grasp if shared is None else jnp.concatenate([new_grasp, shared])
        now_grasps, now_of = jnp.unique(now_keys, size=n_now, fill_value=grasp, return_inverse=True)
        next_grasps, next_of = jnp.unique(new_grasp, size=n_next, fill_value=grasp, return_inverse=True)
        # every distinct (grasp, pose) pair in one batch of IK solves (the batch-last form only where
        # `ik_config.lanes` is True: its compile costs more than it saves on a few dozen problems)
        pos = jnp.concatenate([jnp.broadcast_to(tool_pos, (n_now, 3)), jnp.broadcast_to(pos_n, (n_next, 3))])
        quat = jnp.concatenate([jnp.broadcast_to(tool_quat, (n_now, 4)), jnp.broadcast_to(quat_n, (n_next, 4))])
        grasps_in = jnp.concatenate([now_grasps, next_grasps])
        realised = self.realise_many(grasps_in, pos, quat, lanes=self.ik_config.lanes is True)
        at_now, at_next = now_of.reshape(-1), n_now + next_of.reshape(-1)
        now = jax.tree.map(lambda x: x[at_now[:len(actions)]], realised)
        nxt = jax.tree.map(lambda x: x[at_next], realised)
        during = None if shared is None else jax.tree.map(lambda x: x[at_now[len(actions):]], realised)
        return jax.vmap(self._arrive, (None, None, None, None, None, 0, 0, 0, 0, 0 if during is not None else None))(
            ep, grasp, t, tool_pos, tool_quat, new_grasp, redundant, now, nxt, during)

    @jax.jit
    def transitions(self, episode: Episode, grasps: jax.Array, actions: jax.Array
                    ) -> tuple[State, jax.Array, jax.Array]:
        """`transition` of every step of one episode at once, vmapped: grasps (T,) and actions (T,) at waypoints 0 ..
        T - 1 -> (next states, rewards, done), each with a leading axis T. The motor check (the last step's only) is
        solved for the last row alone, not for every row as a vmapped `transition` does (`score`)."""
        n_t = episode.n_steps
        ts = jnp.arange(n_t, dtype=jnp.int32)

        def deferred(grasp, t, action):
            pos, quat = episode.waypoints[t], episode.quats[t]
            new_grasp, redundant, now, nxt, during = self._realised(episode, grasp, t, pos, quat, action)
            changed = new_grasp != grasp
            terms, problem = self.score_deferred(episode, t, pos, quat, now, nxt, redundant, during, changed)
            return new_grasp, changed, nxt.ik.q, terms, problem

        new_grasp, changed, q, terms, problem = jax.vmap(deferred)(jnp.asarray(grasps, jnp.int32), ts, actions)
        terms = self.with_last_motor(episode, terms, problem)
        moved = jax.vmap(lambda t, g, c, qn, tm: self._settle(episode, t, episode.waypoints[t], g, c, qn, tm))(
            ts, new_grasp, changed, q, terms)
        return moved, moved.terms.reward, moved.done

    @jax.jit
    def _move(self, ep: Episode, grasp, t, tool_pos, tool_quat, action) -> State:
        """The state after `action` from grasp `grasp` at waypoint `t` with the tool at (tool_pos, tool_quat)."""
        new_grasp, redundant, now, nxt, during = self._realised(ep, grasp, t, tool_pos, tool_quat, action)
        return self._arrive(ep, grasp, t, tool_pos, tool_quat, new_grasp, redundant, now, nxt, during)

    def _realised(self, ep: Episode, grasp, t, tool_pos, tool_quat, action):
        """(new grasp, redundant, its contacts now, at waypoint t + 1, the shared grasp's now or None) of `action`."""
        new_grasp, redundant = self.space.apply(grasp, action)
        t_next = jnp.minimum(t + 1, ep.n_steps - 1)
        pos_n, quat_n = ep.waypoints[t_next], ep.quats[t_next]
        # the two (three) IK solves are independent: one vmapped solve runs them in lock step
        shared = [self.space.shared(grasp, action)] if self.reward_config.prices_changes else []
        grasp_in = [new_grasp, new_grasp] + shared
        pos_in = [tool_pos, pos_n, tool_pos][: len(grasp_in)]
        quat_in = [tool_quat, quat_n, tool_quat][: len(grasp_in)]
        realised = jax.vmap(self.realise)(jnp.stack(grasp_in), jnp.stack(pos_in), jnp.stack(quat_in))
        now, nxt, *rest = (jax.tree.map(lambda x, i=i: x[i], realised) for i in range(len(grasp_in)))
        return new_grasp, redundant, now, nxt, rest[0] if rest else None

    def _arrive(self, ep: Episode, grasp, t, tool_pos, tool_quat, new_grasp, redundant, now: Contacts, nxt: Contacts,
                during: Contacts | None) -> State:
        """The state after moving from `grasp` at waypoint t (tool at tool_pos, tool_quat) to `new_grasp`, its
        contacts realised: `now` at the current pose, `nxt` at waypoint t + 1, `during` (the shared grasp's) now."""
        changed = new_grasp != grasp
        terms = self.score(ep, t, tool_pos, tool_quat, now, nxt, redundant, during, changed)
        return self._settle(ep, t, tool_pos, new_grasp, changed, nxt.ik.q, terms)

    def _settle(self, ep: Episode, t, tool_pos, new_grasp, changed, q_next, terms: RewardTerms) -> State:
        """The state at waypoint t + 1 in `new_grasp` (joint angles `q_next`) after a step from waypoint t (tool at
        tool_pos) whose analytic `terms` (`score`) get the learned term and the episode's validity here."""
        t_next = jnp.minimum(t + 1, ep.n_steps - 1)
        pos_n, quat_n = ep.waypoints[t_next], ep.quats[t_next]
        terms = self.with_learned(ep, t, new_grasp, changed, terms)
        invalid = ~episode_ok(ep, self.space.n_grasps)  # traced inputs cannot raise: r_min and a flag, never NaN
        terms = reward_lib.with_invalid(self.reward_config, terms, invalid)
        done = terms.collision | terms.fall | (t + 1 >= ep.n_steps) | invalid
        vel = jnp.concatenate([(pos_n - tool_pos) / ep.dt, jnp.zeros(3, jnp.float32)])
        return State(
            grasp=new_grasp,
            t=t + 1,
            q=q_next,
            tool_pos=pos_n,
            tool_quat=quat_n,
            tool_vel=vel,
            episode=ep,
            done=done,
            terms=terms,
        )


def _only_where(pred, fn, *operands):
    """`fn(*operands)` where `pred` (() bool) holds, zeros of its shape elsewhere: a `lax.cond`. Under `vmap` (a
    batched `cond` predicate becomes a `select`, which runs both sides), one `cond` on whether any row's `pred`
    holds, which then runs `fn` for every row and zeroes the others: a batch none of whose rows needs `fn` (steps
    in lock step before the last waypoint) skips it. Nested `vmap`s nest the rule. `fn` closes over no tracer."""
    @jax.custom_batching.custom_vmap
    def run(pred, *ops):
        def zeros(*o):
            return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(fn, *o))
        return jax.lax.cond(pred, fn, zeros, *ops)

    @run.def_vmap
    def rule(axis_size, in_batched, pred, *ops):
        axes = tuple(jax.tree.map(lambda b: 0 if b else None, b) for b in in_batched[1:])
        each = jax.vmap(fn, in_axes=axes, axis_size=axis_size)
        if not in_batched[0]:
            out = _only_where(pred, each, *ops)
        else:
            def masked(p, *o):
                return jax.tree.map(lambda x: jnp.where(p.reshape(p.shape + (1,) * (x.ndim - 1)), x, 0), each(*o))
            out = _only_where(jnp.any(pred), masked, pred, *ops)
        return out, jax.tree.map(lambda _: True, out)

    return run(pred, *operands)


def _absorbing(state: State, moved: State) -> tuple[State, jax.Array, jax.Array]:
    """(next state, reward, done) of a step from `state` to `moved` (leading axes broadcast): a finished state is
    absorbing, reward 0."""
    out = jax.tree.map(lambda old, new: jnp.where(state.done, old, new), state, moved)
    return out, jnp.where(state.done, 0.0, moved.terms.reward), out.done


def episode_ok(episode: Episode, n_grasps: int) -> jax.Array:
    """() bool, traceable: the episode's inputs are in range -- every field finite, dt, mass, inertia and friction
    positive, the start grasp a grasp of the model. `scenario.validate` checks the same and more from Python, naming
    the field; inside `jit` a step of an episode that fails this gives r_min, done and `RewardTerms.invalid`."""
    leaves = [episode.waypoints, episode.quats, episode.dt, episode.w_ext, episode.mass, episode.inertia, episode.com,
              episode.friction]
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
    positive = (episode.dt > 0) & (episode.mass > 0) & jnp.all(episode.inertia > 0) & (episode.friction > 0)
    return finite & positive & (episode.start_grasp >= 0) & (episode.start_grasp < n_grasps)


@jax.jit
def _replay(sur: Surrogate, episode: Episode, actions: jax.Array):
    """(the state each step starts from, its terms) along `actions` from the episode's start."""
    def step(state, a):
        nxt, _, _ = sur.step(state, a)
        return nxt, (state, nxt.terms)

    return jax.lax.scan(step, sur.reset(episode), actions)[1]
