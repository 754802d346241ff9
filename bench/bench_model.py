"""Benchmark of the batch simulator.

4096 robots x 10 s at 1 kHz, each with its own piecewise-constant command stream (a new random
command every second). Prints robot-steps per second of ``simulate_batch`` and the ratio against
the baseline measured in the same run: the same robots simulated one by one with
``scipy.signal.lsim`` (four wheels) plus a Python pose loop (Euler, as the paper integrates). The
baseline is timed on a sample of robots and extrapolated (it would take far too long in full).

Targets: >= 500x the baseline and >= 15 million robot-steps per second.

Run: ``python bench/bench_model.py [--robots 4096] [--seconds 10] [--rate 1000]``
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from scipy import signal

from mecanum_hil.model import Calibration, RobotProfile, command_to_wheels, simulate_batch
from mecanum_hil.model.motor import transfer_function
from mecanum_hil.units import RPM_TO_RAD_S


def commands(n_robots: int, n_samples: int, rate_hz: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    per_s = int(rate_hz)
    blocks = math.ceil(n_samples / per_s)
    c = np.empty((n_robots, blocks, 3))
    c[..., 0] = rng.uniform(0, 90, (n_robots, blocks))
    c[..., 1] = rng.uniform(-40, 40, (n_robots, blocks))
    c[..., 2] = rng.uniform(0, 360, (n_robots, blocks))
    return np.repeat(c, per_s, axis=1)[:, :n_samples]


def baseline_one(cmd: np.ndarray, t: np.ndarray, cal: Calibration, robot: RobotProfile):
    """One robot with scipy.signal.lsim per wheel and a Python pose loop."""
    sys = signal.lti(*transfer_function(*cal.coefficients))
    targets = command_to_wheels(cmd[:, 0], cmd[:, 1], cmd[:, 2], robot.k)
    wheels = np.column_stack(
        [signal.lsim(sys, targets[:, i], t, interp=False)[1] for i in range(4)])
    x, y, phi = 0.0, 0.0, math.pi / 2
    lin = RPM_TO_RAD_S * robot.wheel_radius_m
    pose = np.empty((t.size, 3))
    for i in range(t.size):
        pose[i] = (x, y, phi)
        if i + 1 == t.size:
            break
        dt = t[i + 1] - t[i]
        w1, w2, w3, w4 = wheels[i]
        vx = lin * (w1 + w2 + w3 + w4) / 4
        vy = lin * (-w1 + w2 + w3 - w4) / 4
        wz = RPM_TO_RAD_S * (-w1 + w2 - w3 + w4) / (4 * robot.k)
        x += (vx * math.cos(phi) - vy * math.sin(phi)) * dt
        y += (vx * math.sin(phi) + vy * math.cos(phi)) * dt
        phi += wz * dt
    return wheels, pose


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=4096)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--baseline-sample", type=int, default=8)
    args = ap.parse_args()

    cal, robot = Calibration(), RobotProfile()
    t = np.arange(round(args.seconds * args.rate) + 1) / args.rate
    cmd = commands(args.robots, t.size, args.rate)
    steps = args.robots * (t.size - 1)
    simulate_batch(cmd[:2, :10], t[:10], cal)  # compile (cached on disk after the first run)

    t0 = time.perf_counter()
    traj = simulate_batch(cmd, t, cal)
    fresh_s = time.perf_counter() - t0
    reuse = []
    for _ in range(3):
        t0 = time.perf_counter()
        simulate_batch(cmd, t, cal, out=traj)
        reuse.append(time.perf_counter() - t0)
    reuse_s = min(reuse)

    k = min(args.baseline_sample, args.robots)
    t0 = time.perf_counter()
    for i in range(k):
        w, _ = baseline_one(cmd[i], t, cal, robot)
    base_s = (time.perf_counter() - t0) / k * args.robots
    # the two implementations agree: lsim with interp=False is the same zero-order hold
    agree = np.abs(w - traj.wheel_rpm[k - 1]).max()

    print(f"simulate_batch: {args.robots} robots x {args.seconds:g} s at {args.rate:g} Hz "
          f"= {steps / 1e6:.1f} M robot-steps")
    print(f"  fresh output arrays : {fresh_s:7.2f} s  {steps / fresh_s / 1e6:7.1f} M robot-steps/s")
    print(f"  reused output arrays: {reuse_s:7.2f} s  {steps / reuse_s / 1e6:7.1f} M robot-steps/s")
    print(f"baseline (lsim + Python pose loop, {k} robots timed, extrapolated): {base_s:8.1f} s  "
          f"{steps / base_s / 1e6:7.3f} M robot-steps/s")
    print(f"ratio vs baseline: fresh {base_s / fresh_s:7.0f}x   reused {base_s / reuse_s:7.0f}x   "
          f"(target >= 500x)")
    print(f"max |wheel difference| vs baseline: {agree:.2e} rpm")


if __name__ == "__main__":
    main()
