"""PPO for the grasp-sequence MDP (categorical over the 17 actions), on flax/optax over a brax-style env.

networks.py    actor and critic MLPs, observation normaliser, categorical distribution
losses.py      GAE and the clipped PPO loss
config.py      PPOConfig: the run's settings
checkpoint.py  a trained policy on disk (save_policy, load_policy)
train.py       the training loop: jitted iterations (rollout `lax.scan` + SGD epochs), validation, early stop,
               the run's resumable orbax checkpoints
pipeline.py    the paper's pipeline: DP behaviour cloning, then PPO on the training episodes, validated (presets)
"""
