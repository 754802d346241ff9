"""Real filming conditions: a wheel starting at rest, a fender and cards hiding the
marker, a camera that shakes and drifts, aliasing, flicker and a marker colour that shifts.

Every case renders a video file with known truth (speeds, the marker's share in view, the
camera's offset) and measures it back with the defaults, as a user would.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from vision_cases import rms

from mecanum_hil.cli import main
from mecanum_hil.errors import VideoError
from mecanum_hil.io.recording import read_recording
from mecanum_hil.vision import MeasureOptions, RenderSettings, measure_video, render_video
from mecanum_hil.vision.hub import camera_offsets
from mecanum_hil.vision.scenarios import scenario_recording
from mecanum_hil.vision.speed import estimate_speed, parse_speed_range

#: Every condition at once (the renderer's knobs).
ALL = {"noise_std": 3.0, "exposure": 0.5, "fender": 0.35, "shake_px": 1.5, "drift_px": 15.0,
       "flicker": 0.2, "hue_shift_deg": 40.0, "lighting_drift": 0.2, "tilt_deg": 25.0}


def score(res, meas) -> dict:
    """The acceptance figures for wheel 1 against the renderer's truth."""
    got = meas.recording.wheel_rpm[:, 0]
    truth = res.wheel_rpm[:, 0]
    vis = res.marker_visible[:, 0]
    t = res.frame_t_s
    changing = np.abs(np.gradient(truth, t)) > 1e-6
    last_change = np.maximum.accumulate(np.where(changing, t, -1e9))
    # Steady state: a constant, non-zero speed held for at least 0.3 s.
    steady = ~changing & (t - last_change >= 0.3) & (np.abs(truth) > 0)
    return {"found_visible": float(np.isfinite(got[vis >= 0.999]).mean()),
            "values_hidden": int(np.isfinite(got[vis <= 0.0]).sum()),
            "rmse": rms(got, truth), "rmse_steady": rms(got[steady], truth[steady])}


def assert_done(s: dict) -> None:
    assert s["found_visible"] >= 0.9, s
    assert s["values_hidden"] == 0, s
    assert s["rmse_steady"] <= 0.5, s
    assert s["rmse"] <= 2.0, s


@pytest.mark.slow
def test_slow_start_at_60_fps_is_measured_throughout(tmp_path):
    res = render_video(scenario_recording("slow-start"), tmp_path / "slow.mp4",
                       RenderSettings(640, 480, fps=60.0, noise_std=2.0, duration_s=8.0))
    meas = measure_video(res.path)
    w = meas.summary["wheels"][0]
    assert w["found_fraction"] >= 0.95 and w["path_coverage"] > 0.9
    s = score(res, meas)
    assert s["found_visible"] >= 0.95
    assert s["rmse"] <= 0.5 and s["rmse_steady"] <= 0.2
    assert w["gaps"] == [] and not w["aliasing"] and w["hub"] == "still"


@pytest.mark.slow
@pytest.mark.parametrize("knobs", [
    {"noise_std": 3.0, "fender": 0.35},
    {"noise_std": 3.0, "shake_px": 1.5, "drift_px": 15.0},
    {"noise_std": 3.0, "flicker": 0.2, "hue_shift_deg": 40.0, "lighting_drift": 0.2},
    {"noise_std": 4.0, "exposure": 0.6, "jpeg_quality": 50},
], ids=["fender", "shake-drift", "light", "blur-compression"])
def test_each_condition_alone(tmp_path, knobs):
    res = render_video(scenario_recording("slow-start"), tmp_path / "c.mp4",
                       RenderSettings(640, 480, fps=30.0, **knobs))
    meas = measure_video(res.path)
    assert_done(score(res, meas))
    w = meas.summary["wheels"][0]
    assert w["hub"] == ("tracked" if "shake_px" in knobs else "still")
    if "fender" in knobs:
        assert w["gaps"] and all(g["bridged"] for g in w["gaps"])


