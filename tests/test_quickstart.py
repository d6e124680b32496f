"""The public face: `import gsp_jax as gsp` gives what a user calls, and the README's Quickstart, which imports
only it, runs as written in a fresh process."""
from __future__ import annotations

import ast
import os
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def quickstart() -> str:
    """The README's Quickstart: the first python block after its heading."""
    text = (ROOT / "README.md").read_text()
    return text.split("## Quickstart", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]


def test_the_quickstart_imports_gsp_jax_only_and_uses_its_public_names():
    import gsp_jax

    tree = ast.parse(quickstart())
    imports = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert [(a.name, a.asname) for n in imports for a in n.names] == [("gsp_jax", "gsp")], ast.dump(imports[0])
    used = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
            and n.value.id == "gsp"}
    assert used and used <= set(gsp_jax.__all__), sorted(used - set(gsp_jax.__all__))


def test_every_public_name_resolves_and_importing_the_package_stays_light():
    code = ("import sys, gsp_jax as gsp\n"
            "heavy = sorted(m for m in ('gsp_jax.surrogate.step', 'gsp_jax.planners.registry', 'gsp_jax.physics')\n"
            "               if m in sys.modules)\n"
            "missing = [n for n in gsp.__all__ if getattr(gsp, n, None) is None]\n"
            "print(heavy, missing, sorted(set(gsp.__all__) - set(dir(gsp))))")
    out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, JAX_PLATFORMS="cpu"), cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
    assert out == "[] [] []", out  # nothing heavy until asked for; every name there; every name listed


def test_the_quickstart_runs_as_written(tmp_path):
    """In a fresh process in an empty folder (it writes nothing there): its first decision, L1's plan and both plans
    executed in C MuJoCo, as its comments say."""
    script = tmp_path / "quickstart.py"
    script.write_text(quickstart())
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True,
                          env=dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT)))
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [ln for ln in proc.stdout.splitlines() if not ln.startswith(("building DP tables", "  "))]
    assert re.fullmatch(r"keep|\w+->(off|\d+)", lines[0]), lines
    changes, ret = re.fullmatch(r"(\[.*\]) (-?\d+\.\d+(e-?\d+)?)", lines[1]).group(1, 2)
    assert all(re.fullmatch(r"t\d+:\w+->(off|\d+)", c) for c in ast.literal_eval(changes)), changes
    assert float(ret) > -200.0, ret  # above `RewardConfig.r_min`: the plan holds in the surrogate
    for line, name in zip(lines[2:4], ["dp-opt", "L1"]):
        assert re.fullmatch(rf"{re.escape(name)} (held|fell) \d+\.\d deg", line), line
    assert len(lines) == 4, lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["quickstart.py"]  # nothing written to the folder
