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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import RecordingError

COLUMNS = (
    "t_s", "n_cmd_rpm", "omega_cmd_dps", "theta_cmd_deg",
    "wheel1_rpm", "wheel2_rpm", "wheel3_rpm", "wheel4_rpm", "x_m", "y_m", "phi_deg",
)
COMMAND_COLUMNS = COLUMNS[1:4]
WHEEL_COLUMNS = COLUMNS[4:8]
POSE_COLUMNS = COLUMNS[8:11]


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


def read_recording(path: str | Path) -> Recording:
    """Read a recording (CSV and, when present, its JSON sidecar).

    Raises
    ------
    RecordingError
        For a missing file, a header that differs from the pinned columns, a row with the wrong
        number of fields, a non-numeric value, a missing time or time that does not increase;
        the message names the file, line and column. A last line cut off mid-row (no final
        newline: a crash while writing) is not an error: it is dropped, and the metadata's
        ``truncated_last_line`` holds it.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise RecordingError(f"{p}: file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise RecordingError(f"{p}: cannot read: {err}") from err
    text, truncated = _drop_cut_last_line(text)
    rows = csv.reader(io.StringIO(text))
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
    if len(set(extra_names)) != len(extra_names) or set(extra_names) & set(COLUMNS):
        raise RecordingError(f"{p}, line 1: duplicate column names")
    values: list[list[float]] = []
    extra: list[list[str]] = [[] for _ in extra_names]
    last_t = -math.inf
    line = 1
    try:
        for line, row in enumerate(rows, start=2):
            if not row or all(not f.strip() for f in row):
                continue
            if len(row) != len(header):
                raise RecordingError(
                    f"{p}, line {line}: {len(row)} fields, header has {len(header)}")
            nums = [_parse_float(row[i], f"{p}, line {line}, column '{COLUMNS[i]}'")
                    for i in range(len(COLUMNS))]
            t = nums[0]
            if math.isnan(t):
                raise RecordingError(f"{p}, line {line}, column 't_s': time is missing")
            if t <= last_t:
                raise RecordingError(
                    f"{p}, line {line}, column 't_s': time {t:g} does not increase "
                    f"(previous {last_t:g})")
            last_t = t
            values.append(nums)
            for j in range(len(extra_names)):
                extra[j].append(row[len(COLUMNS) + j])
    except csv.Error as err:
        raise RecordingError(f"{p}, line {line}: {err}") from err
    arr = np.array(values, dtype=float).reshape(-1, len(COLUMNS))
    metadata: dict[str, Any] = {}
    side = sidecar_path(p)
    if side.exists():
        try:
            metadata = json.loads(side.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise RecordingError(f"{side}: bad JSON sidecar: {err}") from err
        if not isinstance(metadata, dict):
            raise RecordingError(f"{side}: the sidecar must hold a JSON object")
    if truncated:
        metadata = {**metadata, "truncated_last_line": truncated}
    return Recording(arr[:, 0].copy(), arr[:, 1:4].copy(), arr[:, 4:8].copy(),
                     arr[:, 8:11].copy(), dict(zip(extra_names, extra, strict=True)), metadata)


def format_value(value: float, digits: int = 9) -> str:
    """A CSV field: empty for NaN, otherwise a compact round-trippable-enough number."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return f"{value:.{digits}g}"


def _row(t: float, values: Sequence[float], extra: Sequence[str]) -> list[str]:
    return [f"{t:.6f}"] + [format_value(float(v)) for v in values] + list(extra)


def write_metadata(path: str | Path, metadata: Mapping[str, Any]) -> Path:
    """Write the JSON sidecar of a recording."""
    side = sidecar_path(path)
    try:
        side.write_text(json.dumps(dict(metadata), indent=2, sort_keys=True, default=str) + "\n")
    except OSError as err:
        raise RecordingError(f"{side}: cannot write: {err.strerror or err}") from err
    return side


def write_recording(rec: Recording, path: str | Path) -> Path:
    """Write a recording CSV (atomically: a temporary file renamed into place) and its sidecar."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with tmp.open("w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(list(COLUMNS) + list(rec.extra))
            body = np.column_stack([rec.commands, rec.wheel_rpm, rec.pose])
            extra_cols = list(rec.extra.values())
            for i in range(len(rec)):
                w.writerow(_row(float(rec.t_s[i]), body[i], [c[i] for c in extra_cols]))
        os.replace(tmp, p)
    except OSError as err:
        raise RecordingError(f"{p}: cannot write: {err.strerror or err}") from err
    if rec.metadata:
        write_metadata(p, rec.metadata)
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
        self.path = Path(path)
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
        self._fh.flush()
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
        self._csv.writerow(_row(t_s, [*commands, *wheel_rpm, *pose], extra_text))
        self.rows += 1
        self.tick()

    def tick(self) -> None:
        """Flush when the flush interval has passed (call it also while no rows come)."""
        now = time.monotonic()
        if now - self._last_flush >= self.flush_interval_s:
            self.flush()
            self._last_flush = now

    def flush(self) -> None:
        """Push written rows to the operating system (and to disk with ``fsync``)."""
        if self._fh.closed:
            return
        self._fh.flush()
        if self.fsync:
            os.fsync(self._fh.fileno())

    def close(self, metadata_updates: Mapping[str, Any] | None = None) -> None:
        """Flush, close, and rewrite the sidecar with ``metadata_updates`` merged in."""
        if self._fh.closed:
            return
        self.flush()
        self._fh.close()
        if metadata_updates:
            self.metadata.update(metadata_updates)
        if self.metadata:
            write_metadata(self.path, self.metadata)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
