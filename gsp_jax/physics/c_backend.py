"""The C MuJoCo backend of the runner: the same controller, decisions and outcome as the MJX runner
(`runner.Physics.simulate`), with the physics stepped by C MuJoCo on every CPU core. It is the reference every MJX
figure can be checked against, and for this scene the faster engine (per core, than MJX on a GPU:
docs/performance.md).

One lockstep runs every episode of every policy given (Fig. 4b's 5 policies x 27 episodes are one batch of 135):

  at each segment start   each policy decides for its own episodes (one jitted call per policy, on `device`; a
                          policy that reads only its grasp and waypoint, e.g. a sequence or a DP table, in
                          numpy, and JAX only where a grasp changes: `ActionTable`);
  between decisions       the episodes run as chunks of rows side by side (threads; `workers`, default one a
                          core), each chunk's whole segment one call of native code (`native.segment`): at every
                          control tick the contact controller's tick (`native`, the JAX controller's control law
                          compiled by numba) and one `mj_step` of each episode's own model and data (`Engine`),
                          without Python and without its lock.

Each episode's controller and physics are its own: a row's result does not depend on the rows beside it, the
chunking or the core count. Episodes that fell are frozen (no longer stepped). `controller="jax"` runs the JAX
tick instead (one XLA call a tick and chunk, with the fixed cost per call the native tick removes:
docs/performance.md), the reference the native tick must equal; checked by
`tests/test_native.py::test_native_tick_is_the_jax_tick_on_recorded_states`. A policy decided in numpy
(`ActionTable`, `native.keep_grasp`) must give the JAX decisions' run bit for bit; checked by
`tests/test_physics.py::test_c_lockstep_decides_table_policies_in_numpy_as_jax_does`.

The backend reads a `Physics` through its `spec` (`spec.PhysicsSpec`: the scene, the config, the controller, the
timeline and the JAX functions both backends share; every entry point takes a `Physics` or its spec) and knows no
planner: a policy is anything with `act(state)` (`OpenLoop` is its own open-loop one); a policy that decides in
physics has a hook `in_physics(spec, snapshot, rows, obs, episodes, k, n_steps)` that gives the segment's policy.
"""
from __future__ import annotations

import collections
import dataclasses
import os
import time
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
from jax.flatten_util import ravel_pytree

from gsp_jax.model import grasps, scenario
from gsp_jax.model.scenario import Episode
from gsp_jax.physics import native
from gsp_jax.physics import world as world_lib
from gsp_jax.physics.spec import HasSpec, PhysicsSpec, of

CONTROLLERS = ("native", "jax")  # the controller's tick: compiled to native code, or the JAX program


def available_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


class _Flat:
    """Ravel / unravel one episode's pytree (a batch: leading axis) to one float32 vector, inside or outside jit."""

    def __init__(self, one):
        flat, self._unravel = ravel_pytree(jax.tree.map(lambda x: np.asarray(x, np.float32), one))
        self._dtypes = jax.tree.map(lambda x: np.asarray(x).dtype, one)
        self.size = flat.shape[0]

    def ravel(self, tree) -> jax.Array:
        return jax.vmap(lambda t: ravel_pytree(jax.tree.map(lambda x: x.astype(jnp.float32), t))[0])(tree)

    def unravel(self, flat: jax.Array):
        tree = jax.vmap(self._unravel)(flat)
        return jax.tree.map(lambda x, d: jnp.round(x).astype(d) if jnp.issubdtype(d, jnp.integer)
                            else (x > 0.5 if d == jnp.bool_ else x.astype(d)), tree, self._dtypes)


