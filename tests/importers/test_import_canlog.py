"""CAN logs in: candump, ASC and BLF files written with python-can's writers from a simulated
Mecanum run, decoded with drivers/mecanum_hil.dbc or a user's DBC and mapping."""

from __future__ import annotations

import can
import cantools
import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.errors import ConfigError, RecordingError
from mecanum_hil.importers import detect_format, import_source
from mecanum_hil.importers.canlog import default_dbc
from mecanum_hil.importers.rosbag import twist_to_commands
from mecanum_hil.io.recording import read_recording
from mecanum_hil.model import Calibration, RobotProfile, simulate
from mecanum_hil.model.kinematics import command_to_twist
from mecanum_hil.units import RPM_TO_RAD_S, rpm_to_mps

EPOCH_S = 1_700_000_000.0
SEGMENTS = ((0.0, 0.0, 0.0, 90.0), (0.3, 60.0, 0.0, 90.0), (1.0, 80.0, 0.0, 45.0),
            (1.7, 0.0, 60.0, 45.0), (2.4, 50.0, -30.0, 200.0), (3.0, 0.0, 0.0, 200.0))
WRITERS = {"candump": (can.CanutilsLogWriter, ".log"), "asc": (can.ASCWriter, ".asc"),
           "blf": (can.BLFWriter, ".blf")}

USER_DBC = """VERSION ""

NS_ :

BS_:

BU_: PLC DRIVE

BO_ 1280 DRIVE_TWIST: 6 PLC
 SG_ vx : 0|16@1- (0.001,0) [-32.768|32.767] "m/s" DRIVE
 SG_ vy : 16|16@1- (0.001,0) [-32.768|32.767] "m/s" DRIVE
 SG_ wz : 32|16@1- (0.001,0) [-32.768|32.767] "rad/s" DRIVE

BO_ 2147488001 MOTOR_SPEEDS: 8 DRIVE
 SG_ fl : 0|16@1- (0.01,0) [-327.68|327.67] "rad/s" PLC
 SG_ fr : 16|16@1- (0.01,0) [-327.68|327.67] "rad/s" PLC
 SG_ rl : 32|16@1- (0.01,0) [-327.68|327.67] "rad/s" PLC
 SG_ rr : 48|16@1- (0.01,0) [-327.68|327.67] "rad/s" PLC
"""

USER_MAP = f"""
[can]
dbc = "user.dbc"

[can.columns]
cmd_vx_mps = "DRIVE_TWIST.vx"
cmd_vy_mps = "DRIVE_TWIST.vy"
cmd_wz_radps = "DRIVE_TWIST.wz"
wheel1_rpm = {{ signal = "MOTOR_SPEEDS.fl", scale = {1 / RPM_TO_RAD_S!r} }}
wheel2_rpm = {{ signal = "MOTOR_SPEEDS.fr", scale = {1 / RPM_TO_RAD_S!r} }}
wheel3_rpm = {{ signal = "MOTOR_SPEEDS.rl", scale = {1 / RPM_TO_RAD_S!r} }}
wheel4_rpm = {{ signal = "MOTOR_SPEEDS.rr", scale = {1 / RPM_TO_RAD_S!r} }}
"""


def simulated_run(duration_s: float = 3.5, rate_hz: float = 100.0):
    t = np.arange(round(duration_s * rate_hz)) / rate_hz
    cmd = np.zeros((t.size, 3))
    for start, n, omega, theta in SEGMENTS:
        cmd[t >= start - 1e-9] = (n, omega, theta)
    traj = simulate(cmd, t, Calibration(), RobotProfile())
    return t, cmd, traj.wheel_rpm[0]


def _roundtrip(db, name: str, values: dict) -> dict:
    msg = db.get_message_by_name(name)
    return msg.decode(msg.encode(values))


