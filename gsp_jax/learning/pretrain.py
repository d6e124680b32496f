"""DP behaviour-cloning pretraining (the paper's Sec. IV-D): the DP solutions of the training episodes as a
supervised data set -- every discrete state (grasp, waypoint) reachable from the episode's start, its
observation, the DP-optimal action (actor: cross-entropy) and the DP-optimal value (critic: regression) --
trained with optax; PPO then starts from these weights.

    data = dp_dataset(surrogate, episodes, tables)          # stacked episodes and their dp.Tables
    params, history = pretrain(networks, data, BCConfig(), key)
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from tqdm.auto import tqdm

from gsp_jax.planning import dp
from gsp_jax.surrogate import reward as reward_lib
from gsp_jax.planning.dp import table_state
from gsp_jax.surrogate.observation import observation
from gsp_jax.ppo import networks as nets
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate.step import Surrogate


@struct.dataclass
class Dataset:
    obs: jax.Array  # (N, obs_size) observation of a discrete state
    action: jax.Array  # (N,) int32, the DP-optimal action (the first of equal optima)
    value: jax.Array  # (N,) DP-optimal reward-to-go [reward units]
    optimal: jax.Array  # (N, A) bool, every action whose Q equals the optimum (within 1e-6): ties
    episode: jax.Array  # (N,) int32 episode index
    t: jax.Array  # (N,) int32 waypoint

    @property
    def size(self) -> int:
        return int(self.action.shape[0])


@dataclasses.dataclass(frozen=True)
class BCConfig:
    epochs: int = 300
    batch_size: int = 512
    learning_rate: float = 1e-3
    value_coef: float = 1.0  # weight of the critic's MSE against the actor's cross-entropy
    reward_scale: float = 0.1  # critic targets are value * reward_scale: use PPOConfig.reward_scale

    def __post_init__(self):
        for name in ("epochs", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"BCConfig.{name}: must be >= 1, got {getattr(self, name)}")


def reachable(table: dp.Table, start_grasp: jax.Array) -> jax.Array:
    """(G, T) bool: grasp g can be in force at waypoint t, starting from `start_grasp` at 0, through transitions
    that do not end the episode (any actions)."""
    n_g, _, n_t = table.reward.shape
    first = jnp.zeros(n_g, bool).at[start_grasp].set(True)

    def forward(reach, t):
        live = reach[:, None] & ~table.terminal[:, :, t]  # (G, A)
        nxt = jnp.zeros(n_g, bool).at[table.next_grasp.ravel()].max(live.ravel())
        return nxt, reach

    _, reach = jax.lax.scan(forward, first, jnp.arange(n_t))
    return reach.T


def q_values(table: dp.Table, solution: dp.Solution) -> jax.Array:
    """(G, A, T) optimal action values Q(g, a, t) = reward + V(g', t + 1) unless the transition is terminal (with
    the learned term, V weighted by the chance to hold: `reward.backed_up`)."""
    n_t = table.reward.shape[2]
    v_next = solution.value[table.next_grasp][:, :, 1 : n_t + 1]  # (G, A, T)
    return reward_lib.backed_up(table.reward, table.fall_risk, table.terminal, v_next)


def dp_dataset(surrogate: Surrogate, episodes: Episode, tables: dp.Table) -> Dataset:
    """The behaviour-cloning set of a stacked episode set (leaves (N, ...)) and its tables."""
    space = surrogate.space

    @jax.jit
    def per_episode(ep, table):
        sol = dp.backup(table, ep.start_grasp)
        n_g, n_t = sol.policy.shape
        grid_g, grid_t = jnp.meshgrid(jnp.arange(n_g), jnp.arange(n_t), indexing="ij")
        state_obs = lambda g, t: observation(space, table_state(ep, table, g, t))  # noqa: E731
        obs = jax.vmap(jax.vmap(state_obs))(grid_g, grid_t)  # (G, T, D)
        q = q_values(table, sol)  # (G, A, T)
        optimal = jnp.moveaxis(q >= sol.value[:, None, :n_t] - 1e-6, 1, 2)  # (G, T, A)
        return obs, sol.policy, sol.value[:, :n_t], optimal, reachable(table, ep.start_grasp), grid_t

    parts = []
    for i in range(episodes.waypoints.shape[0]):
        ep, table = jax.tree.map(lambda x: x[i], (episodes, tables))
        obs, action, value, optimal, reach, t = map(np.asarray, per_episode(ep, table))
        keep = reach
        parts.append((obs[keep], action[keep], value[keep], optimal[keep], np.full(keep.sum(), i), t[keep]))
    cat = [np.concatenate(p) for p in zip(*parts)]
    return Dataset(
        obs=jnp.asarray(cat[0], jnp.float32),
        action=jnp.asarray(cat[1], jnp.int32),
        value=jnp.asarray(cat[2], jnp.float32),
        optimal=jnp.asarray(cat[3]),
        episode=jnp.asarray(cat[4], jnp.int32),
        t=jnp.asarray(cat[5], jnp.int32),
    )


def metrics(networks: nets.Networks, params: nets.Params, data: Dataset, reward_scale: float) -> dict:
    """Action accuracy (exact DP action; any optimal action), and the critic's RMSE [reward units]."""
    pred = nets.mode(networks.logits(params, data.obs))
    value = networks.value(params, data.obs) / reward_scale
    return {
        "accuracy": jnp.mean(pred == data.action),
        "optimal_accuracy": jnp.mean(jnp.take_along_axis(data.optimal, pred[:, None], 1)),
        "value_rmse": jnp.sqrt(jnp.mean((value - data.value) ** 2)),
    }


