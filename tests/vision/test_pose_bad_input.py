"""measure-pose with bad input: one error line and non-zero exit, never an input overwritten,
an empty result with exit 0, a ZeroDivisionError, or an empty stderr line (the progress bar)."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.io.recording import empty_like_times, write_recording
from mecanum_hil.model import load_calibration, load_robot_profile
from mecanum_hil.prediction import predict
from mecanum_hil.vision.overhead import OverheadSettings, render_overhead
from mecanum_hil.vision.pose import PoseOptions

pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory):
    """A short overhead video, its camera.toml and scene.toml, and the recording it shows."""
    from mecanum_hil.vision.camera import save_camera
    from mecanum_hil.vision.scene import save_scene

    t = np.arange(0.0, 1.2 + 1e-9, 0.01)
    cmd = np.zeros((t.size, 3))
    cmd[:, 2] = 60.0
    cmd[(t >= 0.3) & (t < 0.9), 0] = 60.0
    rec = predict(empty_like_times(t).with_values(commands=cmd), load_calibration(),
                  load_robot_profile())
    d = tmp_path_factory.mktemp("pose_bad")
    res = render_overhead(rec, d / "top.mp4", OverheadSettings(width_px=480, height_px=360))
    camera, scene = d / "top.camera.toml", d / "top.scene.toml"
    save_camera(res.camera, camera)
    save_scene(res.scene, scene)
    write_recording(rec.with_values(pose=np.full_like(rec.pose, np.nan)), d / "rec.csv")
    return res.path, camera, scene, d / "rec.csv"


def _run(argv, capsys):
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


@pytest.mark.parametrize("which", ["video", "camera", "scene", "recording", "sidecar"])
def test_out_naming_an_input_is_refused_and_the_input_kept(scene_files, capsys, which):
    video, camera, scene, rec = scene_files
    out = {"video": video, "camera": camera, "scene": scene, "recording": rec,
           "sidecar": rec.with_suffix(".txt")}[which]  # .txt: its sidecar is rec.json
    before = {p: p.read_bytes() for p in (video, camera, scene, rec, rec.with_suffix(".json"))}
    code, err = _run(["measure-pose", video, "--camera", camera, "--scene", scene,
                      "--recording", rec, "--out", out], capsys)
    assert code == 1 and err.startswith("error: ") and err.count("\n") == 1, err
    assert "--out would overwrite" in err
    assert all(p.read_bytes() == data for p, data in before.items())


@pytest.mark.parametrize("fps", ["inf", "1e-300", "1e-5", "0"])
def test_fps_outside_what_a_camera_has_is_one_line(scene_files, tmp_path, capsys, fps):
    video, camera, scene, _ = scene_files
    code, err = _run(["measure-pose", video, "--camera", camera, "--scene", scene, "--out",
                      tmp_path / "p.csv", "--fps", fps], capsys)
    assert code == 1 and err.startswith("error: --fps must be within 0.1 .. 100000")
    assert err.count("\n") == 1 and not (tmp_path / "p.csv").exists()
    with pytest.raises(Exception, match="--fps must be within"):
        PoseOptions(fps=float(fps))


def test_a_video_start_with_no_overlap_is_an_error_not_empty_pose_columns(
        scene_files, tmp_path, capsys):
    video, camera, scene, rec = scene_files
    out = tmp_path / "filled.csv"
    code, err = _run(["measure-pose", video, "--camera", camera, "--scene", scene,
                      "--recording", rec, "--out", out, "--video-start-s", "1e12"], capsys)
    lines = err.splitlines()
    assert code == 1 and lines[-1].startswith("error: ") and "does not overlap" in lines[-1]
    assert "--video-start-s" in lines[-1] and not out.exists()
    # no empty line (the progress bar's, off a terminal) before the warnings and the error
    assert all(line.startswith(("warning: ", "error: ")) for line in lines), err
