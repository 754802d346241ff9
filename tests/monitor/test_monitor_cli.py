"""``mecanum-hil shadow --replay``: exact JSON, exit codes, event log, one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mecanum_hil.io.recording import write_recording
from mecanum_hil.model import Calibration
from mecanum_hil.monitor.scenarios import driving_commands, make_fault, simulate_run


def cli(*args):
    return subprocess.run([sys.executable, "-m", "mecanum_hil", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("shadow")
    t, cmd = driving_commands(14.0, 100.0)
    cal = Calibration()
    faulty = write_recording(simulate_run(t, cmd, cal, make_fault("stall", 10.0, wheel=3)),
                             d / "faulty.csv")
    nominal = write_recording(simulate_run(t, cmd, cal, None, seed=5), d / "nominal.csv")
    return faulty, nominal


def test_replay_json_with_alarm_exits_3_and_writes_the_event_log(runs, tmp_path):
    faulty, _ = runs
    r = cli("shadow", "--replay", faulty, "--json", "--plot", tmp_path / "p.png")
    assert r.returncode == 3, r.stderr
    out = json.loads(r.stdout)
    assert list(out) == ["alarms", "first_alarm_t_s"]
    assert all(list(a) == ["t_s", "channel", "residual"] for a in out["alarms"])
    assert out["alarms"][0]["channel"] == "wheel3_rpm"
    assert out["first_alarm_t_s"] == out["alarms"][0]["t_s"]
    assert 10.0 <= out["first_alarm_t_s"] <= 10.3
    log = faulty.with_name("faulty.shadow.jsonl")
    events = [json.loads(line) for line in log.read_text().splitlines()]
    assert events[0]["event"] == "start" and events[0]["calibration"].endswith("paper.toml")
    assert next(e["channel"] for e in events if e["event"] == "alarm") == "wheel3_rpm"
    assert events[-1]["event"] == "end"
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_replay_nominal_exits_0_with_null_first_alarm(runs, tmp_path):
    _, nominal = runs
    r = cli("shadow", "--replay", nominal, "--json", "--events", tmp_path / "ev.jsonl")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout) == {"alarms": [], "first_alarm_t_s": None}
    assert (tmp_path / "ev.jsonl").exists()


def test_replay_never_replaces_a_live_runs_event_log(runs, tmp_path):
    # the alarms of a live run (record --shadow) were seen once: a replay beside it writes its
    # own log as run.replay.jsonl (the README's record --shadow then shadow --replay), and
    # refuses an --events that names the live one; a replay's own log is replaced by the next
    faulty, _ = runs
    rec = tmp_path / "run.csv"
    rec.write_bytes(faulty.read_bytes())
    live = tmp_path / "run.shadow.jsonl"
    live.write_text(json.dumps({"event": "start", "t_s": None, "mode": "record"}) + "\n"
                    + json.dumps({"event": "alarm", "t_s": 3.0, "channel": "wheel1_rpm"})
                    + "\n")
    before = live.read_bytes()
    r = cli("shadow", "--replay", rec, "--noise-rpm", "1.0")
    assert r.returncode == 3, r.stderr
    assert "run.replay.jsonl (the live run's run.shadow.jsonl is kept)" in r.stdout
    assert live.read_bytes() == before
    assert '"mode": "replay"' in (tmp_path / "run.replay.jsonl").read_text()
    r = cli("shadow", "--replay", rec, "--noise-rpm", "1.0", "--events", live)
    assert r.returncode == 1 and r.stderr.count("\n") == 1
    assert "event log of a live run (record)" in r.stderr
    assert live.read_bytes() == before
    mine = tmp_path / "replay.jsonl"
    assert cli("shadow", "--replay", rec, "--events", mine).returncode == 3
    assert cli("shadow", "--replay", rec, "--events", mine).returncode == 3  # replaced


def test_an_interrupted_replay_leaves_the_previous_log(runs, tmp_path, monkeypatch):
    # Ctrl-C part-way left a log of "start" and a normal "end" (a replay with no alarms, by
    # the look of it), or a cut one; the previous, whole log was gone
    from mecanum_hil.cli import main
    from mecanum_hil.monitor import core

    faulty, _ = runs
    rec = tmp_path / "run.csv"
    rec.write_bytes(faulty.read_bytes())
    log = tmp_path / "run.shadow.jsonl"
    assert main(["shadow", "--replay", str(rec), "--noise-rpm", "1.0"]) == 3
    before = log.read_bytes()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(core.ShadowMonitor, "run", interrupted)
    assert main(["shadow", "--replay", str(rec), "--noise-rpm", "1.0"]) == 130
    assert log.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv", "run.shadow.jsonl"]


def test_replay_that_compares_nothing_is_an_error_not_all_clear(runs, tmp_path):
    # a noise level given for wheels the recording does not have armed them, and the pose it
    # has never finished its warm-up: "0 alarm(s)" would have read as a robot like its model
    from mecanum_hil.io.recording import read_recording

    rec = read_recording(runs[1])
    rec = rec.select(slice(0, int(np.searchsorted(rec.t_s, 5.0))))  # too short for the pose
    pose_only = write_recording(rec.with_values(wheel_rpm=np.full_like(rec.wheel_rpm, np.nan),
                                                pose=np.zeros_like(rec.pose)),
                                tmp_path / "p.csv")
    r = cli("shadow", "--replay", pose_only, "--no-events", "--noise-rpm", "0.5")
    assert r.returncode == 1 and r.stderr.count("\n") == 1
    assert "nothing was compared" in r.stderr


def test_replay_text_output_names_the_alarm(runs):
    faulty, _ = runs
    r = cli("shadow", "--replay", faulty, "--no-events", "--noise-rpm", "1.0")
    assert r.returncode == 3
    assert "ALARM" in r.stdout and "wheel3_rpm" in r.stdout


def test_an_event_log_that_cannot_be_written_beside_the_recording_names_the_options(
        runs, tmp_path):
    # the default log goes beside the recording, which may be read-only (another lab's data):
    # here its name is taken by a folder, which even root cannot open as a file
    _, nominal = runs
    rec = tmp_path / "run.csv"
    rec.write_bytes(nominal.read_bytes())
    (tmp_path / "run.shadow.jsonl").mkdir()
    r = cli("shadow", "--replay", rec)
    assert r.returncode == 1
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
    assert "cannot create the event log" in r.stderr
    assert "--events PATH" in r.stderr and "--no-events" in r.stderr
    r = cli("shadow", "--replay", rec, "--no-events")
    assert r.returncode == 0, r.stderr


def test_a_recording_shorter_than_the_warm_up_is_refused_not_passed(runs, tmp_path):
    # 1.5 s: the noise estimate never completes, nothing is checked; "0 alarms" and exit 0
    # would read as a robot that matched its model
    _, nominal = runs
    from mecanum_hil.io.recording import read_recording

    rec = read_recording(nominal)
    short = write_recording(rec.select(rec.t_s < 1.5), tmp_path / "short.csv")
    r = cli("shadow", "--replay", short, "--no-events")
    assert r.returncode == 1
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr
    assert "never armed" in r.stderr and "--noise-rpm" in r.stderr
    # given the noise level, it is checked from the first sample
    r = cli("shadow", "--replay", short, "--no-events", "--noise-rpm", "2.0", "--json")
    assert r.returncode in (0, 3), r.stderr
    assert list(json.loads(r.stdout)) == ["alarms", "first_alarm_t_s"]


@pytest.mark.parametrize("args, message", [
    (["--replay", "missing.csv"], "file not found"),
    (["--replay", "x.csv", "--on-divergence", "explode"], "--on-divergence"),
])
def test_bad_input_is_one_error_line(args, message, tmp_path):
    r = cli("shadow", *args)
    assert r.returncode == 1
    assert r.stderr.startswith("error: ") and message in r.stderr
    assert "Traceback" not in r.stderr


def test_recording_without_measurements_is_refused(tmp_path):
    t, cmd = driving_commands(2.0, 50.0)
    rec = simulate_run(t, cmd, Calibration(), None)
    path = write_recording(rec.with_values(wheel_rpm=rec.wheel_rpm * float("nan")),
                           tmp_path / "empty.csv")
    r = cli("shadow", "--replay", path)
    assert r.returncode == 1 and "nothing measured" in r.stderr


def test_listen_on_a_quiet_bus_hears_nothing_and_says_nothing_was_compared(tmp_path):
    # exit 0 read as "no divergence" although nothing was compared
    r = cli("shadow", "--transport", "can", "--interface", "virtual", "--channel", "quiet",
            "--duration", "0.3", "--out", tmp_path / "heard.csv")
    assert r.returncode == 1
    assert r.stderr.startswith("error: heard no telemetry on virtual:quiet")
    assert r.stderr.count("\n") == 1
    assert "listening on virtual:quiet (sending nothing)" in r.stdout
    assert "heard 0 commands" in r.stdout
    assert (tmp_path / "heard.shadow.jsonl").read_text().count('"event"') == 2  # start, end
    for bad in ("nan", "-1", "0"):
        r = cli("shadow", "--transport", "can", "--interface", "virtual", "--channel", "quiet",
                "--duration", bad)
        assert r.returncode == 1 and "--duration must be" in r.stderr


def test_passive_listening_needs_can(tmp_path):
    r = cli("shadow", "--transport", "serial")
    assert r.returncode == 1 and r.stderr.startswith("error: ")
    assert "--transport can" in r.stderr


def test_a_replay_of_a_shipped_sample_writes_into_the_repository_only_when_asked(repo,
                                                                                  tmp_path):
    samples = repo / "recordings" / "samples"
    before = sorted(p.name for p in samples.iterdir())
    rec = samples / "paper-step-60.csv"
    try:
        r = cli("shadow", "--replay", rec, "--calibration", "paper")
        assert r.returncode in (0, 3), r.stderr
        assert sorted(p.name for p in samples.iterdir()) == before
        assert "wrote" not in r.stdout
        # asked for: the log goes where --events names it
        r = cli("shadow", "--replay", rec, "--calibration", "paper", "--events",
                tmp_path / "e.jsonl")
        assert r.returncode in (0, 3), r.stderr
        assert '"mode": "replay"' in (tmp_path / "e.jsonl").read_text()
    finally:
        for p in samples.iterdir():
            if p.name not in before:
                p.unlink()


def test_shipped_folders_are_the_package_and_the_checkouts_own(repo, tmp_path):
    from mecanum_hil.io.resources import is_shipped

    assert is_shipped(repo / "recordings" / "samples" / "paper-step-60.csv")
    assert is_shipped(repo / "mecanum_hil" / "x.csv")
    assert not is_shipped(repo / "runs" / "x.csv")  # a user's folder in the checkout
    assert not is_shipped(tmp_path / "x.csv")