class _Programs:
    """The jitted programs of one `Physics` (built once, shared by every call): start, the JAX controller's tick
    (`controller="jax"`), and a decision per way a policy is batched."""

    def __init__(self, spec: PhysicsSpec, one_episode: Episode):
        self.spec, scene = spec, spec.scene
        m = spec.mj_model
        self.nq, self.nv, self.nu = m.nq, m.nv, m.nu
        zeros = lambda tree: jax.tree.map(lambda x: np.zeros(x.shape, x.dtype), tree)  # noqa: E731
        self.cs = _Flat(zeros(jax.eval_shape(spec.start, one_episode)[1]))  # its layout only: nothing runs
        self.ep = _Flat(zeros(one_episode))
        nq, nv = self.nq, self.nv

        def observe(obs_flat):
            return jax.vmap(scene.observe)(obs_flat[:, :nq], obs_flat[:, nq:nq + nv], obs_flat[:, nq + nv:])

        def start(episodes):
            qpos, cs = jax.vmap(spec.start)(episodes)
            return qpos, self.cs.ravel(cs)

        def tick(cs_flat, obs_flat, seen_flat, ep_flat, j):
            """(next controller states, [ctrl (nu) | external wrench (6) | angle, position error, fell of tick j-1]);
            the status from the observation, the controller from what it observes (`Engine.seen`)."""
            episodes, obs = self.ep.unravel(ep_flat), observe(obs_flat)
            angle, perr, fell = jax.vmap(spec.check, in_axes=(0, 0, None))(obs, episodes, j - 1)
            ctrl, ext, cs = jax.vmap(spec.tick, in_axes=(0, 0, 0, None))(self.cs.unravel(cs_flat),
                                                                         observe(seen_flat), episodes, j)
            status = jnp.stack([angle, perr, fell.astype(jnp.float32)], -1)
            return self.cs.ravel(cs), jnp.concatenate([ctrl, ext, status], -1)

        self.observe = observe
        self.start = jax.jit(start)
        self.tick = jax.jit(tick)
        self.fields = jax.jit(jax.vmap(scene.episode_fields))
        self.hold_error = jax.jit(spec.hold_error, static_argnums=2)
        self.ravel_episodes = jax.jit(self.ep.ravel)
        self._decide = {}

    def decide(self, policy_axis):
        if policy_axis not in self._decide:
            spec = self.spec

            def decide(policy, cs_flat, obs_flat, grasp, episodes, k):
                action, grasp, cs = jax.vmap(spec.decide, in_axes=(policy_axis, 0, 0, 0, 0, None))(
                    policy, self.cs.unravel(cs_flat), self.observe(obs_flat), grasp, episodes, k)
                return action, grasp, self.cs.ravel(cs)

            self._decide[policy_axis] = jax.jit(decide)
        return self._decide[policy_axis]


def programs(phys: PhysicsSpec | HasSpec, episodes: Episode) -> _Programs:
    """The C backend's jitted programs of a `Physics` (or its spec) for episodes of this length (made on first use:
    the flat layout of an episode depends on its number of waypoints)."""
    spec = of(phys)
    return spec.kept(("c", episodes.n_steps), lambda: _Programs(spec, jax.tree.map(lambda x: np.asarray(x)[0],
                                                                                    episodes)))


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """A lockstep's M rows at the start of segment `segment`, before its decision: everything the rest of those
    episodes depends on, so that `simulate(..., start=snapshot)` continues them bit for bit as the original run
    would (with the same policies and row count: the controller's programs are compiled per batch size). numpy."""

    segment: int  # the next segment (its decision not yet made)
    qpos0: np.ndarray  # (M, nq) float64: the episodes' initial configurations
    state: np.ndarray  # (M, nstate) float64: MuJoCo's state rows (`mujoco.batch.Batch.state`: time, qpos, qvel,
    # act, the solver's warm start, ctrl, applied forces, ...)
    obs: np.ndarray  # (M, nq + 2 nv) float32: the observation the decision reads (qfrc_bias is the last step's)
    cs: np.ndarray  # (M, C) float32: the controller states, flat
    grasp: np.ndarray  # (M,) int32: the reference grasp
    fell: np.ndarray  # (M,) bool
    fall_tick: np.ndarray  # (M,) int32, -1 if not fallen
    angle: np.ndarray  # (M, K) float32: the recorded traces so far (later ticks zero)
    perr: np.ndarray  # (M, K) float32
    qpos: np.ndarray  # (M, K, nq) float32
    actions: np.ndarray  # (M, T) int32: the decisions so far
    grasps: np.ndarray  # (M, T) int32
    pending: np.ndarray  # (M, D, nu) float64: motor commands still on their way (a world's delay; zeros without)

    def take(self, rows) -> "Snapshot":
        """The snapshot of `rows` (an index array: rows may repeat, e.g. one copy per branch)."""
        rows = np.asarray(rows)
        return dataclasses.replace(self, **{f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)
                                            if f.name != "segment"})


class Pool:
    """C models and datas kept for reuse, per episode (its fields): a lockstep that starts from a snapshot (a
    branch of L1-physics) sets every state it reads (`mj_setState` of the whole integration state, and the
    pedestals, controls and applied wrench before every step), so a model and data used before serve as a new
    copy would (bit for bit: tests/test_physics.py), without the cost of making them (docs/performance.md)."""

    def __init__(self, most: int = 256):
        self.most, self._free, self._count = most, collections.OrderedDict(), 0  # at most `most` pairs kept

    @staticmethod
    def key(fields) -> bytes:
        """One episode's fields (numpy) as a key."""
        return b"".join(np.ascontiguousarray(x).tobytes() for x in jax.tree.leaves(fields))

    def take(self, scene, key: bytes, fields):
        """A (model, data) of the episode `key`: a kept one, else made (`fields()`: its fields). An episode whose
        last kept pair is taken leaves the pool (every key kept holds at least one pair)."""
        free = self._free.get(key)
        if free:
            self._count -= 1
            pair = free.pop()
            if not free:
                del self._free[key]
            return pair
        m = scene.c_model(fields())
        return m, mujoco.MjData(m)

    def give(self, key: bytes, model, data) -> None:
        """Keep (model, data) for the episode `key`; beyond `most` pairs, the episode given back longest ago loses
        its pairs first."""
        self._free.setdefault(key, []).append((model, data))
        self._free.move_to_end(key)
        self._count += 1
        while self._count > self.most:
            first = next(iter(self._free))
            self._free[first].pop()
            self._count -= 1
            if not self._free[first]:
                del self._free[first]


