"""Benchmark of time to answer: whole ``mecanum-hil`` processes, as a user runs them.

Each command runs as its own process (warm file caches, Python's bytecode cache and numba's
on-disk cache already filled by a first untimed run, with ``PYTHONDONTWRITEBYTECODE`` removed from
the children's environment), median of ``--repeats`` runs. Baseline, measured in the same run:
``python -c "import numpy"``, the least any command of this package can cost.

Commands, on one recording (``../shared/data/real/micromouse/testPid7.csv`` when present, with
its robot profile, else the committed sample ``recordings/samples/paper-step-60.csv``):
``--help``, ``fit``, ``fit --no-report``, ``simulate``, ``shadow --replay``, ``diagnose``.
``fit`` writes its report PNG by default (drawn with Pillow, ~0.07 s).

Run: ``python bench/bench_startup.py [--repeats 5] [--skip-diagnose]``
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "real" / "micromouse"


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed(argv: list[str], repeats: int, env: dict[str, str]) -> tuple[float, float, float, int]:
    """Median and minimum wall time [s] of ``repeats`` runs of ``argv``, their median CPU time
    (user + system) [s], and the last exit code. On a shared machine the CPU time is what the
    wall time would be on an idle one (every command here runs on one core)."""
    times, cpu = [], []
    code = 0
    for _ in range(repeats):
        start, cpu0 = time.perf_counter(), _children_cpu_s()
        done = subprocess.run(argv, capture_output=True, env=env, cwd=ROOT)
        times.append(time.perf_counter() - start)
        cpu.append(_children_cpu_s() - cpu0)
        code = done.returncode
    return statistics.median(times), min(times), statistics.median(cpu), code


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--skip-diagnose", action="store_true", help="leave out diagnose (slow)")
    args = ap.parse_args()

    if (SHARED / "testPid7.csv").is_file():
        rec, robot = SHARED / "testPid7.csv", ["--robot", str(SHARED / "robot.toml")]
    else:
        rec, robot = ROOT / "recordings" / "samples" / "paper-step-60.csv", []
    exe = [sys.executable, "-m", "mecanum_hil"]
    env = dict(os.environ)
    # Warm caches as a user has them: an installed package has its bytecode compiled (pip does
    # it at install; an editable install writes it on the first run). With
    # PYTHONDONTWRITEBYTECODE set (some shells and containers set it) every run would compile
    # mecanum_hil's own ~60 modules again, ~0.1-0.3 s a command that no user pays.
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    with tempfile.TemporaryDirectory() as tmp:
        cal = Path(tmp) / "cal.toml"
        cases = [
            ("mecanum-hil --help", [*exe, "--help"], 0.15),
            ("fit", [*exe, "fit", str(rec), *robot, "--out", str(cal)], 0.5),
            ("fit --no-report", [*exe, "fit", str(rec), *robot, "--out", str(cal),
                                 "--no-report"], 0.5),
            ("simulate", [*exe, "simulate", "--commands", str(rec), *robot, "--calibration",
                          str(cal), "--out", str(Path(tmp) / "pred.csv")], 0.4),
            ("shadow --replay", [*exe, "shadow", "--replay", str(rec), *robot, "--calibration",
                                 str(cal), "--no-events", "--json"], 0.4),
        ]
        if not args.skip_diagnose:
            cases.append(("diagnose", [*exe, "diagnose", str(rec), *robot, "--calibration",
                                       str(cal), "--json"], None))
        # untimed first run of each: fills numba's cache and the calibration file
        for _, argv, _ in cases:
            subprocess.run(argv, capture_output=True, env=env, cwd=ROOT)
        base, base_min, base_cpu, _ = timed([sys.executable, "-c", "import numpy"],
                                            args.repeats, env)
        print(f"recording: {rec}")
        print(f"load average: {os.getloadavg()[0]:.2f}")
        print(f"baseline python -c 'import numpy': median {base:.3f} s (min {base_min:.3f} s, "
              f"CPU {base_cpu:.3f} s)")
        print(f"{'command':<22}{'median [s]':>11}{'min [s]':>9}{'CPU [s]':>9}{'x baseline':>12}"
              f"{'target [s]':>12}  exit")
        for name, argv, target in cases:
            med, low, cpu, code = timed(argv, args.repeats, env)
            tgt = "-" if target is None else f"<= {target:.2f}"
            mark = "" if target is None else ("  met" if med <= target else "  NOT met")
            print(f"{name:<22}{med:>11.3f}{low:>9.3f}{cpu:>9.3f}{med / base:>11.1f}x{tgt:>12}"
                  f"  {code}{mark}")


if __name__ == "__main__":
    main()
