"""References from code, scenarios and docs into docs/*.md name headings that exist.

A reference reads ``docs/algorithm.md, "Heading"`` (or ``[algorithm.md](algorithm.md), "Heading"``
inside docs/), optionally followed by an item number.
"""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIPPED = {".venv", ".git", "runs", "__pycache__", ".hypothesis", ".pytest_cache", "node_modules", "build", "dist",
           "typecheck"}  # typecheck/: symlinks to the package's own files, for mypy
SUFFIXES = {".py", ".md", ".yaml", ".yml"}
REFERENCE = re.compile(r"(\w+)\.md(?:\]\([^)\s]*\))?, \"([^\"\n]+)\"")
GONE = "ALGORITHM" + ".md"  # the file that docs/algorithm.md replaced (spelled so as not to match here)


def searched_files() -> list[Path]:
    files = []
    for path in ROOT.rglob("*"):
        parts = set(path.relative_to(ROOT).parts)
        if path.suffix in SUFFIXES and path.is_file() and not parts & SKIPPED and path != Path(__file__) \
                and not any(p.endswith(".egg-info") for p in parts):
            files.append(path)
    return files


TAG = re.compile(r"\s*\[[A-Z, ]+\]$")  # docs/algorithm.md marks headings by source: "System [P]"


def headings(doc: Path) -> set[str]:
    """The headings of ``doc``, each also without its source tag."""
    titles = {line.lstrip("#").strip() for line in doc.read_text().splitlines() if line.startswith("#")}
    return titles | {TAG.sub("", title) for title in titles}


def test_nothing_refers_to_the_removed_algorithm_file():
    stale = [f"{path.relative_to(ROOT)}:{n}" for path in searched_files()
             for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1) if GONE in line]
    assert stale == [], f"point these to the headings of docs/algorithm.md instead: {stale}"


def test_references_name_existing_headings():
    found, broken = 0, []
    for path in searched_files():
        for name, heading in REFERENCE.findall(path.read_text(errors="replace")):
            doc = ROOT / "docs" / f"{name}.md"
            if not doc.exists():
                continue  # e.g. README.md, "..." in prose: not a reference into docs/
            found += 1
            if heading not in headings(doc):
                broken.append(f"{path.relative_to(ROOT)}: docs/{name}.md has no heading {heading!r}")
    assert broken == []
    assert found >= 20  # the references exist: the pattern still matches how they are written


def test_a_wrong_heading_is_caught():
    """The pattern sees both spellings of a reference."""
    text = 'see docs/algorithm.md, "Offline design", and [methods.md](methods.md), "No such heading".'
    assert REFERENCE.findall(text) == [("algorithm", "Offline design"), ("methods", "No such heading")]
    assert "No such heading" not in headings(ROOT / "docs" / "methods.md")
    assert "System" in headings(ROOT / "docs" / "algorithm.md")