class Engine:
    """The episodes of one lockstep in C MuJoCo: one `MjModel` per episode (a copy of the physics model with the
    episode's fields: tool mass, inertia, CoM, finger-tool friction, pedestals; `Scene.c_model`) and its `MjData`,
    stepped by `mj_step` from native code (`native.step_rows`, `native.segment`: no Python per step). `obs`
    (n, nq + 2 nv) float32 is every episode's observation: qpos, qvel and qfrc_bias after its last step."""

    def __init__(self, scene, fields, qpos0: np.ndarray, log: list | None = None, pool: "Pool | None" = None,
                 world=None):
        n = qpos0.shape[0]
        self.scene, self.n, self.log, self.pool = scene, n, log, pool
        one = lambda e: jax.tree.map(lambda x: np.asarray(x)[e], fields)  # noqa: E731
        nq, nv = scene.model.nq, scene.model.nv
        self.obs = np.zeros((n, nq + 2 * nv), np.float32)
        if pool is None:  # new copies, at the episodes' start
            self.models = [scene.c_model(one(e)) for e in range(n)]
            self.datas = [mujoco.MjData(m) for m in self.models]
            for e, (m, d) in enumerate(zip(self.models, self.datas)):
                d.qpos[:] = qpos0[e]
                mujoco.mj_forward(m, d)
                self.obs[e] = np.concatenate([d.qpos, d.qvel, d.qfrc_bias])
        else:  # the pool's, for a lockstep that restores its states from a snapshot (`restore`)
            self.keys = [Pool.key(one(e)) for e in range(n)]
            self.models, self.datas = map(list, zip(*[pool.take(scene, k, lambda e=e: one(e))
                                                      for e, k in enumerate(self.keys)]))
        if world is None:
            world = world_lib.nominal_batch(n, scene.n_touch, len(scene.hand_dof))
        delay = np.ascontiguousarray(world.delay, np.int64)
        noise = np.ascontiguousarray(world.noise, np.float32)
        # what the controller observes: the observation itself, or its noised copy where any row has noise
        self.seen = self.obs if not noise.any() else self.obs.copy()
        self.native = native.Models(addresses=native.addresses(self.models, self.datas, scene.tool_body),
                                    pedestals=np.ascontiguousarray(fields.pedestal_pos, np.float64),  # at drop 0
                                    geoms=np.asarray(scene.pedestal_geoms, np.int64), delay=delay,
                                    pending=np.zeros((n, int(delay.max(initial=0)) + 1, scene.model.nu)),
                                    noise=noise, key=np.ascontiguousarray(world.key, np.uint32), seen=self.seen,
                                    noisy=np.full(n, self.seen is not self.obs))
        self._spec = mujoco.mjtState.mjSTATE_INTEGRATION
        self.nstate = mujoco.mj_stateSize(scene.model, self._spec)

    def release(self) -> None:
        """Give a pool's models and datas back to it (this engine is not stepped again)."""
        if self.pool is not None:
            for k, m, d in zip(self.keys, self.models, self.datas):
                self.pool.give(k, m, d)
            self.models, self.datas = [], []

    def state(self, ids=None) -> np.ndarray:
        """(n, nstate) float64: every episode's MuJoCo state (`mjSTATE_INTEGRATION`: time, qpos, qvel, act, the
        solver's warm start, ctrl, applied forces, ...); with `ids`, those episodes' only."""
        ids = range(self.n) if ids is None else ids
        out = np.empty((len(ids), self.nstate))
        for row, e in zip(out, ids):
            mujoco.mj_getState(self.models[e], self.datas[e], row, self._spec)
        return out

    def restore(self, state: np.ndarray, obs: np.ndarray, pending: np.ndarray | None = None, tick: int = 0) -> None:
        """Every episode's MuJoCo state rows (n, nstate) and the observation that went with them (its qfrc_bias
        came from the step before: MuJoCo's derived fields are one step behind the state), and the motor commands
        issued before control tick `tick` (`native.Models.pending`, a ring of the last D ticks; None: none). Into a
        ring of another length (a branch in a world of another delay) each tick's command goes to its slot, the
        oldest one given standing in for ticks before it."""
        for e, (m, d) in enumerate(zip(self.models, self.datas)):
            mujoco.mj_setState(m, d, np.asarray(state[e], np.float64), self._spec)
        self.obs[:] = obs
        ring = self.native.pending
        if pending is not None and np.shape(pending) == ring.shape:
            ring[:] = pending
        elif pending is None:
            ring[:] = 0.0
        else:  # slot of tick - t, t = 1 .. D - 1 (a step writes tick's own slot before it reads)
            have, want = np.shape(pending)[1], ring.shape[1]
            ring[:] = 0.0
            for t in range(1, want):
                ring[:, (tick - t) % want] = pending[:, (tick - min(t, have)) % have]

    def see(self, constants, j: int) -> None:
        """What the controller observes at control tick j from the observation now (`world.seen`): a run's first
        tick, or a restored state's (the noise is a function of the episode's key and j: the same again)."""
        if self.seen is not self.obs:
            native.seen_rows(constants, self.native, np.arange(self.n, dtype=np.int64), self.obs, int(j))

    def step(self, constants, ids: np.ndarray, out: np.ndarray, drop: float, buf: np.ndarray, j: int = 0) -> None:
        """Episodes `ids` advance one physics step under their rows of `out` (n, nu + 6 ...): motor commands
        and the tool's external wrench, with the pedestals `drop` (<= 0) metres below their start; the others
        stay as they are. `buf`: float64 scratch of at least max(nq, nv, nu, 6) (one a thread)."""
        if self.log is not None:  # (episodes, their mjSTATE_INTEGRATION rows, pedestal positions) before the step
            self.log.append((ids.copy(), self.state(ids), self.native.pedestals[ids] + np.array([0.0, 0.0, drop])))
        native.step_rows(constants, self.native, np.asarray(ids, np.int64), out, float(drop), self.obs, buf, int(j))


