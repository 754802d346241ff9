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


def command(
    recordings: Annotated[list[Path], typer.Argument(
        help="Recording CSV files (any commands; wheel speeds from telemetry or video).",
        metavar="REC.csv...")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Calibration TOML to write.")],
    method: Annotated[str, typer.Option(
        "--method", "-m", help="lsq (continuous least squares) or paper-grid (the paper's "
        "three-pass grid search).")] = "lsq",
    calibration: Annotated[str, typer.Option(
        "--calibration", "-c", metavar="CAL",
        help="Calibration whose effects are held fixed during the fit (its A, B, C are "
        "replaced).")] = "paper",
    robot: RobotOpt = "tdam-stm",
    report: Annotated[Path | None, typer.Option(
        "--report", help="Report PNG (default: the --out path with .png).")] = None,
    no_report: Annotated[bool, typer.Option("--no-report", help="Write no report PNG.")] = False,
    a_grid: Annotated[str | None, typer.Option("--a-grid", help=f"A grid {_GRID_HELP}; "
                                               "default 0:2000:1.")] = None,
    b_grid: Annotated[str | None, typer.Option("--b-grid", help=f"B sweep {_GRID_HELP}; "
                                               "default 5.5:25.5:0.1.")] = None,
    c_grid: Annotated[str | None, typer.Option("--c-grid", help=f"C grid {_GRID_HELP}; "
                                               "default 0:2000:1.")] = None,
    b_start: Annotated[float | None, typer.Option(
        "--b-start", help="B held in the first pass (paper-grid only); default 15.5.")] = None,
    json_out: JsonOpt = False,
) -> None:
    """Estimate A, B, C from recordings; write a calibration TOML and a report PNG."""
    # OpenBLAS on one thread (docs/fit.md): mecanum_hil/__init__.py set it before numpy loaded
    import json
    import math
    import sys

    from ..errors import FitError
    from ..identify.files import fit_files
    from ..model import load_calibration, load_robot_profile
    from ._options import refuse_overwriting, shipped_or_file

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
    png = None if no_report else (report or out.with_suffix(".png"))
    refuse_overwriting([*((p, "a recording", True) for p in recordings),
                        (shipped_or_file(calibration), "the calibration")],
                       [(out, "--out"), (png, "--report")])
    rob = load_robot_profile(robot)
    cal = load_calibration(calibration)
    output = fit_files(recordings, out, rob, method, cal, png, **grid_options)
    res = output.result
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if json_out:
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
        typer.echo(json.dumps(doc))
        return
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
