"""MCAP files written by ``mecanum-hil export`` in: the recording back (round trip).

Rows are the union of the times (``t_s``, carried exactly in every message) of the commands,
measured wheel speeds, measured 2-D pose and extra-column channels; the sidecar and the order
of the extra columns come from the file's ``mecanum_hil.recording`` metadata record. The
prediction and the alarms are not part of a recording and are left out. A ROS 2 bag stored as
MCAP is the ``rosbag`` format's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import ConfigError, MecanumHILError, RecordingError
from ..io.mcap_export import CHANNELS, METADATA_NAME
from ..io.recording import COMMAND_COLUMNS, POSE_COLUMNS, WHEEL_COLUMNS, Recording
from .rosbag import mcap_profile

NAME = "mcap"

_BLOCKS = {CHANNELS["commands"].topic: (0, COMMAND_COLUMNS),
           CHANNELS["wheels"].topic: (1, WHEEL_COLUMNS),
           CHANNELS["pose2d"].topic: (2, POSE_COLUMNS)}


def sniff(path: Path, head: bytes) -> bool:
    """An MCAP file whose header names mecanum-hil as the writing library."""
    prof = mcap_profile(head)
    return prof is not None and prof[1].startswith("mecanum-hil")


def read(path: Path):
    """Read an MCAP written by ``mecanum-hil export`` back into the recording.

    Returns
    -------
    ImportResult
    """
    from . import ImportResult

    try:
        from mcap.reader import make_reader
    except ImportError as err:
        raise ConfigError("reading MCAP needs the 'foxglove' extra: pip install "
                          "'mecanum-hil[foxglove]'") from err
    p = Path(path)
    rows: dict[float, list] = {}
    metadata: dict = {}
    extra_names: list[str] = []
    try:
        with p.open("rb") as fh:
            reader = make_reader(fh)
            for record in reader.iter_metadata():
                if record.name == METADATA_NAME:
                    metadata = json.loads(record.metadata.get("sidecar", "{}"))
                    extra_names = json.loads(record.metadata.get("extra_columns", "[]"))
            extra_topic = CHANNELS["extra"].topic
            for _schema, channel, message in reader.iter_messages(
                    topics=[*_BLOCKS, extra_topic]):
                msg = json.loads(message.data)
                t = float(msg["t_s"])
                row = rows.get(t)
                if row is None:
                    row = rows[t] = [None, None, None, None]
                if channel.topic == extra_topic:
                    row[3] = msg["columns"]
                else:
                    k, names = _BLOCKS[channel.topic]
                    row[k] = [np.nan if msg.get(n) is None else float(msg[n]) for n in names]
    except MecanumHILError:
        raise
    except Exception as err:  # mcap, json, KeyError: a damaged or foreign file
        raise RecordingError(f"{p}: cannot read the MCAP (truncated or not written by "
                             f"mecanum-hil export?): {type(err).__name__}: {err}") from err
    if not rows:
        raise RecordingError(f"{p}: no recording rows in the MCAP")
    times = sorted(rows)
    width = (3, 4, 3)
    arrays = [np.full((len(times), w), np.nan) for w in width]
    extra: dict[str, list[str]] = {n: [] for n in extra_names}
    for i, t in enumerate(times):
        row = rows[t]
        for k in range(3):
            if row[k] is not None:
                arrays[k][i] = row[k]
        cols = row[3] or {}
        for n in extra_names:
            extra[n].append(cols.get(n, ""))
    rec = Recording(np.array(times), arrays[0], arrays[1], arrays[2], extra, metadata)
    return ImportResult(rec, (f"{len(times)} rows from {p.name}",))
