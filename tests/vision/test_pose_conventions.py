"""measure-pose's pinned conventions checked against a picture made without the renderer.

A camera 2 m straight above the world origin, no lens distortion, image x along world X and
image up along world Y: a point ``(X, Y, z)`` is at pixel ``(319.5 + 500 X / (2 - z),
239.5 - 500 Y / (2 - z))``. Printed markers are pasted into the picture upright or turned by
quarter turns (``cv2.rotate``), so where each corner is, and hence every expected pose, is
worked out by hand here, independently of ``vision/scene.py`` and ``vision/overhead.py``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.io.recording import empty_like_times, read_recording, write_recording

cv2 = pytest.importorskip("cv2")

SIDE_PX = 60  # every marker is 60 px wide in the picture (10 px a cell, 4x4 + border)
CAMERA_TOML = """[camera]
width_px = 640
height_px = 480
fx_px = 500.0
fy_px = 500.0
cx_px = 319.5
cy_px = 239.5
distortion = [0.0, 0.0, 0.0, 0.0, 0.0]
"""
# Floor markers (z = 0: 4 mm a pixel, 0.24 m wide): top-left pixel, quarter turn, yaw [deg].
# Turned counter-clockwise by 90 deg, a marker's top edge (its x axis, top-left -> top-right)
# runs up the picture, along world +Y: yaw 90.
FLOOR = {1: ((40, 40), None, 0.0), 2: ((540, 40), cv2.ROTATE_90_COUNTERCLOCKWISE, 90.0),
         3: ((540, 380), cv2.ROTATE_180, 180.0), 4: ((40, 380), cv2.ROTATE_90_CLOCKWISE, -90.0)}
# The robot's marker: plane 0.25 m up (3.5 mm a pixel, 0.21 m wide), its centre at pixel
# (419.5, 179.5), i.e. world (0.35, 0.21); stuck with its top edge towards the robot's front
# (yaw_deg = -90), 0.15 m forward and 0.05 m left of the robot's centre.
ROBOT_AT = (390, 150)
SCENE_TOML = """[markers]
dictionary = "DICT_4X4_50"
""" + "".join(f"""
[[floor]]
id = {i}
x_m = {(u - 290) / 250}
y_m = {-(v - 210) / 250}
size_m = 0.24
yaw_deg = {yaw}
""" for i, ((u, v), _, yaw) in FLOOR.items()) + """
[robot]
marker_id = 0
size_m = 0.21
height_m = 0.25
forward_m = 0.15
left_m = 0.05
yaw_deg = -90.0
"""
# Robot heading -> how the printed marker is turned in the picture (its top towards the front):
# facing +X (right in the picture) the top points right, a quarter turn clockwise.
TURN = {0: cv2.ROTATE_90_CLOCKWISE, 90: None, 180: cv2.ROTATE_90_COUNTERCLOCKWISE,
        270: cv2.ROTATE_180}
# Robot centre = marker centre (0.35, 0.21) - R(phi) (0.15, 0.05), worked out per heading.
EXPECTED_XY = {0: (0.20, 0.16), 90: (0.40, 0.06), 180: (0.50, 0.26), 270: (0.30, 0.36)}
HEADINGS = [0, 0, 90, 90, None, 180, 180, 270, 270, 360, 360]  # None: the marker is hidden


def paste(frame, marker_id, top_left, turn):
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    img = cv2.aruco.generateImageMarker(dictionary, marker_id, SIDE_PX)
    if turn is not None:
        img = cv2.rotate(img, turn)
    u, v = top_left
    frame[v - 15:v + SIDE_PX + 15, u - 15:u + SIDE_PX + 15] = 255  # white paper
    frame[v:v + SIDE_PX, u:u + SIDE_PX] = img


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from mecanum_hil.vision.video import VideoWriter

    d = tmp_path_factory.mktemp("conventions")
    (d / "camera.toml").write_text(CAMERA_TOML)
    (d / "scene.toml").write_text(SCENE_TOML)
    with VideoWriter(d / "top.avi", 10.0, (640, 480)) as w:
        for phi in HEADINGS:
            frame = np.full((480, 640), 128, np.uint8)
            for i, (at, turn, _) in FLOOR.items():
                paste(frame, i, at, turn)
            if phi is not None:
                paste(frame, 0, ROBOT_AT, TURN[phi % 360])
            w.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    return d


def test_pose_csv_matches_the_hand_computed_poses(files, tmp_path, capsys):
    out = tmp_path / "pose.csv"
    assert main(["measure-pose", str(files / "top.avi"), "--camera", str(files / "camera.toml"),
                 "--scene", str(files / "scene.toml"), "--out", str(out), "--window", "0",
                 "--video-start-s", "1.5", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == len(HEADINGS) and summary["found"] == len(HEADINGS) - 1
    assert summary["found_share"] == pytest.approx(10 / 11, abs=1e-3)
    assert summary["camera_reprojection_rms_px"] < 0.3  # floor yaws as pinned: consistent
    # within 1 mm: with the AprilTag corners half a pixel off (as they come from OpenCV) the
    # camera came out 2.8 mm off (0.5 px at 4 mm a pixel)
    np.testing.assert_allclose(summary["camera_pose"]["position_m"], [0, 0, 2], atol=0.001)
    assert summary["camera_pose"]["tilt_deg"] == pytest.approx(0.0, abs=0.2)
    assert summary["video_start_s"] == 1.5 and summary["video_start_method"] == "given"
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["video_start_s"] == 1.5 and sidecar["video_start_method"] == "given"

    lines = out.read_text().splitlines()
    assert lines[0] == "t_s,x_m,y_m,phi_deg"
    rows = [line.split(",") for line in lines[1:]]
    assert len(rows) == len(HEADINGS)
    for k, (row, phi) in enumerate(zip(rows, HEADINGS, strict=True)):
        assert float(row[0]) == pytest.approx(1.5 + 0.1 * k, abs=1e-6)
        if phi is None:
            assert row[1:] == ["", "", ""]  # not seen: empty cells
            continue
        x, y, heading = (float(v) for v in row[1:])
        assert (x, y) == pytest.approx(EXPECTED_XY[phi % 360], abs=0.003), (k, phi)
        assert heading == pytest.approx(phi, abs=0.5), (k, phi)  # continuous: 270, then 360


def test_recording_filled_on_its_times_never_across_the_hidden_frame(files, tmp_path, capsys):
    t = np.round(np.arange(0.0, 3.0 + 1e-9, 0.01), 6)
    src = tmp_path / "rec.csv"
    write_recording(empty_like_times(t), src)
    out = tmp_path / "filled.csv"
    assert main(["measure-pose", str(files / "top.avi"), "--camera", str(files / "camera.toml"),
                 "--scene", str(files / "scene.toml"), "--recording", str(src), "--out", str(out),
                 "--window", "0", "--video-start-s", "1.5"]) == 0
    assert "video start 1.500 s (given)" in capsys.readouterr().out
    got = read_recording(out)
    assert got.metadata["video_start_s"] == 1.5 and got.metadata["video_start_method"] == "given"
    have = np.isfinite(got.pose).all(axis=1)
    # frames at 1.5 + 0.1 k; frame 4 (t 1.9) has no pose: nothing from 1.8 to 2.0 exclusive,
    # nothing before the first frame or after the last
    assert not have[(t < 1.5 - 1e-9) | (t > 2.5 + 1e-9)].any()
    assert not have[(t > 1.8 + 1e-9) & (t < 2.0 - 1e-9)].any()
    assert have[(t >= 1.5 - 1e-9) & (t <= 1.8 + 1e-9)].all()
    assert have[(t >= 2.0 - 1e-9) & (t <= 2.5 + 1e-9)].all()
    row = np.flatnonzero(np.isclose(t, 1.55))[0]  # between two frames facing +X
    np.testing.assert_allclose(got.pose[row, :2], [0.20, 0.16], atol=0.003)
    assert got.pose[row, 2] == pytest.approx(0.0, abs=0.5)
    row = np.flatnonzero(np.isclose(t, 2.45))[0]  # between the two frames a full turn on
    np.testing.assert_allclose(got.pose[row, :2], [0.20, 0.16], atol=0.003)
    assert got.pose[row, 2] == pytest.approx(360.0, abs=0.5)


def test_detected_corners_are_in_the_pixel_centre_convention(tmp_path):
    """A marker covering pixels 100..159 has its outer corners at 99.5 and 159.5 (0 at the
    centre of the top-left pixel, as camera.toml's cx_px); OpenCV's AprilTag refinement says
    100 and 160, which measure-pose corrects; the same when the crop is searched twice as
    large."""
    from mecanum_hil.vision.pose import _Tracker, detect, make_detector
    from mecanum_hil.vision.scene import load_scene

    frame = np.full((300, 300), 128, np.uint8)
    paste(frame, 3, (100, 100), None)
    want = [[99.5, 99.5], [159.5, 99.5], [159.5, 159.5], [99.5, 159.5]]
    for refinement in ("apriltag", "subpix"):
        got = detect(make_detector("DICT_4X4_50", refinement), frame)[3]
        np.testing.assert_allclose(got, want, atol=0.1 if refinement == "apriltag" else 0.2)
    (tmp_path / "scene.toml").write_text(SCENE_TOML)
    tracker = _Tracker(load_scene(tmp_path / "scene.toml"), (300, 300), 5)
    bgr = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    np.testing.assert_allclose(tracker._crop_detect(bgr, (60, 60, 200, 200))[3], want, atol=0.1)
    np.testing.assert_allclose(tracker._crop_detect(bgr, (60, 60, 200, 200), upscale=2)[3],
                               want, atol=0.1)


def test_truncated_video_is_measured_as_far_as_it_goes_with_a_warning(files, tmp_path, capsys):
    data = (files / "top.avi").read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[:len(data) // 2])
    out = tmp_path / "pose.csv"
    assert main(["measure-pose", str(cut), "--camera", str(files / "camera.toml"), "--scene",
                 str(files / "scene.toml"), "--out", str(out), "--window", "0", "--json"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert 3 <= summary["frames"] < len(HEADINGS)
    assert any("truncated?" in w for w in summary["warnings"])
    assert "warning: the video ends after" in captured.err
