"""The example script runs its loop and writes its plot."""

from __future__ import annotations

import subprocess
import sys


def test_example_runs_and_writes_the_path_plot(repo, tmp_path):
    png = tmp_path / "paths.png"
    out = subprocess.run(
        [sys.executable, str(repo / "examples" / "reach_target.py"), "--episodes", "16",
         "--out", str(png)], capture_output=True, text=True, check=True, cwd=tmp_path)
    lines = out.stdout.splitlines()
    assert lines[0].startswith("scripted: mean return") and "success 100 %" in lines[0]
    assert lines[1].startswith("random  : mean return")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
