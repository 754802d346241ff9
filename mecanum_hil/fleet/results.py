"""The results table of a batch: one row per group, Parquet or CSV, and drift between periods.

Columns (pinned, in this order; docs/scale.md describes each):

- identity: ``group`` (robot), ``period`` (``""`` without ``--period``), ``command``;
- outcome: ``status`` (``ok``; ``partial``: some inputs were left out, named in ``error``;
  ``failed``: no numbers, ``error`` says why), ``n_inputs``, ``inputs`` (relative paths joined
  by ``;``);
- model: ``A``, ``A_lo``, ``A_hi``, ``B``, ``B_lo``, ``B_hi``, ``C``, ``C_lo``, ``C_hi`` (95 %
  intervals), ``effects`` (comma-separated names), ``rmse_rpm``, ``fit_percent``,
  ``rmse_initial_rpm``, ``unexplained``;
- shadow: ``alarms`` (count), ``alarm_inputs``, ``first_alarm_t_s``;
- drift against the robot's previous period with numbers: ``drift_A``, ``drift_B``,
  ``drift_C`` (this minus previous, same unit), ``drift_A_pct`` ... (relative [%]),
  ``effects_appeared``, ``effects_gone``, ``drifted`` (bool), ``drift_note``;
- ``error``; then ``warnings``, ``details`` (JSON), ``content_hash``, ``elapsed_s`` (the stage's
  own time on the worker [s]), ``worker``, ``finished_utc``, ``output``.

Missing numbers are empty in CSV and null in Parquet.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ..errors import ConfigError

#: Column name -> type ("str", "float", "int", "bool").
SCHEMA: dict[str, str] = {
    "group": "str", "period": "str", "command": "str", "status": "str",
    "n_inputs": "int", "inputs": "str",
    "A": "float", "A_lo": "float", "A_hi": "float",
    "B": "float", "B_lo": "float", "B_hi": "float",
    "C": "float", "C_lo": "float", "C_hi": "float",
    "effects": "str", "rmse_rpm": "float", "fit_percent": "float", "rmse_initial_rpm": "float",
    "unexplained": "bool",
    "alarms": "int", "alarm_inputs": "str", "first_alarm_t_s": "float",
    "drift_A": "float", "drift_B": "float", "drift_C": "float",
    "drift_A_pct": "float", "drift_B_pct": "float", "drift_C_pct": "float",
    "effects_appeared": "str", "effects_gone": "str", "drifted": "bool", "drift_note": "str",
    "error": "str", "warnings": "str", "details": "str", "content_hash": "str",
    "elapsed_s": "float", "worker": "str", "finished_utc": "str", "output": "str",
}
COLUMNS = tuple(SCHEMA)
STATUSES = ("ok", "partial", "failed")

#: Default smallest relative change of a coefficient that counts as drift [-].
DRIFT_MIN_RELATIVE = 0.05


def empty_row(group: str, period: str, command: str) -> dict[str, Any]:
    """A row with every column present and nothing known."""
    row: dict[str, Any] = {c: None for c in COLUMNS}
    row.update(group=group, period=period, command=command)
    return row


def _clean(value: Any, kind: str) -> Any:
    """A value as its column's type; None for missing (NaN, empty text in a number column)."""
    if value is None:
        return None
    if kind == "float":
        try:
            v = float(value)
        except (TypeError, ValueError):
            return None
        return v if math.isfinite(v) else None
    if kind == "int":
        if value == "":
            return None
        return int(float(value))
    if kind == "bool":
        if isinstance(value, str):
            if value == "":
                return None
            return value.strip().lower() in ("true", "1", "yes")
        return bool(value)
    if isinstance(value, (list, tuple)):
        return ";".join(str(v) for v in value)
    if isinstance(value, dict):
        return json.dumps(value, sort_keys=True, default=str)
    return str(value)


def normalise(row: Mapping[str, Any]) -> dict[str, Any]:
    """A row with exactly the table's columns, each of its type."""
    return {c: _clean(row.get(c), SCHEMA[c]) for c in COLUMNS}


