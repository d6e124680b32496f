"""The front door: the README stays short, its links and the docs' links resolve, it cites no commit, and its
results table says what the measured data says."""
from __future__ import annotations

import json
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _links(path: pathlib.Path) -> list[str]:
    text = path.read_text()
    return [m for m in re.findall(r"\]\(([^)\s]+)\)", text)
            if not m.startswith(("http://", "https://", "#", "mailto:"))]


def test_readme_is_short_and_cites_no_commit():
    text = README.read_text()
    assert len(text.encode()) <= 10 * 1024, f"README.md is {len(text.encode())} bytes (at most 10 KB)"
    hashes = [h for h in re.findall(r"\b[0-9a-f]{7,40}\b", text) if re.search(r"[a-f]", h) and re.search(r"\d", h)]
    assert not hashes, f"README.md cites commits: {hashes}"
    assert (ROOT / "LICENSE").read_text().lstrip().startswith("Apache License")


def test_every_relative_link_resolves():
    pages = [README, ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "docs/report/REPORT.md"]
    broken = [f"{p.relative_to(ROOT)}: {link}" for p in pages for link in _links(p)
              if not (p.parent / link.split("#")[0]).exists()]
    assert not broken, "broken links:\n" + "\n".join(broken)


def _row(label: str) -> list[str]:
    for line in README.read_text().splitlines():
        cells = [c.strip().strip("*").strip() for c in line.split("|")[1:-1]]
        if cells and cells[0] == label:
            return cells[1:]
    raise AssertionError(f"README.md has no results row {label!r}")


def _pm(cell: str) -> tuple[float, float]:
    mean, ci = cell.replace("−", "-").split("±")
    return float(mean), float(ci)


DATA = ROOT / "docs/data"
SCHEMA = {"name", "date", "commit", "device", "command", "figures"}  # and an optional "note"
ORDER = ["dp-base", "rl", "L1", "L2", "dp-opt"]  # the README's columns


def _file(name: str) -> dict:
    return json.loads((DATA / f"{name}.json").read_text())


def _machine(device: str) -> str:
    """The machine of a recorded device string as the README names it: 'H100', 'H200', ... or 'CPU'."""
    found = re.search(r"\b([A-Z]\d{2,3})\b", device)
    if found:
        return found.group(1)
    assert device.lower().startswith("cpu"), f"no machine in the device {device!r}"
    return "CPU"


def _units() -> list[str]:
    """The README's claims: each table row, each list item, each paragraph (a machine named in one names it for all
    the figures of that one)."""
    units, item = [], []
    for line in README.read_text().splitlines() + [""]:
        starts = line.startswith(("|", "- ", "#")) or not line.strip()
        if starts and item:
            units.append(" ".join(item))
            item = []
        if line.startswith("|"):
            units.append(line)
        elif line.strip():
            item.append(line.strip())
    return units


def _cited(unit: str) -> list[str]:
    """The docs/data files a README claim cites: `<figure>_<device>` in backticks."""
    return [n for n in re.findall(r"`([a-z0-9_]+)`", unit) if (DATA / f"{n}.json").is_file()]


def _row(label: str) -> tuple[str, list[str]]:
    """(the docs/data file it cites, the cells) of the README's results row whose label starts with `label`."""
    for line in README.read_text().splitlines():
        cells = [c.strip().strip("*").strip() for c in line.split("|")[1:-1]]
        if cells and cells[0].startswith(label):
            cited = _cited(cells[0])
            assert len(cited) <= 1, (label, cited)
            return (cited[0] if cited else ""), cells[1:]
    raise AssertionError(f"README.md has no results row {label!r}")


def _pm(cell: str) -> tuple[float, float]:
    mean, ci = cell.replace("−", "-").split("±")
    return float(mean), float(ci)


def _report() -> dict:
    return json.loads((ROOT / "docs/report/report.json").read_text())


