"""Format ``text``: delimited or whitespace-separated numeric logs, mapped by a MAP.toml.

The map (schema pinned in docs/formats-import.md) says which source column is which
recording column, in which unit and with which sign; the layout (delimiter, header row, comment
lines) is detected unless the map's ``[file]`` table states it. Parsing is numpy's C reader over
the whole file (no per-row Python), so an hour at 1 kHz imports in seconds (bench/bench_import.py).
"""

from __future__ import annotations

import codecs
import csv
import io
import math
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, RecordingError
from ..io.recording import Recording
from ..io.time_repair import (
    DEFAULT_MAX_GAP_PERIODS,
    MIN_DEFAULT_MAX_GAP_S,
    decimal_resolution,
    detect_resolution,
    repair_time,
)
from ..io.toml_config import load_toml
from ..units import DPS_PER_RPM, SPEED_UNITS, TIME_UNITS_S, speed_to_rpm
from . import ImportResult

NAME = "text"
#: Claims any numeric text; ``auto`` picks it only when no specific format claims the file.
GENERIC = True

#: Delimiters tried, in order, on the first data line ("whitespace" is the fallback).
DELIMITERS = (",", ";", "\t", "|")
DEFAULT_COMMENTS = ("#", "%")
ANGLE_UNITS = {"deg": 1.0, "rad": 180.0 / math.pi}
TURN_UNITS = {"deg/s": 1.0, "rad/s": 180.0 / math.pi, "rpm": DPS_PER_RPM}
#: Map keys, per table (anything else is refused: a misspelt key must not be ignored).
_KEYS = {
    "": {"format", "file", "time", "wheels", "commands"},
    "file": {"delimiter", "header", "comments", "skip_lines", "encoding"},
    "time": {"column", "unit", "period_s", "start_s", "resolution", "wrap", "max_gap_s"},
    "wheels": {"counts_per_rev", "wheel1", "wheel2", "wheel3", "wheel4"},
    "commands": {"n", "omega", "theta", "setpoint", "wheel1", "wheel2", "wheel3", "wheel4",
                 "counts_per_rev", "k", "robot", "residual_tolerance_rpm"},
    "column": {"column", "value", "unit", "sign", "counts_per_rev"},
}


@dataclass(frozen=True)
class Layout:
    """How a text log is laid out.

    Attributes
    ----------
    delimiter : str or None
        Field separator; None for runs of whitespace.
    names : tuple of str
        Column names (from the header row or a commented header), empty when none.
    n_columns : int
        Fields per data row.
    data_line : int
        0-based line number of the first data row.
    comments : tuple of str
        Comment prefixes.
    """

    delimiter: str | None
    names: tuple[str, ...]
    n_columns: int
    data_line: int
    comments: tuple[str, ...]


def is_number(text: str) -> bool:
    """Whether ``text`` is one number as loggers write them (Python's ``1_0`` is not)."""
    return "_" not in text and _float_like(text)