def pretrain(
    networks: nets.Networks, data: Dataset, config: BCConfig, key: jax.Array, progress: bool = True
) -> tuple[nets.Params, list[dict]]:
    """Fresh networks fitted to `data`: the normaliser set from its observations, then `epochs` of Adam over
    shuffled minibatches (each epoch one jitted `lax.scan`). Returns the params and per-epoch metrics."""
    k_init, key = jax.random.split(key)
    params = networks.update_normalizer(networks.init(k_init), data.obs)
    n = data.size
    batch = min(config.batch_size, n)
    n_batches = n // batch
    optimizer = optax.adam(config.learning_rate)
    trainable = {"actor": params.actor, "critic": params.critic}
    opt_state = optimizer.init(trainable)

    def loss_fn(trainable, obs, action, target):
        p = params.replace(**trainable)
        ce = -jnp.mean(nets.log_prob(networks.logits(p, obs), action))
        mse = jnp.mean((networks.value(p, obs) - target) ** 2)
        return ce + config.value_coef * mse, (ce, mse)

    @jax.jit
    def epoch(trainable, opt_state, k):
        idx = jax.random.permutation(k, n)[: n_batches * batch].reshape(n_batches, batch)

        def step(carry, i):
            trainable, opt_state = carry
            grads, aux = jax.grad(loss_fn, has_aux=True)(
                trainable, data.obs[i], data.action[i], data.value[i] * config.reward_scale
            )
            updates, opt_state = optimizer.update(grads, opt_state, trainable)
            return (optax.apply_updates(trainable, updates), opt_state), aux

        (trainable, opt_state), (ce, mse) = jax.lax.scan(step, (trainable, opt_state), idx)
        return trainable, opt_state, jnp.mean(ce), jnp.mean(mse)

    evaluate = jax.jit(lambda tr: metrics(networks, params.replace(**tr), data, config.reward_scale))
    history = []
    bar = tqdm(range(config.epochs), disable=not progress, desc="DP pretraining", unit="epoch")
    for e in bar:
        key, k = jax.random.split(key)
        trainable, opt_state, ce, mse = epoch(trainable, opt_state, k)
        if (e + 1) % 10 == 0 or e + 1 == config.epochs:
            m = {k: float(v) for k, v in evaluate(trainable).items()}
            history.append({"epoch": e + 1, "cross_entropy": float(ce), "value_mse": float(mse), **m})
            bar.set_postfix(acc=f"{m['accuracy']:.3f}", v_rmse=f"{m['value_rmse']:.2f}", refresh=False)
    return params.replace(**trainable), history
