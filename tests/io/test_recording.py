"""The recording format: round trip, extras, sidecar, malformed input, incremental writing."""

import json

import numpy as np
import pytest

from mecanum_hil.errors import RecordingError
from mecanum_hil.io.recording import (
    COLUMNS,
    Recording,
    RecordingWriter,
    read_recording,
    write_recording,
)

HEADER = ",".join(COLUMNS)


def test_columns_are_pinned():
    assert COLUMNS == (
        "t_s", "n_cmd_rpm", "omega_cmd_dps", "theta_cmd_deg", "wheel1_rpm", "wheel2_rpm",
        "wheel3_rpm", "wheel4_rpm", "x_m", "y_m", "phi_deg")


def test_round_trip_with_missing_values_extras_and_sidecar(tmp_path):
    t = np.array([0.0, 0.01, 0.02])
    rec = Recording(
        t, np.tile([60.0, 0.0, 90.0], (3, 1)),
        np.array([[0, 1.5, np.nan, 2], [3, 4, 5, 6], [np.nan] * 4]),
        np.full((3, 3), np.nan), {"controller_t_s": ["1.0", "1.01", ""], "note": ["a", "b", "c"]},
        {"source": "test", "sample_rate_hz": 100},
    )
    path = write_recording(rec, tmp_path / "run.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == HEADER + ",controller_t_s,note"
    assert lines[1].startswith("0.000000,60,0,90,0,1.5,,2,,,,1.0,a")
    assert json.loads((tmp_path / "run.json").read_text())["source"] == "test"
    back = read_recording(path)
    np.testing.assert_array_equal(back.t_s, t)
    np.testing.assert_array_equal(back.wheel_rpm, rec.wheel_rpm)
    assert np.isnan(back.pose).all()
    assert back.extra == rec.extra
    assert back.metadata["sample_rate_hz"] == 100
    np.testing.assert_array_equal(back.extra_numeric("controller_t_s"), [1.0, 1.01, np.nan])


def test_a_sidecar_not_in_utf8_is_one_error_and_one_with_a_bom_is_read(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text(HEADER + "\n0,1,2,3,,,,,,,\n")
    (tmp_path / "r.json").write_bytes(b'\xef\xbb\xbf{"notes": "ok"}')
    assert read_recording(p).metadata == {"notes": "ok"}
    (tmp_path / "r.json").write_bytes(b'{"notes": "caf\xe9"}')  # Latin-1
    with pytest.raises(RecordingError, match=r"r.json: bad JSON sidecar"):
        read_recording(p)


@pytest.mark.parametrize("value", ['"abc"', "-1", "0", "true", "[1]"])
def test_a_sidecar_gap_limit_that_is_not_seconds_is_one_error_not_ignored(tmp_path, value):
    p = tmp_path / "r.csv"
    p.write_text(HEADER + "\n0,1,2,3,,,,,,,\n0.001,1,2,3,,,,,,,\n")
    (tmp_path / "r.json").write_text('{"time_repair": {"max_gap_s": ' + value + "}}")
    with pytest.raises(RecordingError, match=r"r.json: time_repair.max_gap_s must be a positive "
                       r"number of seconds \(or null\), got"):
        read_recording(p)
    (tmp_path / "r.json").write_text('{"time_repair": {"max_gap_s": null}}')
    assert len(read_recording(p)) == 2


def test_recording_without_sidecar_is_valid(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text(HEADER + "\n0,1,2,3,,,,,,,\n")
    rec = read_recording(p)
    assert len(rec) == 1 and rec.metadata == {}


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("t_s,n_cmd_rpm\n0,1\n", "missing column 'omega_cmd_dps'"),
        (HEADER.replace("wheel2_rpm", "wheel_2") + "\n", "column 6: expected 'wheel2_rpm'"),
        (HEADER + "\n0,1,2,3,,,,,,,\n0.1,abc,2,3,,,,,,,\n", "line 3, column 'n_cmd_rpm'"),
        (HEADER + "\n0,1,2,3,,,,,,,\n0,1,2,3,,,,,,,\n", "line 3, column 't_s': time never"),
        (HEADER + "\n0.2,1,2,3,,,,,,,\n0.1,1,2,3,,,,,,,\n", "line 3, column 't_s': time 0.1 s"
         " does not increase: it runs back"),
        (HEADER + "\n0,1,2,3,,,,,,,\n0.001,1,2,3,,,,,,,\n0.002,1,2,3,,,,,,,\n"
         "0.0005,1,2,3,,,,,,,\n",
         "line 5, column 't_s': time 0.0005 s does not increase: it runs back 1.500 ms"),
        (HEADER + "\n0,1,2,3,,,,,,\n", "line 2: 10 fields, header has 11"),
        (HEADER + "\n,1,2,3,,,,,,,\n", "time is missing"),
        (HEADER + "\n0,1,2,3,nan,,,,,,\n", "not a finite number"),
        ("", "empty file"),
        # Python's float() reads 1_0 as 10; on either reader path it is not a number
        (HEADER + "\n0,1,2,3,1_0,,,,,,\n", "line 2, column 'wheel1_rpm': not a number: '1_0'"),
        (HEADER + ",v\n0,1,2,3,1_0,,,,,,,x\n", "not a number: '1_0'"),
        # a value no robot logs overflows every fit's sum of squares: refused, line named
        (HEADER + "\n0,1,2,3,,,,,,,\n0.1,1,2,3,1e308,,,,,,\n",
         "line 3, column 'wheel1_rpm': 1e+308 is not a value a robot logs"),
        (HEADER + "\n0,1e300,2,3,,,,,,,\n", "column 'n_cmd_rpm': 1e+300 is not a value"),
        (HEADER + ",v\n0,1,2,3,,,,,,,-2e9,x\n", "column 'phi_deg': -2e+09 is not a value"),
        (HEADER + "\n1e300,1,2,3,,,,,,,\n", "column 't_s': 1e+300 is not a value"),
        (HEADER + ",a,b,a\n", "duplicate column name(s): a"),
        # the model would tick its controller through it (2e7 s kept diagnose busy for hours)
        (HEADER + "\n0,1,2,3,,,,,,,\n100000,1,2,3,,,,,,,\n",
         "line 3, column 't_s': a gap of 100000 s before this row, more than a day"),
        (HEADER + ",x_m\n", "duplicate column name(s): x_m"),
    ],
)
def test_malformed_input_names_file_line_and_column(tmp_path, text, fragment):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(RecordingError) as err:
        read_recording(p)
    assert fragment in str(err.value)
    assert str(p) in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(RecordingError, match="file not found"):
        read_recording(tmp_path / "nope.csv")


def test_writer_leaves_a_valid_file_at_every_flush(tmp_path):
    p = tmp_path / "live.csv"
    w = RecordingWriter(p, extra_columns=("controller_t_s",), metadata={"source": "t"},
                        flush_interval_s=0.0)
    for i in range(5):
        w.write(i * 0.01, (10.0, 0.0, 90.0), (1.0, 2.0, 3.0, 4.0), extra=(i * 0.01 + 5,))
        rec = read_recording(p)  # readable while still open: every flushed row is complete
        assert len(rec) == i + 1
    with pytest.raises(RecordingError, match="does not increase"):
        w.write(0.01)
    w.close({"rows": 5})
    assert read_recording(p).metadata == {"source": "t", "rows": 5}
    assert len(read_recording(p)) == 5


def test_select_rows_keeps_extras():
    rec = Recording(np.arange(4.0), np.zeros((4, 3)), np.array([[1.0] * 4, [np.nan] * 4] * 2),
                    np.full((4, 3), np.nan), {"event": ["tlm", "cmd", "tlm", "cmd"]})
    tlm = rec.select(np.isfinite(rec.wheel_rpm[:, 0]))
    np.testing.assert_array_equal(tlm.t_s, [0.0, 2.0])
    assert tlm.extra == {"event": ["tlm", "tlm"]}


def test_a_last_line_cut_mid_row_is_dropped_not_fatal(tmp_path):
    p = tmp_path / "cut.csv"
    p.write_text(HEADER + "\n0,1,2,3,,,,,,,\n0.01,1,2,3,5,,,,,,\n0.02,1,2")
    rec = read_recording(p)
    assert len(rec) == 2 and rec.metadata["truncated_last_line"] == "0.02,1,2"
    # a complete last row without a newline is kept
    p.write_text(HEADER + "\n0,1,2,3,,,,,,,\n0.01,1,2,3,5,,,,,,")
    assert len(read_recording(p)) == 2
    # a bad row in the middle is still an error
    p.write_text(HEADER + "\n0,1,2\n0.01,1,2,3,5,,,,,,\n")
    with pytest.raises(RecordingError, match="line 2"):
        read_recording(p)
