"""The recording: the one file format every command reads and writes.

A recording is a CSV file with a header row whose first eleven columns are, in this order::

    t_s, n_cmd_rpm, omega_cmd_dps, theta_cmd_deg,
    wheel1_rpm, wheel2_rpm, wheel3_rpm, wheel4_rpm, x_m, y_m, phi_deg

Extra columns may follow; they are kept (as text) and written back. Commands are those in force
at ``t_s``. A value that was not measured is an empty field (NaN in memory). An optional JSON
sidecar with the same stem (``run.csv`` -> ``run.json``) carries metadata.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MecanumHILWarning, RecordingError

COLUMNS = (
    "t_s", "n_cmd_rpm", "omega_cmd_dps", "theta_cmd_deg",
    "wheel1_rpm", "wheel2_rpm", "wheel3_rpm", "wheel4_rpm", "x_m", "y_m", "phi_deg",
)
COMMAND_COLUMNS = COLUMNS[1:4]
WHEEL_COLUMNS = COLUMNS[4:8]
POSE_COLUMNS = COLUMNS[8:11]

#: The largest magnitude a value of each column may have: far beyond any robot (a million rpm,
#: deg/s or m; 1e10 s of time, as an import map's start; a heading unwrapped over a million
#: turns), but where sums of squares stay finite. A value beyond it is a corrupt field, not a
#: measurement, and the reader refuses it naming the line (it would overflow every fit).
MAX_ABS_VALUE = dict.fromkeys(COLUMNS, 1e6) | {"t_s": 1e10, "phi_deg": 1e9}

#: The longest gap between two rows of one recording [s]: a day. Longer is two recordings
#: joined or a corrupt stamp, and the model would step its controller through all of it (a
#: 2e7 s gap kept diagnose busy for hours).
MAX_GAP_S = 86400.0


class TimeRepairWarning(MecanumHILWarning):
    """Logged time was repaired on reading (repeated stamps, jitter, a wrapping counter)."""


@dataclass(frozen=True)
class Recording:
    """A recording in memory.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Sample times, strictly increasing [s].
    commands : ndarray, shape (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])`` in force at each sample; NaN where unknown.
    wheel_rpm : ndarray, shape (T, 4)
        Measured wheel speeds 1..4 [rpm]; NaN where not measured.
    pose : ndarray, shape (T, 3)
        Measured ``(X [m], Y [m], phi [deg])``; NaN where not measured.
    extra : Mapping[str, Sequence[str]]
        Extra columns, in file order, as text.
    metadata : Mapping[str, Any]
        The JSON sidecar's content (empty without one).
    """

    t_s: np.ndarray
    commands: np.ndarray
    wheel_rpm: np.ndarray
    pose: np.ndarray
    extra: Mapping[str, Sequence[str]] = field(default_factory=dict)
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.t_s.shape[0]
        for name, arr, width in (("commands", self.commands, 3), ("wheel_rpm", self.wheel_rpm, 4),
                                 ("pose", self.pose, 3)):
            if arr.shape != (n, width):
                raise RecordingError(f"{name} must have shape ({n}, {width}), got {arr.shape}")
        for name, col in self.extra.items():
            if len(col) != n:
                raise RecordingError(f"extra column '{name}' has {len(col)} rows, expected {n}")

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def has_commands(self) -> bool:
        """Whether every sample has all three commands."""
        return bool(len(self)) and bool(np.isfinite(self.commands).all())

    @property
    def measured_period_s(self) -> float:
        """Median interval between rows with a measured wheel speed [s]; rows without one (a
        recorded run's command rows) are not samples. NaN with fewer than two."""
        t = self.t_s[np.isfinite(self.wheel_rpm).any(axis=1)]
        return float(np.median(np.diff(t))) if t.size > 1 else math.nan

    def extra_numeric(self, name: str) -> np.ndarray:
        """An extra column as floats (empty or non-numeric fields become NaN)."""
        out = np.full(len(self), np.nan)
        for i, v in enumerate(self.extra[name]):
            try:
                out[i] = float(v) if v != "" else np.nan
            except ValueError:
                pass
        return out

    def select(self, rows) -> Recording:
        """The recording reduced to ``rows`` (a boolean mask or indices), extras included."""
        idx = np.arange(len(self))[rows]
        extra = {k: [v[i] for i in idx] for k, v in self.extra.items()}
        return replace(self, t_s=self.t_s[idx], commands=self.commands[idx],
                       wheel_rpm=self.wheel_rpm[idx], pose=self.pose[idx], extra=extra)

    def with_values(self, **changes) -> Recording:
        """A copy with some fields replaced."""
        return replace(self, **changes)


def empty_like_times(t_s, metadata: Mapping[str, Any] | None = None) -> Recording:
    """A recording with the given times and every other value missing."""
    t = np.asarray(t_s, dtype=float)
    n = t.size
    return Recording(t, np.full((n, 3), np.nan), np.full((n, 4), np.nan), np.full((n, 3), np.nan),
                     {}, dict(metadata or {}))


def sidecar_path(path: str | Path) -> Path:
    """The JSON sidecar belonging to a recording CSV."""
    return Path(path).with_suffix(".json")


def _parse_float(text: str, where: str) -> float:
    s = text.strip()
    if s == "":
        return math.nan
    try:
        if "_" in s:  # Python's float() reads "1_0" as 10; no logger writes that
            raise ValueError
        value = float(s)
    except ValueError:
        raise RecordingError(f"{where}: not a number: {text!r}") from None
    if math.isnan(value) or math.isinf(value):
        raise RecordingError(f"{where}: not a finite number: {text!r} (leave missing values empty)")
    return value


def _drop_cut_last_line(text: str) -> tuple[str, str]:
    """Drop a last line cut off mid-row (a crash or full disk while writing).

    Every complete row ends with a newline; a last line without one that does not have the
    header's number of fields, or whose fields are not all numbers or empty, is a partial
    write: it is dropped so that everything before it stays readable. Returns the text and the
    dropped line ("" when none).
    """
    if text.endswith("\n") or "\n" not in text:
        return text, ""
    head, _, tail = text.rpartition("\n")
    n_fields = len(next(csv.reader(io.StringIO(text.split("\n", 1)[0]))))
    try:
        fields = next(csv.reader(io.StringIO(tail)))
    except (csv.Error, StopIteration):
        return head + "\n", tail
    if len(fields) != n_fields:
        return head + "\n", tail
    try:
        for f in fields[: len(COLUMNS)]:
            if f.strip():
                float(f)
    except ValueError:
        return head + "\n", tail
    return text, ""


def _numeric_body(text: str) -> np.ndarray | None:
    """The rows of a recording without extra columns, parsed by numpy; None to take the slow path.

    Only well-formed text is read here (what ``write_recording`` writes: no blank lines, no
    quotes, no ``nan``/``inf``, a time in every row, the header's field count); anything else
    returns None and goes through the row-by-row reader, whose messages name line and column.
    """
    body = text.partition("\n")[2]
    if not body or "\n\n" in body or '"' in body or "\r" in body:
        return None
    if any(c in body for c in "nNiI_"):  # nan, inf, infinity (or any other word); 1_000
        return None
    if body.startswith(",") or "\n," in body:
        return None  # a missing time
    filled = body.replace(",,", ",nan,").replace(",,", ",nan,").replace(",\n", ",nan\n")
    if filled.endswith(","):
        filled += "nan"
    try:
        arr = np.loadtxt(io.StringIO(filled), delimiter=",", ndmin=2, dtype=float,
                         comments=None)
    except ValueError:
        return None
    return arr if arr.shape[1] == len(COLUMNS) else None


def read_recording(path: str | Path) -> Recording:
    """Read a recording (CSV and, when present, its JSON sidecar).

    Raises
    ------
    RecordingError
        For a missing file, a header that differs from the pinned columns, a row with the wrong
        number of fields, a non-numeric value, a missing time, time that runs back by more
        than its resolution or a gap over the sidecar's ``time_repair.max_gap_s``;
        the message names the file, line and column. A last line cut off mid-row (no final
        newline: a crash while writing) is not an error: it is dropped, and the metadata's
        ``truncated_last_line`` holds it.

    Warns
    -----
    TimeRepairWarning
        Time that is not strictly increasing the way loggers write it (repeated stamps, jitter
        within the resolution, a wrapping counter) is repaired in memory (the file is not
        changed), said in one line and kept in the metadata's ``time_repair``.
    """
    p = Path(path)
    text, truncated = _drop_cut_last_line(_read_text(p))
    rows = csv.reader(io.StringIO(text))
    header = _read_header(p, rows)
    extra_names = header[len(COLUMNS):]
    arr, extra, lines = _read_rows(p, rows, len(header), extra_names, text)
    refuse_absurd_values(arr, lambda i: f"{p}, line {lines[i]}")
    metadata = _read_sidecar(p)
    if truncated:
        metadata = {**metadata, "truncated_last_line": truncated}
    t, repair = _repaired_time(arr[:, 0], metadata,
                               lambda i: f"{p}, line {lines[i]}, column 't_s'", str(p), text)
    if repair is not None:
        metadata = {**metadata, "time_repair": repair}
    return Recording(t.copy(), arr[:, 1:4].copy(), arr[:, 4:8].copy(),
                     arr[:, 8:11].copy(), dict(zip(extra_names, extra, strict=True)), metadata)


def _read_text(p: Path) -> str:
    """The text of the recording ``p`` (a UTF-8 byte-order mark dropped)."""
    try:
        return p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise RecordingError(f"{p}: file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise RecordingError(f"{p}: cannot read: {err}") from err


def _read_header(p: Path, rows) -> list[str]:
    """The header row of the CSV reader ``rows`` (of file ``p``), stripped and checked: the
    pinned :data:`COLUMNS` first, then extra columns, no name twice."""
    try:
        header = next(rows)
    except StopIteration:
        raise RecordingError(f"{p}: empty file, expected a header row") from None
    except csv.Error as err:
        raise RecordingError(f"{p}, line 1: {err}") from err
    header = [h.strip() for h in header]
    for i, name in enumerate(COLUMNS):
        if i >= len(header):
            raise RecordingError(f"{p}, line 1: missing column '{name}' (column {i + 1})")
        if header[i] != name:
            raise RecordingError(
                f"{p}, line 1, column {i + 1}: expected '{name}', found '{header[i]}' "
                f"(the first columns must be: {', '.join(COLUMNS)})")
    extra_names = header[len(COLUMNS):]
    twice = sorted({n for n in extra_names if extra_names.count(n) > 1 or n in COLUMNS})
    if twice:
        raise RecordingError(f"{p}, line 1: duplicate column name(s): {', '.join(twice)}")
    return header


def _read_rows(p: Path, rows, n_fields: int, extra_names: list[str], text: str):
    """The data rows after the header: the pinned columns as floats, shape (T, len(COLUMNS)),
    each extra column's strings, and each row's line number in the file (blank rows
    skipped). Without extra columns a plain numeric ``text`` is parsed in one pass."""
    values: list[list[float]] = []
    extra: list[list[str]] = [[] for _ in extra_names]
    lines: list[int] = []
    line = 1
    fast = None if extra_names else _numeric_body(text)
    if fast is not None:
        values = fast  # type: ignore[assignment]
        lines = range(2, len(fast) + 2)  # type: ignore[assignment]
        rows = iter(())
    try:
        for line, row in enumerate(rows, start=2):
            if not row or all(not f.strip() for f in row):
                continue
            if len(row) != n_fields:
                raise RecordingError(
                    f"{p}, line {line}: {len(row)} fields, header has {n_fields}")
            nums = [_parse_float(row[i], f"{p}, line {line}, column '{COLUMNS[i]}'")
                    for i in range(len(COLUMNS))]
            if math.isnan(nums[0]):
                raise RecordingError(f"{p}, line {line}, column 't_s': time is missing")
            values.append(nums)
            lines.append(line)
            for j in range(len(extra_names)):
                extra[j].append(row[len(COLUMNS) + j])
    except csv.Error as err:
        raise RecordingError(f"{p}, line {line}: {err}") from err
    return np.array(values, dtype=float).reshape(-1, len(COLUMNS)), extra, lines


def _read_sidecar(p: Path) -> dict[str, Any]:
    """The metadata of the JSON sidecar of recording ``p``; empty without one."""
    side = sidecar_path(p)
    if not side.exists():
        return {}
    try:
        metadata = json.loads(side.read_text(encoding="utf-8-sig"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise RecordingError(f"{side}: bad JSON sidecar: {err}") from err
    if not isinstance(metadata, dict):
        raise RecordingError(f"{side}: the sidecar must hold a JSON object")
    return metadata


def refuse_absurd_values(columns, row_name) -> None:
    """A :class:`RecordingError` naming the first value (by row) that is infinite or beyond
    :data:`MAX_ABS_VALUE`.

    Parameters
    ----------
    columns : array of shape (T, 11) or sequence of 11 arrays of shape (T,)
        The values in the order of :data:`COLUMNS` (checked a column at a time: an hour of
        1 kHz samples is not copied).
    row_name : callable
        ``row_name(i)`` names row ``i`` in the message.
    """
    cols = list(columns.T) if isinstance(columns, np.ndarray) else list(columns)
    first = None  # (row, column)
    for j, name in enumerate(COLUMNS):
        with np.errstate(invalid="ignore"):
            bad = np.abs(cols[j]) > MAX_ABS_VALUE[name]
        if bad.any():
            i = int(np.argmax(bad))
            if first is None or i < first[0]:
                first = (i, j)
    if first is not None:
        i, j = first
        raise RecordingError(
            f"{row_name(i)}, column '{COLUMNS[j]}': {cols[j][i]:g} is not a value a robot logs "
            f"(beyond {MAX_ABS_VALUE[COLUMNS[j]]:g}): a corrupt field? (leave a missing value "
            "empty)")


def _repaired_time(t: np.ndarray, metadata: Mapping[str, Any], row_name, source: str,
                   text: str):
    """``(t, None)`` when ``t`` is strictly increasing, else ``(repaired t, summary)``.

    Time as loggers write it (repeated stamps, jitter within the resolution, a wrapping counter)
    is repaired by :func:`mecanum_hil.io.time_repair.repair_time` and said in one warning line; time
    that runs back by more than the resolution is an error naming the line. The gap limit is the
    one the sidecar states (``time_repair.max_gap_s``, written by ``import``), if any.
    """
    limit = None
    prior = metadata.get("time_repair")
    if isinstance(prior, Mapping) and prior.get("max_gap_s") is not None:
        value = prior["max_gap_s"]
        if (isinstance(value, bool) or not isinstance(value, (int, float))
                or not math.isfinite(value) or value <= 0):
            raise RecordingError(f"{sidecar_path(source)}: time_repair.max_gap_s must be a "
                                 f"positive number of seconds (or null), got {value!r}")
        limit = float(value)
    increasing = t.size < 2 or bool(np.all(np.diff(t) > 0))
    if t.size >= 2:
        d = np.diff(t)
        i = int(np.argmax(d))
        if d[i] > MAX_GAP_S:
            raise RecordingError(
                f"{row_name(i + 1)}: a gap of {d[i]:.6g} s before this row, more than a day "
                "(two recordings joined, or a corrupt time?): split the recording there")
    if increasing and limit is None:
        return t, None
    from .time_repair import decimal_resolution, repair_time

    # the resolution is what the file writes (6 decimals from write_recording: 1 us), not
    # what a clean grid of stamps happens to be a multiple of
    sample = text.partition("\n")[2][:200_000].split("\n")[:2000]
    res = decimal_resolution(line.partition(",")[0] for line in sample)
    rep = repair_time(t, resolution_s=res, max_gap_s=limit, row_name=row_name)
    if not rep.changed:
        return t, None
    warnings.warn(f"{source}: {rep.note}", TimeRepairWarning, stacklevel=3)
    return rep.t_s, rep.summary


def format_value(value: float, digits: int = 9) -> str:
    """A CSV field: empty for NaN, otherwise a compact round-trippable-enough number."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return f"{value:.{digits}g}"


def _row(t: float, values: Sequence[float], extra: Sequence[str]) -> list[str]:
    return [f"{t:.6f}"] + [format_value(float(v)) for v in values] + list(extra)


def _metadata_text(metadata: Mapping[str, Any]) -> str:
    return json.dumps(dict(metadata), indent=2, sort_keys=True, default=str) + "\n"


def _remove(*paths: Path) -> None:
    """Remove temporary files left by a failed write (quietly: the write's error is the one
    to report)."""
    for tmp in paths:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass


def write_metadata(path: str | Path, metadata: Mapping[str, Any]) -> Path:
    """Write the JSON sidecar of a recording (atomically: a reader never sees half of it)."""
    side = sidecar_path(path)
    tmp = side.with_name(side.name + ".tmp")
    try:
        tmp.write_text(_metadata_text(metadata))
        os.replace(tmp, side)
    except OSError as err:
        _remove(tmp)
        raise RecordingError(f"{side}: cannot write: {err.strerror or err}") from err
    return side


def _text_column(values: np.ndarray) -> list[str] | np.ndarray | None:
    """A value column as CSV fields (:func:`format_value`); None when every value is missing.

    Logged commands and quantised speeds repeat a few values many times: each distinct value is
    formatted once.
    """
    finite = np.isfinite(values)
    if not finite.any():
        return None
    same = (values[1:] == values[:-1]) | (~finite[1:] & ~finite[:-1])
    starts = np.flatnonzero(np.concatenate(([True], ~same)))
    if starts.size <= values.size // 8:  # runs (held commands): format each run once
        text = np.array([format_value(v) for v in values[starts].tolist()], dtype=object)
        return np.repeat(text, np.diff(np.append(starts, values.size)))
    uniq, inverse = np.unique(values, return_inverse=True)
    if uniq.size > values.size // 4:
        return [format_value(v) for v in values.tolist()]
    return np.array([format_value(v) for v in uniq.tolist()], dtype=object)[inverse]


def _write_body(fh, rec: Recording, rows: slice, chunk: int = 200_000) -> None:
    """Write rows as CSV text: the same text as csv.writer with :func:`_row`, column-wise."""
    if rec.extra:  # text extras need the csv module's quoting: row by row
        w = csv.writer(fh, lineterminator="\n")
        body = np.column_stack([rec.commands, rec.wheel_rpm, rec.pose])
        extra_cols = list(rec.extra.values())
        for i in range(len(rec))[rows]:
            w.writerow(_row(float(rec.t_s[i]), body[i], [c[i] for c in extra_cols]))
        return
    start, stop, _ = rows.indices(len(rec))
    body = np.column_stack([rec.commands, rec.wheel_rpm, rec.pose])
    width = body.shape[1] + 1
    for a in range(start, stop, chunk):
        b = min(a + chunk, stop)
        cols: list = [_time_column(rec.t_s[a:b])]
        cols += [_text_column(body[a:b, j]) for j in range(body.shape[1])]
        while cols[-1] is None:  # trailing empty columns: one constant end of line
            cols.pop()
        # one join over the interleaved fields and separators: no per-row Python
        parts: list = [None] * ((b - a) * 2 * len(cols))
        step = 2 * len(cols)
        for j, c in enumerate(cols):
            parts[2 * j::step] = [""] * (b - a) if c is None else c
            parts[2 * j + 1::step] = [","] * (b - a)
        parts[step - 1::step] = ["," * (width - len(cols)) + "\n"] * (b - a)
        fh.write("".join(parts))


def _time_column(t: np.ndarray) -> list[str]:
    """Times as ``%.6f`` fields; whole microseconds (the usual case) without per-value format."""
    us = np.rint(t * 1e6)
    exact = (np.abs(t * 1e6 - us) < 1e-3) & (t >= 0) & (us < 2**52)
    if np.count_nonzero(exact) < max(1000, t.size // 2):
        return [f"{v:.6f}" for v in t.tolist()]
    sec, frac = np.divmod(np.where(exact, us, 0).astype(np.int64), 1_000_000)
    s_u, s_i = np.unique(sec, return_inverse=True)
    f_u, f_i = np.unique(frac, return_inverse=True)
    s_txt = np.array([f"{v}." for v in s_u.tolist()], dtype=object)[s_i]
    f_txt = np.array([f"{v:06d}" for v in f_u.tolist()], dtype=object)[f_i]
    out = s_txt + f_txt
    for i in np.flatnonzero(~exact).tolist():  # stamps re-spaced between whole microseconds
        out[i] = f"{t[i]:.6f}"
    return out.tolist()


def format_rows(rec: Recording, n_rows: int) -> str:
    """The header and first ``n_rows`` rows exactly as :func:`write_recording` writes them."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(list(COLUMNS) + list(rec.extra))
    _write_body(buf, rec, slice(0, min(n_rows, len(rec))))
    return buf.getvalue()


def _writable_recording_path(path: str | Path) -> Path:
    """``path`` as a recording to write; a ``.json`` name is refused: it is its own sidecar's
    (the sidecar replaced the file the user had there, then the CSV was lost)."""
    p = Path(path)
    if sidecar_path(p) == p:
        raise RecordingError(f"{p}: a recording cannot be named .json (its JSON sidecar is "
                             "written beside it under that name); name it .csv")
    return p


def write_recording(rec: Recording, path: str | Path) -> Path:
    """Write a recording CSV (atomically: a temporary file renamed into place) and its sidecar."""
    p = _writable_recording_path(path)
    tmp = p.with_name(p.name + ".tmp")
    side = sidecar_path(p)
    side_tmp = side.with_name(side.name + ".tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with tmp.open("w", newline="") as fh:
            csv.writer(fh, lineterminator="\n").writerow(list(COLUMNS) + list(rec.extra))
            _write_body(fh, rec, slice(0, len(rec)))
        # both files are complete before either replaces the old one; the sidecar goes
        # first, so a sidecar that cannot be written leaves the old recording untouched
        if rec.metadata:
            side_tmp.write_text(_metadata_text(rec.metadata))
            os.replace(side_tmp, side)
        os.replace(tmp, p)
    except OSError as err:
        _remove(tmp, side_tmp)
        where = side if err.filename in (str(side), str(side_tmp)) else p
        raise RecordingError(f"{where}: cannot write: {err.strerror or err}") from err
    except BaseException:  # Ctrl-C, SIGTERM: the previous file stays, no .tmp beside it
        _remove(tmp, side_tmp)
        raise
    return p


class RecordingWriter:
    """Incremental recording writer for live data: a crash leaves a valid file.

    Rows are appended as they come and flushed to the operating system at least every
    ``flush_interval_s``; every row written is complete, so a reader sees a valid recording of
    everything up to the last flush whatever happens to the process.

    Parameters
    ----------
    path : str or Path
        CSV to create (its sidecar gets ``metadata``).
    extra_columns : sequence of str
        Names of extra columns after the pinned ones.
    metadata : Mapping, optional
        Written to the sidecar at open and again at close.
    flush_interval_s : float
        Longest time between flushes [s].
    """

    def __init__(self, path: str | Path, extra_columns: Sequence[str] = (),
                 metadata: Mapping[str, Any] | None = None, flush_interval_s: float = 0.2,
                 fsync: bool = False) -> None:
        self.path = _writable_recording_path(path)
        self.extra_columns = tuple(extra_columns)
        self.metadata = dict(metadata or {})
        self.flush_interval_s = flush_interval_s
        self.fsync = fsync
        self.rows = 0
        self._last_t = -math.inf
        self._last_flush = time.monotonic()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self.path.open("w", newline="")
        except OSError as err:
            raise RecordingError(f"{self.path}: cannot create: {err.strerror or err}") from err
        self._csv = csv.writer(self._fh, lineterminator="\n")
        self._csv.writerow(list(COLUMNS) + list(self.extra_columns))
        self.flush()
        if self.metadata:
            write_metadata(self.path, self.metadata)

    def write(self, t_s: float, commands=(math.nan,) * 3, wheel_rpm=(math.nan,) * 4,
              pose=(math.nan,) * 3, extra: Sequence[Any] = ()) -> None:
        """Append one row; ``t_s`` must exceed the previous row's time."""
        if not t_s > self._last_t:
            raise RecordingError(
                f"{self.path}: time {t_s:g} does not increase (previous {self._last_t:g})")
        if len(extra) != len(self.extra_columns):
            raise RecordingError(f"{self.path}: {len(extra)} extra values for "
                                 f"{len(self.extra_columns)} extra columns")
        self._last_t = t_s
        extra_text = [format_value(v) if isinstance(v, float) else str(v) for v in extra]
        try:
            self._csv.writerow(_row(t_s, [*commands, *wheel_rpm, *pose], extra_text))
        except OSError as err:  # a full buffer written to a full disk
            raise self._write_error(err) from err
        self.rows += 1
        self.tick()

    def tick(self) -> None:
        """Flush when the flush interval has passed (call it also while no rows come)."""
        now = time.monotonic()
        if now - self._last_flush >= self.flush_interval_s:
            self.flush()
            self._last_flush = now

    def _write_error(self, err: OSError) -> RecordingError:
        return RecordingError(f"{self.path}: cannot write: {err.strerror or err}")

    def flush(self) -> None:
        """Push written rows to the operating system (and to disk with ``fsync``).

        Raises
        ------
        RecordingError
            When they cannot be written (a full disk, a removed folder).
        """
        if self._fh.closed:
            return
        try:
            self._fh.flush()
            if self.fsync:
                os.fsync(self._fh.fileno())
        except OSError as err:
            raise self._write_error(err) from err

    def close(self, metadata_updates: Mapping[str, Any] | None = None) -> None:
        """Flush, close, and rewrite the sidecar with ``metadata_updates`` merged in.

        Whatever fails, the file is closed and the sidecar written (with ``write_error``
        when the last rows could not be); then the first failure is raised as a
        :class:`RecordingError`. Rows flushed before stay readable.
        """
        if self._fh.closed:
            return
        failure: RecordingError | None = None
        try:
            self.flush()
        except RecordingError as err:
            failure = err
        try:
            self._fh.close()
        except OSError as err:  # the buffer's last rows, again
            failure = failure or self._write_error(err)
        if metadata_updates:
            self.metadata.update(metadata_updates)
        if failure is not None:
            self.metadata["write_error"] = str(failure)
        if self.metadata:
            try:
                write_metadata(self.path, self.metadata)
            except RecordingError as err:
                failure = failure or err
        if failure is not None:
            raise failure

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
