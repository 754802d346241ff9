"""What diagnose finds on the paper-like campaign for each hidden effect (the table of
docs/benchmarks/diagnose-accuracy.md, "Hidden effects in a simulated campaign").

Every campaign is recorded from the simulated controller (in simulated time) whose effects file
hides the effect; A, B, C are fitted with ``fit`` as a user would, then ``diagnose`` runs without
being told anything. Prints one markdown row per case, with the time each took.

Usage: ``python bench/diagnose_campaigns.py [--quick] [--seeds N]`` (``--quick``: the tests'
shorter campaign, steps held 1.5 s, no 15/60 rpm steps and no reversing step; ``--seeds N``:
each case with N noise seeds, printing how often diagnose gave the right answer and the range
of what it recovered, instead of one row per case).
"""

from __future__ import annotations

import argparse
import math
import time

from mecanum_hil.identify.campaign import SHORT_CAMPAIGN, campaign_profiles, paper_campaign
from mecanum_hil.identify.diagnose import diagnose
from mecanum_hil.identify.fit import fit
from mecanum_hil.link.effects_file import sim_effects_for
from mecanum_hil.model import Effects, RobotProfile

NOISE_RPM = 0.25
CASES = [
    ("none", Effects(), None),
    ("dead_time 0.055 s", Effects(dead_time_s=0.055), None),
    ("saturation 110 rpm", Effects(top_speed_rpm=110.0), None),
    ("rate_limit 150 rpm/s", Effects(rate_limit_rpm_per_s=150.0), None),
    ("deadband 6 rpm", Effects(deadband_rpm=6.0), None),
    ("wheel_gain (1, .85, 1, 1.1)", Effects(gains=(1.0, 0.85, 1.0, 1.1)), None),
    ("slip (.9, .75, .85)", Effects(efficiency=(0.9, 0.75, 0.85)), None),
    ("dead_time 0.035 s + saturation 110 rpm",
     Effects(dead_time_s=0.035, top_speed_rpm=110.0), None),
    ("controller_period 20 ms", Effects(controller_period_s=0.02), None),
    ("drive_lag 30 ms", Effects(drive_lag_s=0.03), None),
    ("breakaway 1500 rpm/s", Effects(breakaway_rpm_per_s=1500.0), None),
    ("roller ripple (outside, 5 % at 8 per turn)", Effects(),
     {"roller_ripple": {"amplitude": 0.05, "per_turn": 8.0}}),
    ("3 Hz resonance, zeta 0.15 (outside)", Effects(),
     {"resonance": {"natural_hz": 3.0, "damping": 0.15}}),
]


def _fmt(value) -> str:
    if isinstance(value, list | tuple):
        return "(" + ", ".join(f"{v:.4f}" for v in value) + ")"
    return f"{value:.5f}" if abs(value) < 1.0 else f"{value:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=0)
    args = ap.parse_args()
    robot = RobotProfile()
    profiles = campaign_profiles(**SHORT_CAMPAIGN) if args.quick else campaign_profiles()
    if args.seeds > 0:
        return reliability(robot, profiles, args.seeds)
    print("| hidden | named (share of the gap) | recovered | wheel RMSE [rpm] | unexplained | "
          "time [s] |")
    print("|---|---|---|---|---|---|")
    for seed, (label, effects, unmodelled) in enumerate(CASES, start=1):
        t0 = time.perf_counter()
        fx = sim_effects_for(effects, wheel_rpm_std=NOISE_RPM, seed=seed, unmodelled=unmodelled)
        recs = paper_campaign(fx, robot, profiles=profiles, seed=seed)
        user = fit(recs, robot).calibration
        d = diagnose(recs, user, robot)
        took = time.perf_counter() - t0
        named = ", ".join(f"{s.effect} ({100 * d.share(s):.0f} %)" for s in d.steps) or "nothing"
        got = "; ".join(_fmt(v) for s in d.steps for v in s.parameters.values()) or "-"
        rmse = f"{d.rmse_initial:.3g} -> {d.rmse_final:.3g}"
        if any(s.effect == "slip" for s in d.steps):
            st = next(s for s in d.steps if s.effect == "slip")
            before = math.hypot(*st.pose_rmse_before[:2])
            after = math.hypot(*st.pose_rmse_after[:2])
            rmse += f" (pose {1e3 * before:.1f} -> {1e3 * after:.1f} mm)"
        print(f"| {label} | {named} | {got} | {rmse} | {str(d.unexplained).lower()} | "
              f"{took:.0f} |", flush=True)


def _expected(effects: Effects, unmodelled) -> tuple[list[str], bool]:
    return sorted(effects.active()), bool(unmodelled)


def reliability(robot: RobotProfile, profiles, seeds: int) -> None:
    """Each case with ``seeds`` noise seeds: how often the answer is right."""
    print(f"| hidden | right answer in {seeds} seeds | recovered (min .. max) | "
          "RMSE final / noise (max) | time per run [s] |")
    print("|---|---|---|---|---|")
    for label, effects, unmodelled in CASES:
        want, unexplained = _expected(effects, unmodelled)
        right, values, ratio, took = 0, [], [], []
        for seed in range(100, 100 + seeds):
            t0 = time.perf_counter()
            fx = sim_effects_for(effects, wheel_rpm_std=NOISE_RPM, seed=seed,
                                 unmodelled=unmodelled)
            recs = paper_campaign(fx, robot, profiles=profiles, seed=seed)
            d = diagnose(recs, fit(recs, robot).calibration, robot)
            took.append(time.perf_counter() - t0)
            ok = sorted(d.effects) == want and d.unexplained == unexplained
            right += ok
            if not ok:
                print(f"<!-- {label}, seed {seed}: named {d.effects}, unexplained "
                      f"{d.unexplained} -->", flush=True)
            values.append([v for s in d.steps for p in s.parameters.values()
                           for v in (p if isinstance(p, list | tuple) else [p])])
            ratio.append(d.rmse_final / NOISE_RPM)
        got = "-"
        if want and all(len(v) == len(values[0]) for v in values):
            arr = list(zip(*values, strict=True))
            got = "; ".join(f"{_fmt(min(a))} .. {_fmt(max(a))}" for a in arr)
        print(f"| {label} | {right}/{seeds} | {got} | {max(ratio):.2f} | "
              f"{sum(took) / len(took):.0f} |", flush=True)


if __name__ == "__main__":
    main()
