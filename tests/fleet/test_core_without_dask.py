"""Dask stays an optional extra: the core commands never import it (nor fsspec, pyarrow)."""

from __future__ import annotations

import json
import subprocess
import sys

SCRIPT = r"""
import contextlib, io, json, sys
from mecanum_hil.cli import main
out = sys.argv[1]
with contextlib.redirect_stdout(io.StringIO()):
    assert main(["campaign", "--out", out + "/camp", "--profile", "paper-step-60",
                 "--profile", "paper-turn", "--json"]) == 0
    assert main(["fit", out + "/camp/paper-step-60.csv", out + "/camp/paper-turn.csv",
                 "--out", out + "/cal.toml", "--no-report", "--json"]) == 0
    assert main(["shadow", "--replay", out + "/camp/paper-turn.csv", "--calibration",
                 out + "/cal.toml", "--json", "--no-events"]) in (0, 3)
    for cmd in ("batch", "fleet-report"):
        assert main([cmd, "--help"]) == 0
heavy = sorted(m for m in sys.modules
               if m.split(".")[0] in ("dask", "distributed", "fsspec", "pyarrow", "bokeh"))
print(json.dumps(heavy))
"""


def test_core_commands_do_not_import_the_fleet_extra(tmp_path):
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == []
