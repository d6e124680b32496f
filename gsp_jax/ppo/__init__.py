"""PPO, the algorithm alone (categorical actions, flax/optax, over any brax-style env): it imports nothing of the
domain, only `gsp_jax.core`. The paper's recipe (DP behaviour cloning, then PPO) is `gsp_jax.learning.pipeline`.

networks.py    actor and critic MLPs, observation normaliser, categorical distribution
losses.py      GAE and the clipped PPO loss
config.py      PPOConfig: the run's settings
checkpoint.py  a trained policy on disk (save_policy, load_policy)
train.py       the training loop: jitted iterations (rollout `lax.scan` + SGD epochs), validation, early stop,
               the run's resumable orbax checkpoints
"""