def _gpu() -> str:
    """The slug of the report's run's GPU (h100, h200, ...): its files are docs/data/<figure>_<gpu>."""
    return _machine(_report()["device"]).lower()


def test_every_readme_figure_names_the_machine_of_its_data_file():
    """Each README claim that cites a docs/data file names that file's machine (the one its recorded device says,
    also the file's name's suffix); each results row with our numbers cites one."""
    cited = 0
    for unit in _units():
        for name in _cited(unit):
            cited += 1
            row = _file(name)
            machine = _machine(row["device"])
            assert name.endswith("_" + machine.lower()), f"{name}.json records {row['device']!r}"
            assert re.search(rf"\b{machine}\b( host)?", unit), (f"README names no {machine} "
                                                                 f"where it cites {name}: {unit}")
    assert cited >= 8, f"the README cites {cited} docs/data files"
    for label in ("Fig. 4a", "Fig. 4b: falls", "Fig. 4b: tool angle", "Table 1: ours"):
        assert _row(label)[0], f"README results row {label!r} cites no docs/data file"


def test_results_table_is_docs_data():
    """The README's results rows (Fig. 4a, Fig. 4b, Table 1) equal the docs/data file each cites, at the digits
    shown."""
    name, cells = _row("Fig. 4a: surrogate return")
    fig4a = _file(name)["figures"]["relative"]
    for cell, p in zip(cells, ORDER[:4]):
        assert _pm(cell) == (round(fig4a[p]["mean"], 2), round(fig4a[p]["ci95"], 2)), (p, cell)
    assert cells[4] == "0"
    name, cells = _row("Fig. 4b: falls / 27")
    fig4b = _file(name)["figures"]
    assert [int(x) for x in cells] == [fig4b[p]["falls"] for p in ORDER] and fig4b["rl"]["episodes"] == 27
    name, cells = _row("Fig. 4b: tool angle error")
    fig4b = _file(name)["figures"]
    for cell, p in zip(cells, ORDER):
        assert _pm(cell) == (round(fig4b[p]["mean_deg"], 1), round(fig4b[p]["ci95_deg"], 1)), (p, cell)
    name, cells = _row("Table 1: ours")
    table1 = _file(name)["figures"]
    for cell, p in zip(cells, ORDER):
        value = float(cell.removesuffix(" s"))
        digits = len(cell.removesuffix(" s").split(".")[1])
        assert value == round(table1["warm_s"][p], digits), (p, cell)
    assert [float(c.removesuffix(" s")) for c in _row("Table 1: time per episode, paper")[1]] == [
        table1["paper_s"][p] for p in ORDER]


def _named(prefix: str, device: str = "[a-z0-9]+") -> str:
    """The one docs/data record `<prefix><device>` that the README cites (not the learned term's,
    `<prefix>learned_<device>`); `device` a pattern (e.g. a GPU host's, `h\\d+`)."""
    names = {n for unit in _units() for n in _cited(unit) if re.fullmatch(re.escape(prefix) + device, n)}
    assert len(names) == 1, f"README.md cites {sorted(names)} for {prefix}*"
    return names.pop()


def _claim(pattern: str) -> tuple[str, ...]:
    found = re.findall(pattern, " ".join(README.read_text().split()))
    assert len(found) == 1, f"README.md states {pattern!r} {len(found)} times"
    return found[0] if isinstance(found[0], tuple) else (found[0],)


