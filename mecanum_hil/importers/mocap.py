"""Motion capture: a rigid body's pose into the pose columns of a recording.

Two layouts:

- **OptiTrack Motive's CSV export** (rigid bodies, rotation type Quaternion, coordinate space
  Global): a first metadata row (``Format Version,...,Rotation Type,Quaternion,Length Units,
  Meters,...``), then the ``Type``, ``Name``, ``ID`` rows, a row naming ``Rotation`` /
  ``Position`` and the column row ``Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,...``; an occluded frame
  has empty cells. Motive's frame is Y up; its length unit is stated in the header.
- **Plain CSV**: a header ``t, x, y, z, qx, qy, qz, qw`` (time [s], position, the body's
  orientation as a unit quaternion, scalar last), unit of length from the map (default m),
  capture frame z up unless the map says otherwise.

The map's ``[mocap]`` table says how the capture frame lies on the floor (the world frame of
docs/conventions.md, z up): ``floor = rotation @ capture x scale + translation_m``; ``up = "y"``
(Motive's default: floor X = capture X, floor Y = -capture Z, floor Z = capture Y) or ``"z"``
(the identity), or an explicit ``rotation`` (3 x 3, rows = floor axes in capture coordinates);
``forward_axis`` is the robot's forward direction in the rigid body's own frame (default
``[1, 0, 0]``) and ``centre_m`` the robot's centre in it (default the body's pivot). The heading
phi is the angle of the forward axis, projected on the floor, from floor X.

With ``recording``, the pose is put onto that recording's times (linear between captured
samples, never across an occlusion or outside the capture; see
:mod:`mecanum_hil.io.pose_track`), the capture's first sample at recording time ``start_s``
(seconds, or ``"auto"``: the robot's motion onset against the model's prediction for the
commands).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, RecordingError
from ..io.pose_track import fill_pose, onset_offset, unwrap_deg
from ..io.recording import empty_like_times, read_recording
from ..io.toml_config import TableReader, load_toml
from . import ImportResult
from .text import is_number

NAME = "mocap"

PLAIN_HEADER = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
_MOTIVE_UNITS = {"meters": 1.0, "centimeters": 0.01, "millimeters": 0.001}
_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
_UP = {"z": np.eye(3), "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}


@dataclass(frozen=True)
class MocapMap:
    """The ``[mocap]`` table of a map (defaults when absent)."""

    rotation: np.ndarray | None = None
    up: str | None = None
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    units: str | None = None
    rigid_body: str | None = None
    forward_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    centre_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    calibration: str = "paper"
    robot: str = "tdam-stm"


def load_mocap_map(path: Path | None) -> MocapMap:
    """The ``[mocap]`` table of ``MAP.toml`` (docs/formats-import.md); defaults without a map."""
    if path is None:
        return MocapMap()
    doc = load_toml(path)
    r = TableReader(doc, str(path)).sub("mocap", required=False)
    if r is None:
        raise ConfigError(f"{path}: format 'mocap' needs a [mocap] table (or no --map)")
    r.reject_unknown({"rotation", "up", "translation_m", "units", "rigid_body", "forward_axis",
                      "centre_m", "calibration", "robot"})
    rot = None
    if "rotation" in r.table:
        rows = r.table["rotation"]
        if not isinstance(rows, list) or len(rows) != 3:
            raise r.fail("rotation", "must be three rows of three numbers")
        rot = np.array([TableReader({"row": row}, str(path), "mocap.rotation").numbers("row", 3)
                        for row in rows])
        if not (np.allclose(rot @ rot.T, np.eye(3), atol=1e-6)
                and np.linalg.det(rot) > 0):
            raise r.fail("rotation", "must be a rotation (orthonormal rows, determinant +1)")
    up = r.string("up", "") or None
    if up is not None and up not in _UP:
        raise r.fail("up", f"must be 'y' or 'z', got {up!r}")
    if up is not None and rot is not None:
        raise r.fail("up", "and 'rotation' exclude each other")
    units = r.string("units", "") or None
    if units is not None and units not in _UNITS:
        raise r.fail("units", f"must be one of {', '.join(_UNITS)}, got {units!r}")
    fwd = r.numbers("forward_axis", 3) if "forward_axis" in r.table else (1.0, 0.0, 0.0)
    if np.linalg.norm(fwd) == 0:
        raise r.fail("forward_axis", "must not be zero")
    return MocapMap(rot, up, r.numbers("translation_m", 3) if "translation_m" in r.table
                    else (0.0, 0.0, 0.0), units, r.string("rigid_body", "") or None,
                    tuple(fwd),  # type: ignore[arg-type]
                    r.numbers("centre_m", 3) if "centre_m" in r.table else (0.0, 0.0, 0.0),
                    r.string("calibration", "paper"), r.string("robot", "tdam-stm"))


def _lines(head: bytes) -> list[str]:
    try:
        text = head.decode("utf-8-sig")
    except UnicodeDecodeError:
        return []
    return text.splitlines()


def _is_plain_header(line: str) -> bool:
    return tuple(f.strip().lower() for f in line.split(",")) == PLAIN_HEADER


def sniff(path: Path, head: bytes) -> bool:
    """Motive's export (its first cell ``Format Version``) or the plain header."""
    lines = _lines(head)
    if not lines:
        return False
    if lines[0].startswith("Format Version,"):
        return True
    first = next((ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")), "")
    return _is_plain_header(first)


def _number(text: str, where: str) -> float:
    if text.strip() == "":
        return math.nan
    try:
        v = float(text)
    except ValueError:
        raise RecordingError(f"{where}: not a number: {text!r}") from None
    if not math.isfinite(v):
        raise RecordingError(f"{where}: not a finite number: {text!r}")
    return v


def _read_rows(path: Path) -> tuple[list[list[str]], bool]:
    """The CSV rows, and whether the file ends with a newline (else its last line may have
    been cut off while the export was written)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as err:
        raise RecordingError(f"{path}: cannot read: {err.strerror or err}") from err
    except UnicodeDecodeError:
        raise RecordingError(f"{path}: not UTF-8 text") from None
    return list(csv.reader(io.StringIO(text))), text.endswith(("\n", "\r")) or not text


def _drop_cut_last(data: list[tuple[int, list[str]]], width: int, complete: bool,
                   notes: list[str]) -> list[tuple[int, list[str]]]:
    """``data`` (line, fields) without a last line cut off mid-row (no newline at the end of
    the file, and fewer fields than ``width`` or a field that is not a number), with a note."""
    if complete or not data:
        return data
    last = data[-1][1]
    if len(last) < width or not all(c.strip() == "" or is_number(c) for c in last):
        notes.append(f"last line cut off mid-row (no newline at the end): dropped: "
                     f"{','.join(last)[:60]!r}")
        return data[:-1]
    return data


def _motive(path: Path, rows: list[list[str]], want: str | None, complete: bool = True,
            units: str | None = None, map_path: Path | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, str, list[str]]:
    """Time [s], positions (N, 3), quaternions (N, 4: x, y, z, w), length scale [m per unit],
    the rigid body's name, notes. ``units`` (the map's) is needed when the header does not
    state the length unit."""
    scale = _motive_scale(path, rows[0], units, map_path)
    header_at, label = _motive_header(path, rows)
    cols, kinds = rows[header_at], rows[header_at - 1]
    want, index = _motive_body_columns(path, cols, kinds, label, want)
    notes: list[str] = []
    data = [(k + 1, r) for k, r in enumerate(rows[header_at + 1:], start=header_at + 1)
            if any(c.strip() for c in r)]
    data = _drop_cut_last(data, len(cols), complete, notes)
    t, pq = _motive_values(path, data, len(cols), [index[key] for key in _MOTIVE_NEED])
    return t, pq[:, :3], pq[:, 3:], scale, want, notes


#: A rigid body's columns in a Motive export, in the order of the pose: position, quaternion.
_MOTIVE_NEED = [("Position", a) for a in "XYZ"] + [("Rotation", a) for a in "XYZW"]


def _motive_scale(path: Path, meta: list[str], units: str | None,
                  map_path: Path | None) -> float:
    """The length scale [m per unit] of a Motive export from its first row ``meta`` (or the
    map's ``units`` where it states none), after checking it holds global quaternions."""
    info = {meta[i].strip(): meta[i + 1].strip() for i in range(0, len(meta) - 1, 2)}
    if info.get("Rotation Type", "Quaternion").lower() != "quaternion":
        raise RecordingError(f"{path}: rotation type {info['Rotation Type']!r}; export with "
                             "Rotation Type = Quaternion")
    if info.get("Coordinate Space", "Global").lower() != "global":
        raise RecordingError(f"{path}: coordinate space {info['Coordinate Space']!r}; export "
                             "in Global coordinates")
    if "Length Units" in info:
        if units is not None:
            raise ConfigError(f"{map_path}: key 'mocap.units': the Motive export states its "
                              f"unit ({info['Length Units']}); remove the key")
        unit = info["Length Units"].lower()
        if unit not in _MOTIVE_UNITS:
            raise RecordingError(f"{path}: unknown length unit {info['Length Units']!r}")
        return _MOTIVE_UNITS[unit]
    if units is None:
        raise RecordingError(f"{path}: the export does not state its length unit (no 'Length "
                             "Units' in its first row); give it in the map: [mocap] units = "
                             "\"m\", \"cm\" or \"mm\" (--map)")
    return _UNITS[units]


def _motive_header(path: Path, rows: list[list[str]]) -> tuple[int, dict[str, list[str]]]:
    """The index of the Frame row of a Motive export and its label rows (Type, Name, ID) by
    name."""
    label = {}
    header_at = None
    for k, row in enumerate(rows[1:40], start=1):
        if len(row) > 1 and row[1].strip() in ("Type", "Name", "ID"):
            label[row[1].strip()] = row
        if row and row[0].strip() == "Frame":
            header_at = k
            break
    if header_at is None or "Type" not in label or "Name" not in label:
        raise RecordingError(f"{path}: not a Motive CSV export with a header (the Type, Name "
                             "and Frame rows are missing)")
    return header_at, label


def _cell(row: list[str], j: int) -> str:
    """Field ``j`` of ``row``, stripped; "" past its end."""
    return row[j].strip() if j < len(row) else ""


def _motive_body_columns(path: Path, cols: list[str], kinds: list[str],
                         label: dict[str, list[str]], want: str | None
                         ) -> tuple[str, dict[tuple[str, str], int]]:
    """The rigid body (``want``, or the only one) and its columns by (kind, axis), all of
    :data:`_MOTIVE_NEED` present."""
    types, names = label["Type"], label["Name"]
    bodies = sorted({_cell(names, j) for j in range(2, len(cols))
                     if _cell(types, j) == "Rigid Body"})
    if not bodies:
        raise RecordingError(f"{path}: no rigid body in the export")
    if want is None:
        if len(bodies) > 1:
            raise RecordingError(f"{path}: several rigid bodies ({', '.join(bodies)}); name one "
                                 "in the map ([mocap] rigid_body)")
        want = bodies[0]
    elif want not in bodies:
        raise RecordingError(f"{path}: no rigid body {want!r} (there are: {', '.join(bodies)})")
    index = {}
    for j in range(2, len(cols)):
        if _cell(types, j) == "Rigid Body" and _cell(names, j) == want:
            kind = _cell(kinds, j)
            if kind in ("Rotation", "Position"):
                index[(kind, _cell(cols, j))] = j
    missing = [f"{k} {a}" for k, a in _MOTIVE_NEED if (k, a) not in index]
    if missing:
        raise RecordingError(f"{path}: rigid body {want!r} lacks columns {', '.join(missing)}")
    return want, index


def _motive_values(path: Path, data: list[tuple[int, list[str]]], width: int,
                   columns: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Time [s], shape (N,), and the pose columns ``columns`` (N, 7) of the numbered data
    rows ``data`` of a header ``width`` fields wide."""
    t = np.empty(len(data))
    pq = np.empty((len(data), 7))
    for i, (line, r) in enumerate(data):
        if len(r) < width:
            raise RecordingError(f"{path}, line {line}: {len(r)} fields, fewer than the "
                                 f"header's {width}")
        t[i] = _number(r[1], f"{path}, line {line}, column 'Time (Seconds)'")
        for c, j in enumerate(columns):
            pq[i, c] = _number(r[j] if j < len(r) else "", f"{path}, line {line}, column {j + 1}")
    if np.isnan(t).any():
        raise RecordingError(f"{path}: a row without its time")
    return t, pq


def _plain(path: Path, rows: list[list[str]], complete: bool = True,
           notes: list[str] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    start = next((i for i, r in enumerate(rows)
                  if any(c.strip() for c in r) and not r[0].lstrip().startswith("#")), None)
    if start is None or not _is_plain_header(",".join(rows[start])):
        raise RecordingError(f"{path}: expected the header {', '.join(PLAIN_HEADER)}")
    data = [(i, r) for i, r in enumerate(rows[start + 1:], start=start + 2)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    data = _drop_cut_last(data, 8, complete, [] if notes is None else notes)
    arr = np.empty((len(data), 8))
    for k, (line, r) in enumerate(data):
        if len(r) != 8:
            raise RecordingError(f"{path}, line {line}: {len(r)} fields, expected 8")
        for c in range(8):
            arr[k, c] = _number(r[c], f"{path}, line {line}, column '{PLAIN_HEADER[c]}'")
    if np.isnan(arr[:, 0]).any():
        raise RecordingError(f"{path}: a row without its time")
    return arr[:, 0], arr[:, 1:4], arr[:, 4:8]


def quaternion_matrices(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of unit quaternions ``(x, y, z, w)`` (normalised first)."""
    q = np.asarray(q_xyzw, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def floor_pose(pos: np.ndarray, quat: np.ndarray, scale: float, rotation: np.ndarray,
               m: MocapMap) -> np.ndarray:
    """The robot's floor pose ``(X [m], Y [m], phi [deg])`` per sample (NaN where occluded;
    heading continuous)."""
    ok = np.isfinite(pos).all(axis=1) & np.isfinite(quat).all(axis=1) & \
        (np.linalg.norm(np.nan_to_num(quat), axis=1) > 0.5)
    out = np.full((len(pos), 3), np.nan)
    if not ok.any():
        return out
    r_body = quaternion_matrices(quat[ok])
    centre = pos[ok] * scale + r_body @ np.asarray(m.centre_m, dtype=float)
    floor = centre @ rotation.T + np.asarray(m.translation_m, dtype=float)
    fwd = np.asarray(m.forward_axis, dtype=float)
    f = (r_body @ (fwd / np.linalg.norm(fwd))) @ rotation.T
    out[ok, 0] = floor[:, 0]
    out[ok, 1] = floor[:, 1]
    out[ok, 2] = np.degrees(np.arctan2(f[:, 1], f[:, 0]))
    out[:, 2] = unwrap_deg(out[:, 2])
    return out


def read(path: Path, *, map_path: Path | None = None, recording: Path | None = None,
         start_s: str | float | None = None,
         model_pose: tuple[np.ndarray, np.ndarray] | None = None) -> ImportResult:
    """Import a motion-capture CSV (module docstring); ``recording`` and ``start_s`` as there.

    ``model_pose`` is ``(t_s, pose)``, the model's prediction for the recording's commands,
    needed by ``start_s="auto"`` (the command line computes it with the map's ``calibration``
    and ``robot``: the model is a layer above the importers).
    """
    path = Path(path)
    m = load_mocap_map(map_path)
    rows, complete = _read_rows(path)
    if not rows:
        raise RecordingError(f"{path}: empty file")
    notes: list[str] = []
    if rows[0] and rows[0][0].startswith("Format Version"):
        layout = "motive"
        t, pos, quat, scale, body, more = _motive(path, rows, m.rigid_body, complete, m.units,
                                                  map_path)
        notes += more
        up = m.up or "y"
    else:
        layout = "plain"
        t, pos, quat = _plain(path, rows, complete, notes)
        scale, body = _UNITS[m.units or "m"], None
        up = m.up or "z"
    if len(t) < 2 or not np.all(np.diff(t) > 0):
        raise RecordingError(f"{path}: times must increase (at least two samples)")
    rotation = m.rotation if m.rotation is not None else _UP[up]
    _check_forward_axis(quat, rotation, m, map_path)
    pose = floor_pose(pos, quat, scale, rotation, m)
    occluded = int((~np.isfinite(pose).all(axis=1)).sum())
    if occluded:
        notes.append(f"{occluded} of {len(t)} samples occluded (left empty)")
    meta: dict[str, Any] = {
        "source": str(path), "format": NAME, "layout": layout, "rigid_body": body,
        "map": None if map_path is None else str(map_path),
        "capture_to_floor": {"rotation": rotation.tolist(), "translation_m":
                             list(m.translation_m), "scale_m_per_unit": scale,
                             "forward_axis": list(m.forward_axis), "centre_m": list(m.centre_m)},
        "capture_samples": len(t), "occluded_samples": occluded,
    }
    if recording is None:
        if isinstance(start_s, str) and start_s.strip().lower() == "auto":
            raise ConfigError("--start-s auto needs --recording (the commands to align with)")
        shift = 0.0 if start_s is None else _start(start_s)
        meta.update({"capture_start_s": shift, "notes": list(notes)})
        rec = empty_like_times(t - t[0] + shift, meta).with_values(pose=pose)
        return ImportResult(rec, tuple(notes))
    base = read_recording(recording)
    tc = t - t[0]
    if start_s is None or (isinstance(start_s, str) and start_s.strip().lower() == "auto"):
        if model_pose is None:
            raise ConfigError("--start-s auto needs the model's prediction for the recording "
                              "(given by `mecanum-hil import`); or give --start-s S")
        shift = onset_offset(tc, pose, model_pose[0], model_pose[1], source=str(path))
        how = "auto: the robot's motion onset (1 cm) against the model for the commands"
    else:
        shift, how = _start(start_s), "given"
    notes.append(f"capture's first sample at recording time {shift:.4f} s ({how})")
    meta.update({"capture_start_s": shift, "capture_start_method": how})
    filled = fill_pose(base, tc, pose, shift, {"pose_source": f"import {path}",
                                               "pose_import": meta},
                       track=f"{path}: the capture", recording=str(recording),
                       offset_option="--start-s")
    prior = base.metadata.get("notes")
    prior = [prior] if isinstance(prior, str) else list(prior or [])
    filled = filled.with_values(metadata={**filled.metadata, "notes": prior + notes})
    return ImportResult(filled, tuple(notes))


#: Least length of the forward axis's projection on the floor (the median over the samples):
#: sin(10 deg); an axis closer to the vertical gives no heading.
MIN_FLOOR_PROJECTION = math.sin(math.radians(10.0))


def _forward_on_floor(quat: np.ndarray, rotation: np.ndarray, m: MocapMap) -> np.ndarray:
    """The robot's forward axis in floor coordinates (N, 3), for unit quaternions ``quat``."""
    fwd = np.asarray(m.forward_axis, dtype=float)
    return (quaternion_matrices(quat) @ (fwd / np.linalg.norm(fwd))) @ rotation.T


def _check_forward_axis(quat: np.ndarray, rotation: np.ndarray, m: MocapMap,
                        map_path: Path | None) -> None:
    """Refuse a forward axis that does not project onto the floor plane (phi would be 0 or
    noise): it is (nearly) vertical in the floor frame for most samples."""
    ok = np.isfinite(quat).all(axis=1) & (np.linalg.norm(np.nan_to_num(quat), axis=1) > 0.5)
    if not ok.any():
        return
    f = _forward_on_floor(quat[ok], rotation, m)
    horizontal = float(np.median(np.hypot(f[:, 0], f[:, 1])))
    if horizontal < MIN_FLOOR_PROJECTION:
        where = f"{map_path}: key" if map_path is not None else "the default of key"
        raise ConfigError(f"{where} 'mocap.forward_axis' {list(m.forward_axis)} does not project "
                          f"onto the floor plane (its floor part is {horizontal:.3g} of its "
                          "length: it points up or down, giving no heading); give the robot's "
                          "forward direction in the rigid body's own frame")


def _start(value: str | float) -> float:
    try:
        v = float(value)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise ConfigError(f"--start-s must be a number of seconds or auto, got {value!r}")
    return v

