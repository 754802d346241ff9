"""``batch measure-video``: one task per video, the same measurement as the serial command."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("fsspec")

from mecanum_hil.cli import main
from mecanum_hil.fleet.runner import BatchSettings, run_batch
from mecanum_hil.io.recording import read_recording


def test_measure_video_batch_equals_serial_and_isolates_a_broken_video(dask_client, tmp_path,
                                                                      capsys):
    sim = tmp_path / "sim60.csv"
    assert main(["simulate", "--profile", "paper-step-60", "--out", str(sim)]) == 0
    root = tmp_path / "videos"
    for robot, start in (("robot-v", "0"), ("robot-w", "0.5")):
        assert main(["render-video", "--recording", str(sim), "--out",
                     str(root / robot / "run1.mp4"), "--wheels", "1", "--size", "160x120",
                     "--duration", "3", "--start", start, "--noise", "2", "--seed", "4"]) == 0
    (root / "robot-w" / "broken.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(500))
    out = tmp_path / "videos.csv"
    written = tmp_path / "measured"
    outcome = run_batch(BatchSettings("measure-video", str(root), out, write_to=str(written)),
                        client=dask_client)
    by = {r["inputs"]: r for r in outcome.rows}
    assert sorted(by) == ["robot-v/run1.mp4", "robot-w/broken.mp4", "robot-w/run1.mp4"]
    assert {r["group"] for r in outcome.rows} == {"robot-v", "robot-w"}
    broken = by["robot-w/broken.mp4"]
    assert broken["status"] == "failed" and "robot-w/broken.mp4" in broken["error"]
    assert outcome.counts.done == 2 and outcome.counts.failed == 1
    for rel in ("robot-v/run1.mp4", "robot-w/run1.mp4"):
        capsys.readouterr()
        serial = tmp_path / "serial.csv"
        assert main(["measure-video", str(root / rel), "--out", str(serial), "--json"]) == 0
        doc = json.loads(capsys.readouterr().out)
        details = json.loads(by[rel]["details"])
        assert details["wheels"] == doc["wheels"]
        assert details["frames"] == doc["frames"]
        a = read_recording(serial)
        b = read_recording(written / rel.replace(".mp4", ".csv"))
        np.testing.assert_array_equal(a.t_s, b.t_s)
        np.testing.assert_array_equal(a.wheel_rpm, b.wheel_rpm)


def test_a_video_task_decodes_in_turns_with_its_analysis(monkeypatch, tmp_path):
    """The workers fill the cores: no decoder threads beside each task's analysis."""
    from types import SimpleNamespace

    import mecanum_hil.vision.measure as measure
    from mecanum_hil.fleet import stages

    seen = []

    def measured(path, options=None, progress=None):
        seen.append(options)
        return SimpleNamespace(summary={}, warnings=(), recording=None)

    monkeypatch.setattr(measure, "measure_video", measured)
    stages.run_measure_video(tmp_path / "v.mp4", "v", {"wheel": 2})
    stages.run_measure_video(tmp_path / "v.mp4", "v", {"decode_beside": True})
    assert [o.decode_beside for o in seen] == [False, True]
    assert seen[0].rois == ((2, None),)
