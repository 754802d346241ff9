"""Benchmark of ``fit``: the paper's full three-pass grid and lsq on a 1 s, 100 Hz step.

Baseline, measured in the same run: the same grid procedure done with ``scipy.signal.lsim`` per
grid point (a random sample of points timed and extrapolated to the full grid's count).

Run: ``python bench/bench_fit.py [--lsim-sample 300]``
"""

from __future__ import annotations

import os

# One BLAS thread: tiny matrix calls (the simulator's expm, least squares' SVD) otherwise wait
# for OpenBLAS worker threads competing with numba's on a 2-core machine (measured up to 100x).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import time

import numpy as np


def step_recording(seed: int = 0):
    from mecanum_hil.io.recording import Recording
    from mecanum_hil.model import Calibration, RobotProfile, simulate, uniform_time

    t = uniform_time(1.0, 100.0)
    cmd = np.tile([60.0, 0.0, 90.0], (t.size, 1))  # the paper's step: n = 60 rpm, theta = 90
    w = simulate(cmd, t, Calibration(A=27.0, B=8.5, C=610.0), RobotProfile()).wheel_rpm[0]
    w = w + np.random.default_rng(seed).normal(0.0, 0.7, w.shape)
    return Recording(t, cmd, w, np.full((t.size, 3), np.nan))


def lsim_sse(A, B, C, t, u, y):
    from scipy.signal import lsim

    _, yout, _ = lsim(([A, C], [1.0, A + B, C]), u, t, interp=False)  # zero-order hold
    return float(np.sum((y - yout[:, None]) ** 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lsim-sample", type=int, default=300, help="grid points timed with lsim")
    ap.add_argument("--repeats", type=int, default=3, help="runs of the full grid (best kept)")
    args = ap.parse_args()

    from mecanum_hil.identify import grid
    from mecanum_hil.identify.fit import fit, prepare
    from mecanum_hil.model import Calibration, RobotProfile

    robot = RobotProfile()
    rec = step_recording()
    data = prepare([rec], robot)
    n_points = 2 * grid.axis(grid.PAPER_A_GRID).size * grid.axis(grid.PAPER_C_GRID).size \
        + grid.axis(grid.PAPER_B_GRID).size

    # warm up: compile (or load the cache of) the kernels and the simulator
    grid.paper_grid(data, Calibration(), robot, a_grid=(0, 10, 1), c_grid=(0, 10, 1))
    fit([rec], robot)

    grid_times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        res = grid.paper_grid(data, Calibration(), robot)
        grid_times.append(time.perf_counter() - t0)
    t_grid = min(grid_times)

    # the same procedure point by point with scipy.signal.lsim, on a random sample of its points
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.integers(0, 2001, args.lsim_sample).astype(float),
                           np.round(5.5 + 0.1 * rng.integers(0, 201, args.lsim_sample), 1),
                           rng.integers(1, 2001, args.lsim_sample).astype(float)])
    u = rec.commands[:, 0]  # theta = 90, omega = 0: every wheel target is n
    t0 = time.perf_counter()
    for A, B, C in pts:
        lsim_sse(A, B, C, rec.t_s, u, rec.wheel_rpm)
    per_point = (time.perf_counter() - t0) / args.lsim_sample
    t_lsim = per_point * n_points
    # lsim agrees with the kernel on the SSE (same exact ZOH model)
    check = lsim_sse(res.A, res.B, res.C, rec.t_s, u, rec.wheel_rpm)

    lsq_times = []
    for _ in range(20):
        t0 = time.perf_counter()
        lsq = fit([rec], robot)
        lsq_times.append(time.perf_counter() - t0)
    t_lsq = float(np.median(lsq_times))
    t_lsq_min = float(np.min(lsq_times))

    print(f"1 s, 100 Hz step, 4 wheels; paper grid = {n_points:,} points (3 passes)")
    print(f"paper-grid, compiled kernel   : {t_grid:8.3f} s  (best of {args.repeats}; "
          f"A={res.A:g} B={res.B:g} C={res.C:g}, SSE {res.sse:.6g})")
    print(f"paper-grid, lsim per point    : {t_lsim:8.0f} s  (extrapolated from "
          f"{args.lsim_sample} points, {per_point * 1e3:.3f} ms each; SSE at the argmin "
          f"{check:.6g})")
    print(f"  speed-up                    : {t_lsim / t_grid:8.0f} x")
    print(f"lsq (median of 20)            : {t_lsq * 1e3:8.1f} ms  "
          f"(fastest {t_lsq_min * 1e3:.1f} ms; A={lsq.parameters['A']:.4g} "
          f"B={lsq.parameters['B']:.4g} C={lsq.parameters['C']:.4g}, SSE {lsq.sse:.6g})")
    print(f"  lsq vs compiled paper-grid  : {t_grid / t_lsq:8.0f} x faster, SSE ratio "
          f"{lsq.sse / res.sse:.4f}")
    print(f"  lsq vs lsim paper-grid      : {t_lsim / t_lsq:8.0f} x faster")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"machine: {os.cpu_count()} cores, load average {load:.2f} (other jobs share them)")
    print(f"targets: full grid < 5 s: {'met' if t_grid < 5 else 'MISSED'}; "
          f"lsq < 50 ms: {'met' if t_lsq < 0.05 else 'MISSED'}")


if __name__ == "__main__":
    main()
