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


def test_a_stage_left_by_a_killed_run_is_cleared(tmp_path):
    stale = tmp_path / ".part"
    stale.mkdir()
    (stale / "half.png").write_text("x")
    with staged_folder(tmp_path) as stage:
        assert list(stage.iterdir()) == []
        (stage / "whole.png").write_text("y")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["whole.png"]
