"""Outputs seen whole or not at all: a file put in place when complete, a report folder's files
moved in when all are written, whatever ends the run part-way."""

from __future__ import annotations

import pytest

from mecanum_hil.errors import SessionTerminated
from mecanum_hil.io.paths import part_path, replaced_when_whole, staged_folder


def test_a_file_replaces_the_previous_only_when_whole(tmp_path):
    out = tmp_path / "plot.png"
    out.write_text("previous")
    with pytest.raises(KeyboardInterrupt):
        with replaced_when_whole(out) as tmp:
            assert tmp == part_path(out) == tmp_path / ".plot.part.png"
            tmp.write_text("half")
            raise KeyboardInterrupt
    assert out.read_text() == "previous" and sorted(tmp_path.iterdir()) == [out]
    with replaced_when_whole(out) as tmp:
        tmp.write_text("new")
    assert out.read_text() == "new" and sorted(tmp_path.iterdir()) == [out]


def test_a_device_is_written_as_it_is(tmp_path):
    with replaced_when_whole("/dev/null") as tmp:
        assert str(tmp) == "/dev/null"
        tmp.write_text("discarded")


def test_a_report_folder_keeps_the_earlier_report_when_cut_short(tmp_path):
    out = tmp_path / "report"
    out.mkdir()
    (out / "report.md").write_text("old index")
    (out / "step1.png").write_text("old plot")
    for stop in (KeyboardInterrupt, SessionTerminated, ValueError):
        with pytest.raises(stop):
            with staged_folder(out, last=("report.md",)) as stage:
                (stage / "step1.png").write_text("new plot")
                raise stop()
        assert (out / "step1.png").read_text() == "old plot"
        assert sorted(p.name for p in out.iterdir()) == ["report.md", "step1.png"]


def test_a_report_folder_index_moves_in_last(tmp_path, monkeypatch):
    import os

    out = tmp_path / "new" / "report"  # created where missing
    moved = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (moved.append(os.path.basename(b)),
                                                     real(a, b)))
    with staged_folder(out, last=("report.md",)) as stage:
        for name in ("report.md", "a.png", "z.png"):
            (stage / name).write_text(name)
    assert moved == ["a.png", "z.png", "report.md"]
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "report.md", "z.png"]


def _dead_pid() -> int:
    import subprocess

    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def test_a_stage_left_by_a_killed_run_is_cleared_and_nothing_else(tmp_path):
    import os

    dead = tmp_path / f".mecanum-hil-{_dead_pid()}-abc.part"  # SIGKILL left it
    dead.mkdir()
    (dead / "half.png").write_text("x")
    alive = tmp_path / f".mecanum-hil-{os.getppid()}-def.part"  # a run writing here now
    alive.mkdir()
    (tmp_path / ".part").mkdir()  # the user's own
    with staged_folder(tmp_path) as stage:
        assert list(stage.iterdir()) == []
        (stage / "whole.png").write_text("y")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([".part", alive.name,
                                                                 "whole.png"])


def test_a_file_named_like_a_stage_is_no_obstacle(tmp_path):
    (tmp_path / ".part").write_text("the user's")
    with staged_folder(tmp_path) as stage:
        (stage / "report.md").write_text("new")
    assert (tmp_path / ".part").read_text() == "the user's"
    assert (tmp_path / "report.md").read_text() == "new"


def test_a_folder_in_the_way_is_said_before_anything_moves(tmp_path):
    from mecanum_hil.errors import ConfigError

    (tmp_path / "report.md").write_text("old index")
    (tmp_path / "b.png").mkdir()
    with pytest.raises(ConfigError, match="a folder is in the way"):
        with staged_folder(tmp_path, last=("report.md",)) as stage:
            for name in ("a.png", "b.png", "report.md"):
                (stage / name).write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.png", "report.md"]
    assert (tmp_path / "report.md").read_text() == "old index"


def test_a_linked_file_is_written_where_it_points_with_its_permissions(tmp_path):
    import os
    import stat

    target = tmp_path / "real.png"
    target.write_text("old")
    os.chmod(target, 0o640)
    link = tmp_path / "plot.png"
    link.symlink_to(target)
    with replaced_when_whole(link) as tmp:
        tmp.write_text("new")
    assert link.is_symlink() and target.read_text() == "new"
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
