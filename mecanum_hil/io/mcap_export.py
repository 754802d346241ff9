"""Recordings out as MCAP, and the channels Foxglove and PlotJuggler open without configuration.

Every channel is JSON-encoded with a JSON schema (``jsonschema``): our own for the numbers
(commands, wheel speeds, the 2-D pose; PlotJuggler plots every field, Foxglove's Plot panel too)
and Foxglove's well-known schemas by name for what its panels draw (``foxglove.PoseInFrame`` in
the 3D panel, ``foxglove.Log`` in the Log panel). The same channels serve the live view
(:mod:`mecanum_hil.monitor.foxglove`). Channels and fields are listed in docs/ros2.md.

A message's log time is the row's time on the source's clock: ``start_time_ns`` of the sidecar
(an imported bag's start) plus ``t_s``, else ``t_s`` itself from the epoch; every message also
carries its ``t_s`` [s] exactly, so that :mod:`mecanum_hil.importers.mcap_run` gives the
recording back. ``mcap`` (the ``foxglove`` extra) is imported inside :func:`export_mcap` only.
"""

from __future__ import annotations

import heapq
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError, RecordingError
from .paths import replaced_when_whole
from .recording import COMMAND_COLUMNS, POSE_COLUMNS, WHEEL_COLUMNS, Recording

#: Library string of the MCAP header: how the importer knows its own files.
LIBRARY = f"mecanum-hil {__version__}"
#: MCAP metadata record holding the recording's sidecar and extra column names.
METADATA_NAME = "mecanum_hil.recording"
#: Frame of the pose messages (the world frame of docs/conventions.md).
WORLD_FRAME = "world"

