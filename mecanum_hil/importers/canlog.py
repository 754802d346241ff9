"""CAN logs in: candump ``.log``, Vector ``.asc`` and ``.blf``, read with python-can's readers
and decoded with a DBC (cantools).

Which signal is which recording column is a small mapping: built in for
``drivers/mecanum_hil.dbc`` (this project's protocol: ``MH_COMMAND``, ``MH_STOP``,
``MC_WHEELS``), or a TOML file (``--map``) for the user's own DBC (``--dbc``)::

    [can]
    dbc = "robot.dbc"             # optional (relative to this file); --dbc wins
    stop_message = "DRIVE_STOP"   # optional: a frame that means n = omega = 0

    [can.columns]                 # column = "MESSAGE.signal", or a table with scale/offset
    n_cmd_rpm = "DRIVE_CMD.speed"
    omega_cmd_dps = "DRIVE_CMD.turn"
    theta_cmd_deg = "DRIVE_CMD.direction"
    wheel1_rpm = { signal = "MOTOR_FL.speed", scale = 9.549296585513721 }   # rad/s -> rpm

Instead of the three command columns a log may carry the body twist: ``cmd_vx_mps``,
``cmd_vy_mps``, ``cmd_wz_radps`` (then turned into commands as a bag's Twist is). A column's
value is ``scale * signal + offset``. Frames are timed by the log; the streams are aligned as
:mod:`._streams` says; each command column keeps its last value between its frames.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, MecanumHILError, RecordingError
from ..io.recording import COMMAND_COLUMNS, POSE_COLUMNS, WHEEL_COLUMNS
from ..io.resources import resource_dir
from ..io.toml_config import load_toml
from ._streams import Stream, check_time_order, merge_streams

NAME = "canlog"

TWIST_COLUMNS = ("cmd_vx_mps", "cmd_vy_mps", "cmd_wz_radps")
KNOWN_COLUMNS = COMMAND_COLUMNS + WHEEL_COLUMNS + POSE_COLUMNS + TWIST_COLUMNS

_CANDUMP_LINE = re.compile(rb"^\(\d+(\.\d+)?\)\s+\S+\s+[0-9A-Fa-f]{3,8}#")


@dataclass(frozen=True)
class SignalMap:
    """One recording column from one DBC signal: ``scale * signal + offset``."""

    column: str
    message: str
    signal: str
    scale: float = 1.0
    offset: float = 0.0


@dataclass(frozen=True)
class CanMapping:
    """Which DBC signals give which columns.

    Attributes
    ----------
    signals : tuple of SignalMap
    stop_message : str or None
        A message whose frames mean ``n = omega = 0`` (theta kept).
    dbc : Path or None
        The DBC named by the mapping file.
    source : str
        Where the mapping came from (messages).
    """

    signals: tuple[SignalMap, ...]
    stop_message: str | None = None
    dbc: Path | None = None
    source: str = "built-in mapping"


#: The mapping of this project's protocol (drivers/mecanum_hil.dbc, drivers/protocol.md).
DEFAULT_MAPPING = CanMapping(
    (SignalMap("n_cmd_rpm", "MH_COMMAND", "n_cmd"),
     SignalMap("omega_cmd_dps", "MH_COMMAND", "omega_cmd"),
     SignalMap("theta_cmd_deg", "MH_COMMAND", "theta_cmd"),
     *(SignalMap(f"wheel{i}_rpm", "MC_WHEELS", f"wheel{i}") for i in range(1, 5))),
    stop_message="MH_STOP",
    source="built-in mapping for drivers/mecanum_hil.dbc")


def default_dbc() -> Path:
    """The shipped DBC of the mecanum-hil protocol."""
    return resource_dir("drivers") / "mecanum_hil.dbc"


def load_mapping(path: str | Path) -> CanMapping:
    """Read a TOML mapping (the ``[can]`` table; see the module docstring)."""
    p = Path(path)
    doc = load_toml(p)
    can_table = doc.get("can")
    if not isinstance(can_table, Mapping):
        raise ConfigError(f"{p}: a CAN log mapping needs a [can] table with [can.columns]")
    unknown = set(can_table) - {"dbc", "stop_message", "columns"}
    if unknown:
        raise ConfigError(f"{p}: key 'can.{sorted(unknown)[0]}' is not a known key (known: "
                          "columns, dbc, stop_message)")
    columns = can_table.get("columns")
    if not isinstance(columns, Mapping) or not columns:
        raise ConfigError(f"{p}: missing table [can.columns]")
    signals = []
    for column, spec in columns.items():
        where = f"{p}: key 'can.columns.{column}'"
        if column not in KNOWN_COLUMNS:
            raise ConfigError(f"{where} is not a recording column (known: "
                              f"{', '.join(KNOWN_COLUMNS)})")
        scale, offset = 1.0, 0.0
        if isinstance(spec, Mapping):
            extra = set(spec) - {"signal", "scale", "offset"}
            if extra:
                raise ConfigError(f"{where}: unknown key '{sorted(extra)[0]}' (known: signal, "
                                  "scale, offset)")
            for key in ("scale", "offset"):
                v = spec.get(key, 1.0 if key == "scale" else 0.0)
                if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                    raise ConfigError(f"{where}.{key} must be a finite number, got {v!r}")
            scale, offset = float(spec.get("scale", 1.0)), float(spec.get("offset", 0.0))
            spec = spec.get("signal")
        if not isinstance(spec, str) or spec.count(".") != 1 or not all(spec.split(".")):
            raise ConfigError(f"{where} must be \"MESSAGE.signal\", got {spec!r}")
        message, signal = spec.split(".")
        signals.append(SignalMap(column, message, signal, scale, offset))
    stop = can_table.get("stop_message")
    if stop is not None and not isinstance(stop, str):
        raise ConfigError(f"{p}: key 'can.stop_message' must be a message name, got {stop!r}")
    dbc = can_table.get("dbc")
    if dbc is not None and not isinstance(dbc, str):
        raise ConfigError(f"{p}: key 'can.dbc' must be a path, got {dbc!r}")
    mapping = CanMapping(tuple(signals), stop, (p.parent / dbc) if dbc else None, str(p))
    _check_columns(mapping)
    return mapping


def _check_columns(mapping: CanMapping) -> None:
    cols = [s.column for s in mapping.signals]
    dup = sorted({c for c in cols if cols.count(c) > 1})
    if dup:
        raise ConfigError(f"{mapping.source}: column {dup[0]} is mapped twice")
    has_cmd = set(COMMAND_COLUMNS) <= set(cols)
    has_twist = set(TWIST_COLUMNS) <= set(cols)
    if has_cmd == has_twist or (set(cols) & set(COMMAND_COLUMNS) and set(cols) & set(
            TWIST_COLUMNS)):
        raise ConfigError(f"{mapping.source}: map either the three commands "
                          f"({', '.join(COMMAND_COLUMNS)}) or the twist "
                          f"({', '.join(TWIST_COLUMNS)}), all three of one kind")


# -- log files --------------------------------------------------------------------------------

def log_kind(head: bytes) -> str | None:
    """``blf``, ``asc``, ``candump`` judged by the content, or None."""
    if head.startswith(b"LOGG"):
        return "blf"
    lines = [ln.strip() for ln in head.splitlines()[:20] if ln.strip()]
    if not lines:
        return None
    if any(ln.startswith(b"date ") or re.match(rb"^base (hex|dec)\b", ln) for ln in lines[:5]):
        return "asc"
    if _CANDUMP_LINE.match(lines[0]):
        return "candump"
    return None


def sniff(path: Path, head: bytes) -> bool:
    """A candump log, a Vector ASC or a BLF file, by content."""
    return log_kind(head) is not None


def _reader(path: Path, kind: str):
    import can

    if kind == "blf":
        return can.BLFReader(path)
    if kind == "asc":
        return can.ASCReader(path, relative_timestamp=False)
    return _CandumpReader(path)


class _CandumpReader:
    """candump ``-L`` lines as frames, like python-can's ``CanutilsLogReader``, but naming a
    malformed line, and skipping a last line cut off mid-line (no newline at its end): its
    text is kept in :attr:`cut` for the note. :attr:`line` is the current frame's line."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.line = 0
        self.cut = ""
        self._fh = self.path.open("r", encoding="ascii", errors="replace", newline="")

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._fh.close()

    def __iter__(self):
        for line, raw in enumerate(self._fh, start=1):
            self.line = line
            text = raw.strip()
            if not text:
                continue
            try:
                yield _candump_frame(text)
            except (ValueError, IndexError):
                if not raw.endswith(("\n", "\r")):  # only the last line can lack it
                    self.cut = text  # the logger stopped mid-line
                    return
                raise RecordingError(f"{self.path}, line {self.line}: cannot read the candump "
                                     "log: not a frame line \"(time) interface ID#data\": "
                                     f"{text[:60]!r}") from None


