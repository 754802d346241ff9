"""``mecanum-hil import``: a foreign log (text, rosbag, CAN log, motion capture) as a recording.

One command for every format (``mecanum_hil.importers``); each format's options are declared
here and passed on only when the user gave them, so a format refuses an option it does not take.
"""


from pathlib import Path
from typing import Annotated

import typer

#: Rows that ``--dry-run`` prints.
DRY_RUN_ROWS = 10


SourceArg = Annotated[Path, typer.Argument(help="The log to import (a file or a bag directory).",
                                           metavar="SOURCE")]
ImportOutOpt = Annotated[Path | None, typer.Option(
    "--out", "-o", help="Recording (CSV, with its JSON sidecar) to write.")]
FormatOpt = Annotated[str, typer.Option(
    "--format", "-f", help="auto (detect by content) or a format name: text, ...")]
MapOpt = Annotated[Path | None, typer.Option(
    "--map", help="MAP.toml: which source column is which recording column, in which unit "
    "(docs/formats-import.md).", metavar="MAP.toml")]
DryRunOpt = Annotated[bool, typer.Option(
    "--dry-run", help="Print the first rows as they would be written; write nothing.")]
BagCmdTopicOpt = Annotated[str | None, typer.Option(
    "--cmd-topic", help="rosbag: Twist or TwistStamped commands (default /cmd_vel).")]
BagJointTopicOpt = Annotated[str | None, typer.Option(
    "--joint-topic", help="rosbag: JointState wheel velocities (default /joint_states).")]
BagJointsOpt = Annotated[str | None, typer.Option(
    "--joints", metavar="FL,FR,RL,RR", help="rosbag: joint names of wheels 1 FL, 2 FR, "
    "3 RL, 4 RR (default: detected by name).")]
BagWheelSignsOpt = Annotated[str | None, typer.Option(
    "--wheel-signs", metavar="S1,S2,S3,S4", help="rosbag: +1/-1 per wheel 1..4, -1 for a "
    "joint whose positive axis turns the wheel backwards.")]
BagOdomTopicOpt = Annotated[str | None, typer.Option(
    "--odom-topic", help="rosbag: Odometry giving the pose (optional).")]
BagRobotOpt = Annotated[str | None, typer.Option(
    "--robot", metavar="ROBOT", help="rosbag: robot profile whose wheel radius turns m/s "
    "into wheel rpm (default tdam-stm).")]
DbcOpt = Annotated[Path | None, typer.Option(
    "--dbc", metavar="DBC", help="canlog: the DBC decoding the frames (default: "
    "drivers/mecanum_hil.dbc; with your own, --map says which signal is which column).")]
MocapRecordingOpt = Annotated[Path | None, typer.Option(
    "--recording", metavar="REC.csv", help="mocap: fill this recording's pose columns "
    "(resampled to its times, never across an occlusion).")]
StartOpt = Annotated[str | None, typer.Option(
    "--start-s", metavar="S|auto", help="mocap: recording time of the capture's first "
    "sample [s], or auto (motion onset against the commands; the default with "
    "--recording).")]


def command(
    source: SourceArg,
    out: ImportOutOpt = None,
    fmt: FormatOpt = "auto",
    map_path: MapOpt = None,
    dry_run: DryRunOpt = False,
    cmd_topic: BagCmdTopicOpt = None,
    joint_topic: BagJointTopicOpt = None,
    joints: BagJointsOpt = None,
    wheel_signs: BagWheelSignsOpt = None,
    odom_topic: BagOdomTopicOpt = None,
    robot: BagRobotOpt = None,
    dbc_path: DbcOpt = None,
    recording: MocapRecordingOpt = None,
    start_s: StartOpt = None,
) -> None:
    """Import a log into a recording (CSV + JSON sidecar)."""
    from ..importers import import_source

    _check_outputs(source, out, dry_run, map_path, dbc_path, recording)
    options = {key: value for key, value in (
        ("map_path", map_path), ("cmd_topic", cmd_topic), ("joint_topic", joint_topic),
        ("joints", joints), ("wheel_signs", wheel_signs), ("odom_topic", odom_topic),
        ("dbc_path", dbc_path), ("recording", recording), ("start_s", start_s))
        if value is not None}
    fmt = _with_robot(source, fmt, robot, options)
    _with_model_pose(fmt, options)
    res = _noted_radius(import_source(source, fmt, **options), robot, options)
    _write_or_show(res, out, dry_run)


