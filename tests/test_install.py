"""The package installs as a package: the wheel carries the model files and the shipped policy, and a
non-editable install of it (into a directory of its own, first on the path, the dependencies those of the test's
environment) steps the surrogate from a directory outside the checkout; and the environment the tests run in is
requirements.lock's set, whichever installer made it (the Makefile's uv, or pip). That the pinned dependencies
resolve on a fresh machine is what `make test` and `make demo` do each time they create their environment.
"""
from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys
import zipfile

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

STEP_ONCE = """
import json, pathlib, jax, jax.numpy as jnp
import gsp_jax
from gsp_jax.planning import evaluation
from gsp_jax.model import hand, scenario
from gsp_jax.surrogate import step as surrogate
gsp_jax.enable_cache()  # the run's test cache (GSP_JAX_CACHE, set by conftest.py)
env = surrogate.Surrogate()
state = jax.jit(env.reset)(scenario.make_episode())
state, reward, done = jax.jit(env.step)(state, jnp.int32(3))
from gsp_jax import physics
import importlib, experiments
from experiments.cli import COMMANDS
for module, _ in COMMANDS.values():  # every command's module, its group's subpackage included
    importlib.import_module(module)
nbody = physics.Physics(env).model.nbody  # the physics subpackage and its scene (world, palm, 16 finger bodies, tool)
print(json.dumps(dict(package=str(pathlib.Path(gsp_jax.__file__).parent), models=str(hand.MODELS_DIR),
                      experiments=str(pathlib.Path(experiments.__file__).parent),
                      reward=float(reward), grasp=int(state.grasp), policy=evaluation.SHIPPED_POLICY.is_dir(),
                      nbody=nbody)))
"""


@pytest.mark.timeout(1200)
def test_wheel_installs_outside_the_checkout_and_steps_the_surrogate(tmp_path):
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    run = lambda cmd, **kw: subprocess.run(cmd, check=True, capture_output=True, text=True, **kw)  # noqa: E731

    built = run([*pip, "wheel", "--no-deps", "-w", str(tmp_path / "dist"), str(ROOT)])
    assert "warning" not in (built.stdout + built.stderr).lower(), built.stdout + built.stderr  # a quiet install
    (wheel,) = (tmp_path / "dist").glob("gsp_jax-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    shipped = [f.relative_to(ROOT / "models").as_posix() for f in (ROOT / "models").rglob("*")
               if f.is_file() and "__pycache__" not in f.parts]
    assert {"scene.xml", "hand.xml", "wrench.xml", "reward_calibration.json",
            "policies/ppo_dp_seed0/_METADATA"} <= set(shipped)
    missing = [f for f in shipped if f"gsp_jax/models/{f}" not in names]
    assert not missing, f"models/ files not in the wheel: {missing}"
    assert not any(n.startswith("models/") for n in names)  # one copy, inside the package

    site = tmp_path / "site"
    run([*pip, "install", "--no-deps", "--no-compile", "--target", str(site), str(wheel)])
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",)}
    out = run([sys.executable, "-c", STEP_ONCE], cwd=elsewhere,
              env=dict(env, JAX_PLATFORMS="cpu", PYTHONPATH=str(site)))
    import json

    result = json.loads(out.stdout.strip().splitlines()[-1])
    site = str(site)
    assert result["package"].startswith(site) and result["models"].startswith(site), result  # not the checkout
    assert result["experiments"].startswith(site), result
    assert result["policy"], "the shipped policy is not in the installed package"
    assert result["nbody"] == 19, "the physics scene did not build from the installed package"
    assert -200.0 <= result["reward"] < 0.0 and result["grasp"] >= 0, result
    assert "Failed to import warp" not in out.stdout + out.stderr  # users' output stays clean


def _name(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()  # PEP 503's normalised name


def test_the_environment_is_the_pinned_set():
    """Every distribution of requirements.lock is installed at its pinned version (uv and pip resolve the same set
    from it), and nothing else but the installers and the package itself, unless an extra other than `test`
    (`[gpu]`, `[sb3]`) was added by hand."""
    from importlib import metadata

    pins = dict(line.split("==") for line in (ROOT / "requirements.lock").read_text().split() if "==" in line)
    pins = {_name(name): version for name, version in pins.items()}
    installed = {_name(d.metadata["Name"]): d.version for d in metadata.distributions()}
    wrong = {name: (installed.get(name), pin) for name, pin in pins.items() if installed.get(name) != pin}
    assert not wrong, f"(installed, pinned) against requirements.lock: {wrong}"
    if not {"stable-baselines3", "jax-cuda13-plugin"} & set(installed):  # no extra added by hand
        unpinned = set(installed) - set(pins) - {"gsp-jax", "pip", "setuptools", "wheel", "uv"}
        assert not unpinned, f"installed but not in requirements.lock: {sorted(unpinned)}"
