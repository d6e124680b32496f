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


def test_results_table_is_the_committed_report():
    """The README's results rows (Fig. 4a, Fig. 4b, Table 1) equal docs/report/report.json, the run they come from,
    at the digits shown."""
    report = json.loads((ROOT / "docs/report/report.json").read_text())
    order = ["dp-base", "rl", "L1", "L2", "dp-opt"]
    fig4a = report["fig4a"]["relative"]
    cells = _row("Fig. 4a: surrogate return − DP optimal (mean ± 95% CI), H100")
    for cell, p in zip(cells, order[:4]):
        assert _pm(cell) == (round(fig4a[p]["mean"], 2), round(fig4a[p]["ci95"], 2)), (p, cell)
    assert cells[4] == "0"
    fig4b = report["fig4b"]
    assert [int(x) for x in _row("Fig. 4b: falls / 27 in C MuJoCo, H100 host")] == [fig4b[p]["falls"] for p in order]
    for cell, p in zip(_row("Fig. 4b: tool angle error [deg] (mean ± 95% CI; 180 for a fall)"), order):
        assert _pm(cell) == (round(fig4b[p]["mean_deg"], 1), round(fig4b[p]["ci95_deg"], 1)), (p, cell)
    table1 = report["table1"]["policies"]
    for cell, p in zip(_row("Table 1: ours, one H100"), order):
        value = float(cell.removesuffix(" s"))
        digits = len(cell.removesuffix(" s").split(".")[1])
        assert value == round(table1[p]["warm_s"], digits), (p, cell)
    paper = report["table1"]["paper"]["table1_s"]
    assert [float(c.removesuffix(" s")) for c in _row("Table 1: online time per episode, paper (32-core Xeon)")] == [
        paper[p] for p in order]
