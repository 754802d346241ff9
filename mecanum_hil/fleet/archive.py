"""Find an archive's recordings or videos through fsspec and group them per robot and period.

An archive is a folder tree or an fsspec URL (``file://``, ``s3://``, ``memory://``...). By
default every first-level folder is one robot and every recording (``*.csv``) or video below it
belongs to it, at any depth. ``group_by`` picks another path level (``"2"``: the second-level
folder) or a key of the recordings' JSON sidecars (``"robot_id"``, dotted for nested objects).

Periods (``"day"`` or ``"week"``, UTC) come from the sidecar's ``started_utc`` (written by
``record``) and, for a file without one, from the file's modification time as the storage
reports it (``mtime`` of a local file, ``LastModified`` of an object). Days are ``2026-11-23``,
weeks ISO weeks ``2026-W48``.

Periods can also be a folder level (``period_level``: ``<robot>/<day>/run.csv``), taken as
named, with no sidecar read.

Only the listing and, when the grouping or the period needs them, the small sidecars are read
here; the recordings themselves are read by the tasks, on the workers.
"""

from __future__ import annotations

import datetime as _dt
import json
import posixpath
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..errors import ConfigError

RECORDING_SUFFIXES = (".csv",)
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v")
PERIODS = ("day", "week")


@dataclass(frozen=True)
class ArchiveFile:
    """One input file of the archive.

    Attributes
    ----------
    path : str
        Path in the archive's filesystem (what ``fs.open`` takes).
    rel : str
        Path relative to the archive root, ``/``-separated.
    size_bytes : int
    sidecar : str or None
        Path of the JSON sidecar, when the listing has one.
    time_utc : datetime or None
        Start of the recording (sidecar) or the file's modification time, UTC.
    time_source : str
        ``"started_utc"``, ``"mtime"`` or ``""`` (unknown).
    """

    path: str
    rel: str
    size_bytes: int
    sidecar: str | None = None
    time_utc: _dt.datetime | None = None
    time_source: str = ""


@dataclass(frozen=True)
class Group:
    """One task's inputs: a robot's recordings of one period (or one video).

    Attributes
    ----------
    group : str
        The robot: folder name or sidecar value.
    period : str
        ``""`` without ``--period``.
    files : tuple of ArchiveFile
        Sorted by relative path.
    error : str
        Set when the group cannot be formed (e.g. files outside any robot folder); the task
        then only reports it.
    """

    group: str
    period: str
    files: tuple[ArchiveFile, ...]
    error: str = ""

    @property
    def key(self) -> tuple[str, str]:
        """``(group, period)``: the row's identity in the results table."""
        return (self.group, self.period)


@dataclass(frozen=True)
class Archive:
    """An opened archive: its filesystem, root and the files found.

    Attributes
    ----------
    url : str
        As given.
    fs : fsspec.AbstractFileSystem
    root : str
        The root path in ``fs`` (no trailing slash).
    files : tuple of ArchiveFile
    """

    url: str
    fs: Any
    root: str
    files: tuple[ArchiveFile, ...] = field(default=())


def open_archive(url: str, kind: str = "recordings") -> Archive:
    """List an archive's recordings (``kind="recordings"``) or videos (``kind="videos"``).

    Raises
    ------
    ConfigError
        The archive does not exist, cannot be listed, or holds no input of that kind.
    """
    from . import require_extra

    core = require_extra("fsspec.core")
    try:
        fs, root = core.url_to_fs(str(url))
    except (ValueError, ImportError, OSError) as err:
        raise ConfigError(f"{url}: cannot open the archive: {err}") from err
    root = root.rstrip("/") or "/"
    try:
        if not fs.isdir(root):
            raise ConfigError(f"{url}: not a folder (the archive is a folder tree of robots)")
        listing = fs.find(root, detail=True)
    except OSError as err:
        raise ConfigError(f"{url}: cannot list the archive: {err}") from err
    suffixes = RECORDING_SUFFIXES if kind == "recordings" else VIDEO_SUFFIXES
    paths = set(listing)
    files = []
    for path in sorted(listing):
        info = listing[path]
        if info.get("type", "file") != "file":
            continue
        name = posixpath.basename(path)
        if name.startswith(".") or not name.lower().endswith(suffixes):
            continue
        rel = posixpath.relpath(path, root) if root != "/" else path.lstrip("/")
        side = posixpath.splitext(path)[0] + ".json"
        mtime = _mtime_utc(info)
        files.append(ArchiveFile(path=path, rel=rel, size_bytes=int(info.get("size") or 0),
                                 sidecar=side if side in paths else None, time_utc=mtime,
                                 time_source="mtime" if mtime is not None else ""))
    if not files:
        what = "recordings (*.csv)" if kind == "recordings" else \
            f"videos ({', '.join('*' + s for s in VIDEO_SUFFIXES)})"
        raise ConfigError(f"{url}: no {what} in the archive")
    return Archive(str(url), fs, root, tuple(files))