class _Lockstep:
    """The state of `simulate`'s lockstep: M rows (each group's episodes, one group after another) in one `Engine`,
    split into `workers` chunks of contiguous rows that run side by side (threads); the recorded trace and the
    controller states (flat rows, float32), all numpy."""

    def __init__(self, phys: PhysicsSpec | HasSpec, groups, episodes: Episode, workers: int,
                 engine_log: list | None, start: Snapshot | None = None, controller: str = "native", device=None,
                 world=None):
        if controller not in CONTROLLERS:
            raise ValueError(f"controller must be one of {CONTROLLERS}, got {controller!r}")
        G = len(groups)
        per_group = list(episodes) if isinstance(episodes, (list, tuple)) else [episodes] * G
        if len(per_group) != G or len({e.n_steps for e in per_group}) != 1:
            raise ValueError(f"episodes: one batch for every group, or one batch per group ({G}) of one length")
        episodes = per_group[0]
        sizes = [int(np.shape(e.mass)[0]) for e in per_group]
        self.spec = spec = of(phys)
        self.groups, self.episodes, self.controller = groups, per_group, controller
        scene = spec.scene
        T = episodes.n_steps
        M, K, nq = sum(sizes), spec.n_ticks(T), spec.mj_model.nq
        self.T, self.K, self.nq, self.nu, self.n = T, K, nq, spec.mj_model.nu, spec.n_segment
        self.pr = pr = programs(spec, episodes)
        self.native = native_tick(spec)
        # the device of the decisions' programs (and the episodes' set-up): JAX's default, or the one named
        named = device is not None
        self.device = jax.local_devices(backend=device)[0] if device is None or isinstance(device, str) else device
        original = groups
        if named:
            groups = [(p if _outside_jax(p) else jax.device_put(p, self.device), axis) for p, axis in groups]
            self.groups = groups
        # the lockstep's batch is the groups' episodes one after another
        cat = lambda make: jax.tree.map(lambda *x: np.concatenate([np.asarray(a) for a in x]),  # noqa: E731
                                        *[make(e) for e in per_group])
        self.ep_native = cat(self.native.episodes)
        end = T + spec.n_hold
        if start is not None and (np.shape(start.state)[0] != M or np.shape(start.qpos0)[0] != M
                                  or not 0 <= start.segment <= end):
            raise ValueError(f"start: a snapshot of {M} rows (the groups' episodes) at a segment in 0..{end} is "
                             f"needed, got {np.shape(start.state)[0]} rows at segment {start.segment}")
        if start is None:
            with jax.default_device(self.device):
                qpos0, cs = cat(lambda e: jax.device_get(pr.start(e)))
            self.qpos0 = np.asarray(qpos0, np.float64)
            self.cs = np.ascontiguousarray(cs, np.float32)
        else:  # the start's IK is not run again (its rows were checked above)
            self.qpos0 = np.array(start.qpos0, np.float64)
        worlds = list(world) if isinstance(world, (list, tuple)) else [world] * G  # the episodes' own, per group
        with jax.default_device(self.device):
            fields = jax.tree.map(lambda *x: np.concatenate([np.asarray(a) for a in x]),
                                  *[jax.device_get(pr.fields(e, w)) for e, w in zip(per_group, worlds)])
            # the episodes as the JAX tick reads them (flat rows); the native tick reads `ep_native`
            self.ep_flat = cat(lambda e: np.asarray(pr.ravel_episodes(e))) if controller == "jax" else None
        self.chunks = np.array_split(np.arange(M), workers)  # contiguous rows
        if engine_log is not None and workers != 1:
            raise ValueError(f"engine_log needs workers=1, got workers={workers}")
        pool = spec.kept("c-pool", Pool) if start is not None and engine_log is None else None
        world = None if all(w is None for w in worlds) else jax.tree.map(
            lambda *x: np.concatenate([np.asarray(a) for a in x]),
            *[world_lib.nominal_batch(int(np.shape(e.mass)[0]), scene.n_touch, len(scene.hand_dof)) if w is None
              else jax.device_get(w) for e, w in zip(per_group, worlds)])
        self.engine = Engine(scene, fields, self.qpos0, engine_log, pool, world)
        self.grasp = cat(lambda e: np.asarray(e.start_grasp, np.int32))
        self.fell, self.fall_tick = np.zeros(M, bool), np.full(M, -1, np.int32)
        self.angle, self.perr = np.zeros((M, K), np.float32), np.zeros((M, K), np.float32)
        self.qpos_trace = np.zeros((M, K, nq), np.float32)
        self.actions, self.grasps = np.zeros((M, T), np.int32), np.zeros((M, T), np.int32)
        self.out = np.zeros((M, self.nu + 9), np.float32)  # each row's last tick: ctrl | external | status
        ends = np.cumsum(sizes)
        self.group_rows = [slice(int(e - n), int(e)) for e, n in zip(ends, sizes)]
        self.decides = [pr.decide(0 if _outside_jax(policy) else axis) for policy, axis in groups]
        # a policy that reads only its grasp and waypoint decides in numpy (`ActionTable`), without a JAX call
        self.tables = [action_table(policy, axis, n, spec.space.n_grasps, T) for (policy, axis), n
                       in zip(original, sizes)]
        self.transitions = spec.space.transitions
        # the decisions' episodes on their device once (a call would otherwise send every leaf again)
        self.episodes_on_device = [jax.device_put(e, self.device) for e in per_group]
        self.pedestal_drop, self.tick = scene.pedestal_drop, spec.timestep
        self._scratch = [native.scratch(self.native.constants) for _ in self.chunks]  # one a thread
        self.steps = [0] * len(self.chunks)  # physics steps taken, per chunk
        self.segment = 0
        if start is not None:
            self._restore(start)
        else:
            self.engine.see(self.native.constants, 0)

    def _restore(self, start: Snapshot) -> None:
        """Continue from `start` (its rows are this lockstep's rows)."""
        self.engine.restore(start.state, start.obs, start.pending, start.segment * self.n)
        self.engine.see(self.native.constants, start.segment * self.n)
        self.cs = np.array(start.cs, np.float32)
        self.grasp, self.fell, self.fall_tick = (np.array(x) for x in (start.grasp, start.fell, start.fall_tick))
        self.angle, self.perr, self.qpos_trace = (np.array(x) for x in (start.angle, start.perr, start.qpos))
        self.actions, self.grasps = np.array(start.actions), np.array(start.grasps)
        self.segment = start.segment

    def snapshot(self) -> Snapshot:
        """Every row at the start of the next segment (copies)."""
        return Snapshot(segment=self.segment, qpos0=self.qpos0.copy(), state=self.engine.state(),
                        obs=self.engine.obs.copy(), cs=self.cs.copy(), grasp=self.grasp.copy(),
                        fell=self.fell.copy(), fall_tick=self.fall_tick.copy(), angle=self.angle.copy(),
                        perr=self.perr.copy(), qpos=self.qpos_trace.copy(), actions=self.actions.copy(),
                        grasps=self.grasps.copy(), pending=self.engine.native.pending.copy())

    def advance(self, until: int, progress: bool = False) -> None:
        """Segments self.segment .. until - 1: each a decision, then the chunks' ticks side by side."""
        segments = range(self.segment, until)
        if progress:
            from tqdm.auto import tqdm

            segments = tqdm(segments, desc="C MuJoCo segments", leave=False)
        workers = len(self.chunks)
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for k in segments:
                self.decide(k)
                list(pool.map(self.run_segment, range(workers), [k] * workers))
                self.segment = k + 1

    def record(self, rows: np.ndarray, j, status, now):
        """Tick j's status (angle, position error, fell) and configuration of the episodes `rows`."""
        fell_now = status[:, 2] > 0.5
        self.fall_tick[rows[fell_now & ~self.fell[rows]]] = j
        self.fell[rows] |= fell_now
        self.angle[rows, j], self.perr[rows, j], self.qpos_trace[rows, j] = status[:, 0], status[:, 1], now

    def decide(self, k: int):
        """Each policy decides for its episodes at segment k (the hold: set-up only); the controller states."""
        obs, snapshot = self.engine.seen, None  # what the policies observe
        for g, (policy, _) in enumerate(self.groups):
            rows, decide, table = self.group_rows[g], self.decides[g], self.tables[g]
            if hasattr(policy, "in_physics"):  # a policy that decides in physics (`physics.verified`): its hook
                # gets the lockstep's state and gives this segment's policy (one per episode, axis 0)
                if k < self.T:
                    snapshot = self.snapshot() if snapshot is None else snapshot
                policy = policy.in_physics(self.spec, snapshot if k < self.T else None,
                                           np.arange(len(self.fell))[rows], obs[rows], self.episodes[g], k, self.T)
                table = action_table(policy, 0, rows.stop - rows.start, self.spec.space.n_grasps, self.T)
            if table is not None:
                action = self._decide_in_numpy(rows, table, k)
                if action is None:
                    continue
                if isinstance(policy, ActionTable):  # a grasp changes: the JAX decision, with these actions
                    policy = OpenLoop(np.repeat(action[:, None], self.T, 1))
            with jax.default_device(self.device):
                act, gr, cs_g = decide(policy, jax.device_put(self.cs[rows], self.device), obs[rows],
                                       self.grasp[rows], self.episodes_on_device[g], k)
            if k < self.T:
                self.actions[rows, k], self.grasps[rows, k] = np.asarray(act), np.asarray(gr)
            self.grasp[rows] = np.asarray(gr)
            self.cs[rows] = np.asarray(cs_g)

    def _decide_in_numpy(self, rows: slice, table: np.ndarray, k: int):
        """The decision at segment k of the episodes `rows` from their action tables (R, G, T): made here if no
        grasp changes (then `begin_segment` only restarts the timeline: `native.keep_grasp`), and None returned;
        else their actions (R,), for the JAX decision (a link's new path)."""
        grasp = self.grasp[rows]
        if k < self.T:
            action = table[np.arange(len(grasp)), grasp, k]
            if np.any(self.transitions[grasp, action] != grasp):
                return action
            self.actions[rows, k], self.grasps[rows, k] = action, grasp
        ids = np.arange(rows.start, rows.stop)
        native.keep_grasp(self.native.constants, ids, self.cs, self.spec.segment_start(k))
        return None

    def run_segment(self, w, k):
        """Chunk w's control ticks of segment k."""
        ids, eng, n = self.chunks[w], self.engine, self.n
        j0 = k * n
        drops = np.asarray(self.pedestal_drop(np.arange(j0, j0 + n) * self.tick, xp=np), np.float64)
        if self.controller == "native" and eng.log is None:  # the whole segment in one native call
            trace = native.Trace(self.fell, self.fall_tick, self.angle, self.perr, self.qpos_trace)
            self.steps[w] += native.segment(self.native.constants, j0, drops, ids, self.cs, eng.obs, self.ep_native,
                                            eng.native, trace, self.out, self._scratch[w])
            return
        nu, rows = self.nu, slice(ids[0], ids[-1] + 1)
        alive = ids[~self.fell[ids]]
        for i in range(n):  # tick by tick: the JAX controller, or an engine log
            j = j0 + i
            if self.controller == "native":
                self.native(j, ids, self.cs, eng.obs, self.ep_native, self.out, self._scratch[w], eng.seen)
            else:
                cs, out = self.pr.tick(self.cs[rows], eng.obs[rows], eng.seen[rows], self.ep_flat[rows], j)
                self.cs[rows], self.out[rows] = np.asarray(cs), np.asarray(out)
            if j > 0:
                self.record(ids, j - 1, self.out[ids, nu + 6:], eng.obs[ids, :self.nq])
                alive = ids[~self.fell[ids]]
            if alive.size:
                eng.step(self.native.constants, alive, self.out, drops[i], self._scratch[w].buf, j)
                self.steps[w] += alive.size

    def results(self, outcomes: bool = False):
        """The last tick's status, fallen tools' traces held, and a `runner.Result` (numpy) per group; `outcomes`:
        only (fell (R,), angle error (R,), actions (R, T)) per group, the same values without the rest of a
        `Result` (its traces are not sent through JAX: a branch needs only these)."""
        rows, obs = np.arange(len(self.fell)), self.engine.obs
        status = np.zeros((len(rows), 3), np.float32)
        native.status_rows(self.K - 1, rows, obs, self.ep_native, self.native.constants, status, self._scratch[0])
        self.record(rows, self.K - 1, status, obs[:, :self.nq])
        if outcomes:  # `Physics.result`'s angle error (`hold_error`)
            with jax.default_device(self.device):
                return [(self.fell[g].copy(), np.asarray(self.pr.hold_error(self.angle[g], self.fell[g], self.T)),
                         self.actions[g].copy()) for g in self.group_rows]
        for e in np.flatnonzero(self.fell):  # a fallen tool's trace stays where it was before the tick it fell
            f = self.fall_tick[e]
            self.qpos_trace[e, f:] = self.qpos_trace[e, f - 1] if f > 0 else self.qpos0[e]
        with jax.default_device(self.device):
            return [jax.device_get(self.spec.result(
                jnp.asarray(self.actions[rows]), jnp.asarray(self.grasps[rows]), jnp.asarray(self.angle[rows]),
                jnp.asarray(self.perr[rows]), jnp.asarray(self.qpos_trace[rows]), jnp.asarray(self.fell[rows]),
                jnp.asarray(self.fall_tick[rows]), self.T)) for rows in self.group_rows]


