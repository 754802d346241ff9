"""``mecanum-hil batch``: fit, diagnose, shadow-replay or measure a fleet's archive on Dask."""


from pathlib import Path
from typing import Annotated

import typer

from ._options import JsonOpt, RobotOpt

_STAGES = ("fit", "diagnose", "shadow", "measure-video")

StageArg = Annotated[str, typer.Argument(
    help="fit, diagnose (fit then diagnose), shadow (replay each recording) or "
         "measure-video (each video).", metavar="fit|diagnose|shadow|measure-video")]
ArchiveArg = Annotated[str, typer.Argument(
    help="Folder or fsspec URL (file://, s3://...); each first-level folder is a robot.",
    metavar="ARCHIVE")]
ResultsOpt = Annotated[Path, typer.Option(
    "--out", "-o", help="Results table: .parquet or .csv (one row per group).",
    metavar="RESULTS")]
SchedulerOpt = Annotated[str | None, typer.Option(
    "--scheduler", help="An existing Dask cluster (tcp://HOST:PORT); default: a local "
    "cluster on this machine.", metavar="tcp://HOST:PORT")]
WorkersOpt = Annotated[int | None, typer.Option(
    "--workers", min=1, help="Local cluster: worker processes, one thread each "
    "(default: the cores).")]
GroupByOpt = Annotated[str | None, typer.Option(
    "--group-by", help="Robot = this path level (1 = first-level folder, the default) or "
    "this sidecar key (dotted for nested).", metavar="LEVEL|KEY")]
PeriodOpt = Annotated[str | None, typer.Option(
    "--period", help="Also group per day or week (UTC; sidecar started_utc, else the "
    "file's modification time).", metavar="day|week")]
PeriodLevelOpt = Annotated[int | None, typer.Option(
    "--period-level", min=0, help="Also group per period named by this path level's folder "
    "(robot/DAY/run.csv: 2; 0: the ARCHIVE folder's own name); no sidecar is read.",
    metavar="LEVEL")]
BatchCalibrationOpt = Annotated[str, typer.Option(
    "--calibration", "-c", metavar="CAL",
    help="fit/diagnose: effects held (as for fit); shadow: the model to replay against. A "
    "shipped name, a file, an fsspec URL or a template such as 'cals/{group}.toml' "
    "({group}, {period}).")]
MethodOpt = Annotated[str, typer.Option(
    "--method", "-m", help="fit/diagnose: lsq or paper-grid.")]
CandidatesOpt = Annotated[str | None, typer.Option(
    "--candidates", help="diagnose: comma-separated effects to consider.")]
NoiseRpmOpt = Annotated[float | None, typer.Option(
    "--noise-rpm", help="shadow: wheel noise (1 sigma) [rpm]; default: estimated.")]
DriftOpt = Annotated[float, typer.Option(
    "--drift", help="shadow: CUSUM allowance k [noise sigmas].")]
ThresholdOpt = Annotated[float, typer.Option(
    "--threshold", help="shadow: CUSUM decision threshold h [noise sigmas].")]
WarmupOpt = Annotated[float, typer.Option(
    "--warmup", help="shadow: noise estimation window [s].")]
WheelOpt = Annotated[int, typer.Option(
    "--wheel", min=1, max=4, help="measure-video: wheel column to fill.")]
RoiOpt = Annotated[list[str] | None, typer.Option(
    "--roi", help="measure-video: search region [N:]x,y,w,h [px].",
    metavar="[N:]X,Y,W,H")]
MarkerOpt = Annotated[str, typer.Option(
    "--marker", help="measure-video: auto or aruco.")]
FpsOpt = Annotated[float | None, typer.Option(
    "--fps", help="measure-video: frame rate overriding the timestamps [1/s].")]
MinFoundOpt = Annotated[float, typer.Option(
    "--min-found", help="measure-video: smallest share of frames with the marker.")]
WriteOpt = Annotated[str | None, typer.Option(
    "--write", help="Folder or fsspec URL for each group's output: fit/diagnose "
    "GROUP.toml (GROUP/PERIOD.toml with --period), measure-video the measured "
    "recordings.", metavar="DIR")]
