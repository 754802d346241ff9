#!/usr/bin/env python3
"""Does `mecanum-hil fit` + `mecanum-hil diagnose` reproduce a real recording, step by step?

For one recording (or every CSV of a folder with --all), run as a user would, through the CLI:

    python -m mecanum_hil fit REC --robot ROBOT --out fit.toml --no-report
    python -m mecanum_hil diagnose REC --robot ROBOT --calibration fit.toml --out diag.toml --json

then simulate both calibrations on the recording's commands with the library
(``mecanum_hil.prediction.predict``: a recording that starts in motion starts the model in
steady state at its measured speeds, a frozen first reading is not motion) and judge every step
of every measured wheel (``mecanum_hil.identify.steps``), as tests/identify/test_real_logs.py:

* onset: time to 50 % of the step within max(20 % of the measured time, 2 sample periods);
* level: settled level (mean of the last LEVEL_SHARE of the step) within
  max(3 % of the step's target, 1.5 noise levels);
* RMSE: the diagnosed model's wheel RMSE at least 30 % below fit alone, unless fit alone is
  already within 1.5 x the noise level (then the diagnosed model must be within it too).

The noise level is diagnose's ``noise_rpm``. Frozen leading readings (a stale value repeated,
``mecanum_hil.prediction.frozen_start``) are left out of the measured series.

Prints one line per recording and appends one JSON line per recording to --results.

Usage:
    python bench/real_recordings.py REC.csv [--robot ROBOT.toml] [--results out.jsonl]
    python bench/real_recordings.py --all recordings/real/micromouse [--results out.jsonl]
(ROBOT defaults to robot.toml beside the recording.)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

PYTHON = sys.executable


# --------------------------------------------------------------------------- the CLI


class CliError(Exception):
    """A CLI step that crashed or timed out: ``kind`` is ``crash`` or ``timeout``."""

    def __init__(self, kind: str, step: str, message: str):
        super().__init__(f"{step} {kind}: {message}")
        self.kind, self.step, self.message = kind, step, message


def last_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    return lines[-1] if lines else "(no stderr)"


def run_cli(step: str, args: list[str], timeout_s: float, cwd: Path,
            limit_s: float | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m mecanum_hil ARGS`` in its own process group; on timeout the whole group
    (diagnose's worker processes too) is ended."""
    if timeout_s <= 0:
        raise CliError("timeout", step, "no time left")
    proc = subprocess.Popen([PYTHON, "-m", "mecanum_hil", *map(str, args)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the group this call started, by its id
        except ProcessLookupError:
            pass
        proc.communicate()
        raise CliError("timeout", step, f"still running when the {limit_s or timeout_s:.0f} s "
                         "per recording ran out") from None
    if proc.returncode != 0:
        raise CliError("crash", step, f"exit {proc.returncode}: {last_line(err)}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


# --------------------------------------------------------------------------- the data


def moving_average(y: np.ndarray, n: int = 5) -> np.ndarray:
    out = np.full_like(y, np.nan)
    ok = np.isfinite(y)
    v = y[ok]
    if v.size >= n:
        # a centred mean over n samples, over fewer at the ends (no zero padding)
        k = np.convolve(v, np.ones(n), mode="same") / np.convolve(np.ones(v.size), np.ones(n),
                                                                    mode="same")
        out[np.flatnonzero(ok)] = k
    return out


def data_facts(rec, measured_w: np.ndarray, frozen: np.ndarray, steps, targets) -> dict:
    """What the measurement shows, per measured wheel and step: level/target, overshoot,
    settling time (5 % of target band, 5-sample average), creep of the level, duty clamps."""
    from mecanum_hil.identify.steps import LEVEL_SHARE, level
    from mecanum_hil.prediction import initial_wheel_rpm

    t = rec.t_s
    dt = np.diff(t)
    facts: dict = {
        "samples": len(t), "duration_s": round(float(t[-1] - t[0]), 3),
        "period_ms": round(1000 * float(np.median(dt)), 2),
        "max_gap_ms": round(1000 * float(dt.max()), 2),
        "frozen_samples": [int(frozen[:, w].sum()) for w in range(4) if np.isfinite(
            measured_w[:, w]).any() or frozen[:, w].any()],
        "start_rpm": [round(float(v), 1) for v in initial_wheel_rpm(rec)[:2]],
        "steps": [],
    }
    duty = {}
    for name in ("left_duty", "right_duty"):
        if name in rec.extra:
            d = rec.extra_numeric(name)
            d = d[np.isfinite(d)]
            if d.size:
                duty[name] = {"max_abs": float(np.max(np.abs(d))),
                              "at_255_share": round(float(np.mean(np.abs(d) >= 255)), 3),
                              "first": float(d[0])}
    facts["duty"] = duty
    for s in steps:
        y = measured_w[:, s.wheel]
        seg = y[s.start:s.stop]
        tt = t[s.start:s.stop]
        ok = np.isfinite(seg)
        if not ok.any():
            continue
        lv = level(y, s.start, s.stop)
        n = s.stop - s.start
        q = max(math.ceil(LEVEL_SHARE * n), 1)
        third = seg[max(n - 2 * q, 0):n - q]
        third = third[np.isfinite(third)]
        sgn = 1.0 if s.target_rpm >= s.before_rpm else -1.0
        peak = float(np.nanmax(sgn * seg)) * sgn
        span = abs(lv - s.before_rpm) if abs(lv - s.before_rpm) > 1e-9 else math.nan
        ma = moving_average(seg)
        band = 0.05 * abs(s.target_rpm)
        out = np.flatnonzero(np.isfinite(ma) & (np.abs(ma - lv) > band))
        settle = float(tt[out[-1]] - tt[0]) if out.size else 0.0
        out10 = np.flatnonzero(np.isfinite(ma) & (np.abs(ma - lv) > 2 * band))
        settle10 = float(tt[out10[-1]] - tt[0]) if out10.size else 0.0
        late = ma[n // 2:]
        late = late[np.isfinite(late)]
        half = seg[n // 2:]
        th = tt[n // 2:][np.isfinite(half)]
        slope = (float(np.polyfit(th, half[np.isfinite(half)], 1)[0])
                 if th.size > 3 else math.nan)
        facts["steps"].append({
            "wheel": s.wheel + 1, "step": s.index + 1, "target_rpm": s.target_rpm,
            "level_rpm": round(lv, 2),
            "level_pct_of_target": round(100 * lv / s.target_rpm, 1) if s.target_rpm else None,
            "peak_rpm": round(peak, 2),
            "overshoot_pct": (round(100 * sgn * (peak - lv) / span, 1) if math.isfinite(span)
                              else None),
            "settling_s_5pct": round(settle, 3),
            "settling_s_10pct": round(settle10, 3),
            "second_half_pp_rpm": round(float(np.ptp(late)), 1) if late.size else None,
            "level_creep_rpm": (round(lv - float(third.mean()), 2) if third.size else None),
            "second_half_slope_rpm_per_s": round(slope, 1) if math.isfinite(slope) else None,
        })
    return facts


# --------------------------------------------------------------------------- the judgement


def fmt_params(p: dict) -> str:
    parts = []
    for k, v in p.items():
        if isinstance(v, list):
            parts.append(f"{k}=[" + ",".join(f"{x:.3g}" for x in v
                                             if not (k == "gains" and x == 1.0)) + "]")
        elif isinstance(v, (int, float)):
            parts.append(f"{k}={v:.4g}")
        else:
            parts.append(f"{k}={v}")
    return ",".join(parts)


def evaluate(rec_path: Path, robot_path: Path, timeout_s: float, keep: Path | None) -> dict:
    from mecanum_hil.identify.regimes import wheel_targets
    from mecanum_hil.identify.steps import split_steps, step_figures
    from mecanum_hil.io.recording import read_recording
    from mecanum_hil.model import load_calibration, load_robot_profile
    from mecanum_hil.prediction import frozen_start, predict, without_frozen_start

    t0 = time.monotonic()
    name = rec_path.stem
    res: dict = {"name": name, "recording": str(rec_path), "robot": str(robot_path)}
    work = keep.resolve() / name if keep else Path(tempfile.mkdtemp(prefix=f"eval-{name}-"))
    work.mkdir(parents=True, exist_ok=True)
    fit_toml, diag_toml = work / "fit.toml", work / "diag.toml"

    run_cli("fit", ["fit", rec_path, "--robot", robot_path, "--out", fit_toml, "--no-report"],
            timeout_s - (time.monotonic() - t0), work, timeout_s)
    res["fit_s"] = round(time.monotonic() - t0, 1)
    d = run_cli("diagnose", ["diagnose", rec_path, "--robot", robot_path, "--calibration",
                             fit_toml, "--out", diag_toml, "--json"],
                timeout_s - (time.monotonic() - t0), work, timeout_s)
    res["diagnose_s"] = round(time.monotonic() - t0 - res["fit_s"], 1)
    doc = json.loads(d.stdout)
    (work / "diag.json").write_text(d.stdout)
    noise = float(doc["noise_rpm"])
    res["effects"] = [{"effect": e["effect"], "parameters": e["parameters"]}
                      for e in doc["effects"]]
    res["unexplained"] = doc["unexplained"]
    res["explained_share"] = doc.get("explained_share")
    res["diagnose_rmse"] = {k: doc[k] for k in ("rmse_initial", "rmse_baseline", "rmse_final",
                                                 "rmse_reference")}

    rec = read_recording(rec_path)
    robot = load_robot_profile(robot_path)
    preds = {"fit": predict(rec, load_calibration(fit_toml), robot, source=str(rec_path)),
             "diagnosed": predict(rec, load_calibration(diag_toml), robot, source=str(rec_path))}
    frozen = frozen_start(rec)
    measured = np.asarray(without_frozen_start(rec).wheel_rpm, dtype=float)
    wheels = [w for w in range(4) if np.isfinite(measured[:, w]).any()]
    targets = wheel_targets(rec, robot)
    t = rec.t_s
    period = float(np.median(np.diff(t)))

    # RMSE over the measured samples (frozen leading readings left out)
    mask = np.isfinite(measured)
    rmse = {k: float(np.sqrt(np.mean((measured[mask] - np.asarray(p.wheel_rpm)[mask]) ** 2)))
            for k, p in preds.items()}
    res["rmse"] = {"fit": round(rmse["fit"], 3), "diagnosed": round(rmse["diagnosed"], 3),
                   "noise": round(noise, 3)}
    reasons = []
    if rmse["fit"] > 1.5 * noise:
        rmse_ok = rmse["diagnosed"] <= 0.7 * rmse["fit"]
        if not rmse_ok:
            reasons.append(f"RMSE {rmse['diagnosed']:.2f} only "
                           f"{100 * (1 - rmse['diagnosed'] / rmse['fit']):.0f}% below fit "
                           f"{rmse['fit']:.2f} (needs 30%; noise {noise:.2f})")
    else:
        rmse_ok = rmse["diagnosed"] <= 1.5 * noise
        if not rmse_ok:
            reasons.append(f"RMSE {rmse['diagnosed']:.2f} above 1.5 x noise {noise:.2f}")

    steps = split_steps(t, targets, wheels)
    rows = []
    for w in wheels:
        mine = [s for s in steps if s.wheel == w]
        me = step_figures(t, measured[:, w], mine, noise)
        di = step_figures(t, np.where(mask[:, w], np.asarray(preds["diagnosed"].wheel_rpm)[:, w],
                                      np.nan), mine, noise)
        fi = step_figures(t, np.where(mask[:, w], np.asarray(preds["fit"].wheel_rpm)[:, w],
                                      np.nan), mine, noise)
        for s, m, g, f in zip(mine, me, di, fi, strict=True):
            where = f"w{w + 1}s{s.index + 1}"
            tol_t = max(0.2 * m.t50_s, 2 * period) if math.isfinite(m.t50_s) else math.nan
            if math.isfinite(m.t50_s):
                dt50 = g.t50_s - m.t50_s
                onset_ok = math.isfinite(dt50) and abs(dt50) <= tol_t
            else:
                dt50, onset_ok = math.nan, True  # no measured onset: not judged
            tol_l = max(0.03 * abs(s.target_rpm), 1.5 * noise)
            dl = g.level_rpm - m.level_rpm
            level_ok = math.isfinite(dl) and abs(dl) <= tol_l
            if not onset_ok:
                reasons.append(f"onset {where}: {1000 * g.t50_s:.0f} ms vs measured "
                               f"{1000 * m.t50_s:.0f} ms (tol {1000 * tol_t:.0f})")
            if not level_ok:
                reasons.append(f"level {where}: {g.level_rpm:.1f} vs measured "
                               f"{m.level_rpm:.1f} rpm (tol {tol_l:.1f})")
            rows.append({"wheel": w + 1, "step": s.index + 1, "target_rpm": s.target_rpm,
                         "t_start_s": s.t_start_s,
                         "measured": {"t50_ms": 1000 * m.t50_s, "level_rpm": m.level_rpm},
                         "diagnosed": {"t50_ms": 1000 * g.t50_s, "level_rpm": g.level_rpm},
                         "fit": {"t50_ms": 1000 * f.t50_s, "level_rpm": f.level_rpm},
                         "onset_err_ms": 1000 * dt50, "onset_tol_ms": 1000 * tol_t,
                         "level_err_rpm": dl, "level_err_pct": 100 * dl / abs(s.target_rpm)
                         if s.target_rpm else math.nan, "level_tol_rpm": tol_l,
                         "onset_ok": onset_ok, "level_ok": level_ok})
    res["steps"] = rows
    onset_errs = [abs(r["onset_err_ms"]) for r in rows if math.isfinite(r["onset_err_ms"])]
    level_errs = [abs(r["level_err_pct"]) for r in rows if math.isfinite(r["level_err_pct"])]
    res["worst_onset_err_ms"] = max(onset_errs) if onset_errs else None
    res["worst_level_err_pct"] = max(level_errs) if level_errs else None
    timed = sum(math.isfinite(r["measured"]["t50_ms"]) for r in rows)
    if rows and timed < 0.5 * len(rows):
        reasons.append(f"only {timed} of {len(rows)} steps have a measured onset")
    if not rows:
        reasons.append("no step found in the wheel targets")
    res["reproduced"] = not reasons
    res["reasons"] = reasons
    res["data"] = data_facts(rec, measured, frozen, steps, targets)
    res["seconds"] = round(time.monotonic() - t0, 1)
    res["workdir"] = str(work)
    return res


def clean(o):
    """JSON-safe: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(o, dict):
        return {k: clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    if isinstance(o, (np.floating, float)):
        v = float(o)
        return v if math.isfinite(v) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def line(res: dict) -> str:
    if res.get("status") != "ok":
        return f"{res['name']:<26} {res['status'].upper()}: {res.get('error')}"
    eff = "; ".join(f"{e['effect']}({fmt_params(e['parameters'])})"
                    for e in res["effects"]) or "none"
    r = res["rmse"]
    wo = res["worst_onset_err_ms"]
    wl = res["worst_level_err_pct"]
    s = (f"{res['name']:<26} reproduced={'yes' if res['reproduced'] else 'no':<3} "
         f"RMSE fit/diag/noise={r['fit']:.2f}/{r['diagnosed']:.2f}/{r['noise']:.2f} "
         f"worst onset={'-' if wo is None else f'{wo:.0f}ms'} "
         f"worst level={'-' if wl is None else f'{wl:.1f}%'} effects: {eff}")
    if res["reasons"]:
        more = f" (+{len(res['reasons']) - 2} more)" if len(res["reasons"]) > 2 else ""
        s += " | why: " + "; ".join(res["reasons"][:2]) + more
    return s


def run_one(rec: Path, robot: Path | None, timeout_s: float, keep: Path | None) -> dict:
    rec = rec.resolve()
    robot = (robot or rec.parent / "robot.toml").resolve()
    try:
        res = evaluate(rec, robot, timeout_s, keep)
        res["status"] = "ok"
    except CliError as e:
        res = {"name": rec.stem, "recording": str(rec), "robot": str(robot),
               "status": e.kind, "step": e.step, "error": f"{e.step}: {e.message}"}
    except Exception as e:  # the harness's own failure: one line, not a traceback
        tb = traceback.extract_tb(e.__traceback__)[-1]
        res = {"name": rec.stem, "recording": str(rec), "robot": str(robot), "status": "error",
               "error": f"{type(e).__name__}: {e} ({Path(tb.filename).name}:{tb.lineno})"}
    return clean(res)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", nargs="?", type=Path)
    ap.add_argument("--all", type=Path, metavar="DIR", help="every *.csv of DIR, one at a time")
    ap.add_argument("--robot", type=Path, help="robot profile (default: robot.toml beside "
                                                 "the recording)")
    ap.add_argument("--results", type=Path, help="append one JSON line per recording here")
    ap.add_argument("--timeout", type=float, default=600.0,
                    help="seconds per recording, fit and diagnose together (default 600)")
    ap.add_argument("--keep", type=Path, help="keep fit.toml/diag.toml/diag.json in KEEP/<name>/")
    a = ap.parse_args(argv)
    if (a.recording is None) == (a.all is None):
        ap.error("give one recording or --all DIR")
    recs = sorted(a.all.glob("*.csv")) if a.all else [a.recording]
    n_ok = 0
    for rec in recs:
        res = run_one(rec, a.robot, a.timeout, a.keep)
        print(line(res), flush=True)
        n_ok += bool(res.get("reproduced"))
        if a.results:
            with open(a.results, "a") as f:
                f.write(json.dumps(res) + "\n")
    print(f"{n_ok} of {len(recs)} reproduced", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
