"""A small fleet archive built with ``mecanum-hil campaign --effects``, and a two-worker cluster.

Three robots, two weeks (sidecar ``started_utc`` as ``record`` writes it; robot-c's first week
has none and is dated by the files' modification time):

- robot-a: unchanged (3 recordings a week); one of its second week's files is corrupt;
- robot-b: its coefficients change in the second week (the simulated truth's A, B, C);
- robot-c: a 40 ms dead time appears in the second week.
"""

from __future__ import annotations

import datetime as dt
import json
import os
from pathlib import Path

import pytest

from mecanum_hil.cli import main

WEEKS = {"w1": "2026-11-10T09:00:00+00:00", "w2": "2026-11-17T09:00:00+00:00"}
PROFILES = {"robot-a": ("paper-step-60", "paper-turn", "paper-step-120"),
            "robot-b": ("paper-step-60", "paper-turn"),
            "robot-c": ("paper-step-60", "paper-turn")}
CORRUPT = "robot-a/w2/paper-turn.csv"


def _effects(path: Path, seed: int, dead_time_s: float = 0.0) -> Path:
    text = f"[noise]\nwheel_rpm_std = 0.25\nseed = {seed}\n"
    if dead_time_s:
        text = f"[effects.dead_time]\ndead_time_s = {dead_time_s}\n" + text
    path.write_text(text)
    return path


@pytest.fixture(scope="session")
def fleet_archive(tmp_path_factory) -> Path:
    """The archive's root folder (see the module docstring)."""
    base = tmp_path_factory.mktemp("fleet")
    root = base / "archive"
    drifted = base / "drifted.toml"
    drifted.write_text("[motor]\nA = 11.0\nB = 19.0\nC = 260.0\n")
    for k, (robot, profiles) in enumerate(PROFILES.items()):
        for j, week in enumerate(WEEKS):
            seed = 10 * (k + 1) + j
            fx = _effects(base / f"fx-{robot}-{week}.toml", seed,
                          0.04 if (robot, week) == ("robot-c", "w2") else 0.0)
            out = root / robot / week
            args = ["campaign", "--out", str(out), "--effects", str(fx), "--seed", str(seed),
                    "--json"]
            for p in profiles:
                args += ["--profile", p]
            if (robot, week) == ("robot-b", "w2"):
                args += ["--calibration", str(drifted)]
            assert main(args) == 0
            for side in out.glob("*.json"):
                if (robot, week) == ("robot-c", "w1"):
                    t = dt.datetime(2026, 11, 11, 8, tzinfo=dt.UTC).timestamp()
                    os.utime(side.with_suffix(".csv"), (t, t))
                    continue
                doc = json.loads(side.read_text())
                doc["started_utc"] = WEEKS[week]
                side.write_text(json.dumps(doc))
    bad = root / CORRUPT
    lines = bad.read_text().splitlines()
    fields = lines[40].split(",")
    fields[4] = "12.5x"  # a wheel speed that is not a number, on line 41
    lines[40] = ",".join(fields)
    bad.write_text("\n".join(lines) + "\n")
    return root


@pytest.fixture(scope="session")
def dask_client():
    """A local cluster of two worker processes with one thread each."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import Client

    from mecanum_hil.fleet.runner import local_cluster

    cluster = local_cluster(2, dashboard=False)
    client = Client(cluster)
    yield client
    client.close()
    cluster.close()
