"""The first steps of recordings/README.md, run as written on the shipped samples: no false
alarm on healthy recordings, and nothing written into the repository's folders."""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _steps() -> list[list[str]]:
    text = (REPO / "recordings" / "README.md").read_text(encoding="utf-8")
    block = text.split("```", 2)[1]
    return [shlex.split(line) for line in block.splitlines() if line.startswith("mecanum-hil")]


@pytest.mark.slow
def test_the_samples_first_steps_give_no_false_alarm_and_write_nothing_here(tmp_path):
    before = {p: p.stat().st_mtime_ns for p in (REPO / "recordings").rglob("*")}
    steps = _steps()
    assert [s[1] for s in steps] == ["fit", "diagnose", "shadow"]
    for argv in steps:
        args = [a.replace("/tmp/", f"{tmp_path}/") for a in argv[1:]]
        expanded = []
        for a in args:  # the shell's glob, from the repository's root
            expanded += sorted(str(p) for p in REPO.glob(a)) if "*" in a else [
                str(REPO / a) if a.startswith("recordings/") else a]
        proc = subprocess.run([sys.executable, "-m", "mecanum_hil", *expanded], cwd=tmp_path,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, (argv, proc.stderr[-2000:])
    assert "0 alarm(s)" in proc.stdout
    after = {p: p.stat().st_mtime_ns for p in (REPO / "recordings").rglob("*")}
    assert after == before