def test_readme_sentences_are_docs_data():
    """The figures in the README's sentences equal the files they cite: the L1 decision's latency, L1-physics and
    the envelope (stress set), RL's falls by the oracle (evaluation set), the report's Holm-corrected p."""
    latency_name, fig4b_name = _named("bench_latency_", r"h\d+"), _named("fig4b_")
    latency = _file(latency_name)["figures"]["policies"]["L1"]["decision_median_s"]
    assert float(_claim(rf"One L1 decision takes ([\d.]+) ms \(median\) on the H\d+ host \(`{latency_name}`\)")[0]) \
        == round(1000 * latency, 1)
    fig4b = _file(fig4b_name)["figures"]["L1-physics"]
    falls, n, angle = _claim(r"evaluation set: (\d+) of (\d+) falls, ([\d.]+)° mean angle error "
                             rf"\((?:H\d+ host|2-core CPU), `{fig4b_name}`\)")
    assert (int(falls), int(n), float(angle)) == (fig4b["falls"], fig4b["episodes"], round(fig4b["mean_deg"], 1))
    stress_name, eval_name = _named("envelope_stress_"), _named("envelope_eval_")
    stress = _file(stress_name)["figures"]
    kinds, pool = stress["summary"]["kinds"], stress["summary"]["pool"]
    got = _claim(r"stress set: (\d+) of (\d+) falls, regret (\d+) \(four tips (\d+), DP optimal (\d+), L1 (\d+); "
                 rf"H\d+ host, `{stress_name}`\)")
    assert tuple(map(int, got)) == (kinds["L1-physics"]["falls"], stress["episodes"], kinds["L1-physics"]["regret"],
                                    kinds["four-tips"]["falls"], kinds["dp-opt"]["falls"], kinds["L1"]["falls"])
    got = _claim(r"The stress set has (\d+) episodes.*? The constant four-tip grasp drops (\d+) of them, (\d+) where "
                 r"forces existed"
                 r".*?: DP optimal (\d+), L1 (\d+), L2 (\d+), RL (\d+); L1-physics (\d+)\. Of the sequences the "
                 rf"surrogate calls feasible, (\d+)% hold \(aim 95%\)\. H\d+ host, `{stress_name}`")
    four = kinds["four-tips"]
    assert tuple(map(int, got)) == (stress["episodes"], four["falls"], four["controller"],
                                    *(kinds[k]["regret"] for k in ("dp-opt", "L1", "L2", "rl", "L1-physics")),
                                    round(100 * pool["feasible_hold_share"]))
    rho, auc = _claim(r"Spearman ρ ([\d.]+), AUC ([\d.]+) \(holds against falls\) on the stress pool \(H\d+ host, "
                      rf"`{stress_name}`\)")
    assert (float(rho), float(auc)) == (round(pool["spearman_pooled"], 2), round(pool["auc_pooled"], 2))
    rl = _file(eval_name)["figures"]["summary"]["kinds"]["rl"]
    falls = _claim(rf"RL's (\d+) falls are all necessary by the feasibility oracle \(H\d+ host, `{eval_name}`\)")
    assert int(falls[0]) == rl["falls"] == rl["necessary"]
    holm = {(p["a"], p["b"]): p["p_holm"] for p in _report()["fig4a"]["anova"]["posthoc"]}
    bound = float(_claim(r"L1 and L2 beat RL and DP baseline in the surrogate \(Holm-corrected p ≤ ([\d.]+)\)")[0])
    assert max(holm[a, b] for a in ("dp-base", "rl") for b in ("L1", "L2")) <= bound


