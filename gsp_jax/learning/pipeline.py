"""The paper's training pipeline: PPO on the training episodes (the environment cycles them), validated on the
validation set with the deterministic policy and early-stopped there, optionally starting from behaviour cloning of
the training episodes' DP solutions. Steps are exact table lookups of the surrogate (`gsp_jax.learning.env`).

    s = setup("quick")                                    # environments over tables, networks, configs, DP references
    result = run_seed(s, seed=0, mode="dp", out_dir=path)  # BC + PPO, resumable from path/checkpoints
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from gsp_jax.planning import dp, policies
from gsp_jax.core import files
from gsp_jax.learning import pretrain
from gsp_jax.model import scenario
from gsp_jax.learning.env import GraspEnv
from gsp_jax.planning.evaluation import dp_tables
from gsp_jax.ppo import networks as nets
from gsp_jax.ppo import train as ppo
from gsp_jax.surrogate.step import Surrogate

PRESETS = {  # quick: sized for a CPU; full: the GPU run behind the README's numbers
    "quick": dict(n_envs=256, hidden=(256, 256, 256), iterations=100, bc_epochs=300, minibatches=4),
    "full": dict(n_envs=2048, hidden=(256, 256, 256), iterations=300, bc_epochs=300, minibatches=8),
}



@dataclasses.dataclass
class Setup:
    """Everything a training run needs, built once: environments over tables, networks, configs, DP references."""

    surrogate: Surrogate
    env: GraspEnv  # training: the 9 episodes, auto-reset
    eval_envs: dict  # "val" (early stop) and "train_greedy" (the training set), no auto-reset
    networks: nets.Networks
    ppo_config: ppo.PPOConfig
    bc_config: pretrain.BCConfig
    train_tables: dp.Table
    reference: dict


def setup(preset: str, iterations=None, envs=None, patience=None, table_cache=None, surrogate=None) -> Setup:
    """The training and validation environments, networks and configs of `preset` ("quick" | "full") for
    `surrogate` (None: `Surrogate()`, the default model), with the overrides given (PPO iterations, parallel
    environments, validations without improvement before stopping); the episodes' DP tables kept under
    `table_cache` (`evaluation.dp_tables`; None: built every time)."""
    if preset not in PRESETS:
        raise ValueError(f"setup: preset must be one of {sorted(PRESETS)}, got {preset!r}")
    p = PRESETS[preset]
    sur = surrogate or Surrogate()
    train_eps, val_eps = scenario.training_set(sur.model), scenario.validation_set(sur.model)
    train_tables = dp_tables(sur, "train", train_eps, cache=table_cache)
    val_tables = dp_tables(sur, "val", val_eps, cache=table_cache)
    train_batch, val_batch = scenario.stack(list(train_eps.values())), scenario.stack(list(val_eps.values()))
    env = GraspEnv(sur, train_batch, train_tables)
    eval_envs = {
        "val": GraspEnv(sur, val_batch, val_tables, auto_reset=False),
        "train_greedy": GraspEnv(sur, train_batch, train_tables, auto_reset=False),
    }
    cfg = ppo.PPOConfig(
        n_envs=envs or p["n_envs"],
        minibatches=p["minibatches"],
        max_iterations=iterations or p["iterations"],
        **({} if patience is None else {"patience": patience}),
    )
    networks = nets.make_networks(env.observation_size, env.action_size, nets.NetworkConfig(hidden=p["hidden"]))
    return Setup(
        surrogate=sur,
        env=env,
        eval_envs=eval_envs,
        networks=networks,
        ppo_config=cfg,
        bc_config=pretrain.BCConfig(epochs=p["bc_epochs"], reward_scale=cfg.reward_scale),
        train_tables=train_tables,
        reference=references(train_batch, train_tables, val_batch, val_tables),
    )


def references(train_batch, train_tables, val_batch, val_tables) -> dict:
    """Mean DP returns: optimal per episode, and the DP baseline (the nominal episode's optimal sequence,
    replayed open loop), on the training and validation sets."""
    sols = jax.vmap(dp.backup)(train_tables, train_batch.start_grasp)
    nominal_actions = sols.actions[0]  # the training set's first episode is the nominal one
    out = {}
    for name, batch, tables in (("train", train_batch, train_tables), ("val", val_batch, val_tables)):
        opt = jax.vmap(dp.backup)(tables, batch.start_grasp).ret
        base = jax.vmap(dp.sequence_return, (0, 0, None))(tables, batch.start_grasp, nominal_actions)
        out[name] = {"dp_optimal": float(jnp.mean(opt)), "dp_baseline": float(jnp.mean(base))}
    return out


def ppo_config(s: Setup, mode: str) -> ppo.PPOConfig:
    """From pretrained weights the observation normaliser stays as pretraining set it (see gsp_jax/ppo/train.py)."""
    return dataclasses.replace(s.ppo_config, update_normalizer=mode != "dp")


def pretrained(s: Setup, seed: int, progress: bool = True) -> tuple[nets.Params, dict]:
    """Behaviour cloning of the training episodes' DP solutions (seeded apart from PPO): params and a log."""
    data = pretrain.dp_dataset(s.surrogate, s.env.episodes, s.train_tables)
    params, history = pretrain.pretrain(s.networks, data, s.bc_config, jax.random.PRNGKey(1000 + seed), progress)
    return params, {"dataset_size": data.size, "history": history}


def run_seed(s: Setup, seed: int, mode: str, out_dir, progress: bool = True) -> ppo.TrainResult:
    """One seed: optional DP pretraining, then PPO (resuming from out_dir/checkpoints if present)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    params = None
    if mode == "dp":
        params, bc_log = pretrained(s, seed, progress)
        files.write_json(out_dir / "bc_history.json", bc_log, indent=None)
    trainer = ppo.Trainer(s.env, s.networks, ppo_config(s, mode), s.eval_envs)
    result = ppo.train(trainer, seed, params=params, checkpoint_dir=out_dir, progress=progress)
    files.write_json(out_dir / "history.json", result.history, indent=None)
    policies.save_network_policy(out_dir / "policy", result.policy, s.surrogate)  # with the model it is for
    return result
