"""``export REC.csv --out RUN.mcap``: read back with the ``mcap`` reader (every channel has a
schema, message counts equal the rows, timestamps monotonic) and imported back into the same
recording."""

from __future__ import annotations

import itertools
import json
import shutil

import numpy as np
import pytest

pytest.importorskip("mcap")

from mcap.reader import make_reader

from mecanum_hil.cli import main
from mecanum_hil.importers import detect_format
from mecanum_hil.io.mcap_export import CHANNELS, LIBRARY
from mecanum_hil.io.recording import read_recording

SAMPLE = "paper-step-120"  # the simulated robot's 115 rpm ceiling: shadow mode alarms


@pytest.fixture
def recording(repo, tmp_path):
    """A sample recording (record's extra columns, command rows without telemetry) and its
    shadow-mode event log."""
    src = repo / "recordings" / "samples" / f"{SAMPLE}.csv"
    rec_path = tmp_path / f"{SAMPLE}.csv"
    shutil.copy(src, rec_path)
    shutil.copy(src.with_suffix(".json"), rec_path.with_suffix(".json"))
    assert main(["shadow", "--replay", str(rec_path), "--calibration", "paper"]) == 3
    return rec_path


def _read_mcap(path):
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        header = reader.get_header()
        by_topic: dict[str, list] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema is not None, f"{channel.topic} has no schema"
            by_topic.setdefault(channel.topic, []).append(
                (message.log_time, json.loads(message.data), schema.name, schema.encoding))
    return header, summary, by_topic


def test_export_reads_back_with_the_mcap_reader(recording, tmp_path, capsys):
    out = tmp_path / "run.mcap"
    assert main(["export", str(recording), "--out", str(out), "--calibration", "paper"]) == 0
    capsys.readouterr()
    header, summary, got = _read_mcap(out)
    assert header.library == LIBRARY
    # every channel has a schema, JSON-encoded with a JSON schema Foxglove / PlotJuggler read
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        assert json.loads(schema.data)["title"] == schema.name
    rec = read_recording(recording)
    has = {
        CHANNELS["commands"].topic: np.isfinite(rec.commands).any(axis=1),
        CHANNELS["wheels"].topic: np.isfinite(rec.wheel_rpm).any(axis=1),
        CHANNELS["wheels_predicted"].topic: np.isfinite(rec.commands).all(axis=1),
        CHANNELS["extra"].topic: np.ones(len(rec), bool),
    }
    for topic, rows in has.items():
        msgs = got[topic]
        assert len(msgs) == int(rows.sum()), topic  # counts equal the rows
        assert [m["t_s"] for _, m, _, _ in msgs] == pytest.approx(rec.t_s[rows], abs=0)
        times = [lt for lt, *_ in msgs]
        assert all(a < b for a, b in itertools.pairwise(times)), topic
    wheels = got[CHANNELS["wheels"].topic]
    i = int(np.flatnonzero(np.isfinite(rec.wheel_rpm).any(axis=1))[100])
    assert wheels[100][1]["wheel3_rpm"] == rec.wheel_rpm[i, 2]
    assert wheels[100][2] == "mecanum_hil.WheelSpeeds"
    # no pose measured in this recording; the prediction's pose is a 2-D path
    assert CHANNELS["pose2d"].topic not in got
    path = got[CHANNELS["pose_predicted"].topic]
    assert path[0][2] == "foxglove.PoseInFrame" and path[0][1]["frame_id"] == "world"
    ys = [m["pose"]["position"]["y"] for _, m, _, _ in path]
    assert ys[-1] > 1.0  # 3 s straight ahead (+Y) at up to 120 rpm
    # the shadow alarms as foxglove.Log, warnings, in time order
    events = [json.loads(x) for x in recording.with_name(f"{SAMPLE}.shadow.jsonl")
              .read_text().splitlines()]
    alarms = [e for e in events if e["event"] == "alarm"]
    logs = got[CHANNELS["alarms"].topic]
    assert logs[0][2] == "foxglove.Log"
    warnings = [m for _, m, _, _ in logs if m["level"] == 3]
    assert len(warnings) == len(alarms) > 0
    assert alarms[0]["channel"] in warnings[0]["message"]
    log_times = [lt for lt, *_ in logs]
    assert log_times == sorted(log_times)