def test_readme_learned_term_sentences_are_docs_data():
    """The learned physics term's figures in the README equal the records they cite: the stress set's falls and
    regrets, its feasible-hold share, AUC and the share of those predicted to hold that held; the evaluation set's
    falls; the L1 decision's latency."""
    stress = _file("envelope_stress_learned_h200")["figures"]["summary"]
    kinds, pool = stress["kinds"], stress["pool"]
    got = _claim(r"With it on the stress set, DP optimal falls (\d+) times, regret (\d+); L1 (\d+), L2 (\d+), RL (\d+) "
                 r"\(retrained\); of the surrogate-feasible sequences (\d+)% hold, AUC ([\d.]+) \(H200 host, "
                 r"`envelope_stress_learned_h200`\);\s+(\d+)% of those it predicts to hold")
    assert tuple(float(g) for g in got) == (
        kinds["dp-opt"]["falls"], kinds["dp-opt"]["regret"], kinds["L1"]["regret"], kinds["L2"]["regret"],
        kinds["rl"]["regret"], round(100 * pool["feasible_hold_share"]), round(pool["auc_pooled"], 2),
        round(100 * pool["predicted_hold_share"]))
    evals = _file("envelope_eval_learned_h200")["figures"]["summary"]["kinds"]
    falls, n = _claim(r"Evaluation set: DP optimal, L1, L2 (\d+) of (\d+) falls "
                      r"\(H200 host, `envelope_eval_learned_h200`\)")
    assert all(evals[k]["falls"] == int(falls) for k in ("dp-opt", "L1", "L2")) and int(n) == evals["L1"]["episodes"]
    latency = _file("bench_latency_learned_h200")["figures"]["policies"]["L1"]["decision_median_s"]
    ms = _claim(r"One L1 decision takes ([\d.]+) ms \(`bench_latency_learned_h200`, H200 host\)")[0]
    assert float(ms) == round(1000 * latency, 1)


def test_docs_data_has_one_schema_and_a_history_per_result():
    """Every current result in docs/data has the one schema, is named <figure>_<device> after the machine it records,
    and its history (docs/data/history/<name>.jsonl, a row per run) ends with it; nothing else lives there."""
    current = sorted(DATA.glob("*.json"))
    expected = {f"fig4a_{_gpu()}", f"fig4b_{_gpu()}", f"table1_{_gpu()}", _named("envelope_stress_"),
                _named("envelope_eval_")}
    assert {p.stem for p in current} >= expected
    assert {p.name for p in DATA.iterdir()} == {p.name for p in current} | {"history"}, sorted(DATA.iterdir())
    for path in current:
        row = json.loads(path.read_text())
        assert SCHEMA <= set(row) <= SCHEMA | {"note"}, (path.name, sorted(row))
        assert row["name"] == path.stem and isinstance(row["figures"], dict) and row["figures"], path.name
        assert path.stem.endswith("_" + _machine(row["device"]).lower()), (path.name, row["device"])
        history = (DATA / "history" / f"{path.stem}.jsonl").read_text().splitlines()
        assert json.loads(history[-1]) == row, f"{path.name}: the history's last row is not the current result"
    assert {p.stem for p in (DATA / "history").iterdir()} == {p.stem for p in current}


def test_the_history_manifest_lists_every_file():
    """docs/history/<date>/MANIFEST.md lists (and links) every file of its folder."""
    for folder in sorted((ROOT / "docs/history").iterdir()):
        listed = set(re.findall(r"^\| \[([^\]]+)\]\(", (folder / "MANIFEST.md").read_text(), re.M))
        files = {f.relative_to(folder).as_posix() for f in folder.rglob("*") if f.is_file() and f.name != "MANIFEST.md"}
        assert listed == files, (sorted(files - listed), sorted(listed - files))


def test_the_report_is_the_run_docs_data_holds():
    """docs/report (REPORT.md, report.json) and docs/data's Fig. 4a, Fig. 4b and Table 1 come from the same run."""
    from experiments.paper import fig4a, fig4b
    from experiments.paper.table1 import episode as table1

    report = _report()
    for stage, module in (("fig4a", fig4a), ("fig4b", fig4b), ("table1", table1)):
        assert module.figures(report[stage]) == _file(f"{stage}_{_gpu()}")["figures"], stage


def test_record_writes_the_current_result_and_appends_its_history(tmp_path, monkeypatch):
    """`python -m experiments --record <command>`: `Run.record_figures` writes the schema's row, named for its figure
    and machine, and appends it to the history; without --record it writes nothing."""
    from experiments import common

    assert common.Run().record_figures("bench_x", {"a": 1.0}, data=tmp_path) is None and not any(tmp_path.iterdir())
    run = common.Run(record=True)
    first = run.record_figures("bench_x", {"a": 1.0}, data=tmp_path)
    second = run.record_figures("bench_x", {"a": 2.0}, data=tmp_path)
    assert set(first) == SCHEMA and first["figures"] == {"a": 1.0}
    slug = common.device_slug()
    assert first["name"] == f"bench_x_{slug}"
    assert json.loads((tmp_path / f"bench_x_{slug}.json").read_text()) == second
    rows = [json.loads(line) for line in (tmp_path / "history" / f"bench_x_{slug}.jsonl").read_text().splitlines()]
    assert rows == [first, second]


