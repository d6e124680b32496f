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
    return [m for m in re.findall(r"\]\(([^)\s]+)\)", text) if not m.startswith(("http://", "https://", "#", "mailto:"))]


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


def _data(name: str) -> dict:
    return json.loads((DATA / f"{name}.json").read_text())["figures"]


def _report() -> dict:
    return json.loads((ROOT / "docs/report/report.json").read_text())


def _gpu() -> str:
    """The GPU of the report's run as the README names it (H100, H200, ...); its Table 1 is docs/data/table1_<gpu>."""
    device = _report()["table1"].get("device", _report()["device"])  # Table 1's GPU (a partial run may be another's)
    found = re.search(r"\b([A-Z]\d{2,3})\b", device)
    assert found, f"report.json's Table 1 names no GPU: {device!r}"
    return found.group(1)


def test_results_table_is_docs_data():
    """The README's results rows (Fig. 4a, Fig. 4b, Table 1) equal docs/data (fig4a, fig4b, table1_<the report's
    GPU>), at the digits shown."""
    order = ["dp-base", "rl", "L1", "L2", "dp-opt"]
    fig4a = _data("fig4a")["relative"]
    cells = _row("Fig. 4a: surrogate return − DP optimal (mean ± 95% CI)")
    for cell, p in zip(cells, order[:4]):
        assert _pm(cell) == (round(fig4a[p]["mean"], 2), round(fig4a[p]["ci95"], 2)), (p, cell)
    assert cells[4] == "0"
    fig4b = _data("fig4b")
    assert [int(x) for x in _row("Fig. 4b: falls / 27 in C MuJoCo")] == [fig4b[p]["falls"] for p in order]
    for cell, p in zip(_row("Fig. 4b: tool angle error [deg] (mean ± 95% CI; 180 for a fall)"), order):
        assert _pm(cell) == (round(fig4b[p]["mean_deg"], 1), round(fig4b[p]["ci95_deg"], 1)), (p, cell)
    table1 = _data(f"table1_{_gpu().lower()}")
    for cell, p in zip(_row(f"Table 1: ours, one {_gpu()}"), order):
        value = float(cell.removesuffix(" s"))
        digits = len(cell.removesuffix(" s").split(".")[1])
        assert value == round(table1["warm_s"][p], digits), (p, cell)
    assert [float(c.removesuffix(" s")) for c in _row("Table 1: online time per episode, paper (32-core Xeon)")] == [
        table1["paper_s"][p] for p in order]


def test_docs_data_has_one_schema_and_a_history_per_result():
    """Every current result in docs/data has the one schema, and its history (docs/data/history/<name>.jsonl, a
    row per run) ends with it."""
    current = sorted(DATA.glob("*.json"))
    expected = {"fig4a", "fig4b", f"table1_{_gpu().lower()}", "envelope_stress", "envelope_eval"}
    assert {p.stem for p in current} >= expected
    for path in current:
        row = json.loads(path.read_text())
        assert SCHEMA <= set(row) <= SCHEMA | {"note"}, (path.name, sorted(row))
        assert row["name"] == path.stem and isinstance(row["figures"], dict) and row["figures"], path.name
        history = (DATA / "history" / f"{path.stem}.jsonl").read_text().splitlines()
        assert json.loads(history[-1]) == row, f"{path.name}: the history's last row is not the current result"


def test_the_report_is_the_run_docs_data_holds():
    """docs/report (REPORT.md, report.json) and docs/data's Fig. 4a, Fig. 4b and Table 1 come from the same run."""
    from experiments.paper import fig4a, fig4b
    from experiments.paper.table1 import episode as table1

    report = _report()
    assert fig4a.figures(report["fig4a"]) == _data("fig4a")
    assert fig4b.figures(report["fig4b"]) == _data("fig4b")
    assert table1.figures(report["table1"]) == _data(f"table1_{_gpu().lower()}")


def test_record_writes_the_current_result_and_appends_its_history(tmp_path, monkeypatch):
    """`python -m experiments --record <command>`: `common.record` writes the schema's row and appends it to the
    history; without --record it writes nothing."""
    from experiments import common

    monkeypatch.setattr(common, "RECORD", False)
    assert common.record("bench_x", {"a": 1.0}, data=tmp_path) is None and not any(tmp_path.iterdir())
    monkeypatch.setattr(common, "RECORD", True)
    first = common.record("bench_x", {"a": 1.0}, data=tmp_path)
    second = common.record("bench_x", {"a": 2.0}, data=tmp_path)
    assert set(first) == SCHEMA and first["figures"] == {"a": 1.0}
    assert json.loads((tmp_path / "bench_x.json").read_text()) == second
    rows = [json.loads(line) for line in (tmp_path / "history" / "bench_x.jsonl").read_text().splitlines()]
    assert rows == [first, second]
