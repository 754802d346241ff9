"""Run a batch on Dask: plan the groups, submit one task each, journal rows, write the table.

The client side holds only the list of files and the rows (a few hundred bytes each); the
recordings are read by the tasks on the workers. Rows are appended to a journal
(``RESULTS.journal.jsonl``, one JSON object per line, flushed) as they arrive, so an
interrupted batch loses nothing: the next run reads the table and the journal, and every group
whose content hash did not change is not run again. At the end the table is written
atomically and the journal removed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__
from .._cores import SINGLE_THREAD_ENV
from ..errors import ConfigError, MecanumHILError
from ..io.paths import check_folder_writable
from . import stages
from .archive import Group, group_files, open_archive
from .results import (
    REPORT_COLUMNS,
    add_drift,
    normalise,
    read_results,
    row_key,
    table_format,
    write_results,
)
from .tasks import COMMANDS, GroupSpec, run_group

#: Environment of the local cluster's worker processes: one core each, no nested thread pools
#: (OpenBLAS and numba threads on top of several workers oversubscribe a small machine).
WORKER_ENV = SINGLE_THREAD_ENV


@dataclass(frozen=True)
class BatchSettings:
    """What ``mecanum-hil batch`` was asked to do.

    Attributes
    ----------
    command : str
        ``fit``, ``diagnose``, ``shadow`` or ``measure-video``.
    archive : str
        Folder or fsspec URL.
    out : Path
        Results table (``.parquet`` or ``.csv``).
    group_by : str or None
        Path level or sidecar key (:func:`~.archive.group_files`).
    period : str or None
        ``day`` or ``week``.
    period_level : int or None
        The period is this path level's folder name (instead of ``period``).
    scheduler : str or None
        ``tcp://HOST:PORT`` of an existing cluster; None: a local cluster.
    workers : int or None
        Local cluster: worker processes (default: the machine's cores), one thread each.
    calibration : str
        Shipped name, file, fsspec URL, or a template with ``{group}``/``{period}``.
    robot : str
        Robot profile (shipped name or file).
    options : dict
        Stage options (``method``, ``candidates``, ``config``, ``video``).
    write_to : str or None
        Folder (or fsspec URL) for per-group outputs.
    resume : bool
        Skip groups whose content hash matches the existing table or journal.
    drift_min_relative : float
        Smallest relative coefficient change that counts as drift [-].
    connect_timeout_s : float
        How long to try reaching ``scheduler`` [s].
    """

    command: str
    archive: str
    out: Path
    group_by: str | None = None
    period: str | None = None
    period_level: int | None = None
    scheduler: str | None = None
    workers: int | None = None
    calibration: str = "paper"
    robot: str = "tdam-stm"
    options: dict[str, Any] = field(default_factory=dict)
    write_to: str | None = None
    resume: bool = True
    drift_min_relative: float = 0.05
    connect_timeout_s: float = 30.0


@dataclass
class Counts:
    """Progress of a batch (groups)."""

    total: int = 0
    done: int = 0
    failed: int = 0
    unchanged: int = 0

    @property
    def remaining(self) -> int:
        """Groups not finished yet."""
        return self.total - self.done - self.failed - self.unchanged


@dataclass(frozen=True)
class BatchOutcome:
    """What a batch did.

    Attributes
    ----------
    rows : list of dict
        The table as written.
    counts : Counts
    results : Path
    dashboard : str or None
        The Dask dashboard's address, when there was one.
    wall_s : float
        Time from the first submitted task to the last result [s].
    startup_s : float
        Time to plan the groups and reach the cluster [s].
    failures : list of dict
        The rows of the groups that failed in this run, including those whose earlier
        ``ok``/``partial`` row was kept in the table instead (``kept_earlier`` true).
    """

    rows: list[dict[str, Any]]
    counts: Counts
    results: Path
    dashboard: str | None
    wall_s: float
    startup_s: float
    failures: list[dict[str, Any]] = field(default_factory=list)


def journal_path(out: Path) -> Path:
    """The journal next to the results table."""
    return out.with_name(out.name + ".journal.jsonl")


def spec_key(command: str, group: str, period: str, inputs: Sequence[str]
             ) -> tuple[str, str, str]:
    """The results-table key of a task (:func:`~.results.row_key`)."""
    return row_key({"command": command, "group": group, "period": period,
                    "inputs": ";".join(inputs)})


def previous_rows(out: Path, command: str) -> dict[tuple[str, str, str], dict[str, Any]]:
    """Rows of an earlier run of the same batch (its table, then its journal), by key."""
    rows: dict[tuple[str, str, str], dict[str, Any]] = {}
    if out.exists():
        # a table whose columns were cut would hand its gaps on to the rows kept from it
        for r in read_results(out, require=REPORT_COLUMNS):
            rows[row_key(r)] = r
    jpath = journal_path(out)
    if jpath.exists():
        for line in jpath.read_text(encoding="utf-8").splitlines():
            try:
                r = normalise(json.loads(line))
            except ValueError:
                continue  # a line cut off by the interruption
            rows[row_key(r)] = r
    other = {r["command"] for r in rows.values()} - {command}
    if other:
        raise ConfigError(f"{out} holds results of batch {', '.join(sorted(other))}, not "
                          f"{command}: write to another table")
    return rows


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class _Calibrations:
    """Calibrations by reference, loaded once each (a template gives one per robot)."""

    def __init__(self) -> None:
        self._cache: dict[str, tuple[Any, str] | MecanumHILError] = {}

    def get(self, ref: str) -> tuple[Any, str]:
        if ref not in self._cache:
            try:
                self._cache[ref] = self._load(ref)
            except MecanumHILError as err:
                self._cache[ref] = err
        got = self._cache[ref]
        if isinstance(got, MecanumHILError):
            raise got
        return got

    @staticmethod
    def _load(ref: str) -> tuple[Any, str]:
        from ..io.resources import resolve
        from ..model import load_calibration

        if "://" not in ref:
            path = resolve("calibration", ref)
            return load_calibration(path), _digest(path.read_bytes())
        from . import require_extra

        fsspec = require_extra("fsspec")
        try:
            with fsspec.open(ref, "rb") as fh:
                data = fh.read()
        except (OSError, ValueError) as err:
            raise ConfigError(f"{ref}: cannot read the calibration: {err}") from err
        with tempfile.TemporaryDirectory() as tmp:
            local = Path(tmp) / "calibration.toml"
            local.write_bytes(data)
            cal = load_calibration(local)
        return cal, _digest(data)


#: The placeholders of a ``--calibration`` template.
CALIBRATION_PLACEHOLDERS = ("group", "period")


def calibration_ref(template: str, group: str, period: str) -> str:
    """``--calibration`` for a group: the template's ``{group}`` and ``{period}`` filled.

    Raises
    ------
    ConfigError
        An unknown placeholder or a stray brace, naming the known placeholders.
    """
    known = ", ".join("{" + p + "}" for p in CALIBRATION_PLACEHOLDERS)
    try:
        return template.format(group=group, period=period)
    except KeyError as err:
        raise ConfigError(f"--calibration {template!r}: unknown placeholder {{{err.args[0]}}} "
                          f"(known: {known})") from None
    except (IndexError, ValueError, AttributeError) as err:
        raise ConfigError(f"--calibration {template!r}: not a template ({err}; the known "
                          f"placeholders are {known}, a literal brace is written twice)"
                          ) from None


def refuse_reading_out(settings: BatchSettings) -> None:
    """One line when the results table would be written over a file the batch reads: a
    recording (or video) of a local archive, e.g. ``batch fit ARCH -o ARCH/robA/r1.csv``, or
    would become one: a new ``ARCH/robA/results.csv`` is read as a recording by the next run."""
    url = settings.archive
    if url.startswith("file://"):
        url = url[len("file://"):]
    elif "://" in url:
        return  # a remote archive: the local table cannot be one of its files
    out = Path(settings.out)
    try:
        root, target = Path(url).resolve(), out.resolve()
    except OSError:
        return
    if not target.is_relative_to(root) or target.name.startswith("."):
        return
    from .archive import RECORDING_SUFFIXES, VIDEO_SUFFIXES

    read = VIDEO_SUFFIXES if settings.command == "measure-video" else RECORDING_SUFFIXES
    if not target.name.lower().endswith(read + RECORDING_SUFFIXES):
        return
    if target.is_file():
        raise ConfigError(f"{out}: --out would overwrite an input of the archive "
                          f"({target.relative_to(root)}); write the results elsewhere")
    raise ConfigError(f"{out}: --out inside the archive would be read as one of its "
                      f"recordings by the next batch ({target.relative_to(root)}); write the "
                      "results elsewhere, or as .parquet")


#: Protocols of a Dask scheduler's address that ``--scheduler`` takes.
SCHEDULER_PROTOCOLS = ("tcp", "tls", "ws", "wss")


def check_scheduler(address: str) -> None:
    """One line for a ``--scheduler`` that is not ``PROTOCOL://HOST:PORT`` (or ``HOST:PORT``),
    before anything is planned or started (Dask's own error is a bare ValueError)."""
    protocol, sep, rest = address.partition("://")
    if not sep:
        protocol, rest = "tcp", address
    if rest.startswith("["):  # [IPv6]:PORT
        host, _, tail = rest[1:].partition("]")
        port = tail[1:] if tail.startswith(":") else ""
    else:
        host, _, port = rest.rpartition(":")
    if protocol not in SCHEDULER_PROTOCOLS or not host or "/" in host or \
            not (port.isascii() and port.isdigit() and 0 < int(port) < 65536):
        raise ConfigError(f"--scheduler {address!r}: not the address of a Dask scheduler; "
                          "give tcp://HOST:PORT (or tls://, ws://, wss://; HOST:PORT alone "
                          "is tcp), or leave it out for a local cluster")


def check_out(out: Path) -> None:
    """One line, before anything runs, when the results table (and its journal beside it)
    cannot be written: ``--out`` a folder, or in a folder that cannot be written (or made)."""
    out = Path(out)
    if out.is_dir():
        raise ConfigError(f"{out}: --out is a folder; give the results table's file name "
                          "(.parquet or .csv)")
    check_folder_writable(out.parent, f"--out {out}")


def check_write_to(write_to: str | None) -> None:
    """One line, before anything runs, when ``--write`` cannot take the groups' outputs: a
    file rather than a folder, a local folder that cannot be made or written, a URL whose
    protocol is unknown or whose store cannot be reached (a local folder is made by the
    tasks, when they write)."""
    if write_to is None:
        return
    what = f"--write {write_to}"
    local = write_to[len("file://"):] if write_to.startswith("file://") else \
        None if "://" in write_to else write_to
    if local is not None:
        folder = Path(local)
        if folder.exists() and not folder.is_dir():
            raise ConfigError(f"{what}: a file, not a folder for the groups' outputs")
        check_folder_writable(folder, what)
        return
    from . import require_extra

    core = require_extra("fsspec.core")
    try:
        fs, path = core.url_to_fs(write_to)
        if fs.isfile(path):
            raise ConfigError(f"{what}: a file, not a folder for the groups' outputs")
    except (ValueError, ImportError, OSError) as err:
        raise ConfigError(f"{what}: cannot use it: {err}") from err


def plan(settings: BatchSettings,
         previous: Mapping[tuple[str, str, str], Mapping[str, Any]] | None = None
         ) -> tuple[list[GroupSpec], Any]:
    """The archive's groups as task specs (nothing is run).

    Returns
    -------
    (specs, archive)
    """
    from ..io.resources import resolve
    from ..model import load_robot_profile

    if settings.command not in COMMANDS:
        raise ConfigError(f"batch command must be one of {', '.join(COMMANDS)}, got "
                          f"{settings.command!r}")
    calibration_ref(settings.calibration, "", "")  # a bad template: one line, before the work
    stages.check_options(settings.command, settings.options)
    cals = _Calibrations()
    if calibration_ref(settings.calibration, "g1", "p1") == \
            calibration_ref(settings.calibration, "g2", "p2"):
        # one calibration for every group: a bad one is a bad option, not a group's failure
        cals.get(calibration_ref(settings.calibration, "", ""))
    robot = load_robot_profile(settings.robot)
    robot_hash = _digest(resolve("drivers", settings.robot).read_bytes())
    kind = "videos" if settings.command == "measure-video" else "recordings"
    archive = open_archive(settings.archive, kind)
    level = settings.period_level
    if level and not any(len(f.rel.split("/")) > level for f in archive.files):
        raise ConfigError(f"--period-level {level}: no file of {settings.archive} is inside a "
                          f"level-{level} folder (e.g. {archive.files[0].rel})")
    groups: list[Group] = group_files(archive, settings.group_by, settings.period,
                                      per_file=settings.command == "measure-video",
                                      period_level=settings.period_level)
    specs = []
    for g in groups:
        error = g.error
        cal, cal_hash = None, ""
        if settings.command != "measure-video" or "{" not in settings.calibration:
            ref = calibration_ref(settings.calibration, g.group, g.period)
            try:
                cal, cal_hash = cals.get(ref)
            except MecanumHILError as err:
                error = error or f"calibration: {err}"
        key = spec_key(settings.command, g.group, g.period, [f.rel for f in g.files])
        settings_doc = {"command": settings.command, "options": settings.options,
                        "robot": robot_hash, "calibration": cal_hash, "version": __version__,
                        "stage_revision": stages.REVISIONS.get(settings.command, 1),
                        "write_to": settings.write_to}
        prev = (previous or {}).get(key)
        prev_hash = prev.get("content_hash") if prev and prev.get("status") in (
            "ok", "partial") else None
        specs.append(GroupSpec(
            command=settings.command, group=g.group, period=g.period,
            files=tuple((f.path, f.rel, f.sidecar) for f in g.files), fs=archive.fs,
            robot=robot, calibration=cal, options=dict(settings.options),
            settings_hash=_digest(json.dumps(settings_doc, sort_keys=True, default=str)
                                  .encode()),
            previous_hash=prev_hash, write_to=settings.write_to, error=error))
    return specs, archive


def local_cluster(workers: int | None = None, dashboard: bool = True):
    """A local Dask cluster: ``workers`` processes (default: the cores), one thread each."""
    from . import require_extra

    distributed = require_extra("dask.distributed")
    dask = require_extra("dask")
    n = workers or os.cpu_count() or 1
    # The statistical profiler samples every worker thread each 10 ms: a third of an idle
    # worker's CPU here; batch tasks are coarse, its flame graph not needed. Dask's default
    # worker environment sets MALLOC_TRIM_THRESHOLD_=65536, which fixes glibc's mmap threshold
    # too: every large numpy temporary of a fit is then mapped and unmapped anew, +22 % CPU
    # per fit here (docs/scale.md); the workers keep glibc's adaptive default instead.
    with dask.config.set({"distributed.worker.profile.enabled": False,
                          "distributed.nanny.pre-spawn-environ": dict(WORKER_ENV)}), \
            warnings.catch_warnings():
        # without a dashboard the scheduler still serves its health routes, on 8787 or, when
        # another cluster has it, a free port: that is fine, not worth a warning
        warnings.filterwarnings("ignore", message="Port 8787 is already in use")
        # Dask's nanny writes pre-spawn-environ into *this* process's os.environ and leaves it
        # there: numba, which re-reads NUMBA_NUM_THREADS at every compilation, then refuses
        # to compile once its thread pool has started with another count. Put them back.
        saved = {key: os.environ.get(key) for key in WORKER_ENV}
        try:
            return distributed.LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True,
                dashboard_address="127.0.0.1:0" if dashboard else None,
                silence_logs=logging.ERROR, env=dict(WORKER_ENV))
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


def dashboard_of(client) -> str | None:
    """The dashboard address of a client's scheduler, when it serves one."""
    try:
        services = client.scheduler_info().get("services", {})
    except (OSError, MecanumHILError):
        return None
    return client.dashboard_link if "dashboard" in services else None


def _kept_earlier(earlier: Mapping[str, Any], failed: Mapping[str, Any]) -> dict[str, Any]:
    """The earlier ``ok``/``partial`` row of a group that failed now, kept in the table, with
    the failure in its ``details`` (``rerun_failed``: when and why)."""
    row = dict(earlier)
    try:
        details = json.loads(row.get("details") or "{}")
    except (TypeError, ValueError):
        details = {"earlier": row.get("details")}
    if not isinstance(details, dict):
        details = {"earlier": details}
    details["rerun_failed"] = {"finished_utc": failed.get("finished_utc"),
                               "error": failed.get("error")}
    row["details"] = details
    return normalise(row)


def execute(client, specs: Sequence[GroupSpec], previous: Mapping[tuple[str, str, str], Any],
            journal: Path | None, progress: Callable[[Counts], None] | None = None,
            failures: list[dict[str, Any]] | None = None
            ) -> tuple[list[dict[str, Any]], Counts, float]:
    """Submit one task per spec, collect the rows as they finish, journal them.

    A task that dies (its worker lost, an error outside the stage) becomes a failed row; the
    others go on. A group that fails where ``previous`` holds an ``ok``/``partial`` row of it
    keeps that row (its ``details`` get ``rerun_failed``): a failure never replaces a result.
    ``failures``, when given, receives the failed rows of this run (``kept_earlier`` true where
    the earlier row was kept).

    Returns
    -------
    (rows, counts, wall_s)
    """
    counts = Counts(total=len(specs))
    t0 = time.perf_counter()
    futures = _submit(client, specs, t0)
    rows: list[dict[str, Any]] = []
    jfile = _open_journal(journal, futures)

    def finished(spec: GroupSpec, row: dict[str, Any]) -> None:
        row = _settled_row(spec, row, previous, counts, failures)
        rows.append(row)
        if jfile is not None:
            jfile.write(json.dumps(row) + "\n")
            jfile.flush()
        if progress:
            progress(counts)

    if progress:
        progress(counts)
    try:
        for spec in specs:
            if spec.error:
                finished(spec, run_group(spec))
        if futures:
            from . import require_extra

            distributed = require_extra("dask.distributed")
            for fut in distributed.as_completed(list(futures)):
                spec = futures.pop(fut)
                try:
                    row = fut.result()
                except Exception as err:  # the task itself died: only this group fails
                    row = _task_died(spec, err)
                finished(spec, row)
    finally:
        if jfile is not None:
            jfile.close()
        for fut in futures:
            fut.cancel()
    return rows, counts, time.perf_counter() - t0


def _submit(client, specs: Sequence[GroupSpec], t0: float) -> dict:
    """Submit a :func:`run_group` task per spec that planning found no error in; the futures,
    each to its spec. ``t0`` [s, perf_counter] keeps the task keys unique."""
    futures = {}
    for i, spec in enumerate(specs):
        if spec.error:
            continue  # found while planning: the row says so, no worker needed
        # readable keys on the dashboard; the index and start time keep them unique
        fut = client.submit(run_group, spec, pure=False,
                            key=f"mecanum-hil-{spec.command}-{i}-" + _digest(
                                f"{spec.group}\0{spec.period}\0{t0}".encode())[:12])
        futures[fut] = spec
    return futures


def _open_journal(journal: Path | None, futures: dict):
    """The journal opened for appending (None without one); cancels ``futures`` and raises
    :class:`ConfigError` when it cannot be written."""
    try:
        return journal.open("a", encoding="utf-8") if journal is not None else None
    except OSError as err:
        for fut in futures:
            fut.cancel()
        raise ConfigError(f"{journal}: cannot write the journal: {err.strerror or err}"
                          ) from err


def _settled_row(spec: GroupSpec, row: dict[str, Any],
                 previous: Mapping[tuple[str, str, str], Any], counts: Counts,
                 failures: list[dict[str, Any]] | None) -> dict[str, Any]:
    """The row a finished group leaves in the table, counted in ``counts``: the previous row
    when unchanged, the earlier ``ok``/``partial`` row (:func:`_kept_earlier`) when it failed
    now (the failure also goes to ``failures``), else its own."""
    key = spec_key(spec.command, spec.group, spec.period, [rel for _, rel, _ in spec.files])
    if row["status"] == "unchanged":
        counts.unchanged += 1
        row = dict(previous[key])
    elif row["status"] == "failed":
        counts.failed += 1
        earlier = previous.get(key)
        kept = bool(earlier) and earlier.get("status") in ("ok", "partial")
        if failures is not None:
            failures.append({**normalise(row), "kept_earlier": kept})
        if kept:
            row = _kept_earlier(earlier, row)
    else:
        counts.done += 1
    return normalise(row)


def _task_died(spec: GroupSpec, err: Exception) -> dict[str, Any]:
    """The failed row of a group whose task itself died (its worker lost, an error outside
    the stage)."""
    return normalise({"group": spec.group, "period": spec.period,
                      "command": spec.command, "status": "failed",
                      "n_inputs": len(spec.files),
                      "inputs": [rel for _, rel, _ in spec.files],
                      "error": f"task failed: {type(err).__name__}: {err}"})


def run_batch(settings: BatchSettings, progress: Callable[[Counts], None] | None = None,
              echo: Callable[[str], None] | None = None, client=None) -> BatchOutcome:
    """Plan, run and write a batch (``mecanum-hil batch``).

    Parameters
    ----------
    settings : BatchSettings
    progress : callable, optional
        Called with the :class:`Counts` after each group.
    echo : callable, optional
        Status lines (the plan, the dashboard's address).
    client : dask.distributed.Client, optional
        Use this client instead of the one ``settings.scheduler`` names (tests, benchmarks).
    """
    say = echo or (lambda _m: None)
    t0 = time.perf_counter()
    # everything that can be refused is refused here, before a cluster starts or a group runs
    table_format(settings.out)
    if settings.scheduler and client is None:
        check_scheduler(settings.scheduler)
    refuse_reading_out(settings)
    check_out(settings.out)
    check_write_to(settings.write_to)
    # read even with --no-resume: the table's ok rows survive groups that fail in this run
    earlier = previous_rows(settings.out, settings.command)
    specs, _archive = plan(settings, earlier if settings.resume else {})
    say(f"{settings.archive}: {describe_specs(specs)}")
    own_cluster = own_client = None
    dashboard = None
    try:
        # groups that failed while planning (e.g. no calibration for them) need no worker
        if client is None and any(not s.error for s in specs):
            from . import require_extra

            distributed = require_extra("dask.distributed")
            if settings.scheduler:
                try:
                    own_client = client = distributed.Client(settings.scheduler,
                                                           timeout=settings.connect_timeout_s)
                except (OSError, TimeoutError, ValueError) as err:
                    raise ConfigError(f"cannot reach the Dask scheduler at "
                                      f"{settings.scheduler}: {err}") from err
            else:
                own_cluster = local_cluster(settings.workers)
                own_client = client = distributed.Client(own_cluster)
        dashboard = dashboard_of(client) if client is not None else None
        if dashboard:
            say(f"Dask dashboard: {dashboard}")
        startup = time.perf_counter() - t0
        jpath = journal_path(settings.out)
        try:
            settings.out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ConfigError(f"--out {settings.out}: cannot make its folder: "
                              f"{err.strerror or err}") from err
        failures: list[dict[str, Any]] = []
        rows, counts, wall = execute(client, specs, earlier, jpath, progress, failures)
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()
    table = add_drift(rows, settings.drift_min_relative)
    try:
        write_results(table, settings.out)
    except OSError as err:  # the rows stay in the journal: the next run resumes from it
        raise ConfigError(f"{settings.out}: cannot write the results table: "
                          f"{err.strerror or err} (the rows are in {jpath})") from err
    jpath.unlink(missing_ok=True)
    return BatchOutcome(table, counts, settings.out, dashboard, wall, startup, failures)


def describe_specs(specs: Sequence[GroupSpec]) -> str:
    """One line about the planned tasks."""
    robots = {s.group for s in specs}
    periods = {s.period for s in specs if s.period}
    files = sum(len(s.files) for s in specs)
    return (f"{len(robots)} robot(s)" + (f", {len(periods)} period(s)" if periods else "")
            + f", {files} file(s), {len(specs)} task(s)")
