"""BENCHMARKS.md is a page of today's figures: one table per area, each row with its figure, value, goal, machine
type, date, commit and command, every commit one of this repository's; and every reference to it elsewhere
(``BENCHMARKS.md, "Area", row "..."``) names a section and rows that exist."""

from __future__ import annotations

import re
import subprocess

from shared_data import REPO

PAGE = REPO / "BENCHMARKS.md"
AREAS = ("Formats", "Rasterizer", "Fit", "Build and main job", "Training", "Model accuracy", "Viewer", "GPU")
COLUMNS = ["figure", "value", "goal", "machine", "date", "commit", "command"]
#: A reference: BENCHMARKS.md, "Section"[, row(s) "first words of a row"( and "...")*]
REFERENCE = re.compile(r'BENCHMARKS\.md,\s+"([^"]+)"((?:,?\s+rows?\s+"[^"]+"(?:\s+and\s+"[^"]+")*)?)')


def sections() -> dict[str, list[list[str]]]:
    """Each ``##`` section of the page with the cells of its figure table's rows."""
    out: dict[str, list[list[str]]] = {}
    current = None
    for line in PAGE.read_text().splitlines():
        if line.startswith("## "):
            current = out.setdefault(line[3:].strip(), [])
        elif current is not None and line.startswith("| ") and not line.startswith("| figure |"):
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
            if len(cells) == len(COLUMNS):
                current.append(cells)
    return out


def test_the_page_is_short_and_has_one_table_per_area_with_every_column():
    text = PAGE.read_text()
    assert len(text.splitlines()) <= 400
    header = f"| {' | '.join(COLUMNS)} |"
    for area in AREAS:
        body = text.split(f"\n## {area}\n", 1)[1].split("\n## ", 1)[0]
        assert header in body, area
    found = sections()
    rows = [row for area in AREAS for row in found[area]]
    assert len(rows) >= 60
    for figure, value, goal, machine, date, commit, command in rows:
        assert figure and value and machine and command, figure
        assert re.fullmatch(r"2\d{3}-\d{2}-\d{2}", date), (figure, date)
        assert re.fullmatch(r"[0-9a-f]{7,40}( against [0-9a-f]{7,40})?", commit), (figure, commit)


def test_every_commit_on_the_page_is_in_the_history():
    commits = {c for area in AREAS for row in sections()[area] for c in re.findall(r"[0-9a-f]{7,40}", row[5])}
    assert len(commits) >= 20
    missing = [c for c in sorted(commits) if subprocess.run(["git", "cat-file", "-e", f"{c}^{{commit}}"], cwd=REPO,
                                                            capture_output=True).returncode != 0]
    assert missing == []


def test_every_reference_to_the_page_names_a_section_and_rows_it_has():
    found = sections()
    names = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout.split(b"\0")
    checked, wrong = 0, []
    for name in filter(None, (n.decode() for n in names)):
        path = REPO / name
        if name == "tests/test_benchmarks_page.py" or not path.is_file():
            continue
        if path.suffix not in {".md", ".py", ".sh", ""}:
            continue
        text = " ".join(re.sub(r"^\s*#+\s?", "", line) for line in path.read_text(errors="replace").splitlines())
        text = re.sub(r"\s+", " ", text)
        for match in REFERENCE.finditer(text):
            section, rows = match.group(1), re.findall(r'"([^"]+)"', match.group(2))
            checked += 1
            if section not in found:
                wrong.append(f"{name}: no section {section!r}")
                continue
            wrong += [f"{name}: no row {row!r} in {section!r}" for row in rows
                      if not any(cells[0].startswith(row) for cells in found[section])]
    assert checked >= 8  # README, scripts and tests point at the page
    assert wrong == [], "\n".join(wrong)
