"""The docs read as reference: no page over 400 lines, and short sentences (the median over
all pages at most 22 words). Words are counted between sentence ends, outside code blocks,
tables, headings and indented code."""

from __future__ import annotations

import re
import statistics
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: The pages measured: every Markdown page of docs/ and the README.
PAGES = sorted([*REPO.glob("docs/**/*.md"), REPO / "README.md"])
MAX_LINES = 400
MAX_MEDIAN_WORDS = 22

_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z`(\"'*\[0-9-])")
_LIST = re.compile(r"^\s*(?:[-*+]|\d+[.)])\s+")


def prose(text: str) -> list[str]:
    """The paragraphs of a Markdown page that are prose: fenced code, tables, headings,
    indented code and HTML left out; list items are paragraphs of their own."""
    paragraphs: list[str] = []
    current: list[str] = []
    fenced = False

    def flush() -> None:
        if current:
            paragraphs.append(" ".join(current))
            current.clear()

    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith(("```", "~~~")):
            fenced = not fenced
            flush()
            continue
        if fenced or not stripped or stripped.startswith(("|", "#", "<", ">")) or \
                (line.startswith(("    ", "\t")) and not current):
            flush()
            continue
        if _LIST.match(line):
            flush()
            stripped = _LIST.sub("", line).strip()
        current.append(stripped)
    flush()
    return paragraphs


def sentence_lengths(text: str) -> list[int]:
    """Words per sentence of the page's prose (inline code counts as one word each)."""
    out = []
    for para in prose(text):
        para = re.sub(r"`[^`]*`", "CODE", para)
        para = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", para)  # a link counts as its text
        for sentence in _END.split(para):
            words = [w for w in sentence.split() if re.search(r"\w", w)]
            if words:
                out.append(len(words))
    return out


def test_the_sentence_counter_splits_sentences_and_skips_code_and_tables():
    text = ("# Title\n\nOne two three. Four five `a b c` six.\n\n```\nnot. prose. here.\n```\n"
            "| a | b |\n|---|---|\n- an item of four\n- and one more. Then two\n")
    assert sentence_lengths(text) == [3, 4, 4, 3, 2]


def test_no_docs_page_is_longer_than_400_lines():
    long = {p.relative_to(REPO).as_posix(): n for p in PAGES
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def test_the_median_sentence_of_the_docs_is_at_most_22_words():
    lengths = [n for p in PAGES for n in sentence_lengths(p.read_text())]
    assert statistics.median(lengths) <= MAX_MEDIAN_WORDS, statistics.median(lengths)
