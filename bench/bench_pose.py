"""Benchmark of measure-pose: speed against decoding alone and real time, and accuracy against
the renderer's truth next to the plain per-frame OpenCV pipeline, same videos, same run.

Usage: ``python bench/bench_pose.py [--seconds 10] [--repeat 3]``. Renders overhead videos
(1280x720 and 640x480, 30 fps, .mp4) of the model driving diagonally while turning, from rest
(lens distortion, a 30 degree oblique view, the robot's marker 0.23 m above the floor, offset
and turned, sensor noise 2 grey levels), then:

- speed (1280x720): best of ``--repeat`` interleaved runs of decoding every frame alone and of
  the whole ``measure_pose``; prints frames per second, the cost on top of decoding and the
  real-time factor (target: >= 5x real time);
- accuracy (both sizes): position and heading RMSE against the truth over the frames where the
  marker is visible, and the share of them measured, for ``measure_pose`` (also without its
  smoothing) and for the plain pipeline (``measure_pose_plain``: per frame detect, undistort,
  solvePnP of camera and marker) with OpenCV's usual ``cornerSubPix`` corners and with the
  AprilTag corner refinement ``measure_pose`` uses.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from mecanum_hil.io.recording import empty_like_times
from mecanum_hil.model import load_calibration, load_robot_profile
from mecanum_hil.prediction import predict
from mecanum_hil.vision.overhead import OverheadSettings, render_overhead
from mecanum_hil.vision.pose import PoseOptions, measure_pose, measure_pose_plain, pose_errors
from mecanum_hil.vision.video import iter_frames, open_video


def drive(seconds: float):
    """Rest, then diagonal travel at 60 rpm while turning at 25 deg/s, then a stop."""
    t = np.arange(0.0, seconds + 1e-9, 0.01)
    cmd = np.zeros((t.size, 3))
    cmd[:, 2] = 60.0
    on = (t >= 0.4) & (t < seconds - 0.6)
    cmd[on, 0], cmd[on, 1] = 60.0, 25.0
    return predict(empty_like_times(t).with_values(commands=cmd), load_calibration(),
                   load_robot_profile())


def decode_only(path: Path) -> int:
    cap, _ = open_video(path)
    n = sum(1 for _ in iter_frames(cap))
    cap.release()
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    rec = drive(args.seconds)
    print(f"load average {os.getloadavg()[0]:.1f}; {args.seconds:g} s of video at 30 fps")
    with tempfile.TemporaryDirectory() as tmp:
        renders = {}
        for w, h in ((1280, 720), (640, 480)):
            t0 = time.perf_counter()
            renders[(w, h)] = render_overhead(rec, Path(tmp) / f"v{w}.mp4", OverheadSettings(
                width_px=w, height_px=h, tilt_deg=30.0, noise_std=2.0))
            print(f"rendered {w}x{h} in {time.perf_counter() - t0:.1f} s")
        hd = renders[(1280, 720)]
        best = {"decode": np.inf, "measure": np.inf}
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            n = decode_only(hd.path)
            best["decode"] = min(best["decode"], time.perf_counter() - t0)
            t0 = time.perf_counter()
            measure_pose(hd.path, hd.camera, hd.scene)
            best["measure"] = min(best["measure"], time.perf_counter() - t0)
        duration = n / 30.0
        print(f"\nspeed, 1280x720, {n} frames (best of {args.repeat}):")
        print(f"  decode only     {n / best['decode']:7.1f} fps")
        print(f"  measure_pose    {n / best['measure']:7.1f} fps  = "
              f"{best['measure'] / best['decode'] - 1:+.0%} on top of decoding, "
              f"{duration / best['measure']:.1f}x real time (target >= 5x)")
        print("\naccuracy over the frames with the marker visible "
              "(position RMSE / heading RMSE / found, median errors):")
        for (w, h), res in renders.items():
            vis = res.marker_visible
            rows = []
            m = measure_pose(res.path, res.camera, res.scene)
            rows.append(("measure_pose", m.t_s, m.pose))
            raw = measure_pose(res.path, res.camera, res.scene, PoseOptions(window_s=0.0))
            rows.append(("measure_pose, no smoothing", raw.t_s, raw.pose))
            for refine in ("subpix", "apriltag"):
                t0 = time.perf_counter()
                t, p = measure_pose_plain(res.path, res.camera, res.scene, refinement=refine)
                dt = time.perf_counter() - t0
                rows.append((f"plain per-frame ({refine}; {len(t) / dt:.0f} fps)", t, p))
            print(f"  {w}x{h}:")
            for name, t, p in rows:
                e = pose_errors(t[vis], p[vis], res.pose[vis])
                print(f"    {name:38s} {1000 * e['position_rmse_m']:6.2f} mm  "
                      f"{e['heading_rmse_deg']:6.3f} deg  {100 * e['found_share']:5.1f} %   "
                      f"(median {1000 * e['position_median_m']:5.2f} mm "
                      f"{e['heading_median_deg']:5.3f} deg)")


if __name__ == "__main__":
    main()