def table_format(path: str | Path) -> str:
    """``"parquet"`` or ``"csv"`` from the extension."""
    suffix = Path(str(path)).suffix.lower()
    if suffix in (".parquet", ".pq"):
        return "parquet"
    if suffix == ".csv":
        return "csv"
    raise ConfigError(f"{path}: the results table must end in .parquet or .csv")


def write_results(rows: Iterable[Mapping[str, Any]], path: str | Path) -> Path:
    """Write the table atomically (a temporary file renamed over the target)."""
    p = Path(path)
    fmt = table_format(p)
    rows = [normalise(r) for r in rows]
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.tmp")
    if fmt == "parquet":
        from . import require_extra

        pa = require_extra("pyarrow")
        pq = require_extra("pyarrow.parquet")
        types = {"str": pa.string(), "float": pa.float64(), "int": pa.int64(),
                 "bool": pa.bool_()}
        schema = pa.schema([(c, types[SCHEMA[c]]) for c in COLUMNS])
        table = pa.Table.from_pylist(rows, schema=schema)
        pq.write_table(table, tmp)
    else:
        with tmp.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(COLUMNS)
            for r in rows:
                w.writerow(["" if r[c] is None else r[c] for c in COLUMNS])
    os.replace(tmp, p)
    return p


def read_results(path: str | Path, require: Sequence[str] | None = None
                 ) -> list[dict[str, Any]]:
    """Read a results table written by :func:`write_results` (Parquet or CSV).

    Parameters
    ----------
    path : str or Path
    require : sequence of str, optional
        Columns the table must have (default :data:`REQUIRED_COLUMNS`); a table with rows that
        lacks any is refused in one line naming them (a missing column would read as empty
        values: numbers silently gone). :data:`REPORT_COLUMNS` are those ``fleet-report`` and
        a resumed batch use.
    """
    p = Path(path)
    fmt = table_format(p)
    if not p.exists():
        raise ConfigError(f"{p}: file not found")
    try:
        if fmt == "parquet":
            from . import require_extra

            pq = require_extra("pyarrow.parquet")
            rows = pq.read_table(p).to_pylist()
        else:
            with p.open(newline="", encoding="utf-8") as fh:
                rows = list(csv.DictReader(fh))
    except (OSError, ValueError, csv.Error) as err:
        raise ConfigError(f"{p}: cannot read the results table: {err}") from err
    if rows and "group" not in rows[0]:
        raise ConfigError(f"{p}: not a results table of mecanum-hil batch (no 'group' column)")
    if rows:
        missing = [c for c in (REQUIRED_COLUMNS if require is None else require)
                   if c not in rows[0]]
        if missing:
            raise ConfigError(f"{p}: not a whole results table of mecanum-hil batch (no "
                              f"{', '.join(repr(c) for c in missing)} column"
                              f"{'s' if len(missing) > 1 else ''})")
    if fmt == "csv":
        _check_csv_rows(p, rows)
    return [normalise(r) for r in rows]


#: Columns every results table has (a table cut in its header lacks some).
REQUIRED_COLUMNS = ("group", "period", "command", "status")

#: Columns ``fleet-report`` reads and a resumed batch keeps rows from (every table ``batch``
#: writes has them): identity, outcome, the model with its intervals, shadow alarms, drift.
REPORT_COLUMNS = (
    *REQUIRED_COLUMNS, "inputs", "A", "A_lo", "A_hi", "B", "B_lo", "B_hi", "C", "C_lo", "C_hi",
    "effects", "rmse_rpm", "alarms", "alarm_inputs", "first_alarm_t_s", "effects_appeared",
    "effects_gone", "drifted", "drift_note", "error")


def _check_csv_rows(p: Path, rows: Sequence[Mapping[str, Any]]) -> None:
    """One line for a CSV table that is not whole: columns missing, a row with more cells than
    the header, text in a number column (it would be dropped silently, and the row's plots
    with it)."""
    if not rows:
        return
    missing = [c for c in REQUIRED_COLUMNS if c not in rows[0]]
    if missing:
        raise ConfigError(f"{p}: not a whole results table of mecanum-hil batch (no "
                          f"{', '.join(repr(c) for c in missing)} column)")
    for i, row in enumerate(rows, start=2):  # line 1 is the header
        if None in row:
            raise ConfigError(f"{p}, line {i}: more cells than the header has columns")
        for c, kind in SCHEMA.items():
            v = row.get(c)
            if kind not in ("float", "int") or v is None or v == "":
                continue
            try:
                float(v)
            except ValueError:
                raise ConfigError(f"{p}, line {i}, column {c}: {v!r} is not a number"
                                  ) from None
            if kind == "int" and not math.isfinite(float(v)):
                raise ConfigError(f"{p}, line {i}, column {c}: {v!r} is not a whole number")