@pytest.mark.slow
@pytest.mark.parametrize(("fps", "suffix"), [(30.0, ".mp4"), (60.0, ".mp4"), (30.0, ".avi")])
def test_all_conditions_together(tmp_path, fps, suffix):
    res = render_video(scenario_recording("stop-restart"), tmp_path / f"all{suffix}",
                       RenderSettings(640, 480, fps=fps, **ALL))
    meas = measure_video(res.path)
    assert_done(score(res, meas))
    w = meas.summary["wheels"][0]
    assert w["hub"] == "tracked" and 15.0 < w["camera_motion_px"] < 35.0
    assert w["view_tilt_deg"] == pytest.approx(25.0, abs=3.0)
    # The wheel stops behind the fender and comes back out backwards: that gap cannot be
    # counted and is reported; so may be the first one (the wheel leaves rest behind the
    # fender: the acceleration is not seen on the near side); the others are bridged.
    unbridged = [g for g in w["gaps"] if not g["bridged"]]
    assert any(6.0 < g["start_s"] < 7.0 for g in unbridged)
    assert all(g["reason"] and (6.0 < g["start_s"] < 7.0 or g["start_s"] < 1.5)
               for g in unbridged)
    assert sum(g["bridged"] for g in w["gaps"]) >= 2


@pytest.mark.slow
def test_all_conditions_in_an_inter_frame_codec(tmp_path):
    """VP8 (.webm): the H.264-like codec this OpenCV build can write (no H.264 encoder)."""
    res = render_video(scenario_recording("slow-start"), tmp_path / "all.webm",
                       RenderSettings(640, 480, fps=30.0, duration_s=7.0, **ALL))
    assert_done(score(res, measure_video(res.path)))


def test_gaps_bridged_from_the_speed_either_side_and_long_ones_reported(tmp_path):
    rec = scenario_recording("slow-start")
    res = render_video(rec, tmp_path / "g.avi",
                       RenderSettings(320, 240, fps=30.0, noise_std=2.0, fender=0.35,
                                      occlusions_s=((7.0, 8.6),)))
    # The fender hides the marker for seconds while the wheel starts slowly, the card for
    # 1.6 s: 43 % found (below a --min-found of 50 %).
    meas = measure_video(res.path, MeasureOptions(min_found=0.3))
    w = meas.summary["wheels"][0]
    turns = meas.recording.extra_numeric("wheel1_turns")
    truth = res.angle_turns[:, 0]
    for g in w["gaps"]:
        i0 = int(np.argmin(np.abs(res.frame_t_s - g["start_s"]))) - 1
        i1 = int(np.argmin(np.abs(res.frame_t_s - g["end_s"]))) + 1
        if g["bridged"]:
            assert g["turns"] == pytest.approx(truth[i1] - truth[i0], abs=0.02)
            assert turns[i1] - turns[i0] == pytest.approx(truth[i1] - truth[i0], abs=0.02)
    card = [g for g in w["gaps"] if g["start_s"] <= 7.05 and g["end_s"] >= 8.5]
    assert len(card) == 1 and not card[0]["bridged"] and card[0]["turns"] is None
    assert card[0]["reason"]
    assert any("too long to count the turns" in x for x in meas.warnings)
    assert np.isnan(meas.recording.wheel_rpm[res.marker_visible[:, 0] == 0.0, 0]).all()


def test_aliasing_is_flagged_and_refused_unless_the_range_is_given(tmp_path):
    res = render_video(scenario_recording("through-limit"), tmp_path / "fast.avi",
                       RenderSettings(320, 240, fps=30.0, noise_std=2.0))
    meas = measure_video(res.path)
    w = meas.summary["wheels"][0]
    assert meas.summary["aliasing"] and w["aliasing"] and w["aliased_frames"] > 0
    assert any("aliasing at t=" in x and "--speed-range" in x for x in meas.warnings)
    got = meas.recording.wheel_rpm[:, 0]
    truth = res.wheel_rpm[:, 0]
    # Refused only where the wheel was fast (over a quarter turn a frame, 450 rpm at 30 fps);
    # what is written is right.
    assert truth[np.isnan(got)].min() > 440.0
    slow = truth < 400.0
    assert np.isfinite(got[slow]).all() and rms(got[slow], truth[slow]) < 2.0
    for rng in ((0.0, math.inf), (200.0, 1500.0)):
        told = measure_video(res.path, MeasureOptions(expected_rpm=rng))
        got = told.recording.wheel_rpm[:, 0]
        assert not told.summary["aliasing"] and np.isfinite(got).all()
        settled = (res.frame_t_s < 1.9) | (res.frame_t_s > 4.3)
        assert rms(got[settled], truth[settled]) < 0.5
        assert np.nanmax(got) > 1000.0


def test_speed_range_parsing():
    assert parse_speed_range("0,") == (0.0, math.inf)
    assert parse_speed_range(",0") == (-math.inf, 0.0)
    assert parse_speed_range("-1500,-200") == (-1500.0, -200.0)
    for bad in ("", ",", "5", "3,1", "a,b"):
        with pytest.raises(VideoError, match="--speed-range"):
            parse_speed_range(bad)


