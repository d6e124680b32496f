"""Checked at every door: each bad input to a public entry point is refused with an error that
names the field and the value, before any work; a value on the documented edge is accepted."""
from __future__ import annotations

import argparse
import json

import jax.numpy as jnp
import numpy as np
import pytest

from gsp_jax import physics
from gsp_jax.planning import policies
from gsp_jax.model import scenario
from gsp_jax.model.scenario import EpisodeError

NOMINAL = scenario.make_episode()


@pytest.mark.parametrize("field, value, message", [
    ("waypoints", NOMINAL.waypoints.at[3, 0].set(jnp.nan), r"episode\.waypoints: contains nan"),
    ("dt", jnp.float32(0.0), r"episode\.dt: 0\.0 s \(must be in \[0\.01, 10\.0\] s\)"),
    ("dt", jnp.float32(1e6), r"episode\.dt: 1e\+06 s \(must be in"),
    ("mass", jnp.float32(0.0), r"episode\.mass: 0\.0 kg \(must be within 100x of the model's tool mass 0\.35 kg"),
    ("mass", jnp.float32(1e6), r"episode\.mass: 1e\+06 kg \(must be within 100x"),
    ("mass", jnp.float32(1e-9), r"episode\.mass: 1e-09 kg \(must be within 100x"),
    ("inertia", jnp.float32([1e9, 1e9, 1e9]), r"episode\.inertia: \[1000000000\.0, .* \(each must be in"),
    ("inertia", jnp.float32([1e-3, 1e-3, 3e-3]), r"episode\.inertia: .* \(no body has these principal moments"),
    ("waypoints", jnp.zeros((200, 3), jnp.float32), r"episode\.waypoints: 200 waypoints \(at most 19"),
    ("start_grasp", jnp.int32(288), r"episode\.start_grasp: 288 \(must be in 0\.\.287\)"),
])
def test_the_surrogate_refuses_a_bad_episode_from_python(sur, field, value, message):
    with pytest.raises(EpisodeError, match=message):
        sur.reset(NOMINAL.replace(**{field: value}))


@pytest.mark.parametrize("action", ["3", None, True, 2.5, np.nan])
def test_actions_must_be_integers(sur, action):
    with pytest.raises(ValueError, match=r"action(s)?: .* (is not an integer action|not an integer)"):
        sur.space.check_actions(action)
    with pytest.raises(ValueError, match="SequencePolicy.actions"):  # (numpy itself turns [0, True] into ints)
        policies.SequencePolicy(np.array([False, True]) if action is True else
                                np.array([0, action], dtype=object if isinstance(action, (str, type(None))) else None),
                                sur.space)


@pytest.mark.parametrize("kwargs, message", [
    (dict(start_grasp=2.5), r"episode\.start_grasp: 2\.5 \(must be an int grasp index\)"),
    (dict(friction="0.8"), r"episode\.friction: '0\.8' \(must be a finite number\)"),
    (dict(mass_factor=True), r"episode\.mass_factor: True"),
    (dict(lateral_mm=(0.0, float("inf"))), r"episode\.lateral_mm\[1\]: inf"),
])
def test_make_episode_takes_numbers_only(kwargs, message):
    with pytest.raises(EpisodeError, match=message):
        scenario.make_episode(**kwargs)


def test_a_waypoint_on_the_reach_box_edge_is_in_it():
    edge = NOMINAL.replace(waypoints=NOMINAL.waypoints.at[:, 0].set(np.float32(0.05)))
    scenario.validate(edge)  # float32(0.05) > 0.05 in float64: the box is compared in the waypoints' precision
    with pytest.raises(EpisodeError, match=r"waypoints\[0\]: .* out of the hand's reach"):
        scenario.validate(NOMINAL.replace(waypoints=NOMINAL.waypoints.at[:, 0].set(0.051)))


def test_an_episode_file_with_an_absurd_start_grasp_is_named(tmp_path):
    d = scenario.to_dict(NOMINAL)
    for bad in (1e20, -1, 3.5, [1, 2]):
        path = tmp_path / "e.json"
        path.write_text(json.dumps({"episodes": {"x": {**d, "start_grasp": bad}}}))
        with pytest.raises(EpisodeError, match=r"x\.start_grasp: .* \(must be an integer grasp index\)"):
            scenario.load(path)