STALE_MARK = "†"  # a README claim citing a stale record says so with this mark (the README's Results explain it)


def test_no_readme_figure_is_stale():
    """Every docs/data record the README cites was made by its figure's documented command
    (`experiments/paper/figures.py`) at a commit whose code it measures is the code here: a change to that code since
    (`git diff`), a record from a tree with uncommitted changes or by another command makes the figure stale until
    `python -m experiments --record figures` records it again -- or until the README marks the claim stale
    (`STALE_MARK`). A marked claim must cite a stale record: the mark goes when the figure is re-recorded."""
    import subprocess

    import pytest

    from experiments.paper import figures

    if subprocess.run(["git", "rev-parse", "--is-shallow-repository"], cwd=ROOT, capture_output=True,
                      text=True).stdout.strip() != "false":
        pytest.skip("needs the project's whole git history (a full clone)")
    units = [(unit, _cited(unit)) for unit in _units()]
    cited = sorted({name for _, names in units for name in names})
    assert cited, "the README cites no docs/data record"
    why = {name: figures.stale(_file(name)) for name in cited}
    unmarked = {name: why[name] for unit, names in units for name in names if why[name] and STALE_MARK not in unit}
    assert not unmarked, "stale README figures (python -m experiments --record figures, or mark them):\n" + "\n".join(
        f"{name}: {'; '.join(w)}" for name, w in unmarked.items())
    marked = [unit for unit, names in units if STALE_MARK in unit and names and not any(why[n] for n in names)]
    assert not marked, "README claims marked stale whose records are current (drop the mark):\n" + "\n".join(marked)


def _scratch_clone(tmp_path):
    """(a clone of the project's last commit in tmp_path, its commit in 12 hex digits); skips without git."""
    import shutil
    import subprocess

    import pytest

    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs git and the project's repository")
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", "--depth", "1", f"file://{ROOT}", str(clone)], check=True)
    head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=clone, capture_output=True, text=True,
                          check=True).stdout.strip()
    return clone, head


def test_staleness_sees_a_change_to_the_code_a_record_measures(tmp_path):
    """`figures.stale` on a record of the current commit: current as long as the code it measures is unchanged (a
    file outside it changed, a new file no measured one imports, another shipped model's files); a measured file
    changed or deleted, a dirty tree or another command make it stale (git in a scratch clone)."""
    import subprocess

    from experiments import common
    from experiments.paper import figures

    clone, head = _scratch_clone(tmp_path)
    fig = next(f for f in figures.FIGURES if f.name == "envelope-stress")
    row = dict(name="envelope_stress_h100", commit=head,
               command="python -m experiments --record " + " ".join(fig.command))
    original = common.ROOT
    try:
        common.ROOT = clone
        assert figures.stale(row) == []
        assert figures.stale(dict(row, commit=head + "+dirty")) and figures.stale(dict(row, command="python -m "
                                                                                     "experiments envelope"))
        (clone / "README.md").write_text("not measured\n")
        (clone / "gsp_jax" / "new_module.py").write_text("x = 1\n")  # added: reached only through an import
        subprocess.run(["git", "add", "-A"], cwd=clone, check=True)
        assert figures.stale(row) == []
        subprocess.run(["git", "rm", "-q", "gsp_jax/core/stats.py"], cwd=clone, check=True)
        assert any("gsp_jax/core/stats.py" in why for why in figures.stale(row))
        subprocess.run(["git", "reset", "-q", "--hard"], cwd=clone, check=True)
        for other in ("models/allegro/scene.learned.npz", "models/policies/hammer_ppo_dp_seed0.model.json"):
            with open(clone / other, "ab") as f:  # another shipped model's: not what a figure of the default measures
                f.write(b"\n")
        assert figures.stale(row) == []
        with open(clone / "models" / "scene.learned.npz", "ab") as f:
            f.write(b"\n")
        assert any("models/scene.learned.npz" in why for why in figures.stale(row))
        subprocess.run(["git", "reset", "-q", "--hard"], cwd=clone, check=True)
        with open(clone / "gsp_jax" / "surrogate" / "reward.py", "a") as f:
            f.write("\n# changed\n")
        assert any("gsp_jax/surrogate/reward.py" in why for why in figures.stale(row))
    finally:
        common.ROOT = original