def test_bridging_is_exact_for_constant_acceleration_and_refuses_ambiguity():
    fps = 30.0
    t = np.arange(240) / fps
    turns = 0.05 * t + 0.1 * t ** 2  # 3 rpm + 12 rpm/s
    angle = 2 * np.pi * turns
    hidden = (t > 2.0) & (t < 3.1)
    a = np.where(hidden, np.nan, angle)
    est = estimate_speed(t, np.angle(np.exp(1j * a)), 0.1)
    assert len(est.gaps) == 1 and est.gaps[0].bridged
    ok = np.isfinite(est.turns)
    np.testing.assert_allclose(est.turns[ok] - est.turns[0], turns[ok] - turns[0], atol=1e-6)
    assert np.isnan(est.rpm[hidden]).all() and np.isnan(est.turns[hidden]).all()
    # Stopping behind the cover and coming back out backwards: both sides' speeds say "go on",
    # only the whole-turn count tells otherwise: not bridged.
    back = np.where(t < 3.0, 0.5 * t, 1.5 - 0.5 * (t - 3.0))
    a = np.where((t > 2.5) & (t < 3.5), np.nan, 2 * np.pi * back)
    est = estimate_speed(t, np.angle(np.exp(1j * a)), 0.1)
    assert len(est.gaps) == 1 and not est.gaps[0].bridged
    # Hidden for more than a turn at steady speed: a whole turn could hide in it.
    a = np.where((t > 2.0) & (t < 5.0), np.nan, 2 * np.pi * 0.5 * t)
    est = estimate_speed(t, np.angle(np.exp(1j * a)), 0.1)
    assert not est.gaps[0].bridged and "whole turn" in est.gaps[0].reason


def test_still_camera_offsets_are_zero_and_moving_ones_follow_the_truth(tmp_path):
    hub = np.column_stack([100 + 0.02 * np.sin(np.arange(50)), np.full(50, 80.0),
                           np.full(50, 5000.0)])
    off, ok = camera_offsets(hub)
    assert ok.all() and not off.any()
    # A frame whose dark area jumps (a card) is interpolated, not trusted.
    hub = np.column_stack([100 + np.arange(50.0), np.full(50, 80.0), np.full(50, 5000.0)])
    hub[20] = (300.0, 10.0, 2000.0)
    off, ok = camera_offsets(hub)
    assert not ok[20] and off[20, 0] == pytest.approx(20.0) and off[20, 1] == 0.0


