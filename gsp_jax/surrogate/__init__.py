"""The surrogate: one decision step (step.py: `Surrogate.reset`, `Surrogate.step`), the reward (reward.py: config,
terms, scoring, the calibrated defaults), what a policy observes (observation.py) and the learned physics term
(learned.py: a fall hazard fitted on a physics corpus, priced by the reward)."""
from gsp_jax.surrogate.step import State, Surrogate

__all__ = ["State", "Surrogate"]
