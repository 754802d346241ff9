"""Time-stamped streams (commands, wheel speeds, pose) merged into recording rows (pure).

Shared by the importers whose sources carry each quantity on its own stream at its own times
(ROS bags, CAN logs). The rule, documented in docs/ros2.md ("Alignment"):

1. Times are rounded to the microsecond (the recording's resolution: ``t_s`` is written with
   six decimals). Rows are the union of the command times and the wheel-speed times; samples
   in the same microsecond share one row, the later one's values winning.
2. Commands are piecewise constant (docs/conventions.md): every row carries the last command
   at or before its time (zero-order hold); rows before the first command are dropped (the
   model's input is unknown there) and a note says how many.
3. Wheel speeds appear only on the rows of their own samples (exact values, never
   interpolated); a wheel absent from a sample is empty.
4. Pose is linearly interpolated onto every row inside the pose stream's time span (heading
   unwrapped first, so it stays continuous); empty outside it.
5. ``t_s`` counts from the first kept row; that row's time on the source's clock [ns] is the
   metadata's ``start_time_ns``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import RecordingError
from ..io.recording import Recording


@dataclass(frozen=True)
class Stream:
    """One quantity's samples in time order.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (N,)
        Sample times [ns] on the source's clock.
    values : ndarray, shape (N, width)
        Samples; NaN where a component was not in the sample.
    """

    t_ns: np.ndarray
    values: np.ndarray

    @classmethod
    def of(cls, t_ns, values, width: int) -> Stream:
        """A stream sorted by time (stable: equal times keep their order of arrival)."""
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        v = np.asarray(values, dtype=float).reshape(-1, width)
        order = np.argsort(t, kind="stable")
        return cls(t[order], v[order])

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


#: How far a sample's time may lie before an earlier sample's (receive jitter) and still be
#: sorted into place [ns]; more is an error (a clock reset, a stamp from another clock).
BACK_TOLERANCE_NS = 1_000_000


def check_time_order(t_ns, name, what: str = "samples",
                     tolerance_ns: int = BACK_TOLERANCE_NS) -> str:
    """Refuse time running back by more than ``tolerance_ns``; say what jitter is sorted.

    Parameters
    ----------
    t_ns : array_like of int, shape (N,)
        Sample times [ns] in the order the source delivered them.
    name : callable
        ``name(i)`` names sample ``i`` (0-based, in that order) in the error.
    what : str
        What the samples are, for the note.
    tolerance_ns : int
        Largest step back that is sorted rather than refused [ns].

    Returns
    -------
    str
        A note on the samples sorted into time order, or "" when they were in order.

    Raises
    ------
    RecordingError
        A sample more than ``tolerance_ns`` before an earlier one.
    """
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    if t.size < 2:
        return ""
    prev_max = np.maximum.accumulate(t)[:-1]
    back = prev_max - t[1:]
    late = back > tolerance_ns
    if late.any():
        i = int(np.argmax(late)) + 1
        d = int(back[i - 1])
        step = f"{d * 1e-6:.3f} ms" if d < 1_000_000_000 else f"{d * 1e-9:.6g} s"
        raise RecordingError(
            f"{name(i)}: time {t[i] * 1e-9:.6f} s does not increase: it runs back {step} "
            f"from {prev_max[i - 1] * 1e-9:.6f} s, more than "
            f"{tolerance_ns * 1e-6:g} ms (a clock reset or stamps of another clock?)")
    n_back = int((back > 0).sum())
    if not n_back:
        return ""
    return (f"{n_back} {what} up to {back.max() * 1e-6:.3f} ms earlier than a sample before "
            "them (jitter) sorted into time order")


def _to_microseconds(stream: Stream) -> Stream:
    # two samples less than 1 us apart would print as one time in the CSV: make them one row
    return Stream((stream.t_ns + 500) // 1000 * 1000, stream.values)


def _last_per_time(t_ns: np.ndarray, values: np.ndarray,
                   rows_t: np.ndarray) -> tuple[np.ndarray, int]:
    """Values placed on their own rows; samples sharing a time merged, later ones winning.

    Returns the rows and how many values a later one in the same row replaced (components
    that only complete each other, as one frame per wheel does, replace nothing).
    """
    out = np.full((rows_t.shape[0], values.shape[1]), np.nan)
    pos = np.searchsorted(rows_t, t_ns)
    on_a_row = t_ns >= rows_t[0]  # samples before the first row are not on any row
    replaced = 0
    for j in range(values.shape[1]):
        ok = np.isfinite(values[:, j]) & on_a_row
        # a repeated index takes the last value assigned: the later sample wins
        out[pos[ok], j] = values[ok, j]
        replaced += int(ok.sum()) - np.unique(pos[ok]).size
    return out, replaced


def merge_streams(commands: Stream, wheels: Stream, pose: Stream | None = None,
                  metadata: dict | None = None,
                  source: str = "source") -> tuple[Recording, tuple[str, ...]]:
    """Merge command, wheel-speed and pose streams into a recording.

    Parameters
    ----------
    commands : Stream
        ``(n [rpm], omega [deg/s], theta [deg])`` as sent, width 3.
    wheels : Stream
        Wheel speeds 1..4 [rpm], width 4.
    pose : Stream, optional
        ``(X [m], Y [m], phi [deg])``, width 3.
    metadata : dict, optional
        Sidecar content; ``start_time_ns`` (the absolute time of ``t_s = 0``) is added.
    source : str
        Name used in messages.

    Returns
    -------
    (Recording, tuple of str)
        The recording and one-line notes on what was done.

    Raises
    ------
    RecordingError
        When no command precedes the last row (nothing to keep).
    """
    notes: list[str] = []
    if not len(commands):
        raise RecordingError(f"{source}: no commands")
    commands, wheels = _to_microseconds(commands), _to_microseconds(wheels)
    if pose is not None:
        pose = _to_microseconds(pose)
    rows_t = np.union1d(commands.t_ns, wheels.t_ns)
    first = int(np.searchsorted(rows_t, commands.t_ns[0]))
    if first:
        notes.append(f"dropped {first} sample(s) before the first command (the model's input "
                     "is unknown there)")
    rows_t = rows_t[first:]
    if rows_t.size == 0:
        raise RecordingError(f"{source}: no samples at or after the first command")
    idx = np.searchsorted(commands.t_ns, rows_t, side="right") - 1
    cmd = commands.values[idx]
    wheel, replaced = (_last_per_time(wheels.t_ns, wheels.values, rows_t) if len(wheels)
                       else (np.full((rows_t.size, 4), np.nan), 0))
    if replaced:  # said, not silent
        notes.append(f"{replaced} wheel speed(s) replaced by a later sample in the same "
                     "microsecond")
    pose_rows = np.full((rows_t.size, 3), np.nan)
    if pose is not None and len(pose):
        pt = pose.t_ns
        # interpolate on float seconds relative to the first pose: int64 ns would lose nothing,
        # but np.interp works in float64 anyway and absolute epoch ns would cost precision
        rel = (pt - pt[0]).astype(float) * 1e-9
        at = (rows_t - pt[0]).astype(float) * 1e-9
        inside = (rows_t >= pt[0]) & (rows_t <= pt[-1])
        pv = pose.values.copy()
        ok = np.isfinite(pv).all(axis=1)
        pv, rel_ok = pv[ok], rel[ok]
        if rel_ok.size:
            pv[:, 2] = np.rad2deg(np.unwrap(np.deg2rad(pv[:, 2])))
            for j in range(3):
                pose_rows[inside, j] = np.interp(at[inside], rel_ok, pv[:, j])
        outside = int((~inside).sum())
        if outside:
            notes.append(f"pose empty on {outside} row(s) outside the pose stream's time span")
    t0 = int(rows_t[0])
    t_s = (rows_t - t0).astype(float) * 1e-9
    meta = dict(metadata or {})
    meta["start_time_ns"] = t0
    return Recording(t_s, cmd, wheel, pose_rows, {}, meta), tuple(notes)
