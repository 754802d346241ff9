"""The real-data figures of docs/benchmarks/diagnose-micromouse.md: fit -> diagnose ->
simulate on each shared micromouse recording alone, as a user runs them, with the acceptance
figures.

Run: ``.venv/bin/python bench/diagnose_real.py [DATA_DIR] [OUT_DIR]`` (defaults
``../shared/data/real/micromouse`` and ``docs/img``). Writes, per recording, the fitted and the
diagnosed calibration, the ``diagnose --json`` document and a PNG (measured, fit alone,
diagnosed), and prints one table row: onset (time to 50 % of the target) and settled level
(mean over the last second) errors per wheel, wheel RMSE of fit alone and diagnosed, time.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXE = str(ROOT / ".venv" / "bin" / "mecanum-hil")


def onset_s(t: np.ndarray, w: np.ndarray, t_step: float, target: float) -> float:
    """Time from the step to the first crossing of half the target, linearly interpolated."""
    half = 0.5 * target
    ok = np.isfinite(w) & (t >= t_step)
    tt, ww = t[ok], w[ok]
    k = np.flatnonzero(ww >= half)
    if not k.size:
        return float("nan")
    j = int(k[0])
    if j == 0:
        return float(tt[0] - t_step)
    f = (half - ww[j - 1]) / (ww[j] - ww[j - 1])
    return float(tt[j - 1] + f * (tt[j] - tt[j - 1]) - t_step)


def figures(rec, pred, target: float) -> dict:
    """Onset and level errors per measured wheel, model minus measured."""
    t = rec.t_s
    moving = np.flatnonzero(rec.commands[:, 0] != 0)
    t_step = float(t[moving[0]]) if moving.size else float(t[0])
    last = t >= t[-1] - 1.0
    out = {}
    for i in range(4):
        m = rec.wheel_rpm[:, i]
        if not np.isfinite(m).any():
            continue
        p = np.where(np.isfinite(m), pred.wheel_rpm[:, i], np.nan)
        out[f"wheel{i + 1}"] = {
            "onset_measured_s": onset_s(t, m, t_step, target),
            "onset_model_s": onset_s(t, p, t_step, target),
            "level_measured_rpm": float(np.nanmean(m[last])),
            "level_model_rpm": float(np.nanmean(p[last])),
        }
    return out


def rmse(rec, pred) -> float:
    r = rec.wheel_rpm - pred.wheel_rpm
    return float(np.sqrt(np.nanmean(r ** 2)))


def main() -> None:
    from mecanum_hil.identify.diagnose.report import plot_comparison
    from mecanum_hil.io.recording import read_recording

    data = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT.parent / "shared/data/real/micromouse"
    out = Path(sys.argv[2]) if len(sys.argv) > 2 else ROOT / "docs" / "img"
    out.mkdir(parents=True, exist_ok=True)
    robot = str(data / "robot.toml")
    rows = []
    for csv in sorted(data.glob("*.csv")):
        name = csv.stem
        fit_toml = out / f"{name}-fit.toml"
        diag_toml = out / f"{name}-diagnosed.toml"
        subprocess.run([EXE, "fit", str(csv), "--robot", robot, "-o", str(fit_toml),
                        "--no-report"], check=True, capture_output=True)
        t0 = time.perf_counter()
        run = subprocess.run([EXE, "diagnose", str(csv), "--robot", robot, "-c", str(fit_toml),
                              "-o", str(diag_toml), "--json"], check=True,
                             capture_output=True, text=True)
        seconds = time.perf_counter() - t0
        doc = json.loads(run.stdout)
        (out / f"{name}-diagnose.json").write_text(json.dumps(doc, indent=1) + "\n")
        preds = {}
        for label, cal in (("fit alone", fit_toml), ("diagnosed", diag_toml)):
            sim = out / f"{name}-{label.replace(' ', '-')}.csv"
            subprocess.run([EXE, "simulate", "--commands", str(csv), "--robot", robot,
                            "-c", str(cal), "-o", str(sim)], check=True, capture_output=True)
            preds[label] = read_recording(sim)
            sim.unlink()
            sim.with_suffix(".json").unlink(missing_ok=True)
        rec = read_recording(csv)
        target = float(np.max(np.abs(rec.commands[:, 0])))
        fig = {k: figures(rec, p, target) for k, p in preds.items()}
        err = {k: rmse(rec, p) for k, p in preds.items()}
        plot_comparison(rec, preds, out / f"diagnose-{name}.png",
                        f"{name}: wheel RMSE fit alone {err['fit alone']:.3g} rpm, "
                        f"diagnosed {err['diagnosed']:.3g} rpm")
        d = fig["diagnosed"]
        on = max(abs(w["onset_model_s"] - w["onset_measured_s"]) for w in d.values())
        lev = max(abs(w["level_model_rpm"] - w["level_measured_rpm"]) for w in d.values())
        rows.append((name, [e["effect"] for e in doc["effects"]], err["fit alone"],
                     err["diagnosed"], 1000 * on, 100 * lev / target, seconds, d))
    print("| recording | effects named | RMSE fit alone [rpm] | RMSE diagnosed [rpm] | "
          "change | worst onset error [ms] | worst level error [% of target] | time [s] |")
    print("|---|---|---|---|---|---|---|---|")
    for name, eff, a, b, on, lev, sec, _ in rows:
        print(f"| {name} | {', '.join(eff) or 'none'} | {a:.2f} | {b:.2f} | "
              f"{100 * (b - a) / a:+.0f} % | {on:.1f} | {lev:.1f} | {sec:.1f} |")
    for name, *_, d in rows:
        print(name, json.dumps(d))


if __name__ == "__main__":
    main()
