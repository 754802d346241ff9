"""Benchmark of ``mecanum-hil import`` (format text): a 1-hour 1 kHz wheel log, 3.6 M rows.

The log is written as a lab's logger writes it: a ``%`` header naming the columns, time in
seconds with 1 ms resolution and a stamp repeated every ~1000 rows (the stamp clock a little
slower than the sampling), a signed setpoint and four wheel speeds in rad/s, whitespace-separated.
Measured in one run:

* baseline: ``numpy.loadtxt`` of the same file (numpy's C reader, the parse alone);
* ``import_source`` (parse, units, time repair, commands) and ``write_recording`` (the CSV and
  sidecar), in process, and the whole ``mecanum-hil import`` command in a subprocess;
  each as seconds and as a ratio of the baseline. Target: the command under 20 s;
* ``read_recording`` of the recording written (what ``fit`` then reads), for information.

Wall and CPU seconds are both printed: on a shared machine the wall time follows the load.

Run: ``python bench/bench_import.py [--hours H] [--keep DIR]``.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mecanum_hil.importers import import_source
from mecanum_hil.io.recording import read_recording, write_recording

MAP = """
[time]
column = "time_s"
unit = "s"
[wheels]
wheel1 = { column = "w_fl", unit = "rad/s" }
wheel2 = { column = "w_fr", unit = "rad/s" }
wheel3 = { column = "w_rl", unit = "rad/s" }
wheel4 = { column = "w_rr", unit = "rad/s" }
[commands]
setpoint = { column = "setpoint", unit = "rad/s" }
"""


def make_log(path: Path, n: int) -> None:
    """Write the log in chunks: steps and reversals, first-order wheels, 0.23 rad/s steps."""
    rng = np.random.default_rng(1)
    chunk = 500_000
    with path.open("w") as fh:
        fh.write("% 1 kHz wheel log\n% time_s setpoint w_fl w_fr w_rl w_rr\n")
        level, w = 0.0, np.zeros(4)
        for a in range(0, n, chunk):
            k = np.arange(a, min(a + chunk, n))
            t = np.floor(k * 0.9990 + 1e-9) * 1e-3  # a repeated stamp every ~1000 rows
            sp = np.empty(k.size)
            wheels = np.empty((k.size, 4))
            for i in range(k.size):  # setup only, not timed
                if k[i] % 2000 == 0:
                    level = float(rng.uniform(-30, 30))
                sp[i] = level
                w += (level - w) * 0.08
                wheels[i] = w
            wheels = np.round((wheels + rng.normal(0, 0.1, wheels.shape)) / 0.23) * 0.23
            np.savetxt(fh, np.column_stack([t, sp, wheels]),
                       fmt="%.3f %.2f %.2f %.2f %.2f %.2f")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--keep", type=Path, default=None, help="Keep the files in this folder.")
    args = ap.parse_args()
    n = round(args.hours * 3600 * 1000)
    tmp = args.keep or Path(tempfile.mkdtemp(prefix="bench_import_"))
    tmp.mkdir(parents=True, exist_ok=True)
    log, mp, out = tmp / "log.txt", tmp / "map.toml", tmp / "rec.csv"
    mp.write_text(MAP)
    if not log.exists():
        t0 = time.perf_counter()
        make_log(log, n)
        print(f"wrote the log: {n} rows, {log.stat().st_size / 1e6:.0f} MB "
              f"({time.perf_counter() - t0:.1f} s, not timed)")
    load = os.getloadavg()[0]

    def timed(fn):
        w0, c0 = time.perf_counter(), time.process_time()
        value = fn()
        return value, time.perf_counter() - w0, time.process_time() - c0

    base, w_base, c_base = timed(lambda: np.loadtxt(log, comments="%"))
    assert base.shape == (n, 6)
    del base
    res, w_read, c_read = timed(lambda: import_source(log, "text", map_path=mp))
    rec, notes = res.recording, res.notes
    _, w_write, c_write = timed(lambda: write_recording(rec, out))
    assert len(rec) == n

    def command():
        r = subprocess.run([sys.executable, "-m", "mecanum_hil", "import", str(log), "--map",
                            str(mp), "--out", str(out)], capture_output=True, text=True)
        if r.returncode:
            raise SystemExit(r.stderr)

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    _, w_cli, _ = timed(command)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    c_cli = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)

    print(f"import of {n} rows ({n / 3.6e6:.2f} h at 1 kHz), load average {load:.1f} "
          f"(2 cores); wall and CPU seconds, ratio to the baseline's")
    print(f"  baseline numpy.loadtxt (parse only): {w_base:6.2f} s wall {c_base:6.2f} s CPU")
    for name, w, c in (("import_source (parse + repair)     ", w_read, c_read),
                       ("write_recording (CSV + sidecar)    ", w_write, c_write),
                       ("mecanum-hil import (whole command) ", w_cli, c_cli)):
        print(f"  {name}: {w:6.2f} s wall {c:6.2f} s CPU   {w / w_base:5.2f}x wall "
              f"{c / c_base:5.2f}x CPU")
    back, w_back, c_back = timed(lambda: read_recording(out))
    assert len(back) == n
    print(f"  read_recording of the output (fit's read): {w_back:6.2f} s wall {c_back:6.2f} s CPU"
          f"   {w_back / w_base:5.2f}x wall {c_back / c_base:5.2f}x CPU")
    print(f"  target: the command under 20 s: wall {'met' if w_cli < 20 else 'NOT met'}, "
          f"CPU {'met' if c_cli < 20 else 'NOT met'}")
    print(f"  notes: {'; '.join(notes)}")


if __name__ == "__main__":
    main()
