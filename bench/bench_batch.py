"""Benchmark of ``mecanum-hil batch fit``: a synthetic fleet archive on Dask.

200 robots x 10 recordings (one group of 10 recordings per robot), fitted

1. **directly**: one process calling the stage (read the recordings, ``fit``) group after group
   (the baseline);
2. **as batch tasks in one process**: ``run_group`` serially (adds streaming, hashing, the row);
3. on a **local Dask cluster with 1 worker** and **with 2 workers** (one thread each), as
   ``mecanum-hil batch`` runs them (minus the final table).

The four run in interleaved blocks of 40 groups (direct, run_group, 1 worker, 2 workers, then
the next block), so that a change of the machine's load during the run (the 2-core machine is
shared) falls on all four alike.

Printed: wall and CPU time per group, throughput (groups/s, recordings/s), the Dask overhead
per task against the direct baseline (target: under 10 % for groups of 10 recordings) and the
speed-up from the second worker. The overhead is judged on CPU time (every process counted:
this one with the client, schedulers and nannies, and every worker; minus the idle clusters'
background rate, measured first, times each phase's wall time): on the shared 2-core machine
the wall time of a task depends on what else runs, the CPU it takes does not. Cluster
start-up and numba's first compilation are excluded (a warm-up task runs on every worker
first) and reported apart.

The archive is generated with the model's simulator, not the lockstep recorder: every robot
has its own A, B, C (the paper's +-15 %, uniform), ten step profiles (10..120 rpm straight,
turns, strafes; 0.3 s rest, 1.5 s step, 1 s stop) sampled at 100 Hz by ``simulate_batch`` (one
call per profile for all robots), plus Gaussian wheel noise of 0.25 rpm. It takes seconds,
where recording 2,000 runs through the simulated controller would take minutes.

Usage: ``python bench/bench_batch.py [--robots 200] [--recordings 10] [--workers 1,2]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

# the same one-core settings as the cluster's workers (runner.WORKER_ENV), so that the direct
# baseline computes exactly as a task does and takes no more cores than one worker
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402  (after the thread settings)

STEPS = ((10.0, 90.0, 0.0), (20.0, 90.0, 0.0), (30.0, 0.0, 0.0), (45.0, 90.0, 0.0),
         (0.0, 90.0, 40.0), (60.0, 45.0, 0.0), (75.0, 90.0, 0.0), (90.0, 0.0, 0.0),
         (0.0, 90.0, 60.0), (110.0, 90.0, 0.0))  # (n [rpm], theta [deg], omega [deg/s])


def make_archive(root: Path, robots: int, recordings: int, seed: int = 0) -> float:
    """Write the synthetic archive; returns the time it took [s]."""
    from mecanum_hil.io.recording import Recording, write_recording
    from mecanum_hil.model import Calibration, simulate_batch
    from mecanum_hil.profiles import step

    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    base = Calibration()
    scale = rng.uniform(0.85, 1.15, size=(robots, 3))
    cals = [Calibration(A=base.A * a, B=base.B * b, C=base.C * c) for a, b, c in scale]
    for j in range(recordings):
        n, theta, omega = STEPS[j % len(STEPS)]
        prof = step(n, theta_deg=theta, omega_dps=omega, duration_s=1.5, rest_s=0.3,
                    stop_s=1.0, name=f"step-{j:02d}")
        t, cmd = prof.sample(100.0)
        traj = simulate_batch(cmd, t, cals)
        for i in range(robots):
            wheels = traj.wheel_rpm[i] + rng.normal(0.0, 0.25, size=traj.wheel_rpm[i].shape)
            rec = Recording(t, cmd, wheels, np.full((t.size, 3), np.nan), {}, {
                "source": "bench_batch.py: simulate_batch + 0.25 rpm Gaussian noise",
                "profile": prof.name})
            write_recording(rec, root / f"robot-{i:04d}" / f"{prof.name}.csv")
    return time.perf_counter() - t0


def direct(specs) -> tuple[float, float]:
    """The stage called directly, group after group, in this thread: (wall, CPU) [s].

    CPU is counted as for the clusters (:func:`_cpu_all`); the idle clusters' background is
    subtracted later.
    """
    from mecanum_hil.fleet import stages

    t0, c0 = time.perf_counter(), _cpu_all()
    for s in specs:
        paths = [Path(p) for p, _, _ in s.files]
        recs, names, bad = stages.read_recordings(paths, [rel for _, rel, _ in s.files])
        assert not bad, bad
        stages.run_fit(recs, names, s.robot, s.calibration)
    return time.perf_counter() - t0, _cpu_all() - c0


def tasks_in_process(specs) -> tuple[float, float, list[dict]]:
    """``run_group`` serially in this thread: (wall, CPU) [s] and its rows."""
    from mecanum_hil.fleet.tasks import run_group

    t0, c0 = time.perf_counter(), _cpu_all()
    rows = [run_group(s) for s in specs]
    return time.perf_counter() - t0, _cpu_all() - c0, rows


def _cpu_all() -> float:
    """CPU time of this process (client, scheduler, nannies) and its children (workers) [s]."""
    import psutil

    me = psutil.Process()
    total = 0.0
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
        except psutil.Error:
            continue
        total += t.user + t.system
    return total


def start_cluster(workers: int):
    """A local cluster as ``batch`` starts it, warmed up: (cluster, client, start-up [s])."""
    from dask.distributed import Client

    from mecanum_hil.fleet.runner import local_cluster

    t0 = time.perf_counter()
    cluster = local_cluster(workers, dashboard=False)
    client = Client(cluster)
    return cluster, client, time.perf_counter() - t0


def warm_up(client, spec) -> float:
    """Run one task on every worker (numba's compilation or cache load) [s]."""
    from mecanum_hil.fleet.tasks import run_group

    t0 = time.perf_counter()
    addrs = list(client.scheduler_info()["workers"])
    client.gather([client.submit(run_group, spec, workers=[a], pure=False) for a in addrs])
    return time.perf_counter() - t0


def on_dask(client, specs) -> tuple[float, float, list[dict]]:
    """The groups as ``batch`` runs them on ``client``: (wall, CPU of every process) [s], rows.

    The CPU time counts this process (client, scheduler, nannies) and every worker process;
    the idle background (both clusters waiting) is subtracted later.
    """
    from mecanum_hil.fleet.runner import execute

    c0 = _cpu_all()
    rows, counts, wall = execute(client, specs, {}, None)
    cpu = _cpu_all() - c0
    assert counts.failed == 0, [r["error"] for r in rows if r["status"] == "failed"]
    return wall, cpu, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", type=int, default=200)
    ap.add_argument("--recordings", type=int, default=10)
    ap.add_argument("--workers", default="1,2", help="worker counts to run, comma-separated")
    ap.add_argument("--block", type=int, default=40,
                    help="groups per interleaved block (direct, run_group, each cluster)")
    ap.add_argument("--keep", type=Path, default=None, help="write the archive here and keep it")
    args = ap.parse_args()

    from mecanum_hil.fleet.runner import BatchSettings, plan

    tmp = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    root = args.keep or tmp / "archive"
    try:
        print(f"load average at start: {os.getloadavg()[0]:.2f} (2 cores)")
        gen = make_archive(root, args.robots, args.recordings)
        size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
        n_rec = args.robots * args.recordings
        print(f"archive: {args.robots} robots x {args.recordings} recordings = {n_rec} files, "
              f"{size / 1e6:.1f} MB, generated in {gen:.1f} s (simulate_batch + noise)")
        specs, _ = plan(BatchSettings("fit", str(root), tmp / "unused.parquet"))
        import resource

        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        direct(specs[:1])  # numba compiles (or loads its cache) once, outside the timing
        tasks_in_process(specs[:1])
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        counts = [int(x) for x in args.workers.split(",")]
        clusters = {w: start_cluster(w) for w in counts}
        for w, (_, client, startup) in clusters.items():
            print(f"local cluster, {w} worker(s): started in {startup:.1f} s, warm-up task on "
                  f"each worker {warm_up(client, specs[0]):.1f} s (not in the figures below)")
        c0, t0 = _cpu_all(), time.perf_counter()
        time.sleep(10.0)
        background = (_cpu_all() - c0) / (time.perf_counter() - t0)
        print(f"idle background of both clusters and this process: {1e3 * background:.1f} ms "
              "of CPU per second (subtracted below, times each phase's wall time)")
        # interleaved blocks: the machine's load (other jobs) drifts, and each way of running
        # sees the same drift instead of its own stretch of it
        t = {"direct": 0.0, "tasks": 0.0, **{w: 0.0 for w in counts}}
        cpu = dict.fromkeys(t, 0.0)
        rows_by: dict = {"tasks": [], **{w: [] for w in counts}}
        blocks = [specs[k:k + args.block] for k in range(0, len(specs), args.block)]
        for block in blocks:
            dt, dc = direct(block)
            t["direct"] += dt
            cpu["direct"] += dc
            dt, dc, rows = tasks_in_process(block)
            t["tasks"] += dt
            cpu["tasks"] += dc
            rows_by["tasks"] += rows
            for w in counts:
                dt, dc, rows = on_dask(clusters[w][1], block)
                t[w] += dt
                cpu[w] += dc
                rows_by[w] += rows
        for cluster, client, _ in clusters.values():
            client.close()
            cluster.close()
        for key in cpu:
            cpu[key] -= background * t[key]
        rss2 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(f"peak memory of this process: {rss0:.0f} MB before, {rss1:.0f} MB after one "
              f"group, {rss2:.0f} MB after all {len(specs)} (bounded by one group)")
        n = len(specs)

        def line(label: str, key, extra: str = "") -> None:
            sec = t[key]
            print(f"{label:32s}: wall {sec:6.1f} s {1e3 * sec / n:6.0f} ms/group "
                  f"{n / sec:5.2f} groups/s {n_rec / sec:6.1f} rec/s | CPU {cpu[key]:6.1f} s "
                  f"{1e3 * cpu[key] / n:5.0f} ms/group{extra}")

        line("direct (stage calls, 1 thread)", "direct")
        line("run_group serially (1 thread)", "tasks",
             f" ({100 * (cpu['tasks'] / cpu['direct'] - 1):+.1f} % CPU vs direct)")
        key = lambda r: (r["group"], r["period"])  # noqa: E731
        ref = sorted(rows_by["tasks"], key=key)
        for w in counts:
            in_task = statistics.fmean(r["elapsed_s"] for r in rows_by[w])
            line(f"dask, {w} worker(s) x 1 thread", w,
                 f" (mean wall time inside a task {1e3 * in_task:.0f} ms)")
            got = sorted(rows_by[w], key=key)
            same = all(a["A"] == b["A"] and a["B"] == b["B"] and a["C"] == b["C"]
                       for a, b in zip(ref, got, strict=True))
            print(f"   same A, B, C as run_group in this process: {same}")
        if 1 in counts:
            over = cpu[1] / cpu["direct"] - 1
            print(f"Dask overhead in CPU, 1 worker vs direct: {100 * over:+.1f} % "
                  f"({1e3 * (cpu[1] - cpu['direct']) / n:+.1f} ms of CPU per task of "
                  f"{args.recordings} recordings); target < 10 %: "
                  f"{'met' if over < 0.10 else 'NOT met'}")
            print(f"   in wall time: {100 * (t[1] / t['direct'] - 1):+.1f} % "
                  "(meaningful only on an idle machine)")
            print(f"   of which outside the task (scheduling, transfer): "
                  f"{1e3 * (t[1] - sum(r['elapsed_s'] for r in rows_by[1])) / n:+.1f} ms per "
                  f"task")
        if 1 in counts and 2 in counts:
            print(f"speed-up from the second worker (wall): {t[1] / t[2]:.2f}x; CPU per group "
                  f"{1e3 * cpu[2] / n:.0f} ms against {1e3 * cpu[1] / n:.0f} ms with one")
        print(f"load average at end: {os.getloadavg()[0]:.2f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