def _mtime_utc(info: Mapping[str, Any]) -> _dt.datetime | None:
    """The modification time an fsspec listing reports, as an aware UTC datetime."""
    for key in ("mtime", "LastModified", "last_modified", "modified", "created"):
        value = info.get(key)
        if value is None:
            continue
        if isinstance(value, _dt.datetime):
            return value if value.tzinfo else value.replace(tzinfo=_dt.UTC)
        if isinstance(value, (int, float)):
            return _dt.datetime.fromtimestamp(float(value), _dt.UTC)
        if isinstance(value, str):
            parsed = parse_time(value)
            if parsed is not None:
                return parsed
    return None


def parse_time(text: str) -> _dt.datetime | None:
    """An ISO 8601 time as an aware UTC datetime (naive times are taken as UTC); None if bad."""
    try:
        t = _dt.datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        return None
    return t.astimezone(_dt.UTC) if t.tzinfo else t.replace(tzinfo=_dt.UTC)


def period_of(t: _dt.datetime | None, period: str) -> str:
    """The period label of a UTC time: ``2026-11-23`` (day) or ``2026-W48`` (ISO week)."""
    if t is None:
        return "unknown"
    if period == "day":
        return t.strftime("%Y-%m-%d")
    year, week, _ = t.isocalendar()
    return f"{year}-W{week:02d}"


def _dotted(doc: Mapping[str, Any], key: str) -> Any:
    value: Any = doc
    for part in key.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    return value


def read_sidecars(archive: Archive, files: Sequence[ArchiveFile]
                  ) -> dict[str, dict[str, Any] | str]:
    """The JSON sidecars of ``files`` (those that have one): path -> object, or an error text.

    fsspec fetches them concurrently where the filesystem is asynchronous (object stores).
    """
    wanted = [f.sidecar for f in files if f.sidecar]
    if not wanted:
        return {}
    try:
        raw = archive.fs.cat(wanted, on_error="return")
    except OSError as err:
        raise ConfigError(f"{archive.url}: cannot read the sidecars: {err}") from err
    out: dict[str, dict[str, Any] | str] = {}
    for path in wanted:
        data = raw.get(path) if isinstance(raw, Mapping) else None
        if isinstance(data, Exception) or data is None:
            out[path] = f"{path}: cannot read the sidecar: {data}"
            continue
        try:
            doc = json.loads(data)
        except (ValueError, UnicodeDecodeError) as err:
            out[path] = f"{path}: bad JSON sidecar: {err}"
            continue
        out[path] = doc if isinstance(doc, dict) else f"{path}: the sidecar is not an object"
    return out


def parse_group_by(group_by: str | None) -> tuple[str, int | str]:
    """``None`` -> ``("level", 1)``; ``"2"`` -> ``("level", 2)``; ``"robot_id"`` -> key."""
    if group_by is None or not str(group_by).strip():
        return ("level", 1)
    text = str(group_by).strip()
    if text.isdigit():
        level = int(text)
        if level < 1:
            raise ConfigError(f"--group-by: path levels start at 1, got {text}")
        return ("level", level)
    return ("key", text)


