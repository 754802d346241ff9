"""One group as one self-contained task (what a Dask worker runs).

:func:`run_group` streams the group's files from the archive's filesystem to the worker's disk
in 1 MiB chunks, hashing them as they pass; when the hash (files, sidecars, and the stage's
settings) equals the previous run's it stops there (``unchanged``); otherwise it runs the stage
through :mod:`.stages` and returns one row. The recordings of one group are the most that is
in memory at once; the result is a small dict. Nothing raised by the stage escapes: a bad
group is a ``failed`` row, a bad file an entry of ``error`` in a ``partial`` row.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
import posixpath
import socket
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ConfigError, MecanumHILError
from . import stages
from .results import empty_row

COMMANDS = ("fit", "diagnose", "shadow", "measure-video")
_CHUNK = 1 << 20


@dataclass(frozen=True)
class GroupSpec:
    """Everything a task needs (pickled to the worker).

    Attributes
    ----------
    command : str
        One of :data:`COMMANDS`.
    group, period : str
    files : tuple of (path, rel, sidecar or None)
        The inputs in the archive's filesystem.
    fs : fsspec.AbstractFileSystem
        The archive's filesystem (fsspec filesystems pickle to their constructor arguments).
    robot : RobotProfile
    calibration : Calibration
    options : dict
        Stage options (``method``, ``candidates``, shadow ``config``, video options).
    settings_hash : str
        Hash of the stage and its settings (command, options, calibration and robot files,
        tool version); part of the content hash.
    previous_hash : str or None
        The content hash of this group's row in the previous run.
    write_to : str or None
        fsspec URL of a folder for the per-group outputs (calibrations, measured recordings).
    error : str
        A problem found while grouping: the task only reports it.
    """

    command: str
    group: str
    period: str
    files: tuple[tuple[str, str, str | None], ...]
    fs: Any
    robot: Any
    calibration: Any
    options: dict[str, Any] = field(default_factory=dict)
    settings_hash: str = ""
    previous_hash: str | None = None
    write_to: str | None = None
    error: str = ""


def _is_local(fs) -> bool:
    protocol = fs.protocol if isinstance(fs.protocol, tuple) else (fs.protocol,)
    return bool({"file", "local"} & set(protocol))


def _stream(fs, path: str, target: Path | None, h) -> Path:
    """Hash a file while copying it to ``target`` (or only reading it, for local files)."""
    with fs.open(path, "rb") as src:
        if target is None:
            while chunk := src.read(_CHUNK):
                h.update(chunk)
            return Path(path)
        with target.open("wb") as dst:
            while chunk := src.read(_CHUNK):
                h.update(chunk)
                dst.write(chunk)
    return target


def stage_files(spec: GroupSpec, workdir: Path) -> tuple[list[Path], list[str], list[str], str]:
    """Bring the group's files to local paths and hash them.

    Returns
    -------
    (paths, names, bad, content_hash)
        Local paths with their archive names, the files that could not be read
        (``"name: why"``), and the hash of settings and contents.
    """
    h = hashlib.sha256(spec.settings_hash.encode())
    local = _is_local(spec.fs)
    paths, names, bad = [], [], []
    for i, (path, rel, sidecar) in enumerate(spec.files):
        h.update(b"\0file\0" + rel.encode())
        folder = workdir / str(i)
        folder.mkdir()
        base = posixpath.basename(path)
        try:
            got = _stream(spec.fs, path, None if local else folder / base, h)
            if sidecar:
                h.update(b"\0sidecar\0")
                side_target = None if local else folder / posixpath.basename(sidecar)
                _stream(spec.fs, sidecar, side_target, h)
        except OSError as err:
            h.update(b"\0unreadable\0")
            bad.append(f"{rel}: cannot read: {err}")
            continue
        paths.append(got)
        names.append(rel)
    return paths, names, bad, h.hexdigest()


def _output_url(spec: GroupSpec, name: str) -> str:
    return posixpath.join(spec.write_to.rstrip("/"), name)


def _put_text(url: str, text: str) -> str:
    import fsspec

    try:
        with fsspec.open(url, "w", encoding="utf-8", auto_mkdir=True) as fh:
            fh.write(text)
    except (OSError, ValueError) as err:  # the folder gone, a file in the way, no room ...
        raise ConfigError(f"--write: cannot write {url}: {_why(err)}") from err
    return url


def _put_file(url: str, path: Path) -> str:
    import fsspec

    try:
        with fsspec.open(url, "wb", auto_mkdir=True) as dst, path.open("rb") as src:
            while chunk := src.read(_CHUNK):
                dst.write(chunk)
    except (OSError, ValueError) as err:
        raise ConfigError(f"--write: cannot write {url}: {_why(err)}") from err
    return url


def _why(err: Exception) -> str:
    return (err.strerror if isinstance(err, OSError) and err.strerror else str(err)) \
        or type(err).__name__


def _outputs(spec: GroupSpec, result: Any, workdir: Path) -> str | None:
    """Write the group's output (a calibration, a measured recording) under ``write_to``."""
    if spec.write_to is None or result is None:
        return None
    if spec.command in ("fit", "diagnose"):
        stem = spec.group if not spec.period else f"{spec.group}/{spec.period}"
        header = (f"Written by mecanum-hil batch {spec.command} for {spec.group} "
                  f"{spec.period}".rstrip() + f" from {len(spec.files)} recording(s).")
        return _put_text(_output_url(spec, stem + ".toml"),
                         stages.calibration_text(result, header))
    if spec.command == "measure-video":
        rel = spec.files[0][1]
        stem = posixpath.splitext(rel)[0]
        local = stages.recording_text(result, workdir / "out" / (posixpath.basename(stem)
                                                                  + ".csv"))
        url = _put_file(_output_url(spec, stem + ".csv"), local)
        side = local.with_suffix(".json")
        if side.exists():
            _put_file(_output_url(spec, stem + ".json"), side)
        return url
    return None


