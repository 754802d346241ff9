"""Discovery and grouping through fsspec (an in-memory filesystem stands in for a bucket)."""

from __future__ import annotations

import json

import pytest

from mecanum_hil.errors import ConfigError
from mecanum_hil.fleet.archive import group_files, open_archive, period_of

fsspec = pytest.importorskip("fsspec")


@pytest.fixture
def bucket():
    fs = fsspec.filesystem("memory")
    root = "/fleet-test"
    if fs.exists(root):
        fs.rm(root, recursive=True)
    files = {
        "site-1/r1/2026-11-16/a.csv": {"robot_id": "R1", "started_utc": "2026-11-16T23:59:00Z"},
        "site-1/r1/2026-11-17/b.csv": {"robot_id": "R1", "started_utc": "2026-11-17T00:01:00Z"},
        "site-1/r2/c.csv": {"robot_id": "R2", "started_utc": "2026-11-23T10:00:00+01:00"},
        "site-2/r3/d.csv": {"started_utc": "2026-11-17T08:00:00Z"},
        "site-2/r3/notes.txt": None,
    }
    for rel, side in files.items():
        fs.pipe(f"{root}/{rel}", b"t_s\n")
        if side is not None:
            fs.pipe(f"{root}/{rel[:-4]}.json", json.dumps(side).encode())
    yield f"memory://{root}"
    fs.rm(root, recursive=True)


def test_groups_per_path_level_sidecar_key_and_period(bucket):
    arch = open_archive(bucket)
    assert [f.rel for f in arch.files] == ["site-1/r1/2026-11-16/a.csv",
                                            "site-1/r1/2026-11-17/b.csv", "site-1/r2/c.csv",
                                            "site-2/r3/d.csv"]
    by_site = group_files(arch)
    assert [(g.group, len(g.files)) for g in by_site] == [("site-1", 3), ("site-2", 1)]
    by_robot = group_files(arch, "2")
    assert [(g.group, len(g.files)) for g in by_robot] == [("r1", 2), ("r2", 1), ("r3", 1)]
    days = group_files(arch, "2", "day")
    assert [(g.group, g.period) for g in days] == [
        ("r1", "2026-11-16"), ("r1", "2026-11-17"), ("r2", "2026-11-23"), ("r3", "2026-11-17")]
    weeks = group_files(arch, "robot_id", "week")
    # 2026-11-16 and -17 are the same ISO week; 10:00+01:00 is 09:00 UTC
    assert [(g.group, g.period, len(g.files), bool(g.error)) for g in weeks] == [
        ("(no robot_id)", "2026-W47", 1, True), ("R1", "2026-W47", 2, False),
        ("R2", "2026-W48", 1, False)]
    assert "site-2/r3/d.csv" in weeks[0].error and "robot_id" in weeks[0].error
    folders = group_files(arch, "2", period_level=3)  # robot/DAY/run.csv, no sidecar read
    assert [(g.group, g.period, bool(g.error)) for g in folders] == [
        ("r1", "2026-11-16", False), ("r1", "2026-11-17", False), ("r2", "unknown", True),
        ("r3", "unknown", True)]
    whole = group_files(open_archive(bucket + "/site-1"), period_level=0)
    assert {g.period for g in whole} == {"site-1"}
    deep = group_files(arch, "3")
    assert deep[0].group == "(outside any robot folder)" and deep[0].error
    assert period_of(None, "day") == "unknown"


def test_archive_errors(bucket, tmp_path):
    with pytest.raises(ConfigError, match="no videos"):
        open_archive(bucket, "videos")
    with pytest.raises(ConfigError, match="not a folder"):
        open_archive(str(tmp_path / "missing"))
    with pytest.raises(ConfigError, match="--period"):
        group_files(open_archive(bucket), period="month")
    with pytest.raises(ConfigError, match="levels start at 1"):
        group_files(open_archive(bucket), "0")
    with pytest.raises(ConfigError, match="not both"):
        group_files(open_archive(bucket), period="day", period_level=2)
