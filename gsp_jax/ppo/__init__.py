"""PPO for the grasp-sequence MDP (categorical over the 17 actions), on flax/optax over a brax-style env.

networks.py  actor and critic MLPs, observation normaliser, categorical distribution
losses.py    GAE and the clipped PPO loss
train.py     the training loop: jitted iterations (rollout `lax.scan` + SGD epochs), validation, early stop,
             orbax checkpoints
"""