@dataclasses.dataclass(frozen=True)
class ActionTable:
    """A policy given as its actions (not a JAX policy): each episode's action at every grasp and waypoint, for a
    group whose decisions read nothing else (e.g. a branch's first action, then a DP table). The lockstep decides
    it in numpy; policy axis 0 (one table per episode)."""

    table: np.ndarray  # (R, G, T) int32


@struct.dataclass
class OpenLoop:
    """A JAX policy given as its action at each waypoint, whatever the state: actions (T,), or (E, T) at policy
    axis 0 (one row an episode). The physics check's own open-loop policy (the JAX decision of an `ActionTable`
    whose grasp changes, a policy that decides in physics at a segment, the preflight's hold), with the same
    decisions as `planning.policies.SequencePolicy` (it reads only its waypoint: decided in numpy, `act_table`)."""

    actions: jax.Array  # (T,) or (E, T) int32

    def act(self, state) -> jax.Array:
        return self.actions[jnp.minimum(state.t, self.actions.shape[0] - 1)]

    def act_table(self, n_grasps: int, n_steps: int) -> np.ndarray:
        """(..., n_grasps, n_steps) int32 numpy: `act` at every grasp and waypoint (it reads nothing else)."""
        actions = np.asarray(self.actions, np.int32)
        actions = actions[..., np.minimum(np.arange(n_steps), actions.shape[-1] - 1)]
        return np.broadcast_to(actions[..., None, :], actions.shape[:-1] + (n_grasps, n_steps))


