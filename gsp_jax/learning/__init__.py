"""Learning over the surrogate: the surrogate as a brax environment (env.py) and as Gymnasium environments
(gym_env.py), DP behaviour cloning (pretrain.py) and the paper's recipe, BC then PPO, validated (pipeline.py). PPO
itself is `gsp_jax.ppo`."""
