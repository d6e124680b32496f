"""The episode runner: a policy's decisions at the waypoints, the contact controller between them, stepped by
MuJoCo MJX (`Physics.simulate`, pure JAX: jit and vmap over episodes) or by C MuJoCo (`backend="c"`, the
reference implementation of the engine; `gsp_jax.physics.c_backend`).

Timeline of an episode (`PhysicsConfig.timeline`): T decision segments of the episodes' dt (`scenario.DT`), then
`hold` seconds at the final pose, in control ticks of the scene's physics step (the controller acts at every step).
At the start of segment k < T the policy observes the *simulated* state (joint angles, tool pose and velocity: the
surrogate's `State`) and picks an action; the new reference grasp is executed by the controller during the segment
while the tool tracks the reference motion from waypoint k to k+1. In the hold the episode's external wrench ramps
on (`xfrc_applied` at the tool's CoM, known to the controller); the tool's angle and position errors are averaged
over the hold.

A tool that touches the table (after the first segment, when the start pedestals drop), moves `fall_distance`
from its reference or turns more than `fall_angle` has fallen (`PhysicsConfig.outcome`): its angle error is
`FALLEN_ERROR` (180 degrees) and its simulation freezes there (a dropped tool never reaches the solver as NaN).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from mujoco import mjx

from gsp_jax.model import scenario
from gsp_jax.physics import world as world_lib
from gsp_jax.physics.config import PhysicsConfig
from gsp_jax.physics.controller import Controller, ControllerState, reference_motion
from gsp_jax.physics.scene import Observation, Scene
from gsp_jax.physics.spec import PhysicsSpec
from gsp_jax.surrogate.reward import RewardTerms
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate.step import State, Surrogate

BACKENDS = ("mjx", "c")
FALLEN_ERROR = 180.0  # [deg] the angle error a fallen tool reports (`Result.angle_error`, `Result.max_angle`)


@struct.dataclass
class Result:
    """One simulated episode. Shapes for one episode (a batch adds a leading axis); K control ticks in all."""

    actions: jax.Array  # (T,) int32, the policy's actions
    grasps: jax.Array  # (T,) int32, reference grasp after each decision
    angle_error: jax.Array  # () [deg] mean tool angle error over the hold; FALLEN_ERROR (180) if it fell
    position_error: jax.Array  # () [m] mean tool position error over the hold (meaningless if it fell)
    max_angle: jax.Array  # () [deg] largest angle error before the hold (the lift's tilt); 180 if it fell then
    fell: jax.Array  # () bool: touched the table, dropped, or turned past fall_angle
    fall_time: jax.Array  # () [s] when it fell; -1 if it did not
    angle: jax.Array  # (K,) [deg] angle error after each control tick
    qpos: jax.Array  # (K, nq) the simulated configuration after each control tick (for plots and video)


@struct.dataclass
class _Carry:
    data: mjx.Data
    cs: ControllerState
    grasp: jax.Array
    fell: jax.Array
    fall_tick: jax.Array
    pending: jax.Array | None = None  # (D, nu) the motor commands on their way (a world's delay; None: no world)
    delay: jax.Array | None = None  # () int32 ticks a command waits (the world's)


class Physics:
    """Scene + contact controller + episode runner for one hand/tool model. Stateless after construction."""

    def __init__(self, surrogate: Surrogate | None = None, config: PhysicsConfig | None = None):
        """The physics of the surrogate's model (its scene file, `HandModel.source`; None: `Surrogate()`, the
        default model). `config` None: the default controller with the model's own tuning where
        `calibrate --tune --write` made one (`tuning.config`)."""
        self.surrogate = surrogate or Surrogate()
        if config is None:
            from gsp_jax.physics import tuning

            config = tuning.config(self.surrogate.model)
        self.hand, self.space, self.config = self.surrogate.hand, self.surrogate.space, config
        self.scene = Scene(self.hand, config)
        self.model = self.scene.model
        self.timestep = self.scene.timestep  # [s] the control period: the scene's physics step
        self.segment = scenario.DT  # [s] between decisions: the episodes' dt (`check_episodes`)
        self.controller = Controller(self.hand, self.space, config, self.scene.ctrl_range, self.hand.gravity,
                                     self.timestep)
        self.n_segment = self.ticks(self.segment)  # control ticks per segment
        self.n_hold = max(1, int(round(config.timeline.hold / self.segment)))  # hold segments
        self._kept = {}  # `kept`: this Physics's programs and what else its backends make once
        # what the C backend reads of this Physics (`spec.PhysicsSpec`)
        self.spec = PhysicsSpec(
            hand=self.hand, space=self.space, scene=self.scene, mj_model=self.model, config=config,
            controller=self.controller, timestep=self.timestep, n_segment=self.n_segment, n_hold=self.n_hold,
            start=self.start, decide=self.decide, tick=self.tick, check=self.check,
            observed_state=self.observed_state, hold_error=self.hold_error, result=self.result, kept=self.kept,
            nominal=lambda: scenario.make_episode(model=self.surrogate.model))

    def kept(self, key, make):
        """What `make()` gives, made on the first call with this key and kept for this Physics: its compiled
        programs (the MJX batch per policy axis, the C backend's per episode length, L1-physics's decisions) and
        the backends' state made once (the native tick, the branches' model pool, the widths already compiled)."""
        if key not in self._kept:
            self._kept[key] = make()
        return self._kept[key]

    def ticks(self, seconds: float) -> int:
        """Whole control ticks (at least 1) nearest `seconds`."""
        return max(1, int(round(seconds / self.timestep)))

    def n_ticks(self, n_steps: int) -> int:
        """Control ticks of an episode with n_steps waypoints (the length of `Result.angle`)."""
        return self.spec.n_ticks(n_steps)

    def segment_start(self, k: int) -> np.float32:
        """[s] when segment k starts, float32 as `decide` computes it in JAX (k n_segment, then times the tick)."""
        return self.spec.segment_start(k)

    def hold_time(self, n_steps: int) -> float:
        """Simulated time at which the hold starts [s]."""
        return self.spec.hold_time(n_steps)

    # ------------------------------------------------------------------ the pieces both backends share
    def start(self, episode: Episode):
        """(initial qpos (nq,), controller state) of an episode: the start grasp realised by IK at waypoint 0,
        the tool at rest there."""
        q0 = self.surrogate.realise(episode.start_grasp, episode.waypoints[0], episode.quats[0]).ik.q
        qpos = self.scene.initial_qpos(episode, q0)
        obs = self.scene.observe(qpos, jnp.zeros(self.model.nv), jnp.zeros(self.model.nv))
        return qpos, self.controller.start(episode, q0, obs)

    def decide(self, policy, cs: ControllerState, obs: Observation, grasp, episode: Episode, k):
        """Segment k's decision: the policy acts on the observed state if k < T; (action (-1 in the hold), new
        grasp, controller state for the segment)."""
        decision, state = k < episode.n_steps, self.observed_state(obs, grasp, episode, k)
        action = jax.lax.cond(decision, lambda s: jnp.asarray(policy.act(s), jnp.int32), lambda s: jnp.int32(0), state)
        grasp = jnp.where(decision, self.space.apply(grasp, action)[0], grasp)
        cs = self.controller.begin_segment(cs, obs, grasp, k * self.n_segment * self.timestep)
        return jnp.where(decision, action, -1), grasp, cs

    def observed_state(self, obs: Observation, grasp, episode: Episode, k) -> State:
        """The surrogate `State` a policy reads at segment k: the simulated joints and tool, the reference grasp."""
        t = jnp.minimum(k, episode.n_steps - 1)
        return State(grasp=jnp.asarray(grasp, jnp.int32), t=jnp.asarray(t, jnp.int32), q=obs.q, tool_pos=obs.tool_pos,
                     tool_quat=obs.tool_quat, tool_vel=obs.tool_vel, episode=episode, done=jnp.array(False),
                     terms=RewardTerms.zeros())

    def external(self, episode: Episode, j) -> jax.Array:
        """(6,) the external wrench applied during control tick j (ramped on in the hold)."""
        held = (j + 1) * self.timestep - self.hold_time(episode.n_steps)
        return jnp.clip(held / self.config.timeline.ramp, 0.0, 1.0) * episode.w_ext

    def tick(self, cs: ControllerState, obs: Observation, episode: Episode, j):
        """Control tick j: (motor commands (nu,), tool external wrench (6,), controller state)."""
        time = j * self.timestep
        ext = self.external(episode, j)  # fed forward: the controller knows the external wrench
        tau, cs = self.controller.control(cs, obs, episode, reference_motion(episode, time), time, ext)
        ctrl = jnp.zeros(self.model.nu, jnp.float32).at[self.scene.hand_act].set(tau)
        return ctrl, ext, cs

    def check(self, obs: Observation, episode: Episode, j):
        """Status after control tick j: (angle error [deg], position error [m], fallen?)."""
        ref = reference_motion(episode, (j + 1) * self.timestep)
        return self.scene.status(obs, ref.pos, ref.quat, j >= self.n_segment)

    def hold_error(self, angle, fell, n_steps: int) -> jax.Array:
        """(...) [deg] the mean tool angle error over the hold of episodes of n_steps waypoints (`angle` (..., K) a
        tick), FALLEN_ERROR where `fell` (...): `Result.angle_error`."""
        return jnp.where(fell, FALLEN_ERROR, jnp.mean(angle[..., n_steps * self.n_segment:], -1))

    def result(self, actions, grasps, angle, perr, qpos, fell, fall_tick, n_steps) -> Result:
        n_before = n_steps * self.n_segment
        return Result(
            actions=actions, grasps=grasps,
            angle_error=self.hold_error(angle, fell, n_steps),
            position_error=jnp.mean(perr[..., n_before:], -1),
            max_angle=jnp.where(fell & (fall_tick < n_before), FALLEN_ERROR, jnp.max(angle[..., :n_before], -1)),
            fell=fell, fall_time=jnp.where(fell, (fall_tick + 1).astype(jnp.float32) * self.timestep, -1.0),
            angle=angle, qpos=qpos)

    # ---------------------------------------------------------------------------------- the MJX runner
    def _observe(self, data: mjx.Data) -> Observation:
        return self.scene.observe(data.qpos, data.qvel, data.qfrc_bias)

    def _init(self, episode: Episode) -> _Carry:
        """The MJX state and controller state of one episode at t = 0."""
        qpos, cs = self.start(episode)
        data = mjx.make_data(self.scene.mx).replace(qpos=qpos)
        return _Carry(data=data, cs=cs, grasp=jnp.asarray(episode.start_grasp, jnp.int32), fell=jnp.array(False),
                      fall_tick=jnp.asarray(-1, jnp.int32))

    def _decide(self, policy, carry: _Carry, episode: Episode, world, k):
        """Segment k's decision for one episode in `world` (None: nominal): (carry, (action, grasp))."""
        obs = world_lib.seen(self._observe(carry.data), world, k * self.n_segment)
        action, grasp, cs = self.decide(policy, carry.cs, obs, carry.grasp, episode, k)
        return carry.replace(cs=cs, grasp=grasp), (action, grasp)

    def _step(self, carry: _Carry, episode: Episode, fields, world, j):
        """Control tick j of one episode in MJX in `world` (None: nominal; its fields are in `fields`): (carry,
        (angle, position error, qpos))."""
        scene = self.scene
        mx = scene.mjx_model(fields, scene.pedestal_drop(j * self.timestep))
        ctrl, ext, cs = self.tick(carry.cs, world_lib.seen(self._observe(carry.data), world, j), episode, j)
        xfrc = jnp.zeros((self.model.nbody, 6), jnp.float32).at[scene.tool_body].set(ext)
        pending = carry.pending
        if pending is not None:  # a world's delay: the command of tick j - delay acts (zeros before the first)
            ring = pending.shape[0]
            pending = pending.at[j % ring].set(ctrl)
            ctrl = pending[(j - carry.delay) % ring]
        data = carry.data.replace(ctrl=ctrl, xfrc_applied=xfrc)
        data = mjx.step(mx, data)
        angle, perr, fell_now = self.check(self._observe(data), episode, j)
        keep = carry.fell | fell_now  # freeze: a fallen tool stays put, a non-finite step is never stored
        data = jax.tree.map(lambda old, new: jnp.where(keep, old, new), carry.data, data)
        fall_tick = jnp.where(fell_now & ~carry.fell, j, carry.fall_tick)
        carry = carry.replace(data=data, cs=cs, fell=carry.fell | fell_now, fall_tick=fall_tick, pending=pending)
        return carry, (angle, perr, data.qpos)

    def _run(self, policy, episodes: Episode, policy_axis, batched: bool, world=None) -> Result:
        """The MJX episode loop: a scan over segments, each a decision and a scan over its control ticks. With
        `batched`, every per-episode function is vmapped *inside* the scans (the carry is batched from the start:
        tracing a vmapped scan instead re-batches its body until the carry's batching settles, a slow trace:
        docs/performance.md)."""
        T, n = episodes.n_steps, self.n_segment
        vm = (lambda f, axes: jax.vmap(f, in_axes=axes)) if batched else (lambda f, axes: f)  # noqa: E731
        fields = vm(self.scene.episode_fields, 0)(episodes, world)  # the world's model fields
        carry = vm(self._init, 0)(episodes)
        if world is not None:  # a ring longer than any delay a world may draw (`world.MOST_DELAY`)
            ring = jnp.zeros((world_lib.MOST_DELAY + 1, self.model.nu), jnp.float32)
            carry = carry.replace(pending=jnp.broadcast_to(ring, (*jnp.shape(world.delay), *ring.shape)),
                                  delay=jnp.asarray(world.delay, jnp.int32))

        def segment(carry: _Carry, k):
            carry, decision = vm(self._decide, (policy_axis, 0, 0, 0, None))(policy, carry, episodes, world, k)
            tick = lambda carry, i: vm(self._step, (0, 0, 0, 0, None))(  # noqa: E731
                carry, episodes, fields, world, k * n + i)
            carry, trace = jax.lax.scan(tick, carry, jnp.arange(n))
            return carry, (decision, trace)

        carry, ((actions, grasps), trace) = jax.lax.scan(segment, carry, jnp.arange(T + self.n_hold))
        # (segments, ticks[, batch], ...) -> ([batch,] segments * ticks, ...); decisions -> ([batch,] T)
        lead = 1 if batched else 0
        trace = jax.tree.map(lambda x: jnp.moveaxis(x.reshape(-1, *x.shape[2:]), 0, lead), trace)
        actions, grasps = (jnp.moveaxis(x, 0, lead)[..., :T] for x in (actions, grasps))
        angle, perr, qpos = trace
        return self.result(actions, grasps, angle, perr, qpos, carry.fell, carry.fall_tick, T)

    def simulate(self, policy, episode: Episode, world=None) -> Result:
        """One episode of `policy` (anything with `act(State) -> action`) on `episode`, stepped by MJX; see the
        module docstring. Open loop is `policies.SequencePolicy`; closed loop any policy that reads the state.
        `world`: the episode's world (`gsp_jax.physics.world`; None: nominal), hidden from the controller and policy.
        Pure JAX: jit it, or vmap it over episodes (`simulate_batch` runs a batch faster to trace)."""
        return self._run(policy, episode, None, batched=False, world=world)

    def simulate_batch(self, policy, episodes: Episode, policy_axis: int | None = None, backend: str = "mjx",
                       progress: bool = False, cores: int | None = None, world=None) -> Result:
        """Every episode of a batch (leading axis) with `policy`; with policy_axis=0 the policy pytree carries the
        same batch axis (e.g. one `SequencePolicy` per episode). backend "mjx": one XLA kernel, `simulate`'s loop
        with its per-tick step vmapped inside the scans (jitted once per structure); "c": C MuJoCo on `cores` CPU
        cores (default all; `c_backend.simulate`), the same controller."""
        return self.simulate_many([(policy, policy_axis)], episodes, backend, progress, cores, world=world)[0]

    def simulate_many(self, policies, episodes: Episode, backend: str = "mjx", progress: bool = False,
                      cores: int | None = None, workers: int | None = None, world=None) -> list[Result]:
        """Several policies on the same episodes: `policies` is a list of (policy, policy_axis) pairs (axis as in
        `simulate_batch`); one `Result` per pair. In C MuJoCo every policy's episodes run in one lockstep on
        `cores` cores, as `workers` chunks side by side (`c_backend.simulate`; defaults: all cores, a chunk a
        core); in MJX one batch per policy. `world`: the episodes' worlds (`gsp_jax.physics.world.World` with the
        episodes' leading axis; None: the nominal world), hidden from the controller and the policies: every
        policy of the batch meets the same world on the same episode."""
        self._check_batch(policies, episodes)
        check_episodes(episodes)
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        for name, value in (("cores", cores), ("workers", workers)):
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if backend != "c" and any(hasattr(p, "in_physics") for p, _ in policies):
            raise ValueError(f"policy: a policy that decides in physics (e.g. PhysicsLookahead) branches copies of C "
                             f"MuJoCo's state and needs backend='c', got backend={backend!r}")
        if self.config.controller.predictive and backend != "c":
            raise ValueError(f"PhysicsConfig.controller.predictive: the predictive hold rolls the hold out in C "
                             f"MuJoCo and needs backend='c', got backend={backend!r}")
        world_lib.check(world, episodes, self.scene)
        if backend == "c":
            from gsp_jax.physics import c_backend

            if self.config.controller.predictive:
                return self._predictive(policies, episodes, cores, progress, workers, world)[0]
            return c_backend.simulate(self.spec, list(policies), episodes, cores=cores, progress=progress,
                                      workers=workers, world=world)
        out = []
        for policy, policy_axis in policies:
            run = self.kept(("mjx", policy_axis), lambda a=policy_axis: jax.jit(
                lambda policy, episodes, world: self._run(policy, episodes, a, True, world)))
            out.append(run(policy, episodes, world))
        return out

    def simulate_predictive(self, policies, episodes: Episode, cores: int | None = None, progress: bool = False,
                            workers: int | None = None, world=None) -> tuple[list[Result], list[np.ndarray]]:
        """`simulate_many(..., backend="c")` with the predictive hold whatever the config says, and which candidate
        each episode kept: (results, chosen), one `Result` and one (R,) int32 array per policy
        (`gsp_jax.physics.predictive`; the candidates' physics are kept, built once)."""
        self._check_batch(policies, episodes)
        check_episodes(episodes)
        world_lib.check(world, episodes, self.scene)
        return self._predictive(policies, episodes, cores, progress, workers, world)

    def _predictive(self, policies, episodes: Episode, cores, progress, workers, world=None):
        """`simulate_predictive` of a batch already checked."""
        from gsp_jax.physics import predictive

        def build():  # the first candidate is the run's own settings: its spec (the predictive flag aside) is ours
            others = predictive.candidate_configs(self.config, self.hand)[1:]
            return [self.spec] + [Physics(self.surrogate, c).spec for c in others]

        specs = self.kept("predictive", build)
        return predictive.simulate(self.spec, specs, list(policies), episodes, cores, progress, workers, world)

    def _check_batch(self, policies, episodes: Episode) -> None:
        """Named errors for a batch the runner cannot take: episodes without a batch axis, an invalid episode of the
        model (`scenario.validate`), a per-episode policy (axis 0) whose batch is not the episodes'."""
        if isinstance(episodes.mass, jax.core.Tracer):
            return
        if np.ndim(episodes.mass) != 1:
            raise ValueError(f"episodes: expected a batch (a leading axis on every field: scenario.stack([...])), got "
                             f"mass of shape {np.shape(episodes.mass)}")
        n = int(np.shape(episodes.mass)[0])
        for i, ep in enumerate(scenario.unstack(episodes)):
            scenario.validate(ep, f"episodes[{i}]", hand=self.hand)
        for k, (policy, axis) in enumerate(policies):
            if not (isinstance(axis, int) and axis == 0):  # None, or a pytree of in_axes (e.g. a `Lookahead`'s)
                continue
            sizes = {np.shape(x)[0] if np.ndim(x) else None for x in jax.tree.leaves(policy)}
            if sizes != {n}:
                raise ValueError(f"policies[{k}]: a per-episode policy (policy_axis=0) needs a leading axis of {n} "
                                 f"(the episodes) on every array, got {sorted(sizes, key=str)}")


def check_episodes(episodes: Episode) -> None:
    """Clear errors for episodes the physics check cannot run (concrete arrays only)."""
    dt = np.asarray(episodes.dt)
    if not np.allclose(dt, scenario.DT, rtol=1e-5):
        raise ValueError(f"episode.dt must equal the physics check's segment, scenario.DT = {scenario.DT} s, got "
                         f"{np.unique(dt)}")
    for name in ("mass", "friction"):
        value = np.asarray(getattr(episodes, name))
        if not np.all(np.isfinite(value) & (value > 0)):
            raise ValueError(f"episode.{name} must be finite and > 0, got {value}")
    inertia = np.asarray(episodes.inertia)
    if not np.all(np.isfinite(inertia) & (inertia > 0)):
        raise ValueError(f"episode.inertia must be finite and > 0, got {inertia}")
