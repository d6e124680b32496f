"""`python -m experiments [--processes N] <words>` in a folder of its own, as a user starts it: what the tests of
several processes share. Each run's episodes are cut to their first `WAYPOINTS` (`SHORT_PLUGIN`, a `--plugin`), as
the in-process tests cut them, so that tables and physics stay quick."""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
WAYPOINTS = 3
SHORT_PLUGIN = '''"""Every episode set cut to its first {w} waypoints, as the in-process tests cut them."""
from gsp_jax.model import scenario

_episode_set = scenario.episode_set
scenario.episode_set = lambda name, model=None: {{k: e.head({w}) for k, e in _episode_set(name, model).items()}}
'''


def run(folder: pathlib.Path, n: int, words: list[str], plugins: dict[str, str] | None = None
        ) -> subprocess.CompletedProcess:
    """`python -m experiments --processes n <words>` in `folder` (created) on the CPU, the episodes cut to
    `WAYPOINTS`; `plugins` (file name -> source) are written there and loaded with `--plugin` after the cut."""
    folder.mkdir(exist_ok=True)
    plugins = {"short.py": SHORT_PLUGIN.format(w=WAYPOINTS), **(plugins or {})}
    for name, source in plugins.items():
        (folder / name).write_text(source)
    words = [*words] + [w for name in plugins for w in ("--plugin", name)]
    return subprocess.run([sys.executable, "-m", "experiments", "--processes", str(n), *words], cwd=folder,
                          capture_output=True, text=True, timeout=1200,
                          env=dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu"))
