"""Timing telemetry by the controller's clock (pure).

``record`` stamps every row with the host's receive time ``t_s`` and keeps the controller's own
timestamp of each telemetry sample in the extra column ``controller_time_s``. A host that stalls
(a loaded machine, a garbage collection, a USB hiccup) receives a burst of samples late: their
receive times are wrong by the stall, and on a transient a 40 ms error is tens of rpm. The
controller's clock does not stall. For analysis (fit, diagnose, shadow replay), telemetry rows
are re-timed onto the host's clock by the controller's: ``t = controller_time + offset(t)``,
where the offset is the lower envelope of ``receive - controller`` time (a sample can arrive
late, never early), a straight line through the least-delayed sample of each second so that a
drift between the two crystals is followed. Command rows keep their send times; each telemetry
row then gets the command in force at its new time.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import MecanumHILWarning
from .recording import Recording, read_recording

CONTROLLER_TIME = "controller_time_s"


def controller_offset(receive_s: np.ndarray, controller_s: np.ndarray,
                      window_s: float = 1.0) -> tuple[float, float]:
    """Offset and drift mapping controller time onto receive time (the lower envelope).

    Returns ``(a, b)`` with ``receive ~ controller + a + b * controller`` for the least-delayed
    samples and ``controller + a + b * controller <= receive`` for every sample [s], [-].
    """
    d = receive_s - controller_s
    c = controller_s
    bins = np.floor((c - c[0]) / window_s).astype(np.int64)
    order = np.lexsort((d, bins))
    first = np.ones(order.size, bool)
    first[1:] = bins[order][1:] != bins[order][:-1]
    lows = order[first]  # the least-delayed sample of each window
    if lows.size >= 3:
        b, a = np.polyfit(c[lows], d[lows], 1)
    else:
        a, b = float(d.min()), 0.0
    a -= max(0.0, float(np.max(a + b * c - d)))  # never earlier than received
    return float(a), float(b)


class ClockWarning(MecanumHILWarning):
    """The controller's clock column cannot be trusted and is not used."""


#: How far the controller's clock may run fast or slow against the host's before it is not
#: trusted (crystals differ by parts per million; a factor this far off is a wrong column or
#: unit) [-].
MAX_CLOCK_RATE_ERROR = 0.1


def clock_doubt(receive_s: np.ndarray, controller_s: np.ndarray) -> str:
    """Why a controller clock cannot time its telemetry ("" when it can): it must run strictly
    forward (a reset, a wrap or a frozen clock does not) at the host's rate within
    :data:`MAX_CLOCK_RATE_ERROR` over the recording."""
    d = np.diff(controller_s)
    if not (d > 0).all():
        k = int(np.flatnonzero(~(d > 0))[0])
        how = "runs back" if d[k] < 0 else "stands still"
        why = "a reset?" if d[k] < 0 else "a frozen clock?"
        return (f"it {how} from telemetry sample {k + 1} to {k + 2}, {controller_s[k]:.6g} -> "
                f"{controller_s[k + 1]:.6g} s, {why}")
    span_c = float(controller_s[-1] - controller_s[0])
    span_r = float(receive_s[-1] - receive_s[0])
    if span_r > 0 and not abs(span_c / span_r - 1.0) <= MAX_CLOCK_RATE_ERROR:
        return (f"it spans {span_c:.6g} s while the host received for {span_r:.6g} s: a "
                "wrong unit or column, or a jump of the host's clock?")
    return ""


def retime_telemetry(rec: Recording, source: str = "recording") -> Recording:
    """Telemetry rows timed by the controller's clock (see the module docstring).

    A recording without a ``controller_time_s`` column (or with fewer than two values in it) is
    returned unchanged; so is one whose clock cannot be trusted (:func:`clock_doubt`), with a
    :class:`ClockWarning` naming ``source``.
    """
    if CONTROLLER_TIME not in rec.extra:
        return rec
    ct = rec.extra_numeric(CONTROLLER_TIME)
    tlm = np.isfinite(ct)
    if tlm.sum() < 2:
        return rec
    doubt = clock_doubt(rec.t_s[tlm], ct[tlm])
    if doubt:
        warnings.warn(f"{source}: {CONTROLLER_TIME} not used: {doubt}; telemetry timed by the "
                      "host's receive times",
                      ClockWarning, stacklevel=2)
        return rec
    a, b = controller_offset(rec.t_s[tlm], ct[tlm])
    t_new = rec.t_s.copy()
    t_new[tlm] = ct[tlm] + a + b * ct[tlm]
    order = np.argsort(t_new, kind="stable")
    out = rec.select(order)
    t = t_new[order]
    for i in range(1, t.size):  # equal times after merging: keep them strictly increasing
        if t[i] <= t[i - 1]:
            t[i] = t[i - 1] + 1e-6
    tlm = tlm[order]
    commands = out.commands.copy()
    is_cmd = ~tlm & np.isfinite(commands).all(axis=1)
    if is_cmd.any():
        last = np.maximum.accumulate(np.where(is_cmd, np.arange(t.size), -1))
        take = tlm & (last >= 0)
        commands[take] = commands[last[take]]
    meta = dict(rec.metadata)
    meta["retimed"] = {"by": CONTROLLER_TIME, "offset_s": a, "drift": b}
    return out.with_values(t_s=t, commands=commands, metadata=meta)


def read_for_analysis(path) -> Recording:
    """Read a recording and time its telemetry by the controller's clock when it has one.

    What ``fit``, ``diagnose`` and ``shadow --replay`` read: the file itself is not changed.
    """
    return retime_telemetry(read_recording(path), str(path))
