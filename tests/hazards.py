"""An untrained hazard network for tests of the learned physics term on any model (`learned.Fitted`): fall chances
spread over (0, 1) without a corpus or a fit."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.model import grasps
from gsp_jax.model import load as model_lib
from gsp_jax.surrogate import learned


def fitted(digest: str, bias: float = 0.0, seed: int = 0, space=None) -> learned.Fitted:
    """An untrained hazard network of the corpus's features (random weights, `bias` added to the logit; an ensemble
    of one), scaled by rough feature magnitudes so its probabilities spread over (0, 1); its inputs those of
    `space`'s grasps (None: the wrench's)."""
    names = learned.input_names(space or grasps.space_of(model_lib.load_model().hand))
    F = len(names)
    params = learned._MLP((16,)).init(jax.random.PRNGKey(seed), jnp.zeros((1, F)))
    params = jax.tree.map(lambda x: x, params)
    params["params"]["Dense_1"]["bias"] = params["params"]["Dense_1"]["bias"] + bias
    scale = np.ones(F, np.float32)
    scale[learned.FEATURES.index("reward")] = 50.0
    scale[learned.FEATURES.index("t")] = 2.0
    params = jax.tree.map(lambda x: x[None], params)
    return learned.Fitted(params, jnp.zeros(F), jnp.asarray(scale), (16,), names, digest)
