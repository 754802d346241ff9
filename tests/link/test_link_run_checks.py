"""``record`` never reports success for a run that was not what was asked: the e-stop or a
drive fault, commands the controller does not acknowledge, wheel readings that are not
numbers, a controller clock that drifts and a host that paused its own command stream each
end with STOP, their own reason and exit code, one summary line and every sample kept."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from mecanum_hil.io.recording import read_recording
from mecanum_hil.link import protocol as proto
from mecanum_hil.link.record import format_summary
from mecanum_hil.link.session import (
    EXIT_CODES,
    NOT_AS_ASKED,
    STOP_AT_ONCE,
    SessionConfig,
    run_record_session,
)
from mecanum_hil.model import RobotProfile

ROBOT = RobotProfile()
FAST = SessionConfig(connect_timeout_s=1.0, link_timeout_s=0.3, tail_s=0.05)


def _stream(duration_s, rate_hz=50.0):
    t = np.arange(int(duration_s * rate_hz) + 1) / rate_hz
    return t, np.tile([30.0, 0.0, 90.0], (t.size, 1))


def _events(rec, kind):
    return [i for i, e in enumerate(rec.extra["event"]) if e == kind]


def _run(p, host_serial, tmp_path, t, cmd, **kw):
    res = run_record_session(host_serial(p.path), t, cmd, tmp_path / "r.csv", ROBOT,
                             config=kw.pop("config", FAST), **kw)
    side = json.loads((tmp_path / "r.json").read_text())
    return res, read_recording(tmp_path / "r.csv"), side


def _ends_as(res, side, reason):
    assert res.reason == reason and res.exit_code == EXIT_CODES[reason], res.message
    assert side["end_reason"] == reason and side["exit_code"] == res.exit_code
    first = format_summary(res).splitlines()[0]
    assert first.startswith(f"{reason} (exit {res.exit_code})") and res.message in first


@pytest.mark.parametrize(("bit", "reason"), [(proto.Status.ESTOP, "estop"),
                                             (proto.Status.FAULT, "drive_fault")])
def test_the_e_stop_or_a_fault_mid_run_stops_at_once(bit, reason, pty_pair, scripted,
                                                     host_serial, tmp_path):
    p = pty_pair()
    ctrl = scripted(p.master, telemetry=400, status_of=lambda i: int(bit) if i >= 50 else 0)
    t, cmd = _stream(1.5)
    res, rec, side = _run(p, host_serial, tmp_path, t, cmd)
    _ends_as(res, side, reason)
    assert reason in STOP_AT_ONCE
    tlm, stop = _events(rec, "tlm"), _events(rec, "stop")
    assert len(stop) == 1 and _events(rec, "cmd")[-1] < stop[0]  # no command after STOP
    statuses = [int(float(rec.extra["status"][i])) for i in tlm]
    # at once: STOP follows the sample that set the bit, with no command of the profile
    # between them (rows, not seconds: a loaded machine stretches the seconds)
    first = tlm[statuses.index(int(bit))]
    assert not [i for i in _events(rec, "cmd") if first < i < stop[0]]
    assert res.commands_sent < t.size // 2
    # every sample kept: the 50 before the bit, the one that set it, the tail after STOP
    assert statuses[:50] == [0] * 50 and statuses[50] == int(bit)
    assert any(i > stop[0] for i in tlm)
    assert isinstance(ctrl.received[-1], proto.Stop)


def test_commands_left_unacknowledged_stop_the_run(pty_pair, scripted, host_serial, tmp_path):
    p = pty_pair()
    # telemetry at 250 Hz whose ack_seq stays 0 (the HELLO's): no command is ever taken
    scripted(p.master, telemetry=400, acks=False)
    t, cmd = _stream(1.5)
    res, rec, side = _run(p, host_serial, tmp_path, t, cmd)
    _ends_as(res, side, "not_acknowledged")
    assert "ack_seq stays at 0" in res.message
    # judged 0.5 s after the first command went unanswered, long before the profile's end
    assert 0.5 <= res.duration_s < 1.2
    assert side["run_checks"]["unacknowledged_commands"] >= 10
    assert _events(rec, "stop") and len(_events(rec, "tlm")) == res.telemetry_received


def test_acknowledged_commands_never_trip_the_ack_check(pty_pair, scripted, host_serial,
                                                        tmp_path):
    p = pty_pair()
    scripted(p.master, telemetry=400)
    t, cmd = _stream(1.2)
    res, _, side = _run(p, host_serial, tmp_path, t, cmd)
    _ends_as(res, side, "completed")
    assert side["run_checks"]["unacknowledged_commands"] < 10


def test_a_run_of_non_finite_readings_ends_the_completed_run_as_not_asked(
        pty_pair, scripted, host_serial, tmp_path):
    p = pty_pair()
    # 40 samples (160 ms) with NaN on wheel 2: longer than the 0.1 s a run may last
    scripted(p.master, telemetry=400,
             wheels_of=lambda i: (1.0, math.nan if 50 <= i < 90 else 2.0, 3.0, 4.0))
    t, cmd = _stream(1.0)
    res, rec, side = _run(p, host_serial, tmp_path, t, cmd)
    _ends_as(res, side, "invalid_readings")
    assert "in a row" in res.message and "invalid_readings" in NOT_AS_ASKED
    assert res.commands_sent == t.size  # judged at the end: the profile ran to its end
    assert side["run_checks"]["longest_invalid_s"] > 0.1
    assert np.isnan(rec.wheel_rpm[_events(rec, "tlm"), 1]).sum() == 40


def test_one_non_finite_reading_in_many_is_within_the_share(pty_pair, scripted, host_serial,
                                                            tmp_path):
    p = pty_pair()
    scripted(p.master, telemetry=400,
             wheels_of=lambda i: (1.0, math.inf if i == 50 else 2.0, 3.0, 4.0))
    t, cmd = _stream(1.0)
    res, _, side = _run(p, host_serial, tmp_path, t, cmd)
    _ends_as(res, side, "completed")
    assert side["invalid_readings"] == 1 and res.telemetry_received > 100


def test_a_controller_clock_at_a_third_of_the_host_s_is_clock_drift(pty_pair, scripted,
                                                                    host_serial, tmp_path):
    p = pty_pair()
    # a sample every 12 ms of host time, each stamped 4 ms later (the announced 250 Hz)
    scripted(p.master, telemetry=400, period_s=0.012, time_step_us=4000)
    t, cmd = _stream(2.5)
    config = SessionConfig(connect_timeout_s=1.0, link_timeout_s=0.3, tail_s=0.05,
                           clock_drift_slack_s=0.1)
    res, _, side = _run(p, host_serial, tmp_path, t, cmd, config=config)
    _ends_as(res, side, "clock_drift")
    assert res.commands_sent == t.size
    assert side["run_checks"]["clock_drift_s"] > 1.0
    assert "controller clock advanced" in res.message


def test_a_host_that_paused_its_command_stream_is_host_stall(pty_pair, scripted, host_serial,
                                                            tmp_path):
    p = pty_pair()
    scripted(p.master, telemetry=400)
    paused = []

    def progress(elapsed_s, total_s, counters):  # runs on the session's thread: a host stall
        if elapsed_s > 0.3 and not paused:
            paused.append(elapsed_s)
            time.sleep(0.2)

    t, cmd = _stream(1.0)
    config = SessionConfig(connect_timeout_s=1.0, link_timeout_s=0.3, tail_s=0.05,
                           host_stall_share=0.5)
    res, _, side = _run(p, host_serial, tmp_path, t, cmd, progress=progress, config=config)
    _ends_as(res, side, "host_stall")
    assert "paused" in res.message and side["run_checks"]["widest_command_gap_s"] > 0.125
    assert res.commands_sent == t.size
    assert [e["event"] for e in side["link_events"]].count("host_stall") == 1


def test_a_run_check_s_limit_comes_from_the_config_then_the_environment(monkeypatch):
    from mecanum_hil.errors import ConfigError
    from mecanum_hil.link.session import run_check_limit

    monkeypatch.setenv("MECANUM_HIL_HOST_STALL_SHARE", "0.8")
    assert run_check_limit(None, "MECANUM_HIL_HOST_STALL_SHARE", 0.5) == 0.8
    assert run_check_limit(0.3, "MECANUM_HIL_HOST_STALL_SHARE", 0.5) == 0.3
    monkeypatch.setenv("MECANUM_HIL_HOST_STALL_SHARE", "inf")
    assert run_check_limit(None, "MECANUM_HIL_HOST_STALL_SHARE", 0.5) == math.inf
    monkeypatch.delenv("MECANUM_HIL_HOST_STALL_SHARE")
    assert run_check_limit(None, "MECANUM_HIL_HOST_STALL_SHARE", 0.5) == 0.5
    for bad in ("half", "-1", "nan"):
        monkeypatch.setenv("MECANUM_HIL_HOST_STALL_SHARE", bad)
        with pytest.raises(ConfigError, match="MECANUM_HIL_HOST_STALL_SHARE must be a number"):
            run_check_limit(None, "MECANUM_HIL_HOST_STALL_SHARE", 0.5)


def test_a_bad_limit_in_the_environment_is_refused_before_anything_is_sent(
        pty_pair, host_serial, tmp_path, monkeypatch):
    from mecanum_hil.errors import ConfigError

    p = pty_pair()
    monkeypatch.setenv("MECANUM_HIL_CLOCK_DRIFT_SLACK_S", "soon")
    t, cmd = _stream(0.5)
    with pytest.raises(ConfigError, match="MECANUM_HIL_CLOCK_DRIFT_SLACK_S"):
        run_record_session(host_serial(p.path), t, cmd, tmp_path / "r.csv", ROBOT, config=FAST)
    assert not (tmp_path / "r.csv").exists()