_TIME = {"type": "object", "title": "time", "properties": {
    "sec": {"type": "integer", "minimum": 0},
    "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}


def _numbers(title: str, description: str, fields: Mapping[str, str]) -> dict[str, Any]:
    props: dict[str, Any] = {"timestamp": _TIME,
                             "t_s": {"type": "number", "description": "recording time [s]"}}
    props.update({k: {"type": ["number", "null"], "description": v} for k, v in fields.items()})
    return {"title": title, "description": description, "type": "object", "properties": props}


_VEC3 = {"type": "object", "properties": {a: {"type": "number"} for a in "xyz"}}
_QUAT = {"type": "object", "properties": {a: {"type": "number"} for a in "xyzw"}}

SCHEMAS: dict[str, dict[str, Any]] = {
    "mecanum_hil.Commands": _numbers(
        "mecanum_hil.Commands", "Commands in force (docs/conventions.md)",
        {"n_cmd_rpm": "wheel speed command [rpm]",
         "omega_cmd_dps": "turning speed, counter-clockwise positive [deg/s]",
         "theta_cmd_deg": "direction of travel, 0 right, 90 ahead [deg]"}),
    "mecanum_hil.WheelSpeeds": _numbers(
        "mecanum_hil.WheelSpeeds", "Wheel speeds 1 FL, 2 FR, 3 RL, 4 RR",
        {c: f"wheel {i + 1} [rpm]" for i, c in enumerate(WHEEL_COLUMNS)}),
    "mecanum_hil.Pose2D": _numbers(
        "mecanum_hil.Pose2D", "Pose in the world frame (plot y_m against x_m for the path)",
        {"x_m": "X [m]", "y_m": "Y [m]", "phi_deg": "heading, counter-clockwise from X [deg]"}),
    "mecanum_hil.ExtraColumns": {
        "title": "mecanum_hil.ExtraColumns", "type": "object",
        "description": "The recording's extra columns of one row, as text",
        "properties": {"timestamp": _TIME, "t_s": {"type": "number"},
                       "columns": {"type": "object",
                                   "additionalProperties": {"type": "string"}}}},
    "foxglove.PoseInFrame": {
        "title": "foxglove.PoseInFrame", "description": "A timestamped pose in a named frame",
        "type": "object", "properties": {
            "timestamp": _TIME, "frame_id": {"type": "string"},
            "pose": {"type": "object", "title": "foxglove.Pose",
                     "properties": {"position": {**_VEC3, "title": "foxglove.Vector3"},
                                    "orientation": {**_QUAT, "title": "foxglove.Quaternion"}}}}},
    "foxglove.Log": {
        "title": "foxglove.Log", "description": "A log message", "type": "object",
        "properties": {
            "timestamp": _TIME,
            "level": {"type": "integer", "title": "foxglove.LogLevel",
                      "description": "0 UNKNOWN, 1 DEBUG, 2 INFO, 3 WARNING, 4 ERROR, 5 FATAL",
                      "enum": [0, 1, 2, 3, 4, 5]},
            "message": {"type": "string"}, "name": {"type": "string"},
            "file": {"type": "string"}, "line": {"type": "integer", "minimum": 0}}},
}


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: its topic and schema name (a key of :data:`SCHEMAS`)."""

    topic: str
    schema: str


#: Channels by role. ``*_predicted``: the model's prediction (``export --calibration``, live
#: shadow mode).
CHANNELS: dict[str, ChannelSpec] = {
    "commands": ChannelSpec("/mecanum/commands", "mecanum_hil.Commands"),
    "wheels": ChannelSpec("/mecanum/wheels/measured", "mecanum_hil.WheelSpeeds"),
    "wheels_predicted": ChannelSpec("/mecanum/wheels/predicted", "mecanum_hil.WheelSpeeds"),
    "pose2d": ChannelSpec("/mecanum/pose2d/measured", "mecanum_hil.Pose2D"),
    "pose": ChannelSpec("/mecanum/pose/measured", "foxglove.PoseInFrame"),
    "pose2d_predicted": ChannelSpec("/mecanum/pose2d/predicted", "mecanum_hil.Pose2D"),
    "pose_predicted": ChannelSpec("/mecanum/pose/predicted", "foxglove.PoseInFrame"),
    "alarms": ChannelSpec("/mecanum/alarms", "foxglove.Log"),
    "extra": ChannelSpec("/mecanum/extra", "mecanum_hil.ExtraColumns"),
}

#: foxglove.Log levels.
LOG_DEBUG, LOG_INFO, LOG_WARNING, LOG_ERROR = 1, 2, 3, 4


def stamp(ns: int) -> dict[str, int]:
    """``{"sec", "nsec"}`` of a time in nanoseconds."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def values_message(ns: int, t_s: float, names, values) -> dict[str, Any]:
    """A numbers message (commands, wheel speeds, 2-D pose); NaN becomes null."""
    msg: dict[str, Any] = {"timestamp": stamp(ns), "t_s": float(t_s)}
    for name, v in zip(names, values, strict=True):
        msg[name] = _num(float(v))
    return msg


def pose_message(ns: int, pose) -> dict[str, Any]:
    """``foxglove.PoseInFrame`` of ``(X [m], Y [m], phi [deg])`` in the world frame."""
    half = math.radians(float(pose[2])) / 2.0
    return {"timestamp": stamp(ns), "frame_id": WORLD_FRAME, "pose": {
        "position": {"x": float(pose[0]), "y": float(pose[1]), "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)}}}


def log_message(ns: int, level: int, text: str, name: str = "mecanum-hil shadow") -> dict:
    """``foxglove.Log``."""
    return {"timestamp": stamp(ns), "level": int(level), "message": text, "name": name,
            "file": "", "line": 0}


@dataclass(frozen=True)
class LogEntry:
    """A log message to export: time [s] on the recording's clock, level, text."""

    t_s: float
    level: int
    text: str


def time_base_ns(rec: Recording) -> int:
    """Log time of ``t_s = 0`` [ns]: the sidecar's ``start_time_ns`` (an imported source's
    clock), else the epoch; moved so that the first row is not before 0 (MCAP times are
    unsigned)."""
    start = rec.metadata.get("start_time_ns")
    base = int(start) if isinstance(start, int) and start >= 0 else 0
    if len(rec):
        base = max(base, -round(float(rec.t_s[0]) * 1e9))
    return base


def row_times_ns(rec: Recording) -> np.ndarray:
    """Log time of every row [ns] (:func:`time_base_ns` + ``t_s``)."""
    return time_base_ns(rec) + np.round(np.asarray(rec.t_s, dtype=float) * 1e9).astype(np.int64)


def role_messages(rec: Recording, predicted: Recording | None = None) -> list:
    """``(role, generator)`` of every role that has messages; each generator yields
    ``(role, log_time_ns, message)`` in time order."""
    ns = row_times_ns(rec)
    t = rec.t_s

    def values(role, names, vals, rows):
        for i in rows:
            yield role, int(ns[i]), values_message(int(ns[i]), t[i], names, vals[i])

    def poses(suffix, pose, rows):
        for i in rows:
            yield "pose2d" + suffix, int(ns[i]), values_message(int(ns[i]), t[i], POSE_COLUMNS,
                                                                pose[i])
            if np.isfinite(pose[i]).all():
                yield "pose" + suffix, int(ns[i]), pose_message(int(ns[i]), pose[i])

    def extras(names, cols):
        for i in range(len(rec)):
            yield "extra", int(ns[i]), {"timestamp": stamp(int(ns[i])), "t_s": float(t[i]),
                                        "columns": {n: str(c[i]) for n, c in zip(
                                            names, cols, strict=True)}}

    out = []
    blocks = [("commands", COMMAND_COLUMNS, rec.commands),
              ("wheels", WHEEL_COLUMNS, rec.wheel_rpm)]
    if predicted is not None:
        blocks.append(("wheels_predicted", WHEEL_COLUMNS, predicted.wheel_rpm))
    for role, names, vals in blocks:
        rows = np.flatnonzero(np.isfinite(vals).any(axis=1))
        if rows.size:
            out.append(([role], values(role, names, vals, rows)))
    pose_sets = [("", rec.pose)] + ([("_predicted", predicted.pose)] if predicted is not None
                                    else [])
    for suffix, pose in pose_sets:
        rows = np.flatnonzero(np.isfinite(pose).any(axis=1))
        if rows.size:
            roles = ["pose2d" + suffix] + (["pose" + suffix]
                                           if np.isfinite(pose[rows]).all(axis=1).any() else [])
            out.append((roles, poses(suffix, pose, rows)))
    if rec.extra and len(rec):
        names = list(rec.extra)
        out.append((["extra"], extras(names, [rec.extra[n] for n in names])))
    return out


def row_messages(rec: Recording, predicted: Recording | None = None):
    """``(role, log_time_ns, message)`` for every row that has values, role by role."""
    for _, gen in role_messages(rec, predicted):
        yield from gen


@dataclass(frozen=True)
class ExportSummary:
    """What :func:`export_mcap` wrote: messages per topic."""

    path: Path
    counts: dict[str, int]


def export_mcap(rec: Recording, out: str | Path, predicted: Recording | None = None,
                logs: Iterable[LogEntry] = (), source: str = "") -> ExportSummary:
    """Write a recording (and the model's prediction, and log messages) as MCAP.

    Parameters
    ----------
    rec : Recording
    out : str or Path
        MCAP file to write (atomically: a temporary file renamed into place).
    predicted : Recording, optional
        The model's prediction for ``rec`` (same times).
    logs : iterable of LogEntry
        Alarms and other events (shadow mode), on ``/mecanum/alarms``.
    source : str
        Where the recording came from (MCAP metadata).

    Returns
    -------
    ExportSummary
    """
    try:
        from mcap.writer import CompressionType, Writer
    except ImportError as err:
        raise ConfigError("writing MCAP needs the 'foxglove' extra: pip install "
                          "'mecanum-hil[foxglove]'") from err
    if predicted is not None and (len(predicted) != len(rec)
                                  or not np.array_equal(predicted.t_s, rec.t_s)):
        raise RecordingError("the prediction must have the recording's times")
    if not len(rec):
        raise RecordingError(f"{source or 'recording'}: no rows to export")
    streams = role_messages(rec, predicted)
    base = time_base_ns(rec)
    alarms = []
    for entry in sorted(logs, key=lambda e: e.t_s):
        ns = max(0, base + round(entry.t_s * 1e9))
        alarms.append(("alarms", ns, log_message(ns, entry.level, entry.text)))
    if alarms:
        streams.append((["alarms"], iter(alarms)))
    # each role is in time order: merged as they are written, never all in memory (an hour
    # at 1 kHz is millions of messages); equal times keep their role order
    msgs = heapq.merge(*(gen for _, gen in streams), key=lambda m: m[1])
    p = Path(out)
    counts: dict[str, int] = {}
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        # written beside it and put in place whole: nothing half-written left behind
        with replaced_when_whole(p) as tmp, tmp.open("wb") as fh:
            w = Writer(fh, compression=CompressionType.ZSTD)
            w.start(profile="", library=LIBRARY)
            schema_ids = {name: w.register_schema(name, "jsonschema",
                                                  json.dumps(s).encode("utf-8"))
                          for name, s in SCHEMAS.items()}
            roles = sorted({r for rs, _ in streams for r in rs}, key=list(CHANNELS).index)
            channel_ids = {r: w.register_channel(CHANNELS[r].topic, "json",
                                                 schema_ids[CHANNELS[r].schema])
                           for r in roles}
            for role, ns, msg in msgs:
                seq = counts.get(role, 0)
                w.add_message(channel_ids[role], log_time=ns, publish_time=ns, sequence=seq,
                              data=json.dumps(msg, separators=(",", ":")).encode("utf-8"))
                counts[role] = seq + 1
            w.add_metadata(METADATA_NAME, {
                "sidecar": json.dumps(dict(rec.metadata), default=str),
                "extra_columns": json.dumps(list(rec.extra)),
                "source": source, "tool_version": __version__})
            w.finish()
    except OSError as err:
        raise RecordingError(f"{p}: cannot write: {err.strerror or err}") from err
    return ExportSummary(p, {CHANNELS[r].topic: n for r, n in counts.items()})
