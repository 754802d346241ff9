"""The shadow monitor's JSON-lines event log, next to the recording it watches.

``run.csv`` -> ``run.shadow.jsonl``: one JSON object per line, appended as events happen and
flushed at once (an alarm must be on disk even if the process dies right after). Fields are
listed in docs/shadow.md ("Event log"); every line has ``event`` and ``t_s``.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import MecanumHILError
from ..model.calibration import Calibration
from .core import ShadowConfig

#: Suffix of the event log, replacing the recording's ``.csv``.
EVENT_LOG_SUFFIX = ".shadow.jsonl"


def alarm_line(event: dict) -> str:
    """One terminal line for an alarm or recovery event (the terminal's view of the log)."""
    if event["event"] == "alarm":
        return (f"ALARM t={event['t_s']:.3f}s {event['channel']}: residual "
                f"{event['residual']:+.3g} {event['unit']} (onset {event['onset_t_s']:.3f}s, "
                f"noise {event['noise']:.3g} {event['unit']})")
    return f"recovered t={event['t_s']:.3f}s {event['channel']}"


def event_log_path(recording_path: str | Path) -> Path:
    """The event log belonging to a recording: ``run.csv`` -> ``run.shadow.jsonl``."""
    p = Path(recording_path)
    return p.with_name(p.stem + EVENT_LOG_SUFFIX)


def written_by(path: str | Path) -> str | None:
    """The ``mode`` of the run that wrote an existing event log (``record``, ``replay``,
    ``listen-can`` ...), from its ``start`` line; ``None`` when there is no such file or it
    does not start like an event log."""
    try:
        with Path(path).open(encoding="utf-8") as fh:
            first = json.loads(fh.readline())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(first, dict) or first.get("event") != "start":
        return None
    mode = first.get("mode")
    return str(mode) if mode is not None else None


def _clean(value: Any) -> Any:
    # JSON has no inf/nan: write them as null so every line stays strict JSON
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    return value


class EventLog:
    """Append-only JSON-lines writer; usable as a monitor listener (call it with an event).

    Parameters
    ----------
    path : str or Path
        File to create (replaced if it exists).
    calibration : Calibration
        Written into the ``start`` line.
    config : ShadowConfig
        Written into the ``start`` line.
    header : Mapping, optional
        More fields for the ``start`` line (recording, mode, ...).
    whole : bool
        Write to a temporary file put in place by :meth:`close` (a replay: an interrupted one
        leaves the previous log, see :meth:`discard`); default: to ``path`` directly, each line
        flushed as it comes (a live run: what was seen survives a crash).
    """

    def __init__(self, path: str | Path, calibration: Calibration, config: ShadowConfig,
                 header: Mapping[str, Any] | None = None, whole: bool = False) -> None:
        self.path = Path(path)
        self._target = self.path.with_name(self.path.name + ".tmp") if whole else self.path
        try:
            if whole and self.path.is_dir():  # found now, not when the whole log is put there
                raise IsADirectoryError(21, "Is a directory")
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = self._target.open("w", encoding="utf-8")
        except OSError as err:
            raise MecanumHILError(
                f"{self.path}: cannot create the event log: {err.strerror or err}") from err
        self.counts: dict[str, int] = {}
        self.write({
            "event": "start", "t_s": None,
            "wall_time": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "tool_version": __version__,
            "calibration": calibration.source,
            "coefficients": {"A": calibration.A, "B": calibration.B, "C": calibration.C},
            "effects": calibration.effects.active(),
            "config": {k: getattr(config, k) for k in config.__dataclass_fields__},
            **dict(header or {}),
        })

    def write(self, event: Mapping[str, Any]) -> None:
        """Append one event line and flush it."""
        if self._fh.closed:
            return
        self.counts[event["event"]] = self.counts.get(event["event"], 0) + 1
        try:
            self._fh.write(json.dumps(_clean(dict(event)), default=str) + "\n")
            self._fh.flush()
        except OSError as err:
            raise MecanumHILError(
                f"{self.path}: cannot write the event log: {err.strerror or err}") from err

    __call__ = write

    def close(self, summary: Mapping[str, Any] | None = None) -> None:
        """Write the ``end`` line (counts and ``summary``) and close."""
        if self._fh.closed:
            return
        self.write({"event": "end", "t_s": None, "counts": dict(self.counts),
                    **dict(summary or {})})
        self._fh.close()
        if self._target != self.path:
            try:
                os.replace(self._target, self.path)
            except OSError as err:
                self.discard()
                raise MecanumHILError(f"{self.path}: cannot write the event log: "
                                      f"{err.strerror or err}") from err

    def discard(self) -> None:
        """Close without an ``end`` line; a log written whole is removed (the previous one at
        its path stays). For a run that did not finish."""
        if not self._fh.closed:
            self._fh.close()
        if self._target != self.path:
            try:
                self._target.unlink(missing_ok=True)
            except OSError:
                pass

    def __enter__(self) -> EventLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
