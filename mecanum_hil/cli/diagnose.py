"""``mecanum-hil diagnose``: name the physical effects the model lacks, add them, show the gap."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, RobotOpt


def command(
    recordings: Annotated[list[Path], typer.Argument(
        help="Recordings (CSV) with commands and measured wheel speeds (pose where measured); "
             "at least two.", metavar="REC.csv...")],
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Write the extended calibration (TOML) here.",
        metavar="CAL2.toml")] = None,
    report: Annotated[Path | None, typer.Option(
        "--report", help="Folder for the report (report.md and PNG plots).",
        metavar="DIR")] = None,
    candidates: Annotated[str | None, typer.Option(
        "--candidates", help="Comma-separated effects to consider (default: the whole library: "
                             "dead_time, saturation, rate_limit, deadband, wheel_gain, slip).")
    ] = None,
    json_out: JsonOpt = False,
) -> None:
    """Find where model and recordings disagree, name the missing effects, refit, show the gap.

    Each effect of the library is fitted together with A, B, C and compared on held-out
    recordings; the best is added only if it explains a significant part of the gap, then the
    next round. Structured residual that no effect explains is reported as unexplained.
    """
    import json

    from ..identify.diagnose import CANDIDATES, diagnose
    from ..io.timing import read_for_analysis
    from ..model import load_calibration, load_robot_profile, save_calibration

    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    recs = [read_for_analysis(p) for p in recordings]
    names = [p.stem for p in recordings]
    if len(set(names)) != len(names):
        names = [str(p) for p in recordings]
    pool = CANDIDATES if candidates is None else tuple(
        c.strip() for c in candidates.split(",") if c.strip())
    echo = None if json_out else typer.echo
    diag = diagnose(recs, cal, rob, names=names, candidates=pool, echo=echo)
    if out is not None:
        save_calibration(diag.calibration, out,
                         f"extended by mecanum-hil diagnose from {calibration} on "
                         f"{', '.join(names)}")
    if report is not None:
        from ..identify.diagnose_report import write_report

        write_report(diag, recs, report, rob)
    if json_out:
        typer.echo(json.dumps(diag.to_json()))
        return
    named = ", ".join(f"{s.effect} {s.parameters}" for s in diag.steps) or "nothing missing"
    typer.echo(f"named: {named}")
    typer.echo(f"wheel RMSE {diag.rmse_initial:.4g} -> {diag.rmse_final:.4g} rpm"
               + ("; structured residual remains that no effect explains (unexplained)"
                  if diag.unexplained else ""))
    if out is not None:
        typer.echo(f"wrote {out}")
    if report is not None:
        typer.echo(f"wrote {report / 'report.md'}")
