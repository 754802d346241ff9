"""Benchmark of diagnose: its cost against one ``fit``, and its held-out score against exact LOO.

Measured in one run on a campaign like the paper's (100 Hz, 0.25 rpm noise) with a hidden drive
ceiling (saturation 110 rpm):

* wall time of ``fit`` (A, B, C, the user's step) as the baseline, and of ``diagnose`` as a
  ratio of it;
* the approximate leave-one-recording-out score (one Gauss-Newton step per left-out recording,
  :func:`mecanum_hil.identify.diagnose.heldout_score`) against the exact one (a full refit on
  the other recordings for each left-out one), for the model without and with the named
  effect: their values and the cost ratio.

The timing targets (``--targets``): a single 2-s recording diagnoses in under 10 s and a
12-recording campaign in under 60 s. Measured in one run, each beside a ``fit`` of the same
data as the baseline: the 2-s recording is a 200 rpm step at 500 Hz from the simulated model with
a hidden breakaway and per-wheel gains (and, when ``../shared/data/real/micromouse`` is there,
each real recording alone); the campaign is the paper-like default (12 recordings) with a
hidden ceiling. Wall and CPU time (``time.process_time``: this process, all threads) are printed
side by side with the load average (the machine is shared), and the real recordings are also
diagnosed as a user runs them, one fresh ``mecanum-hil diagnose`` process each (imports and
loading the compiled kernels included).

Run: ``python bench/bench_diagnose.py [--quick] [--targets] [--jobs N]`` (``--quick``: fewer
recordings; ``--jobs``: processes for diagnose's candidates, default its own choice).
CPU time is this process's: a helper process's (``--jobs 2``) is not in it.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mecanum_hil.identify.campaign import campaign_profiles, paper_campaign
from mecanum_hil.identify.diagnose import _Evaluator, diagnose, heldout_score
from mecanum_hil.identify.fit import fit, fit_parameters, parameter_value, with_parameters
from mecanum_hil.link.effects_file import sim_effects_for
from mecanum_hil.model import Effects, RobotProfile


def exact_loo(recs, cal, robot, free) -> float:
    """Held-out mean square wheel residual by refitting ``free`` without each recording."""
    ev = _Evaluator(recs, robot)
    sse = n = 0.0
    for i in range(len(recs)):
        others = [r for k, r in enumerate(recs) if k != i]
        res = fit_parameters(others, cal, robot, free,
                             x0={p: parameter_value(cal, p) for p in free})
        c = with_parameters(cal, res.parameters)
        r = ev.channel(ev.predict([c], subset=[i])[0], "wheel")[i]
        sse += float(r @ r)
        n += r.size
    return sse / n


def _timed(f):
    t0 = time.perf_counter()
    out = f()
    return out, time.perf_counter() - t0


def _timed_cpu(f):
    """Result, wall time [s] and CPU time of this process (all its threads) [s]."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = f()
    return out, time.perf_counter() - t0, time.process_time() - c0


def _load() -> str:
    try:
        with open("/proc/loadavg") as f:
            return " ".join(f.read().split()[:3])
    except OSError:
        return "n/a"