def protocol_frames():
    """Frames of the mecanum-hil protocol for the run, and the values they carry."""
    db = cantools.database.load_file(str(default_dbc()))
    t, cmd, wheels = simulated_run()
    frames, exp_cmd, exp_wheels = [], [], []
    for i, ti in enumerate(t):
        ts = EPOCH_S + ti
        if i % 2 == 0:
            values = {"n_cmd": cmd[i, 0], "omega_cmd": cmd[i, 1], "theta_cmd": cmd[i, 2],
                      "seq": i // 2 % 256, "reserved": 0}
            data = db.get_message_by_name("MH_COMMAND").encode(values)
            frames.append(can.Message(timestamp=ts, arbitration_id=0x101, data=data,
                                      is_extended_id=False))
            got = _roundtrip(db, "MH_COMMAND", values)
            exp_cmd.append([got["n_cmd"], got["omega_cmd"], got["theta_cmd"]])
        status = db.get_message_by_name("MC_STATUS").encode(
            {"time_us": round(ti * 1e6), "status": 0, "ack_seq": 0, "seq": i % 256})
        frames.append(can.Message(timestamp=ts, arbitration_id=0x181, data=status,
                                  is_extended_id=False))
        wv = {f"wheel{k + 1}": wheels[i, k] for k in range(4)}
        frames.append(can.Message(timestamp=ts, arbitration_id=0x182,
                                  data=db.get_message_by_name("MC_WHEELS").encode(wv),
                                  is_extended_id=False))
        got = _roundtrip(db, "MC_WHEELS", wv)
        exp_wheels.append([got[f"wheel{k + 1}"] for k in range(4)])
    stop_t = EPOCH_S + t[-1] + 0.005
    frames.append(can.Message(timestamp=stop_t, arbitration_id=0x100, data=bytes([7]),
                              is_extended_id=False))
    return frames, t, np.repeat(np.array(exp_cmd), 2, axis=0)[: t.size], np.array(exp_wheels)


def write_log(path, frames, kind: str):
    writer_cls, _ = WRITERS[kind]
    writer = writer_cls(path)
    for f in frames:
        writer.on_message_received(f)
    writer.stop()
    return path


@pytest.mark.parametrize("kind", list(WRITERS))
def test_protocol_log_recovers_the_run(tmp_path, kind):
    frames, t, exp_cmd, exp_wheels = protocol_frames()
    # content, not the name, tells the format
    path = write_log(tmp_path / ("run" + WRITERS[kind][1]), frames, kind)
    renamed = path.rename(tmp_path / "run.dat")
    assert detect_format(renamed) == "canlog"
    rec = import_source(renamed).recording
    assert len(rec) == t.size + 1  # a row per sample, and the STOP
    np.testing.assert_allclose(rec.t_s[:-1], t, rtol=0, atol=2e-6)
    np.testing.assert_allclose(rec.commands[:-1], exp_cmd, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(rec.wheel_rpm[:-1], exp_wheels)
    # STOP: n = omega = 0, theta kept
    np.testing.assert_allclose(rec.commands[-1], [0.0, 0.0, exp_cmd[-1, 2]])
    assert np.isnan(rec.wheel_rpm[-1]).all()
    assert rec.metadata["import"]["log_kind"] == kind


def test_users_dbc_and_mapping_with_a_twist(tmp_path, capsys):
    (tmp_path / "user.dbc").write_text(USER_DBC)
    (tmp_path / "map.toml").write_text(USER_MAP)
    db = cantools.database.load_string(USER_DBC)
    radius = RobotProfile().wheel_radius_m
    t, cmd, wheels = simulated_run()
    tw = command_to_twist(cmd[:, 0], cmd[:, 1], cmd[:, 2])
    frames, sent_twist, exp_wheels = [], [], []
    for i, ti in enumerate(t):
        values = {"vx": rpm_to_mps(tw[i, 0], radius), "vy": rpm_to_mps(tw[i, 1], radius),
                  "wz": np.radians(cmd[i, 1])}
        frames.append(can.Message(timestamp=EPOCH_S + ti, arbitration_id=0x500,
                                  data=db.get_message_by_name("DRIVE_TWIST").encode(values),
                                  is_extended_id=False))
        got = _roundtrip(db, "DRIVE_TWIST", values)
        sent_twist.append([got["vx"], got["vy"], got["wz"]])
        wv = dict(zip(("fl", "fr", "rl", "rr"), wheels[i] * RPM_TO_RAD_S, strict=True))
        frames.append(can.Message(timestamp=EPOCH_S + ti + 0.001, arbitration_id=0x1101,
                                  data=db.get_message_by_name("MOTOR_SPEEDS").encode(wv),
                                  is_extended_id=True))
        got = _roundtrip(db, "MOTOR_SPEEDS", wv)
        exp_wheels.append([got[k] / RPM_TO_RAD_S for k in ("fl", "fr", "rl", "rr")])
    log = write_log(tmp_path / "user.log", frames, "candump")
    out = tmp_path / "rec.csv"
    code = main(["import", str(log), "--map", str(tmp_path / "map.toml"), "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    rec = read_recording(out)
    st = np.array(sent_twist)
    expected = twist_to_commands(st[:, 0], st[:, 1], st[:, 2], radius)
    # rows: the twist at t, the motor speeds 1 ms later
    np.testing.assert_allclose(rec.t_s[0::2], t, atol=2e-6)
    np.testing.assert_allclose(rec.commands[0::2], expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(rec.wheel_rpm[1::2], exp_wheels, rtol=1e-8, atol=1e-6)
    assert np.isnan(rec.wheel_rpm[0::2]).all()
    assert rec.metadata["import"]["wheel_radius_m"] == radius
    assert any("frames (candump)" in n for n in rec.metadata["notes"])
    assert any("give --robot" in n for n in rec.metadata["notes"])


# -- bad input: one line naming the problem --------------------------------------------------

def test_dbc_lacking_a_mapped_signal(tmp_path, one_line_error):
    (tmp_path / "user.dbc").write_text(USER_DBC)
    (tmp_path / "map.toml").write_text(USER_MAP.replace("MOTOR_SPEEDS.rr", "MOTOR_SPEEDS.rear"))
    frames, *_ = protocol_frames()
    log = write_log(tmp_path / "run.log", frames[:10], "candump")
    err = one_line_error(["import", str(log), "--map", str(tmp_path / "map.toml"),
                                   "--out", str(tmp_path / "r.csv")])
    assert "user.dbc" in err and "no signal rear" in err and "wheel4_rpm" in err
    # the user's DBC without a mapping: the built-in mapping's messages are not in it
    err = one_line_error(["import", str(log), "--dbc", str(tmp_path / "user.dbc"),
                                   "--out", str(tmp_path / "r.csv")])
    assert "no message MH_COMMAND" in err


def test_log_without_the_mapped_frames_and_empty_log(tmp_path, one_line_error):
    frames, *_ = protocol_frames()
    only_wheels = [f for f in frames if f.arbitration_id == 0x182]
    log = write_log(tmp_path / "w.log", only_wheels, "candump")
    err = one_line_error(["import", str(log), "--out", str(tmp_path / "r.csv")])
    assert "no frames of MH_COMMAND" in err
    empty = write_log(tmp_path / "e.blf", [], "blf")
    err = one_line_error(["import", str(empty), "--out", str(tmp_path / "r.csv")])
    assert "no frames" in err


def test_truncated_blf(tmp_path, capsys):
    frames, *_ = protocol_frames()
    path = write_log(tmp_path / "run.blf", frames, "blf")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2 + 7])
    with pytest.raises(RecordingError, match="truncated") as err:
        import_source(path)
    assert str(path) in str(err.value)


def test_a_corrupt_frame_mid_log_is_one_error_and_closes_the_log(tmp_path):
    """python-can's readers close their file only at the end of the log: a corrupt line in
    the middle must not leave it open."""
    import gc
    import warnings

    frames, *_ = protocol_frames()
    path = write_log(tmp_path / "run.log", frames, "candump")
    lines = path.read_text().splitlines(True)
    lines.insert(len(lines) // 2, "(1700000000.000000) vcan0 1G2#ZZZZ\n")
    path.write_text("".join(lines))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(RecordingError, match="cannot read the candump log") as err:
            import_source(path)
        del err
        gc.collect()
    leaked = [w for w in caught if issubclass(w.category, ResourceWarning)]
    assert not leaked, leaked[0].message


def test_bad_mapping_files(tmp_path):
    bad = tmp_path / "m.toml"
    bad.write_text('[can.columns]\nn_cmd_rpm = "A.b"\nwheel1_rpm = "A.c"\n')
    with pytest.raises(ConfigError, match="either the three commands"):
        import_source(write_log(tmp_path / "x.log", protocol_frames()[0][:3], "candump"),
                      map_path=bad)
    bad.write_text('[can.columns]\nspeed = "A.b"\n')
    with pytest.raises(ConfigError, match="not a recording column"):
        import_source(tmp_path / "x.log", map_path=bad)


# -- time that runs back, cut and malformed lines ---------------------------------------------

def test_a_clock_reset_is_refused_naming_the_line(tmp_path, one_line_error):
    """A log whose clock resets halfway is not sorted into interleaved halves."""
    frames, *_ = protocol_frames()
    half = len(frames) // 2
    for f in frames[half:]:
        f.timestamp -= 1.7
    log = write_log(tmp_path / "reset.log", frames, "candump")
    err = one_line_error(["import", str(log), "--out", str(tmp_path / "r.csv")])
    first = next(k for k in range(half, len(frames)) if frames[k].arbitration_id != 0x181)
    assert f"line {first + 1} (" in err and "runs back 1.69 s" in err, err
    assert not (tmp_path / "r.csv").exists()
    # every wheel frame on a clock 1e8 s earlier (python-can's writer would clamp it)
    log = write_log(tmp_path / "tb.log", protocol_frames()[0], "candump")
    log.write_text("".join(ln.replace("(17", "(16", 1) if " 182#" in ln else ln
                           for ln in log.read_text().splitlines(True)))
    with pytest.raises(RecordingError, match=r"tb\.log, line \d+ \(MC_WHEELS\).*runs back "
                       r"1e\+08 s"):
        import_source(log)


def test_jitter_within_a_millisecond_is_sorted_with_a_note(tmp_path):
    frames, *_ = protocol_frames()
    wheels = [k for k, f in enumerate(frames) if f.arbitration_id == 0x182]
    k = wheels[10]  # a wheel frame logged 0.5 ms after its successor's status frame
    frames[k].timestamp += 0.0105
    frames[k], frames[k + 1] = frames[k + 1], frames[k]
    res = import_source(write_log(tmp_path / "j.log", frames, "candump"))
    assert any("1 frame(s) up to" in n and "sorted into time order" in n for n in res.notes)


def test_a_cut_last_line_is_skipped_and_a_malformed_line_named(tmp_path, one_line_error):
    frames, *_ = protocol_frames()
    log = write_log(tmp_path / "cut.log", frames, "candump")
    text = log.read_text()
    log.write_text(text[: len(text) - 20])  # the logger stopped mid-line
    res = import_source(log)
    assert any("last line cut off mid-line" in n and "skipped" in n for n in res.notes)
    lines = text.splitlines(True)
    lines[99] = "(1700000000.5) vcan0 182#00G0\n"
    log.write_text("".join(lines))
    err = one_line_error(["import", str(log), "--out", str(tmp_path / "r.csv")])
    assert "line 100" in err and "182#00G0" in err


def test_an_option_the_format_does_not_take_lists_user_facing_flags(tmp_path, one_line_error):
    log = write_log(tmp_path / "run.log", protocol_frames()[0][:30], "candump")
    err = one_line_error(["import", str(log), "--joints", "a,b,c,d", "--out",
                          str(tmp_path / "r.csv")])
    assert "--dbc, --map, --robot" in err and "--wheel-radius-m" not in err
