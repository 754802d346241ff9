"""Shadow mode: per-sample cost, detection delay and false alarms.

Run as ``python bench/bench_shadow.py [--quick]``. Prints

1. the cost of one live sample (``ShadowMonitor.on_telemetry``, median / p99 / max [us]) and of
   one replayed sample, against the baseline measured in the same run: advancing the model by
   calling ``simulate`` from the previous ``final_state`` for each sample (the obvious way to
   stream the library's simulator) plus the same CUSUM in NumPy;
2. detection delay [ms] of the injected faults (gain -20 %, stall, +50 ms dead time) on every
   wheel at 100 Hz and 1 kHz, several noise seeds, and the CUSUM's misses (> 0.3 s);
3. false alarms over 10 simulated minutes of nominal driving with noise (several seeds, both
   rates), against a single-sample threshold detector on the same normalised residuals
   (|z| > 5, too many false alarms to use) as the baseline.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mecanum_hil.model import Calibration, RobotProfile, simulate
from mecanum_hil.model.stepper import BatchStepper
from mecanum_hil.monitor import ShadowMonitor, replay
from mecanum_hil.monitor.scenarios import (
    FAULT_KINDS,
    driving_commands,
    make_fault,
    simulate_run,
)
from mecanum_hil.prediction import predict

CAL = Calibration()


def per_sample_cost(n: int) -> dict[str, float]:
    t, cmd = driving_commands(n / 1000.0, 1000.0)
    rec = simulate_run(t, cmd, CAL, None, noise_rpm=1.0)
    mon = ShadowMonitor(CAL)
    ns = np.empty(len(rec), dtype=np.int64)
    pc = time.perf_counter_ns
    for i in range(len(rec)):
        a = pc()
        mon.on_telemetry(rec.t_s[i], rec.commands[i], rec.wheel_rpm[i])
        ns[i] = pc() - a
    live = ns / 1e3
    start = time.perf_counter()
    replay(rec, CAL)
    batch_us = (time.perf_counter() - start) / len(rec) * 1e6

    # baseline: the library simulator continued from final_state, one call per sample
    m = min(len(rec), 3000)
    state, pose, sig = None, np.array([0.0, 0.0, 90.0]), 1.0
    s_pos = np.zeros(4)
    s_neg = np.zeros(4)
    base = np.empty(m - 1)
    for i in range(1, m):
        a = pc()
        tr = simulate(rec.commands[i - 1:i + 1], rec.t_s[i - 1:i + 1], CAL, initial_state=state,
                      initial_pose=pose, initial_command=rec.commands[i - 1])
        state, pose = tr.final_state, tr.pose[0, -1]
        z = (rec.wheel_rpm[i] - tr.wheel_rpm[0, -1]) / sig
        s_pos = np.maximum(0.0, s_pos + z - 1.0)
        s_neg = np.maximum(0.0, s_neg - z - 1.0)
        _ = (s_pos > 10.0).any() or (s_neg > 10.0).any()
        base[i - 1] = (pc() - a) / 1e3
    # second baseline: the model's fixed-period array stepper (cached tables), one step a sample
    stepper = BatchStepper(1, 1e-3, CAL)
    step_ns = np.empty(m - 1)
    for i in range(1, m):
        a = pc()
        stepper.step(rec.commands[i - 1:i])
        z = (rec.wheel_rpm[i] - stepper.wheel_rpm[0]) / sig
        s_pos = np.maximum(0.0, s_pos + z - 1.0)
        s_neg = np.maximum(0.0, s_neg - z - 1.0)
        _ = (s_pos > 10.0).any() or (s_neg > 10.0).any()
        step_ns[i - 1] = (pc() - a) / 1e3
    return {"stepper_median_us": float(np.median(step_ns)),
            "stepper_p99_us": float(np.percentile(step_ns, 99)),
            "live_median_us": float(np.median(live)), "live_p99_us": float(np.percentile(live, 99)),
            "live_max_us": float(live.max()), "replay_us": batch_us,
            "baseline_median_us": float(np.median(base)),
            "baseline_p99_us": float(np.percentile(base, 99))}


def detection(seeds: int) -> list[tuple]:
    rows = []
    for rate in (100.0, 1000.0):
        t, cmd = driving_commands(24.0, rate)
        for kind in FAULT_KINDS:
            delays, misses, wrong, th_delays, th_misses = [], 0, 0, [], 0
            for wheel in (1, 2, 3, 4):
                for seed in range(seeds):
                    fault = make_fault(kind, 20.0, wheel=wheel)
                    rec = simulate_run(t, cmd, CAL, fault, seed=100 * wheel + seed)
                    res = replay(rec, CAL)
                    th = threshold_first(rec, fault.channels, 20.0)
                    if th is None or th > 0.3:
                        th_misses += 1
                    if th is not None:
                        th_delays.append(th * 1e3)
                    hits = [a for a in res.alarms if a.channel in fault.channels]
                    if res.alarms and res.alarms[0].channel not in fault.channels:
                        wrong += 1
                    if not hits or hits[0].t_s - 20.0 > 0.3:
                        misses += 1
                    if hits:
                        delays.append((hits[0].t_s - 20.0) * 1e3)
            d = np.array(delays)
            thm = float(np.median(th_delays)) if th_delays else float("nan")
            rows.append((rate, kind, len(d), float(np.median(d)), float(d.max()), misses, wrong,
                         thm, th_misses))
    return rows


def _threshold_z(rec, sigma_window_s: float = 1.0):
    """Normalised residuals of the baseline: |measured - model| / sigma (MAD of the first s)."""
    pred = predict(rec, CAL, RobotProfile())
    r = rec.wheel_rpm - pred.wheel_rpm
    warm = rec.t_s < rec.t_s[0] + sigma_window_s
    med = np.median(r[warm], axis=0)
    sigma = np.maximum(1.4826 * np.median(np.abs(r[warm] - med), axis=0), 0.2)
    z = np.abs(r) / sigma
    z[warm] = 0.0
    return z


def threshold_alarms(rec, z_max: float = 5.0) -> int:
    """Baseline: alarms of a single-sample |z| > z_max test on the same residuals."""
    return int((_threshold_z(rec) > z_max).sum())


def threshold_first(rec, channels, fault_t_s: float, z_max: float = 5.0) -> float | None:
    """Baseline: delay of the first |z| > z_max on a faulty channel [s], or None."""
    z = _threshold_z(rec)
    cols = [int(c[5]) - 1 for c in channels]
    hit = np.flatnonzero((z[:, cols] > z_max).any(axis=1) & (rec.t_s >= fault_t_s))
    return float(rec.t_s[hit[0]] - fault_t_s) if hit.size else None


def false_alarms(seeds: int, minutes: float) -> list[tuple]:
    rows = []
    for rate in (100.0, 1000.0):
        t, cmd = driving_commands(60.0 * minutes, rate)
        cusum = thresh = 0
        elapsed = 0.0
        for seed in range(seeds):
            rec = simulate_run(t, cmd, CAL, None, noise_rpm=1.0, pose_noise_m=0.002, seed=seed)
            start = time.perf_counter()
            cusum += len(replay(rec, CAL).alarms)
            elapsed += time.perf_counter() - start
            thresh += threshold_alarms(rec)
        rows.append((rate, seeds, minutes, cusum, thresh, elapsed / seeds))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer seeds and samples")
    args = ap.parse_args()
    seeds = 2 if args.quick else 5
    ShadowMonitor(CAL)  # load the compiled core before timing
    simulate(np.zeros((2, 3)), [0.0, 0.01], CAL)

    c = per_sample_cost(5000 if args.quick else 30000)
    print("per-sample cost [us]                    median      p99      max")
    print(f"  live  ShadowMonitor.on_telemetry    {c['live_median_us']:8.2f} "
          f"{c['live_p99_us']:8.2f} {c['live_max_us']:8.1f}")
    print(f"  replay (same core, compiled loop)   {c['replay_us']:8.2f}")
    print(f"  baseline simulate() per sample      {c['baseline_median_us']:8.2f} "
          f"{c['baseline_p99_us']:8.2f}")
    print(f"  baseline BatchStepper.step (1 ms)   {c['stepper_median_us']:8.2f} "
          f"{c['stepper_p99_us']:8.2f}")
    live_med, live_p99 = c["live_median_us"], c["live_p99_us"]
    print(f"  ratio simulate() / live             {c['baseline_median_us'] / live_med:8.1f}x"
          f"   (p99 {c['baseline_p99_us'] / live_p99:.1f}x)")
    print(f"  ratio BatchStepper / live           {c['stepper_median_us'] / live_med:8.1f}x"
          f"   (p99 {c['stepper_p99_us'] / live_p99:.1f}x)")
    print(f"  1 kHz budget used by live p99       {c['live_p99_us'] / 1000.0:8.2%}")

    print("\ndetection delay of injected faults at t = 20 s (every wheel x seeds)")
    print("  rate   fault        runs  median [ms]  max [ms]  misses(>0.3s)  first-on-wrong"
          "  | baseline |z|>5: median [ms]  misses")
    for rate, kind, n, med, mx, miss, wrong, thm, thmiss in detection(seeds):
        print(f"  {rate:5.0f}  {kind:10s} {n:5d} {med:11.0f} {mx:9.0f} {miss:13d} {wrong:15d}"
              f"  | {thm:26.0f} {thmiss:7d}")

    minutes = 2.0 if args.quick else 10.0
    print(f"\nfalse alarms over {minutes:g} simulated minutes of nominal driving with noise "
          "(wheel sigma 1 rpm, pose 2 mm / 0.2 deg)")
    print("  rate   seeds  CUSUM alarms  |z|>5 threshold alarms (baseline)  replay time [s]")
    for rate, n, _, cus, thr, el in false_alarms(seeds, minutes):
        print(f"  {rate:5.0f}  {n:5d}  {cus:12d}  {thr:32d}  {el:14.2f}")


if __name__ == "__main__":
    main()
