"""PPO's settings (`PPOConfig`), one place for the trainer and the policies that remember their reward scale."""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    n_envs: int = 2048  # parallel environments
    unroll: int = 16  # environment steps per environment and iteration (one episode's length)
    epochs: int = 4  # passes over an iteration's data
    minibatches: int = 8  # Adam steps per epoch
    learning_rate: float = 3e-4
    # piecewise-linear learning-rate factor over training: (fraction of max_iterations, factor) knots
    lr_knots: tuple[tuple[float, float], ...] = ((0.0, 1.0), (0.5, 1.0), (1.0, 0.1))
    max_iterations: int = 300
    gamma: float = 1.0  # finite horizon, undiscounted: the DP's return
    gae_lambda: float = 0.95
    clip: float = 0.2
    # an iteration's remaining Adam steps are skipped once a minibatch's approx. KL from the rollout policy exceeds
    # this (None: never). Fresh Adam moves every weight by ~lr whatever the gradient, so without it the first
    # iteration after DP pretraining throws the near-deterministic cloned policy far off (docs/rl.md).
    target_kl: float | None = 0.05
    vf_coef: float = 0.5
    ent_coef: float = 0.01
    max_grad_norm: float = 0.5
    reward_scale: float = 0.1  # rewards (and so critic targets) are multiplied by this in the update
    update_normalizer: bool = True  # fold every rollout into the observation statistics (off: keep them fixed)
    eval_every: int = 5  # iterations between validations of the deterministic policy
    patience: int = 20  # validations without improvement before an early stop (0: never stop early)
    checkpoint_every: int = 10  # iterations between checkpoints (and at the end)

    def __post_init__(self):
        for name in ("n_envs", "unroll", "epochs", "minibatches", "max_iterations", "eval_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"PPOConfig.{name}: must be >= 1, got {getattr(self, name)}")
        if (self.n_envs * self.unroll) % self.minibatches:
            raise ValueError(
                f"PPOConfig.minibatches: {self.minibatches} does not divide n_envs * unroll = "
                f"{self.n_envs * self.unroll}"
            )
        if self.target_kl is not None and not self.target_kl > 0:
            raise ValueError(f"PPOConfig.target_kl: must be > 0 or None, got {self.target_kl}")
        if not 0 < self.learning_rate < 1:
            raise ValueError(f"PPOConfig.learning_rate: expected in (0, 1), got {self.learning_rate}")

    def learning_rate_at(self, step):
        """The schedule over Adam steps (piecewise linear in the fraction of training done), held for an iteration
        from its first step (steps that `target_kl` skips count as taken)."""
        total = self.max_iterations * self.epochs * self.minibatches
        xs, ys = zip(*self.lr_knots)
        return self.learning_rate * jnp.interp(step / total, jnp.asarray(xs), jnp.asarray(ys))