def _float_like(text: str) -> bool:
    """Whether Python reads ``text`` as a number (``1_0`` included): the layout's test (a
    header, data lines), so that a mistyped value is named as such, not taken for a header
    and its row dropped."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    return [f.strip() for f in next(csv.reader([line], delimiter=delimiter))]


def _guess_delimiter(line: str) -> str | None:
    """The delimiter of a line: of :data:`DELIMITERS` present, the first that splits it into
    numbers (or, for a header, into fields without inner blanks); else whitespace."""
    present = [d for d in DELIMITERS
               if d in line and not any(len(f.split()) > 1 for f in line.split(d))]
    for d in present:
        if all(f.strip() == "" or _float_like(f) for f in line.split(d)):
            return d
    return present[0] if present else None


def _decode(head: bytes, encoding: str = "utf-8-sig") -> str | None:
    try:
        return head.decode(encoding)
    except UnicodeDecodeError as err:
        if err.start > len(head) - 4:  # a multi-byte character cut at the end of the head
            return head[: err.start].decode(encoding)
        return None


def detect_layout(lines: list[str], *, delimiter: str | None = "auto", header: Any = "auto",
                  comments=DEFAULT_COMMENTS, skip_lines: int = 0, where: str = "",
                  wanted: tuple[str, ...] = ()) -> Layout:
    """The layout of a log from its first lines.

    A header row is the first non-comment line when ``header`` is true, or, with ``"auto"``,
    when one of its fields is not a number. Without one, the last comment line before the data
    whose fields (after the comment mark) are as many as the data's and not all numbers names
    the columns (a ``% time w1 w2`` line); of several such lines (names, then units: ``% s
    rad/s rad/s``), the last that holds every name in ``wanted`` (the names a map uses).
    """
    comments = tuple(comments)
    pending_comment: str | None = None
    comment_lines: list[str] = []
    i = skip_lines
    while i < len(lines):
        s = lines[i].strip()
        if not s:
            i += 1
            continue
        mark = next((c for c in comments if s.startswith(c)), None)
        if mark is not None:
            comment_lines.append(s[len(mark):].strip())
            i += 1
            continue
        pending_comment = s
        break
    if pending_comment is None:
        raise RecordingError(f"{where}: no data rows (only comments or blank lines)")
    first = pending_comment
    delim = _guess_delimiter(first) if delimiter == "auto" else (
        None if delimiter in ("whitespace", " ") else delimiter)
    fields = _split(first, delim)
    is_header = (not all(_float_like(f) for f in fields if f != "")) if header == "auto" \
        else bool(header)
    names: tuple[str, ...] = ()
    data_line = i
    if is_header:
        names = tuple(fields)
        data_line = i + 1
        for _ in range(3):  # the header's own lines: a units row (s, rad/s ...) or two
            while data_line < len(lines) and (not lines[data_line].strip() or any(
                    lines[data_line].strip().startswith(c) for c in comments)):
                data_line += 1
            if data_line >= len(lines):
                break
            row = _split(lines[data_line].strip(), delim)
            if len(row) != len(names) or any(f == "" or _float_like(f) for f in row):
                break
            data_line += 1
        if data_line >= len(lines):
            raise RecordingError(f"{where}: a header row but no data rows")
        n_columns = len(_split(lines[data_line].strip(), delim))
        if n_columns != len(names):
            raise RecordingError(f"{where}, line {data_line + 1}: {n_columns} fields, the header "
                                 f"row (line {i + 1}) names {len(names)}")
    else:
        n_columns = len(fields)
        candidates = []
        for c in reversed(comment_lines):
            cand = _split(c, delim) if delim is not None else c.split()
            if len(cand) != n_columns and delim is not None:
                cand = c.split()  # '% t w1 w2' above comma-separated data
            if len(cand) == n_columns and not all(_float_like(f) for f in cand):
                candidates.append(tuple(cand))
        names = next((c for c in candidates if set(wanted) <= set(c)),
                     candidates[0] if candidates else ())
    return Layout(delim, names, n_columns, data_line, comments)


def sniff(path: Path, head: bytes, encoding: str = "utf-8-sig") -> bool:
    """Whether the file is numeric text (in ``encoding``, the map's ``file.encoding``): some
    line, not a comment, of numbers only."""
    try:
        text = _decode(head, encoding)
    except LookupError:
        return False
    if text is None or "\x00" in text:
        return False
    lines = text.splitlines()
    if len(head) >= 65536 and lines:
        lines = lines[:-1]  # the last line may be cut
    try:
        lay = detect_layout(lines[:200], where=str(path))
    except (RecordingError, csv.Error):
        return False
    data = lines[lay.data_line] if lay.data_line < len(lines) else ""
    fields = _split(data.strip(), lay.delimiter)
    return bool(fields) and all(f == "" or _float_like(f) for f in fields)


# --- the map -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Column:
    """One mapped value: a source column (or a constant), its unit and sign."""

    key: str
    column: str | int | None
    value: float | None
    unit: str
    sign: float
    counts_per_rev: float | None


def _check_keys(table: dict, kind: str, where: str) -> None:
    extra = set(table) - _KEYS[kind]
    if extra:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(extra))} "
                          f"(known: {', '.join(sorted(_KEYS[kind]))})")


def _column(spec: Any, key: str, units, where: str, default_unit: str | None = None,
            counts_per_rev: float | None = None) -> Column:
    if isinstance(spec, (str, int)) and not isinstance(spec, bool):
        spec = {"column": spec}
    if not isinstance(spec, dict):
        raise ConfigError(f"{where}: key '{key}' must be a table like "
                          "{ column = \"name\" or 0, unit = \"...\", sign = 1 }")
    _check_keys(spec, "column", f"{where}: '{key}'")
    col, value = spec.get("column"), spec.get("value")
    if (col is None) == (value is None):
        raise ConfigError(f"{where}: '{key}' needs exactly one of 'column' (a name or 0-based "
                          "index) and 'value' (a constant)")
    if col is not None and (isinstance(col, bool) or not isinstance(col, (str, int))
                            or (isinstance(col, int) and col < 0)):
        raise ConfigError(f"{where}: '{key}.column' must be a name or a 0-based index")
    if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
        raise ConfigError(f"{where}: '{key}.value' must be a number")
    unit = spec.get("unit", default_unit)
    if unit not in units:
        raise ConfigError(f"{where}: '{key}.unit' must be one of {', '.join(units)}"
                          + ("" if unit is None else f", got {unit!r}"))
    sign = spec.get("sign", 1)
    if sign not in (1, -1):
        raise ConfigError(f"{where}: '{key}.sign' must be 1 or -1, got {sign!r}")
    cpr = spec.get("counts_per_rev", counts_per_rev)
    if unit == "counts/s" and not (isinstance(cpr, (int, float)) and cpr > 0):
        raise ConfigError(f"{where}: '{key}' in counts/s needs counts_per_rev (a positive "
                          "number, in the column or its table)")
    return Column(key, col, None if value is None else float(value), unit, float(sign), cpr)


@dataclass(frozen=True)
class TextMap:
    """A parsed MAP.toml (see docs/formats-import.md)."""

    file: dict
    time: Column | None
    period_s: float | None
    start_s: float
    resolution: float | None
    wrap: float | None
    max_gap_s: float | None
    wheels: dict[int, Column]
    command_mode: str  # "n_omega_theta", "setpoint", "wheels" or "none"
    commands: dict[str, Column]
    k: float | None
    robot: str | None
    residual_tolerance_rpm: float | None


#: The largest ``time.start_s`` a map may give [s] (Unix time is about 1.8e9 s; at 1e10 s a
#: double still resolves about 2 us).
MAX_START_S = 1e10


def _number(table: dict, key: str, where: str, *, positive: bool = True) -> float | None:
    v = table.get(key)
    if v is None:
        return None
    if (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
            or (positive and not v > 0)):
        raise ConfigError(f"{where}: '{key}' must be a finite {'positive ' if positive else ''}"
                          "number")
    return float(v)


def load_map(path: str | Path) -> TextMap:
    """Read and check a MAP.toml for the text format."""
    where = str(path)
    doc = load_toml(path)
    _check_keys(doc, "", where)
    if doc.get("format", NAME) != NAME:
        raise ConfigError(f"{where}: a map for format '{doc['format']}', not '{NAME}'")
    tables = {}
    for name in ("file", "time", "wheels", "commands"):
        t = doc.get(name, {})
        if not isinstance(t, dict):
            raise ConfigError(f"{where}: '{name}' must be a table [{name}]")
        _check_keys(t, name, f"{where}: [{name}]")
        tables[name] = t
    tt = tables["time"]
    time_col = None
    if "column" in tt:
        time_col = _column({"column": tt["column"], "unit": tt.get("unit", "s")}, "time",
                           tuple(TIME_UNITS_S), f"{where}: [time]")
    period = _number(tt, "period_s", f"{where}: [time]")
    if (time_col is None) == (period is None):
        raise ConfigError(f"{where}: [time] needs exactly one of 'column' (the time column) and "
                          "'period_s' (the fixed sample period when there is none)")
    with_column = sorted(k for k in ("unit", "resolution", "wrap", "max_gap_s") if k in tt)
    if time_col is None and with_column:
        # not ignored: 'unit = "ms"' beside 'period_s = 2' would otherwise give 2 s periods
        raise ConfigError(f"{where}: [time] {', '.join(with_column)} describe(s) a time column; "
                          "with 'period_s' (in seconds) there is none")
    wt = tables["wheels"]
    cpr = _number(wt, "counts_per_rev", f"{where}: [wheels]")
    wheels = {}
    for j in range(1, 5):
        if f"wheel{j}" in wt:
            wheels[j] = _column(wt[f"wheel{j}"], f"wheel{j}", SPEED_UNITS, f"{where}: [wheels]",
                                counts_per_rev=cpr)
    ct = tables["commands"]
    ccpr = _number(ct, "counts_per_rev", f"{where}: [commands]") or cpr
    forms = {"n_omega_theta": [k for k in ("n", "omega", "theta") if k in ct],
             "setpoint": [k for k in ("setpoint",) if k in ct],
             "wheels": [k for k in ("wheel1", "wheel2", "wheel3", "wheel4") if k in ct]}
    given = [f for f, keys in forms.items() if keys]
    if len(given) > 1:
        raise ConfigError(f"{where}: [commands] mixes forms ({', '.join(given)}); give n, omega "
                          "and theta, or setpoint, or wheel1..wheel4")
    mode = given[0] if given else "none"
    need = {"n_omega_theta": ("n", "omega", "theta"), "setpoint": ("setpoint",),
            "wheels": ("wheel1", "wheel2", "wheel3", "wheel4"), "none": ()}[mode]
    missing = [k for k in need if k not in ct]
    if missing:
        raise ConfigError(f"{where}: [commands] is missing {', '.join(missing)} (the {mode} form "
                          f"needs {', '.join(need)})")
    cw = f"{where}: [commands]"
    commands = {}
    for key in need:
        if key == "omega":
            commands[key] = _column(ct[key], key, tuple(TURN_UNITS), cw, "deg/s")
        elif key == "theta":
            commands[key] = _column(ct[key], key, tuple(ANGLE_UNITS), cw, "deg")
        else:
            commands[key] = _column(ct[key], key, SPEED_UNITS, cw, counts_per_rev=ccpr)
    if "k" in ct and "robot" in ct:
        raise ConfigError(f"{cw}: give 'k' or 'robot', not both")
    robot = ct.get("robot")
    if robot is not None and not isinstance(robot, str):
        raise ConfigError(f"{cw}: 'robot' must be a profile name or file")
    start = _number(tt, "start_s", f"{where}: [time]", positive=False) or 0.0
    if abs(start) > MAX_START_S:
        raise ConfigError(f"{where}: [time] 'start_s' = {start:g} s: beyond {MAX_START_S:g} s "
                          "a time stamp loses its microseconds")
    return TextMap(tables["file"], time_col, period, start,
                   _number(tt, "resolution", f"{where}: [time]"),
                   _number(tt, "wrap", f"{where}: [time]"),
                   _number(tt, "max_gap_s", f"{where}: [time]"), wheels, mode, commands,
                   _number(ct, "k", cw), robot,
                   _number(ct, "residual_tolerance_rpm", cw))


# --- parsing -----------------------------------------------------------------------------------

def _index(col: Column, layout: Layout, where: str) -> int:
    if isinstance(col.column, int):
        if col.column >= layout.n_columns:
            raise ConfigError(f"{where}: '{col.key}' is column {col.column}, the log has "
                              f"{layout.n_columns} (0..{layout.n_columns - 1})")
        return col.column
    if col.column in layout.names:
        return layout.names.index(col.column)
    known = (", ".join(layout.names) if layout.names
             else "none: the log has no header; use 0-based indices")
    raise ConfigError(f"{where}: '{col.key}' names column '{col.column}', not in the log "
                      f"(columns: {known})")


def _bad_line(path: Path, layout: Layout, usecols: list[int], encoding: str) -> str:
    """The first data line that numpy could not read, as a one-line message (slow path)."""
    with path.open(encoding=encoding, errors="replace") as fh:
        for ln, line in enumerate(fh, start=1):
            if ln <= layout.data_line:
                continue
            s = line.strip()
            if not s or any(s.startswith(c) for c in layout.comments):
                continue
            try:
                fields = _split(s, layout.delimiter)
            except csv.Error as err:
                return f"{path}, line {ln}: {err}"
            if len(fields) != layout.n_columns:
                return f"{path}, line {ln}: {len(fields)} fields, expected {layout.n_columns}"
            for c in usecols:
                if fields[c] != "" and not is_number(fields[c]):
                    name = layout.names[c] if layout.names else str(c)
                    return f"{path}, line {ln}, column {name}: not a number: {fields[c]!r}"
    return ""


def _line_of(path: Path, layout: Layout, row: int, encoding: str) -> int:
    """The 1-based file line of data row ``row`` (0-based; for error messages only)."""
    seen = -1
    with path.open(encoding=encoding, errors="replace") as fh:
        for ln, line in enumerate(fh, start=1):
            s = line.strip()
            if ln <= layout.data_line or not s or any(s.startswith(c) for c in layout.comments):
                continue
            seen += 1
            if seen == row:
                return ln
    return layout.data_line + row + 1


def _is_cut(line: bytes, layout: Layout, encoding: str) -> bool:
    """Whether a last line without its newline was cut off mid-row (a logger stopped while
    writing): fewer fields than the data, or a field that is not a number."""
    text = line.decode(encoding, "replace").strip()
    if not text or any(text.startswith(c) for c in layout.comments):
        return False
    try:
        fields = _split(text, layout.delimiter)
    except csv.Error:
        return True
    return len(fields) < layout.n_columns or not all(f == "" or is_number(f) for f in fields)


def _fill_blank_fields(raw: bytes, d: bytes) -> bytes:
    """Empty fields (also padded with blanks, or at the very end) as ``nan``.

    numpy's reader wants a token in every field. The common cases (``,,`` and a delimiter at
    the end of a line) are plain replacements; fields of blanks only (fixed-width loggers pad
    them) need the regular expression, which is slower, so it runs only when they are there.
    """
    if d + d in raw or d + b"\n" in raw or b"\n" + d in raw or d + b"\r" in raw \
            or raw.startswith(d) or raw.endswith(d):
        raw = raw.replace(d + d, d + b"nan" + d).replace(d + d, d + b"nan" + d)
        raw = raw.replace(d + b"\r", d + b"nan\r").replace(d + b"\n", d + b"nan\n")
        raw = raw.replace(b"\n" + d, b"\nnan" + d)
        if raw.startswith(d):
            raw = b"nan" + raw
        if raw.endswith(d):
            raw += b"nan"
    e = re.escape(d)
    blank = re.compile(rb"(?m)(?:(?<=" + e + rb")[ \t]+(?=" + e + rb"|\r?$)|^[ \t]+(?=" + e
                       + rb"))")
    if d + b" " in raw or d + b"\t" in raw or b" " + d in raw or b"\t" + d in raw:
        raw = blank.sub(b"nan", raw)
    return raw


#: Bytes parsed at a time: the file is streamed, never held whole in memory.
CHUNK_BYTES = 1 << 25


def _parse_block(raw: bytes, layout: Layout, encoding: str) -> np.ndarray:
    """Every column of the data rows in ``raw`` (whole lines), shape ``(rows, n_columns)``."""
    # numpy's C reader takes one one-character comment mark; a list of marks sends every line
    # through Python (several times slower), so only the marks the block contains count
    marks = [c for c in layout.comments if c.encode(encoding, "replace") in raw]
    comments: str | list[str] | None = (marks[0] if len(marks) == 1 and len(marks[0]) == 1
                                        else marks or None)
    d = (layout.delimiter or "").encode()
    if d:
        # quoted numbers ("1.5", as spreadsheets export them): the csv module's reading
        raw = raw.replace(b'"', b"") if b'"' in raw else raw
        raw = _fill_blank_fields(raw, d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # a block of comment lines only
        # every column is read (not only the used ones): numpy then refuses a row with
        # extra fields
        table = np.loadtxt(io.BytesIO(raw), delimiter=layout.delimiter, encoding=encoding,
                           comments=comments, ndmin=2, dtype=float)
    if not table.size:
        return np.empty((0, layout.n_columns))
    if table.shape[1] != layout.n_columns:
        raise ValueError(f"{table.shape[1]} fields, expected {layout.n_columns}")
    return table


def ascii_compatible(encoding: str) -> bool:
    """Whether numbers, delimiters, comment marks and newlines are the same bytes in
    ``encoding`` as in ASCII (UTF-8, Latin-1, cp1252 ...; not UTF-16 or UTF-32), so that the
    file can be parsed as bytes."""
    probe = "0123456789+-.eEnaNA,;|\t \r\n#%"
    try:
        return probe.encode(encoding) == probe.encode("ascii")
    except (UnicodeError, LookupError):
        return False


def _byte_blocks(path: Path, data_line: int, utf8: bool):
    """The file's data lines as raw byte blocks of about :data:`CHUNK_BYTES`."""
    with path.open("rb") as fh:
        for _ in range(data_line):
            fh.readline()
        first = data_line == 0
        while block := fh.read(CHUNK_BYTES):
            if first and utf8:
                block = block.removeprefix(b"\xef\xbb\xbf")
            first = False
            yield block


