"""Benchmark of the Gymnasium environments: robot-steps per second.

Measures, in one run, ``MecanumHILVectorEnv`` against Gymnasium's own ``SyncVectorEnv`` over
single ``MecanumHILEnv`` instances (the baseline), for 1 and for 4096 robots, on the shipped
paper calibration (closed-form path) and on a "diagnosed" calibration with a dead time that
splits every period, saturation (20 sub-steps per 20 ms period) and domain randomisation.
Random actions, 20 ms control period, episodes of 10 s with next-step autoreset included.

Run: ``python bench/bench_env.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import numpy as np

from mecanum_hil.envs import MecanumHILEnv, MecanumHILVectorEnv
from mecanum_hil.model import Calibration, Effects

DIAGNOSED = Calibration(
    A=12.0, B=14.0, C=280.0,
    effects=Effects(dead_time_s=0.031, top_speed_rpm=120.0, deadband_rpm=2.0,
                    gains=(1.0, 0.95, 1.0, 1.05), efficiency=(0.95, 0.85, 0.9)),
    ci95={"A": (11.0, 13.0), "B": (13.0, 15.0), "C": (260.0, 300.0)}, source="diagnosed")

CASES = {
    "paper": {"calibration": "paper"},
    "diagnosed+randomised": {"calibration": DIAGNOSED, "randomize": True},
}


def robot_steps_per_s(envs, n_robots: int, steps: int, seed: int = 0) -> float:
    """Best of three timed runs of ``steps`` vector steps (after a warm-up) [robot-steps/s]."""
    envs.reset(seed=seed)
    rng = np.random.default_rng(seed)
    space = envs.single_action_space
    actions = rng.uniform(space.low, space.high, size=(16, n_robots, 3))
    for k in range(3):
        envs.step(actions[k])
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for k in range(steps):
            envs.step(actions[k % 16])
        best = min(best, time.perf_counter() - t0)
    return n_robots * steps / best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps (a smoke test)")
    args = parser.parse_args()
    scale = 0.1 if args.quick else 1.0
    print(f"cores: {os.cpu_count()}, load average at start: "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    for name, kwargs in CASES.items():
        print(f"\n== {name} ==")
        sync1 = gym.vector.SyncVectorEnv([lambda kw=kwargs: MecanumHILEnv(**kw)])
        base1 = robot_steps_per_s(sync1, 1, int(3000 * scale))
        ours1 = robot_steps_per_s(MecanumHILVectorEnv(1, **kwargs), 1, int(3000 * scale))
        print(f"1 robot     SyncVectorEnv(1 env)      {base1:12,.0f} robot-steps/s  (baseline)")
        print(f"1 robot     MecanumHILVectorEnv       {ours1:12,.0f} robot-steps/s  "
              f"x{ours1 / base1:.2f}")
        n = 4096
        t0 = time.perf_counter()
        sync = gym.vector.SyncVectorEnv([lambda kw=kwargs: MecanumHILEnv(**kw)] * n)
        made = time.perf_counter() - t0
        base = robot_steps_per_s(sync, n, max(2, int(10 * scale)))
        print(f"4096 robots SyncVectorEnv(4096 envs)  {base:12,.0f} robot-steps/s  (baseline; "
              f"made in {made:.1f} s)")
        for threads in (1, None):
            vec = MecanumHILVectorEnv(n, num_threads=threads, **kwargs)
            # 600 steps: every robot's 10 s episode ends once, so the resets are included
            ours = robot_steps_per_s(vec, n, max(20, int(600 * scale)))
            label = f"MecanumHILVectorEnv ({vec.core.stepper.num_threads} thread"
            label += "s)" if vec.core.stepper.num_threads > 1 else ")"
            verdict = "meets" if ours >= 1e6 else "BELOW"
            print(f"4096 robots {label:25s} {ours:12,.0f} robot-steps/s  x{ours / base:,.0f}"
                  f"  ({verdict} the 1e6 target)")
    print(f"\nload average at end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