def test_the_physics_batch_is_checked_before_it_runs(sur):
    phys = physics.Physics(sur)
    two = scenario.stack([NOMINAL, scenario.make_episode(shift_mm=2)])
    with pytest.raises(ValueError, match=r"policies\[0\]: a per-episode policy .* leading axis of 2 .* got \[3\]"):
        phys.simulate_batch(policies.SequencePolicy(jnp.zeros((3, 16), jnp.int32)), two, policy_axis=0, backend="c")
    with pytest.raises(ValueError, match=r"episodes: expected a batch .* got mass of shape \(\)"):
        phys.simulate_batch(policies.SequencePolicy(jnp.zeros(16, jnp.int32)), NOMINAL, backend="c")
    with pytest.raises(EpisodeError, match=r"episodes\[1\]\.waypoints: contains nan"):
        phys.simulate_batch(policies.SequencePolicy(jnp.zeros(16, jnp.int32)),
                            two.replace(waypoints=two.waypoints.at[1, 2, 2].set(jnp.nan)), backend="c")


def test_gym_env_checks_the_episodes_it_is_given():
    from gsp_jax.learning import gym_env

    with pytest.raises(EpisodeError, match=r"bad\.dt: 0\.0"):
        gym_env.make(episodes={"bad": NOMINAL.replace(dt=jnp.float32(0.0))}, backend="surrogate", progress=False)


@pytest.mark.parametrize("argv, message", [
    (["--episodes", "-1"], r"--episodes: -1 \(must be >= 1\)"),
    (["--render-episode", "bogus", "--policy", "four-tips"], r"--render-episode: 'bogus' is not one of"),
])
def test_the_physics_command_refuses_bad_options_before_any_work(argv, message):
    from experiments import common
    from experiments.physics import check

    parser = argparse.ArgumentParser()
    check.add_arguments(parser)
    with pytest.raises(SystemExit, match=message):
        check.main(parser.parse_args(["--set", "nominal", *argv]), common.Run())


@pytest.mark.parametrize("field, value", [("waypoints", NOMINAL.waypoints.at[3, 0].set(jnp.nan)), ("dt", 0.0),
                                          ("mass", 0.0), ("start_grasp", 288)])
def test_inside_jit_an_invalid_episode_gives_r_min_and_a_flag_never_nan(sur, field, value):
    """Traced, nothing can raise: every step of an invalid episode is r_min, done and flagged invalid (the probes
    gave NaN rewards, or for mass 0 a better reward than the nominal); a valid one is unflagged."""
    import jax

    step = jax.jit(lambda ep: sur.step(sur._reset(ep), jnp.int32(0)))
    bad = NOMINAL.replace(**{field: jnp.asarray(value, NOMINAL.start_grasp.dtype if field == "start_grasp"
                                                else jnp.float32)})
    state, reward, done = step(bad)
    assert float(reward) == sur.reward_config.r_min and bool(done) and bool(state.terms.invalid)
    state, reward, done = step(NOMINAL)  # (keeping the three-tip start grasp falls there: r_min, but valid)
    assert not bool(state.terms.invalid) and np.isfinite(float(reward))


def test_the_physics_batch_check_takes_a_pytree_of_policy_axes(sur):
    """A per-episode policy given as a pytree of in_axes (L1 searching each episode's table: a `Lookahead` of axes,
    as `planners.make` gives it) passes the batch check; `make demo` runs one through the physics."""
    axis = policies.Lookahead(None, None, depth=1, inner=0)
    two = scenario.stack([NOMINAL, scenario.make_episode(shift_mm=2)])
    physics.Physics(sur)._check_batch([(policies.SequencePolicy(jnp.zeros(16, jnp.int32)), axis)], two)


def test_dp_checks_concrete_episodes_before_any_work(sur):
    """`dp.solve` / `dp.build_tables` called from Python name the bad episode of a batch and its field."""
    from gsp_jax.planning import dp

    with pytest.raises(EpisodeError, match=r"episode\.mass: 0\.0 kg"):
        dp.solve(sur, NOMINAL.replace(mass=jnp.float32(0.0)))
    batch = scenario.stack([NOMINAL, NOMINAL.replace(dt=jnp.float32(-1.0))])
    with pytest.raises(EpisodeError, match=r"episodes\[1\]\.dt: -1\.0 s"):
        dp.build_tables(sur, batch)
