"""The simulator's remembered work: time plans and what is known of unchanging arrays.

A fit simulates the same recording thousands of times, through a new dead time on many
trials; planning its time grid (and hashing the bytes that key the plan) costs as much as a
short kernel. This module keeps that work between calls to
:func:`~mecanum_hil.model.simulate.simulate_batch`. It holds no physics: a result is the same
bit for bit with every cache empty.

Contract
--------
Array facts (``_FACTS``), keyed by ``id(array)``:
    Only arrays declared with :func:`unchanging` are entered (numpy's read-only flag can be set
    back, and an array a view looks at may be written, so it proves nothing). An entry holds a
    weak reference to its array and a dict of what was learnt: its bytes (``"bytes"``, a plan's
    key), and the checks it passed (``"times"``, ``"finite"``). A lookup is a hit only when the
    weak reference still gives the same object. No bound: an entry is evicted when its array is
    garbage-collected (the weak reference's callback). Writing a declared array afterwards
    gives wrong results: declare a private copy.
Plans and delayed commands (``_PLANS``), keyed by the full input as bytes:
    ``("plan", bytes of time_s, dead time [s], max sub-step [s] or None)`` -> :class:`Plan`;
    ``("delayed", bytes of time_s, dead time [s], bytes of the command stream, bytes of the
    initial command)`` -> a 1-tuple of delayed commands (1, G, 3). A key is the whole input,
    never an identity, so a hit is always the value ``make()`` would give again.
    Bounds: at most ``_PLANS_MAX`` (64) entries and ``_PLANS_MAX_BYTES`` (64 MiB) of arrays in
    all. After each insertion the least recently used entries are evicted until both bounds
    hold, but one entry always stays (a single plan larger than the byte bound is kept until
    the next insertion). A hit makes its entry the most recently used.
Read-only values:
    Every array in a remembered value is made read-only before it is stored: later calls share
    it (and the compiled kernel then sees one array type). A caller that needs to write copies.
Thread safety:
    ``_PLANS`` and its byte count are guarded by one lock; a value is made outside it, so two
    threads may make the same plan at once, and the first stored is kept (both are equal).
    ``_FACTS`` is a plain dict whose single get / set / pop are atomic under the GIL; two
    threads may learn the same fact twice, which is harmless (the values are equal).
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError

#: What was learnt about arrays whose elements nothing changes any more, by identity: their
#: bytes (the plans' keys below) and the checks they passed. Only arrays declared so
#: (:func:`unchanging`: a fit's recordings) are kept: numpy's read-only flag can be set back,
#: and an array it views may be written, so it proves nothing.
#: A fit passes the same recording thousands of times, and copying and hashing its bytes cost
#: as much as a short kernel. An entry goes when its array does.
_FACTS: dict[int, tuple[weakref.ref, dict]] = {}


def array_facts(a: np.ndarray) -> dict | None:
    """The facts remembered about ``a`` (a dict to fill), or None when ``a`` is not declared
    unchanging."""
    hit = _FACTS.get(id(a))
    return hit[1] if hit is not None and hit[0]() is a else None


def unchanging(a: np.ndarray) -> np.ndarray:
    """Declare that nothing will change the elements of ``a`` any more.

    A caller that simulates the same commands and times again and again (a fit: thousands of
    times) declares them so, and :func:`~mecanum_hil.model.simulate.simulate_batch` keeps what
    it learnt about them (their bytes, the checks they passed) instead of copying and hashing
    them on every call. An array written after it was declared gives wrong results: declare a
    private copy.

    Parameters
    ----------
    a : ndarray
        A float array as passed to :func:`~mecanum_hil.model.simulate.simulate_batch`
        (``commands`` or ``time_s``; another dtype is converted there on every call, and gains
        nothing).

    Returns
    -------
    ndarray
        ``a`` itself.
    """
    key = id(a)
    if array_facts(a) is None:
        _FACTS[key] = (weakref.ref(a, lambda _, key=key: _FACTS.pop(key, None)), {})
    return a


def bytes_of(a: np.ndarray) -> bytes:
    """``a.tobytes()``, the same bytes object each time for an array declared
    :func:`unchanging` (its hash is then computed once)."""
    facts = array_facts(a)
    if facts is None:
        return a.tobytes()
    b = facts.get("bytes")
    if b is None:
        b = facts["bytes"] = a.tobytes()
    return b


#: Plans (time grids, step-length tables) of recent calls, by their inputs' bytes: a fit
#: simulates the same recording hundreds of times, and these cost as much as a short kernel.
_PLANS: OrderedDict = OrderedDict()
_PLANS_MAX = 64
#: ... and at most this many bytes of arrays in all: a long recording's plans are megabytes.
_PLANS_MAX_BYTES = 64 * 2 ** 20
_PLANS_LOCK = threading.Lock()
_plans_bytes = 0


def remember(key, make):
    """``make()`` (a tuple) for ``key`` (hashable, the full input), remembered for the last
    calls; its arrays are made read-only."""
    global _plans_bytes
    with _PLANS_LOCK:
        hit = _PLANS.get(key)
        if hit is not None:
            _PLANS.move_to_end(key)
            return hit
    value = make()
    for v in value:
        if isinstance(v, np.ndarray):
            v.flags.writeable = False  # shared by later calls (and one type for the kernel)
    with _PLANS_LOCK:
        if key not in _PLANS:
            _PLANS[key] = value
            _plans_bytes += _nbytes(value)
        while len(_PLANS) > _PLANS_MAX or (_plans_bytes > _PLANS_MAX_BYTES and len(_PLANS) > 1):
            _plans_bytes -= _nbytes(_PLANS.popitem(last=False)[1])
    return value


def _nbytes(value: tuple) -> int:
    return sum(v.nbytes for v in value if isinstance(v, np.ndarray))


class Plan(NamedTuple):
    """A group's time grid and its steps: what depends on the sample times, the dead time and
    the sub-step length alone (not on the robots), remembered by :func:`plan`."""

    grid: np.ndarray | None   # (G,) refined by the dead time [s]; None: the sample times
    src: np.ndarray | None    # (G,) sample whose command acts at each grid point (-1: before)
    record: np.ndarray        # (G,) each grid point's sample (-1: none): the kernel's ``record``
    didx: np.ndarray          # (G,) row of the step each grid point starts (0 for the last)
    nsub: np.ndarray          # (G,) its sub-step count (0 for the last)
    h_uniq: np.ndarray        # (K,) the distinct (sub-)step lengths [s]: the tables' rows
    substeps: int             # sub-steps in all (the kernel's job size per robot)


def plan(t: np.ndarray, delay_s: float, max_substep_s: float | None) -> Plan:
    """The time grid of a group with dead time ``delay_s`` [s] and its steps (sub-stepped at
    ``max_substep_s`` [s], None: the closed-form path), remembered by their inputs: a fit
    simulates the same recording thousands of times, through a new dead time on many."""
    return remember(("plan", bytes_of(t), float(delay_s), max_substep_s),
                    lambda: _make_plan(t, float(delay_s), max_substep_s))


def _make_plan(t: np.ndarray, delay_s: float, max_substep_s: float | None) -> Plan:
    if t.size > 1 and _kernels_compiled():
        # the same numbers in one compiled pass (a fit plans a grid per trial dead time)
        from .._jit import compiled
        from ._grid_kernels import plan_kernel

        planned, grid, src, record, didx, nsub, h, first, ok = compiled(plan_kernel)(
            t, delay_s, _time_rounding(t), max_substep_s or 0.0, _FEW_LENGTHS)
        if planned:
            if not ok:  # many distinct lengths (a real clock's): numpy's sort
                first, rows = _sorted_lengths(_length_keys(h))
                didx = np.append(rows, 0)
            return Plan(grid if delay_s > 0 else None, src if delay_s > 0 else None, record,
                         didx, nsub, h[first], int(nsub.sum()))
    if delay_s > 0:
        grid, src, sample_idx = _delay_plan(t, delay_s)
        if sample_idx[-1] >= grid.size:
            raise ConfigError(f"sample times closer than {_time_rounding(t):.3g} s cannot be "
                              "simulated through a dead time")
        record = np.full(grid.size, -1, dtype=np.int64)
        record[sample_idx] = np.arange(sample_idx.size)
    else:
        grid, src, record = None, None, np.arange(t.size, dtype=np.int64)
    didx, nsub, h_uniq = _grid_steps(t if grid is None else grid, max_substep_s)
    return Plan(grid, src, record, didx, nsub, h_uniq, int(nsub.sum()))


def _time_rounding(t: np.ndarray) -> float:
    """The rounding of ``t + delay`` [s]: 1 ns, or a few float steps where the times are large
    (a fraction of the recording's end time merged the 10 ms samples of a recording with a
    months-long gap: 2e7 s gave 20 ms)."""
    return max(1e-9, 16.0 * float(np.spacing(max(abs(t[0]), abs(t[-1])))))


def _delay_plan(t: np.ndarray, delay_s: float):
    """The refined grid, each grid point's source sample (-1: before the first) and the
    samples' places on the grid (numpy: the reference of the compiled
    :func:`~mecanum_hil.model._grid_kernels.plan_kernel`, which hands degenerate grids here)."""
    eps = _time_rounding(t)
    shifted = t + delay_s
    shifted = shifted[shifted < t[-1]]
    # A delayed command change within rounding of a sample time is taken at that sample time, so
    # every sample time stays on the grid and no step is (almost) empty.
    j = np.searchsorted(t, shifted)
    near = (np.abs(t[np.clip(j, 0, t.size - 1)] - shifted) <= eps) | (
        np.abs(t[np.clip(j - 1, 0, t.size - 1)] - shifted) <= eps)
    grid = np.union1d(t, shifted[~near])
    grid = grid[np.concatenate([[True], np.diff(grid) > eps])]
    src = np.searchsorted(t, grid - delay_s + 2 * eps, side="right") - 1
    sample_idx = np.searchsorted(grid, t - eps)
    return grid, src, sample_idx


def _grid_steps(grid: np.ndarray, max_substep_s: float | None):
    """:func:`_step_lengths` of a grid's steps, with the row and sub-step count of its last
    point (which starts no step) set to 0."""
    if grid.size == 1:
        return np.zeros(1, np.int64), np.zeros(1, np.int64), _step_lengths(np.ones(1),
                                                                           max_substep_s)[2]
    didx, nsub, h_uniq = _step_lengths(np.diff(grid), max_substep_s)
    return np.append(didx, 0), np.append(nsub, 0), h_uniq


def _step_lengths(dt: np.ndarray, max_substep_s: float | None):
    """Per step: its row among the distinct (sub-)step lengths and its sub-step count; and
    those lengths (numpy: the reference of the compiled
    :func:`~mecanum_hil.model._grid_kernels.plan_kernel`)."""
    from .stepper import substeps

    nsub = substeps(dt, max_substep_s)
    h = dt / nsub
    first, didx = _sorted_lengths(_length_keys(h))
    return didx, nsub, h[first]


def _length_keys(h: np.ndarray) -> np.ndarray:
    """Step lengths [s] as keys: lengths equal to rounding (a picosecond) share one table row.
    Floats: an int64 overflows for a gap over 9.2e6 s (106 days between two samples)."""
    return np.round(h * 1e12)


def _sorted_lengths(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first step of each distinct key (sorted) and each step's row among them, by
    numpy's sort (:func:`~mecanum_hil.model._grid_kernels.unique_keys_kernel` scans a few)."""
    _, first, rows = np.unique(key, return_index=True, return_inverse=True)
    return first, rows.astype(np.int64).reshape(-1)


#: Distinct step lengths up to which the compiled scan replaces ``np.unique``'s sort (a
#: uniform log and its dead time give a handful; a real clock's, thousands).
_FEW_LENGTHS = 32


def _kernels_compiled() -> bool:
    """Whether the simulator's kernels are numba's by now (then the grid helpers run compiled
    too: :mod:`mecanum_hil.model._grid_kernels`); in the interpreter, numpy."""
    from .._jit import is_compiled, mode

    return mode() != "never" and is_compiled("mecanum_hil.model._kernels")
