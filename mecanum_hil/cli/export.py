"""``mecanum-hil export``: a recording as MCAP for Foxglove and PlotJuggler.

Commands, measured wheel speeds and pose, and optionally the model's prediction
(``--calibration``) and shadow mode's events (the recording's ``REC.shadow.jsonl``, or
``--events``) as log messages. ``mecanum-hil import RUN.mcap`` gives the recording back.
"""


from pathlib import Path
from typing import Annotated

import typer

from ._options import RobotOpt


def command(
    recording: Annotated[Path, typer.Argument(help="Recording (CSV) to export.",
                                              metavar="REC.csv")],
    out: Annotated[Path, typer.Option("--out", "-o", help="MCAP file to write.",
                                      metavar="RUN.mcap")],
    calibration: Annotated[str | None, typer.Option(
        "--calibration", "-c", metavar="CAL", help="Also the model's prediction for the "
        "recording's commands: a shipped name (paper) or a TOML file.")] = None,
    robot: RobotOpt = "tdam-stm",
    events: Annotated[Path | None, typer.Option(
        "--events", help="Shadow-mode event log whose events become log messages (default: "
        "REC.shadow.jsonl when it exists).", metavar="EVENTS.jsonl")] = None,
    no_events: Annotated[bool, typer.Option("--no-events", help="Export no events.")] = False,
) -> None:
    """Write a recording (and the model's prediction, and shadow events) as MCAP."""
    import numpy as np

    from ..errors import ConfigError, UsageError
    from ..io.mcap_export import export_mcap
    from ..io.recording import read_recording
    from ..monitor.eventlog import event_log_path
    from ..monitor.foxglove import read_event_log
    from ._options import refuse_overwriting

    if events is not None and no_events:
        raise UsageError("give --events or --no-events, not both")
    log_path = None if no_events else (events or event_log_path(recording))
    if log_path is not None and events is None and not log_path.exists():
        log_path = None  # the default log is optional
    refuse_overwriting([(recording, "the recording", True), (log_path, "the event log")],
                       [(out, "--out")])
    rec = read_recording(recording)
    predicted = None
    if calibration is not None:
        from ..model import load_calibration, load_robot_profile
        from ..prediction import predict

        known = np.flatnonzero(np.isfinite(rec.commands).all(axis=1))
        if known.size == 0:
            raise ConfigError(f"{recording}: no row has all three commands: nothing to predict")
        # rows before the first known command (a listener joining late) get no prediction
        part = predict(rec.select(slice(int(known[0]), None)), load_calibration(calibration),
                       load_robot_profile(robot), source=str(recording))
        pad = int(known[0])
        predicted = part.with_values(
            t_s=rec.t_s,
            wheel_rpm=np.vstack([np.full((pad, 4), np.nan), part.wheel_rpm]),
            pose=np.vstack([np.full((pad, 3), np.nan), part.pose]),
            commands=rec.commands, extra={})
    logs = read_event_log(log_path) if log_path is not None else []
    summary = export_mcap(rec, out, predicted, logs, source=str(recording))
    total = sum(summary.counts.values())
    typer.echo(f"wrote {summary.path} ({total} messages: "
               + ", ".join(f"{t} {n}" for t, n in summary.counts.items()) + ")")
