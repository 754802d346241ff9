"""Compiled helpers of the simulator's time grid (numba): a dead time's refined grid and the
distinct step lengths of a grid, in one pass each. Pure: arrays in, arrays out.

A fit plans a new grid for every trial dead time (thousands in ``diagnose``); with numpy
(``union1d``, ``searchsorted``, ``unique``) that cost more than a short simulation. Each helper
computes the same numbers as the numpy code in :mod:`mecanum_hil.model.simulate`, which runs
where the simulator's kernels are not compiled.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit


@njit(cache=True)
def delay_plan_kernel(t, delay_s, eps):
    """The dead time's refined grid in one pass: what ``plan_cache._delay_plan`` computes with
    numpy (``union1d``, the merge of points closer than ``eps`` [s], three ``searchsorted``),
    the same numbers, for a fit that plans a grid for every trial dead time (about 0.4 ms
    with numpy for 700 samples, most of an evaluation's time outside the kernel).

    Returns
    -------
    grid : (G,) float64
        Sample times and the delayed command changes that are not within ``eps`` of one.
    src : (G,) int64
        Sample whose command is in force at each grid point through the dead time (-1:
        before the first).
    sample_idx : (T,) int64
        Each sample's place on the grid.
    """
    n = t.size
    last = t[n - 1]
    merged = np.empty(2 * n)
    m = 0
    k = 0  # next sample time to merge
    for a in range(n):
        s = t[a] + delay_s
        if not s < last:
            break
        # searchsorted(t, s), left: the first sample time >= s
        while k < n and t[k] < s:
            merged[m] = t[k]
            m += 1
            k += 1
        j = k
        jc = j if j < n else n - 1
        jm = j - 1 if j - 1 > 0 else 0
        if abs(t[jc] - s) <= eps or abs(t[jm] - s) <= eps:
            continue  # taken at that sample time
        if m > 0 and merged[m - 1] == s:
            continue  # union: an exact duplicate once
        merged[m] = s
        m += 1
    while k < n:
        merged[m] = t[k]
        m += 1
        k += 1
    # points closer than eps to the one before them (in the union) are dropped
    keep = 1
    for i in range(1, m):
        if merged[i] - merged[i - 1] > eps:
            keep += 1
    grid = np.empty(keep)
    grid[0] = merged[0]
    g = 1
    for i in range(1, m):
        if merged[i] - merged[i - 1] > eps:
            grid[g] = merged[i]
            g += 1
    # searchsorted(t, grid - delay + 2 eps, right) - 1 and searchsorted(grid, t - eps), left
    src = np.empty(keep, np.int64)
    p = 0
    for i in range(keep):
        x = grid[i] - delay_s + 2 * eps
        while p < n and t[p] <= x:
            p += 1
        src[i] = p - 1
    sample_idx = np.empty(n, np.int64)
    p = 0
    for i in range(n):
        x = t[i] - eps
        while p < keep and grid[p] < x:
            p += 1
        sample_idx[i] = p
    return grid, src, sample_idx


@njit(cache=True)
def unique_keys_kernel(key, most):
    """``np.unique(key, return_index=True, return_inverse=True)`` for a few distinct values
    among many (the step lengths of a grid): the sorted distinct values' first places and each
    value's row, by a scan against the values seen so far (the last one first: lengths come in
    runs). Gives up (``ok`` False, the caller sorts) past ``most`` distinct values.

    Returns
    -------
    first : (M,) int64;  rows : (N,) int64;  ok : bool
    """
    n = key.size
    vals = np.empty(most)
    firsts = np.empty(most, np.int64)
    rows = np.empty(n, np.int64)
    m = 0
    hit = -1
    for i in range(n):
        v = key[i]
        if hit < 0 or vals[hit] != v:
            hit = -1
            for q in range(m):
                if vals[q] == v:
                    hit = q
                    break
            if hit < 0:
                if m == most:
                    return firsts[:0], rows[:0], False
                vals[m] = v
                firsts[m] = i
                hit = m
                m += 1
        rows[i] = hit
    order = np.argsort(vals[:m])
    rank = np.empty(m, np.int64)
    for r in range(m):
        rank[order[r]] = r
    for i in range(n):
        rows[i] = rank[rows[i]]
    return firsts[:m][order], rows, True


@njit(cache=True)
def plan_kernel(t, delay_s, eps, max_substep_s, most):
    """A group's whole time plan in one pass (``plan_cache._make_plan``): the dead time's grid
    (:func:`delay_plan_kernel`; none for ``delay_s`` 0), each grid point's sample, and the steps'
    sub-step counts and distinct lengths (:func:`unique_keys_kernel`).

    Parameters
    ----------
    t : (T,) float64
        Sample times [s], T >= 2.
    delay_s, eps : float
        Dead time [s] (0: the grid is ``t``) and the rounding of times [s].
    max_substep_s : float
        Longest sub-step [s]; 0 for one sub-step per step (the closed-form path).
    most : int
        Distinct step lengths up to which they are found by a scan.

    Returns
    -------
    planned : bool
        False where the dead time's grid merged samples (closer than ``eps``): nothing else is
        set, and the caller plans with numpy.
    grid : (G,) float64;  src : (G,) int64 (empty without a dead time);  record : (G,) int64
        The grid, each point's source sample through the dead time and each point's sample
        (-1: none).
    didx, nsub : (G,) int64
        Row of the distinct length and sub-step count of the step each point starts (0 for
        the last).
    h : (G - 1,) float64;  first : (K,) int64;  ok : bool
        Each step's sub-step length, the first step of each distinct length (sorted), and
        False when there are more than ``most`` (then ``didx`` is unset: the caller sorts).
    """
    n = t.size
    none = np.zeros(0, np.int64)
    if delay_s > 0:
        grid, src, sample_idx = delay_plan_kernel(t, delay_s, eps)
        if grid.size < 2 or sample_idx[n - 1] >= grid.size:
            # samples closer than ``eps`` merged (times under a nanosecond apart): the numpy
            # code decides (it refuses them)
            return False, grid, src, none, none, none, np.empty(0), none, False
        record = np.full(grid.size, -1, np.int64)
        for i in range(n):
            record[sample_idx[i]] = i
    else:
        grid = t.copy()
        src = np.empty(0, np.int64)
        record = np.arange(n)
    g = grid.size
    nsub = np.zeros(g, np.int64)
    h = np.empty(g - 1)
    for i in range(g - 1):
        dt = grid[i + 1] - grid[i]
        k = 1
        if max_substep_s > 0:
            k = max(1, math.ceil(dt / max_substep_s - 1e-9))
        nsub[i] = k
        h[i] = dt / k
    first, rows, ok = unique_keys_kernel(np.rint(h * 1e12), most)
    didx = np.zeros(g, np.int64)
    if ok:
        didx[:g - 1] = rows
    return True, grid, src, record, didx, nsub, h, first, ok