def group_files(archive: Archive, group_by: str | None = None, period: str | None = None,
                per_file: bool = False, period_level: int | None = None) -> list[Group]:
    """Group the archive's files per robot (and period).

    Parameters
    ----------
    archive : Archive
    group_by : str, optional
        A path level (``"1"``, the default: first-level folder) or a sidecar key.
    period : {"day", "week"}, optional
        Split each robot's files per period (sidecar ``started_utc``, else modification time).
    per_file : bool
        One group per file (``measure-video``: one task per video); ``group`` is still the
        robot.
    period_level : int, optional
        The period is the name of this path level's folder (e.g. ``<robot>/<day>/run.csv``:
        level 2; 0: the archive folder's own name, ``runs/<day>/`` with ARCHIVE
        ``runs/<day>``), as it is, instead of a time: no sidecar is read for it.

    Returns
    -------
    list of Group
        Sorted by group, period (and file).
    """
    _check_period_options(period, period_level)
    how, which = parse_group_by(group_by)
    need_sidecars = how == "key" or period is not None
    sidecars = read_sidecars(archive, archive.files) if need_sidecars else {}
    buckets: dict[tuple[str, str], list[ArchiveFile]] = {}
    errors: dict[tuple[str, str], list[str]] = {}
    for f in archive.files:
        doc = sidecars.get(f.sidecar) if f.sidecar else None
        name, problem = _group_name(f, doc, how, which)
        f, label, problem = _period_label(f, doc, archive, period, period_level, problem)
        key = (name, label)
        buckets.setdefault(key, []).append(f)
        if problem:
            errors.setdefault(key, []).append(problem)
    groups = []
    for key in sorted(buckets):
        files = tuple(sorted(buckets[key], key=lambda x: x.rel))
        err = "; ".join(errors.get(key, []))
        if per_file:
            groups.extend(Group(key[0], key[1], (f,), err) for f in files)
        else:
            groups.append(Group(key[0], key[1], files, err))
    return groups


def _check_period_options(period: str | None, period_level: int | None) -> None:
    """Refuse a period that is not one of :data:`PERIODS`, both options, or a negative
    level."""
    if period is not None and period not in PERIODS:
        raise ConfigError(f"--period must be day or week, got {period!r}")
    if period is not None and period_level is not None:
        raise ConfigError("give --period or --period-level, not both")
    if period_level is not None and period_level < 0:
        raise ConfigError(f"--period-level: 0 (the archive folder itself) or a path level "
                          f"from 1, got {period_level}")


def _group_name(f: ArchiveFile, doc, how: str, which: int | str) -> tuple[str, str]:
    """The group (robot) of file ``f`` by path level or sidecar key (``doc``: its sidecar, an
    error text, or None), and the problem that made it a placeholder ("" for none)."""
    if how == "level":
        parts = f.rel.split("/")
        if len(parts) <= int(which):
            return ("(outside any robot folder)",
                    f"{f.rel}: not inside a level-{which} folder of the archive (each "
                    f"robot's recordings go in its own folder)")
        return parts[int(which) - 1], ""
    value = _dotted(doc, str(which)) if isinstance(doc, dict) else None
    if value is None or isinstance(value, (dict, list)):
        why = doc if isinstance(doc, str) else \
            "no sidecar" if f.sidecar is None else f"its sidecar has no key {which!r}"
        return f"(no {which})", f"{f.rel}: {why}"
    return str(value), ""


def _period_label(f: ArchiveFile, doc, archive: Archive, period: str | None,
                  period_level: int | None, problem: str) -> tuple[ArchiveFile, str, str]:
    """The period of file ``f`` ("" without one): by its time (the sidecar's ``started_utc``
    replaces the file's time in the returned file) or by a path level's folder name; and
    ``problem``, or a new one where ``f`` is not that deep."""
    if period is not None:
        started = parse_time(doc.get("started_utc", "")) if isinstance(doc, dict) and \
            doc.get("started_utc") else None
        if started is not None:
            f = ArchiveFile(f.path, f.rel, f.size_bytes, f.sidecar, started, "started_utc")
        return f, period_of(f.time_utc, period), problem
    if period_level == 0:
        return f, posixpath.basename(archive.root.rstrip("/")) or "unknown", problem
    if period_level is not None:
        parts = f.rel.split("/")
        if len(parts) > period_level:
            return f, parts[period_level - 1], problem
        return f, "unknown", problem or f"{f.rel}: not inside a level-{period_level} folder"
    return f, "", problem


def describe(groups: Iterable[Group]) -> str:
    """One line: how many robots, periods, groups and files."""
    groups = list(groups)
    robots = {g.group for g in groups}
    periods = {g.period for g in groups if g.period}
    files = sum(len(g.files) for g in groups)
    text = f"{len(robots)} robot(s), {len(groups)} group(s), {files} file(s)"
    return text + (f", {len(periods)} period(s)" if periods else "")
