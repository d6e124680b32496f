"""The model: an MJCF scene -> a `Model` (load.py: `load_model`, `check_model`), its constant arrays (hand.py),
forward kinematics (kinematics.py), grasps and actions (grasps.py), episodes, their sets and their checks
(scenario.py)."""
from gsp_jax.model.load import Model, ModelError, check_model, load_model

__all__ = ["Model", "ModelError", "check_model", "load_model"]