def _candump_frame(text: str):
    """One candump ``-L`` line as a ``can.Message`` (python-can's parsing, strict)."""
    import can

    fields = text.split()
    if len(fields) == 4 and fields[3].lower() in ("r", "t"):
        is_rx = fields.pop().lower() == "r"
    else:
        is_rx = True
    stamp, channel, frame = fields  # ValueError: too few or too many fields
    if not (stamp.startswith("(") and stamp.endswith(")")):
        raise ValueError(stamp)
    timestamp = float(stamp[1:-1])
    if not math.isfinite(timestamp):
        raise ValueError(stamp)
    can_id_text, data = frame.split("#", maxsplit=1)
    if not 1 <= len(can_id_text) <= 8:
        raise ValueError(can_id_text)
    can_id = int(can_id_text, 16)
    is_fd = brs = esi = False
    if data and data[0] == "#":
        is_fd = True
        flags = int(data[1], 16)
        brs, esi = bool(flags & 0x01), bool(flags & 0x02)
        data = data[2:]
    if data and data[0].lower() == "r":
        remote, dlc, payload = True, int(data[1:]) if len(data) > 1 else 0, None
    else:
        if len(data) % 2:
            raise ValueError(data)
        remote, payload = False, bytearray.fromhex(data)
        dlc = len(payload)
    if can_id & 0x20000000 and can_id & 0x00000080:  # CAN_ERR_FLAG, CAN_ERR_BUSERROR
        return can.Message(timestamp=timestamp, is_error_frame=True)
    return can.Message(timestamp=timestamp, arbitration_id=can_id & 0x1FFFFFFF,
                       is_extended_id=len(can_id_text) > 3, is_remote_frame=remote, is_fd=is_fd,
                       is_rx=is_rx, bitrate_switch=brs, error_state_indicator=esi, dlc=dlc,
                       data=payload, channel=int(channel) if channel.isdigit() else channel)


