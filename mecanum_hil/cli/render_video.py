"""``mecanum-hil render-video``: a video of wheel markers turning as a recording says."""


import json
from pathlib import Path
from types import SimpleNamespace
from typing import Annotated

import typer

from ._options import JsonOpt

RecordingOpt = Annotated[Path, typer.Option(
    "--recording", help="Recording whose wheel columns drive the wheels, or "
    "scenario:NAME (slow-start, stop-restart, reverse, through-limit).")]
VideoOutOpt = Annotated[Path, typer.Option("--out", "-o", help="Video to write (.mp4 or .avi).")]
WheelsOpt = Annotated[str, typer.Option(
    "--wheels", help="Wheels to show side by side, e.g. 1 or 1,2.")]
FpsOpt = Annotated[float, typer.Option("--fps", help="Frame rate [1/s], 0.1..1000.")]
SizeOpt = Annotated[str, typer.Option(
    "--size", help="Frame size WxH [px], at most 4096 a side and 4096x2160 in all.")]
StartOpt = Annotated[float, typer.Option(
    "--start", help="Recording time of the first frame after the recording's start [s], "
    ">= 0.")]
DurationOpt = Annotated[float | None, typer.Option(
    "--duration", help="Video length [s] (default and most: to the recording's end).")]
NoiseOpt = Annotated[float, typer.Option(
    "--noise", help="Sensor noise, standard deviation [grey levels], 0..255.")]
BlurOpt = Annotated[float, typer.Option(
    "--blur", help="Motion blur: shutter open for this share of a frame (0..1).")]
LightingOpt = Annotated[float, typer.Option(
    "--lighting-drift", help="Relative amplitude of slow brightness change (0..1).")]
TiltOpt = Annotated[float, typer.Option(
    "--tilt", help="Oblique view: angle off the wheel axis [deg].")]
TiltAxisOpt = Annotated[float, typer.Option(
    "--tilt-axis", help="Direction of the tilt axis in the image [deg].")]
JpegOpt = Annotated[int | None, typer.Option(
    "--jpeg", help="Extra JPEG compression of each frame, quality 1..100.")]
DistractorsOpt = Annotated[int, typer.Option(
    "--distractors", min=0, help="Saturated objects off the wheels (every 2nd moves), "
    "at most 100.")]
MirrorOpt = Annotated[bool, typer.Option(
    "--mirror", help="Film from the other side: positive speed turns clockwise.")]
SeedOpt = Annotated[int, typer.Option(
    "--seed", help="Seed of noise and distractors, 0..2147483647.")]
MarkerOpt = Annotated[str, typer.Option(
    "--marker", help="dot (saturated dot near the rim) or aruco (ArUco marker on the hub).")]
FenderOpt = Annotated[float, typer.Option(
    "--fender", help="Share of each wheel's height hidden by a fender from the top.")]
HideOpt = Annotated[list[str] | None, typer.Option(
    "--hide", help="A card hides the wheels from A to B [s] (video clock), e.g. 2-2.5.",
    metavar="A-B")]
ShakeOpt = Annotated[float, typer.Option(
    "--shake", help="Camera shake: random offset of each frame, SD per axis [px] (at most "
    "the frame's smaller side).")]
DriftOpt = Annotated[float, typer.Option(
    "--drift", help="Camera drift: amplitude of a slow wandering [px] (at most the "
    "frame's smaller side).")]
FlickerOpt = Annotated[float, typer.Option(
    "--flicker", help="Mains-light flicker, relative amplitude (0..1).")]
FlickerHzOpt = Annotated[float, typer.Option(
    "--flicker-hz", help="Flicker frequency [Hz] (100 or 120).")]
HueShiftOpt = Annotated[float, typer.Option(
    "--hue-shift", help="Marker colour drifting under the light, amplitude [deg], 0..180.")]
TruthOpt = Annotated[Path | None, typer.Option(
    "--truth", help="Also write the true wheel speeds at the frame times (video clock), "
    "with each marker's share in view and the camera's offset.")]
OverheadOpt = Annotated[bool, typer.Option(
    "--overhead", help="Draw an overhead camera's view of the robot (its pose columns) "
    "with floor markers instead of wheels; --tilt is the camera's tilt from straight down; "
    "writes V.camera.toml, V.scene.toml and the pose truth (--truth, default V.truth.csv).")]
DistortionOpt = Annotated[str | None, typer.Option(
    "--distortion", help="--overhead: the lens's k1,k2,p1,p2,k3 (OpenCV; finite numbers).")]


