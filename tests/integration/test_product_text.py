"""Product text describes the product as it is: no development history outside CHANGELOG.md.

README.md, docs/, evchain/, pipelines/, plugins/ and tests/ must not say "session N", "issue N",
"the lead", name helpers as people, or point to the removed development log (docs/benchmarks.md);
history belongs in CHANGELOG.md. The word "helper" for a helper function is fine.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCANNED = ["README.md", "docs", "evchain", "pipelines", "plugins", "tests"]
SUFFIXES = {".md", ".py", ".yaml", ".yml", ".toml", ".txt", ".cfg", ".rst"}

RULES = [
    ("a development session", re.compile(r"\bsession[ -][0-9]+", re.IGNORECASE)),
    ("an issue number", re.compile(r"\bissue[ -][0-9]+", re.IGNORECASE)),
    ("the lead as a person", re.compile(r"\bthe lead\b", re.IGNORECASE)),
    ("a helper as a person", re.compile(
        r"\bhelper\s+`[a-z][a-z0-9]*`"                         # helper `planeslow`
        r"|\bhelper\s+[a-z][a-z0-9]*\s*\)"                     # (session 7, helper lkx)
        r"|\bother helpers\b"                                  # while other helpers ran
        r"|\bhelpers?'s?\s+(?:worktree|branch|jobs?|runs?|`)"  # the helper's worktree
        r"|\banother helper\b"                                # another helper's version
        r"|\b(?:a|the|this) helper (?:was|is|did|merged|found|measured|tried|ran|started)\b",
        re.IGNORECASE)),
    ("the removed development log", re.compile(r"benchmarks\.md")),
]


def violations(text: str) -> list[tuple[int, str, str]]:
    """(line number, rule, line) for every line of ``text`` that breaks a rule."""
    found = []
    for n, line in enumerate(text.splitlines(), start=1):
        for what, pattern in RULES:
            if pattern.search(line):
                found.append((n, what, line.strip()))
    return found


def scanned_files() -> list[Path]:
    files = []
    for name in SCANNED:
        path = ROOT / name
        if path.is_file():
            files.append(path)
        elif path.is_dir():
            files += [p for p in sorted(path.rglob("*"))
                      if p.is_file() and p.suffix in SUFFIXES and p != Path(__file__).resolve()
                      and not any(part.startswith(".") or part in ("__pycache__", "build")
                                  or part.endswith(".egg-info") for part in p.parts)]
    return files


@pytest.mark.parametrize("text", [
    "measured in session 7, then", "Session 10: the decay", "see docs/benchmarks.md",
    "(issue 3's bar)", "the lead's call", "The lead cherry-picked it",
    "### Burst onsets (session 6, helper `lkonset`)", "(session 7, helper foemapspeed)",
    "while other helpers ran", "patch in the helper's worktree", "the helper did not merge it",
    "(two runs while a helper was starting)", "another helper's improved version",
    "scripts in the helper's `/tmp/lkx`",
])
def test_rules_catch_history(text):
    assert violations(text), text


@pytest.mark.parametrize("text", [
    "helpers of the hot loops", "an inlined helper taking arrays costs reference counting",
    "Build a series array (helper for tests and other producers).", "Test helpers for authors",
    "the timing scorer helper against the emulator", "def test_timing_errors_helper():",
    "lead = self.x_lead(t_us)", "the leading edge", "a sessionless run", "CHANGELOG.md",
    "one code path for both signs of a vote (two helpers fewer)",
    "The helper `evchain.core.series.DensityCounter` does", "the helper `box_albedo`",
    "docs/results.md, \"Benchmarks\"",
])
def test_rules_leave_product_words_alone(text):
    assert not violations(text), text


def test_scan_covers_the_product():
    files = {p.relative_to(ROOT).as_posix() for p in scanned_files()}
    assert "README.md" in files and "CHANGELOG.md" not in files
    assert "pipelines/reference-lk.yaml" in files
    assert "docs/explanation/concepts.md" in files
    assert "evchain/filters/foe_fit.py" in files
    assert any(f.startswith("plugins/") for f in files)


def test_no_history_in_product_text():
    found = []
    for path in scanned_files():
        for n, what, line in violations(path.read_text(encoding="utf-8", errors="replace")):
            found.append(f"{path.relative_to(ROOT).as_posix()}:{n}: {what}: {line}")
    assert not found, ("history belongs in CHANGELOG.md, not in product text:\n"
                       + "\n".join(found))