def _check_outputs(source: Path, out: Path | None, dry_run: bool, map_path: Path | None,
                   dbc_path: Path | None, recording: Path | None) -> None:
    """An ``--out`` (unless a dry run) that overwrites none of the inputs."""
    from ..errors import UsageError
    from ._options import refuse_overwriting

    if out is None and not dry_run:
        raise UsageError("give --out REC.csv (or --dry-run)")
    if not dry_run:
        refuse_overwriting([(source, "the log"), (map_path, "the map"), (dbc_path, "the DBC"),
                            (recording, "the --recording", True)], [(out, "--out", True)])


def _noted_radius(res, robot: str | None, options: dict):
    """``res``, with a note where m/s became wheel rpm with a radius the user did not
    choose."""
    from ..importers import with_notes

    used = res.recording.metadata.get("import")
    if (robot is None and "wheel_radius_m" in options and isinstance(used, dict)
            and used.get("wheel_radius_m")):
        # m/s became wheel rpm with a radius the user did not choose: say which
        res = with_notes(res, f"speeds in m/s converted with the wheel radius "
                              f"{options['wheel_radius_m']:g} m of robot profile tdam-stm "
                              "(give --robot for your robot's)")
    return res


def _write_or_show(res, out: Path | None, dry_run: bool) -> None:
    """The import's notes as warnings; the recording written (or its first rows shown)."""
    import sys

    from ..io.recording import format_rows, write_recording

    rec = res.recording
    for note in res.notes:
        print(f"warning: {note}", file=sys.stderr)
    if dry_run:
        typer.echo(format_rows(rec, DRY_RUN_ROWS), nl=False)
        typer.echo(f"({len(rec)} rows; nothing written)")
        return
    write_recording(rec, out)
    span = float(rec.t_s[-1] - rec.t_s[0]) if len(rec) else 0.0
    typer.echo(f"wrote {out} ({len(rec)} samples, {span:.3f} s)")


def _with_robot(source: Path, fmt: str, robot: str | None, options: dict) -> str:
    """Resolve the format; give a format that converts speeds [m/s] the robot's wheel radius."""
    import inspect

    from ..errors import ConfigError
    from ..importers import detect_format, format_module

    name = detect_format(source, options.get("map_path")) if fmt == "auto" else fmt
    if "wheel_radius_m" in inspect.signature(format_module(name).read).parameters:
        from ..model import load_robot_profile

        options["wheel_radius_m"] = load_robot_profile(robot or "tdam-stm").wheel_radius_m
    elif robot is not None:
        raise ConfigError(f"format '{name}' does not take --robot")
    return name


def _with_model_pose(name: str, options: dict) -> None:
    """mocap with ``--recording`` and an automatic start: give the format the model's
    prediction for the recording's commands (calibration and robot from the map)."""
    import inspect

    from ..importers import format_module

    start = options.get("start_s")
    if ("model_pose" not in inspect.signature(format_module(name).read).parameters
            or options.get("recording") is None
            or (start is not None and str(start).strip().lower() != "auto")):
        return
    from ..importers.mocap import load_mocap_map
    from ..io.recording import read_recording
    from ..model import load_calibration, load_robot_profile
    from ..prediction import predict

    m = load_mocap_map(options.get("map_path"))
    rec = read_recording(options["recording"])
    model = predict(rec, load_calibration(m.calibration), load_robot_profile(m.robot),
                    source=str(options["recording"]))
    options["model_pose"] = (model.t_s, model.pose)
