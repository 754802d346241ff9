"""Benchmark of ``fit --method paper-grid`` on the shipped sample recordings.

Each sample is timed as a host receives telemetry: hundreds of distinct step lengths. The
paper grid (8,008,203 points in three passes) is timed in full; the baseline, measured in the
same run, is an exhaustive evaluation (every point's whole sum) of a random sample of the
grid's points, extrapolated to the grid's count.

Run: ``python bench/bench_paper_grid.py [--sample 2000]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

SAMPLES = Path(__file__).resolve().parents[1] / "recordings" / "samples"


def main() -> None:
    from mecanum_hil.identify import grid
    from mecanum_hil.identify.fit import prepare
    from mecanum_hil.io.timing import read_for_analysis
    from mecanum_hil.model import load_calibration, load_robot_profile

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sample", type=int, default=2000, help="baseline points")
    args = parser.parse_args()
    cal, robot = load_calibration(), load_robot_profile()
    rng = np.random.default_rng(0)
    a, c = grid.axis(grid.PAPER_A_GRID), grid.axis(grid.PAPER_C_GRID)
    n_points = 2 * a.size * c.size + grid.axis(grid.PAPER_B_GRID).size
    print(f"{'recording':<22} {'steps':>6} {'grid [s]':>9} {'exhaustive [s]':>15} {'ratio':>7}")
    for path in sorted(SAMPLES.glob("*.csv")):
        data = prepare([read_for_analysis(path)], robot)
        g = grid.grid_data(data, cal, robot)
        grid.grid_argmin(g, a[:4], [15.5], c[:4])  # numba's kernels loaded before timing
        t0 = time.perf_counter()
        res = grid.paper_grid(data, cal, robot)
        took = time.perf_counter() - t0
        pts = np.column_stack([rng.choice(a, args.sample), np.full(args.sample, 15.5),
                               rng.choice(c, args.sample)])
        t0 = time.perf_counter()
        grid.evaluate_points(g, pts)
        exhaustive = (time.perf_counter() - t0) / args.sample * n_points
        print(f"{path.name:<22} {g.h_s.size:>6} {took:>9.2f} {exhaustive:>15.1f} "
              f"{exhaustive / took:>6.0f}x   A={res.A:g} B={res.B:g} C={res.C:g}")


if __name__ == "__main__":
    main()
