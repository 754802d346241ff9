"""``mecanum-hil simulate``: the model's prediction for a recording's commands or a profile."""


from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, OutOpt, RobotOpt


def command(
    out: OutOpt,
    commands: Annotated[Path | None, typer.Option(
        "--commands", help="Recording whose command columns (and t_s) drive the model.")] = None,
    profile: Annotated[str | None, typer.Option(
        "--profile", help="Built-in profile (paper-step-60, ...) or profile TOML file.")] = None,
    rate_hz: Annotated[float, typer.Option(
        "--rate", help="Sample rate for --profile [Hz].")] = 100.0,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    plot: Annotated[Path | None, typer.Option("--plot", help="Also write a PNG plot.")] = None,
) -> None:
    """Write the model's prediction as a recording with the same t_s and commands."""
    from ..io.recording import empty_like_times, read_recording, write_recording
    from ..model import load_calibration, load_robot_profile
    from ..prediction import predict
    from ..profiles import resolve_profile
    from ._options import refuse_overwriting, shipped_or_file

    refuse_overwriting([(commands, "the --commands recording", True),
                        (shipped_or_file(calibration), "the calibration")],
                       [(out, "--out", True), (plot, "--plot")])
    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    if commands is not None:
        rec = read_recording(commands)
        source = str(commands)
    else:
        prof = resolve_profile(profile)
        t, cmd = prof.sample(rate_hz)
        rec = empty_like_times(t).with_values(commands=cmd)
        source = f"profile {prof.name}"
    _warn_beyond_limit(rob, rec.commands[:-1] if len(rec) > 1 else rec.commands, source)
    pred = predict(rec, cal, rob, source=source)
    write_recording(pred, out)
    typer.echo(f"wrote {out} ({len(pred)} samples, {pred.t_s[-1] - pred.t_s[0]:.3f} s)")
    if plot is not None:
        from ..plots import plot_recordings

        plot_recordings({"model": pred}, plot, title=f"model prediction: {source}")
        typer.echo(f"wrote {plot}")


def _warn_beyond_limit(robot, commands, source: str) -> None:
    """Commands beyond the robot's limit: one warning line, and the simulation goes on.

    The limit protects a robot from what is sent to it; a simulation sends nothing, and a
    recording brought from elsewhere may well exceed the profile given. Commands that are not
    finite numbers still stop it (the model cannot run them).
    """
    import warnings

    import numpy as np

    from ..errors import LimitError, MecanumHILWarning

    try:
        robot.check_commands(commands, source)
    except LimitError as err:
        if not np.isfinite(np.asarray(commands, dtype=float)).all():
            raise
        warnings.warn(f"{err}; simulated all the same (a simulation sends nothing to a robot)",
                      MecanumHILWarning, stacklevel=2)
