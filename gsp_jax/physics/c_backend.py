"""The C MuJoCo backend of the runner: the same controller, decisions and outcome as the MJX runner
(`runner.Physics.simulate`), with the physics stepped by `mujoco.mj_step` on the CPU. It is the reference every
MJX figure can be checked against, and for small batches the faster engine (C MuJoCo steps this scene ~20x faster
per core than MJX on an H100: ../shared/ENVIRONMENT.md).

The episodes of a batch advance in lockstep: at each control tick one jitted, vmapped JAX call reads every
episode's state and returns every episode's motor commands (and the status of the tick before), then each
episode's C model steps `control_every` times. So the per-tick JAX dispatch is paid once per batch, not per
episode.
"""
from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from gsp_jax.physics.scene import AWAY
from gsp_jax.scenario import Episode

_LOCK = threading.Lock()  # policies may run side by side in threads (`experiments fig4b --jobs`)


def _compiled(phys, policy_axis):
    """(start, decide, tick, check, episode_fields), jitted once per `Physics`: only `decide` depends on how the
    policy is batched, so every policy shares the others' compiled programs. Threads (policies run side by side)
    take turns here, so they share one set."""
    scene = phys.scene

    def observe(raw):
        return jax.vmap(scene.observe)(*raw)

    with _LOCK:
        if "c" not in phys._jitted:

            def tick(cs, raw, episodes, j):
                obs = observe(raw)
                status = jax.vmap(phys.check, in_axes=(0, 0, None))(obs, episodes, j - 1)
                ctrl, ext, cs = jax.vmap(phys.tick, in_axes=(0, 0, 0, None))(cs, obs, episodes, j)
                return status, ctrl, ext, cs

            def check(raw, episodes, j):
                return jax.vmap(phys.check, in_axes=(0, 0, None))(observe(raw), episodes, j)

            shared = (jax.jit(jax.vmap(phys.start)), jax.jit(tick), jax.jit(check),
                      jax.jit(jax.vmap(scene.episode_fields)))
            phys._jitted["c"] = tuple(map(_compiled_once, shared))
        key = ("c-decide", policy_axis)
        if key not in phys._jitted:

            def decide(policy, cs, raw, grasp, episodes, k):
                return jax.vmap(phys.decide, in_axes=(policy_axis, 0, 0, 0, 0, None))(policy, cs, observe(raw), grasp,
                                                                                      episodes, k)

            phys._jitted[key] = jax.jit(decide)
        start, tick, check, episode_fields = phys._jitted["c"]
        return start, phys._jitted[key], tick, check, episode_fields


def _compiled_once(fn):
    """`fn` (jitted) whose first call runs in one thread at a time: policies simulated side by side in threads
    wait for its one compilation instead of each compiling it."""
    lock, warm = threading.Lock(), []

    def call(*args):
        if not warm:
            with lock:
                out = jax.block_until_ready(fn(*args))
                warm.append(True)
            return out
        return fn(*args)

    return call


def simulate(phys, policy, episodes: Episode, policy_axis: int | None = None, progress: bool = False):
    """`Physics.simulate_batch(..., backend="c")`: a `runner.Result` of numpy arrays, batch axis first."""
    start, decide, tick, check, episode_fields = _compiled(phys, policy_axis)
    scene, c = phys.scene, phys.config
    N, T, n = int(np.shape(episodes.mass)[0]), episodes.n_steps, phys.n_segment
    K = phys.n_ticks(T)
    cpu = jax.devices("cpu")[0]
    on_cpu = lambda tree: jax.device_put(tree, cpu)  # noqa: E731  (the per-tick program follows its inputs there)
    on_default = lambda tree: jax.device_put(tree, jax.devices()[0])  # noqa: E731
    episodes_cpu = on_cpu(episodes)
    fields = jax.device_get(episode_fields(episodes))
    qpos0, cs = start(episodes)
    cs = on_cpu(cs)
    qpos0 = np.asarray(qpos0, np.float64)
    models, datas = [], []
    field_list = [jax.tree.map(lambda x: x[e], fields) for e in range(N)]
    for e in range(N):
        m = scene.c_model(field_list[e])
        d = mujoco.MjData(m)
        d.qpos[:] = qpos0[e]
        mujoco.mj_forward(m, d)
        models.append(m)
        datas.append(d)

    def raw():
        return tuple(np.stack([getattr(d, f) for d in datas]).astype(np.float32) for f in ("qpos", "qvel", "qfrc_bias"))

    grasp = jnp.asarray(episodes.start_grasp, jnp.int32)
    fell = np.zeros(N, bool)
    fall_tick = np.full(N, -1, np.int32)
    angle, perr = np.zeros((N, K), np.float32), np.zeros((N, K), np.float32)
    qpos_trace = np.zeros((N, K, phys.model.nq), np.float32)
    actions, grasps = [], []
    state = raw()
    segments = range(T + phys.n_hold)
    if progress:
        from tqdm.auto import tqdm

        segments = tqdm(segments, desc="C MuJoCo segments", leave=False)

    def record(j, status, now):
        a, p, f = (np.asarray(x) for x in status)
        new_fall = f & ~fell
        fall_tick[new_fall] = j
        fell[:] |= f
        angle[:, j], perr[:, j] = a, p
        prev = qpos_trace[:, j - 1] if j > 0 else qpos0.astype(np.float32)
        qpos_trace[:, j] = np.where((fell & (new_fall | (fall_tick < j)))[:, None], prev, now)

    for k in segments:
        action, grasp, cs = decide(policy, on_default(cs), state, grasp, episodes, k)
        cs = on_cpu(cs)
        actions.append(np.asarray(action))
        grasps.append(np.asarray(grasp))
        for i in range(n):
            j = k * n + i
            drop = float(scene.pedestal_drop(j * c.tick, xp=np))
            if drop > AWAY:  # sinking (afterwards they stay away)
                for e in np.flatnonzero(~fell):
                    scene.c_pedestals(models[e], field_list[e], drop)
            status, ctrl, ext, cs = tick(cs, state, episodes_cpu, j)
            if j > 0:
                record(j - 1, status, state[0])
            ctrl, ext = np.asarray(ctrl, np.float64), np.asarray(ext, np.float64)
            for e in np.flatnonzero(~fell):
                d = datas[e]
                d.ctrl[:] = ctrl[e]
                d.xfrc_applied[scene.tool_body] = ext[e]
                for _ in range(c.control_every):
                    mujoco.mj_step(models[e], d)
            state = raw()
    record(K - 1, check(state, episodes_cpu, K - 1), state[0])
    actions, grasps = np.stack(actions, 1)[:, :T], np.stack(grasps, 1)[:, :T]
    res = phys.result(jnp.asarray(actions), jnp.asarray(grasps), jnp.asarray(angle), jnp.asarray(perr),
                      jnp.asarray(qpos_trace), jnp.asarray(fell), jnp.asarray(fall_tick), T)
    return jax.device_get(res)
