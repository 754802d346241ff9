"""Code, tests, benchmarks, drivers and CI state reasons, not where they came from.

A comment that says a thing was done for a numbered issue or in a numbered work session tells a
reader nothing once the issue is closed: the reason itself belongs there (what the code must do,
what was measured, what broke without it). Every text file matched by :data:`COVERED` is read
and each such reference fails with its file and line.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

#: Globs, relative to the repository, of the files checked. Extend here (e.g. ``docs/**/*.md``,
#: ``README.md``) to cover more of the repository.
COVERED = [
    "mecanum_hil/**/*",
    "tests/**/*",
    "bench/**/*",
    "drivers/**/*",
    ".ci/**/*",
    "pyproject.toml",
    "docs/**/*.md",
    "README.md",
    "CONTRIBUTING.md",
    "recordings/**/*.md",
]

#: Folders of generated files, never read.
SKIPPED_DIRS = {"__pycache__", ".pytest_cache", ".ruff_cache", ".hypothesis"}

# either word, singular or plural, any case, then a number after spaces, "_", "#" or "-"; built
# from pieces so that this file does not match itself
_WORDS = "|".join(["iss" + "ue", "sess" + "ion"])
HISTORY_REF = re.compile(r"(?<![a-z])(?:" + _WORDS + r")s?[ _#-]*\d+", re.IGNORECASE)


def _covered_files() -> list[Path]:
    files: set[Path] = set()
    for pattern in COVERED:
        for path in REPO.glob(pattern):
            rel = path.relative_to(REPO)
            if path.is_file() and not SKIPPED_DIRS.intersection(rel.parts):
                files.add(path)
    return sorted(files)


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary file (a NUL byte, or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def test_the_covered_globs_find_files():
    for pattern in COVERED:
        assert any(REPO.glob(pattern)), f"{pattern} matches nothing"
    assert Path(__file__).resolve() in _covered_files()


def test_the_pattern_finds_what_it_must_and_nothing_else():
    for hit in ["see " + "iss" + "ue 12", "ISS" + "UE #3", "iss" + "ues 7 and 12",
                "def test_" + "iss" + "ue18_x", "iss" + "ue-12", "Sess" + "ion 21",
                "(sess" + "ion 23)"]:
        assert HISTORY_REF.search(hit), hit
    for fine in ["SessionTerminated", "a session at 50 Hz", "tissue 3", "an issue of timing",
                 "run_record_session(link, 2)", "scope=\"session\""]:
        assert not HISTORY_REF.search(fine), fine


def test_no_issue_or_session_numbers_in_code_tests_or_docs():
    found = []
    for path in _covered_files():
        text = _text(path)
        if text is None:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            if HISTORY_REF.search(line):
                found.append(f"{path.relative_to(REPO)}:{number}: {line.strip()}")
    assert not found, ("write the reason, not the issue or session it came from:\n"
                       + "\n".join(found))
