"""Accuracy on rendered videos with known truth: steady speeds, the paper's profiles, realism."""

from __future__ import annotations

import numpy as np
import pytest
from vision_cases import rms, steady

from mecanum_hil.vision import (
    MarkerSpec,
    MeasureOptions,
    RenderSettings,
    measure_video,
    render_video,
)
from mecanum_hil.vision.loop import render_and_measure


@pytest.mark.parametrize(("rpm", "fps"), [(10, 30), (60, 30), (130, 30), (10, 60), (130, 60)])
def test_steady_speed_rms_below_half_rpm(tmp_path, rpm, fps):
    res = render_video(steady(rpm), tmp_path / "v.mp4", RenderSettings(fps=fps, noise_std=2.0))
    meas = measure_video(res.path)
    got = meas.recording.wheel_rpm[:, 0]
    assert np.isfinite(got).all()
    assert meas.summary["wheels"][0]["found_fraction"] == 1.0
    assert rms(got, res.wheel_rpm[:, 0]) < 0.5
    assert abs(np.mean(got) - rpm) < 0.1
    assert meas.recording.t_s[1] == pytest.approx(1.0 / fps, abs=1e-6)


@pytest.mark.parametrize("knobs", [
    {"noise_std": 6.0, "exposure": 0.8},
    {"tilt_deg": 50.0, "tilt_axis_deg": 30.0},
    {"distractors": 4, "lighting_drift": 0.25},
    {"jpeg_quality": 35, "noise_std": 3.0},
    {"noise_std": 4.0, "exposure": 0.5, "tilt_deg": 35.0, "distractors": 3, "jpeg_quality": 60,
     "lighting_drift": 0.15},
], ids=["noise-blur", "oblique", "distractors-lighting", "compression", "all"])
def test_realism_knobs_keep_steady_rms_below_half_rpm(tmp_path, knobs):
    res = render_video(steady(90.0), tmp_path / "v.avi", RenderSettings(**knobs))
    meas = measure_video(res.path)
    assert rms(meas.recording.wheel_rpm[:, 0], res.wheel_rpm[:, 0]) < 0.5
    w = meas.summary["wheels"][0]
    if "tilt_deg" in knobs:
        assert w["path"] == "ellipse"
        assert w["view_tilt_deg"] == pytest.approx(knobs["tilt_deg"], abs=2.0)


def _onset(t, v, threshold):
    return float(t[np.argmax(v > threshold)])


@pytest.mark.parametrize("fps", [30, 60])
def test_paper_step_onset_within_one_frame(tmp_path, paper, fps):
    rec = paper("paper-step-60")
    res = render_video(rec, tmp_path / "step.mp4",
                       RenderSettings(fps=fps, noise_std=3.0, duration_s=3.0))
    got = measure_video(res.path).recording.wheel_rpm[:, 0]
    truth = res.wheel_rpm[:, 0]
    for level in (6.0, 30.0, 54.0):  # 10 %, 50 %, 90 % of the step
        assert abs(_onset(res.frame_t_s, got, level) - _onset(res.frame_t_s, truth, level)) \
            <= 1.0 / fps + 1e-9
    settled = res.frame_t_s > 1.2
    assert rms(got[settled], truth[settled]) < 0.5


def test_paper_ramp_tracks_truth(tmp_path, paper):
    res = render_video(paper("paper-ramp"), tmp_path / "ramp.mp4",
                       RenderSettings(width_px=240, height_px=180, duration_s=12.0,
                                      noise_std=2.0))
    got = measure_video(res.path).recording.wheel_rpm[:, 0]
    assert res.wheel_rpm[-1, 0] > 50.0
    assert rms(got, res.wheel_rpm[:, 0]) < 0.5


