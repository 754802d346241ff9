"""calibrate-camera on rendered views of a ChArUco board with a known lens."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.vision.calibrate import BoardSpec, parse_board, render_board_view
from mecanum_hil.vision.camera import CameraModel, CameraPose, load_camera

cv2 = pytest.importorskip("cv2")

TRUE = CameraModel(640, 480, 520.0, 518.0, 322.0, 236.0, (-0.25, 0.08, 0.001, -0.0007, 0.0))
BOARD = "charuco:7x5:0.04:0.03"


def views(cells, per_cell=2, seed=1, camera=TRUE):
    """Board views through ``camera`` centred on the given image cells (u, v shares), tilted
    at random."""
    spec = BoardSpec(7, 5, 0.04, 0.03)
    rng = np.random.default_rng(seed)
    out = []
    for u, v in cells:
        for _ in range(per_cell):
            rv = rng.uniform(-0.45, 0.45, 3)
            rv[2] = rng.uniform(-0.3, 0.3)
            r = cv2.Rodrigues(rv)[0]
            n = camera.normalised(np.array([[u * camera.width_px, v * camera.height_px]]))[0]
            centre = rng.uniform(0.45, 0.6) * np.array([n[0], n[1], 1.0])
            t = centre - r @ np.array([0.14, 0.10, 0.0])
            out.append(render_board_view(spec, camera, CameraPose(rv, t), noise_std=2.0,
                                         seed=len(out)))
    return out


def write(images, folder):
    folder.mkdir()
    for i, img in enumerate(images):
        cv2.imwrite(str(folder / f"view{i:02d}.png"), img)
    return folder


GRID = [(u, v) for u in (0.2, 0.5, 0.8) for v in (0.2, 0.5, 0.8)]


def test_calibration_recovers_the_lens(tmp_path, capsys):
    folder = write(views(GRID), tmp_path / "views")
    out = tmp_path / "camera.toml"
    assert main(["calibrate-camera", str(folder), "--board", BOARD, "--out", str(out),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["rms_px"] < 0.3
    cam = load_camera(out)
    assert cam.fx_px == pytest.approx(TRUE.fx_px, rel=0.01)
    assert cam.fy_px == pytest.approx(TRUE.fy_px, rel=0.01)
    assert abs(cam.cx_px - TRUE.cx_px) < 3.0 and abs(cam.cy_px - TRUE.cy_px) < 3.0
    # the radial distortion agrees out to the image's corners (within 0.4 %, ~1 px there)
    r = np.linspace(0.0, 0.75, 16)

    def radial(c):
        k1, k2, _, _, k3 = c.distortion
        return 1 + k1 * r ** 2 + k2 * r ** 4 + k3 * r ** 6

    assert np.abs(radial(cam) - radial(TRUE)).max() < 0.004


def test_calibration_refuses_poor_coverage(tmp_path, capsys):
    left = [(0.2, v) for v in (0.2, 0.5, 0.8)] + [(0.45, 0.5)]
    folder = write(views(left, per_cell=2), tmp_path / "left")
    assert main(["calibrate-camera", str(folder), "--board", BOARD, "--out",
                 str(tmp_path / "c.toml")]) == 1
    err = capsys.readouterr().err
    assert "do not cover" in err and "right" in err and "top-left" not in err
    assert not (tmp_path / "c.toml").exists()


def test_bad_board_and_too_few_views(tmp_path, capsys):
    with pytest.raises(Exception, match="charuco:COLSxROWS"):
        parse_board("chess:7x5:0.04:0.03")
    assert main(["calibrate-camera", str(tmp_path), "--board", "charuco:7x5:0.03:0.04",
                 "--out", str(tmp_path / "c.toml")]) == 1
    assert "MARKER_M < SQUARE_M" in capsys.readouterr().err
    folder = write(views([(0.5, 0.5)], per_cell=2), tmp_path / "two")
    assert main(["calibrate-camera", str(folder), "--board", BOARD, "--out",
                 str(tmp_path / "c.toml")]) == 1
    assert "need at least 5" in capsys.readouterr().err


def test_calibration_from_a_video(tmp_path, capsys):
    from mecanum_hil.vision.video import VideoWriter

    video = tmp_path / "board.avi"
    with VideoWriter(video, 10.0, (TRUE.width_px, TRUE.height_px)) as w:
        for img in views(GRID, per_cell=1, seed=3):
            w.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    out = tmp_path / "camera.toml"
    assert main(["calibrate-camera", str(video), "--board", BOARD, "--out", str(out)]) == 0
    assert "RMS reprojection error" in capsys.readouterr().out
    assert load_camera(out).fx_px == pytest.approx(TRUE.fx_px, rel=0.02)


def test_views_of_a_long_video_in_bounded_memory(tmp_path):
    """A calibration video's views are spread over all of it, but never all its frames held at
    once (a minute of 1080p would be gigabytes of grey frames)."""
    import tracemalloc

    from mecanum_hil.vision.calibrate import read_views
    from mecanum_hil.vision.video import VideoWriter

    video = tmp_path / "long.avi"
    n = 240
    with VideoWriter(video, 30.0, (320, 240)) as w:
        for i in range(n):
            w.write(np.full((240, 320, 3), i, np.uint8))  # the frame's index as its grey level
    tracemalloc.start()
    try:
        got = read_views(video, max_views=6)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4e6, peak  # all 240 grey frames: 18 MB
    levels = [float(v.mean()) for v in got]
    assert len(got) == 6 and levels == sorted(levels)
    assert levels[0] < 2 and levels[-1] > 0.8 * n
