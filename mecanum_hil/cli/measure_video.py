"""``mecanum-hil measure-video``: wheel speed from a camera video of wheel markers."""


import json
from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, OutOpt, RobotOpt

VideoArg = Annotated[Path, typer.Argument(help="Video file (anything OpenCV decodes).")]
WheelOpt = Annotated[int, typer.Option(
    "--wheel", min=1, max=4, help="Wheel column to fill (1 FL, 2 FR, 3 RL, 4 RR).")]
RoiOpt = Annotated[list[str] | None, typer.Option(
    "--roi", help="Search region [N:]x,y,w,h [px]; one per wheel for several wheels.",
    metavar="[N:]X,Y,W,H")]
MarkerOpt = Annotated[str, typer.Option(
    "--marker", help="auto (any saturated dot) or aruco (DICT_4X4_50, orientation).")]
MarkerHsvOpt = Annotated[str | None, typer.Option(
    "--marker-hsv", help="Pin the dot's colour: OpenCV HSV box H,S,V:H,S,V (H 0..179).",
    metavar="H,S,V:H,S,V")]
InvertOpt = Annotated[bool, typer.Option(
    "--invert", help="Count clockwise in the image as positive.")]
FpsOpt = Annotated[float | None, typer.Option(
    "--fps", help="Frame rate to use instead of the video's timestamps [1/s].")]
WindowOpt = Annotated[float, typer.Option(
    "--window", help="Speed regression window [s].")]
MinFoundOpt = Annotated[float, typer.Option(
    "--min-found", help="Smallest share of frames with the marker (0..1).")]
SpeedRangeOpt = Annotated[str | None, typer.Option(
    "--speed-range", metavar="LO,HI", help="Expected speed range [rpm] (after --invert); "
    "one side may be empty: '0,' forwards only, ',0' backwards only. Resolves speeds beyond "
    "half a turn per frame (aliasing), refused without it.")]
FixedCameraOpt = Annotated[bool, typer.Option(
    "--fixed-camera", help="Do not follow the hub: the camera is on a tripod.")]
RecordingOpt = Annotated[Path | None, typer.Option(
    "--recording", help="Recording from `record` to align with and merge into.")]
MergedOpt = Annotated[Path | None, typer.Option(
    "--merged", help="Merged recording to write (default: OUT stem + '.merged.csv').")]


def command(
    video: VideoArg,
    out: OutOpt,
    wheel: WheelOpt = 1,
    roi: RoiOpt = None,
    marker: MarkerOpt = "auto",
    marker_hsv: MarkerHsvOpt = None,
    invert: InvertOpt = False,
    fps: FpsOpt = None,
    window_s: WindowOpt = 0.1,
    min_found: MinFoundOpt = 0.3,
    speed_range: SpeedRangeOpt = None,
    fixed_camera: FixedCameraOpt = False,
    recording: RecordingOpt = None,
    merged: MergedOpt = None,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    as_json: JsonOpt = False,
) -> None:
    """Measure wheel speed from a video of wheel markers; write a recording."""
    from rich.console import Console

    from ..io.recording import read_recording, write_recording

    opts = _options(wheel, roi, marker, marker_hsv, invert, fps, window_s, min_found,
                    speed_range, fixed_camera)
    # Refuse before the (long) measurement: writing over the inputs would lose them.
    _refuse_overwriting_inputs(video, recording, out, merged)
    rec = read_recording(recording) if recording is not None else None
    err_console = Console(stderr=True)
    result = _measure_with_progress(video, opts, err_console)
    merged_path = None
    if rec is not None:
        merged_path = merged or out.with_name(out.stem + ".merged.csv")
        result = _merge(result, rec, calibration, robot, merged_path)
    write_recording(result.recording, out)
    summary = {**result.summary, "out": str(out),
               "merged": None if merged_path is None else str(merged_path)}
    for w in result.warnings:
        err_console.print(f"warning: {w}", markup=False, highlight=False, soft_wrap=True)
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
        return
    _echo_summary(video, summary, out, merged_path)


