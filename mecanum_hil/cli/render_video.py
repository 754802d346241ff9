"""``mecanum-hil render-video``: a video of wheel markers turning as a recording says."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ._options import JsonOpt


def command(
    recording: Annotated[Path, typer.Option(
        "--recording", help="Recording whose wheel columns drive the wheels.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Video to write (.mp4 or .avi).")],
    wheels: Annotated[str, typer.Option(
        "--wheels", help="Wheels to show side by side, e.g. 1 or 1,2.")] = "1",
    fps: Annotated[float, typer.Option("--fps", help="Frame rate \\[1/s].")] = 30.0,
    size: Annotated[str, typer.Option("--size", help="Frame size WxH \\[px].")] = "320x240",
    start_s: Annotated[float, typer.Option(
        "--start", help="Recording time of the first frame after the recording's start \\[s].")
    ] = 0.0,
    duration_s: Annotated[float | None, typer.Option(
        "--duration", help="Video length \\[s] (default: to the recording's end).")] = None,
    noise: Annotated[float, typer.Option(
        "--noise", help="Sensor noise, standard deviation \\[grey levels].")] = 0.0,
    blur: Annotated[float, typer.Option(
        "--blur", help="Motion blur: shutter open for this share of a frame (0..1).")] = 0.0,
    lighting: Annotated[float, typer.Option(
        "--lighting-drift", help="Relative amplitude of slow brightness change.")] = 0.0,
    tilt: Annotated[float, typer.Option(
        "--tilt", help="Oblique view: angle off the wheel axis \\[deg].")] = 0.0,
    tilt_axis: Annotated[float, typer.Option(
        "--tilt-axis", help="Direction of the tilt axis in the image \\[deg].")] = 0.0,
    jpeg: Annotated[int | None, typer.Option(
        "--jpeg", help="Extra JPEG compression of each frame, quality 1..100.")] = None,
    distractors: Annotated[int, typer.Option(
        "--distractors", min=0, help="Saturated objects off the wheels (every 2nd moves).")] = 0,
    mirror: Annotated[bool, typer.Option(
        "--mirror", help="Film from the other side: positive speed turns clockwise.")] = False,
    seed: Annotated[int, typer.Option("--seed", help="Seed of noise and distractors.")] = 0,
    marker: Annotated[str, typer.Option(
        "--marker", help="dot (saturated dot near the rim) or aruco (ArUco marker on the hub).")
    ] = "dot",
    truth: Annotated[Path | None, typer.Option(
        "--truth", help="Also write the true wheel speeds at the frame times (video clock).")
    ] = None,
    as_json: JsonOpt = False,
) -> None:
    """Render wheels with markers turning as a recording's wheel speeds say."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn

    from ..errors import VideoError
    from ..io.recording import empty_like_times, read_recording, write_recording
    from ..vision.render import RenderSettings, render_video

    try:
        shown = tuple(int(w) for w in wheels.split(","))
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise VideoError(f"--wheels '{wheels}' / --size '{size}': expected e.g. 1,2 and 320x240"
                         ) from None
    settings = RenderSettings(width, height, fps, shown, start_s, duration_s, mirror=mirror,
                              noise_std=noise, exposure=blur, lighting_drift=lighting,
                              tilt_deg=tilt, tilt_axis_deg=tilt_axis, jpeg_quality=jpeg,
                              distractors=distractors, seed=seed, marker=marker)
    rec = read_recording(recording)
    with Progress(TextColumn("rendering"), BarColumn(),
                  TextColumn("{task.completed}/{task.total} frames"),
                  console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("render", total=None)
        result = render_video(rec, out, settings,
                              progress=lambda d, t: bar.update(task, completed=d, total=t))
    if truth is not None:
        w = empty_like_times(result.frame_t_s).wheel_rpm
        for k, wheel in enumerate(shown):
            w[:, wheel - 1] = result.wheel_rpm[:, k]
        write_recording(empty_like_times(result.frame_t_s, {
            "source": "mecanum-hil render-video (truth)", "video": str(out),
            "recording": str(recording), "camera_start_s": start_s}).with_values(wheel_rpm=w),
            truth)
    summary = {"video": str(out), "frames": int(result.frame_t_s.size), "fps": fps,
               "size_px": [width, height], "wheels": list(shown),
               "rois": {str(p.wheel): list(p.roi) for p in result.placements},
               "camera_start_s": start_s, "truth": None if truth is None else str(truth)}
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
        return
    rois = " ".join(f"--roi {p.wheel}:{','.join(map(str, p.roi))}" for p in result.placements)
    typer.echo(f"wrote {out} ({summary['frames']} frames, {fps:g} fps, {width}x{height}); "
               f"wheel regions: {rois}")