def _transcoded_blocks(path: Path, data_line: int, encoding: str):
    """The file's data lines decoded from ``encoding`` and encoded as UTF-8, in blocks: a
    text in an encoding whose bytes are not ASCII's (UTF-16 from a Windows logger) is parsed
    as UTF-8, streamed as the byte path is."""
    with path.open(encoding=encoding, newline="") as fh:
        for _ in range(data_line):
            fh.readline()
        while text := fh.read(CHUNK_BYTES // 4):
            yield text.removeprefix("\ufeff").encode("utf-8")


def read_table(path: Path, layout: Layout, usecols: list[int],
               encoding: str = "utf-8-sig") -> tuple[np.ndarray, str]:
    """The used columns of every data row, shape ``(T, len(usecols))``; empty fields are NaN.

    The file is parsed in blocks of whole lines (:data:`CHUNK_BYTES`). A last line cut off
    mid-row (:func:`_is_cut`) is dropped and returned (else "") for the caller's note.
    """
    utf8 = encoding.lower().replace("_", "-") in ("utf-8-sig", "utf-8", "utf8")
    as_bytes = ascii_compatible(encoding)
    # numpy decodes UTF-8 itself; the -sig codec would go line by line through Python
    enc = "utf-8" if utf8 or not as_bytes else encoding
    parts: list[np.ndarray] = []
    cut = ""
    try:
        blocks = (_byte_blocks(path, layout.data_line, utf8) if as_bytes
                  else _transcoded_blocks(path, layout.data_line, encoding))
        pending = b""
        for block in blocks:
            data = pending + block
            end = data.rfind(b"\n") + 1
            data, pending = data[:end], data[end:]
            if data:
                parts.append(_parse_block(data, layout, enc)[:, usecols])
        if pending and _is_cut(pending, layout, enc):
            cut = pending.decode(enc, "replace").strip()
        elif pending:
            parts.append(_parse_block(pending, layout, enc)[:, usecols])
    except OSError as err:
        raise RecordingError(f"{path}: cannot read: {err.strerror or err}") from err
    except UnicodeDecodeError as err:  # before ValueError, its base class
        raise RecordingError(f"{path}: not text in {encoding}: {err.reason}") from None
    except (ValueError, IndexError) as err:
        msg = _bad_line(path, layout, usecols, encoding)
        raise RecordingError(msg or f"{path}: {err}") from None
    table = np.concatenate(parts) if parts else np.empty((0, len(usecols)))
    return table, cut


# --- commands from wheel setpoints ---------------------------------------------------------------

def wheel_setpoints_to_commands(wheels_rpm: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """``(n, omega, theta)`` whose wheel targets are the setpoints, and the residual.

    The exact inverse of :func:`mecanum_hil.model.kinematics.command_to_wheels` on its image:
    the body twist is the forward kinematics (least squares) of the four setpoints; ``omega =
    6 wz``, ``theta = atan2(vx, -vy)`` and ``n = |v| (|sin theta| + |cos theta|)``. A twist with
    no translation gets ``theta = 90``. Four setpoints outside the 3-D image of the inverse
    kinematics leave a residual ``r (1, 1, -1, -1)`` with ``r = (w1 + w2 - w3 - w4) / 4``.

    Returns
    -------
    commands : ndarray, shape (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])``.
    residual_rpm : ndarray, shape (T,)
        ``|r|``: how far each row's setpoints are from the image [rpm].
    """
    # The importer sits at the data edge but must invert the model's kinematics exactly, so
    # it uses them rather than a second copy.
    from ..model.kinematics import twist_to_wheels, wheels_to_twist

    twist = wheels_to_twist(wheels_rpm, k)
    residual = np.max(np.abs(wheels_rpm - twist_to_wheels(twist, k)), axis=-1)
    vx, vy, wz = twist[..., 0], twist[..., 1], twist[..., 2]
    v = np.hypot(vx, vy)
    still = v <= 1e-9 * np.maximum(1.0, np.max(np.abs(wheels_rpm), axis=-1))
    th = np.where(still, np.pi / 2, np.arctan2(vx, -vy))
    n = np.where(still, 0.0, v * (np.abs(np.sin(th)) + np.abs(np.cos(th))))
    theta = np.mod(np.rad2deg(th), 360.0)
    return np.stack([n, wz * DPS_PER_RPM, theta], axis=-1), residual


def _kinematic_k(m: TextMap) -> float:
    if m.k is not None:
        return m.k
    from ..model.robot import load_robot_profile

    return load_robot_profile(m.robot or "tdam-stm").k


# --- read --------------------------------------------------------------------------------------

def read(path: Path, *, map_path: Path | None = None) -> ImportResult:
    """Import a text log with a MAP.toml (docs/formats-import.md)."""
    path = Path(path)
    if map_path is None:
        raise ConfigError("format 'text' needs --map MAP.toml (which column is which; "
                          "docs/formats-import.md)")
    m = load_map(map_path)
    tab = _MappedTable.load(path, m, str(map_path))
    notes: list[str] = []
    if tab.cut:
        notes.append(f"last line cut off mid-row (no newline at the end): dropped: "
                     f"{tab.cut[:60]!r}")
    t, time_meta = _times(m, tab, notes)
    wheel = np.full((tab.n, 4), np.nan)
    for j, col in m.wheels.items():
        wheel[:, j - 1] = speed_to_rpm(tab.raw(col), col.unit, col.counts_per_rev) * col.sign
    commands = _commands(m, tab, notes)
    named = ([("time", m.time)] if m.time else []) + [
        (f"wheels.wheel{j}", c) for j, c in m.wheels.items()] + [
        (f"commands.{key}", c) for key, c in m.commands.items()]
    metadata: dict[str, Any] = {
        "source": str(path), "format": NAME, "map": str(map_path),
        "columns": {name: {"column": c.column, "value": c.value, "unit": c.unit,
                           "sign": c.sign} for name, c in named},
        "command_form": m.command_mode, "time_repair": time_meta, "notes": list(notes),
    }
    rec = Recording(t, commands, wheel, np.full((tab.n, 3), np.nan), {}, metadata)
    return ImportResult(rec, tuple(notes))


#: Names a map may give for a delimiter that is not one printable character.
_DELIMITER_NAMES = {"tab": "\t", "\\t": "\t", "space": "whitespace"}


def _file_options(f: Mapping[str, Any], where: str) -> tuple[str, str | None, Any, list, int]:
    """The map's ``[file]`` table checked: ``(encoding, delimiter, header, comments,
    skip_lines)``; a wrong value is a :class:`ConfigError` naming the map and the key."""
    encoding = f.get("encoding", "utf-8-sig")
    try:
        if not isinstance(encoding, str):
            raise LookupError
        codecs.lookup(encoding)
    except LookupError:
        raise ConfigError(f"{where}: file.encoding: unknown encoding {encoding!r} (for example "
                          "'utf-8', 'latin-1', 'cp1252')") from None
    delimiter = f.get("delimiter", "auto")
    if isinstance(delimiter, str):
        delimiter = _DELIMITER_NAMES.get(delimiter.lower(), delimiter)
    if not (delimiter in ("auto", "whitespace")
            or (isinstance(delimiter, str) and len(delimiter) == 1
                and delimiter not in "\"\r\n")):
        raise ConfigError(f"{where}: file.delimiter must be one character (',', ';', '|'), "
                          f"'tab', 'whitespace' or 'auto', got {delimiter!r}")
    header = f.get("header", "auto")
    if not (isinstance(header, bool) or header == "auto"):
        raise ConfigError(f"{where}: file.header must be true, false or 'auto', got {header!r}")
    skip = f.get("skip_lines", 0)
    if isinstance(skip, bool) or not isinstance(skip, int) or skip < 0:
        raise ConfigError(f"{where}: file.skip_lines must be a whole number >= 0, got {skip!r}")
    comments = f.get("comments", list(DEFAULT_COMMENTS))
    if isinstance(comments, str):
        comments = [comments]
    if not (isinstance(comments, list) and all(isinstance(c, str) and c for c in comments)):
        raise ConfigError(f"{where}: file.comments must be a string or a list of strings")
    return encoding, delimiter, header, comments, skip


@dataclass
class _MappedTable:
    """The mapped columns of a text log, read as numbers, and where each row came from."""

    path: Path
    where: str
    encoding: str
    lines: list[str]
    layout: Layout
    used: list[int]
    table: np.ndarray
    cut: str

    @classmethod
    def load(cls, path: Path, m: TextMap, where: str) -> _MappedTable:
        """Read the columns ``m`` maps from ``path`` (``where``: the map, for errors)."""
        encoding, delimiter, header, comments, skip_lines = _file_options(m.file, where)
        try:
            with path.open("rb") as fh:
                head = fh.read(1 << 20)
        except OSError as err:
            raise RecordingError(f"{path}: cannot read: {err.strerror or err}") from err
        text = _decode(head, encoding)
        if text is None or "\x00" in text:
            raise RecordingError(f"{path}: not a text file (in {encoding})")
        lines = text.splitlines()
        if len(head) >= 1 << 20:
            lines = lines[:-1]
        cols: list[Column] = ([m.time] if m.time else []) + list(m.wheels.values()) + list(
            m.commands.values())
        layout = detect_layout(lines, delimiter=delimiter, header=header, comments=comments,
                               skip_lines=skip_lines, where=str(path),
                               wanted=tuple({c.column for c in cols
                                             if isinstance(c.column, str)}))
        used = sorted({_index(c, layout, where) for c in cols if c.column is not None})
        table, cut = read_table(path, layout, used or [0], encoding)
        if table.shape[0] == 0:
            raise RecordingError(f"{path}: no data rows")
        if np.isinf(table).any():
            i, j = (int(v[0]) for v in np.nonzero(np.isinf(table)))
            raise RecordingError(f"{path}, line {_line_of(path, layout, i, encoding)}, column "
                                 f"{layout.names[used[j]] if layout.names else used[j]}: "
                                 "infinite value (leave missing values empty or nan)")
        return cls(path, where, encoding, lines, layout, used, table, cut)

    @property
    def n(self) -> int:
        return self.table.shape[0]

    def raw(self, col: Column) -> np.ndarray:
        """The column's values as written (a constant's, repeated)."""
        if col.column is None:
            return np.full(self.n, col.value)
        return self.table[:, self.used.index(_index(col, self.layout, self.where))]

    def row_name(self, i: int) -> str:
        return f"{self.path}, line {_line_of(self.path, self.layout, i, self.encoding)}"


def _first_row_of(mask: np.ndarray) -> int:
    return int(np.argmax(mask))


def _times(m: TextMap, tab: _MappedTable, notes: list[str]) -> tuple[np.ndarray, dict]:
    """Row times [s], repaired (resets, wraps, gaps), and what the repair did."""
    n = tab.n
    if m.time is None:
        t = m.start_s + m.period_s * np.arange(n)
        return t, {"period_s": m.period_s, "note": "no time column: fixed period"}
    t_raw = tab.raw(m.time) * m.time.sign
    if not np.isfinite(t_raw).all():
        i = _first_row_of(~np.isfinite(t_raw))
        raise RecordingError(f"{tab.row_name(i)}: time is missing")
    scale = TIME_UNITS_S[m.time.unit]
    res_src = m.resolution
    if res_src is None and isinstance(m.time.column, (str, int)):
        # what the log writes (0.341 -> 1 ms), from the first data lines
        layout = tab.layout
        j = _index(m.time, layout, tab.where)
        sample = [_split(x.strip(), layout.delimiter) for x in
                  tab.lines[layout.data_line: layout.data_line + 2000]]
        res_src = decimal_resolution(
            f[j] for f in sample
            if len(f) > j and not any(f[0].startswith(c) for c in layout.comments))
    if res_src is None:
        res_src = detect_resolution(t_raw)
    t0 = t_raw[0]
    period_guess = float(np.median(np.diff(t_raw))) * scale if n > 1 else 0.0
    max_gap = m.max_gap_s if m.max_gap_s is not None else max(
        MIN_DEFAULT_MAX_GAP_S, DEFAULT_MAX_GAP_PERIODS * max(period_guess, 0.0))
    rep = repair_time((t_raw - t0) * scale, resolution_s=res_src * scale,
                      max_gap_s=max_gap, wrap_s=None if m.wrap is None else m.wrap * scale,
                      row_name=tab.row_name)
    if rep.note:
        notes.append(rep.note)
    time_meta = {**rep.summary, "max_gap_s": max_gap, "source_unit": m.time.unit,
                 "first_stamp": float(t0)}
    return rep.t_s + m.start_s, time_meta


def _commands(m: TextMap, tab: _MappedTable, notes: list[str]) -> np.ndarray:
    """The commands ``(n [rpm], omega [deg/s], theta [deg])`` in the map's command form."""
    raw = tab.raw
    commands = np.full((tab.n, 3), np.nan)
    if m.command_mode == "n_omega_theta":
        c = m.commands
        commands[:, 0] = speed_to_rpm(raw(c["n"]), c["n"].unit, c["n"].counts_per_rev) \
            * c["n"].sign
        commands[:, 1] = raw(c["omega"]) * TURN_UNITS[c["omega"].unit] * c["omega"].sign
        commands[:, 2] = raw(c["theta"]) * ANGLE_UNITS[c["theta"].unit] * c["theta"].sign
    elif m.command_mode == "setpoint":
        c = m.commands["setpoint"]
        s = speed_to_rpm(raw(c), c.unit, c.counts_per_rev) * c.sign
        commands[:, 0] = np.abs(s)
        commands[:, 1] = 0.0
        commands[:, 2] = np.where(s < 0, 270.0, 90.0)
        commands[~np.isfinite(s)] = np.nan
    elif m.command_mode == "wheels":
        commands = _commands_from_wheel_setpoints(m, tab, notes)
    for j in range(3):
        bad = np.isinf(commands[:, j])
        if bad.any():
            raise RecordingError(f"{tab.row_name(_first_row_of(bad))}: command is infinite")
    if m.command_mode == "none":
        notes.append("no commands mapped: command columns left empty")
    return commands


def _commands_from_wheel_setpoints(m: TextMap, tab: _MappedTable,
                                   notes: list[str]) -> np.ndarray:
    """Commands from four wheel setpoints: their least-squares fit, refused when the
    setpoints are further off the kinematics' image than the map's tolerance."""
    sp = np.column_stack([
        speed_to_rpm(tab.raw(c), c.unit, c.counts_per_rev) * c.sign
        for c in (m.commands[f"wheel{j}"] for j in range(1, 5))])
    k = _kinematic_k(m)
    commands, residual = wheel_setpoints_to_commands(sp, k)
    finite = np.isfinite(residual)
    commands[~np.isfinite(sp).all(axis=1)] = np.nan
    scale = float(np.nanmax(np.abs(sp))) if np.isfinite(sp).any() else 0.0
    tol = m.residual_tolerance_rpm if m.residual_tolerance_rpm is not None else max(
        0.5, 0.01 * scale)
    worst = float(residual[finite].max()) if finite.any() else 0.0
    if worst > tol:
        i = _first_row_of(finite & (residual > tol))
        raise RecordingError(
            f"{tab.row_name(i)}: the four wheel setpoints are {residual[i]:.4g} rpm off the "
            f"kinematics' image (w1 + w2 - w3 - w4 must be 0; tolerance {tol:.4g} rpm, "
            "residual_tolerance_rpm in [commands])")
    if worst > 1e-9 * max(1.0, scale):
        notes.append(f"wheel setpoints off the kinematics' image by up to {worst:.4g} rpm "
                     f"(tolerance {tol:.4g} rpm): commands are their least-squares fit")
    return commands
