"""``mecanum-hil diagnose`` as a user runs it, its report, and the real micromouse data."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mecanum_hil.identify.campaign import paper_campaign
from mecanum_hil.identify.diagnose import diagnose
from mecanum_hil.identify.fit import fit
from mecanum_hil.io.recording import read_recording, write_recording
from mecanum_hil.link.effects_file import sim_effects_for
from mecanum_hil.model import Effects, RobotProfile, load_calibration
from mecanum_hil.profiles import ramp, step

ROBOT = RobotProfile()
REPO = Path(__file__).resolve().parents[2]
# a short campaign: two steps and a fast ramp past a 110 rpm ceiling
PROFILES = [step(60.0, duration_s=1.5, rest_s=0.3, stop_s=1.0),
            step(120.0, duration_s=1.5, rest_s=0.3, stop_s=1.0),
            ramp(130.0, 20.0, hold_s=0.5, rest_s=0.3, stop_s=1.0)]


#: The keys of ``diagnose --json`` (docs/diagnose.md), in order.
JSON_KEYS = ["effects", "unexplained", "rmse_initial", "rmse_final", "rmse_baseline",
             "noise_rpm", "rmse_reference", "explained_share", "pose_rmse_before",
             "pose_rmse_after", "residual"]


#: Effects that a latency of the link (host <-> controller) can be named as.
LATENCY = ("dead_time", "drive_lag", "controller_period")


def cli(*args):
    return subprocess.run([sys.executable, "-m", "mecanum_hil", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def campaign():
    hidden = sim_effects_for(Effects(top_speed_rpm=110.0), wheel_rpm_std=0.25, seed=11)
    return paper_campaign(hidden, ROBOT, seed=11, profiles=PROFILES)


def test_cli_json_out_and_report_with_two_candidates(tmp_path, campaign):
    """The fast suite's run of the command: the two effects the ceiling and the link's latency
    are named as; the whole library's search is the slow test below."""
    paths = [write_recording(r, tmp_path / f"{r.metadata['profile']}.csv") for r in campaign]
    out = tmp_path / "cal2.toml"
    r = cli("diagnose", *paths, "--calibration", "paper", "--candidates", "saturation,dead_time",
            "--out", out, "--report", tmp_path / "rep", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)  # stdout is exactly the JSON document
    assert list(doc) == JSON_KEYS
    assert "diagnose: round 1 " in r.stderr  # a sign of life meanwhile
    names = [e["effect"] for e in doc["effects"]]
    assert names[0] == "saturation", doc
    assert set(names[1:]) <= {"dead_time"}, doc
    for e in doc["effects"][1:]:
        assert e["parameters"]["dead_time_s"] <= 0.002, doc
    assert doc["effects"][0]["parameters"]["top_speed_rpm"] == pytest.approx(110.0, abs=1.5)
    assert doc["unexplained"] is False
    assert doc["rmse_final"] <= 0.5 * doc["rmse_initial"]
    cal = load_calibration(out)
    assert cal.effects.top_speed_rpm == pytest.approx(110.0, abs=1.5)
    assert cal.info["effects_added"] == names
    text = (tmp_path / "rep" / "report.md").read_text()
    assert "## Step 1: saturation" in text and "step1-saturation.png" in text
    assert (tmp_path / "rep" / "step1-saturation.png").stat().st_size > 10_000
    _header_counts_agree_with_the_regime_table(text)
    _every_key_is_named_in_the_docs(doc)
    # the extended calibration is accepted by simulate
    r = cli("simulate", "--commands", paths[1], "--calibration", out, "--out", tmp_path / "s.csv")
    assert r.returncode == 0, r.stderr
    assert read_recording(tmp_path / "s.csv").wheel_rpm.max() < 111.0