def command(
    recording: RecordingOpt,
    out: VideoOutOpt,
    wheels: WheelsOpt = "1",
    fps: FpsOpt = 30.0,
    size: SizeOpt = "320x240",
    start_s: StartOpt = 0.0,
    duration_s: DurationOpt = None,
    noise: NoiseOpt = 0.0,
    blur: BlurOpt = 0.0,
    lighting: LightingOpt = 0.0,
    tilt: TiltOpt = 0.0,
    tilt_axis: TiltAxisOpt = 0.0,
    jpeg: JpegOpt = None,
    distractors: DistractorsOpt = 0,
    mirror: MirrorOpt = False,
    seed: SeedOpt = 0,
    marker: MarkerOpt = "dot",
    fender: FenderOpt = 0.0,
    hide: HideOpt = None,
    shake: ShakeOpt = 0.0,
    drift: DriftOpt = 0.0,
    flicker: FlickerOpt = 0.0,
    flicker_hz: FlickerHzOpt = 100.0,
    hue_shift: HueShiftOpt = 0.0,
    truth: TruthOpt = None,
    overhead: OverheadOpt = False,
    distortion: DistortionOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Render wheels with markers turning as a recording's wheel speeds say."""
    a = SimpleNamespace(**locals())  # the options, by name, for the steps below
    if overhead:
        _refuse_wheel_options(a)
        _overhead(recording, out, fps, size, start_s, duration_s, noise, tilt, jpeg, seed,
                  distortion, truth, as_json)
        return
    shown, frame, settings = _wheel_settings(a)
    if truth is not None:
        _check_truth_overwrites_nothing(truth, out, recording)  # and that it can be written
    result = _render_wheels(recording, out, settings)
    if truth is not None:
        _write_wheel_truth(result, shown, out, recording, start_s, truth)
    _print_wheels(result, out, fps, frame, shown, start_s, truth, as_json)


def _refuse_wheel_options(a) -> None:
    """One-line error for options of the wheel view given with ``--overhead``."""
    from ..errors import VideoError

    unused = [flag for flag, value, default in (
        ("--wheels", a.wheels, "1"), ("--blur", a.blur, 0.0),
        ("--lighting-drift", a.lighting, 0.0), ("--tilt-axis", a.tilt_axis, 0.0),
        ("--distractors", a.distractors, 0), ("--mirror", a.mirror, False),
        ("--marker", a.marker, "dot"), ("--fender", a.fender, 0.0),
        ("--hide", a.hide or None, None), ("--shake", a.shake, 0.0), ("--drift", a.drift, 0.0),
        ("--flicker", a.flicker, 0.0), ("--hue-shift", a.hue_shift, 0.0)) if value != default]
    if unused:
        raise VideoError(f"{', '.join(unused)}: not used with --overhead")


def _wheel_settings(a):
    """``(wheels shown, (width, height) [px], RenderSettings)`` from the wheel view's
    options."""
    from ..errors import VideoError
    from ..vision.render import RenderSettings

    if a.distortion is not None:
        raise VideoError("--distortion is for --overhead")
    try:
        shown = tuple(int(w) for w in a.wheels.split(","))
        width, height = (int(v) for v in a.size.lower().split("x"))
    except ValueError:
        raise VideoError(f"--wheels '{a.wheels}' / --size '{a.size}': expected e.g. 1,2 and "
                         "320x240") from None
    from ..vision.scenarios import parse_hide

    settings = RenderSettings(width, height, a.fps, shown, a.start_s, a.duration_s,
                              mirror=a.mirror, noise_std=a.noise, exposure=a.blur,
                              lighting_drift=a.lighting, tilt_deg=a.tilt,
                              tilt_axis_deg=a.tilt_axis, jpeg_quality=a.jpeg,
                              distractors=a.distractors, seed=a.seed, marker=a.marker,
                              fender=a.fender, occlusions_s=parse_hide(a.hide or []),
                              shake_px=a.shake, drift_px=a.drift, flicker=a.flicker,
                              flicker_hz=a.flicker_hz, hue_shift_deg=a.hue_shift)
    return shown, (width, height), settings


def _render_wheels(recording: Path, out: Path, settings):
    """Render the recording (or scenario) into ``out`` behind a progress bar."""
    from ..vision.render import render_video
    from ..vision.scenarios import recording_or_scenario

    rec = recording_or_scenario(recording)
    return _with_progress_bar(lambda progress: render_video(rec, out, settings,
                                                            progress=progress))


def _print_wheels(result, out: Path, fps: float, frame: tuple[int, int], shown, start_s: float,
                  truth: Path | None, as_json: bool) -> None:
    """What was written: a line with the wheel regions to measure, or JSON."""
    width, height = frame
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


def _check_truth_overwrites_nothing(truth: Path, out: Path, recording: Path) -> None:
    from ._options import refuse_overwriting

    source = None if str(recording).startswith("scenario:") else Path(recording)
    refuse_overwriting([(out, "the video (--out)"),
                        (source, "the recording given with --recording")], [(truth, "--truth")])


def _with_progress_bar(render):
    """Run ``render(progress)`` behind a frame-count bar on stderr; return its result."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn

    console = Console(stderr=True)
    with Progress(TextColumn("rendering"), BarColumn(),
                  TextColumn("{task.completed}/{task.total} frames"),
                  console=console, transient=True, disable=not console.is_terminal) as bar:
        task = bar.add_task("render", total=None)
        return render(lambda d, t: bar.update(task, completed=d, total=t))


def _write_wheel_truth(result, shown: tuple[int, ...], out: Path, recording: Path,
                       start_s: float, truth: Path) -> None:
    """The true wheel speeds at the frame times (video clock), with the markers' view."""
    from ..io.recording import empty_like_times, write_recording
    from ..vision.scenarios import truth_extra

    w = empty_like_times(result.frame_t_s).wheel_rpm
    for k, wheel in enumerate(shown):
        w[:, wheel - 1] = result.wheel_rpm[:, k]
    write_recording(empty_like_times(result.frame_t_s, {
        "source": "mecanum-hil render-video (truth)", "video": str(out),
        "recording": str(recording), "camera_start_s": start_s}).with_values(
            wheel_rpm=w, extra=truth_extra(result)), truth)


def _overhead(recording: Path, out: Path, fps: float, size: str, start_s: float,
              duration_s: float | None, noise: float, tilt: float, jpeg: int | None, seed: int,
              distortion: str | None, truth: Path | None, as_json: bool) -> None:
    """``render-video --overhead``: the video, its camera and scene files, the pose truth."""
    from ..errors import VideoError
    from ..io.recording import empty_like_times, read_recording, write_recording
    from ..vision.camera import save_camera
    from ..vision.overhead import OverheadSettings, render_overhead
    from ..vision.scene import save_scene
    from ._options import refuse_overwriting

    try:
        width, height = (int(v) for v in size.lower().split("x"))
        lens = {} if distortion is None else {
            "distortion": tuple(float(v) for v in distortion.split(","))}
    except ValueError:
        raise VideoError(f"--size '{size}' / --distortion '{distortion}': expected e.g. "
                         "1280x720 and -0.2,0.06,0,0,0") from None
    if len(lens.get("distortion", (0,) * 5)) != 5:
        raise VideoError("--distortion needs five numbers k1,k2,p1,p2,k3")
    settings = OverheadSettings(width, height, fps, start_s, duration_s, tilt_deg=tilt,
                                noise_std=noise, jpeg_quality=jpeg, seed=seed, **lens)
    stem = out.with_suffix("")
    camera_file, scene_file = Path(f"{stem}.camera.toml"), Path(f"{stem}.scene.toml")
    truth_path = truth if truth is not None else Path(f"{stem}.truth.csv")
    truth_option = "--truth" if truth is not None else "the truth beside --out"
    refuse_overwriting([(recording, "the recording given with --recording", True)],
                       [(out, "--out"), (camera_file, "the camera file beside --out"),
                        (scene_file, "the scene file beside --out"),
                        (truth_path, truth_option, True)])
    refuse_overwriting([(out, "the video (--out)"), (camera_file, "the camera file"),
                        (scene_file, "the scene file")], [(truth_path, truth_option, True)])
    rec = read_recording(recording)
    res = _with_progress_bar(lambda progress: render_overhead(rec, out, settings,
                                                              progress=progress))
    camera_path = save_camera(res.camera, camera_file,
                              "the renderer's camera (exact intrinsics and distortion)")
    scene_path = save_scene(res.scene, scene_file, "the renderer's scene")
    meta = {"source": "mecanum-hil render-video --overhead (truth)", "video": str(out),
            "recording": str(recording), "camera_start_s": start_s,
            "camera_pose": res.camera_pose.summary(),
            "marker_visible": [bool(v) for v in res.marker_visible],
            "notes": "t_s is the video clock (0 at the first frame); pose = the recording's, "
                     "linear between its samples"}
    write_recording(empty_like_times(res.frame_t_s, meta).with_values(pose=res.pose), truth_path)
    summary = {"video": str(out), "frames": int(res.frame_t_s.size), "fps": fps,
               "size_px": [width, height], "camera": str(camera_path), "scene": str(scene_path),
               "truth": str(truth_path), "camera_pose": res.camera_pose.summary(),
               "marker_visible_share": round(float(res.marker_visible.mean()), 4),
               "camera_start_s": start_s}
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
        return
    typer.echo(f"wrote {out} ({summary['frames']} frames, {fps:g} fps, {width}x{height}), "
               f"{camera_path}, {scene_path}, truth {truth_path}")
