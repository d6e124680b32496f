"""The layout shows the architecture: the library's imports follow the layer table of docs/architecture.md, neither
the library's nor the commands' import graph has a circle, the experiments' commands import the library's public
names and `experiments.common` but never one another, and docs/architecture.md names every folder of code."""
from __future__ import annotations

import ast
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _module(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: pathlib.Path) -> list[tuple[str, str]]:
    """(module, name) of every import in the file, at any depth (a function's own imports count: they are edges
    too); `name` is "" for `import module`."""
    package = _module(path) if path.name == "__init__.py" else _module(path).rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(a.name, "") for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            out += [(base, a.name) for a in node.names]
    return out


def _graph(top: str) -> dict[str, set[str]]:
    files = {_module(p): p for p in (ROOT / top).rglob("*.py")}
    graph = {}
    for mod, path in files.items():
        edges = set()
        for base, name in _imports(path):
            target = f"{base}.{name}" if f"{base}.{name}" in files else base
            if target in files and target != mod:
                edges.add(target)
        graph[mod] = edges
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_library_and_the_commands_have_no_import_circle():
    graph = _graph("gsp_jax")
    assert len(graph) > 30 and "gsp_jax.physics.c_backend" in graph
    assert _cycles(graph) == []
    commands = _graph("experiments")
    assert "experiments.cli" in commands["experiments.__main__"] and "experiments.common" in commands["experiments.cli"]
    assert _cycles(commands) == []


