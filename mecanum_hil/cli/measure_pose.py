"""``mecanum-hil measure-pose``: the robot's pose (X, Y, phi) from an overhead camera's video."""


import json
from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, RobotOpt

VideoArg = Annotated[Path, typer.Argument(help="Overhead video of the robot.")]
CameraOpt = Annotated[Path, typer.Option(
    "--camera", help="camera.toml (calibrate-camera).", metavar="CAMERA.toml")]
SceneOpt = Annotated[Path, typer.Option(
    "--scene", help="scene.toml: floor markers and the robot's marker.",
    metavar="SCENE.toml")]
PoseOutOpt = Annotated[Path, typer.Option(
    "--out", "-o", help="POSE.csv to write; with --recording the recording with its pose "
    "columns filled.")]
RecordingOpt = Annotated[Path | None, typer.Option(
    "--recording", help="Fill this recording's pose columns from the video.",
    metavar="REC.csv")]
VideoStartOpt = Annotated[str | None, typer.Option(
    "--video-start-s", help="Recording time of the first frame [s], or auto (the "
    "robot's motion onset against the model for the commands; needs --recording). "
    "Default: 0, with --recording auto.", metavar="S|auto")]
WindowOpt = Annotated[float, typer.Option(
    "--window", help="Smoothing window [s] (0: per-frame poses).")]
FpsOpt = Annotated[float | None, typer.Option(
    "--fps", help="Frame rate overriding the video's timestamps [1/s].")]
MinFoundOpt = Annotated[float, typer.Option(
    "--min-found", help="Refuse when the robot's marker is in fewer frames (0..1).")]


def command(
    video: VideoArg,
    camera: CameraOpt,
    scene: SceneOpt,
    out: PoseOutOpt,
    recording: RecordingOpt = None,
    video_start: VideoStartOpt = None,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    window_s: WindowOpt = 0.2,
    fps: FpsOpt = None,
    min_found: MinFoundOpt = 0.2,
    as_json: JsonOpt = False,
) -> None:
    """Measure the robot's pose per frame: static camera from the floor markers over the whole
    video, the robot's marker on its known plane, smoothed without lag."""
    from ..io.recording import read_recording
    from ..vision.camera import load_camera
    from ..vision.pose import PoseOptions
    from ..vision.scene import load_scene
    from ._options import refuse_overwriting

    start_auto, start_s = _parse_video_start(video_start, recording)
    # Refuse before the (long) measurement: writing over an input would lose it.
    refuse_overwriting([(video, "the video being measured"), (camera, "the camera (--camera)"),
                        (scene, "the scene (--scene)"),
                        (recording, "the recording given with --recording", True)],
                       [(out, "--out", True)])
    cam = load_camera(camera)
    scn = load_scene(scene)
    rec = read_recording(recording) if recording is not None else None
    m = _measure_with_progress(video, cam, scn, PoseOptions(window_s=window_s, fps=fps,
                                                            min_found=min_found))
    for w in m.warnings:
        typer.echo(f"warning: {w}", err=True)
    method = "given"
    if start_auto:
        assert rec is not None
        start_s = _motion_onset_start(m, rec, calibration, robot, recording, video)
        method = "auto: the robot's motion onset (1 cm) against the model for the commands"
    summary = {**m.summary, "video_start_s": round(start_s, 6), "video_start_method": method}
    _write(m, rec, summary, video, recording, out, start_s, method)
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
        return
    cp = summary["camera_pose"]
    typer.echo(f"{summary['frames']} frames, robot found in {100 * summary['found_share']:.1f} %;"
               f" camera at {cp['position_m']} m, tilt {cp['tilt_deg']:.1f} deg, floor markers "
               f"reproject {summary['camera_reprojection_rms_px']:.3f} px RMS; video start "
               f"{start_s:.3f} s ({method}) -> {out}")


def _write(m, rec, summary: dict, video: Path, recording: Path | None, out: Path,
           start_s: float, method: str) -> None:
    """The recording with its pose columns filled, or the poses alone (with a sidecar);
    ``summary`` gets what was written."""
    from ..io.pose_track import fill_pose
    from ..io.recording import write_metadata, write_recording
    from ..vision.pose import write_pose_csv

    if rec is not None:
        filled = fill_pose(rec, m.t_s, m.pose, start_s, {
            "pose_source": f"measure-pose {video}", "video_start_s": start_s,
            "video_start_method": method, "pose_measurement": summary},
            track=f"{video}: the video", recording=str(recording),
            offset_option="--video-start-s")
        with_pose = int(sum(1 for row in filled.pose if all(v == v for v in row)))
        write_recording(filled, out)
        summary["out"] = str(out)
        summary["recording_rows_with_pose"] = with_pose
    else:
        write_pose_csv(out, m.t_s + start_s, m.pose)
        write_metadata(out, summary)
        summary["out"] = str(out)


def _parse_video_start(video_start: str | None, recording: Path | None) -> tuple[bool, float]:
    """``(found from the motion onset?, the video's start [s] when given)``."""
    import math

    from ..errors import ConfigError

    if video_start is None:
        return recording is not None, 0.0
    if video_start.strip().lower() == "auto":
        if recording is None:
            raise ConfigError("--video-start-s auto needs --recording (the commands to find the "
                              "robot's motion onset against)")
        return True, 0.0
    try:
        start_s = float(video_start)
    except ValueError:
        start_s = math.nan
    if not math.isfinite(start_s):
        raise ConfigError(f"--video-start-s must be a number of seconds or auto, got "
                          f"{video_start!r}")
    return False, start_s


def _measure_with_progress(video: Path, cam, scn, opts):
    """:func:`~mecanum_hil.vision.pose.measure_pose` behind a frame-count bar on stderr (only
    on a terminal: elsewhere the bar's empty line would precede every warning and error)."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn

    from ..vision.pose import measure_pose

    console = Console(stderr=True)
    with Progress(TextColumn("measuring pose"), BarColumn(),
                  TextColumn("{task.completed}/{task.total} frames"),
                  console=console, transient=True, disable=not console.is_terminal) as bar:
        task = bar.add_task("measure", total=None)
        return measure_pose(video, cam, scn, opts,
                            progress=lambda d, t: bar.update(task, completed=d, total=t or None))


def _motion_onset_start(m, rec, calibration: str, robot: str, recording: Path | None,
                        video: Path) -> float:
    """The video's start on the recording's clock [s]: where the measured motion begins
    against the model's prediction for the recorded commands."""
    from ..io.pose_track import onset_offset
    from ..model import load_calibration, load_robot_profile
    from ..prediction import predict

    model = predict(rec, load_calibration(calibration), load_robot_profile(robot),
                    source=str(recording))
    return onset_offset(m.t_s, m.pose, model.t_s, model.pose, source=str(video))
