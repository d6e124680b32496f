"""gsp_jax: grasp-sequence planning for in-hand tool manipulation, in pure JAX.

Data flows one way:

    models/*.xml -> hand.py (constant arrays) -> kinematics.py, ik.py, wrench.py (kernels)
    scenario.py (Episode) -> surrogate.py (reset/step, reward terms) -> dp.py (table, Bellman backup)
                                                                     -> policies.py (one `act(state)` interface)

The surrogate step is `surrogate.Surrogate.step`: `realise` (IK) at the current and next waypoint, then
`score` (three wrench solves) -> reward.
"""