def test_a_figures_run_records_the_commit_it_started_from(tmp_path, monkeypatch):
    """`figures`: its records and report are tracked files, so the second figure of a run would find the tree
    changed by the first; every record of the run names the commit the run started from (clean: the records and the
    report aside), and a change to the code makes it `+dirty` (git in a scratch clone)."""
    import argparse

    from experiments import cli, common
    from experiments.paper import figures

    clone, head = _scratch_clone(tmp_path)
    cpu = [f for f in figures.FIGURES if f.machine == "cpu"]
    tracked = [p.stem.rsplit("_", 1)[0] for p in sorted((clone / "docs/data").glob("*_cpu.json"))]
    assert len(cpu) >= 2 and tracked

    def run_command(words, run):  # each figure records one tracked record: the tree differs from HEAD after the first
        run.record_figures(tracked[0], {"words": len(words)})

    for k, v in dict(ROOT=clone, DATA=clone / "docs/data").items():
        monkeypatch.setattr(common, k, v)
    monkeypatch.setattr(cli, "run_command", run_command)
    monkeypatch.setattr(common, "device_slug", lambda: "cpu")
    args = argparse.Namespace(list=False, stale=False, machine="cpu", only=None)
    figures.main(args, common.Run(record=True))
    rows = [json.loads(line) for line in (clone / f"docs/data/history/{tracked[0]}_cpu.jsonl").read_text().splitlines()]
    assert [r["commit"] for r in rows[-len(cpu):]] == [head] * len(cpu)
    assert [r["command"] for r in rows[-len(cpu):]] == ["python -m experiments --record " + " ".join(f.command)
                                                        for f in cpu]
    with open(clone / "gsp_jax" / "surrogate" / "reward.py", "a") as f:
        f.write("\n# changed\n")
    figures.main(argparse.Namespace(list=False, stale=False, machine="cpu", only=[cpu[0].name]),
                 common.Run(record=True))
    last = json.loads((clone / f"docs/data/{tracked[0]}_cpu.json").read_text())
    assert last["commit"] == head + "+dirty"


def test_hands_table_is_docs_data():
    """The README's hands x tools table equals the record its paragraph cites (falls per planner, one number per
    tool of the hand's row, in the row's order), each cell planned with a learned term where one is shipped, and
    that record is the hands figure's (`figures`: `hands --learned`, on a CPU)."""
    name = _named("hands_learned_")
    cells = {c["model"]: c for c in _file(name)["figures"]["cells"]}
    rows = {"ours": ("wrench", "screwdriver", "hammer"), "Allegro": ("allegro", "allegro-screwdriver"),
            "LEAP": ("leap-bar", "leap-screwdriver"), "Shadow": ("shadow-bar", "shadow-screwdriver"),
            "Sharpa": ("sharpa-bar", "sharpa-screwdriver")}
    assert set(cells) == {m for models in rows.values() for m in models}, sorted(cells)
    for label, models in rows.items():
        _, got = _row(label)
        for planner, cell in zip(("dp-opt", "L1", "L1-physics"), got):
            falls = [int(x) for x in cell.split("/")]
            assert falls == [cells[m][planner]["falls"] for m in models], (label, planner, cell)
    folders = {"wrench": "", "screwdriver": "screwdriver", "hammer": "hammer", "allegro": "allegro",
               "allegro-screwdriver": "allegro-screwdriver"}
    for m, c in cells.items():  # the term where its weights are shipped (a published cell's beside its scene)
        folder = ROOT / "models" / folders[m] if m in folders else ROOT / "examples" / "published" / m
        assert c["learned"] == (folder / "scene.learned.npz").exists(), (m, c["learned"])
    assert _file(name)["command"] == "python -m experiments --record hands --learned"


