"""The PPO training loop: every iteration one jitted function (a `lax.scan` rollout of `unroll` steps in
`n_envs` vmapped environments, GAE, `epochs` x `minibatches` Adam steps), validation of the deterministic
policy, early stop on the validation return, and orbax checkpoints from which a killed run resumes to the same
result, bit for bit, as an uninterrupted one.

    trainer = Trainer(env, networks, PPOConfig(), eval_envs={"val": val_env, "train_greedy": train_env_greedy})
    result = train(trainer, seed=0, params=pretrained, checkpoint_dir="runs/ppo_seed0")
    result.policy                                   # the best validation Params; result.history: per iteration

Data-parallel on several devices (`devices`, default every device of every process): the environments are split
over them (a mesh axis), each device steps its share and shuffles its own part of the batch, and every minibatch
takes an equal slice from each device, so its gradient is the mean over all of them (XLA's all-reduce); one
optimiser state, the parameters on every device. The same seed and device count give the same curve; one device
runs the single-device program unchanged.

Rewards enter the update multiplied by `reward_scale`, so the critic predicts returns in those units; returns
reported in `history` are in reward units. Starting from pretrained `params` keeps the weights and the
normaliser but starts a fresh Adam state (the pretraining optimiser's moments belong to another objective); run
it with `update_normalizer=False`, since folding PPO's rollouts into the statistics moves the pretrained
network's inputs under it and undoes the pretraining (docs/rl.md).
"""
from __future__ import annotations

import dataclasses
import json
import pathlib
import time
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from gsp_jax.core import files
from gsp_jax.ppo import losses
# load_policy and save_policy re-exported: tests/test_ppo.py calls them as `train.save_policy`/`train.load_policy`
from gsp_jax.ppo.checkpoint import load_policy, save_policy, uncommitted  # noqa: F401
from gsp_jax.ppo.config import PPOConfig
from gsp_jax.ppo import networks as nets


@struct.dataclass
class TrainState:
    """Everything a run needs to continue: checkpointed whole."""

    params: nets.Params
    opt_state: Any
    env_state: Any  # brax State of the n_envs environments
    key: jax.Array
    iteration: jax.Array  # () int32, iterations done
    best_params: nets.Params  # the best validated policy so far
    best_return: jax.Array  # () its validation return
    evals_since_best: jax.Array  # () int32


@dataclasses.dataclass
class TrainResult:
    state: TrainState
    history: list[dict]  # one record per iteration (and iteration 0): returns, losses, env steps, wall time

    @property
    def policy(self) -> nets.Params:
        return self.state.best_params

    @property
    def stopped_early(self) -> bool:
        """The validation return stopped improving (patience ran out) before max_iterations."""
        return bool(self.history) and bool(self.history[-1].get("early_stop", False))


ENV_AXIS = "envs"  # the mesh axis the environments are split over