def _cli_diagnose(csv, robot_toml, jobs: int | None = None) -> tuple[float, float]:
    """Wall and CPU time [s] of ``mecanum-hil fit`` + ``diagnose`` as a user runs them (a fresh
    process each: imports and loading the compiled kernels included); the diagnose alone."""
    import resource
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    exe = [str(Path(sys.executable).with_name("mecanum-hil"))]
    with tempfile.TemporaryDirectory() as tmp:
        fit_toml = str(Path(tmp) / "fit.toml")
        subprocess.run([*exe, "fit", str(csv), "--robot", str(robot_toml), "-o", fit_toml,
                        "--no-report"], check=True, capture_output=True)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run([*exe, "diagnose", str(csv), "--robot", str(robot_toml), "-c", fit_toml,
                        "-o", str(Path(tmp) / "diag.toml"),
                        *(["--jobs", str(jobs)] if jobs else [])], check=True,
                       capture_output=True)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def timing_targets(jobs: int | None = None) -> None:
    """The two timing targets (one 2-s recording < 10 s, 12 recordings < 60 s), each with a
    fit of the same data as the baseline; ``jobs`` as ``diagnose`` takes it (default: its own
    choice by the load)."""
    from pathlib import Path

    from mecanum_hil.io.recording import Recording, read_recording
    from mecanum_hil.model import Calibration, load_robot_profile
    from mecanum_hil.model.simulate import simulate

    rows = []
    robot = RobotProfile()
    t = np.arange(1001) / 500.0
    cmd = np.tile([0.0, 0.0, 90.0], (t.size, 1))
    cmd[10:, 0] = 200.0
    truth = Calibration(A=3.0, B=8.0, C=500.0, effects=Effects(
        breakaway_rpm_per_s=4000.0, gains=(0.9, 0.95, 1.0, 1.0)))
    w = simulate(cmd, t, truth, robot).wheel_rpm[0]
    w = w + np.random.default_rng(0).normal(0.0, 2.0, w.shape)
    synth = Recording(t, cmd, w, np.full((t.size, 3), np.nan))
    cases = [("synthetic 2-s step (breakaway + gains)", [synth], robot)]
    real = Path(__file__).resolve().parents[2] / "shared/data/real/micromouse"
    if real.is_dir():
        mm = load_robot_profile(real / "robot.toml")
        cases += [(f"real {p.stem}", [read_recording(p)], mm)
                  for p in sorted(real.glob("*.csv"))]
    hidden = sim_effects_for(Effects(top_speed_rpm=110.0), wheel_rpm_std=0.25, seed=1)
    camp = paper_campaign(hidden, robot, seed=1)
    cases.append((f"campaign of {len(camp)} recordings (ceiling)", camp, robot))
    print(f"load average before: {_load()}; jobs: {jobs or 'default (by the load)'}")
    for label, recs, rob in cases:
        fitted, t_fit, c_fit = _timed_cpu(lambda recs=recs, rob=rob: fit(recs, rob))
        d, t_diag, c_diag = _timed_cpu(
            lambda recs=recs, rob=rob, c=fitted.calibration: diagnose(recs, c, rob, jobs=jobs))
        rows.append((label, sum(len(r) for r in recs), t_fit, c_fit, t_diag, c_diag, d,
                     _load()))
    print("In process (the first case also loads the compiled kernels):")
    print("| data | samples | fit wall / CPU [s] | diagnose wall / CPU [s] | ratio (wall, CPU) | "
          "named | wheel RMSE [rpm] | load after |")
    print("|---|---|---|---|---|---|---|---|")
    for label, n, tf, cf, td, cd, d, load in rows:
        print(f"| {label} | {n} | {tf:.2f} / {cf:.2f} | {td:.1f} / {cd:.1f} | "
              f"{td / tf:.0f} x, {cd / max(cf, 1e-9):.0f} x | {', '.join(d.effects) or 'none'} | "
              f"{d.rmse_initial:.4g} -> {d.rmse_final:.4g} | {load} |")
    if real.is_dir():
        print("As a user runs it (a fresh `mecanum-hil diagnose` process per recording):")
        print("| recording | diagnose wall / CPU [s] | load after |")
        print("|---|---|---|")
        for p in sorted(real.glob("*.csv")):
            wall, cpu = _cli_diagnose(p, real / "robot.toml", jobs)
            print(f"| {p.stem} | {wall:.1f} / {cpu:.1f} | {_load()} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--targets", action="store_true",
                    help="the timing targets: one 2-s recording < 10 s, 12 recordings < 60 s")
    ap.add_argument("--jobs", type=int, default=None,
                    help="diagnose's --jobs (default: its own choice by the load)")
    args = ap.parse_args()
    if args.targets:
        timing_targets(args.jobs)
        return
    robot = RobotProfile()
    steps = (4.0, 30.0, 120.0) if args.quick else (4.0, 8.0, 30.0, 100.0, 120.0)
    profiles = campaign_profiles(steps_rpm=steps, step_hold_s=1.5, reverse=False)
    hidden = sim_effects_for(Effects(top_speed_rpm=110.0), wheel_rpm_std=0.25, seed=1)
    recs = paper_campaign(hidden, robot, seed=1, profiles=profiles)
    print(f"campaign: {len(recs)} recordings, {sum(len(r) for r in recs)} samples")

    t0 = time.perf_counter()
    user = fit(recs, robot).calibration
    t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    d = diagnose(recs, user, robot)
    t_diag = time.perf_counter() - t0
    print(f"fit A, B, C (baseline): {t_fit:6.2f} s")
    print(f"diagnose:               {t_diag:6.2f} s = {t_diag / t_fit:5.1f} x fit; named "
          f"{d.effects}, RMSE {d.rmse_initial:.3f} -> {d.rmse_final:.3f} rpm")

    ev = _Evaluator(recs, robot)
    rows = []
    for label, cal, free in (("A, B, C only", d.baseline, ["A", "B", "C"]),
                             ("with saturation", d.calibration,
                              ["A", "B", "C", "top_speed_rpm"])):
        t0 = time.perf_counter()
        approx = heldout_score(ev, cal, free).heldout_ms
        t_a = time.perf_counter() - t0
        t0 = time.perf_counter()
        exact = exact_loo(recs, cal, robot, free)
        t_e = time.perf_counter() - t0
        rows.append((label, approx, exact, t_a, t_e))
    print("held-out mean square [rpm^2]: approximate (one step) vs exact (refit) LOO")
    for label, a, e, ta, te in rows:
        print(f"  {label:16s} approx {a:10.4f}  exact {e:10.4f}  ratio {a / e:6.3f}  "
              f"cost {ta:5.2f} s vs {te:6.2f} s = {te / max(ta, 1e-9):5.1f} x")
    ratio = [r[1] / r[2] for r in rows]
    print(f"agreement of approximate and exact held-out scores: "
          f"{np.min(ratio):.3f} .. {np.max(ratio):.3f}")


if __name__ == "__main__":
    main()
