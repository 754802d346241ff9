"""Importers: foreign logs in, recordings out (``mecanum-hil import``).

Each format lives in its own module, listed in :data:`FORMATS` by name and imported only when
needed (a format's own libraries are imported inside its functions). A format module defines:

``NAME: str``
    The format's name (the key in :data:`FORMATS`).
``sniff(path: Path, head: bytes) -> bool``
    Whether the file is of this format, judged by its content (``head`` is the file's first
    :data:`HEAD_BYTES` bytes) and, where that helps, its name. A text format's ``sniff`` may
    also take ``encoding`` (the map's ``file.encoding``, given to ``auto`` detection).
``read(path: Path, **options) -> ImportResult``
    The recording; keyword options only (``map_path``, ``cmd_topic``, ``dbc_path`` ...). The
    result's notes are also the sidecar's ``notes`` (:func:`import_source` puts them there
    when the format does not).
``GENERIC: bool`` (optional, default False)
    A catch-all format (plain text) that ``auto`` chooses only when no specific format claims
    the file: a motion-capture CSV is also text, and must not be ambiguous with it.
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from ..errors import ConfigError, RecordingError
from ..io.recording import Recording, refuse_absurd_values

#: Format name -> module path; one line per format, added by whoever writes the module.
FORMATS: dict[str, str] = {
    "text": "mecanum_hil.importers.text",
    "rosbag": "mecanum_hil.importers.rosbag",
    "mcap": "mecanum_hil.importers.mcap_run",
    "canlog": "mecanum_hil.importers.canlog",
    "mocap": "mecanum_hil.importers.mocap",
}

#: How much of the file's beginning ``sniff`` sees [bytes].
HEAD_BYTES = 65536


@dataclass(frozen=True)
class ImportResult:
    """What an importer returns.

    Attributes
    ----------
    recording : Recording
        The imported recording (its metadata becomes the JSON sidecar).
    notes : tuple of str
        One-line warnings and what was done to the data (also in the sidecar's ``notes``).
    """

    recording: Recording
    notes: tuple[str, ...] = ()


def format_module(name: str) -> ModuleType:
    """The module of a format, imported by name."""
    if name not in FORMATS:
        raise ConfigError(f"unknown import format '{name}' (known: {', '.join(sorted(FORMATS))})")
    return importlib.import_module(FORMATS[name])


def _head(path: Path) -> bytes:
    try:
        with path.open("rb") as fh:
            return fh.read(HEAD_BYTES)
    except FileNotFoundError:
        raise RecordingError(f"{path}: file not found") from None
    except IsADirectoryError:
        return b""  # a directory (a ROS 2 bag) is sniffed by its path
    except OSError as err:
        raise RecordingError(f"{path}: cannot read: {err.strerror or err}") from err


def detect_format(path: str | Path, map_path: str | Path | None = None) -> str:
    """The format of a file, asked of every format's ``sniff``.

    Parameters
    ----------
    path : str or Path
        The log.
    map_path : str or Path, optional
        The user's map: the text encoding it states (``[file] encoding``) is given to formats
        whose ``sniff`` reads text.

    Raises
    ------
    RecordingError
        When no format, or more than one specific format, claims the file.
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: file not found")
    head = _head(p)
    encoding = _map_encoding(map_path)
    specific: list[str] = []
    generic: list[str] = []
    for name in FORMATS:
        try:
            mod = format_module(name)
        except ImportError:  # a format whose module needs a missing extra cannot claim files
            continue
        kw = ({"encoding": encoding} if encoding is not None
              and "encoding" in inspect.signature(mod.sniff).parameters else {})
        if mod.sniff(p, head, **kw):
            (generic if getattr(mod, "GENERIC", False) else specific).append(name)
    found = specific or generic
    if not found:
        if p.is_file() and not head.strip():
            raise RecordingError(f"{p}: empty file: nothing to import")
        if p.is_file() and len([ln for ln in head.splitlines() if ln.strip()]) == 1 \
                and len(head) < 4096:
            raise RecordingError(f"{p}: a single line (a header without data rows?); if it "
                                 "is data, give --format")
        raise RecordingError(f"{p}: format not recognised (known: {', '.join(sorted(FORMATS))}); "
                             "give --format")
    if len(found) > 1:
        raise RecordingError(f"{p}: ambiguous format ({', '.join(found)}); give --format")
    return found[0]


#: Options whose command-line flag is not the option's name with dashes (the wheel radius
#: comes from the robot profile that ``--robot`` names).
_FLAGS = {"map_path": "--map", "dbc_path": "--dbc", "wheel_radius_m": "--robot"}

#: Options the command line computes itself: no flag of their own, not listed to the user.
_INTERNAL = {"model_pose"}


def _flag(option: str) -> str:
    return _FLAGS.get(option, "--" + option.replace("_", "-"))


def import_source(path: str | Path, fmt: str = "auto", **options) -> ImportResult:
    """Import a log with the format's ``read``.

    Parameters
    ----------
    path : str or Path
        The log (a file, or a directory for formats that are directories).
    fmt : str
        A name in :data:`FORMATS`, or ``"auto"`` to detect it.
    **options
        Keyword options of the format's ``read``; one it does not take is refused.
    """
    p = Path(path)
    name = detect_format(p, options.get("map_path")) if fmt == "auto" else fmt
    mod = format_module(name)
    params = inspect.signature(mod.read).parameters
    takes = [k for k, v in params.items()
             if k != "path" and v.kind in (v.KEYWORD_ONLY, v.POSITIONAL_OR_KEYWORD)]
    for key in options:
        if key not in takes:
            known = ", ".join(_flag(t) for t in takes if t not in _INTERNAL) or "no options"
            raise ConfigError(f"format '{name}' does not take {_flag(key)} (it takes: {known})")
    if not p.exists():
        raise RecordingError(f"{p}: file not found")
    with np.errstate(over="ignore"):  # a unit conversion overflowing: refused just below
        res = mod.read(p, **options)
    rec = res.recording
    refuse_absurd_values([rec.t_s, *rec.commands.T, *rec.wheel_rpm.T, *rec.pose.T],
                         lambda i: f"{p}: imported row {i + 1} (t = {rec.t_s[i]:.6g} s)")
    if "notes" not in res.recording.metadata:  # a format that keeps them only in the result
        res = with_notes(res)
    return res


def _map_encoding(map_path) -> str | None:
    """The ``[file] encoding`` a map states, for detection (``None`` without one; a map that
    cannot be read is reported by the format that reads it)."""
    if map_path is None:
        return None
    from ..io.toml_config import load_toml

    try:
        enc = load_toml(map_path).get("file", {}).get("encoding")
    except (ConfigError, AttributeError):
        return None
    return enc if isinstance(enc, str) else None


def with_notes(res: ImportResult, *notes: str) -> ImportResult:
    """``res`` with ``notes`` added, in its notes and in its sidecar's ``notes`` (which then
    hold every note of the result, as the module docstring promises)."""
    all_notes = tuple(dict.fromkeys((*res.notes, *notes)))
    kept = list(res.recording.metadata.get("notes") or [])
    meta = {**res.recording.metadata, "notes": kept + [n for n in all_notes if n not in kept]}
    return ImportResult(res.recording.with_values(metadata=meta), all_notes)