class Trainer:
    """PPO on a brax-style env (one env; vmapped here). `eval_envs` (name -> env without auto-reset) are rolled out
    deterministically from every episode's start; the first is the validation set used for early stopping.
    `devices`: the environments split over these (default `jax.devices()`, every process's); `n_envs` and a
    minibatch must divide by their number."""

    def __init__(self, env, networks: nets.Networks, config: PPOConfig, eval_envs: dict[str, Any], devices=None):
        devices = list(jax.devices() if devices is None else devices)
        self.n_devices = len(devices)
        if config.n_envs % self.n_devices or (config.n_envs * config.unroll // config.minibatches) % self.n_devices:
            raise ValueError(f"PPOConfig.n_envs: {config.n_envs} environments (minibatches of "
                             f"{config.n_envs * config.unroll // config.minibatches}) do not split evenly over "
                             f"{self.n_devices} devices")
        self.mesh = Mesh(np.array(devices), (ENV_AXIS,)) if self.n_devices > 1 else None
        if not eval_envs:
            raise ValueError("eval_envs: need at least one (the validation set)")
        if "train" in eval_envs:
            raise ValueError("eval_envs: the name 'train' is taken (history's train_return is the stochastic return)")
        self.env, self.networks, self.config, self.eval_envs = env, networks, config, dict(eval_envs)
        self.val_name = next(iter(self.eval_envs))  # the early-stop set (jit returns dicts in sorted key order)
        self.optimizer = optax.chain(
            optax.clip_by_global_norm(config.max_grad_norm),
            optax.inject_hyperparams(optax.adam)(learning_rate=config.learning_rate),  # set per iteration
        )
        self.iteration = jax.jit(self._iteration)
        self.evaluate = jax.jit(self._evaluate)
        self._record = jax.jit(self._record_eval)

    # --------------------------------------------------------------------------------------- devices
    def _constrain(self, tree, axis: int = 0):
        """`tree` with its leaves split over the devices along `axis` (unchanged on one device)."""
        if self.mesh is None:
            return tree
        return jax.lax.with_sharding_constraint(tree, NamedSharding(self.mesh, PartitionSpec(*[None] * axis, ENV_AXIS)))

    # ------------------------------------------------------------------------------------------ state
    def init(self, key: jax.Array, params: nets.Params | None = None) -> TrainState:
        """The state before the first iteration; on several devices made in one program (every process the same),
        the environments split over the devices and the rest on every device."""
        return self._init(key, params) if self.mesh is None else jax.jit(self._init)(key, params)

    def _init(self, key: jax.Array, params: nets.Params | None) -> TrainState:
        k_params, k_env, key = jax.random.split(key, 3)
        params = self.networks.init(k_params) if params is None else params
        env_state = jax.vmap(self.env.reset)(jax.random.split(k_env, self.config.n_envs))
        if self.mesh is not None:  # inside `init`'s program
            everywhere = NamedSharding(self.mesh, PartitionSpec())
            params = jax.lax.with_sharding_constraint(params, everywhere)
            key = jax.lax.with_sharding_constraint(key, everywhere)
            env_state = self._constrain(env_state)
        return TrainState(
            params=params,
            opt_state=self.optimizer.init(_trainable(params)),
            env_state=env_state,
            key=key,
            iteration=jnp.zeros((), jnp.int32),
            best_params=params,
            best_return=jnp.array(-jnp.inf, jnp.float32),
            evals_since_best=jnp.zeros((), jnp.int32),
        )

    # -------------------------------------------------------------------------------------- iteration
    def _rollout(self, params: nets.Params, env_state, key: jax.Array):
        """`unroll` steps of every env under the sampling policy: the last env state and the trajectory's
        (obs, action, logp, value, scaled reward, done, episode return, hold), each (U, B, ...)."""
        cfg, networks = self.config, self.networks

        def env_step(env_state, k):
            logits = networks.logits(params, env_state.obs)
            action = nets.sample(k, logits)
            nxt = jax.vmap(self.env.step)(env_state, action)
            out = (
                env_state.obs,
                action,
                nets.log_prob(logits, action),
                networks.value(params, env_state.obs),
                nxt.reward * cfg.reward_scale,
                nxt.done,
                nxt.metrics["episode_return"],
                nxt.info["hold"],
            )
            return nxt, out

        return jax.lax.scan(env_step, env_state, jax.random.split(key, cfg.unroll))

    def _sgd(self, params: nets.Params, opt_state, batch: losses.Batch, key: jax.Array, lr):
        """`epochs` passes of `minibatches` Adam steps over the flattened batch (stopped early by `target_kl`):
        the trainable parameters, the optimiser state and the steps' metrics."""
        cfg, networks = self.config, self.networks
        n = batch.action.shape[0]

        def loss_fn(trainable, mb):
            return losses.ppo_loss(
                params.replace(**trainable), networks, mb, cfg.clip, cfg.vf_coef, cfg.ent_coef
            )

        def sgd_step(carry, mb):
            trainable, opt_state, stopped = carry
            (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(trainable, mb)
            if cfg.target_kl is not None:  # the KL of the params before this step, on this minibatch
                stopped = stopped | (metrics["approx_kl"] > cfg.target_kl)
            updates, new_opt_state = self.optimizer.update(grads, opt_state, trainable)
            keep = lambda new, old: jnp.where(stopped, old, new)  # noqa: E731
            trainable = jax.tree.map(keep, optax.apply_updates(trainable, updates), trainable)
            opt_state = jax.tree.map(keep, new_opt_state, opt_state)
            metrics["sgd_steps"] = (~stopped).astype(jnp.float32)
            return (trainable, opt_state, stopped), metrics

        def epoch(carry, k):
            if self.mesh is None:
                perm = jax.random.permutation(k, n)
                mbs = jax.tree.map(lambda x: x[perm].reshape(cfg.minibatches, -1, *x.shape[1:]), batch)
            else:  # each device shuffles its own rows; minibatch m takes each device's m-th slice
                D, M = self.n_devices, cfg.minibatches
                perms = jax.vmap(lambda kd: jax.random.permutation(kd, n // D))(jax.random.split(k, D))

                def shuffle(x):
                    local = jax.vmap(lambda xd, p: xd[p])(x.reshape(D, n // D, *x.shape[1:]), perms)
                    local = local.reshape(D, M, n // (D * M), *x.shape[1:]).swapaxes(0, 1)
                    return local.reshape(M, n // M, *x.shape[1:])

                mbs = self._constrain(jax.tree.map(shuffle, self._constrain(batch)), axis=1)
            return jax.lax.scan(sgd_step, carry, mbs)

        clip_state, adam_state = opt_state
        adam_state = adam_state._replace(hyperparams={**adam_state.hyperparams, "learning_rate": jnp.asarray(
            lr, jnp.float32)})
        (trainable, opt_state, _), metrics = jax.lax.scan(
            epoch, (_trainable(params), (clip_state, adam_state), jnp.array(False)), jax.random.split(key, cfg.epochs)
        )
        return trainable, opt_state, metrics

    def _iteration(self, ts: TrainState) -> tuple[TrainState, dict]:
        cfg, networks = self.config, self.networks
        key, k_roll, k_sgd = jax.random.split(ts.key, 3)
        params = ts.params
        env_state, (obs, action, logp, value, reward, done, ep_return, hold) = self._rollout(params, ts.env_state,
                                                                                               k_roll)
        bootstrap = networks.value(params, env_state.obs)
        advantage, target = losses.gae(reward, value, done, bootstrap, cfg.gamma, cfg.gae_lambda, hold)
        batch = losses.Batch(obs, action, logp, value, advantage, target)
        if self.mesh is None:
            batch = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), batch)  # (U * B, ...)
        else:  # environment-major, (B * U, ...): each device's environments stay one block of rows
            batch = jax.tree.map(lambda x: x.swapaxes(0, 1).reshape(-1, *x.shape[2:]), batch)
        lr = cfg.learning_rate_at(ts.iteration * cfg.epochs * cfg.minibatches)
        trainable, opt_state, metrics = self._sgd(params, ts.opt_state, batch, k_sgd, lr)
        sgd_steps = jnp.sum(metrics.pop("sgd_steps"))
        params = params.replace(**trainable)
        if cfg.update_normalizer:
            params = networks.update_normalizer(params, obs)
        finished = jnp.sum(done)
        metrics = jax.tree.map(jnp.mean, metrics)
        metrics.update(
            train_return=jnp.sum(jnp.where(done, ep_return, 0.0)) / jnp.maximum(finished, 1),
            episodes=finished,
            sgd_steps=sgd_steps,  # Adam steps applied (epochs x minibatches unless target_kl stopped them)
            learning_rate=lr,
        )
        ts = ts.replace(params=params, opt_state=opt_state, env_state=self._constrain(env_state), key=key,
                        iteration=ts.iteration + 1)
        return ts, metrics

    # ------------------------------------------------------------------------------------- validation
    def _evaluate(self, params: nets.Params) -> dict[str, jax.Array]:
        """Deterministic returns (N,) of the policy on every episode of each evaluation env."""
        return {name: greedy_returns(env, self.networks, params) for name, env in self.eval_envs.items()}

    def _record_eval(self, ts: TrainState, val_return: jax.Array) -> TrainState:
        better = val_return > ts.best_return
        return ts.replace(
            best_params=jax.tree.map(lambda new, old: jnp.where(better, new, old), ts.params, ts.best_params),
            best_return=jnp.where(better, val_return, ts.best_return),
            evals_since_best=jnp.where(better, 0, ts.evals_since_best + 1),
        )


def greedy_returns(env, networks: nets.Networks, params: nets.Params) -> jax.Array:
    """(Expected) return (N,) of the deterministic policy on each of env's N episodes, from its start
    (env.auto_reset off)."""
    if env.auto_reset:
        raise ValueError("env.auto_reset: evaluation needs an env without auto-reset (GraspEnv(..., auto_reset=False))")

    def one(index):
        def step(state, _):
            action = nets.mode(networks.logits(params, state.obs))
            return env.step(state, action), None

        final, _ = jax.lax.scan(step, env.reset_to(index), None, length=env.n_steps)
        return final.info["return"]

    return jax.vmap(one)(jnp.arange(env.n_episodes))


def _trainable(params: nets.Params) -> dict:
    return {"actor": params.actor, "critic": params.critic}


# ------------------------------------------------------------------------------------------------ the loop
def train(
    trainer: Trainer,
    seed: int,
    params: nets.Params | None = None,
    checkpoint_dir: str | pathlib.Path | None = None,
    progress: bool = True,
    stop_after: int | None = None,
    stop_when=None,
) -> TrainResult:
    """Run PPO to `max_iterations` or an early stop. With `checkpoint_dir`, a run saves there every
    `checkpoint_every` iterations and, started again, resumes from its latest checkpoint. `stop_after` ends this
    call after that many iterations in total (with a checkpoint there; for time-sliced jobs); `stop_when(record)`
ends it after the first iteration whose history record satisfies it (e.g. a target return)."""
    if checkpoint_dir is None:
        return _train(trainer, seed, params, None, progress, stop_after, stop_when)
    with files.folder_lock(checkpoint_dir):  # a second run on the same folder is refused, naming it
        return _train(trainer, seed, params, checkpoint_dir, progress, stop_after, stop_when)


def _train(trainer, seed, params, checkpoint_dir, progress, stop_after, stop_when) -> TrainResult:
    cfg = trainer.config
    ts = trainer.init(jax.random.PRNGKey(seed), params)
    history: list[dict] = []
    manager = _manager(checkpoint_dir, trainer, seed) if checkpoint_dir is not None else None
    if manager is not None and manager.latest_step() is not None:
        ts, history = _restore(manager, ts)
    wall0 = history[-1]["wall_s"] if history else 0.0
    t0 = time.perf_counter()
    env_steps_per_iter = cfg.n_envs * cfg.unroll
    if not history:  # iteration 0: the starting policy
        ts, record = _validate(trainer, ts, {"iteration": 0})
        history.append({**record, "env_steps": 0, "wall_s": 0.0, "max_iterations": cfg.max_iterations})

    start = int(ts.iteration)
    last = cfg.max_iterations if stop_after is None else min(cfg.max_iterations, stop_after)
    bar = tqdm(total=cfg.max_iterations, initial=start, disable=not progress, desc=f"PPO seed {seed}", unit="it")
    for it in range(start + 1, last + 1):
        if cfg.patience and int(ts.evals_since_best) >= cfg.patience:
            history[-1]["early_stop"] = True
            break
        ts, metrics = trainer.iteration(ts)
        record = {"iteration": it, **{k: float(v) for k, v in metrics.items()}}
        if it % cfg.eval_every == 0 or it == cfg.max_iterations:
            ts, record = _validate(trainer, ts, record)
        record.update(
            env_steps=it * env_steps_per_iter, wall_s=wall0 + time.perf_counter() - t0,
            max_iterations=cfg.max_iterations,
        )
        history.append(record)
        bar.update(1)
        bar.set_postfix(
            train=f"{record['train_return']:.2f}", val=f"{float(ts.best_return):.2f}", refresh=False
        )
        if manager is not None and (it % cfg.checkpoint_every == 0 or it == last):
            _save(manager, it, ts, history)
        if stop_when is not None and stop_when(record):
            break
    bar.close()
    if manager is not None:
        if manager.latest_step() != int(ts.iteration):
            _save(manager, int(ts.iteration), ts, history)
        manager.wait_until_finished()
        manager.close()
    return TrainResult(state=ts, history=history)


def _validate(trainer: Trainer, ts: TrainState, record: dict) -> tuple[TrainState, dict]:
    returns = trainer.evaluate(ts.params)
    for name in trainer.eval_envs:
        record[f"{name}_return"] = float(jnp.mean(returns[name]))
    ts = trainer._record(ts, jnp.mean(returns[trainer.val_name]))
    return ts, record


def _restore(manager: ocp.CheckpointManager, ts: TrainState) -> tuple[TrainState, list[dict]]:
    """The latest intact checkpoint: a step that cannot be read (a crash truncated it) is reported with its path and
    the previous step is tried; ValueError naming the folder if none can be read."""
    args = ocp.args.Composite(state=ocp.args.StandardRestore(ts), history=ocp.args.JsonRestore())
    for step in sorted(manager.all_steps(), reverse=True):
        try:
            restored = manager.restore(step, args=args)
            history = list(restored.history)
            if not history or history[-1].get("iteration") != step:
                raise ValueError(f"its history ends at {history[-1].get('iteration') if history else None}")
        except Exception as e:  # noqa: BLE001 -- any unreadable step: orbax, tensorstore or JSON errors
            warnings.warn(f"checkpoint {manager.directory / str(step)} cannot be read ({type(e).__name__}: "
                          f"{str(e).splitlines()[0][:200]}); resuming from the step before it", stacklevel=3)
            continue
        return uncommitted(restored.state), history
    raise ValueError(f"checkpoint_dir {manager.directory}: no step can be read ({sorted(manager.all_steps())}); "
                     "move the folder away to start again")


def _differences(old, new, prefix: str = "") -> list[str]:
    """'field: old -> new' for every leaf where two JSON-like configs differ."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [d for k in sorted(set(old) | set(new))
                for d in _differences(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else k)]
    return [] if old == new else [f"{prefix}: {old!r} -> {new!r}"]


def _manager(directory, trainer: Trainer, seed: int) -> ocp.CheckpointManager:
    directory = pathlib.Path(directory).absolute()
    directory.mkdir(parents=True, exist_ok=True)
    meta = {"seed": seed, "config": _jsonable(dataclasses.asdict(trainer.config)),
            "networks": _jsonable(dataclasses.asdict(trainer.networks.config))}
    hand = trainer.env.surrogate.hand
    if hand.source:  # the model it trains for: a run is never resumed for another one
        model = trainer.env.surrogate.model
        meta["model"] = {"name": model.name, "digest": model.digest}
    meta_file = directory / "run.json"
    if meta_file.exists():
        old = files.read_json(meta_file)
        for field in meta:
            if old.get(field) != meta[field]:
                diff = "; ".join(_differences(old.get(field), meta[field], field))
                raise ValueError(f"checkpoint_dir {directory}: holds a run with a different {field} ({diff}); use "
                                 "another directory to start a new run")
    else:
        files.write_json(meta_file, meta)
    options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True, enable_async_checkpointing=False)
    return ocp.CheckpointManager(directory / "checkpoints", options=options)


def _save(manager: ocp.CheckpointManager, step: int, ts: TrainState, history: list[dict]) -> None:
    manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(ts), history=ocp.args.JsonSave(history)))


def _jsonable(x):
    return json.loads(json.dumps(x, default=lambda o: list(o) if isinstance(o, tuple) else str(o)))
