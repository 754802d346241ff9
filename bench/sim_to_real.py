"""Train on the model, run on the robot: the sim-to-real gap of the paper's model, the fit and
the diagnosed model (the table of docs/benchmarks/rl.md, the path plot of docs/rl.md).

The "robot" is the simulated controller (``sim-robot``'s firmware and robot) with a hidden truth
in an effects file: a drive ceiling well below the profile's 130 rpm limit (saturation at
90 rpm) and a dead time of 60 ms, wheel-speed noise 0.5 rpm. Steps, all through the command
line where a user would use it:

1. ``mecanum-hil campaign --effects truth.toml`` -> ``fit`` -> ``diagnose``;
2. ``mecanum-hil train`` on the paper's model, on the fit, on the diagnosed model, and on the
   diagnosed model with ``--randomize``, for reach and for dodge;
3. each policy (and the scripted baseline) evaluated in simulation on the model it was trained
   on (*predicted*) and, in closed loop over the wire protocol, on the simulated robot
   (*achieved*): :func:`mecanum_hil.link.policy_session.run_policy_lockstep`, the same
   firmware as ``sim-robot`` on a virtual clock (``record --policy`` against ``sim-robot`` runs
   the same host loop in real time; the lockstep does hundreds of episodes in minutes), the
   episodes drawn as ``evaluate`` draws them.

Prints a markdown table and writes ``results.json`` and the path plot.

Usage: ``python bench/sim_to_real.py [--out DIR] [--budget-reach S] [--budget-dodge S]
[--sim-episodes N] [--wire-reach N] [--wire-dodge N] [--plot PNG]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from mecanum_hil.envs.task import resolve_task
from mecanum_hil.link.effects_file import load_sim_effects, save_sim_effects, sim_effects_for
from mecanum_hil.link.policy_session import run_policy_lockstep
from mecanum_hil.model import Calibration, Effects, load_calibration, load_robot_profile
from mecanum_hil.policy import ScriptedPolicy, episode_draw, evaluate, load_policy
from mecanum_hil.policy.evaluate import dodge_clearance_m

TRUTH = Effects(dead_time_s=0.06, top_speed_rpm=90.0)
EVAL_SEED = 1000


def cli(*args: str) -> dict:
    """Run ``mecanum-hil ARGS --json`` and return its JSON (the last line of its output)."""
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "mecanum_hil", *args, "--json"],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"mecanum-hil {' '.join(args)} failed: {proc.stderr.strip()}")
    print(f"  mecanum-hil {args[0]} ... {time.monotonic() - t0:.1f} s", file=sys.stderr)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def true_success(task, robot, task_state, final_pose) -> bool:
    """Success judged on the simulated robot's true pose (not the host's odometry)."""
    if task.__class__.__name__ == "DodgeTask":
        return bool(dodge_clearance_m(final_pose[None], task_state[None], task, robot)[0] > 0)
    d = np.hypot(*(task_state[:2] - final_pose[:2]))
    dphi = (task_state[2] - final_pose[2] + 180.0) % 360.0 - 180.0
    return bool(d < task.position_tolerance_m and abs(dphi) < task.heading_tolerance_deg)


def over_the_wire(policy, robot, sim_effects, episodes: int) -> dict:
    """Closed-loop episodes on the simulated robot (paper coefficients + hidden effects)."""
    cal = policy.calibration()
    out = {"success": [], "true_success": [], "returns": [], "end_time_s": [], "paths": []}
    t0 = time.monotonic()
    for i in range(episodes):
        state = episode_draw(policy.task, EVAL_SEED, i)
        ep = run_policy_lockstep(policy, robot, state, calibration=cal, truth=Calibration(),
                                 sim_effects=sim_effects)
        o = ep.outcome
        out["success"].append(o.success)
        out["true_success"].append(true_success(policy.task, robot, state, ep.true_path[-1]))
        out["returns"].append(o.episode_return)
        out["end_time_s"].append(o.end_time_s)
        if i < 3:
            out["paths"].append(ep.true_path)
    out["elapsed_s"] = time.monotonic() - t0
    return out


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = ["paper", "diagnosed"]
    fig, axes = plt.subplots(2, 2, figsize=(11, 11))
    for r, task in enumerate(("reach", "dodge")):
        for c, model in enumerate(shown):
            ax = axes[r, c]
            row = next(x for x in rows if x["task"] == task and x["trained_on"] == model)
            tk = resolve_task(task)
            for i, (pred, ach) in enumerate(zip(row["pred_paths"], row["wire_paths"],
                                                strict=False)):
                color = f"C{i}"
                ax.plot(pred[:, 0], pred[:, 1], "-", color=color,
                        label="predicted (own model)" if i == 0 else None)
                ax.plot(ach[:, 0], ach[:, 1], "--", color=color,
                        label="achieved (simulated robot)" if i == 0 else None)
                state = episode_draw(tk, EVAL_SEED, i)
                if task == "reach":
                    ax.plot(*state[:2], "x", color=color, ms=10)
                else:
                    beta = np.radians(state[0])
                    d = np.array([np.cos(beta), np.sin(beta)])
                    ax.plot([-1.5 * d[0], 1.5 * d[0]], [-1.5 * d[1], 1.5 * d[1]], ":",
                            color=color, lw=1)
            ax.plot(0, 0, "ko")
            ax.set_aspect("equal")
            ax.set_xlabel("X [m]")
            ax.set_ylabel("Y [m]")
            ax.set_title(f"{task}: policy trained on the {model} model\n"
                         f"predicted {100 * row['pred_success']:.0f} %, achieved "
                         f"{100 * row['wire_success']:.0f} %")
            ax.legend(loc="best", fontsize=8)
    fig.suptitle("Paths of the first 3 episodes: solid predicted, dashed achieved "
                 "(truth: saturation 90 rpm, dead time 60 ms)")
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench_out/sim_to_real"))
    ap.add_argument("--budget-reach", type=float, default=120.0)
    ap.add_argument("--budget-dodge", type=float, default=300.0)
    ap.add_argument("--sim-episodes", type=int, default=512)
    ap.add_argument("--wire-reach", type=int, default=30)
    ap.add_argument("--wire-dodge", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plot", type=Path, default=Path("docs/rl_paths.png"))
    ap.add_argument("--reuse", action="store_true",
                    help="keep truth.toml, fit.toml and diagnosed.toml already in --out "
                    "(skip campaign -> fit -> diagnose)")
    ap.add_argument("--reuse-policies", action="store_true",
                    help="keep the policy files already in --out (skip training)")
    args = ap.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    robot = load_robot_profile("tdam-stm")
    t_all = time.monotonic()

    fx = out / "truth.toml"
    if args.reuse and all((out / n).exists() for n in ("truth.toml", "fit.toml",
                                                       "diagnosed.toml")):
        print(f"identification: reusing {out}/fit.toml and diagnosed.toml", file=sys.stderr)
    else:
        print("identification (campaign -> fit -> diagnose)", file=sys.stderr)
        save_sim_effects(sim_effects_for(TRUTH, wheel_rpm_std=0.5, seed=1), fx)
        camp = out / "campaign"
        cli("campaign", "--effects", str(fx), "--out", str(camp))
        recs = sorted(str(p) for p in camp.glob("*.csv"))
        cli("fit", *recs, "--out", str(out / "fit.toml"), "--no-report")
        cli("diagnose", *recs, "--calibration", str(out / "fit.toml"), "--out",
            str(out / "diagnosed.toml"))
    sim_effects = load_sim_effects(fx)
    diagnosed = load_calibration(out / "diagnosed.toml")
    models = [("paper", "paper", False), ("fit", str(out / "fit.toml"), False),
              ("diagnosed", str(out / "diagnosed.toml"), False),
              ("diagnosed+randomize", str(out / "diagnosed.toml"), True)]

    rows = []
    for task in ("reach", "dodge"):
        budget = args.budget_reach if task == "reach" else args.budget_dodge
        wire_n = args.wire_reach if task == "reach" else args.wire_dodge
        entries = [("scripted", None, "paper", False)]
        for name, cal, rand in models:
            pol_path = out / f"{task}-{name}.npz"
            if args.reuse_policies and pol_path.exists():
                info = load_policy(pol_path).training
                trained = {"policy": str(pol_path), "elapsed_s": info["elapsed_s"],
                           "generations": info["generations"]}
            else:
                print(f"{task}: train on {name}", file=sys.stderr)
                trained = cli("train", "--calibration", cal, "--task", task, "--out",
                              str(pol_path), "--budget-s", str(budget), "--seed",
                              str(args.seed), *(["--randomize"] if rand else []),
                              "--no-progress")
            entries.append((name, trained, cal, rand))
        for name, trained, cal, _rand in entries:
            pol = (ScriptedPolicy(robot, resolve_task(task)) if trained is None
                   else load_policy(trained["policy"]))
            pred = evaluate(pol, load_calibration(cal), robot, episodes=args.sim_episodes,
                            seed=EVAL_SEED, keep_paths=3)
            pred_diag = evaluate(pol, diagnosed, robot, episodes=args.sim_episodes,
                                 seed=EVAL_SEED)
            print(f"{task}: {name} over the wire ({wire_n} episodes)", file=sys.stderr)
            wire = over_the_wire(pol, robot, sim_effects, wire_n)
            row = {
                "task": task, "trained_on": name,
                "train_s": None if trained is None else trained["elapsed_s"],
                "generations": None if trained is None else trained["generations"],
                "pred_success": pred.success_rate,
                "pred_success_same_episodes": float(pred.success[:wire_n].mean()),
                "pred_return": pred.mean_return,
                "pred_on_diagnosed": pred_diag.success_rate,
                "wire_success": float(np.mean(wire["success"])),
                "wire_true_success": float(np.mean(wire["true_success"])),
                "wire_return": float(np.mean(wire["returns"])),
                "wire_episodes": wire_n, "wire_s": wire["elapsed_s"],
                "pred_time_to_target_s": pred.time_to_target_s,
                "pred_margin_m": pred.margin_m,
                "pred_paths": pred.paths, "wire_paths": wire["paths"],
            }
            row["gap"] = row["wire_success"] - row["pred_success"]
            rows.append(row)
            print(f"  {name}: predicted {row['pred_success']:.3f}, achieved "
                  f"{row['wire_success']:.3f} (true pose {row['wire_true_success']:.3f})",
                  file=sys.stderr)

    print(f"\ntruth: paper coefficients + saturation {TRUTH.top_speed_rpm:g} rpm + dead time "
          f"{TRUTH.dead_time_s * 1e3:g} ms (profile limit {robot.wheel_speed_max_rpm:g} rpm)")
    f = load_calibration(out / "fit.toml")
    print(f"fit: A={f.A:.4g}, B={f.B:.4g}, C={f.C:.4g} (fit {f.info.get('fit_percent')} %); "
          f"diagnosed: A={diagnosed.A:.4g}, B={diagnosed.B:.4g}, C={diagnosed.C:.4g}, "
          f"effects {diagnosed.effects.active()}\n")
    print("| task | policy (trained on) | training | predicted success (own model, "
          f"{args.sim_episodes} ep.) | predicted, the wire's episodes | achieved success "
          "(over the wire) | achieved - predicted (same episodes) | predicted on the "
          "diagnosed model | predicted / achieved return |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        tr = "-" if r["train_s"] is None else f"{r['train_s']:.0f} s, {r['generations']} gen."
        print(f"| {r['task']} | {r['trained_on']} | {tr} | {r['pred_success']:.3f} | "
              f"{r['pred_success_same_episodes']:.3f} | {r['wire_success']:.3f} "
              f"({r['wire_episodes']} ep.; true pose {r['wire_true_success']:.3f}) | "
              f"{r['wire_success'] - r['pred_success_same_episodes']:+.3f} | "
              f"{r['pred_on_diagnosed']:.3f} | {r['pred_return']:+.2f} / "
              f"{r['wire_return']:+.2f} |")
    plot(rows, args.plot)
    dump = [{k: v for k, v in r.items() if not k.endswith("_paths")} for r in rows]
    (out / "results.json").write_text(json.dumps(dump, indent=2, default=float) + "\n")
    print(f"\nwrote {args.plot} and {out / 'results.json'} in "
          f"{(time.monotonic() - t_all) / 60:.1f} min")


if __name__ == "__main__":
    main()
