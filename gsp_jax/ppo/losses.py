"""GAE and the clipped PPO objective (Schulman et al. 2017). Time-major arrays: (U, B) = (unroll, envs)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from gsp_jax.ppo import networks as nets


@struct.dataclass
class Batch:
    """Transitions for one PPO update; leading axes (U, B) from a rollout, flattened to (N,) for SGD."""

    obs: jax.Array  # (..., obs_size)
    action: jax.Array  # (...,) int32
    log_prob: jax.Array  # (...,) log pi_old(action)
    value: jax.Array  # (...,) V_old(obs)
    advantage: jax.Array  # (...,)
    target: jax.Array  # (...,) value target = advantage + value


def gae(rewards, values, dones, bootstrap, gamma: float, lam: float, hold=None) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimates (U, B) and value targets (U, B).

    rewards, values, dones: (U, B), step u's reward, V(obs_u), and whether step u ended an episode (then the
    next observation belongs to a new episode and is not bootstrapped); bootstrap: (B,) V of the observation
    after the last step; hold: (U, B) the chance step u's segment held (the learned physics term's chance node,
    `env.GraspEnv`: what follows counts with it, as in `reward.backed_up`), None: 1."""
    hold = jnp.ones_like(rewards) if hold is None else hold

    def back(carry, x):
        adv_next, v_next = carry
        r, v, d, h = x
        live = (1.0 - d.astype(r.dtype)) * h
        delta = r + gamma * live * v_next - v
        adv = delta + gamma * lam * live * adv_next
        return (adv, v), adv

    _, adv = jax.lax.scan(back, (jnp.zeros_like(bootstrap), bootstrap), (rewards, values, dones, hold), reverse=True)
    return adv, adv + values


def ppo_loss(params: nets.Params, networks: nets.Networks, batch: Batch, clip: float, vf_coef: float, ent_coef: float):
    """Clipped surrogate + vf_coef * value MSE - ent_coef * entropy, on a minibatch (N,). Returns (loss, metrics)."""
    logits = networks.logits(params, batch.obs)
    logp = nets.log_prob(logits, batch.action)
    ratio = jnp.exp(logp - batch.log_prob)
    adv = (batch.advantage - batch.advantage.mean()) / (batch.advantage.std() + 1e-8)
    policy_loss = -jnp.mean(jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - clip, 1.0 + clip) * adv))
    value_loss = 0.5 * jnp.mean((networks.value(params, batch.obs) - batch.target) ** 2)
    ent = jnp.mean(nets.entropy(logits))
    loss = policy_loss + vf_coef * value_loss - ent_coef * ent
    metrics = {
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy": ent,
        "approx_kl": jnp.mean((ratio - 1.0) - jnp.log(ratio)),
        "clip_fraction": jnp.mean(jnp.abs(ratio - 1.0) > clip),
    }
    return loss, metrics
