"""``mecanum-hil fleet-report``: which robots drifted and how, from a batch's results table."""


from pathlib import Path
from typing import Annotated

import typer


def command(
    results: Annotated[list[Path], typer.Argument(
        help="Results tables of mecanum-hil batch (.parquet or .csv); several (e.g. one per "
             "day) are joined and the drift recomputed across them.", metavar="RESULTS...")],
    out: Annotated[Path, typer.Option(
        "--out", "-o", help="Folder for summary.md and the PNG plots.", metavar="DIR")],
    drift_threshold: Annotated[float | None, typer.Option(
        "--drift-threshold", help="Recompute the drift with this smallest coefficient change "
        "[%] (default: as the batch wrote it; 5 when joining tables).")] = None,
) -> None:
    """Write drift plots (PNG) and a Markdown summary of a fleet's batch results."""
    import math

    from ..errors import ConfigError
    from ..fleet.report import write_report
    from ..fleet.results import (
        DRIFT_MIN_RELATIVE,
        REPORT_COLUMNS,
        add_drift,
        read_results,
        row_key,
    )

    if drift_threshold is not None and not (math.isfinite(drift_threshold)
                                            and drift_threshold >= 0):
        raise ConfigError(f"--drift-threshold must be a finite percentage >= 0, got "
                          f"{drift_threshold}")
    if out.exists() and not out.is_dir():
        given = any(p.exists() and out.samefile(p) for p in results)
        raise ConfigError(f"{out}: --out is a folder for summary.md and the plots, and this is "
                          + ("the results table given" if given else "a file"))
    joined: dict = {}
    for path in results:
        rows_read = read_results(path, require=REPORT_COLUMNS)  # a cut column: refused
        if not rows_read:
            raise ConfigError(f"{path}: no rows: not a results table of mecanum-hil batch, or "
                              "one cut before its first row")
        for row in rows_read:
            joined[row_key(row)] = row  # a later table's row replaces an earlier one's
    rows = list(joined.values())
    threshold = None if drift_threshold is None else drift_threshold / 100.0
    if threshold is None and len(results) > 1:
        threshold = DRIFT_MIN_RELATIVE
    if threshold is not None:
        rows = add_drift(rows, threshold)
    written = write_report(rows, out, source=", ".join(p.name for p in results))
    drifted = sorted({r["group"] for r in rows if r["drifted"]})
    typer.echo(f"{len(rows)} row(s); drifted: {', '.join(drifted) or 'none'}")
    for path in written.values():
        typer.echo(f"wrote {path}")