def _load_dbc(path: Path):
    import cantools

    try:
        return cantools.database.load_file(str(path))
    except FileNotFoundError:
        raise ConfigError(f"{path}: DBC file not found") from None
    except Exception as err:  # cantools raises several parse error types
        raise ConfigError(f"{path}: cannot load the DBC: {err}") from err


def _resolve(db, mapping: CanMapping, dbc: Path):
    """``{(frame_id, extended): (message, [(SignalMap, column index)], is_stop)}``."""
    by_message: dict[str, list[SignalMap]] = {}
    for s in mapping.signals:
        by_message.setdefault(s.message, []).append(s)
    names = {m.name: m for m in db.messages}
    plan = {}
    wanted = list(by_message) + ([mapping.stop_message] if mapping.stop_message else [])
    for name in wanted:
        msg = names.get(name)
        if msg is None:
            cols = [s.column for s in by_message.get(name, ())] or ["the stop"]
            raise ConfigError(f"{dbc}: no message {name} (mapped to {', '.join(cols)} by "
                              f"{mapping.source})")
        have = {sig.name for sig in msg.signals}
        for s in by_message.get(name, ()):
            if s.signal not in have:
                raise ConfigError(f"{dbc}: message {name} has no signal {s.signal} (mapped to "
                                  f"{s.column} by {mapping.source})")
        key = (msg.frame_id, bool(msg.is_extended_frame))
        plan[key] = (msg, by_message.get(name, []), name == mapping.stop_message)
    return plan


def _hold_last(values: np.ndarray) -> np.ndarray:
    """Each column's missing values (NaN) filled with its last value before them, in place
    (a signal keeps its value between the frames that carry it); NaN before the first."""
    for j in range(values.shape[1]):
        col = values[:, j]
        last = np.where(np.isfinite(col), np.arange(col.size), -1)
        np.maximum.accumulate(last, out=last)
        values[:, j] = np.where(last >= 0, col[np.maximum(last, 0)], np.nan)
    return values


