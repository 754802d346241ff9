"""End to end: ``sim-robot`` in a separate process on a real pseudo-terminal (serial framing,
and SLCAN for CAN), ``record`` talking to it; a killed simulator, SIGTERM, the dry run."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.io.recording import read_recording
from mecanum_hil.link.sim_process import SINGLE_THREAD_ENV, spawn_sim_robot
from mecanum_hil.model import load_calibration, load_robot_profile, simulate
from mecanum_hil.prediction import predict

PROFILE = """
[profile]
name = "e2e"
[[segments]]
kind = "hold"
duration_s = 0.2
[[segments]]
kind = "step"
duration_s = 0.6
n_rpm = 60.0
[[segments]]
kind = "ramp"
duration_s = 0.4
omega_dps = 40.0
[[segments]]
kind = "step"
duration_s = 0.3
n_rpm = 0.0
omega_dps = 0.0
"""
NOISE_STD = 0.5


@pytest.fixture
def profile_file(tmp_path):
    p = tmp_path / "e2e.toml"
    p.write_text(PROFILE)
    return p


def _check_against_model(path, noise_std, quantum=0.0):
    """Telemetry agrees with the model's prediction for the commands as sent, within the noise
    and the link's timing, whatever the machine's load.

    A sample taken at controller time ``c`` (host time ``c + offset``) saw commands that
    reached the controller up to the measured worst command-to-acknowledgement latency ``D``
    late, so it lies within the prediction's range over ``[c - D, c]`` (plus the noise); where
    the prediction is flat over that window the residual is the noise alone.
    """
    rec = read_recording(path)
    cal, robot = load_calibration(), load_robot_profile()
    tlm = np.array([e == "tlm" for e in rec.extra["event"]])
    assert tlm.sum() > 50
    ctrl_t = rec.extra_numeric("controller_time_s")[tlm]
    sample_t = ctrl_t + np.min(rec.t_s[tlm] - ctrl_t)  # on the host clock
    late_s = rec.metadata["latency_ms"]["ack_max"] / 1e3 + 0.002
    # a sample can predate the first command (received just after it): start the grid early
    start = min(0.0, float(sample_t.min()) - late_s) - 0.01
    grid = np.arange(start, rec.t_s[-1] + 0.01, 0.001)
    held = np.searchsorted(rec.t_s, grid, side="right") - 1
    commands = np.where((held >= 0)[:, None], rec.commands[np.clip(held, 0, None)],
                        [0.0, 0.0, 90.0])  # at rest before the first command
    wheels = simulate(commands, grid, cal, robot).wheel_rpm[0]
    lo_i = np.searchsorted(grid, sample_t - late_s)
    hi_i = np.searchsorted(grid, sample_t + 0.0015, side="right")
    lo = np.array([wheels[a:b].min(axis=0) for a, b in zip(lo_i, hi_i, strict=True)])
    hi = np.array([wheels[a:b].max(axis=0) for a, b in zip(lo_i, hi_i, strict=True)])
    got = rec.wheel_rpm[tlm]
    slack = 4.5 * noise_std + quantum + 1e-6
    assert (got >= lo - slack).all() and (got <= hi + slack).all()
    calm = (hi - lo).max(axis=1) < 0.05 * max(noise_std, 1.0)
    # how many samples are calm depends on the link's latency (the machine's load): enough
    # for the statistics below, whose tolerance follows the count
    assert calm.sum() >= 20
    residual = got[calm] - 0.5 * (lo[calm] + hi[calm])
    if noise_std > 0:
        # 4 standard errors of a standard deviation estimated from residual.size values
        assert residual.std() == pytest.approx(noise_std, rel=4.0 / math.sqrt(2 * residual.size))
    else:
        assert np.abs(residual).max() <= quantum + 0.025 + 1e-9
    # and the model's own prediction for the recording (host times) is close on average
    pred = predict(rec, cal, robot)
    assert np.median(np.abs(pred.wheel_rpm[tlm] - got)) < 2 * noise_std + 0.5
    return rec


def test_record_over_serial_to_sim_robot_matches_the_model(tmp_path, profile_file, capsys):
    fx = tmp_path / "fx.toml"
    fx.write_text(f"[noise]\nwheel_rpm_std = {NOISE_STD}\nseed = 3\n")
    out = tmp_path / "run.csv"
    with spawn_sim_robot("--serial", "--effects", str(fx)) as sim:
        code = main(["record", "--port", sim.path, "--profile", str(profile_file),
                     "--out", str(out), "--no-progress"])
        text = capsys.readouterr().out
        assert code == 0, text
        # the same commands again, now read from the recording just made
        again = tmp_path / "again.csv"
        assert main(["record", "--port", sim.path, "--commands", str(out), "--out", str(again),
                     "--no-progress"]) == 0
        time.sleep(0.1)
        log = sim.log()
    assert "completed (exit 0)" in text and "lost 0" in text and "round trip  p50" in text
    rec = _check_against_model(out, NOISE_STD)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["end_reason"] == "completed" and meta["controller"] == "mecanum-hil sim-robot"
    ctrl_t = rec.extra_numeric("controller_time_s")
    tlm = np.isfinite(ctrl_t)
    assert np.all(np.diff(ctrl_t[tlm]) > 0)  # controller clock kept beside host time
    # host and controller clocks differ by a constant plus the link latency (and, on a loaded
    # machine, the odd stall: a late sample keeps its own controller time)
    offset = rec.t_s[tlm] - ctrl_t[tlm]
    assert np.median(offset - offset.min()) < 0.02
    _check_against_model(again, NOISE_STD)
    assert log.count("STOP received") == 2 and log.count("HELLO: session started") == 2


def test_record_force_replaces_a_former_run_with_its_event_log(tmp_path, profile_file,
                                                               capsys):
    # --force replaced the CSV and sidecar but left the former run's REC.shadow.jsonl, which
    # export and a replay then took for the new run's
    out = tmp_path / "run.csv"
    out.write_text("t_s\n0\n")
    stale = tmp_path / "run.shadow.jsonl"
    stale.write_text('{"event": "start", "t_s": null, "mode": "record"}\n')
    with spawn_sim_robot("--serial") as sim:
        args = ["record", "--port", sim.path, "--profile", str(profile_file), "--out", str(out),
                "--no-progress"]
        assert main(args) == 1  # refused: a recording is there
        assert "already there" in capsys.readouterr().err and stale.exists()
        assert main([*args, "--force"]) == 0
    assert not stale.exists()
    assert json.loads(out.with_suffix(".json").read_text())["end_reason"] == "completed"


def test_record_over_slcan_to_sim_robot_in_another_process(tmp_path, profile_file):
    out = tmp_path / "can.csv"
    with spawn_sim_robot("--slcan") as sim:
        code = main(["record", "--transport", "can", "--interface", "slcan", "--channel",
                     sim.path, "--link-option", "sleep_after_open=0", "--profile",
                     str(profile_file), "--out", str(out), "--no-progress"])
    assert code == 0
    rec = _check_against_model(out, 0.0, quantum=0.005)  # 0.01 rpm signal resolution
    assert json.loads(out.with_suffix(".json").read_text())["link_stats"]["lost"] == 0
    assert rec.metadata["transport"] == "can"


def test_sim_robot_killed_mid_run_is_a_lost_link(tmp_path, capsys):
    out = tmp_path / "killed.csv"
    with spawn_sim_robot("--serial") as sim:
        timer = threading.Timer(0.8, sim.proc.kill)
        timer.start()
        code = main(["record", "--port", sim.path, "--profile", "paper-step-60",
                     "--out", str(out), "--no-progress"])
        timer.join()
    err = capsys.readouterr().err
    assert code == 4 and "link lost" in err
    rec = read_recording(out)  # valid, with everything received before the kill
    assert 0.5 < rec.t_s[-1] < 3.0 and rec.extra["event"].count("tlm") > 30
    assert json.loads(out.with_suffix(".json").read_text())["end_reason"] == "link_lost"


def test_sigterm_stops_the_robot_and_closes_the_recording(tmp_path):
    out = tmp_path / "term.csv"
    with spawn_sim_robot("--serial") as sim:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mecanum_hil", "record", "--port", sim.path, "--profile",
             "paper-step-60", "--out", str(out), "--no-progress"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**SINGLE_THREAD_ENV,
                                                                 **_env()})
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # wait until the run is under way
            if out.exists() and out.read_text().count("\n") > 20:
                break
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        stdout, _ = proc.communicate(timeout=20)
        time.sleep(0.1)
        log = sim.log()
    assert proc.returncode == 143
    assert b"terminated (exit 143)" in stdout
    assert "STOP received" in log
    rec = read_recording(out)
    assert rec.extra["event"][-1] == "stop"
    assert json.loads(out.with_suffix(".json").read_text())["end_reason"] == "terminated"


def test_a_closed_stdout_neither_ends_the_run_nor_changes_its_exit_code(tmp_path):
    """``record ... | head -c0``: the summary cannot be printed. Click exited 1 with no
    message although the run completed (the sidecar said 0); now the run's own code."""
    out = tmp_path / "run.csv"
    profile = tmp_path / "short.toml"
    profile.write_text('[profile]\nname = "short"\n[[segments]]\nkind = "step"\n'
                       'duration_s = 0.3\nn_rpm = 20.0\n')
    with spawn_sim_robot("--serial") as sim:
        read_end, write_end = os.pipe()
        os.close(read_end)  # nobody reads: every write is EPIPE
        try:
            proc = subprocess.run(
                [sys.executable, "-m", "mecanum_hil", "record", "--port", sim.path,
                 "--profile", str(profile), "--out", str(out), "--no-progress"],
                stdout=write_end, stderr=subprocess.PIPE, timeout=60,
                env={**SINGLE_THREAD_ENV, **_env()})
        finally:
            os.close(write_end)
        time.sleep(0.1)
        log = sim.log()
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == b""
    assert "STOP received" in log
    assert json.loads(out.with_suffix(".json").read_text())["exit_code"] == 0


def _env():
    import os

    return dict(os.environ)


def test_dry_run_and_limits_open_nothing(tmp_path, capsys):
    out = tmp_path / "dry.csv"
    code = main(["record", "--port", "/dev/does-not-exist", "--profile", "paper-step-60",
                 "--out", str(out), "--dry-run"])
    text = capsys.readouterr().out
    assert code == 0 and not out.exists()
    assert "dry run" in text and "COMMAND 00 04 02 02" in text and "within limits" in text
    prof = tmp_path / "fast.toml"
    prof.write_text('[[segments]]\nkind = "step"\nduration_s = 1.0\nn_rpm = 150.0\n')
    code = main(["record", "--port", "/dev/does-not-exist", "--profile", str(prof),
                 "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and err.startswith("error: ") and "beyond the robot's limit" in err
    assert not out.exists()
    assert main(["record", "--port", "/dev/does-not-exist", "--profile", "paper-step-60",
                 "--out", str(out), "--no-progress"]) == 1
    assert "cannot open serial port" in capsys.readouterr().err