def _outside_jax(policy) -> bool:
    """A group's policy that is not a JAX policy as given: one that decides in physics (its hook gives each
    segment's policy, per episode) or an `ActionTable` (decided in numpy)."""
    return hasattr(policy, "in_physics") or isinstance(policy, ActionTable)


def action_table(policy, axis, rows: int, n_grasps: int, n_steps: int) -> np.ndarray | None:
    """(rows, G, T) int32: the actions of a policy that reads only its grasp and waypoint (`ActionTable`, or one
    with `act_table`: `OpenLoop`, `policies.SequencePolicy`, `TablePolicy`) at policy_axis None (one for every
    row) or 0 (one a row); None for any other policy."""
    if isinstance(policy, ActionTable):
        return policy.table
    if not hasattr(policy, "act_table") or axis not in (None, 0) \
            or any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(policy)):
        return None
    table = policy.act_table(n_grasps, n_steps)
    if table.ndim != (2 if axis is None else 3) or (axis == 0 and table.shape[0] != rows):
        return None
    return np.broadcast_to(table, (rows, n_grasps, n_steps))


def native_tick(phys: PhysicsSpec | HasSpec) -> native.Tick:
    """The native tick of a `Physics` (or its spec; made once)."""
    spec = of(phys)
    return spec.kept("native", lambda: native.Tick(spec))