def _layer_table() -> dict[str, int]:
    """Each folder the library table of docs/architecture.md names -> its row (0: the top row); one folder a row."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text.split("### `gsp_jax/`: the library", 1)[1].split("\n#", 1)[0]
    rows = [line.split("|") for line in section.splitlines() if line.startswith("| ") and "`" in line]
    table = {}
    for i, cells in enumerate(rows):
        folders = re.findall(r"`gsp_jax/(\w+)/`", cells[2])
        assert len(folders) == 1, f"row {i} of the layer table names {folders}: one folder a row"
        table["gsp_jax." + folders[0]] = i
    return table


def _layer(table: dict[str, int], module: str) -> int | None:
    """The row of the folder `module` sits in (None: the package's own `__init__`, or a module in no folder)."""
    parts = module.split(".")
    return table.get(".".join(parts[:2])) if len(parts) > 1 else None


def test_the_layer_finder_reads_the_folder():
    table = {"gsp_jax.core": 0, "gsp_jax.ppo": 1}
    assert [_layer(table, m) for m in ("gsp_jax.core.files", "gsp_jax.ppo", "gsp_jax.ppo.train", "gsp_jax",
                                       "gsp_jax.other.x")] == [0, 1, 1, None, None]


def test_every_library_import_follows_the_layer_table():
    """The folders are the layers: a module imports only its own folder's modules or those of the folders above
    (docs/architecture.md), every module of the library sits in a folder of the table, and every folder has a row."""
    table = _layer_table()
    folders = {"gsp_jax." + p.name for p in (ROOT / "gsp_jax").iterdir() if (p / "__init__.py").is_file()} - \
        {"gsp_jax.models"}
    assert set(table) == folders, f"folders without a row: {sorted(folders - set(table))}; " \
        f"rows without a folder: {sorted(set(table) - folders)}"
    graph = _graph("gsp_jax")
    unplaced = sorted(m for m in graph if m != "gsp_jax" and _layer(table, m) is None)
    assert not unplaced, f"modules in no folder of docs/architecture.md's table: {unplaced}"
    upward = _upward(table, graph)
    assert not upward, "\n".join(upward)


def _upward(table: dict[str, int], graph: dict[str, set[str]]) -> list[str]:
    """Every import of a module from a folder below its own."""
    return [f"{m} (row {_layer(table, m)}) imports {t} (row {_layer(table, t)})" for m in sorted(graph)
            if m != "gsp_jax" for t in sorted(graph[m]) if t != "gsp_jax" and _layer(table, t) > _layer(table, m)]


def test_the_layer_check_finds_an_upward_import():
    """A model module importing the surrogate's folder is named; one importing its own folder or core is not."""
    table = _layer_table()
    graph = {"gsp_jax.model.scenario": {"gsp_jax.surrogate.step", "gsp_jax.model.hand", "gsp_jax.core.files"},
             "gsp_jax.surrogate.step": {"gsp_jax.model.scenario"}, "gsp_jax.model.hand": set(),
             "gsp_jax.core.files": set()}
    assert _upward(table, graph) == [f"gsp_jax.model.scenario (row {table['gsp_jax.model']}) imports "
                                     f"gsp_jax.surrogate.step (row {table['gsp_jax.surrogate']})"]


def _functions(path: pathlib.Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node.name, node.end_lineno - node.lineno + 1


def test_no_library_function_is_longer_than_120_lines():
    long = [f"{p.relative_to(ROOT)}: {name} ({n} lines)" for p in sorted((ROOT / "gsp_jax").rglob("*.py"))
            for name, n in _functions(p) if n > 120]
    assert not long, "\n".join(long)


def test_importing_the_package_changes_no_jax_setting():
    """`import gsp_jax` (and the public face's names) leaves every JAX config value as it was, and registers no
    Gymnasium environment: the cache and the environment are switched on by a call."""
    import subprocess
    import sys

    probe = """
import json, os, jax
before = {k: repr(v) for k, v in jax.config.values.items()}
import gymnasium
envs = set(gymnasium.registry)
import gsp_jax
from gsp_jax import Surrogate, context, plan, Physics  # the lazy names too
after = {k: repr(v) for k, v in jax.config.values.items()}
print(json.dumps(dict(changed=sorted(k for k in after if after[k] != before.get(k)),
                      envs=sorted(set(gymnasium.registry) - envs))))
"""
    env = {k: v for k, v in __import__("os").environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR",)}
    env.update(JAX_PLATFORMS="cpu", GSP_JAX_CACHE="")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    got = __import__("json").loads(out.stdout.strip().splitlines()[-1])
    assert got == {"changed": [], "envs": []}


SHARED = ("experiments", "experiments.common", "experiments.processes", "experiments.cli")  # every command may
# import these (`cli`: a pipeline runs its stages with `cli.run_command`)


def test_commands_import_the_library_and_common_only():
    """Every command module (and a command package's own modules) imports from `experiments` only
    `experiments.common`, the process launcher `experiments.processes` and its own package, and no name of `gsp_jax`
    that starts with an underscore."""
    from experiments.cli import COMMANDS

    commands = {path for path, _ in COMMANDS.values()}
    modules = {_module(p) for p in (ROOT / "experiments").rglob("*.py")}
    wrong = []
    for path in sorted((ROOT / "experiments").rglob("*.py")):
        mod = _module(path)
        if mod in ("experiments", "experiments.__main__", "experiments.cli", "experiments.common") or \
                path.name == "__init__.py" and \
                mod not in commands:
            continue
        own = next((c for c in commands if mod == c or mod.startswith(c + ".")), None)
        for base, name in _imports(path):
            target = f"{base}.{name}" if f"{base}.{name}" in modules else base
            if base.startswith("gsp_jax") and (name.startswith("_") or any(p.startswith("_") for p in base.split("."))):
                wrong.append(f"{mod}: {target} (private)")
            elif target.startswith("experiments") and target not in SHARED and not (
                    own and (target == own or target.startswith(own + "."))):
                wrong.append(f"{mod}: {target}")
    assert not wrong, "\n".join(wrong)


def test_the_architecture_page_names_every_folder_of_code():
    text = (ROOT / "docs" / "architecture.md").read_text()
    folders = sorted({str(p.parent.relative_to(ROOT)) for top in ("gsp_jax", "experiments")
                      for p in (ROOT / top).rglob("*.py")})
    missing = [f for f in folders if f"`{f}/`" not in text]
    assert not missing, f"docs/architecture.md does not name: {missing}"


def test_every_folder_of_code_is_a_declared_package():
    """pyproject.toml lists its packages by name: a new folder of code must be among them, or the wheel lacks it."""
    import tomllib

    declared = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {_module(p) for top in ("gsp_jax", "experiments") for p in (ROOT / top).rglob("__init__.py")}
    assert folders - declared == set(), f"folders of code not in pyproject's packages: {sorted(folders - declared)}"


def test_an_old_module_path_warns_and_gives_the_module_in_its_folder():
    """`from gsp_jax import dp` (the paths before the layer folders) lives one release: a DeprecationWarning naming
    the new place, and the module itself; every old name maps to a module that exists."""
    import importlib
    import warnings

    import gsp_jax
    from gsp_jax.planning import dp

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert gsp_jax.dp is dp
    assert any(issubclass(w.category, DeprecationWarning) and "gsp_jax.planning.dp" in str(w.message) for w in caught)
    for old, new in gsp_jax._MOVED.items():
        assert importlib.util.find_spec(new) is not None, (old, new)
        assert not (ROOT / "gsp_jax" / f"{old}.py").exists(), old