@pytest.mark.slow
def test_cli_json_out_and_report(tmp_path, campaign):
    paths = [write_recording(r, tmp_path / f"{r.metadata['profile']}.csv") for r in campaign]
    out = tmp_path / "cal2.toml"
    r = cli("diagnose", *paths, "--calibration", "paper", "--out", out,
            "--report", tmp_path / "rep", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)  # stdout is exactly the JSON document
    assert list(doc) == JSON_KEYS
    # the ceiling first; the link's own latency (about 1 ms: tests/identify/test_diagnose.py)
    # may be named after it, and nothing else
    names = [e["effect"] for e in doc["effects"]]
    assert names[0] == "saturation", doc
    for e in doc["effects"][1:]:
        assert e["effect"] in LATENCY, doc
        # a drive lag and the motor's time constant can be exchanged (docs/diagnose.md): the
        # latency is the shorter of the lag named and its twin
        latency = [*e["parameters"].values()]
        if "equivalent" in e:
            latency.append(e["equivalent"]["drive_lag_s"])
        assert min(latency) <= 0.002, doc
    assert list(doc["effects"][0]) == ["effect", "parameters", "rmse_before", "rmse_after",
                                       "share", "pose_rmse_before", "pose_rmse_after"]
    assert doc["effects"][0]["share"] > 0.9
    assert doc["effects"][0]["parameters"]["top_speed_rpm"] == pytest.approx(110.0, abs=1.5)
    assert doc["unexplained"] is False
    assert doc["rmse_final"] <= 0.5 * doc["rmse_initial"]
    cal = load_calibration(out)
    assert cal.effects.top_speed_rpm == pytest.approx(110.0, abs=1.5)
    assert cal.info["effects_added"] == names
    text = (tmp_path / "rep" / "report.md").read_text()
    assert "## Step 1: saturation" in text and "step1-saturation.png" in text
    _header_counts_agree_with_the_regime_table(text)
    _every_key_is_named_in_the_docs(doc)
    assert (tmp_path / "rep" / "step1-saturation.png").stat().st_size > 10_000
    _header_counts_agree_with_the_regime_table(text)
    _every_key_is_named_in_the_docs(doc)
    # the extended calibration is accepted by simulate
    r = cli("simulate", "--commands", paths[1], "--calibration", out, "--out", tmp_path / "s.csv")
    assert r.returncode == 0, r.stderr
    assert read_recording(tmp_path / "s.csv").wheel_rpm.max() < 111.0


def _header_counts_agree_with_the_regime_table(text: str) -> None:
    """The report's header counts the wheel samples that each regime grouping shares out."""
    n = int(re.search(r"(\d+) measured wheel samples", text).group(1))
    table = text.split("## Where the model as given fails", 1)[1].split("```")[1]
    groups: dict[str, int] = {}
    for line in table.splitlines():
        if line.startswith(" by "):
            group = line.strip()
            groups[group] = 0
        elif groups and line.startswith("  ") and "%" in line:
            groups[group] += int(line[14:].split()[0])
    assert len(groups) == 3 and set(groups.values()) == {n}, (n, groups)


def _keys(value):
    if isinstance(value, dict):
        for k, v in value.items():
            yield k
            yield from _keys(v)
    elif isinstance(value, list):
        for v in value:
            yield from _keys(v)


def _every_key_is_named_in_the_docs(doc: dict) -> None:
    docs = (REPO / "docs" / "diagnose.md").read_text(encoding="utf-8")
    missing = sorted({k for k in _keys(doc) if f"`{k}`" not in docs})
    assert not missing, f"docs/diagnose.md names no `{missing}`"