def read_log(path: str | Path, *, dbc_path: str | Path | None = None,
             map_path: str | Path | None = None, wheel_radius_m: float | None = None):
    """Read a CAN log into a recording; returns ``(Recording, notes)``. See :func:`read`."""
    p = Path(path)
    mapping = load_mapping(map_path) if map_path is not None else DEFAULT_MAPPING
    dbc = Path(dbc_path) if dbc_path is not None else (mapping.dbc or default_dbc())
    db = _load_dbc(dbc)
    plan = _resolve(db, mapping, dbc)
    kind = _log_kind_of(p)
    twist = TWIST_COLUMNS[0] in {s.column for s in mapping.signals}
    cmd_cols = TWIST_COLUMNS if twist else COMMAND_COLUMNS
    got = _Decoded(twist, cmd_cols)
    _decode_log(p, kind, plan, got)
    frames = got.frames
    if not frames:
        raise RecordingError(f"{p}: the log holds no frames")
    cmd_names = sorted({s.message for s in mapping.signals if s.column in cmd_cols})
    if not got.cmd_t:
        raise RecordingError(f"{p}: no frames of {', '.join(cmd_names)} (the commands) among "
                             f"{frames} frames; check the DBC ({dbc}) and the mapping")
    notes = [f"{frames} frames ({kind}), {got.decoded} decoded with {dbc.name}"]
    if got.cut:
        notes.append(f"last line cut off mid-line (no newline at the end): skipped: "
                     f"{got.cut[:60]!r}")
    if got.bad:
        notes.append(f"{got.bad} frame(s) that do not decode skipped")
    # frames are timed by the log's clock: one running back is a reset, not jitter to sort
    order = check_time_order(got.order_t, lambda i: "{}, {} ({})".format(
        p, *got.order_where[i]), "frame(s)")
    if order:
        notes.append(order)
    cmd_stream = _command_stream(p, got, wheel_radius_m)
    pose_stream = None
    if got.pose_t:
        pose_stream = Stream.of(got.pose_t, got.pose_v, 3)
        _hold_last(pose_stream.values)
    meta = {"source": f"mecanum-hil import (canlog) {p.name}",
            "import": {"format": NAME, "log_kind": kind, "dbc": str(dbc),
                       "mapping": mapping.source}}
    if twist:  # the radius that turned m/s into wheel rpm
        meta["import"]["wheel_radius_m"] = wheel_radius_m
    rec, merge_notes = merge_streams(cmd_stream, Stream.of(got.wheel_t, got.wheel_v, 4)
                                     if got.wheel_t else Stream.of([], np.zeros((0, 4)), 4),
                                     pose_stream, meta, str(p))
    return rec, tuple(notes) + merge_notes


def _log_kind_of(p: Path) -> str:
    """The log's kind from its first bytes (see :func:`log_kind`)."""
    try:
        with p.open("rb") as fh:
            kind = log_kind(fh.read(4096))
    except OSError as err:
        raise RecordingError(f"{p}: cannot read: {err.strerror or err}") from err
    if kind is None:
        raise RecordingError(f"{p}: not a candump, ASC or BLF log")
    return kind


class _Decoded:
    """The mapped signals of a log's frames, by stream (bus time [ns], row), and counts."""

    def __init__(self, twist: bool, cmd_cols: tuple[str, ...]) -> None:
        self.twist, self.cmd_cols = twist, cmd_cols
        self.col_index = {c: i for i, c in enumerate(cmd_cols)}
        self.col_index.update({c: i for i, c in enumerate(WHEEL_COLUMNS)})
        self.col_index.update({c: i for i, c in enumerate(POSE_COLUMNS)})
        self.cmd_t: list[int] = []
        self.cmd_v: list[list[float]] = []
        self.wheel_t: list[int] = []
        self.wheel_v: list[list[float]] = []
        self.pose_t: list[int] = []
        self.pose_v: list[list[float]] = []
        self.frames = self.decoded = self.bad = 0
        #: every decoded frame's time [ns] and name (where, message), in the log's order
        self.order_t: list[int] = []
        self.order_where: list[tuple[str, str]] = []
        self.cut = ""

    def add(self, t_ns: int, values, sigs, is_stop: bool, where: str = "",
            message: str = "") -> None:
        """Add one decoded frame's mapped signals (and a STOP's zero command)."""
        self.decoded += 1
        self.order_t.append(t_ns)
        self.order_where.append((where, message))
        if is_stop:
            self.cmd_t.append(t_ns)
            stop = [np.nan] * 3
            if self.twist:
                stop[:] = (0.0, 0.0, 0.0)
            else:
                stop[0], stop[1] = 0.0, 0.0
            self.cmd_v.append(stop)
        rows = {}
        for s in sigs:
            group = ("cmd" if s.column in self.cmd_cols
                     else "wheel" if s.column in WHEEL_COLUMNS else "pose")
            row = rows.setdefault(group, [np.nan] * (4 if group == "wheel" else 3))
            row[self.col_index[s.column]] = s.scale * float(values[s.signal]) + s.offset
        for group, row in rows.items():
            ts, vs = {"cmd": (self.cmd_t, self.cmd_v), "wheel": (self.wheel_t, self.wheel_v),
                      "pose": (self.pose_t, self.pose_v)}[group]
            ts.append(t_ns)
            vs.append(row)