def test_paper_turn_two_wheels_aligned_with_recording(tmp_path, paper, model):
    rec = paper("paper-turn")
    loop = render_and_measure(rec, tmp_path / "turn.mp4",
                              RenderSettings(width_px=400, wheels=(1, 2), camera_start_s=0.37,
                                             noise_std=2.0), calibration=model[0],
                              robot=model[1])
    meas = loop.measurement
    assert meas.summary["alignment"]["method"] == "cross-correlation"
    assert meas.summary["offset_s"] == pytest.approx(0.37, abs=0.01)
    w = meas.recording.wheel_rpm
    turning = (loop.render.recording_t_s > 1.5) & (loop.render.recording_t_s < 3.4)
    assert np.nanmean(w[turning, 0]) < -40 and np.nanmean(w[turning, 1]) > 40  # FL back, FR fwd
    for k, wheel in enumerate((1, 2)):
        assert rms(w[turning, wheel - 1], loop.render.wheel_rpm[turning, k]) < 0.5
    # The prediction already fills the wheel columns: the video goes into extra columns.
    merged = loop.merged
    video = merged.extra_numeric("wheel2_video_rpm")
    inside = np.isfinite(video)
    assert inside.sum() > 0.8 * len(merged)
    steady_turn = (merged.t_s > 1.5) & (merged.t_s < 3.4)
    assert np.nanmax(np.abs(video - merged.wheel_rpm[:, 1])[steady_turn]) < 1.5


def test_mirror_gives_negative_speed_and_invert_restores_it(tmp_path):
    res = render_video(steady(45.0), tmp_path / "m.mp4", RenderSettings(mirror=True))
    assert np.nanmean(measure_video(res.path).recording.wheel_rpm[:, 0]) == pytest.approx(
        -45.0, abs=0.2)
    inv = measure_video(res.path, MeasureOptions(invert=True)).recording.wheel_rpm[:, 0]
    assert np.nanmean(inv) == pytest.approx(45.0, abs=0.2)


def test_occlusion_leaves_gaps_empty(tmp_path):
    res = render_video(steady(60.0, 3.0), tmp_path / "o.mp4",
                       RenderSettings(occlusions_s=((1.0, 1.5),)))
    rec = measure_video(res.path).recording
    hidden = (res.frame_t_s >= 1.0) & (res.frame_t_s < 1.5 - 1e-9)
    assert np.isnan(rec.wheel_rpm[hidden, 0]).all()
    assert np.isnan(rec.extra_numeric("wheel1_turns")[hidden]).all()
    seen = np.isfinite(rec.wheel_rpm[:, 0])
    assert seen.sum() >= (~hidden).sum() - 2
    assert rms(rec.wheel_rpm[seen, 0], res.wheel_rpm[seen, 0]) < 0.5


def test_pinned_hsv_marker_among_same_hue_distractors(tmp_path):
    from mecanum_hil.vision import parse_hsv

    res = render_video(steady(70.0), tmp_path / "h.mp4",
                       RenderSettings(distractors=4, marker_hues_deg=(0.0,), seed=3))
    meas = measure_video(res.path, MeasureOptions(marker=parse_hsv("170,120,80:10,255,255")))
    assert rms(meas.recording.wheel_rpm[:, 0], res.wheel_rpm[:, 0]) < 0.5


@pytest.mark.parametrize("fps", [30, 60])
def test_aruco_orientation_oblique_noisy(tmp_path, fps):
    res = render_video(steady(75.0, 1.0), tmp_path / "a.avi",
                       RenderSettings(fps=fps, marker="aruco", tilt_deg=30.0, tilt_axis_deg=20.0,
                                      noise_std=3.0, exposure=0.3))
    meas = measure_video(res.path, MeasureOptions(marker=MarkerSpec("aruco")))
    w = meas.summary["wheels"][0]
    assert w["found_fraction"] == 1.0 and w["path"] == "aruco"
    assert w["view_tilt_deg"] == pytest.approx(30.0, abs=2.0)
    # Corner positions jitter more than a dot's centroid: 0.3 rpm RMS at 30 fps, 0.7 at 60 fps.
    assert rms(meas.recording.wheel_rpm[:, 0], res.wheel_rpm[:, 0]) < (0.5 if fps == 30 else 1.0)


def test_short_arc_is_warned_about_and_an_oblique_one_still_fits_an_ellipse(tmp_path):
    res = render_video(steady(10.0, 2.0), tmp_path / "slow.avi",
                       RenderSettings(tilt_deg=40.0, tilt_axis_deg=30.0, noise_std=2.0))
    meas = measure_video(res.path)  # a third of a turn
    assert meas.summary["wheels"][0]["path"] == "ellipse"
    assert rms(meas.recording.wheel_rpm[:, 0], res.wheel_rpm[:, 0]) < 0.5
    assert any("too little to tell its path's shape" in w for w in meas.warnings)
    full = measure_video(render_video(steady(30.0, 2.0), tmp_path / "turn.avi").path)
    assert full.warnings == ()