@pytest.mark.slow
def test_one_recording_is_enough(tmp_path, campaign):
    # the fast ramp alone reaches the ceiling: held-out time blocks instead of recordings
    p = write_recording(campaign[2], tmp_path / "ramp.csv")
    r = cli("diagnose", p, "--calibration", "paper", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert list(doc) == JSON_KEYS
    assert "saturation" in [e["effect"] for e in doc["effects"]]
    assert doc["rmse_final"] <= 0.5 * doc["rmse_initial"]


def test_cli_errors_are_one_line(tmp_path, campaign):
    p = write_recording(campaign[0], tmp_path / "one.csv")
    r = cli("diagnose", p, p, "--candidates", "backlash")
    assert r.returncode == 1
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1
    assert r.returncode == 1 and "unknown effect(s) 'backlash'" in r.stderr
    r = cli("diagnose", p, "--candidates", " , ")
    assert r.returncode == 1 and r.stderr.count("\n") == 1
    assert "--candidates names no effect" in r.stderr
    r = cli("diagnose", tmp_path / "missing.csv", p)
    assert r.returncode == 1 and "file not found" in r.stderr


def _onset_s(t, w, t_step, target):
    """Time from the step to the interpolated crossing of half the target [s]."""
    ok = np.isfinite(w) & (t >= t_step)
    tt, ww = t[ok], w[ok]
    j = int(np.argmax(ww >= 0.5 * target))
    f = (0.5 * target - ww[j - 1]) / (ww[j] - ww[j - 1]) if j else 0.0
    return tt[max(j - 1, 0)] + f * (tt[j] - tt[max(j - 1, 0)]) - t_step


@pytest.mark.slow
@pytest.mark.parametrize("name", ["testPid7", "testPid8", "controllerDelayImpact1ms"])
def test_real_micromouse_recording_alone(shared_real_data, name):
    """diagnose on each real recording alone: its wheel RMSE at least 30 % below fit's
    (figures in docs/benchmarks/diagnose-micromouse.md)."""
    from mecanum_hil.model import load_robot_profile
    from mecanum_hil.prediction import predict

    folder = shared_real_data / "micromouse"
    if not (folder / f"{name}.csv").exists():
        pytest.skip("the micromouse recordings are not there")
    robot = load_robot_profile(folder / "robot.toml")
    rec = read_recording(folder / f"{name}.csv")
    user = fit([rec], robot).calibration
    d = diagnose([rec], user, robot, names=[name])
    alone, diagnosed = predict(rec, user, robot), predict(rec, d.calibration, robot)
    t, target = rec.t_s, float(np.max(rec.commands[:, 0]))
    t_step = t[np.argmax(rec.commands[:, 0] != 0)]
    last = t >= t[-1] - 1.0
    for i in (0, 1):
        m, p = rec.wheel_rpm[:, i], diagnosed.wheel_rpm[:, i]
        assert abs(_onset_s(t, p, t_step, target) - _onset_s(t, m, t_step, target)) <= 0.020
        assert abs(np.mean(p[last]) - np.nanmean(m[last])) <= 0.03 * target
    def rmse(a):
        return float(np.sqrt(np.nanmean((rec.wheel_rpm - a.wheel_rpm) ** 2)))

    # at least 30 % below fit alone on each
    assert rmse(diagnosed) <= 0.7 * rmse(alone)
    if name == "testPid7":
        # wheel gains and a fast-decay drive (docs/benchmarks/diagnose-micromouse.md): the final
        # model does better than the generic linear reference of higher order, and the drive's
        # friction and no-load speed are those the logged duty says (about 2950 rpm/s at zero
        # duty, 544-905 rpm)
        assert "fast_decay" in d.effects
        assert d.explained_share >= 1.0
        fx = d.calibration.effects
        assert 2500.0 <= fx.coast_decel_rpm_per_s <= 3400.0
        assert 544.0 <= fx.no_load_rpm <= 905.0
    doc = d.to_json()
    assert doc["rmse_reference"] > 0 and doc["residual"]["shares"]


@pytest.mark.slow
def test_demo_story_finds_the_hidden_ceiling(tmp_path):
    from mecanum_hil.identify.diagnose_report import STORY_EFFECTS, diagnose_story

    lines: list[str] = []
    from mecanum_hil.identify.campaign import SHORT_CAMPAIGN, campaign_profiles

    files = diagnose_story(tmp_path, echo=lines.append,
                           profiles=campaign_profiles(**SHORT_CAMPAIGN))
    cal = load_calibration(files["diagnosed"])
    assert cal.effects.active().keys() == {"saturation"}
    assert cal.effects.top_speed_rpm == pytest.approx(STORY_EFFECTS.top_speed_rpm, abs=1.5)
    assert "## Step 1: saturation" in files["report"].read_text()
    assert lines[-1].startswith("named: saturation")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_quick_exit_still_ends_the_helper_process(tmp_path, campaign):
    """``diagnose`` ends with ``os._exit`` after its exit handlers (mecanum_hil/cli: the
    interpreter's teardown cost 0.3 s): nothing of the command outlives it (its helper
    process ended, by the handler that closes it or, at the latest, by its stdin's end), and
    its output and exit code are whole. The handlers themselves: tests/cli/test_cli_simulate.py."""
    import os
    import time

    p = write_recording(campaign[0], tmp_path / "one.csv")
    proc = subprocess.Popen([sys.executable, "-m", "mecanum_hil", "diagnose", p, "--calibration",
                             "paper", "--candidates", "dead_time,wheel_gain", "--jobs", "2",
                             "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert list(json.loads(out)) == JSON_KEYS

    def left() -> list[int]:
        pids = []
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                with open(f"/proc/{entry}/stat") as f:
                    stat = f.read()
            except OSError:
                continue
            # fields after the command's closing parenthesis: state, ppid, pgrp, session
            fields = stat.rsplit(")", 1)[1].split()
            if int(fields[3]) == proc.pid and fields[0] != "Z":
                pids.append(int(entry))
        return pids

    deadline = time.monotonic() + 5.0
    while left() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert left() == [], "a process of the diagnosis outlived it"
