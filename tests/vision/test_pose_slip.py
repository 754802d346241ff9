"""Slip seen only by an overhead camera.

Slip is hidden in the simulated controller; recordings forward, sideways and turning (each at
two speeds) get their pose only from rendered overhead videos through ``measure-pose``;
``diagnose`` (through the command line) names slip and recovers each efficiency within 0.05.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.io.recording import read_recording

pytest.importorskip("cv2")

EFFICIENCY = (0.9, 0.8, 0.85)

PROFILE = """[profile]
name = "{name}"
[[segments]]
kind = "hold"
duration_s = 0.6
[[segments]]
kind = "step"
duration_s = 2.0
{command}
[[segments]]
kind = "step"
duration_s = 1.0
n_rpm = 0.0
omega_dps = 0.0
"""
# Each kind of motion twice (two speeds): diagnose compares models on recordings they were not
# fitted to (leave one recording out); a recording that alone moves along one axis leaves that
# axis's efficiency unknown when it is left out (with one recording per kind, slip was named
# for one set of renders and not for another: docs/vision-pose.md).
MOTIONS = {"forward-40": "n_rpm = 40.0\ntheta_deg = 90.0",
           "forward-80": "n_rpm = 80.0\ntheta_deg = 90.0",
           "sideways-40": "n_rpm = 40.0\ntheta_deg = 180.0",
           "sideways-80": "n_rpm = 80.0\ntheta_deg = 180.0",
           "turning-30": "omega_dps = 30.0",
           "turning-60": "omega_dps = 60.0"}


@pytest.mark.slow
def test_diagnose_names_slip_from_overhead_videos(tmp_path, capsys):
    fx = tmp_path / "robot.toml"
    fx.write_text(f"[effects.slip]\nefficiency = {list(EFFICIENCY)}\n\n"
                  "[noise]\nwheel_rpm_std = 0.25\nseed = 1\n")
    args = ["campaign", "--effects", str(fx), "--out", str(tmp_path / "camp"),
            "--pose-noise", "0,0,0"]
    for name, command in MOTIONS.items():
        prof = tmp_path / f"{name}.toml"
        prof.write_text(PROFILE.format(name=name, command=command))
        args += ["--profile", str(prof)]
    assert main(args) == 0
    measured = []
    for k, name in enumerate(MOTIONS):
        rec = tmp_path / "camp" / f"{name}.csv"
        video = tmp_path / f"{name}.mp4"
        start = 0.2 + 0.02 * k  # the camera starts late, by an amount measure-pose must find
        assert main(["render-video", "--overhead", "--recording", str(rec), "--out", str(video),
                     "--size", "640x480", "--tilt", "30", "--noise", "2", "--seed", str(k),
                     "--start", str(start)]) == 0
        out = tmp_path / f"{name}-video-pose.csv"
        assert main(["measure-pose", str(video), "--camera", str(tmp_path / f"{name}.camera.toml"),
                     "--scene", str(tmp_path / f"{name}.scene.toml"), "--recording", str(rec),
                     "--out", str(out), "--json"]) == 0
        capsys.readouterr()
        got = read_recording(out)
        assert got.metadata["video_start_s"] == pytest.approx(start, abs=1 / 30)
        # the pose columns are the video's alone: the recording's (the simulator's truth) are
        # replaced, and rows before the camera started are empty
        assert not np.isfinite(got.pose[got.t_s < start - 0.05]).any()
        measured.append(str(out))
    assert main(["diagnose", *measured, "--calibration", "paper", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    named = [e["effect"] for e in result["effects"]]
    assert named == ["slip"], result
    eff = result["effects"][0]["parameters"]["efficiency"]
    np.testing.assert_allclose(eff, EFFICIENCY, atol=0.05)


@pytest.mark.slow
def test_demo_pose_stage_plumbing(tmp_path):
    """The demo's pose stage (:func:`mecanum_hil.demo.pose_story`) on two short runs: videos,
    recordings filled from them, a diagnosis and the paper-experiment plot."""
    from mecanum_hil.demo import pose_story
    from mecanum_hil.profiles import PAPER_EXPERIMENTS, step

    lines = []
    res = pose_story(tmp_path, echo=lines.append, size=(480, 360),
                     profiles=[PAPER_EXPERIMENTS["paper-turn"],
                               step(60.0, duration_s=1.5, name="forward-60")])
    assert [p.name for p in res["measured"]] == ["paper-turn.csv", "forward-60.csv"]
    for name, err in res["errors"].items():
        assert err["position_rmse_m"] < 0.01 and err["found_share"] > 0.95, name
    rec = read_recording(res["measured"][0])
    assert rec.metadata["video_start_s"] == pytest.approx(0.2, abs=1 / 30)
    assert [p.name for p in res["plots"]] == ["paper-turn-pose.png"]
    assert res["plots"][0].stat().st_size > 10_000
    assert any(line.startswith("diagnose on the video's pose") for line in lines)
