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
    """Each file and folder the library table of docs/architecture.md names -> its row (0: the top row)."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text.split("### `gsp_jax/`: the library", 1)[1].split("\n#", 1)[0]
    rows = [line.split("|") for line in section.splitlines() if line.startswith("| ") and "`" in line]
    table = {}
    for i, cells in enumerate(rows):
        for name in re.findall(r"`([\w/]+?)(?:\.py)?`", cells[2]):
            table["gsp_jax." + name.strip("/").replace("/", ".")] = i
    return table


def _layer(table: dict[str, int], module: str) -> int | None:
    """The row of the most specific file or folder the table names for `module`."""
    parts = module.split(".")
    return next((table[".".join(parts[:k])] for k in range(len(parts), 1, -1) if ".".join(parts[:k]) in table), None)


def test_the_layer_finder_takes_the_most_specific_row():
    table = {"gsp_jax.a": 0, "gsp_jax.ppo": 2, "gsp_jax.ppo.networks": 1}
    assert [_layer(table, m) for m in ("gsp_jax.a", "gsp_jax.ppo.train", "gsp_jax.ppo.networks", "gsp_jax.b")] == \
        [0, 2, 1, None]


def test_every_library_import_follows_the_layer_table():
    """A module imports only its own row's modules or those of the rows above (docs/architecture.md), and every
    module of the library has a row."""
    table = _layer_table()
    assert len(set(table.values())) >= 8 and "gsp_jax.planners" in table and "gsp_jax.ppo.networks" in table
    graph = _graph("gsp_jax")
    unplaced = sorted(m for m in graph if m != "gsp_jax" and _layer(table, m) is None)
    assert not unplaced, f"modules docs/architecture.md's table does not place: {unplaced}"
    upward = [f"{m} (row {_layer(table, m)}) imports {t} (row {_layer(table, t)})" for m in sorted(graph)
              if m != "gsp_jax" for t in sorted(graph[m]) if t != "gsp_jax" and _layer(table, t) > _layer(table, m)]
    assert not upward, "\n".join(upward)


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
