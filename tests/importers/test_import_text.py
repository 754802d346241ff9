"""Format ``text`` of ``mecanum-hil import``: logs as other labs write them, mapped by MAP.toml."""

import csv
import io
import math

import numpy as np
import pytest

from mecanum_hil.errors import ConfigError, RecordingError
from mecanum_hil.importers import detect_format, import_source
from mecanum_hil.importers.text import wheel_setpoints_to_commands
from mecanum_hil.io.recording import (
    COLUMNS,
    Recording,
    format_rows,
    read_recording,
    write_recording,
)
from mecanum_hil.model.kinematics import command_to_wheels
from mecanum_hil.units import RPM_TO_RAD_S


def step(n, level, tau=15.0, seed=0):
    rng = np.random.default_rng(seed)
    return level * (1 - np.exp(-np.arange(n) / tau)) + rng.normal(0, 0.05, n)


def write_map(tmp_path, text, name="map.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_headerless_csv_in_rad_s_with_a_fixed_period(tmp_path):
    n = 500
    w = np.column_stack([step(n, 20.0, seed=j) for j in range(4)])
    log = tmp_path / "lab_a.csv"
    np.savetxt(log, np.column_stack([np.full(n, 20.0), w]), fmt="%.4f", delimiter=",")
    m = write_map(tmp_path, """
[time]
period_s = 0.002
[wheels]
wheel1 = { column = 1, unit = "rad/s" }
wheel2 = { column = 2, unit = "rad/s", sign = -1 }
wheel3 = { column = 3, unit = "rad/s" }
[commands]
setpoint = { column = 0, unit = "rad/s" }
""")
    assert detect_format(log) == "text"
    res = import_source(log, map_path=m)
    rec = res.recording
    np.testing.assert_allclose(rec.t_s, 0.002 * np.arange(n))
    np.testing.assert_allclose(rec.wheel_rpm[:, 0], np.round(w[:, 0], 4) / RPM_TO_RAD_S)
    np.testing.assert_allclose(rec.wheel_rpm[:, 1], -np.round(w[:, 1], 4) / RPM_TO_RAD_S)
    assert np.isnan(rec.wheel_rpm[:, 3]).all()  # absent wheel stays empty
    np.testing.assert_allclose(rec.commands[0], [20 / RPM_TO_RAD_S, 0, 90])
    assert res.notes == ()
    assert rec.metadata["time_repair"]["period_s"] == 0.002


def percent_log(tmp_path, t, sp, w1, w2):
    log = tmp_path / "lab_b.txt"
    with log.open("w") as fh:
        fh.write("% wheel test, lab B\n% time_s   setpoint   w_left   w_right\n")
        for r in zip(t, sp, w1, w2, strict=True):
            fh.write("{:.3f}\t {:.2f}   {:.3f} {:.3f}\n".format(*r))
    return log


PERCENT_MAP = """
[time]
column = "time_s"
unit = "s"
[wheels]
wheel1 = { column = "w_left", unit = "rad/s" }
wheel2 = { column = "w_right", unit = "rad/s" }
[commands]
setpoint = { column = "setpoint", unit = "rad/s" }
"""


def test_whitespace_text_with_a_percent_header_and_repeated_stamps(tmp_path):
    n = 970
    t = np.round(np.arange(n) * 1e-3, 3)
    t[[100, 500, 800]] = t[[99, 499, 799]]  # 3 of 970 rows repeat their stamp
    sp = np.where(np.arange(n) < 400, 16.0, -30.0)
    log = percent_log(tmp_path, t, sp, step(n, 16.0), step(n, 16.0, seed=1))
    res = import_source(log, map_path=write_map(tmp_path, PERCENT_MAP))
    rec = res.recording
    assert len(rec) == n and np.all(np.diff(rec.t_s) > 0)
    assert res.notes == ("time (median period 1.000 ms, resolution 1.000 ms): 3 repeated stamps "
                         "spread up to the next stamp",)
    assert rec.metadata["notes"] == list(res.notes)
    # a signed setpoint: n = |s|, theta 90 ahead, 270 back
    np.testing.assert_allclose(rec.commands[0], [16 / RPM_TO_RAD_S, 0, 90])
    np.testing.assert_allclose(rec.commands[-1], [30 / RPM_TO_RAD_S, 0, 270])
    targets = command_to_wheels(*rec.commands.T, k=2.0)
    np.testing.assert_allclose(targets[-1], [-30 / RPM_TO_RAD_S] * 4)
    assert np.isnan(rec.wheel_rpm[:, 2:]).all()


def test_csv_with_named_columns_in_ms_and_n_omega_theta(tmp_path):
    n = 300
    log = tmp_path / "lab_c.csv"
    with log.open("w") as fh:
        fh.write("# exported by firmware 2.1\nstamp_ms,cmd_speed,turn,dir,fl,fr,rl,rr\n")
        for i in range(n):
            fh.write(f"{1000 + 2 * i},{10.0},{0},{1.5707963},{i * 0.01:.2f},,,\n")
    m = write_map(tmp_path, """
[file]
delimiter = ","
[time]
column = "stamp_ms"
unit = "ms"
[wheels]
wheel1 = { column = "fl", unit = "rad/s" }
wheel2 = { column = "fr", unit = "rad/s" }
[commands]
n = { column = "cmd_speed", unit = "rad/s" }
omega = { column = "turn", unit = "rad/s" }
theta = { column = "dir", unit = "rad" }
""")
    rec = import_source(log, "text", map_path=m).recording
    np.testing.assert_allclose(rec.t_s, 0.002 * np.arange(n))  # from the first stamp
    assert rec.metadata["time_repair"]["first_stamp"] == 1000
    np.testing.assert_allclose(rec.commands[5], [10 / RPM_TO_RAD_S, 0, 90], atol=1e-5)
    assert np.isnan(rec.wheel_rpm[:, 1]).all()  # empty fields are missing values
    np.testing.assert_allclose(rec.wheel_rpm[7, 0], 0.07 / RPM_TO_RAD_S)


def test_constants_counts_and_a_wrapping_counter(tmp_path):
    n = 2000
    counter = (np.arange(n) + 65000) % 65536
    log = tmp_path / "enc.txt"
    np.savetxt(log, np.column_stack([counter, np.full(n, 2048.0)]), fmt="%d")
    m = write_map(tmp_path, """
[time]
column = 0
unit = "ms"
[wheels]
counts_per_rev = 4096
wheel1 = { column = 1, unit = "counts/s" }
[commands]
n = { value = 30, unit = "rpm" }
omega = { value = 0 }
theta = { value = 90 }
""")
    res = import_source(log, map_path=m)
    np.testing.assert_allclose(np.diff(res.recording.t_s), 1e-3)
    np.testing.assert_allclose(res.recording.wheel_rpm[:, 0], 30.0)
    assert "1 wrap of a 65.536 s counter unwrapped" in res.notes[0]


def test_wheel_setpoints_map_through_the_exact_inverse_kinematics():
    k = 2.3
    rng = np.random.default_rng(5)
    cmd = np.column_stack([rng.uniform(0, 100, 50), rng.uniform(-90, 90, 50),
                           rng.uniform(0, 360, 50)])
    wheels = command_to_wheels(*cmd.T, k=k)
    back, residual = wheel_setpoints_to_commands(wheels, k)
    np.testing.assert_allclose(command_to_wheels(*back.T, k=k), wheels, atol=1e-9)
    assert residual.max() < 1e-9
    still, _ = wheel_setpoints_to_commands(np.zeros((1, 4)), k)
    np.testing.assert_allclose(still, [[0, 0, 90]])


WHEELS_MAP = """
[time]
period_s = 0.001
[commands]
k = 2.0
wheel1 = { column = 0, unit = "rpm" }
wheel2 = { column = 1, unit = "rpm" }
wheel3 = { column = 2, unit = "rpm" }
wheel4 = { column = 3, unit = "rpm" }
"""


def test_wheel_setpoints_off_the_image_warn_or_fail_with_the_residual(tmp_path):
    m = write_map(tmp_path, WHEELS_MAP)
    log = tmp_path / "sp.txt"
    log.write_text("10 10 10 10\n10 10.2 10 10\n")
    res = import_source(log, map_path=m)
    assert "off the kinematics' image by up to 0.05 rpm" in res.notes[0]
    log.write_text("10 10 10 10\n10 30 10 10\n")
    with pytest.raises(RecordingError, match=r"sp.txt, line 2: .* 5 rpm off the kinematics"):
        import_source(log, map_path=m)


@pytest.mark.parametrize(
    ("log", "map_text", "fragment"),
    [
        ("1 2\n3 x\n", "[time]\nperiod_s = 0.001\n[wheels]\nwheel1 = {column = 1, unit = "
         "\"rpm\"}\n",
         "line 2, column 1: not a number: 'x'"),
        ("1,2\n3,4,5\n", "[time]\nperiod_s = 0.001\n[wheels]\nwheel1 = { column = 1 , unit = "
         "\"rpm\" }\n", "line 2: 3 fields, expected 2"),
        ("% t w\n1 2\n", "[time]\ncolumn = \"time\"\n", "names column 'time', not in the log "
         "(columns: t, w)"),
        ("1 2\n", "[time]\nperiod_s = 0.001\npriod = 2\n", "unknown key(s) priod"),
        ("1 2\n", "[time]\ncolumn = 0\nperiod_s = 0.001\n", "exactly one of 'column'"),
        ("1 2\n", "[time]\nperiod_s = 2\nunit = \"ms\"\n", "[time] unit describe(s) a time "
         "column; with 'period_s' (in seconds) there is none"),
        ("1 2\n", "[time]\nperiod_s = 0.001\n[wheels]\nwheel1 = { column = 1, unit = \"m/s\" }\n",
         "must be one of rpm, rad/s, deg/s, counts/s"),
        ("1 2\n", "[time]\nperiod_s = 0.001\n[wheels]\nwheel1 = { column = 1, unit = "
         "\"counts/s\" }\n", "needs counts_per_rev"),
        ("% only comments\n", "[time]\nperiod_s = 0.001\n", "no data rows"),
        ("0 1\n0.001 1\n0.0005 1\n", "[time]\ncolumn = 0\n",
         "line 3: time 0.0005 s does not increase: it runs back"),
        ("% t w\n0 1\n0.001 inf\n", "[time]\ncolumn = 0\n[wheels]\nwheel1 = {column = \"w\", "
         "unit = \"rpm\"}\n", "line 3, column w: infinite value"),
        ("1 2\n", "[file]\ndelimiter = \",,\"\n[time]\nperiod_s = 0.001\n",
         "file.delimiter must be one character"),
        ("1 2\n", "[file]\ndelimiter = \"\"\n[time]\nperiod_s = 0.001\n",
         "file.delimiter must be one character"),
        ("1 2\n", "[file]\nencoding = \"ANSI\"\n[time]\nperiod_s = 0.001\n",
         "file.encoding: unknown encoding 'ANSI'"),
        ("1 2\n", "[file]\nencoding = 5\n[time]\nperiod_s = 0.001\n",
         "file.encoding: unknown encoding 5"),
        ("1 2\n", "[file]\nskip_lines = -1\n[time]\nperiod_s = 0.001\n",
         "file.skip_lines must be a whole number >= 0"),
        ("1 2\n", "[file]\nheader = \"yes\"\n[time]\nperiod_s = 0.001\n",
         "file.header must be true, false or 'auto'"),
        ("1 2\n", "[time]\nperiod_s = 0.001\nstart_s = nan\n",
         "'start_s' must be a finite number"),
        ("1 2\n", "[time]\nperiod_s = 0.001\nstart_s = 1e300\n",
         "a time stamp loses its microseconds"),
        # Python's float() reads 1_0 as 10: named, not a number; on the first line not taken
        # for a header (its row was dropped, exit 0)
        ("1_0 2\n3 4\n5 6\n", "[time]\nperiod_s = 0.01\n[wheels]\nwheel1 = { column = 0, "
         "unit = \"rpm\" }\n", "line 1, column 0: not a number: '1_0'"),
        ("t w\n0 1\n0.01 1_0\n", "[time]\ncolumn = \"t\"\nunit = \"s\"\n[wheels]\n"
         "wheel1 = { column = \"w\", unit = \"rpm\" }\n", "line 3, column w: not a number"),
    ],
)
def test_malformed_logs_and_maps_are_one_clear_error(tmp_path, log, map_text, fragment):
    p = tmp_path / "log.txt"
    p.write_text(log)
    with pytest.raises((RecordingError, ConfigError)) as err:
        import_source(p, "text", map_path=write_map(tmp_path, map_text))
    assert fragment in str(err.value)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("spelling", ["\\t", "tab", "TAB", "\t"])
def test_a_tab_delimiter_as_a_map_may_spell_it(tmp_path, spelling):
    # a TOML literal string '\t' is two characters: backslash, t
    p = tmp_path / "log.txt"
    p.write_text("t\tw\n0\t1\n0.001\t2\n0.002\t3\n")
    m = write_map(tmp_path, f"[file]\ndelimiter = '{spelling}'\n[time]\ncolumn = \"t\"\n"
                  "[wheels]\nwheel1 = {column = \"w\", unit = \"rpm\"}\n")
    rec = import_source(p, "text", map_path=m).recording
    np.testing.assert_allclose(rec.wheel_rpm[:, 0], [1.0, 2.0, 3.0])


def test_unknown_format_options_and_binary_files_are_refused(tmp_path):
    p = tmp_path / "log.txt"
    p.write_text("1 2\n")
    with pytest.raises(ConfigError, match=r"'text' does not take --cmd-topic \(it takes: --map\)"):
        import_source(p, "text", cmd_topic="/cmd_vel")
    with pytest.raises(ConfigError, match="unknown import format 'nope'"):
        import_source(p, "nope")
    b = tmp_path / "blob.bin"
    b.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(RecordingError, match="format not recognised"):
        detect_format(b)


def test_an_empty_or_header_only_log_says_so_not_format_not_recognised(tmp_path):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(RecordingError, match="empty file: nothing to import"):
        detect_format(empty)
    header = tmp_path / "header.csv"
    header.write_text("t,speed\n")
    with pytest.raises(RecordingError, match=r"a single line \(a header without data rows\?\)"):
        detect_format(header)


def _old_writer(rec):
    """The row-by-row writer the column-wise one replaces (the file format must not change)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    body = np.column_stack([rec.commands, rec.wheel_rpm, rec.pose])
    for i in range(len(rec)):
        w.writerow([f"{rec.t_s[i]:.6f}"] + ["" if math.isnan(v) else f"{v:.9g}" for v in body[i]])
    return buf.getvalue()


def test_the_column_wise_writer_writes_the_same_text(tmp_path):
    rng = np.random.default_rng(2)
    n = 1000
    cmd = np.repeat(rng.uniform(-50, 50, (10, 3)), 100, axis=0)
    wheels = rng.normal(0, 30, (n, 4))
    wheels[:, 3] = np.nan
    wheels[::7, 1] = np.nan
    pose = np.full((n, 3), np.nan)
    pose[:, 0] = np.round(rng.uniform(0, 1, n), 2)
    rec = Recording(np.arange(n) * 0.001, cmd, wheels, pose)
    p = write_recording(rec, tmp_path / "r.csv")
    assert p.read_text() == _old_writer(rec)
    assert format_rows(rec, 3) == "".join(_old_writer(rec).splitlines(True)[:4])
    back = read_recording(p)  # numpy's reader for such well-formed files
    np.testing.assert_allclose(back.wheel_rpm, rec.wheel_rpm, rtol=1e-8)
    np.testing.assert_allclose(back.pose, rec.pose, rtol=1e-8)
    np.testing.assert_allclose(back.commands, rec.commands, rtol=1e-8)
    np.testing.assert_allclose(back.t_s, rec.t_s, atol=1e-9)


# -- real files as loggers leave them -----------------------------------------------------------

NAMED_MS_MAP = """
[time]
column = "time_ms"
unit = "ms"
[wheels]
wheel1 = { column = "w_fl", unit = "rad/s" }
wheel2 = { column = "w_fr", unit = "rad/s" }
[commands]
setpoint = { column = "cmd", unit = "rad/s" }
"""


def test_padded_empty_cells_bom_crlf_and_a_trailing_blank_line(tmp_path):
    """A fixed-width CSV pads its empty cells with blanks: they are missing values, not an
    error; with a BOM, CRLF line ends, blanks after the values and an empty last line."""
    rows = ["time_ms , cmd , w_fl , w_fr "]
    for i in range(12):
        cmd = "    " if i == 4 else " NaN" if i == 5 else f"{i * 0.5:4.1f}"
        fr = "     " if i == 7 else " 2.00"
        rows.append(f"{2 * i:7d} ,{cmd} , 1.00 ,{fr} ")
    log = tmp_path / "padded.csv"
    log.write_bytes(b"\xef\xbb\xbf" + ("\r\n".join(rows) + "\r\n\r\n").encode())
    rec = import_source(log, "text", map_path=write_map(tmp_path, NAMED_MS_MAP)).recording
    np.testing.assert_allclose(rec.t_s, 0.002 * np.arange(12))
    assert np.isnan(rec.commands[4:6]).all() and np.isfinite(rec.commands[6]).all()
    np.testing.assert_allclose(rec.commands[3], [1.5 / RPM_TO_RAD_S, 0.0, 90.0])
    assert np.isnan(rec.wheel_rpm[7, 1]) and np.isfinite(np.delete(rec.wheel_rpm[:, 1], 7)).all()
    np.testing.assert_allclose(rec.wheel_rpm[:, 0], 1.0 / RPM_TO_RAD_S)


def test_quoted_numbers_as_spreadsheets_export_them(tmp_path):
    log = tmp_path / "quoted.csv"
    log.write_text('"time_ms","cmd","w_fl","w_fr"\n"0","1.5","2","3"\n"2","1.5","2.5",""\n')
    rec = import_source(log, "text", map_path=write_map(tmp_path, NAMED_MS_MAP)).recording
    np.testing.assert_allclose(rec.wheel_rpm[:, 0], np.array([2.0, 2.5]) / RPM_TO_RAD_S)
    assert np.isnan(rec.wheel_rpm[1, 1])


def test_a_last_line_cut_off_mid_row_is_dropped_with_a_note(tmp_path):
    """A logger stopped while writing: every complete row is imported, the cut one is named
    in a note (and the sidecar), not silently lost and not a refusal of the whole log."""
    log = tmp_path / "cut.csv"
    log.write_text("time_ms,cmd,w_fl,w_fr\n0,1,2,3\n2,1,2,3\n4,1,2")
    res = import_source(log, "text", map_path=write_map(tmp_path, NAMED_MS_MAP))
    assert len(res.recording) == 2
    assert any("last line cut off" in n and "'4,1,2'" in n for n in res.notes)
    assert res.notes == tuple(res.recording.metadata["notes"])
    # a complete last row without its newline, and one whose last cell is empty, are kept
    log.write_text("time_ms,cmd,w_fl,w_fr\n0,1,2,3\n2,1,2,")
    res = import_source(log, "text", map_path=write_map(tmp_path, NAMED_MS_MAP))
    assert len(res.recording) == 2 and np.isnan(res.recording.wheel_rpm[1, 1])
    assert not any("cut off" in n for n in res.notes)


@pytest.mark.parametrize("chunk", [1 << 25, 7, 64])
def test_the_log_is_streamed_in_blocks_with_the_same_result(tmp_path, monkeypatch, chunk):
    """The file is parsed block by block (never held whole): block edges inside rows, before
    an empty first cell, among comment and blank lines, change nothing."""
    from mecanum_hil.importers import text as text_format

    rows = ["\ufeff# exported", "time_ms,cmd,w_fl,w_fr"]
    for i in range(40):
        rows.append(f"{2 * i},{'' if i % 9 == 4 else i * 0.25},{i * 0.5},{'' if i % 7 else 3}")
        if i % 13 == 5:
            rows += ["% a comment in the data", ""]
    log = tmp_path / "blocks.csv"
    log.write_text("\r\n".join(rows) + "\r\n80,1,2")  # and a last line cut off
    monkeypatch.setattr(text_format, "CHUNK_BYTES", chunk)
    res = import_source(log, "text", map_path=write_map(tmp_path, NAMED_MS_MAP))
    rec = res.recording
    i = np.arange(40)
    np.testing.assert_allclose(rec.t_s, 0.002 * i)
    np.testing.assert_allclose(rec.wheel_rpm[:, 0], i * 0.5 / RPM_TO_RAD_S)
    np.testing.assert_array_equal(np.isnan(rec.wheel_rpm[:, 1]), i % 7 != 0)
    np.testing.assert_array_equal(np.isnan(rec.commands[:, 0]), i % 9 == 4)
    assert any("'80,1,2'" in n for n in res.notes)


def test_a_units_comment_line_below_the_names_does_not_hide_them(tmp_path):
    """``% time_s setpoint w_left w_right`` then ``% s rad/s rad/s rad/s``: the map's names
    are on the first comment line, not the last one."""
    log = tmp_path / "units.txt"
    log.write_text("% lab B\n% time_s setpoint w_left w_right\n% s rad/s rad/s rad/s\n"
                   "0.000 16.0 1.0 2.0\n0.001 16.0 1.5 2.5\n")
    rec = import_source(log, "text", map_path=write_map(tmp_path, PERCENT_MAP)).recording
    np.testing.assert_allclose(rec.wheel_rpm[:, :2], np.array([[1.0, 2.0], [1.5, 2.5]])
                               / RPM_TO_RAD_S)
    np.testing.assert_allclose(rec.commands[:, 0], 16.0 / RPM_TO_RAD_S)


def test_a_units_row_under_the_header_row_is_part_of_the_header(tmp_path):
    log = tmp_path / "units.csv"
    log.write_text("time_ms,cmd,w_fl,w_fr\nms,rad/s,rad/s,rad/s\n0,1,2,3\n2,1,2.5,3\n")
    rec = import_source(log, "text", map_path=write_map(tmp_path, NAMED_MS_MAP)).recording
    np.testing.assert_allclose(rec.t_s, [0.0, 0.002])
    np.testing.assert_allclose(rec.wheel_rpm[:, 0], np.array([2.0, 2.5]) / RPM_TO_RAD_S)


@pytest.mark.parametrize("encoding", ["utf-16", "utf-32", "latin-1", "cp1252"])
def test_a_log_in_the_encoding_its_map_states_is_read_and_detected(tmp_path, encoding):
    # UTF-16 and UTF-32 (a Windows logger's "Unicode" text) are not ASCII's bytes: they are
    # transcoded while streamed; Latin-1 and cp1252 are parsed as bytes. A header with a
    # character outside ASCII (the degree sign) and a comment line; auto detection reads the
    # head in the map's encoding too.
    rows = [f"{0.002 * i:.3f};{20.0 * (1 - math.exp(-i / 5)):.3f};100" for i in range(300)]
    text = "% speed in rpm, angle in \u00b0\nt;v\u00b0;cmd\n" + "\r\n".join(rows) + "\r\n"
    p = tmp_path / "log.txt"
    p.write_bytes(text.encode(encoding))
    m = write_map(tmp_path, f"[file]\nencoding = \"{encoding}\"\n[time]\ncolumn = \"t\"\n"
                  "unit = \"s\"\n[wheels]\nwheel1 = { column = \"v\u00b0\", unit = \"rpm\" }\n"
                  "[commands]\nsetpoint = { column = \"cmd\", unit = \"rpm\" }\n")
    for fmt in ("text", "auto"):
        rec = import_source(p, fmt, map_path=m).recording
        assert len(rec) == 300
        np.testing.assert_allclose(rec.t_s, 0.002 * np.arange(300), atol=1e-9)
        np.testing.assert_allclose(rec.wheel_rpm[:, 0],
                                   [float(r.split(";")[1]) for r in rows])
        assert (rec.commands[:, 0] == 100).all()
    assert detect_format(p, m) == "text"


def test_a_value_overflowing_its_unit_conversion_is_refused_not_written(tmp_path):
    p = tmp_path / "log.txt"
    p.write_text("t,w\n0,1\n0.001,1e308\n0.002,3\n")
    m = write_map(tmp_path, "[time]\ncolumn = \"t\"\n[wheels]\n"
                  "wheel1 = { column = \"w\", unit = \"rad/s\" }\n")
    with pytest.raises(RecordingError, match=r"imported row 2 \(t = 0.001 s\), column "
                       r"'wheel1_rpm': inf is not a value a robot logs"):
        import_source(p, "text", map_path=m)