def test_readme_controller_sentence_is_docs_data():
    """The contact controller's sentence (issue 84) equals the three CPU records it cites: the stress set's controller
    falls of four tips, DP optimal, L1 and L2 with the default (measured frames), with `--controller paper` and with
    `--controller predictive`."""
    ks = ("four-tips", "dp-opt", "L1", "L2")
    runs = [_file(f"envelope_stress_learned{c}_cpu")["figures"]["summary"]["kinds"]
            for c in ("", "_paper", "_predictive")]
    got = _claim(r"Stress\s+set, controller falls of four tips / DP optimal / L1 / L2: (\d+) / (\d+) / (\d+) / (\d+); "
                 r"paper's (\d+) / (\d+) / (\d+) / (\d+); predictive\s+\(\[hold rolled out\]\([^)]*\)\) "
                 r"(\d+) / (\d+) / (\d+) / (\d+)\. Aim 3 \(2-core CPU,\s+`envelope_stress_learned_cpu`, "
                 r"`envelope_stress_learned_paper_cpu`, `envelope_stress_learned_predictive_cpu`\)")
    assert tuple(map(int, got)) == tuple(r[k]["controller"] for r in runs for k in ks)


def test_readme_world_gap_figures_are_docs_data():
    """The world gap's figures in the README equal the records they cite, beside the nominal ones: DP optimal, L1
    and L2's falls on the evaluation and stress sets without and with `--world gap`, with the default controller and
    with `--controller robust`, and Fig. 4b's row."""
    kinds = lambda name: _file(name)["figures"]["summary"]["kinds"]  # noqa: E731
    got = _claim(r"falls of DP optimal / L1 / L2, evaluation set (\d+) / (\d+) / (\d+) → (\d+) / (\d+) / (\d+), stress "
                 r"set (\d+) / (\d+) / (\d+) → (\d+) / (\d+) / (\d+) \(2-core CPU, `envelope_eval_learned_gap_cpu`, "
                 r"`envelope_stress_learned_gap_cpu`\)")
    want = [kinds(f"envelope_{s}_learned{w}_cpu")[k]["falls"] for s in ("eval", "stress") for w in ("", "_gap")
            for k in ("dp-opt", "L1", "L2")]
    assert list(map(int, got)) == want
    cited, row = _row("Fig. 4b in a [world unlike the model](docs/world.md), `--world gap`: falls / 27")
    assert cited == "fig4b_gap_cpu" and list(map(int, row)) == [_file(cited)["figures"][k]["falls"] for k in ORDER]
    got = _claim(r"`envelope_stress_learned_gap_cpu`\)\. `--controller robust`: (\d+) / (\d+) / (\d+) → (\d+) / "
                 r"(\d+) / (\d+) and (\d+) / (\d+) / (\d+) → (\d+) / (\d+) / (\d+) "
                 r"\(`envelope_eval_learned_robust_cpu`, `envelope_eval_learned_robust_gap_cpu`, "
                 r"`envelope_stress_learned_robust_cpu`, `envelope_stress_learned_robust_gap_cpu`\)")
    want = [kinds(f"envelope_{s}_learned_robust{w}_cpu")[k]["falls"] for s in ("eval", "stress")
            for w in ("", "_gap") for k in ("dp-opt", "L1", "L2")]
    assert list(map(int, got)) == want