def row_key(row: Mapping[str, Any]) -> tuple[str, str, str]:
    """A row's identity: ``(group, period, "")``; ``measure-video`` has a row per video, so its
    key adds the video's path (``inputs``)."""
    extra = (row.get("inputs") or "") if row.get("command") == "measure-video" else ""
    return (row.get("group") or "", row.get("period") or "", extra)


def _split(text: str | None, sep: str = ",") -> list[str]:
    return [s for s in (text or "").split(sep) if s]


def _half_width(row: Mapping[str, Any], k: str) -> float:
    lo, hi = row.get(f"{k}_lo"), row.get(f"{k}_hi")
    if lo is None or hi is None:
        return math.nan
    return 0.5 * (float(hi) - float(lo))


def add_drift(rows: Sequence[Mapping[str, Any]],
              min_relative: float = DRIFT_MIN_RELATIVE) -> list[dict[str, Any]]:
    """Drift of each robot's coefficients and effects against its previous period.

    For each row with coefficients (``fit``, ``diagnose``) the previous row of the same group
    with coefficients (periods sort as text: days and ISO weeks sort in time order) gives
    ``drift_X = X - X_prev`` and ``drift_X_pct``. A coefficient has drifted when the change is
    both larger than the two 95 % half-widths combined (``sqrt(h^2 + h_prev^2)``: the
    difference is outside what the intervals allow; skipped when either interval is missing)
    and at least ``min_relative`` of the previous value (intervals are optimistic on real
    data; docs/fit.md). An effect named now but not before (``effects_appeared``) or the
    reverse (``effects_gone``) counts as drift too. The first period of a robot has no drift.

    Returns
    -------
    list of dict
        The rows, sorted by group and period, with the drift columns filled.
    """
    out = [normalise(r) for r in rows]
    out.sort(key=lambda r: (r["group"] or "", r["period"] or ""))
    prev: dict[str, dict[str, Any]] = {}
    for r in out:
        for k in ("A", "B", "C"):
            r[f"drift_{k}"] = r[f"drift_{k}_pct"] = None
        r["effects_appeared"] = r["effects_gone"] = r["drift_note"] = None
        r["drifted"] = None
        if r["status"] not in ("ok", "partial") or r["A"] is None or \
                r["command"] not in ("fit", "diagnose"):
            continue
        p = prev.get(r["group"])
        prev[r["group"]] = r
        if p is None:
            continue
        notes = []
        drifted = False
        for k in ("A", "B", "C"):
            d = r[k] - p[k]
            r[f"drift_{k}"] = d
            r[f"drift_{k}_pct"] = 100.0 * d / abs(p[k]) if p[k] else None
            hw = math.hypot(_half_width(r, k), _half_width(p, k))
            outside = math.isfinite(hw) and abs(d) > hw
            large = p[k] != 0 and abs(d) >= min_relative * abs(p[k])
            if outside and large:
                drifted = True
                notes.append(f"{k} {p[k]:.4g} -> {r[k]:.4g} ({100 * d / abs(p[k]):+.1f} %)")
        now, before = set(_split(r["effects"])), set(_split(p["effects"]))
        appeared, gone = sorted(now - before), sorted(before - now)
        r["effects_appeared"] = ",".join(appeared)
        r["effects_gone"] = ",".join(gone)
        if appeared:
            notes.append("appeared: " + ", ".join(appeared))
        if gone:
            notes.append("gone: " + ", ".join(gone))
        r["drifted"] = bool(drifted or appeared or gone)
        r["drift_note"] = f"since {p['period']}: " + "; ".join(notes) if notes else ""
    return out
