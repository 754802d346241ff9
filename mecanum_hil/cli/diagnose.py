"""``mecanum-hil diagnose``: name the physical effects the model lacks, add them, show the gap."""

import math
from pathlib import Path
from typing import Annotated

import typer

from ._options import CalibrationOpt, JsonOpt, RobotOpt

RecordingsArg = Annotated[list[Path], typer.Argument(
    help="Recordings (CSV) with commands and measured wheel speeds (pose where measured); "
         "one is enough.", metavar="REC.csv...")]
ExtendedOutOpt = Annotated[Path | None, typer.Option(
    "--out", "-o", help="Write the extended calibration (TOML) here.",
    metavar="CAL2.toml")]
ReportOpt = Annotated[Path | None, typer.Option(
    "--report", help="Folder for the report (report.md and PNG plots).",
    metavar="DIR")]
CandidatesOpt = Annotated[str | None, typer.Option(
    "--candidates", help="Comma-separated effects to consider (default: the whole library: "
                         "dead_time, saturation, windup, rate_limit, deadband, wheel_gain, "
                         "controller_period, drive_lag, breakaway, friction, drive_deadband, "
                         "braking_limit, fast_decay, slip).")]
JobsOpt = Annotated[int | None, typer.Option(
    "--jobs", min=1, help="Processes that fit each round's candidates, this one included "
                          "(default: 2 where a second core is idle, else 1; the result is "
                          "the same).")]


def command(
    recordings: RecordingsArg,
    calibration: CalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    out: ExtendedOutOpt = None,
    report: ReportOpt = None,
    candidates: CandidatesOpt = None,
    jobs: JobsOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Find where model and recordings disagree, name the missing effects, refit, show the gap.

    Each effect of the library is fitted together with A, B, C and compared on held-out
    recordings (held-out time blocks when there is one recording); the best is kept if it
    lowers the held-out error significantly, then the next round. What remains is described by
    its shape and compared with a generic reference model of higher order.
    """
    import json

    from ..identify.diagnose import candidate_pool, diagnose
    from ..model import load_calibration, load_robot_profile
    from ._options import refuse_overwriting, shipped_or_file

    refuse_overwriting([*((p, "a recording", True) for p in recordings),
                        (shipped_or_file(calibration), "the calibration")], [(out, "--out")])
    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    recs, names = _read(recordings)
    pool = candidate_pool(None if candidates is None else candidates.split(","))
    echo = _progress_on_stderr if json_out else typer.echo
    diag = diagnose(recs, cal, rob, names=names, candidates=pool, echo=echo, jobs=jobs)
    _write(diag, recs, rob, out, report, f"extended by mecanum-hil diagnose from {calibration} "
           f"on {', '.join(names)}")
    if json_out:
        typer.echo(json.dumps(diag.to_json()))
        return
    _print(diag, out, report)


def _read(recordings: list[Path]):
    """``(the recordings, their names)``: file stems, or paths where two stems are alike."""
    from ..io.timing import read_for_analysis

    recs = [read_for_analysis(p) for p in recordings]
    names = [p.stem for p in recordings]
    if len(set(names)) != len(names):
        names = [str(p) for p in recordings]
    return recs, names


def _write(diag, recs, rob, out: Path | None, report: Path | None, note: str) -> None:
    """The extended calibration (``--out``) and the report (``--report``), where asked for."""
    from ..model import save_calibration

    if out is not None:
        save_calibration(diag.calibration, out, note)
    if report is not None:
        from ..identify.diagnose_report import write_report

        write_report(diag, recs, report, rob)


def _print(diag, out: Path | None, report: Path | None) -> None:
    """The effects named, the gap before and after, the files written."""
    from ..identify.diagnose.reference import reference_comparison

    named = ", ".join(f"{s.effect} {s.parameters} ({_percent(diag.share(s))} of the gap)"
                      for s in diag.steps) or "nothing missing"
    typer.echo(f"named: {named}")
    _print_equivalents(diag)
    for entry in diag.to_json()["effects"]:
        if entry["effect"] == "slip" and entry["pose_rmse_before"]["position_m"] is not None:
            b, a = entry["pose_rmse_before"], entry["pose_rmse_after"]
            typer.echo(f"slip: pose RMSE {b['position_m']:.4g} m, {b['heading_deg']:.4g} deg "
                       f"-> {a['position_m']:.4g} m, {a['heading_deg']:.4g} deg")
    typer.echo(f"wheel RMSE {diag.rmse_initial:.4g} -> {diag.rmse_final:.4g} rpm"
               + ("; structured residual remains (unexplained)" if diag.unexplained else ""))
    if diag.shape is not None and diag.unexplained:
        typer.echo(f"what remains: {diag.shape.describe()}")
    typer.echo(f"reference model: wheel RMSE {diag.rmse_reference:.4g} rpm; "
               + reference_comparison(diag.rmse_baseline, diag.rmse_final, diag.rmse_reference))
    if out is not None:
        typer.echo(f"wrote {out}")
    if report is not None:
        typer.echo(f"wrote {report / 'report.md'}")


def _print_equivalents(diag) -> None:
    """For a drive lag named: the same wheel speeds as another A, B, C (or why none)."""
    for s in diag.steps:
        if s.equivalent_problem is not None:
            typer.echo(f"drive_lag: no equivalent model: degenerate ({s.equivalent_problem})")
        elif s.equivalent is not None:
            q = s.equivalent
            typer.echo(f"drive_lag: equally, a lag of {q['drive_lag_s']:.4g} s with A = "
                       f"{q['A']:.4g}, B = {q['B']:.4g}, C = {q['C']:.4g} (the same wheel "
                       "speeds: they cannot tell the drive's lag from the motor's time constant)")


def _percent(share: float) -> str:
    """A share [-] as a whole percentage, "n/a" when it cannot be computed."""
    return f"{100 * share:.0f} %" if math.isfinite(share) else "n/a"


def _progress_on_stderr(line: str) -> None:
    """With ``--json`` (stdout is the document): each round's start and outcome on stderr, so
    a diagnosis of many seconds shows it is alive."""
    text = line.strip()
    if text.startswith(("round ", "-> ")):
        typer.echo(f"diagnose: {text}", err=True)
