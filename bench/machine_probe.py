"""The machine's speed now: a fixed workload timed in the same run as a benchmark.

The 2-core machine these benchmarks run on changes speed by up to a factor of two within
minutes (other tenants; it reports no steal time): the same ``diagnose`` took 5.9 s and 12.3 s
an hour apart. A figure measured beside this probe can be compared across runs as a ratio
(``seconds / probe``), and read at the machine's usual speed (the probe's median over a
session, :data:`USUAL_PROBE_S`, from ``--log``).

The workload is the interpreter's own arithmetic loop (no numpy, no threads): what most of
``diagnose``'s time outside the compiled kernel is, and it scales with the core's speed as
the kernel does. One probe is the median of :data:`REPEATS` runs of about 0.2 s.

Run: ``python bench/machine_probe.py`` (one probe) or ``python bench/machine_probe.py --log
SECONDS`` (a probe every SECONDS [s], one line each: UTC time, probe [s], load average, until
stopped).
"""

from __future__ import annotations

import argparse
import statistics
import time

#: Runs of the loop per probe (the median is kept: one run interrupted by another job's burst
#: does not move it).
REPEATS = 5
#: The loop's length: about 0.2 s a run on the benchmark machine.
LOOP = 3_000_000
#: The probe's median on the benchmark machine over session 23 (2026-11-28, docs/benchmarks/
#: diagnose.md, "The machine's speed"): its usual speed, at which the targets are read.
USUAL_PROBE_S = 0.20


def _loop() -> float:
    t0 = time.perf_counter()
    s = 0
    for i in range(LOOP):
        s += i * i
    return time.perf_counter() - t0


def probe_s() -> float:
    """The median time [s] of :data:`REPEATS` runs of the fixed loop."""
    return statistics.median(_loop() for _ in range(REPEATS))


def load() -> str:
    """The load average (1, 5, 15 min), or ``n/a``."""
    try:
        with open("/proc/loadavg") as f:
            return " ".join(f.read().split()[:3])
    except OSError:
        return "n/a"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--log", type=float, default=None, metavar="SECONDS")
    args = ap.parse_args()
    if args.log is None:
        print(f"probe {probe_s():.3f} s (usual {USUAL_PROBE_S:.3f} s), load {load()}")
        return
    while True:
        print(f"{time.strftime('%H:%M:%S', time.gmtime())} {probe_s():.4f} {load()}",
              flush=True)
        time.sleep(args.log)


if __name__ == "__main__":
    main()
