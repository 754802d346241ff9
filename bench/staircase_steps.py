"""The staircase of docs/benchmarks/diagnose-accuracy.md ("A staircase log, step by step"):
a synthetic lab log, imported with a map, then fit -> diagnose -> simulate as a user runs them,
judged step by step.

The log: a small fast motor (PI loop, at the target in about 10 ms) whose drive runs into its
battery voltage at 29.1 rad/s, logged at 1 kHz as whitespace text with a `%` header (time in s,
1 ms resolution, two wheels, signed set-points), a staircase of 20 steps with reversals
(16 -> -30 rad/s), 0.3 s each, 0.08 rad/s of noise.

Run: ``.venv/bin/python bench/staircase_steps.py [OUT_DIR]`` (default ``docs/img``). Writes
``diagnose-staircase-steps.png`` (the report's per-step plot) there and prints the effects
named, the wheel RMSE of fit alone and diagnosed, the worst step against the per-step
tolerances and the per-step table of wheel 1 (markdown).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LEVELS = [4, 8, 12, 16, -30, -20, -10, 0, 6, 16, 24, 30, 16, -30, -16, -8, 0, 10, 20, 5]
ROBOT_TOML = """[robot]
name = "small-lab-robot"
wheel_radius_m = 0.03
lx_plus_ly_m = 0.15
body_length_m = 0.2
body_width_m = 0.2
mass_kg = 2.0

[limits]
wheel_speed_max_rpm = 400.0
"""
MAP_TOML = """[time]
column = "time_s"
unit = "s"
[wheels]
wheel1 = { column = "w_left", unit = "rad/s" }
wheel2 = { column = "w_right", unit = "rad/s" }
[commands]
setpoint = { column = "setpoint", unit = "rad/s" }
"""


def cli(*args) -> str:
    r = subprocess.run([sys.executable, "-m", "mecanum_hil", *map(str, args)],
                       capture_output=True, text=True, check=True)
    return r.stdout


def main() -> None:
    from mecanum_hil.identify.diagnose.report import step_rows, step_table_lines
    from mecanum_hil.io.recording import read_recording
    from mecanum_hil.model import Calibration, Effects, load_robot_profile
    from mecanum_hil.model.simulate import simulate
    from mecanum_hil.units import RPM_TO_RAD_S

    out_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "img"
    tmp = Path(tempfile.mkdtemp(prefix="staircase-"))
    (tmp / "robot.toml").write_text(ROBOT_TOML)
    (tmp / "map.toml").write_text(MAP_TOML)
    robot = load_robot_profile(tmp / "robot.toml")
    truth = Calibration(A=200.0, B=40.0, C=1e4,
                        effects=Effects(top_speed_rpm=29.1 / RPM_TO_RAD_S))
    dt, n_step = 0.001, 300
    s = np.concatenate([np.zeros(100)] + [np.full(n_step, v, float) for v in LEVELS])
    t = np.arange(s.size) * dt
    rpm = s / RPM_TO_RAD_S
    cmd = np.stack([np.abs(rpm), np.zeros_like(rpm), np.where(rpm >= 0, 90.0, 270.0)], 1)
    w = simulate(cmd, t, truth, robot).wheel_rpm[0] * RPM_TO_RAD_S
    rng = np.random.default_rng(1)
    sd = 0.08
    w1, w2 = (w[:, i] + rng.normal(0.0, sd, t.size) for i in (0, 1))
    stamps = np.floor((t + 0.3405) * 1000.0 + 1e-6) / 1000.0
    lines = ["% lab B speed test", "% time_s  setpoint  w_left  w_right"]
    lines += [f"{a:.3f} {b:.1f} {c:.4f} {d:.4f}"
              for a, b, c, d in zip(stamps, s, w1, w2, strict=True)]
    (tmp / "log.txt").write_text("\n".join(lines) + "\n")

    rec = tmp / "rec.csv"
    cli("import", tmp / "log.txt", "--map", tmp / "map.toml", "--out", rec)
    cli("fit", rec, "--robot", tmp / "robot.toml", "-o", tmp / "fit.toml", "--no-report")
    t0 = time.perf_counter()
    doc = json.loads(cli("diagnose", rec, "--robot", tmp / "robot.toml", "-c", tmp / "fit.toml",
                         "-o", tmp / "diag.toml", "--json", "--report", tmp / "rep"))
    seconds = time.perf_counter() - t0
    preds = {}
    for label, cal in (("fit alone", "fit.toml"), ("diagnosed", "diag.toml")):
        sim = tmp / f"{label.replace(' ', '-')}.csv"
        cli("simulate", "--commands", rec, "--robot", tmp / "robot.toml", "-c", tmp / cal,
            "-o", sim)
        preds[label] = read_recording(sim)
    measured = read_recording(rec)
    noise = sd / RPM_TO_RAD_S
    rows = step_rows(measured, preds, robot, noise)
    err = {k: float(np.sqrt(np.nanmean((measured.wheel_rpm - p.wheel_rpm) ** 2)))
           for k, p in preds.items()}
    out_dir.mkdir(parents=True, exist_ok=True)
    png = out_dir / "diagnose-staircase-steps.png"
    shutil.copy(tmp / "rep" / "steps-1.png", png)
    print(f"effects named: {[(e['effect'], e['parameters']) for e in doc['effects']]}")
    print(f"wheel RMSE fit alone {err['fit alone']:.3f} rpm, diagnosed {err['diagnosed']:.3f} "
          f"rpm (noise {noise:.3f} rpm); diagnose {seconds:.1f} s")
    period = float(np.median(np.diff(measured.t_s)))
    wheel1 = [r for r in rows if r.step.wheel == 0]
    for label in preds:
        bad_t = sum(1 for r in rows if math.isfinite(r.figures["measured"].t50_s) and abs(
            r.figures[label].t50_s - r.figures["measured"].t50_s)
            > max(0.2 * r.figures["measured"].t50_s, 2 * period))
        bad_l = sum(1 for r in rows if abs(r.figures[label].level_rpm
                                           - r.figures["measured"].level_rpm)
                    > max(0.03 * abs(r.step.target_rpm), 1.5 * noise))
        print(f"{label}: steps outside the time tolerance {bad_t} of {len(rows)}, "
              f"outside the level tolerance {bad_l} of {len(rows)}")
    print("\n".join(step_table_lines(wheel1, list(preds), period, noise)))
    print(f"wrote {png}")


if __name__ == "__main__":
    main()