def test_cli_renders_a_scenario_with_conditions_and_measures_it(tmp_path, capsys):
    video, truth, out = tmp_path / "v.mp4", tmp_path / "truth.csv", tmp_path / "m.csv"
    code = main(["render-video", "--recording", "scenario:slow-start", "--out", str(video),
                 "--fender", "0.3", "--shake", "1", "--drift", "6", "--flicker", "0.2",
                 "--hue-shift", "30", "--hide", "7-7.5", "--truth", str(truth), "--json"])
    assert code == 0
    roi = json.loads(capsys.readouterr().out)["rois"]["1"]
    code = main(["measure-video", str(video), "--out", str(out), "--roi",
                 "1:" + ",".join(map(str, roi)), "--json", "--speed-range=0,"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    w = summary["wheels"][0]
    for key in ("gaps", "gaps_unbridged", "aliasing", "aliased_frames", "hub",
                "camera_motion_px", "partial_dropped"):
        assert key in w
    assert summary["expected_rpm"] == [0.0, None]
    assert w["hub"] == "tracked" and not summary["aliasing"]
    got, tru = read_recording(out), read_recording(truth)
    vis = tru.extra_numeric("wheel1_marker_visible")
    assert np.isnan(got.wheel_rpm[vis == 0.0, 0]).all()
    assert np.isfinite(got.wheel_rpm[vis >= 0.999, 0]).mean() >= 0.9
    assert rms(got.wheel_rpm[:, 0], tru.wheel_rpm[:, 0]) < 1.0
    assert np.isfinite(tru.extra_numeric("camera_dx_px")).all()


@pytest.mark.parametrize("args", [["--speed-range", "5,1"], ["--speed-range", "x"]])
def test_cli_bad_speed_range_is_one_line(tmp_path, capsys, args):
    video = tmp_path / "v.avi"
    render_video(scenario_recording("reverse"), video, RenderSettings(duration_s=1.0))
    code = main(["measure-video", str(video), "--out", str(tmp_path / "m.csv"), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and err[0].startswith("error: ")


def test_cli_bad_hide_and_scenario(tmp_path, capsys):
    for args in (["--hide", "3-1"], ["--recording", "scenario:nope"]):
        base = ["render-video", "--recording", "scenario:reverse", "--out",
                str(tmp_path / "v.avi")]
        if args[0] == "--recording":
            base = base[:1] + args + base[3:]
        else:
            base += args
        code = main(base)
        err = capsys.readouterr().err.strip().splitlines()
        assert code != 0 and len(err) == 1 and err[0].startswith("error: "), err


def test_hub_tracking_is_what_keeps_a_shaking_camera_accurate(tmp_path):
    res = render_video(scenario_recording("reverse"), tmp_path / "shake.avi",
                       RenderSettings(320, 240, noise_std=2.0, shake_px=1.0, drift_px=8.0))
    tracked = measure_video(res.path)
    fixed = measure_video(res.path, MeasureOptions(track_hub=False))
    assert tracked.summary["wheels"][0]["hub"] == "tracked"
    assert fixed.summary["wheels"][0]["hub"] == "not tracked"
    err_tracked = rms(tracked.recording.wheel_rpm[:, 0], res.wheel_rpm[:, 0])
    err_fixed = rms(fixed.recording.wheel_rpm[:, 0], res.wheel_rpm[:, 0])
    # (Tracked below half an rpm, and fixed coordinates at least twice as far off.)
    assert err_tracked < 0.5
    assert 2 * err_tracked < err_fixed


def test_render_truth_never_overwrites_the_recording_or_the_video(tmp_path, capsys):
    from mecanum_hil.io.recording import write_recording

    rec_path, video = tmp_path / "rec.csv", tmp_path / "v.avi"
    write_recording(scenario_recording("reverse"), rec_path)
    before = rec_path.read_bytes()
    for truth in (rec_path, video):
        code = main(["render-video", "--recording", str(rec_path), "--out", str(video),
                     "--duration", "0.5", "--truth", str(truth)])
        err = capsys.readouterr().err.strip().splitlines()
        assert code != 0 and len(err) == 1 and "would overwrite" in err[0], err
    assert rec_path.read_bytes() == before and not video.exists()


@pytest.mark.parametrize("expected", [None, (0.0, math.inf), (-100.0, 1500.0)])
def test_a_reflection_never_becomes_a_whole_turn_with_a_speed_range(expected):
    """One frame where a reflection is taken for the marker: dropped, also when the expected
    range would otherwise resolve its jump back into a whole turn forwards."""
    t = np.arange(120) / 30.0
    angle = 2 * np.pi * t  # 60 rpm
    angle[60] += 2 * np.pi * 0.3
    est = estimate_speed(t, np.angle(np.exp(1j * angle)), 0.1, expected_rpm=expected)
    assert est.outliers == 1 and np.isnan(est.rpm[60])
    np.testing.assert_allclose(np.delete(est.rpm, 60), 60.0, atol=1e-6)
    assert est.turns[-1] - est.turns[0] == pytest.approx(t[-1] - t[0])


def test_a_wheel_beyond_the_limit_from_the_start_is_warned_about(tmp_path):
    """1116 rpm at 30 fps (0.62 turn a frame) never crosses the limit: the images are those of
    684 rpm backwards. That reading cannot be refused, but it must not come silently."""
    from vision_cases import steady

    res = render_video(steady(1116.0, 1.0), tmp_path / "fast.avi", RenderSettings(noise_std=2.0))
    meas = measure_video(res.path)
    assert np.nanmedian(meas.recording.wheel_rpm[:, 0]) == pytest.approx(-684.0, abs=2.0)
    assert any("-684 rpm" in w and "1116 rpm" in w and "--speed-range" in w
               for w in meas.warnings), meas.warnings
    told = measure_video(res.path, MeasureOptions(expected_rpm=(0.0, math.inf)))
    assert np.nanmedian(told.recording.wheel_rpm[:, 0]) == pytest.approx(1116.0, abs=2.0)
    assert told.warnings == ()
    # Below a quarter turn a frame (420 rpm here) nothing is said.
    slow = render_video(steady(420.0, 1.0), tmp_path / "slow.avi", RenderSettings(noise_std=2.0))
    assert measure_video(slow.path).warnings == ()
