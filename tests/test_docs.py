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


def test_results_table_is_the_measured_fig4b():
    """The README's Fig. 4b rows equal the committed measurement they come from."""
    data = json.loads((ROOT / "docs/fig4b_h100_feedback_floor.json").read_text())["policies"]
    order = ["dp-base", "rl", "L1", "L2", "dp-opt"]
    rows = {line.split("|")[1].strip(): [c.strip().strip("*") for c in line.split("|")[2:-1]]
            for line in README.read_text().splitlines() if line.startswith("| Fig. 4b")}
    falls = rows["Fig. 4b: falls / 27 in C MuJoCo, H100 host"]
    assert [int(x) for x in falls] == [data[p]["falls"] for p in order]
    angles = rows["Fig. 4b: tool angle error [deg] (mean ± 95% CI; 180 for a fall)"]
    for cell, p in zip(angles, order):
        mean, ci = (float(x) for x in cell.split("±"))
        assert (mean, ci) == (round(data[p]["mean_deg"], 1), round(data[p]["ci95_deg"], 1)), (p, cell)
