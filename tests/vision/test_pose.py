"""measure-pose against the overhead renderer's truth: accuracy, gaps, the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.io.pose_track import fill_pose, motion_onset, resample_pose
from mecanum_hil.io.recording import empty_like_times, read_recording, write_recording
from mecanum_hil.model import load_calibration, load_robot_profile
from mecanum_hil.prediction import predict
from mecanum_hil.vision.overhead import OverheadSettings, render_overhead
from mecanum_hil.vision.pose import measure_pose, measure_pose_plain, pose_errors

pytest.importorskip("cv2")


def drive(duration_s: float = 3.0, rest_s: float = 0.4) -> object:
    """The model driving diagonally while turning (translation and rotation at once), from rest."""
    t = np.arange(0.0, duration_s + 1e-9, 0.01)
    cmd = np.zeros((t.size, 3))
    cmd[:, 2] = 60.0
    moving = (t >= rest_s) & (t < duration_s - 0.5)
    cmd[moving, 0] = 60.0
    cmd[moving, 1] = 25.0
    return predict(empty_like_times(t).with_values(commands=cmd), load_calibration(),
                   load_robot_profile())


@pytest.fixture(scope="module")
def rec():
    return drive()


def _render(rec, tmp_path_factory, **kw):
    path = tmp_path_factory.mktemp("overhead") / "v.mp4"
    return render_overhead(rec, path, OverheadSettings(tilt_deg=30.0, noise_std=2.0, **kw))


@pytest.fixture(scope="module")
def hd(rec, tmp_path_factory):
    return _render(rec, tmp_path_factory, width_px=1280, height_px=720)


@pytest.fixture(scope="module")
def vga(rec, tmp_path_factory):
    return _render(rec, tmp_path_factory, width_px=640, height_px=480,
                   occlusions_s=((1.2, 1.45),))


def _check(res, pos_m, head_deg):
    m = measure_pose(res.path, res.camera, res.scene)
    vis = res.marker_visible
    found = m.found
    # found in >= 95 % of the frames where the marker is visible, never where it is hidden
    assert found[vis].mean() >= 0.95
    assert not found[~vis].any()
    ours = pose_errors(m.t_s[vis], m.pose[vis], res.pose[vis])
    t, plain = measure_pose_plain(res.path, res.camera, res.scene)
    base = pose_errors(t[vis], plain[vis], res.pose[vis])
    assert ours["position_rmse_m"] <= pos_m
    assert ours["heading_rmse_deg"] <= head_deg
    # the static camera, the plane and time beat the per-frame pipeline
    assert ours["position_rmse_m"] < base["position_rmse_m"]
    assert ours["heading_rmse_deg"] < base["heading_rmse_deg"]
    # the camera's pose is found from the floor markers
    assert np.linalg.norm(m.camera_pose.position_m - res.camera_pose.position_m) < 0.01
    return m, ours, base


@pytest.mark.slow
def test_accuracy_1280x720(hd):
    assert hd.marker_visible.all()
    _, ours, _ = _check(hd, 0.005, 0.3)
    assert ours["found_share"] == 1.0


def test_accuracy_640x480_with_the_marker_hidden(vga):
    assert 0 < (~vga.marker_visible).sum() < 12
    m, _, _ = _check(vga, 0.008, 0.8)
    assert m.summary["camera_reprojection_rms_px"] < 0.5


def test_accuracy_640x480_with_a_calibrated_camera(vga, tmp_path, capsys):
    """The whole chain without the renderer's intrinsics: calibrate-camera on ChArUco views
    through the same lens, then measure-pose with that camera.toml (only the video, the
    calibration and the scene's measured marker places go in)."""
    from test_pose_calibrate import BOARD, GRID, views, write

    from mecanum_hil.vision.camera import load_camera

    folder = write(views(GRID, camera=vga.camera), tmp_path / "views")
    camera = tmp_path / "camera.toml"
    assert main(["calibrate-camera", str(folder), "--board", BOARD, "--out", str(camera)]) == 0
    capsys.readouterr()
    cam = load_camera(camera)
    assert cam != vga.camera  # a calibration, not the renderer's own numbers
    m = measure_pose(vga.path, cam, vga.scene)
    vis = vga.marker_visible
    err = pose_errors(m.t_s[vis], m.pose[vis], vga.pose[vis])
    assert err["position_rmse_m"] <= 0.008 and err["heading_rmse_deg"] <= 0.8
    assert m.found[vis].mean() >= 0.95


def test_resample_never_across_a_gap_nor_outside():
    t = np.arange(10) * 0.1
    pose = np.column_stack([t, 2 * t, 170.0 + 10 * np.arange(10)])
    pose[4] = np.nan
    q = np.array([-0.05, 0.0, 0.05, 0.35, 0.45, 0.55, 0.85, 0.9, 0.95])
    out = resample_pose(t, pose, q)
    assert np.isnan(out[0]).all() and np.isnan(out[-1]).all()  # outside: never extrapolated
    assert np.isnan(out[3]).all() and np.isnan(out[4]).all()  # next to the missing sample
    np.testing.assert_allclose(out[[1, 2, 5, 6, 7], 0], [0.0, 0.05, 0.55, 0.85, 0.9])
    np.testing.assert_allclose(out[6, 2], 175.0 + 10 * 8)  # heading continuous past 180
    # a real gap in time (no sample missing, but far apart) is not bridged either
    t2 = np.array([0.0, 0.1, 0.2, 0.9, 1.0])
    out2 = resample_pose(t2, np.column_stack([t2, t2, t2]), np.array([0.5, 0.95]))
    assert np.isnan(out2[0]).all() and out2[1, 0] == pytest.approx(0.95)


def test_fill_pose_refuses_to_fill_no_row():
    """One check for every track (camera, motion capture): placed where it misses the
    recording, or overlapping it only where the robot was not measured, it fills no pose row:
    an error naming the track, the recording and the option that placed it, not empty columns."""
    from mecanum_hil.errors import RecordingError
    from mecanum_hil.io.recording import empty_like_times

    rec = empty_like_times(np.arange(0.0, 3.0, 0.01))
    t = np.arange(0.0, 1.0, 0.1)
    pose = np.column_stack([t, t, t])
    names = dict(track="cap.csv: the capture", recording="rec.csv", offset_option="--start-s")
    with pytest.raises(RecordingError, match=r"cap\.csv: the capture \(recording time 50\.000 to "
                       r"50\.900 s .*--start-s\) does not overlap the recording rec\.csv"):
        fill_pose(rec, t, pose, 50.0, **names)
    hidden = pose.copy()
    hidden[:5] = np.nan  # seen only after the recording's end
    with pytest.raises(RecordingError, match=r"the capture measured the robot at no time of a "
                       r"row of rec\.csv \(5 of 10 samples measured"):
        fill_pose(rec, t, hidden, 2.5, **names)
    filled = fill_pose(rec, t, pose, 0.5, **names)
    assert 90 <= np.isfinite(filled.pose).all(axis=1).sum() <= 91  # 0.5 .. 1.4 s


def test_motion_onset():
    t = np.arange(100) * 0.01
    x = np.where(t > 0.5, 0.5 * (t - 0.5) ** 2 * 8.0, 0.0)
    pose = np.column_stack([x, np.zeros(100), np.full(100, 90.0)])
    onset = motion_onset(t, pose, 0.01)
    assert onset == pytest.approx(0.5 + math.sqrt(0.01 / 4.0), abs=0.005)
    assert motion_onset(t, pose[60:]) is None  # moving from the start: no onset


def test_cli_chain_with_recording(vga, rec, tmp_path, capsys):
    d = vga.path.parent
    camera, scene = d / "v.camera.toml", d / "v.scene.toml"
    from mecanum_hil.vision.camera import save_camera
    from mecanum_hil.vision.scene import save_scene

    save_camera(vga.camera, camera)
    save_scene(vga.scene, scene)
    out = tmp_path / "pose.csv"
    assert main(["measure-pose", str(vga.path), "--camera", str(camera), "--scene", str(scene),
                 "--out", str(out), "--video-start-s", "0.25", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    for key in ("frames", "found_share", "camera_reprojection_rms_px", "camera_pose"):
        assert key in summary
    assert summary["frames"] == vga.frame_t_s.size
    lines = out.read_text().splitlines()
    assert lines[0] == "t_s,x_m,y_m,phi_deg"
    assert float(lines[1].split(",")[0]) == pytest.approx(0.25)
    assert any(line.endswith(",,,") for line in lines[1:])  # the hidden frames stay empty
    assert json.loads(out.with_suffix(".json").read_text())["found_share"] < 1.0

    # the recording's pose columns filled, the video's start found from the motion onset
    src = tmp_path / "rec.csv"
    write_recording(rec.with_values(pose=np.full_like(rec.pose, np.nan)), src)
    filled = tmp_path / "filled.csv"
    assert main(["measure-pose", str(vga.path), "--camera", str(camera), "--scene", str(scene),
                 "--recording", str(src), "--out", str(filled), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["video_start_s"] == pytest.approx(0.0, abs=1 / 30)
    got = read_recording(filled)
    assert got.metadata["video_start_method"].startswith("auto")
    ok = np.isfinite(got.pose).all(axis=1)
    err = np.hypot(*(got.pose[ok, :2] - rec.pose[ok, :2]).T)
    assert np.sqrt(np.mean(err ** 2)) < 0.01
    # rows inside the hidden interval have no pose, rows after the video's end neither
    hidden = (got.t_s > 1.25) & (got.t_s < 1.4)
    assert not ok[hidden].any()


def test_cli_bad_input(vga, tmp_path, capsys):
    d = vga.path.parent
    scene = tmp_path / "scene.toml"
    scene.write_text("[markers]\ndictionary = 'DICT_4X4_50'\n[robot]\nmarker_id = 0\n"
                     "size_m = 0.2\nheight_m = 0.23\n")
    camera = tmp_path / "camera.toml"
    camera.write_text("[camera]\nwidth_px = 1280\nheight_px = 720\nfx_px = 900.0\n"
                      "fy_px = 900.0\ncx_px = 640.0\ncy_px = 360.0\n"
                      "distortion = [0.0, 0.0, 0.0, 0.0, 0.0]\n")
    args = ["measure-pose", str(vga.path), "--out", str(tmp_path / "p.csv")]
    assert main([*args, "--camera", str(camera), "--scene", str(scene)]) == 1
    assert "at least one [[floor]]" in capsys.readouterr().err
    from mecanum_hil.vision.scene import save_scene

    save_scene(vga.scene, scene)
    assert main([*args, "--camera", str(camera), "--scene", str(scene)]) == 1
    err = capsys.readouterr().err
    assert err.strip().startswith("error:") and "640x480" in err
    assert len(err.strip().splitlines()) == 1
    assert main([*args, "--camera", str(camera), "--scene", str(scene),
                        "--video-start-s", "auto"]) == 1
    assert "needs --recording" in capsys.readouterr().err
    assert main(["measure-pose", str(d / "missing.mp4"), "--camera", str(camera), "--scene",
                 str(scene), "--out", str(tmp_path / "p.csv")]) == 1
    assert "file not found" in capsys.readouterr().err


def test_render_video_overhead_writes_the_truth_beside(tmp_path, capsys):
    rec = drive(duration_s=1.6, rest_s=0.3)
    src = tmp_path / "rec.csv"
    write_recording(rec, src)
    video = tmp_path / "top.avi"
    assert main(["render-video", "--overhead", "--recording", str(src), "--out", str(video),
                 "--size", "480x360", "--tilt", "20", "--distortion", "-0.15,0.03,0,0,0",
                 "--jpeg", "80", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 49 and summary["marker_visible_share"] == 1.0
    truth = read_recording(tmp_path / "top.truth.csv")
    np.testing.assert_allclose(truth.pose[-1], rec.pose[-1], atol=1e-6)
    assert truth.metadata["camera_pose"]["tilt_deg"] == pytest.approx(20.0, abs=0.01)
    from mecanum_hil.vision.camera import load_camera
    from mecanum_hil.vision.scene import load_scene

    cam, scn = load_camera(tmp_path / "top.camera.toml"), load_scene(tmp_path / "top.scene.toml")
    assert cam.distortion == (-0.15, 0.03, 0.0, 0.0, 0.0) and len(scn.floor) == 8
    m = measure_pose(video, cam, scn)
    err = pose_errors(m.t_s, m.pose, truth.pose)
    assert err["found_share"] == 1.0 and err["position_rmse_m"] < 0.008
    # the wheel renderer's knobs are refused with --overhead, not silently ignored
    assert main(["render-video", "--overhead", "--recording", str(src), "--out", str(video),
                 "--blur", "0.5", "--mirror"]) == 1
    assert "--blur, --mirror: not used with --overhead" in capsys.readouterr().err
    # a corrupt video is one line, not a traceback
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\x00" * 1000)
    assert main(["measure-pose", str(bad), "--camera", str(tmp_path / "top.camera.toml"),
                 "--scene", str(tmp_path / "top.scene.toml"), "--out",
                 str(tmp_path / "p.csv")]) == 1
    assert "not a video OpenCV can decode" in capsys.readouterr().err