def run_group(spec: GroupSpec) -> dict[str, Any]:
    """Run one group; always returns a row (never raises for bad data).

    ``status`` is ``unchanged`` (only the key and ``content_hash`` are meaningful: keep the
    previous row), ``ok``, ``partial`` or ``failed``.
    """
    row = empty_row(spec.group, spec.period, spec.command)
    row.update(n_inputs=len(spec.files), inputs=[rel for _, rel, _ in spec.files],
               worker=f"{socket.gethostname()}:{os.getpid()}")
    t0 = time.perf_counter()
    bad: list[str] = []
    try:
        if spec.error:
            row.update(status="failed", error=spec.error)
            return row
        with tempfile.TemporaryDirectory(prefix="mecanum-hil-batch-") as tmp:
            workdir = Path(tmp)
            paths, names, unreadable, digest = stage_files(spec, workdir)
            bad += unreadable
            row["content_hash"] = digest
            if spec.previous_hash is not None and digest == spec.previous_hash:
                row["status"] = "unchanged"
                return row
            fields, result = _run_stage(spec, paths, names, bad)
            row.update(fields)
            row["output"] = _outputs(spec, result, workdir)
        row["status"] = "partial" if bad else "ok"
        if bad:
            row["error"] = f"left out {len(bad)} of {len(spec.files)} input(s): " + \
                " | ".join(bad)
    except MecanumHILError as err:
        row["status"] = "failed"
        row["error"] = str(err) + (f" (inputs left out: {' | '.join(bad)})" if bad else "")
    except Exception as err:  # a bug or a foreign failure stays in this row, not the batch
        row["status"] = "failed"
        row["error"] = f"internal error: {type(err).__name__}: {err}"
        row["details"] = {"traceback": traceback.format_exc(limit=8)}
    finally:
        row["elapsed_s"] = time.perf_counter() - t0
        row["finished_utc"] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    return row


def _run_stage(spec: GroupSpec, paths: list[Path], names: list[str], bad: list[str]
               ) -> tuple[dict[str, Any], Any]:
    """Run the stage; inputs left out are appended to ``bad`` (kept when the stage fails)."""
    opts = spec.options
    if spec.command == "measure-video":
        if not paths:
            raise MecanumHILError("no readable video")
        fields, rec = stages.run_measure_video(paths[0], names[0], opts.get("video", {}))
        return fields, rec
    recs, ok, unreadable = stages.read_recordings(paths, names)
    bad += unreadable
    if not recs:
        raise MecanumHILError("no readable recording in the group")
    if spec.command == "fit":
        fields, cal = stages.run_fit(recs, ok, spec.robot, spec.calibration,
                                     opts.get("method", "lsq"))
        return fields, cal
    if spec.command == "diagnose":
        fields, cal = stages.run_diagnose(recs, ok, spec.robot, spec.calibration,
                                          opts.get("method", "lsq"), opts.get("candidates"))
        return fields, cal
    if spec.command == "shadow":
        fields, more = stages.run_shadow(recs, ok, spec.robot, spec.calibration,
                                         opts.get("config"))
        bad += more
        if len(more) == len(recs):
            raise MecanumHILError("no recording could be replayed")
        return fields, None
    raise MecanumHILError(f"unknown batch command {spec.command!r}")