def _decode_log(p: Path, kind: str, plan: dict, got: _Decoded) -> None:
    """Decode every frame the plan maps into ``got``; a damaged log is a RecordingError."""
    try:
        # the reader closes its file only at the end of the log: also on a corrupt frame
        with _reader(p, kind) as reader:
            for frame in reader:
                got.frames += 1
                if frame.is_error_frame or frame.is_remote_frame:
                    continue
                entry = plan.get((frame.arbitration_id, bool(frame.is_extended_id)))
                if entry is None:
                    continue
                msg, sigs, is_stop = entry
                try:
                    values = msg.decode(bytes(frame.data), decode_choices=False)
                except Exception:  # cantools DecodeError, a short frame: counted, not fatal
                    got.bad += 1
                    continue
                where = (f"line {reader.line}" if isinstance(reader, _CandumpReader)
                         else f"frame {got.frames}")
                got.add(round(frame.timestamp * 1e9), values, sigs, is_stop, where, msg.name)
            got.cut = getattr(reader, "cut", "")
            size = getattr(reader, "file_size", None)  # BLF: the header's file size
            if size and p.stat().st_size < size:
                raise RecordingError(f"{p}: truncated BLF: {p.stat().st_size} of the header's "
                                     f"{size} bytes ({got.frames} frames readable)")
    except MecanumHILError:
        raise
    except Exception as err:  # python-can readers: a damaged or truncated log
        raise RecordingError(f"{p}: cannot read the {kind} log (truncated or corrupt?) after "
                             f"{got.frames} frames: {type(err).__name__}: {err}") from err


def _command_stream(p: Path, got: _Decoded, wheel_radius_m: float | None) -> Stream:
    """The commands ``(n [rpm], omega [deg/s], theta [deg])`` from the frames heard: each
    signal held between its frames, rows before all are known dropped, a twist converted."""
    from .rosbag import twist_to_commands

    cmd_stream = Stream.of(got.cmd_t, got.cmd_v, 3)
    vals = _hold_last(cmd_stream.values)  # each command keeps its value between its frames
    known = np.isfinite(vals).all(axis=1)
    if not known.any():
        raise RecordingError(f"{p}: the commands are never all known "
                             f"({', '.join(got.cmd_cols)})")
    cmd_stream = Stream(cmd_stream.t_ns[known], vals[known])
    if got.twist:
        if wheel_radius_m is None:
            raise RecordingError("a twist in m/s needs the wheel radius (--robot)")
        v = cmd_stream.values
        cmd_stream = Stream(cmd_stream.t_ns, twist_to_commands(v[:, 0], v[:, 1], v[:, 2],
                                                               wheel_radius_m))
    return cmd_stream


def read(path: Path, *, dbc_path: str | Path | None = None,
         map_path: str | Path | None = None, wheel_radius_m: float | None = None):
    """Read a CAN log (candump, ASC, BLF) into a recording.

    Parameters
    ----------
    path : Path
        The log.
    dbc_path : str or Path, optional
        DBC decoding the frames (default: the mapping's, else drivers/mecanum_hil.dbc).
    map_path : str or Path, optional
        TOML mapping of signals to columns (default: the mecanum-hil protocol's).
    wheel_radius_m : float, optional
        Wheel radius [m], for a mapping that gives the twist in m/s (the CLI passes its
        ``--robot`` profile's).

    Returns
    -------
    ImportResult
    """
    from . import ImportResult

    rec, notes = read_log(path, dbc_path=dbc_path, map_path=map_path,
                          wheel_radius_m=wheel_radius_m)
    return ImportResult(rec, notes)
