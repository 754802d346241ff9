"""``mecanum-hil campaign`` then ``fit`` then ``diagnose``, as a user reproduces diagnose's
proof from the command line: the effects file hides a deadband, nothing else is told."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mecanum_hil.io.recording import read_recording
from mecanum_hil.model import load_calibration


def cli(*args):
    return subprocess.run([sys.executable, "-m", "mecanum_hil", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_a_short_campaign_fit_diagnose_from_the_command_line(tmp_path):
    """The fast suite's run of the three commands: two recordings hide a 40 ms dead time, and
    diagnose weighs two candidates; the whole short campaign and library are the slow test below."""
    fx = tmp_path / "truth.toml"
    fx.write_text("[effects.dead_time]\ndead_time_s = 0.04\n[noise]\nwheel_rpm_std = 0.25\n"
                  "seed = 3\n")
    camp = tmp_path / "camp"
    r = cli("campaign", "--effects", fx, "--profile", "paper-step-60", "--profile", "paper-turn",
            "--out", camp, "--json")
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["recordings"]
    assert len(files) == 2
    rec = read_recording(files[0])
    assert set(rec.extra["event"]) == {"cmd", "tlm", "stop"}
    assert np.isfinite(rec.extra_numeric("controller_time_s")).sum() > 200
    assert rec.metadata["simulated_controller"]["effects"] == str(fx)
    cal = tmp_path / "cal.toml"
    r = cli("fit", *files, "--out", cal, "--no-report")
    assert r.returncode == 0, r.stderr
    # the text the command prints (diagnose --json: tests/identify/test_diagnose_cli.py)
    out = tmp_path / "diagnosed.toml"
    r = cli("diagnose", *files, "--calibration", cal, "--candidates", "dead_time,saturation",
            "--out", out)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    named = [x for x in lines if x.startswith("named: ")]
    assert len(named) == 1 and named[0].startswith("named: dead_time {'dead_time_s': "), r.stdout
    assert lines[-1] == f"wrote {out}"
    rmse = next(x for x in lines if x.startswith("wheel RMSE "))
    assert "unexplained" not in rmse, rmse
    before, after = (float(v) for v in rmse.removeprefix("wheel RMSE ").split(" rpm")[0]
                     .split(" -> "))
    assert after <= 0.5 * before
    diagnosed = load_calibration(out)
    assert diagnosed.info["effects_added"] == ["dead_time"]
    # the link adds about 1 ms to the robot's dead time (tests/identify/test_diagnose.py)
    assert diagnosed.effects.dead_time_s == pytest.approx(0.041, abs=0.003)
    assert not any(k.startswith("true_") for k in rec.metadata)
    r = cli("campaign", "--profile", "paper-turn", "--out", camp)
    assert r.returncode == 1 and "already holds recordings" in r.stderr


@pytest.mark.slow
def test_campaign_fit_diagnose_from_the_command_line(tmp_path):
    fx = tmp_path / "truth.toml"
    fx.write_text("[effects.deadband]\ndeadband_rpm = 6.0\n[noise]\nwheel_rpm_std = 0.25\n"
                  "seed = 3\n")
    camp = tmp_path / "camp"
    r = cli("campaign", "--effects", fx, "--short", "--out", camp, "--json")
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["recordings"]
    assert len(files) == 9
    rec = read_recording(files[0])
    # as record writes them: command, telemetry and stop rows, the controller's clock
    assert set(rec.extra["event"]) == {"cmd", "tlm", "stop"}
    assert np.isfinite(rec.extra_numeric("controller_time_s")).sum() > 200
    assert rec.metadata["simulated_controller"]["effects"] == str(fx)
    cal = tmp_path / "cal.toml"
    r = cli("fit", *files, "--out", cal, "--no-report")
    assert r.returncode == 0, r.stderr
    r = cli("diagnose", *files, "--calibration", cal, "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert [e["effect"] for e in doc["effects"]] == ["deadband"]
    assert doc["effects"][0]["parameters"]["deadband_rpm"] == pytest.approx(6.0, abs=0.3)
    assert doc["rmse_final"] <= 0.5 * doc["rmse_initial"] and not doc["unexplained"]
    # the truth stays in the effects file; a second campaign into the same folder is refused
    assert not any(k.startswith("true_") for k in rec.metadata)
    r = cli("campaign", "--short", "--out", camp)
    assert r.returncode == 1 and "already holds recordings" in r.stderr


@pytest.mark.parametrize("args, message", [
    (("--effects", "missing.toml"), "missing.toml"),
    (("--pose-noise", "1,2"), "--pose-noise"),
    (("--profile", "paper-turn", "--short"), "not both"),
    (("--profile", "no-such-profile"), "unknown profile"),
    (("--profile", "paper-turn", "--profile", "paper-turn"), "two profiles are named"),
    (("--telemetry-rate", "0"), "--telemetry-rate"),
    (("--pose-noise", "inf,0,0"), "--pose-noise"),
])
def test_bad_input_is_one_line(tmp_path, args, message):
    r = cli("campaign", "--out", tmp_path / "c", *args)
    assert r.returncode != 0
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
    assert message in r.stderr
    assert not (tmp_path / "c").exists()


def test_a_campaign_cut_short_leaves_none_of_its_recordings(tmp_path, monkeypatch, capsys):
    # a folder with some of the campaign's recordings looks like a smaller finished campaign
    # (fit and diagnose take it as one) and refuses the re-run
    import mecanum_hil.io.recording as recording
    from mecanum_hil.cli import main

    real, calls = recording.write_recording, []

    def write_then_interrupt(rec, path):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(rec, path)

    monkeypatch.setattr(recording, "write_recording", write_then_interrupt)
    camp = tmp_path / "camp"
    argv = ["campaign", "--profile", "paper-turn", "--profile", "paper-step-30", "--out", str(camp)]
    assert main(argv) == 130
    # said in one line (typer turned Ctrl-C into a silent exit 130)
    assert capsys.readouterr().err == "error: interrupted\n"
    assert len(calls) == 2 and list(camp.iterdir()) == []
    monkeypatch.setattr(recording, "write_recording", real)
    assert main(argv) == 0  # the re-run is not refused, and writes the whole campaign
    assert sorted(p.name for p in camp.glob("*.csv")) == ["paper-step-30.csv", "paper-turn.csv"]
    assert not (camp / ".part").exists()