NoResumeOpt = Annotated[bool, typer.Option(
    "--no-resume", help="Run every group, even those whose inputs did not change.")]
DriftThresholdOpt = Annotated[float, typer.Option(
    "--drift-threshold", help="Smallest coefficient change flagged as drift (also outside "
    "the 95 % intervals) [%].")]


def command(
    stage: StageArg,
    archive: ArchiveArg,
    out: ResultsOpt,
    scheduler: SchedulerOpt = None,
    workers: WorkersOpt = None,
    group_by: GroupByOpt = None,
    period: PeriodOpt = None,
    period_level: PeriodLevelOpt = None,
    calibration: BatchCalibrationOpt = "paper",
    robot: RobotOpt = "tdam-stm",
    method: MethodOpt = "lsq",
    candidates: CandidatesOpt = None,
    noise_rpm: NoiseRpmOpt = None,
    drift: DriftOpt = 1.0,
    threshold: ThresholdOpt = 10.0,
    warmup: WarmupOpt = 2.0,
    wheel: WheelOpt = 1,
    roi: RoiOpt = None,
    marker: MarkerOpt = "auto",
    fps: FpsOpt = None,
    min_found: MinFoundOpt = 0.5,
    write: WriteOpt = None,
    no_resume: NoResumeOpt = False,
    drift_threshold: DriftThresholdOpt = 5.0,
    json_out: JsonOpt = False,
) -> None:
    """Run a stage over a fleet's archive on Dask: one task per robot (and period).

    Writes one table row per group (coefficients with intervals, effects, RMSE, alarms, drift
    against the robot's previous period, error). A bad recording or group fails alone, in its
    row; a re-run skips groups whose inputs did not change.
    """

    # OpenBLAS on one thread: mecanum_hil/__init__.py set it before numpy loaded (workers get
    # mecanum_hil._cores.SINGLE_THREAD_ENV from the cluster)
    from ..fleet.runner import BatchSettings

    _check(stage, period, method, marker, scheduler, workers, drift_threshold, fps)
    options = _stage_options(stage, method=method, candidates=candidates, drift=drift,
                             threshold=threshold, warmup=warmup, noise_rpm=noise_rpm,
                             wheel=wheel, roi=roi, marker=marker, fps=fps, min_found=min_found)
    settings = BatchSettings(
        command=stage, archive=archive, out=out, group_by=group_by, period=period,
        period_level=period_level,
        scheduler=scheduler, workers=workers, calibration=calibration, robot=robot,
        options=options, write_to=write, resume=not no_resume,
        drift_min_relative=drift_threshold / 100.0)
    _report(_run_with_progress(settings, quiet=json_out), json_out)


def _check(stage, period, method, marker, scheduler, workers, drift_threshold, fps) -> None:
    """One-line errors for option values batch does not take, before any work."""
    from ..errors import ConfigError

    if stage not in _STAGES:
        raise ConfigError(f"batch runs {', '.join(_STAGES)}; got {stage!r}")
    if period is not None and period not in ("day", "week"):
        raise ConfigError(f"--period must be day or week, got {period!r}")
    if method not in ("lsq", "paper-grid"):
        raise ConfigError(f"--method must be lsq or paper-grid, got {method!r}")
    if marker not in ("auto", "aruco"):
        raise ConfigError(f"--marker must be auto or aruco, got {marker!r}")
    if scheduler is not None and workers is not None:
        raise ConfigError("--workers sizes the local cluster; it does not go with --scheduler")
    if not (drift_threshold >= 0 and drift_threshold < float("inf")):
        raise ConfigError(f"--drift-threshold must be a finite percentage >= 0, got "
                          f"{drift_threshold}")
    if stage == "measure-video":
        from ..vision.video import check_fps

        check_fps(fps)