def warm_up(phys: PhysicsSpec | HasSpec):
    """Compile the native code a C MuJoCo run calls (numba's, kept in its cache on disk once compiled) in a
    background thread: runs the model's nominal episode under its start grasp held, one episode, in `phys` (numba
    compiles a function whole on its first call, whatever the grasps; a grasp held is decided in numpy, so no XLA
    decision is compiled here). XLA releases Python's lock while it compiles, so the caller compiles its own
    programs meanwhile (a DP table, a lookahead) on the other cores. Returns a `concurrent.futures.Future`:
    `.result()` waits for it (and raises what the run raised)."""
    spec = of(phys)

    def run():
        episodes = scenario.stack([spec.nominal()])
        hold = np.full((1, spec.space.n_grasps, episodes.n_steps), grasps.NULL, np.int32)
        simulate(spec, [(ActionTable(hold), 0)], episodes, workers=1)

    pool = ThreadPoolExecutor(1, thread_name_prefix="gsp_jax-warm-up")
    future = pool.submit(run)
    pool.shutdown(wait=False)
    return future


def simulate(phys: PhysicsSpec | HasSpec, groups, episodes: Episode | list[Episode], cores: int | None = None,
             progress: bool = False, workers: int | None = None, engine_log: list | None = None,
             start: Snapshot | None = None, until: int | None = None, controller: str = "native",
             stats: dict | None = None, device=None, outcomes: bool = False, world=None):
    """`Physics.simulate_many(..., backend="c")`: every (policy, policy_axis) of `groups` on every episode of
    `episodes` (leading axis) in one lockstep; a list of `runner.Result`s of numpy arrays, one per group.
    `episodes` may instead be a list of batches, one per group (of one length, any sizes): group g runs on its own.
    `world`: the episodes' worlds (`gsp_jax.physics.world.World`, the episodes' leading axis; a list, one per group,
    where `episodes` is; None: the nominal world), hidden from the controller and the policies.

    Between two decisions the lockstep's episodes run as `workers` chunks of rows side by side (threads), each
    chunk's whole segment one call of native code (`native.segment`: the controller's ticks and `mj_step`,
    without Python's lock). Default: one chunk a core (at most `cores`, default all).
    `controller="jax"`: the JAX controller (`Physics.tick`, one XLA call a tick and chunk) instead of its native
    twin: the reference the native one is measured against (tests/test_native.py).
    `device` (a `jax.Device` or a platform name, e.g. "cpu"; default JAX's default device): where the decisions'
    programs run (cheap policies decide faster on a CPU than a GPU answers a call).
    `engine_log` (a list, one worker only): every step's states are appended to it (`Engine.log`; `engine_alone`
    replays them to time the engine alone). `stats` (a dict): its "steps" grows by the physics steps taken.

    `outcomes`: per group only (fell (R,), angle error (R,) [deg], actions (R, T)), numpy, instead of `Result`s.
    `until`: stop at the start of segment `until` (before its decision) and return the lockstep's `Snapshot`
    instead of results. `start`: continue from such a snapshot (rows: groups x episodes, the same order) instead
    of from the episodes' start; with the same groups, episodes and controller the continuation is the original
    run's, bit for bit, at any row count (tests/test_physics.py), so a snapshot's rows can be branched under
    other policies."""
    one = episodes[0] if isinstance(episodes, (list, tuple)) else episodes
    M = sum(int(np.shape(e.mass)[0]) for e in episodes) if isinstance(episodes, (list, tuple)) \
        else len(groups) * int(np.shape(one.mass)[0])
    cores = available_cores() if cores is None else cores
    workers = max(1, min(cores, M)) if workers is None else max(1, min(workers, M))
    spec = of(phys)
    run = _Lockstep(spec, groups, episodes, workers, engine_log, start, controller, device, world)
    end = one.n_steps + spec.n_hold
    if until is not None and not run.segment <= until <= end:
        raise ValueError(f"until must be a segment in {run.segment}..{end}, got {until!r}")
    run.advance(end if until is None else until, progress)
    if stats is not None:
        stats["steps"] = stats.get("steps", 0) + sum(run.steps)
    out = run.snapshot() if until is not None else run.results(outcomes)
    run.engine.release()
    return out


def engine_alone(phys: PhysicsSpec | HasSpec, episodes: Episode, log: list) -> tuple[float, int]:
    """(steps / s of `mujoco.mj_step` on one core, steps) over the states of an engine log (`simulate(...,
    engine_log=log)` on `episodes`): every logged state is loaded into its episode's own model and data and
    stepped once; only `mj_step` is timed. The engine's own limit on this machine, for the same steps."""
    spec = of(phys)
    scene = spec.scene
    fields = jax.device_get(jax.vmap(scene.episode_fields)(episodes))
    eng = Engine(scene, fields, np.tile(spec.mj_model.qpos0, (int(np.shape(episodes.mass)[0]), 1)))
    busy, steps = 0.0, 0
    for ids, states, pedestals in log:
        for e, state, ped in zip(ids, states, pedestals):
            m, d = eng.models[e], eng.datas[e]
            m.geom_pos[scene.pedestal_geoms] = ped
            mujoco.mj_setState(m, d, state, eng._spec)
            t0 = time.perf_counter()
            mujoco.mj_step(m, d)
            busy += time.perf_counter() - t0
            steps += 1
    return steps / busy, steps
