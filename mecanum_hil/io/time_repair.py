"""Time as real loggers write it (pure functions on arrays).

A logger stamps samples with a clock of finite resolution (1 ms is common) that need not agree
with the sampling clock: two samples then get the same stamp, or one a stamp a tick late and the
next a tick early (jitter). Counters of a few bits wrap. Samples go missing. None of this makes
the data wrong; refusing it (or dropping rows) loses good data. :func:`repair_time` changes only
the stamps that are not increasing, by less than the log's resolution plus one period, and says
what it did in one line. Every reader of recordings and logs uses it
(:func:`mecanum_hil.io.recording.read_recording`, the ``import`` formats).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Counter moduli tried when a time jumps back by much more than the resolution: 2**8 .. 2**32
#: ticks of 1 us, 1 ms or 1 s [s].
WRAP_CANDIDATES_S = tuple(sorted(2.0 ** k * u for k in range(8, 33) for u in (1e-6, 1e-3, 1.0)))

#: Longest gap an import accepts by default: this many median periods, and at least
#: :data:`MIN_DEFAULT_MAX_GAP_S`.
DEFAULT_MAX_GAP_PERIODS = 50
MIN_DEFAULT_MAX_GAP_S = 0.1


@dataclass(frozen=True)
class TimeRepair:
    """The outcome of :func:`repair_time`.

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Strictly increasing times [s] (the input, where nothing needed doing).
    note : str
        One line saying what was done ("" when the time was left alone and had no gaps).
    summary : dict
        The same as JSON-able numbers (for the sidecar's ``time_repair``).
    changed : bool
        Whether any stamp was changed.
    """

    t_s: np.ndarray
    note: str
    summary: dict
    changed: bool


def detect_resolution(t_s: np.ndarray) -> float:
    """The coarsest decimal step (1 s, 0.1 s ... 1 ns) that every stamp is a multiple of [s].

    Returns 0.0 for stamps finer than 1 ns (a float clock).
    """
    t = np.asarray(t_s, dtype=float)
    t = t - np.floor(t[0]) if t.size else t  # keeps the quotients small, so float error too
    probe = t[:: max(1, t.size // 4096)]  # rules out the coarse steps cheaply

    def multiple(x: np.ndarray, q: float) -> bool:
        return bool(np.all(np.abs(x / q - np.rint(x / q)) < 1e-3))

    for k in range(10):
        q = 10.0 ** -k
        if multiple(probe, q) and multiple(t, q):
            return q
    return 0.0


def decimal_resolution(fields) -> float | None:
    """The resolution a log writes its stamps at: 10^-(most decimals among ``fields``).

    ``fields`` are stamps as text (a sample of them is enough); None when one is in exponent
    notation or not a number (then :func:`detect_resolution` judges by value).
    """
    most = -1
    for f in fields:
        f = f.strip()
        if not f:
            continue
        if any(c in f for c in "eEnN"):
            return None
        whole, dot, frac = f.partition(".")
        whole = whole.lstrip("+-")
        if (frac and not frac.isdigit()) or (whole and not whole.isdigit()):
            return None
        most = max(most, len(frac) if dot else 0)
    return None if most < 0 else 10.0 ** -most


def _ms(x: float) -> str:
    return f"{x * 1e3:.3f} ms"


def _unwrap(t: np.ndarray, res: float, period: float, max_gap: float, wrap_s: float | None,
            row_name) -> tuple[np.ndarray, int, float]:
    """Unwrap a counter: add the modulus after each jump back that fits one.

    A jump fits a guessed modulus ``m`` when the step across it, ``t[i] + m - t[i-1]``, is a
    step the log makes elsewhere (at most 1.5 median periods plus the resolution) and ``m``
    spans at least 50 periods; a stated ``wrap_s`` fits any step up to the gap limit.
    """
    back = np.flatnonzero(np.diff(t) < -max(res, 0.0) * 1.5) + 1
    if back.size == 0:
        return t, 0, 0.0
    cands = (wrap_s,) if wrap_s else WRAP_CANDIDATES_S
    step = max_gap if wrap_s else 1.5 * period  # a guessed modulus: only across a usual step
    modulus = 0.0
    offset = np.zeros_like(t)
    for i in back:
        prev = t[i - 1]
        fit = [m for m in cands if m > prev - res and (wrap_s or m >= 50 * period)
               and 0.0 <= t[i] + m - prev <= step + res]
        if modulus:
            fit = [m for m in fit if m == modulus]
        if not fit:
            raise_back(t, i, res, row_name, prev)
        modulus = fit[0]
        offset[i:] += modulus
    return t + offset, back.size, modulus


def raise_back(t: np.ndarray, i: int, res: float, row_name, prev: float) -> None:
    from ..errors import RecordingError

    raise RecordingError(
        f"{row_name(i)}: time {t[i]:.6g} s does not increase: it runs back {_ms(prev - t[i])} "
        f"from {prev:.6g} s, more than the log's resolution ({_ms(res)}); a counter that wraps is "
        "unwrapped only when the jump fits a modulus (give it as 'wrap' in the map)")


def repair_time(t_s, *, resolution_s: float | None = None, max_gap_s: float | None = None,
                wrap_s: float | None = None, row_name=None) -> TimeRepair:
    """Make logged time strictly increasing, the way its logger meant it.

    1. A counter that wraps (a jump back to near zero from just below a modulus, ``wrap_s`` or
       one of :data:`WRAP_CANDIDATES_S`) is unwrapped.
    2. A stamp more than the resolution below an earlier one is an error naming its row.
    3. Stamps that do not exceed every earlier stamp (repeated stamps, jitter back within the
       resolution) join the row that set that stamp; the rows of such a run are spread evenly
       from its stamp towards the next larger stamp, at most one median period apart
       (:func:`_respace`). Every other stamp is kept.
    4. Gaps (a step above 1.5 median periods in a regularly sampled log) are kept as gaps, no
       sample is invented or dropped; one longer than ``max_gap_s`` is an error naming its row.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Logged times, finite [s].
    resolution_s : float, optional
        The stamps' resolution [s]; detected (:func:`detect_resolution`) when omitted.
    max_gap_s : float, optional
        Longest gap accepted [s]; no limit when omitted.
    wrap_s : float, optional
        The counter's modulus [s]; detected when omitted.
    row_name : callable, optional
        ``row_name(i)`` names row ``i`` (0-based) in error messages; default "row i+1".

    Raises
    ------
    RecordingError
        Time running back by more than the resolution, a gap over ``max_gap_s``, or a time that
        never advances.
    """
    if row_name is None:
        def row_name(i):
            return f"row {i + 1}"
    t = np.asarray(t_s, dtype=float).copy()
    res = detect_resolution(t) if resolution_s is None else float(resolution_s)
    summary: dict = {"resolution_s": res}
    if t.size < 2:
        return TimeRepair(t, "", summary, False)
    period = _median_period(t, res, row_name)
    gap_limit = np.inf if max_gap_s is None else float(max_gap_s)
    t, n_wraps, modulus = _unwrap(t, res, period, gap_limit, wrap_s, row_name)
    bad, n_repeat, n_back = _stamps_behind(t, res, row_name)
    changed = bool(bad.any()) or n_wraps > 0
    if bad.any():
        t = _respace(t, period)
    d = np.diff(t)
    regular = np.mean(np.abs(d - period) <= max(res, 0.05 * period)) >= 0.75
    # stamps back within the resolution mean jitter, which can also make a step long
    slack = res if n_back else 0.0
    gaps = _gaps(t, period, slack) if regular else np.zeros(d.size, bool)
    _check_gap_limit(d, gap_limit, row_name)
    missing = int(np.sum(np.rint(d[gaps] / period) - 1)) if gaps.any() else 0
    summary.update({"median_period_s": period, "repeated_stamps": n_repeat,
                    "stamps_back": n_back, "wraps": n_wraps, "wrap_s": modulus or None,
                    "gaps": int(gaps.sum()), "missing_samples": missing,
                    "longest_gap_s": float(d[gaps].max()) if gaps.any() else 0.0,
                    "max_gap_s": None if max_gap_s is None else gap_limit})
    note = _repair_note(summary)
    summary["note"] = note
    return TimeRepair(t, note, summary, changed)


def _median_period(t: np.ndarray, res: float, row_name) -> float:
    """The median step of the times ``t`` [s] (of the positive steps when most are zero) [s].

    Raises
    ------
    RecordingError
        A time that never advances (naming the first row that runs back, if one does).
    """
    from ..errors import RecordingError

    d = np.diff(t)
    period = float(np.median(d))
    if not period > 0:
        period = float(np.median(d[d > 0])) if (d > 0).any() else 0.0
    if not period > 0:
        if (d < 0).any():
            i = int(np.argmax(d < 0)) + 1
            raise_back(t, i, res, row_name, float(t[i - 1]))
        raise RecordingError(f"{row_name(t.size - 1)}: time never advances ({t[0]:.6g} s "
                             "throughout)")
    return period


def _stamps_behind(t: np.ndarray, res: float, row_name) -> tuple[np.ndarray, int, int]:
    """The stamps that do not exceed every earlier one (bool, shape (T,)), and how many of
    them repeat the previous stamp and how many run back within the resolution ``res`` [s].

    Raises
    ------
    RecordingError
        A stamp more than the resolution below an earlier one.
    """
    prev_max = np.maximum.accumulate(t)[:-1]
    late = t[1:] < prev_max - res * (1 + 1e-6)
    if late.any():
        i = int(np.argmax(late)) + 1
        raise_back(t, i, res, row_name, float(prev_max[i - 1]))
    bad = np.zeros(t.size, bool)
    bad[1:] = t[1:] <= prev_max
    n_repeat = int(np.count_nonzero(np.diff(t)[bad[1:]] == 0))
    return bad, n_repeat, int(np.count_nonzero(bad)) - n_repeat


def _check_gap_limit(d: np.ndarray, gap_limit: float, row_name) -> None:
    """Refuse a step of ``d`` [s] longer than ``gap_limit`` [s], naming the row after it."""
    from ..errors import RecordingError

    too_long = d > gap_limit
    if too_long.any():
        i = int(np.argmax(too_long)) + 1
        raise RecordingError(f"{row_name(i)}: a gap of {d[i - 1]:.6g} s before this row is longer "
                             f"than the limit of {gap_limit:.6g} s (max_gap_s)")


def _repair_note(summary: dict) -> str:
    """One line on what was repaired, from a :class:`TimeRepair` summary; "" for nothing."""
    n_wraps, n_repeat, n_back = summary["wraps"], summary["repeated_stamps"], summary["stamps_back"]
    n_gaps, missing = summary["gaps"], summary["missing_samples"]
    parts = []
    if n_wraps:
        parts.append(f"{n_wraps} wrap{'s' * (n_wraps > 1)} of a {summary['wrap_s']:.6g} s "
                     "counter unwrapped")
    if n_repeat or n_back:
        what = " and ".join(x for x in (
            f"{n_repeat} repeated stamp{'s' * (n_repeat != 1)}" if n_repeat else "",
            f"{n_back} stamp{'s' * (n_back != 1)} back within the resolution" if n_back else "")
            if x)
        parts.append(f"{what} spread up to the next stamp")
    if n_gaps:
        parts.append(f"{n_gaps} gap{'s' * (n_gaps > 1)} kept ({missing} missing "
                     f"sample{'s' * (missing != 1)}, longest {_ms(summary['longest_gap_s'])})")
    if not parts:
        return ""
    return (f"time (median period {_ms(summary['median_period_s'])}, resolution "
            f"{_ms(summary['resolution_s'])}): " + "; ".join(parts))


def _gaps(t: np.ndarray, period: float, slack: float, window: int = 3) -> np.ndarray:
    """Steps over 1.5 periods that the steps around them do not make up (jitter does)."""
    d = np.diff(t)
    n = d.size
    i = np.arange(n)
    lo, hi = np.clip(i - window, 0, n), np.clip(i + window + 1, 0, n)
    span = t[hi] - t[lo]
    return (d > 1.5 * period) & (span > (hi - lo + 0.5) * period + slack)


def _respace(t: np.ndarray, period: float) -> np.ndarray:
    """Spread each run of rows that share a stamp (after the running maximum) up to the next.

    A row whose stamp does not exceed every earlier stamp belongs to the plateau of the row that
    set that maximum ``v``; the ``m`` rows of a plateau get ``v + k d``, ``k = 0 .. m-1``, with
    ``d = min((v_next - v) / m, period)``: inside ``[v, v_next)``, where a stamp that truncates
    the true time says the samples were, and at the median period at most, so that a gap after
    a repeated stamp stays a gap. The first row of every plateau keeps its stamp: no drift.
    """
    n = t.size
    level = np.maximum.accumulate(t)
    start = np.ones(n, bool)
    start[1:] = level[1:] > level[:-1]
    starts = np.flatnonzero(start)
    sizes = np.diff(np.append(starts, n))
    value = level[starts]
    nxt = np.append(value[1:], np.inf)
    step = np.minimum((nxt - value) / sizes, period)
    label = np.cumsum(start) - 1
    k = np.arange(n) - starts[label]
    return value[label] + k * step[label]
