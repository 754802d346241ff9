"""``mecanum-hil fit``: the wheel model's coefficients A, B, C from recordings."""


import math
from pathlib import Path
from typing import Annotated

import typer

from ._options import JsonOpt, RobotOpt

_GRID_HELP = "as FIRST:LAST:STEP (paper-grid only)"


def _grid(text: str | None, name: str):
    if text is None:
        return None
    from ..errors import FitError

    try:
        parts = tuple(float(v) for v in text.split(":"))
    except ValueError:
        parts = ()
    if len(parts) != 3 or not all(math.isfinite(v) for v in parts):
        raise FitError(f"--{name}-grid must be FIRST:LAST:STEP in finite numbers, got {text!r}")
    return parts


RecordingsArg = Annotated[list[Path], typer.Argument(
    help="Recording CSV files (any commands; wheel speeds from telemetry or video).",
    metavar="REC.csv...")]
CalOutOpt = Annotated[Path, typer.Option("--out", "-o", help="Calibration TOML to write.")]
MethodOpt = Annotated[str, typer.Option(
    "--method", "-m", help="lsq (continuous least squares) or paper-grid (the paper's "
    "three-pass grid search).")]
HeldCalibrationOpt = Annotated[str, typer.Option(
    "--calibration", "-c", metavar="CAL",
    help="Calibration whose effects are held fixed during the fit (its A, B, C are "
    "replaced).")]
ReportOpt = Annotated[Path | None, typer.Option(
    "--report", help="Report PNG (default: the --out path with .png).")]
NoReportOpt = Annotated[bool, typer.Option("--no-report", help="Write no report PNG.")]
AGridOpt = Annotated[str | None, typer.Option("--a-grid", help=f"A grid {_GRID_HELP}; "
                                              "default 0:2000:1.")]
BGridOpt = Annotated[str | None, typer.Option("--b-grid", help=f"B sweep {_GRID_HELP}; "
                                              "default 5.5:25.5:0.1.")]
CGridOpt = Annotated[str | None, typer.Option("--c-grid", help=f"C grid {_GRID_HELP}; "
                                              "default 0:2000:1.")]
BStartOpt = Annotated[float | None, typer.Option(
    "--b-start", help="B held in the first pass (paper-grid only); default 15.5.")]


def command(
    recordings: RecordingsArg,
    out: CalOutOpt,
    method: MethodOpt = "lsq",
    calibration: HeldCalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    report: ReportOpt = None,
    no_report: NoReportOpt = False,
    a_grid: AGridOpt = None,
    b_grid: BGridOpt = None,
    c_grid: CGridOpt = None,
    b_start: BStartOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Estimate A, B, C from recordings; write a calibration TOML and a report PNG."""
    # OpenBLAS on one thread (docs/fit.md): mecanum_hil/__init__.py set it before numpy loaded
    from ._options import refuse_overwriting, shipped_or_file

    grid_options = _grid_options(method, a_grid, b_grid, c_grid, b_start)
    png = None if no_report else (report or out.with_suffix(".png"))
    refuse_overwriting([*((p, "a recording", True) for p in recordings),
                        (shipped_or_file(calibration), "the calibration")],
                       [(out, "--out"), (png, "--report")])
    output = _fit(recordings, out, robot, method, calibration, png, grid_options)
    if json_out:
        typer.echo(_json(output.result))
        return
    _print(output)


def _grid_options(method: str, a_grid: str | None, b_grid: str | None, c_grid: str | None,
                  b_start: float | None) -> dict:
    """The paper-grid's options given (one-line errors for a method, grid or start it does
    not take)."""
    from ..errors import FitError

    if method not in ("lsq", "paper-grid"):
        raise FitError(f"--method must be lsq or paper-grid, got {method!r}")
    if b_start is not None and not (math.isfinite(b_start) and b_start >= 0):
        raise FitError(f"--b-start must be a finite number >= 0 [1/s], got {b_start:g}")
    grid_options = {k: v for k, v in (("a_grid", _grid(a_grid, "a")),
                                      ("b_grid", _grid(b_grid, "b")),
                                      ("c_grid", _grid(c_grid, "c")),
                                      ("b_start", b_start)) if v is not None}
    if grid_options and method != "paper-grid":
        raise FitError("--a-grid, --b-grid, --c-grid and --b-start apply to --method paper-grid")
    return grid_options


def _fit(recordings: list[Path], out: Path, robot: str, method: str, calibration: str,
         png: Path | None, grid_options: dict):
    """Fit and write the calibration (and report); its warnings on stderr."""
    import sys

    from ..identify.files import fit_files
    from ..model import load_calibration, load_robot_profile

    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    output = fit_files(recordings, out, rob, method, cal, png, **grid_options)
    for w in output.result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return output


def _json(res) -> str:
    """The fit as one JSON line (a number or interval that is not finite: null)."""
    import json

    def num(v: float):
        return float(v) if math.isfinite(v) else None

    c = res.calibration
    doc = {
        "A": c.A, "B": c.B, "C": c.C,
        "rmse_rpm": num(res.rmse_rpm), "fit_percent": num(res.fit_percent),
        # an interval the data cannot bound (NaN) is null, as one not computed
        "ci95": {k: [res.ci95[k][0], res.ci95[k][1]] if k in res.ci95
                 and all(map(math.isfinite, res.ci95[k])) else None for k in ("A", "B", "C")},
        "method": res.method,
    }
    return json.dumps(doc)


def _print(output) -> None:
    """The coefficients with their intervals, the fit, the files written."""
    res = output.result
    c = res.calibration
    for k in ("A", "B", "C"):
        lo, hi = res.ci95.get(k, (math.nan, math.nan))
        interval = f"95 % interval {lo:.6g} .. {hi:.6g}" if math.isfinite(lo + hi) else \
            "unidentifiable: the data cannot bound it"
        typer.echo(f"{k} = {getattr(c, k):.6g}   ({interval})")
    typer.echo(f"fit {res.fit_percent:.2f} %, RMSE {res.rmse_rpm:.4g} rpm over {res.n_samples} "
               f"wheel samples ({res.method})")
    typer.echo(f"wrote {output.calibration_path}")
    if output.report_path is not None:
        typer.echo(f"wrote {output.report_path}")