def test_import_of_the_export_gives_the_recording_back(recording, tmp_path, capsys):
    out = tmp_path / "run.mcap"
    assert main(["export", str(recording), "--out", str(out)]) == 0
    assert detect_format(out) == "mcap"
    back = tmp_path / "back.csv"
    assert main(["import", str(out), "--out", str(back)]) == 0, capsys.readouterr().err
    a, b = read_recording(recording), read_recording(back)
    np.testing.assert_array_equal(a.t_s, b.t_s)
    for name in ("commands", "wheel_rpm", "pose"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert dict(a.extra) == {k: list(v) for k, v in b.extra.items()}
    for key, value in a.metadata.items():
        assert b.metadata[key] == value
    # the CSV itself is the same, byte for byte
    assert back.read_text() == recording.read_text()


def test_export_of_a_broken_recording_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,n_cmd_rpm\n0,1\n")
    out = tmp_path / "run.mcap"
    assert main(["export", str(bad), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "bad.csv" in err
    assert not out.exists()


def test_export_never_writes_over_the_event_log_it_reads(recording, tmp_path, capsys):
    # the default event log (REC.shadow.jsonl) is an input like --events: naming it --out
    # was written over with MCAP, and a later export failed on it
    log = recording.with_name(f"{SAMPLE}.shadow.jsonl")
    before = log.read_bytes()
    assert main(["export", str(recording), "--out", str(log)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "event log" in err
    assert log.read_bytes() == before
    # an event log that is not text is one line, not an internal error
    log.write_bytes(b"\x89MCAP0\r\n\xff\xfe")
    assert main(["export", str(recording), "--out", str(tmp_path / "r.mcap")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and "not an event log" in err


def test_an_export_that_cannot_be_put_in_place_leaves_no_temporary_file(tmp_path, capsys):
    from mecanum_hil.errors import RecordingError
    from mecanum_hil.io.mcap_export import export_mcap
    from mecanum_hil.io.recording import Recording

    t = np.arange(5) / 100.0
    rec = Recording(t, np.tile([60.0, 0.0, 90.0], (5, 1)), np.full((5, 4), 1.0),
                    np.full((5, 3), np.nan))
    out = tmp_path / "run.mcap"
    out.mkdir()  # its place is taken: the rename fails after the file was written
    with pytest.raises(RecordingError, match=r"run\.mcap: cannot write"):
        export_mcap(rec, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


def test_an_imported_recording_exported_imports_back(recording, tmp_path, capsys):
    """A recording that an import made (its sidecar's ``import`` names the wheel radius used)
    exported to MCAP imports back: the mcap format takes no wheel radius."""
    import json

    side = recording.with_suffix(".json")
    meta = json.loads(side.read_text())
    meta["import"] = {"format": "rosbag", "wheel_radius_m": 0.102}
    side.write_text(json.dumps(meta))
    out = tmp_path / "run.mcap"
    assert main(["export", str(recording), "--out", str(out)]) == 0
    back = tmp_path / "back.csv"
    assert main(["import", str(out), "--out", str(back)]) == 0, capsys.readouterr().err
    assert read_recording(back).metadata["import"]["wheel_radius_m"] == 0.102


def test_an_export_cut_short_leaves_the_previous_file(recording, tmp_path, monkeypatch, capsys):
    from mcap.writer import Writer

    out = tmp_path / "run.mcap"
    args = ["export", str(recording), "--out", str(out), "--calibration", "paper"]
    assert main(args) == 0
    before = out.read_bytes()
    calls = itertools.count()
    real = Writer.add_message

    def interrupted(self, *a, **k):
        if next(calls) == 1000:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(Writer, "add_message", interrupted)
    assert main(args) == 130
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir() if "run" in p.name) == ["run.mcap"]