def _options(wheel: int, roi: list[str] | None, marker: str, marker_hsv: str | None,
             invert: bool, fps: float | None, window_s: float, min_found: float,
             speed_range: str | None, fixed_camera: bool):
    """The measurement's options (one-line errors for a marker, region or range it cannot
    take)."""
    from ..errors import VideoError
    from ..vision.detect import MarkerSpec, parse_hsv, parse_roi
    from ..vision.measure import MeasureOptions
    from ..vision.speed import parse_speed_range

    if marker not in ("auto", "aruco"):
        raise VideoError(f"--marker must be auto or aruco, got '{marker}'")
    if marker_hsv is not None and marker == "aruco":
        raise VideoError("--marker-hsv pins a dot's colour; it does not go with --marker aruco")
    spec = parse_hsv(marker_hsv) if marker_hsv is not None else MarkerSpec(marker)
    rois = tuple(parse_roi(r, wheel) for r in roi) if roi else ((wheel, None),)
    return MeasureOptions(rois=rois, marker=spec, invert=invert, fps=fps, window_s=window_s,
                          min_found=min_found, track_hub=not fixed_camera,
                          expected_rpm=None if speed_range is None
                          else parse_speed_range(speed_range))


def _merge(result, rec, calibration: str, robot: str, merged_path: Path):
    """Align the measurement with the recording, write the merged recording; the aligned
    measurement."""
    from ..io.recording import write_recording
    from ..model import load_calibration, load_robot_profile
    from ..vision.measure import align_with_recording

    merged_rec, result = align_with_recording(result, rec, load_calibration(calibration),
                                              load_robot_profile(robot))
    write_recording(merged_rec, merged_path)
    return result


def _refuse_overwriting_inputs(video: Path, recording: Path | None, out: Path,
                               merged: Path | None) -> None:
    from ..errors import VideoError
    from ._options import refuse_overwriting

    merged_path = None
    if recording is not None:
        merged_path = merged or out.with_name(out.stem + ".merged.csv")
        if merged_path.resolve() == out.resolve():
            raise VideoError(f"{out}: --merged and --out name the same file")
    refuse_overwriting([(recording, "the recording given with --recording", True),
                        (video, "the video being measured")],
                       [(out, "--out", True), (merged_path, "--merged", True)])


def _measure_with_progress(video: Path, opts, err_console):
    """:func:`~mecanum_hil.vision.measure.measure_video` behind a frame-count bar on stderr."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from ..vision.measure import measure_video

    with Progress(TextColumn("measuring {task.fields[name]}"), BarColumn(),
                  TextColumn("{task.completed}/{task.total} frames"), TimeRemainingColumn(),
                  console=err_console, transient=True,
                  disable=not err_console.is_terminal) as bar:
        task = bar.add_task("measure", total=None, name=video.name)

        def progress(done: int, total: int) -> None:
            if done % 10 == 0 or done == total:
                bar.update(task, completed=done, total=total or None)

        return measure_video(video, opts, progress)


def _echo_summary(video: Path, summary: dict, out: Path, merged_path: Path | None) -> None:
    """The measurement in a few lines: timing, each wheel, the offset, what was written."""
    typer.echo(f"{video}: {summary['frames']} frames, {summary['fps']:g} fps "
               f"({summary['timing']}), {summary['duration_s']:.2f} s")
    for w in summary["wheels"]:
        mean = "-" if w["mean_rpm"] is None else f"{w['mean_rpm']:.2f}"
        typer.echo(f"  wheel {w['wheel']}: marker found in {100 * w['found_fraction']:.1f}% of "
                   f"frames, mean {mean} rpm, max |{w['max_abs_rpm']}| rpm")
        if w.get("gaps"):
            typer.echo(f"    {len(w['gaps'])} gap(s) without the marker, "
                       f"{w['gaps_unbridged']} not bridged (see --json 'gaps')")
        if w.get("aliasing"):
            typer.echo(f"    aliasing: no speed for {w['aliased_frames']} frames")
    if summary.get("alignment"):
        a = summary["alignment"]
        typer.echo(f"  offset: recording time = video time + {a['offset_s']:.4f} s "
                   f"({a['method']}, correlation {a['correlation']:.3f})")
    typer.echo(f"wrote {out}" + (f" and {merged_path}" if merged_path else ""))
