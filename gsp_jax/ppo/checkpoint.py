"""A trained policy on disk: its networks' parameters as an orbax checkpoint directory (`save_policy`,
`load_policy`). The training run's own checkpoints (resume) are `ppo.train`'s."""
from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from gsp_jax.ppo import networks as nets


def save_policy(path: str | pathlib.Path, params: nets.Params) -> None:
    """Write a policy (Params) to an orbax checkpoint directory."""
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(pathlib.Path(path).absolute(), params, force=True)


def load_policy(path: str | pathlib.Path, networks: nets.Networks) -> nets.Params:
    """Read a policy written by `save_policy`, for networks of the same shape."""
    path = pathlib.Path(path).absolute()
    if not path.exists():
        raise FileNotFoundError(f"policy: no checkpoint at {path}")
    # the parameters' shapes without running `init` (op by op it compiles dozens of small programs)
    device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    target = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device),
                          jax.eval_shape(networks.init, jax.random.PRNGKey(0)))
    with ocp.StandardCheckpointer() as ckpt:
        return uncommitted(ckpt.restore(path, target))


def uncommitted(tree):
    """Restored arrays come back committed to a device, which jit treats as a new signature (a recompile):
    hand them over as plain arrays."""
    return jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), tree)