def _stage_options(stage: str, *, method, candidates, drift, threshold, warmup, noise_rpm,
                   wheel, roi, marker, fps, min_found) -> dict:
    """The options of ``stage`` that go to each group's task."""
    options: dict = {}
    if stage in ("fit", "diagnose"):
        options["method"] = method
    if stage == "diagnose" and candidates:
        options["candidates"] = [c.strip() for c in candidates.split(",") if c.strip()]
    if stage == "shadow":
        options["config"] = {"drift_k": drift, "threshold_h": threshold, "warmup_s": warmup,
                             "noise_rpm": noise_rpm}
    if stage == "measure-video":
        options["video"] = {"wheel": wheel, "roi": list(roi or []), "marker": marker,
                            "fps": fps, "min_found": min_found}
    return options


def _report(outcome, json_out: bool) -> None:
    """Print the outcome (a line per count, or JSON); every group failed: a one-line error."""
    import json
    import sys

    from ..errors import ConfigError

    c = outcome.counts
    drifted = sorted({r["group"] for r in outcome.rows if r.get("drifted")})
    alarmed = sorted({r["group"] for r in outcome.rows if (r.get("alarms") or 0) > 0})
    # this run's failures, also those whose earlier ok row the table keeps
    failed = list(outcome.failures)
    kept = sum(1 for r in failed if r.get("kept_earlier"))
    partial = [r for r in outcome.rows if r["status"] == "partial"]
    # every group failed: no result at all, whatever the table says (exit 0 read as success)
    all_failed = c.total > 0 and c.failed == c.total
    if json_out:
        typer.echo(json.dumps({
            "results": str(outcome.results), "groups": c.total, "done": c.done,
            "failed": c.failed, "kept_earlier": kept, "unchanged": c.unchanged,
            "partial": len(partial), "drifted": drifted, "alarms": alarmed,
            "dashboard": outcome.dashboard, "wall_s": outcome.wall_s}))
        if all_failed:
            raise ConfigError(_all_failed(failed, outcome.results))
        return
    typer.echo(f"{c.total} group(s): {c.done} run, {c.unchanged} unchanged (skipped), "
               f"{c.failed} failed, {len(partial)} with inputs left out; "
               f"{outcome.wall_s:.1f} s")
    if drifted:
        typer.echo(f"drifted: {', '.join(drifted)}")
    if alarmed:
        typer.echo(f"alarms: {', '.join(alarmed)}")
    for r in failed + partial:
        note = " (the table keeps its earlier row)" if r.get("kept_earlier") else ""
        print(f"warning: {r['group']} {r['period'] or ''}".rstrip() + f": {r['error']}{note}",
              file=sys.stderr)
    typer.echo(f"wrote {outcome.results}")
    if all_failed:
        raise ConfigError(_all_failed(failed, outcome.results))


def _all_failed(failed, results: Path) -> str:
    first = failed[0]
    kept = sum(1 for r in failed if r.get("kept_earlier"))
    where = (f"each group's error is in {results}" if not kept else
             f"{results} keeps the earlier rows of {kept} of them")
    return (f"every group failed ({len(failed)}); first, {first['group']}: {first['error']} "
            f"({where})")


def _run_with_progress(settings, quiet: bool):
    """Run the batch with a progress bar on stderr (done / failed / skipped / remaining)."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..fleet.runner import run_batch

    console = Console(stderr=True)
    columns = (TextColumn("batch {task.fields[stage]}"), BarColumn(),
               TextColumn("{task.fields[text]}"), TimeElapsedColumn())
    # the bar on a terminal only: in a log its last state would precede the warnings and errors
    with Progress(*columns, console=console, disable=quiet or not console.is_terminal,
                  transient=False) as bar:
        task = bar.add_task("batch", total=None, stage=settings.command, text="planning")

        def progress(c) -> None:
            bar.update(task, total=c.total, completed=c.total - c.remaining,
                       text=f"{c.done} done, {c.failed} failed, {c.unchanged} unchanged, "
                            f"{c.remaining} remaining")

        def echo(line: str) -> None:
            if not quiet:
                bar.console.print(line, markup=False, highlight=False)

        return run_batch(settings, progress=progress, echo=echo)
