"""The platform a kernel is traced for, decided once at trace time.

Some kernels have a CPU form and a GPU form of the same arithmetic (`kinematics.small_einsum`, the IK's normal
equations and damped step, the table's IK). `jax.lax.platform_dependent` would trace and lower both forms into
every program and let XLA drop one, doubling the trace and lowering work (docs/performance.md). `by_platform`
traces only the form of the platform the program will run on: the default device's (`jax.default_device`, when
set) or else the default backend's. A program jitted explicitly for another backend still computes the same
result (both forms agree to float32 rounding), in the other platform's form.
"""
from __future__ import annotations

from typing import Any, Callable

import jax


def current() -> str:
    """'cpu', 'gpu', 'tpu', ...: the platform that programs traced now run on."""
    return platform_of(jax.config.jax_default_device)


def platform_of(device) -> str:
    """The platform of a default device as `jax.default_device` takes it (None: the default backend's; a platform
    name; a `jax.Device`), with CUDA and ROCm both read as 'gpu'."""
    name = jax.default_backend() if device is None else device if isinstance(device, str) else device.platform
    return "gpu" if name in ("cuda", "rocm") else name


def by_platform(*args: Any, cpu: Callable, default: Callable) -> Any:
    """`cpu(*args)` when tracing for a CPU (`current`), else `default(*args)`."""
    return (cpu if current() == "cpu" else default)(*args)
