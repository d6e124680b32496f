"""XLA's compiled programs kept on disk: JAX's persistent compilation cache, on for every user of the package.

`import gsp_jax` calls `enable()`. A process that builds a program some earlier process already built (the same
program, jax version, XLA flags and machine) loads it instead of compiling it: the first plan of a new process
then costs tracing and loading, not XLA's compile (figures: docs/performance.md, `python -m experiments
bench-startup`).

    GSP_JAX_CACHE unset        the folder `default_folder()`: $XDG_CACHE_HOME (or ~/.cache) / gsp_jax / xla / <cpu>
    GSP_JAX_CACHE=<folder>     that folder (a subfolder per CPU is made inside it)
    GSP_JAX_CACHE=off          no cache (also 0, none, false)

A cache the user configured (`jax_compilation_cache_dir` set before the import, e.g. by JAX_COMPILATION_CACHE_DIR)
is left as it is. Every program is cached, however fast it compiled (JAX's default keeps only those that took 1 s
or more; the surrogate's small programs add up). JAX's key holds the program, the jax and XLA versions and
XLA_FLAGS, not the CPU's instruction set, so the folder has one subfolder per CPU (a hash of its model and feature
flags): a home folder shared by machines of different CPUs never loads another CPU's machine code.
"""
from __future__ import annotations

import hashlib
import os
import pathlib
import platform as _platform

OFF = ("", "off", "0", "none", "false")


def cpu_tag() -> str:
    """A short tag of this machine's CPU: its architecture, model name and feature flags (Linux's /proc/cpuinfo;
    elsewhere the processor string), hashed."""
    text = f"{_platform.machine()} {_platform.processor()}"
    try:
        with open("/proc/cpuinfo") as f:
            lines = [line for line in f if line.startswith(("model name", "flags", "Features", "CPU part"))]
        text += "".join(sorted(set(lines)))
    except OSError:
        pass
    return f"{_platform.machine()}-{hashlib.sha256(text.encode()).hexdigest()[:12]}"


def default_folder() -> pathlib.Path:
    """$GSP_JAX_CACHE, or $XDG_CACHE_HOME (default ~/.cache) / gsp_jax / xla, with this CPU's subfolder."""
    root = os.environ.get("GSP_JAX_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "gsp_jax", "xla")
    return pathlib.Path(root).expanduser() / cpu_tag()


def enable() -> str | None:
    """Turn the persistent compilation cache on (see the module docstring); returns its folder, or None when it is
    off. Leaves a cache the user configured alone (and returns its folder)."""
    import jax

    configured = jax.config.jax_compilation_cache_dir
    if configured:
        return configured
    if os.environ.get("GSP_JAX_CACHE", "unset").strip().lower() in OFF:
        return None
    folder = default_folder()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: run without the cache rather than fail the import
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return str(folder)
