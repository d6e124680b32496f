"""Actor and critic: 3-hidden-layer ReLU MLPs over normalised observations; a categorical policy head.

    nets = make_networks(obs_size, n_actions, NetworkConfig())
    params = nets.init(key)                       # Params(normalizer, actor, critic)
    logits = nets.logits(params, obs)             # (..., A)
    value = nets.value(params, obs)               # (...,)  in reward_scale units (see ppo.config.PPOConfig)

The normaliser is brax's running mean/std (Welford); it is a part of the parameters so that a saved policy
carries it, but only `update_normalizer` changes it, never a gradient step.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from brax.training.acme import running_statistics, specs
from flax import struct


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    hidden: Sequence[int] = (256, 256, 256)  # the paper's 3-layer MLPs; ReLU (the paper chose it over tanh)
    normalize_obs: bool = True
    obs_clip: float = 10.0  # normalised observations are clipped to +-obs_clip
    std_min: float = 1e-2  # floor of the normaliser's std: a feature constant in training data stays ~bounded


class MLP(nn.Module):
    hidden: Sequence[int]
    out: int
    out_scale: float = 1.0  # scale of the last layer's init (small for the policy head: near-uniform at start)

    @nn.compact
    def __call__(self, x):
        for width in self.hidden:
            x = nn.relu(nn.Dense(width, kernel_init=nn.initializers.orthogonal(jnp.sqrt(2.0)))(x))
        return nn.Dense(self.out, kernel_init=nn.initializers.orthogonal(self.out_scale))(x)


@struct.dataclass
class Params:
    normalizer: running_statistics.RunningStatisticsState
    actor: Any
    critic: Any


@dataclasses.dataclass(frozen=True)
class Networks:
    obs_size: int
    n_actions: int
    config: NetworkConfig

    @property
    def actor_net(self) -> MLP:
        return MLP(tuple(self.config.hidden), self.n_actions, out_scale=0.01)

    @property
    def critic_net(self) -> MLP:
        return MLP(tuple(self.config.hidden), 1, out_scale=1.0)

    def init(self, key: jax.Array) -> Params:
        k_actor, k_critic = jax.random.split(key)
        dummy = jnp.zeros((1, self.obs_size), jnp.float32)
        return Params(
            normalizer=jax.tree.map(  # arrays throughout (init gives a Python float std_eps; update an array)
                jnp.asarray, running_statistics.init_state(specs.Array((self.obs_size,), jnp.dtype("float32")))
            ),
            actor=self.actor_net.init(k_actor, dummy),
            critic=self.critic_net.init(k_critic, dummy),
        )

    def normalize(self, params: Params, obs: jax.Array) -> jax.Array:
        if not self.config.normalize_obs:
            return obs
        return running_statistics.normalize(obs, params.normalizer, max_abs_value=self.config.obs_clip)

    def logits(self, params: Params, obs: jax.Array) -> jax.Array:
        """(..., obs_size) -> (..., n_actions)."""
        return self.actor_net.apply(params.actor, self.normalize(params, obs))

    def value(self, params: Params, obs: jax.Array) -> jax.Array:
        """(..., obs_size) -> (...,)."""
        return self.critic_net.apply(params.critic, self.normalize(params, obs))[..., 0]

    def update_normalizer(self, params: Params, obs: jax.Array) -> Params:
        """Fold a batch of observations (..., obs_size) into the running statistics."""
        if not self.config.normalize_obs:
            return params
        stats = running_statistics.update(
            params.normalizer, obs.reshape(-1, self.obs_size), std_min_value=self.config.std_min
        )
        return params.replace(normalizer=stats)


def make_networks(obs_size: int, n_actions: int, config: NetworkConfig = NetworkConfig()) -> Networks:
    return Networks(obs_size=obs_size, n_actions=n_actions, config=config)


# ------------------------------------------------------------------------------- categorical distribution
def log_prob(logits: jax.Array, action: jax.Array) -> jax.Array:
    """log pi(action) for logits (..., A) and integer actions (...)."""
    logp = jax.nn.log_softmax(logits)
    return jnp.take_along_axis(logp, action[..., None].astype(jnp.int32), axis=-1)[..., 0]


def entropy(logits: jax.Array) -> jax.Array:
    """Entropy (...) of the categorical with logits (..., A), in nats."""
    logp = jax.nn.log_softmax(logits)
    return -jnp.sum(jnp.exp(logp) * logp, axis=-1)


def sample(key: jax.Array, logits: jax.Array) -> jax.Array:
    """A stochastic action (...) (training)."""
    return jax.random.categorical(key, logits).astype(jnp.int32)


def mode(logits: jax.Array) -> jax.Array:
    """The deterministic action (...) (validation, deployment): the most probable one."""
    return jnp.argmax(logits, axis=-1).astype(jnp.int32)
