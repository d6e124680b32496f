"""Fuzzing the doors (hypothesis): random valid episodes and actions are accepted and give finite results; random
invalid ones are refused with an error naming the field."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gsp_jax.model import scenario
from gsp_jax.model.scenario import EpisodeError

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
VALID = dict(
    shift_mm=st.floats(-6, 12), torque=st.floats(-2, 2), mass_factor=st.floats(0.25, 3), com_y_cm=st.floats(-2, 2),
    friction=st.floats(0.3, 2), com_x_cm=st.floats(-2, 2), torque_axis=st.sampled_from(["x", "y", "z"]),
    lateral_mm=st.tuples(st.floats(-15, 15), st.floats(-15, 15)), start_grasp=st.integers(0, 287),
)


@pytest.fixture(scope="module")
def first_step(sur):
    """reset + one step, one program (compiled once for the module)."""
    return jax.jit(lambda ep, a: sur.step(sur._reset(ep), a))


@SETTINGS
@given(st.fixed_dictionaries(VALID), st.integers(0, 16))
def test_valid_episodes_and_actions_are_accepted_and_finite(sur, first_step, kwargs, action):
    episode = scenario.make_episode(**kwargs)
    sur.space.check_actions(action)
    state, reward, done = first_step(episode, jnp.int32(action))
    assert np.isfinite(float(reward)) and sur.reward_config.r_min <= float(reward) <= 0
    assert np.all(np.isfinite(np.asarray(state.q)))


BAD = {  # field -> values that are never valid
    "dt": [0.0, -0.25, np.nan, np.inf, 1e-3, 1e6],
    "mass": [0.0, -1.0, np.nan, 1e-9, 1e6],
    "friction": [0.0, -0.5, 3.5, np.nan],
    "start_grasp": [-1, 288, 10**6],
    "inertia": [[0.0, 1e-3, 1e-3], [1e-5, -1e-3, 1e-3], [np.nan, 1e-3, 1e-3], [1e9, 1e9, 1e9], [1e-3, 1e-3, 3e-3]],
    "com": [[0.5, 0.0, 0.0], [0.0, np.inf, 0.0]],
    "w_ext": [[0, 0, 0, 0, 0, np.nan]],
}


@SETTINGS
@given(st.sampled_from(sorted(BAD)), st.data())
def test_invalid_episodes_are_refused_by_name(sur, field, data):
    value = data.draw(st.sampled_from(BAD[field]))
    dtype = jnp.int32 if field == "start_grasp" else jnp.float32
    episode = scenario.make_episode().replace(**{field: jnp.asarray(value, dtype)})
    with pytest.raises(EpisodeError, match=rf"episode\.{field}"):
        sur.reset(episode)


@SETTINGS
@given(st.one_of(st.integers(max_value=-1), st.integers(min_value=17), st.floats(allow_nan=True).filter(
    lambda x: not float(x).is_integer()), st.text(max_size=3), st.none(), st.booleans()))
def test_invalid_actions_are_refused_by_name(sur, action):
    with pytest.raises(ValueError, match=r"^action: "):
        sur.space.check_actions(action)
