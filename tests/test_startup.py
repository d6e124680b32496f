"""A first plan in seconds: the compilation cache the package turns on, the kernels traced in one form,
and the surrogate's programs built once per model."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.core import cache, platform
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate
from gsp_jax.surrogate.reward import RewardConfig

PROBE = """
import json, jax, jax.numpy as jnp
import gsp_jax
folder = gsp_jax.enable_cache()
jax.block_until_ready(jax.jit(lambda x: jnp.sin(x) * 2.0)(jnp.arange(3.0)))  # compiles in well under 1 s
print(json.dumps(dict(folder=jax.config.jax_compilation_cache_dir, package=folder,
                      min_s=jax.config.jax_persistent_cache_min_compile_time_secs)))
"""


def _probe(tmp_path, **env) -> dict:
    base = {k: v for k, v in os.environ.items() if k not in ("GSP_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR")}
    base.update(JAX_PLATFORMS="cpu", XDG_CACHE_HOME=str(tmp_path / "xdg"), **env)
    out = subprocess.run([sys.executable, "-c", PROBE], env=base, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_enable_cache_turns_on_the_compilation_cache_and_keeps_small_programs(tmp_path):
    """`gsp_jax.enable_cache()` turns the cache on in the user's cache folder (XDG_CACHE_HOME), one subfolder per CPU,
    and writes even a program that compiled in milliseconds (JAX keeps only those over 1 s by default)."""
    got = _probe(tmp_path)
    expected = tmp_path / "xdg" / "gsp_jax" / "xla" / cache.cpu_tag()
    assert got["folder"] == got["package"] == str(expected) and got["min_s"] == 0.0
    assert any(expected.iterdir()), "nothing was written to the cache"


def test_gsp_jax_cache_names_the_folder_or_turns_it_off(tmp_path):
    got = _probe(tmp_path, GSP_JAX_CACHE=str(tmp_path / "mine"))
    assert got["folder"] == str(tmp_path / "mine" / cache.cpu_tag()) and any((tmp_path / "mine").rglob("*"))
    for off in ("off", "0", "none"):
        got = _probe(tmp_path, GSP_JAX_CACHE=off)
        assert got["folder"] is None and got["package"] is None, off
    assert not (tmp_path / "xdg").exists()


def test_a_cache_the_user_configured_is_left_alone(tmp_path):
    got = _probe(tmp_path, JAX_COMPILATION_CACHE_DIR=str(tmp_path / "theirs"))
    assert got["folder"] == got["package"] == str(tmp_path / "theirs") and got["min_s"] == 1.0
    assert not (tmp_path / "xdg").exists()


def test_the_cpu_tag_is_stable_and_names_the_architecture():
    assert cache.cpu_tag() == cache.cpu_tag() and cache.cpu_tag().startswith(os.uname().machine)


def test_kernels_are_traced_in_the_platforms_form_alone(sur):
    """The surrogate step's program holds one form of each CPU/GPU kernel pair (`platform.by_platform`), not both
    behind a platform switch (`lax.platform_dependent` lowered 208 such branch pairs into it): its one branch is
    the motor check's `cond` on the last step (`Surrogate.score`)."""
    assert platform.current() == "cpu"
    state = sur.reset(scenario.make_episode())
    text = jax.jit(sur.step).lower(state, jnp.int32(3)).as_text()
    assert text.count("stablehlo.case") == 1 and "platform_index" not in text
    no_motor = surrogate.Surrogate(sur.hand, reward=dataclasses.replace(sur.reward_config, motor_fall_unmet=np.inf),
                                   learned=False)
    assert "stablehlo.case" not in jax.jit(no_motor.step).lower(state, jnp.int32(3)).as_text()
    with jax.default_device(jax.devices("cpu")[0]):
        assert platform.current() == "cpu"
    assert platform.by_platform(2, cpu=lambda x: x + 1, default=lambda x: x - 1) == 3


def test_by_platform_follows_the_platform_traced_for(monkeypatch):
    """A GPU (or any other platform) gets the default form; the platform of a default device named by a string or
    a device object is read as JAX names it ('cuda' and 'rocm' are GPUs)."""
    monkeypatch.setattr(platform, "current", lambda: "gpu")
    assert platform.by_platform(2, cpu=lambda x: x + 1, default=lambda x: x - 1) == 1
    assert platform.platform_of("cuda") == platform.platform_of("rocm") == "gpu"
    assert platform.platform_of(jax.devices("cpu")[0]) == "cpu" and platform.platform_of(None) == "cpu"


def test_surrogates_of_one_model_share_their_programs(hand):
    """Two surrogates of the same hand and configs are equal and hash alike, so `reset` (compiled: `_reset`) builds
    one program for both; another reward config is another model."""
    a, b = surrogate.Surrogate(hand, learned=False), surrogate.Surrogate(hand, learned=False)
    other = surrogate.Surrogate(hand, reward=RewardConfig(w_redundant=0.1), learned=False)
    assert a == b and hash(a) == hash(b) and a != other
    episode = scenario.make_episode().head(5)  # a shape no other test resets
    before = surrogate.Surrogate._reset._cache_size()
    sa, sb = a.reset(episode), b.reset(episode)
    assert surrogate.Surrogate._reset._cache_size() == before + 1
    for x, y in zip(jax.tree.leaves(sa), jax.tree.leaves(sb)):
        assert bool(jnp.all(x == y))
    other.reset(episode)
    assert surrogate.Surrogate._reset._cache_size() == before + 2


def test_reset_from_python_equals_reset_inside_a_program(sur):
    """`reset` compiled on its own and traced into a caller's program: the same state."""
    episode = scenario.make_episode()
    alone = sur.reset(episode)
    inside = jax.jit(lambda e: sur.reset(e))(episode)
    assert int(alone.grasp) == int(inside.grasp) and int(alone.t) == 0
    assert jnp.allclose(alone.q, inside.q, atol=1e-6)


