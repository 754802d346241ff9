"""Lab logs judged step by step, from robots whose physics is NOT the project's model.

The lab logs of tests/identify/test_real_logs.py and bench/staircase_steps.py are made with the
project's own simulator, so ``import -> fit -> diagnose -> simulate`` reproducing them proves
little. Here every log comes from an independent numpy plant (nothing of
``mecanum_hil.model`` is used for the truth):

* per wheel a brushed DC motor: armature resistance R, inductance L (electrical time constant
  0.25-1.5 ms), torque / back-EMF constant, rotor + reflected load inertia, viscous AND Coulomb
  friction (stiction: a wheel at rest stays at rest until the motor torque exceeds it), a small
  cogging torque, a gearbox;
* a drive whose voltage is ``duty x battery``, the duty clipped at +-1 (so +-battery);
* a discrete firmware speed loop at the log's rate (PI with conditional-integration anti-windup,
  or P-only; optionally a set-point deadband), reading the speed as encoder counts per period
  (quantised: counts_per_rev x gear) or from a tachometer through a 12-bit ADC with noise;
* the motor integrated with a 20 us step between controller ticks (exact exponential for the
  current, semi-implicit Euler for the speed, Coulomb friction with sticking).

Logs, each written as a lab would write it and imported with a MAP.toml:

a) small fast motor, 1 kHz PI, at the target in 10-20 ms, whitespace text with a `%` header,
   time in s at 1 ms resolution (host clock drifting against the firmware's: a few repeated
   stamps), two wheels, 20-step signed staircase with reversals (16 -> -30 rad/s), the high
   steps running into the battery (settling ~3 % below 30 rad/s);
b) four-wheel robot at 500 Hz, headerless CSV in rad/s, no time column (2 ms period), encoder
   readings quantised in 0.23 rad/s steps, four per-wheel set-points (form 3 of the map);
c) P-only loop (level ~85 % of every target), CSV with a units row, time in ms, speeds in rpm,
   tachometer + ADC noise;
d) firmware deadband (|set-point| < 1.5 rad/s -> duty 0), tab-separated, a wrapping uint32 us
   counter for time, speeds in counts/s;
e) the robot of (a) on the floor (body inertia, more friction) -- compared with (a) in the air.

For each log the CLI runs as a user runs it (``import --map``, ``fit --no-report``,
``diagnose --json``, ``simulate`` with the fit alone and with the diagnosed calibration), every
command timed; then every step is judged as tests/identify/test_real_logs.py judges it
(:func:`mecanum_hil.identify.steps.step_table`): time to 50 % within max(20 % of the measured,
2 samples), level within max(3 % of the target, 1.5 noise sd), wheel RMSE 30 % below the fit
alone unless that is within 1.5 x noise, and the effects named. Nothing is asserted: a table of
pass/fail per criterion is printed. The noise sd used is the logged speed's deviation from the
plant's true mean speed over each sample period (quantisation + sensor noise), in rpm;
diagnose's own estimate is printed beside it.

Run: ``.venv/bin/python bench/foreign_plants.py [--only a,b] [--keep DIR]`` (``--keep``: write
the logs, maps, recordings and calibrations under DIR and leave them there).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RAD_S_PER_RPM = 2.0 * math.pi / 60.0
ROBOT_TOML = """[robot]
name = "small-lab-robot"
wheel_radius_m = 0.03
lx_plus_ly_m = 0.15
body_length_m = 0.2
body_width_m = 0.2
mass_kg = 2.0

[limits]
wheel_speed_max_rpm = 600.0
"""
K_ROBOT = 0.15 / 0.03  # (lx + ly) / r of ROBOT_TOML
SUB_DT = 20e-6  # [s] integration step of the plant
STAIRCASE = [4, 8, 12, 16, -30, -20, -10, 0, 6, 16, 24, 30, 16, -30, -16, -8, 0, 10, 20, 5]


# --------------------------------------------------------------------------- the plant


@dataclass(frozen=True)
class Motor:
    """One brushed DC motor + gearbox + load, motor side except ``gear`` [SI units]."""

    R: float  # armature resistance [ohm]
    L: float  # inductance [H]
    K: float  # torque constant = back-EMF constant [N m / A] = [V s / rad]
    J: float  # rotor + reflected load inertia [kg m^2]
    b: float  # viscous friction [N m s / rad]
    Tc: float  # Coulomb friction [N m]
    gear: float  # motor turns per wheel turn [-]
    cog: float = 0.0  # cogging torque amplitude [N m]
    cog_n: int = 6  # cogging periods per motor turn


@dataclass(frozen=True)
class Firmware:
    """The speed loop: duty = Kp e + I (duty per wheel rad/s), at period ``T``."""

    T: float  # controller / log period [s]
    Kp: float
    Ki: float  # [duty / rad]; 0: P-only
    vbat: float  # battery [V]
    sensor: str = "encoder"  # "encoder" (counts per period) or "tach" (ADC, with noise)
    cpr: int = 4096  # encoder counts per motor turn (quadrature)
    tach_sd: float = 0.0  # tachometer noise [wheel rad/s]
    adc_step: float = 0.0  # ADC resolution [wheel rad/s]
    deadband: float = 0.0  # |set-point| below this [wheel rad/s] -> duty 0, integral reset


def steady_top_speed(m: Motor, vbat: float) -> float:
    """Wheel speed at full battery voltage [rad/s] (steady state, no cogging)."""
    return (m.K * vbat / m.R - m.Tc) / (m.K * m.K / m.R + m.b) / m.gear


def run_plant(sp: np.ndarray, motors: list[Motor], fw: Firmware, rng: np.random.Generator):
    """Closed-loop simulation of each wheel.

    Parameters
    ----------
    sp : ndarray (N, W)
        Wheel set-points [rad/s] in force from each controller tick.

    Returns
    -------
    meas : ndarray (N, W)
        What the firmware read at each tick and logs [wheel rad/s].
    true_mean : ndarray (N, W)
        The true mean wheel speed over the period that ended at each tick [rad/s].
    duty : ndarray (N, W)
    """
    n_tick, n_w = sp.shape
    n_sub = round(fw.T / SUB_DT)
    h = fw.T / n_sub
    meas = np.zeros((n_tick, n_w))
    true_mean = np.zeros((n_tick, n_w))
    duties = np.zeros((n_tick, n_w))
    two_pi = 2.0 * math.pi
    for w in range(n_w):
        m = motors[w]
        a_el = math.exp(-h * m.R / m.L)
        R, K, J, b, Tc, cog, cn = m.R, m.K, m.J, m.b, m.Tc, m.cog, m.cog_n
        i = om = 0.0
        th = float(rng.uniform(0.0, two_pi))  # encoder offset
        cnt_prev = math.floor(th * fw.cpr / two_pi)
        th_prev = th
        integ = 0.0
        k_counts = two_pi / (fw.cpr * m.gear * fw.T)
        noise = rng.normal(0.0, fw.tach_sd, n_tick) if fw.tach_sd > 0 else np.zeros(n_tick)
        spw = sp[:, w]
        for k in range(n_tick):
            # --- the firmware's tick: read the speed, compute and apply the duty
            if fw.sensor == "encoder":
                cnt = math.floor(th * fw.cpr / two_pi)
                y = (cnt - cnt_prev) * k_counts
                cnt_prev = cnt
            else:
                true_inst = om / m.gear
                y = true_inst + noise[k]
                if fw.adc_step > 0:
                    y = round(y / fw.adc_step) * fw.adc_step
            true_mean[k, w] = ((th - th_prev) / (m.gear * fw.T) if k else 0.0) \
                if fw.sensor == "encoder" else true_inst
            th_prev = th
            meas[k, w] = y
            s = spw[k]
            if abs(s) < fw.deadband:
                duty, integ = 0.0, 0.0
            else:
                e = s - y
                u = fw.Kp * e + integ
                duty = min(1.0, max(-1.0, u))
                # conditional integration: not while the clip holds the error back
                if fw.Ki and (duty == u or (u > 0) != (e > 0)):
                    integ += fw.Ki * fw.T * e
            duties[k, w] = duty
            v = duty * fw.vbat
            # --- the motor between ticks
            for _ in range(n_sub):
                i_inf = (v - K * om) / R
                i = i_inf + (i - i_inf) * a_el
                tq = K * i + (cog * math.sin(cn * th) if cog else 0.0)
                if om == 0.0:
                    if abs(tq) <= Tc:
                        continue  # stuck
                    om = h / J * (tq - math.copysign(Tc, tq))
                else:
                    new = om + h / J * (tq - b * om - math.copysign(Tc, om))
                    om = 0.0 if (new > 0) != (om > 0) else new
                th += om * h
    return meas, true_mean, duties


def staircase(levels, step_s: float, period_s: float, lead_s: float = 0.1) -> np.ndarray:
    n_lead, n_step = round(lead_s / period_s), round(step_s / period_s)
    return np.concatenate([np.zeros(n_lead)] + [np.full(n_step, v, float) for v in levels])


# --------------------------------------------------------------------------- the robots

#: small fast motor, wheel in the air (a): tau_e 0.25 ms, tau_m 4 ms, 10:1, 4096 counts/turn
SMALL_AIR = Motor(R=2.0, L=0.5e-3, K=0.02, J=8e-7, b=1e-6, Tc=1.5e-4, gear=10.0,
                  cog=3e-5)
#: the same on the floor (e): + a quarter of the 2 kg body at r = 3 cm, rolling / roller friction
SMALL_FLOOR = replace(SMALL_AIR, J=8e-7 + 0.5 * 0.03 ** 2 / 10.0 ** 2, b=5e-6, Tc=1.5e-3)


def _vbat_for_top(m: Motor, top_wheel_rad_s: float) -> float:
    return (top_wheel_rad_s * m.gear * (m.K * m.K / m.R + m.b) + m.Tc) * m.R / m.K


SMALL_VBAT = _vbat_for_top(SMALL_AIR, 29.1)  # the battery ceiling of (a): 3 % below 30 rad/s
SMALL_FW = Firmware(T=0.001, Kp=0.028, Ki=7.0, vbat=SMALL_VBAT, cpr=4096)


def _spread(m: Motor, n: int, rng: np.random.Generator) -> list[Motor]:
    """``n`` motors of one type with manufacturing spread (R +-5 %, friction +-20 %)."""
    return [replace(m, R=m.R * rng.uniform(0.95, 1.05), Tc=m.Tc * rng.uniform(0.8, 1.2),
                    b=m.b * rng.uniform(0.8, 1.2)) for _ in range(n)]


@dataclass
class Log:
    """One generated lab log: the file, its map, and what is known about it."""

    key: str
    title: str
    file: str
    text: str
    map_toml: str
    noise_rpm: float  # sd of the logged speed about the true period mean [rpm]
    expect: dict  # effect -> description of the expected parameter
    notes: list[str] = field(default_factory=list)
    gen_s: float = 0.0


def _noise_rpm(meas: np.ndarray, true_mean: np.ndarray) -> float:
    d = (meas - true_mean)[1:]
    return float(np.std(d)) / RAD_S_PER_RPM


def _host_stamps(n: int, period: float, rng: np.random.Generator) -> np.ndarray:
    """Stamps a host writes [s]: a ms clock 300 ppm slow against the firmware's, jitter
    2 us, truncated to 1 ms (so a few stamps repeat and a few skip)."""
    t = np.arange(n) * period * (1.0 - 3e-4) + 0.3405 + rng.normal(0.0, 2e-6, n)
    return np.floor(t * 1000.0 + 1e-6) / 1000.0


def _whitespace_two_wheels(key, title, motors, levels, rng, notes) -> Log:
    fw = SMALL_FW
    s = staircase(levels, 0.3, fw.T)
    sp = np.repeat(s[:, None], len(motors), 1)
    meas, tm, duty = run_plant(sp, motors, fw, rng)
    stamps = _host_stamps(s.size, fw.T, rng)
    rep = int(np.sum(np.diff(stamps) <= 0))
    lines = ["% lab B speed test", "% time_s  setpoint  w_left  w_right"]
    lines += [f"{a:.3f} {b:.1f} {c:.4f} {d:.4f}"
              for a, b, c, d in zip(stamps, s, meas[:, 0], meas[:, 1], strict=True)]
    tops = [steady_top_speed(m, fw.vbat) for m in motors]
    top_txt = ", ".join(f"{x:.2f}" for x in tops)
    notes = [*notes, f"{rep} repeated stamps",
             f"steady top speed at full battery {top_txt} rad/s",
             f"duty clipped on {100 * np.mean(np.abs(duty) >= 1):.1f} % of ticks"]
    map_toml = """[time]
column = "time_s"
unit = "s"
[wheels]
wheel1 = { column = "w_left", unit = "rad/s" }
wheel2 = { column = "w_right", unit = "rad/s" }
[commands]
setpoint = { column = "setpoint", unit = "rad/s" }
"""
    return Log(key, title, "log.txt", "\n".join(lines) + "\n", map_toml, _noise_rpm(meas, tm),
               {"saturation": f"top ~{min(tops):.2f}-{max(tops):.2f} rad/s "
                f"({min(tops) / RAD_S_PER_RPM:.0f}-{max(tops) / RAD_S_PER_RPM:.0f} rpm)"}, notes)


def make_a(rng) -> Log:
    motors = _spread(SMALL_AIR, 2, rng)
    return _whitespace_two_wheels("a", "small fast motor, 1 kHz PI, whitespace, battery ceiling",
                                  motors, STAIRCASE, rng, [])


def make_e(rng) -> Log:
    motors = _spread(SMALL_FLOOR, 2, rng)
    return _whitespace_two_wheels("e", "robot (a) on the floor (J x6.6, friction x5-10)",
                                  motors, STAIRCASE, rng, [])


def make_b(rng) -> Log:
    """Four wheels, 500 Hz, headerless CSV, 0.23 rad/s encoder steps, per-wheel set-points."""
    gear = 2.0 * math.pi / (4096 * 0.23 * 0.002)  # 3.335: a belt
    base = Motor(R=1.0, L=1.5e-3, K=0.03, J=3e-6 + (1e-4 + 4.5e-4) / gear ** 2, b=2e-5,
                 Tc=5e-3, gear=gear, cog=5e-4)
    motors = _spread(base, 4, rng)
    fw = Firmware(T=0.002, Kp=0.03, Ki=0.6, vbat=12.0, cpr=4096)
    pattern = [(6, 6, 6, 6), (14, 14, 14, 14), (20, 20, 20, 20), (-10, 10, 10, -10),
               (-8, 8, -8, 8), (6, 14, 6, 14), (-12, -12, -12, -12), (0, 0, 0, 0),
               (0, 16, 16, 0), (20, 20, 20, 20)]
    n_lead, n_step = 50, 200
    sp = np.concatenate([np.zeros((n_lead, 4))] + [np.tile(np.array(p, float), (n_step, 1))
                                                    for p in pattern])
    meas, tm, _ = run_plant(sp, motors, fw, rng)
    lines = [",".join(f"{x:.2f}" for x in row) for row in np.hstack([sp, meas])]
    map_toml = ("[time]\nperiod_s = 0.002\n[wheels]\n"
                + "".join(f'wheel{i} = {{ column = {3 + i}, unit = "rad/s" }}\n'
                          for i in range(1, 5))
                + "[commands]\n"
                + "".join(f'wheel{i} = {{ column = {i - 1}, unit = "rad/s" }}\n'
                          for i in range(1, 5))
                + f"k = {K_ROBOT}\n")
    tops = [steady_top_speed(m, fw.vbat) for m in motors]
    return Log("b", "four wheels, 500 Hz, headerless CSV, 0.23 rad/s steps", "log.csv",
               "\n".join(lines) + "\n", map_toml, _noise_rpm(meas, tm), {},
               [f"quantum {2 * math.pi / (4096 * gear * 0.002):.4f} rad/s",
                f"steady top speed {min(tops):.0f} rad/s (no ceiling reached)"])


def make_c(rng) -> Log:
    """P-only loop, ~85 % of each target; CSV with units row, ms, rpm; tach + ADC."""
    m0 = Motor(R=1.5, L=1.0e-3, K=0.025, J=2e-5, b=3e-6, Tc=3e-4, gear=20.0, cog=5e-5)
    motors = _spread(m0, 2, rng)
    loop_gain = 0.85 / 0.15
    kp = loop_gain * m0.K * m0.gear / 12.0  # duty per rad/s: level = g / (1 + g) target
    fw = Firmware(T=0.001, Kp=kp, Ki=0.0, vbat=12.0, sensor="tach", tach_sd=0.05,
                  adc_step=80.0 / 4096)
    levels = [4, 8, 12, 16, -16, -8, 0, 10, 20, 5]
    s = staircase(levels, 0.4, fw.T)
    sp = np.repeat(s[:, None], 2, 1)
    meas, tm, _ = run_plant(sp, motors, fw, rng)
    rpm = meas / RAD_S_PER_RPM
    t_ms = 120000 + np.arange(s.size)  # ms since boot
    lines = ["time,cmd,left,right", "ms,rpm,rpm,rpm"]
    lines += [f"{a},{b / RAD_S_PER_RPM:.2f},{c:.3f},{d:.3f}"
              for a, b, c, d in zip(t_ms, s, rpm[:, 0], rpm[:, 1], strict=True)]
    ratios = []  # steady state: 12 kp K / R (v - y) = (K^2 / R + b) gear y + Tc
    for v in levels:
        for mtr in motors if v else ():
            a = kp * 12.0 * mtr.K / mtr.R
            c = (mtr.K ** 2 / mtr.R + mtr.b) * mtr.gear
            ratios.append((a * abs(v) - mtr.Tc) / (a + c) / abs(v))
    map_toml = """[time]
column = "time"
unit = "ms"
[wheels]
wheel1 = { column = "left", unit = "rpm" }
wheel2 = { column = "right", unit = "rpm" }
[commands]
setpoint = { column = "cmd", unit = "rpm" }
"""
    return Log("c", "P-only loop (~85 %), CSV + units row, ms, rpm, tach + ADC", "log.csv",
               "\n".join(lines) + "\n", map_toml, _noise_rpm(meas, tm),
               {"proportional_only": f"level ratio {min(ratios):.3f}-{max(ratios):.3f}"},
               [f"Kp {kp:.3f} duty/(rad/s), loop gain {loop_gain:.2f}"])


def make_d(rng) -> Log:
    """Deadband firmware, 1 kHz, tab-separated, uint32 us counter wrapping, counts/s."""
    motors = _spread(SMALL_AIR, 2, rng)
    fw = replace(SMALL_FW, deadband=1.5)
    levels = [1.0, 4, 8, 1.2, -1.0, -6, 0, 10]
    s = staircase(levels, 0.3, fw.T)
    sp = np.repeat(s[:, None], 2, 1)
    meas, tm, _ = run_plant(sp, motors, fw, rng)
    cpr_wheel = fw.cpr * SMALL_AIR.gear
    cps = np.rint(meas * cpr_wheel / (2 * math.pi)).astype(int)  # counts per second
    us = (2 ** 32 - 1_200_000 + np.arange(s.size) * 1000
          + rng.integers(-3, 4, s.size)) % 2 ** 32
    lines = ["micros\tsp_rad_s\tenc_l\tenc_r"]
    lines += [f"{a}\t{b:.2f}\t{c}\t{d}" for a, b, c, d in zip(us, s, cps[:, 0], cps[:, 1],
                                                             strict=True)]
    map_toml = f"""[time]
column = "micros"
unit = "us"
[wheels]
counts_per_rev = {cpr_wheel:g}
wheel1 = {{ column = "enc_l", unit = "counts/s" }}
wheel2 = {{ column = "enc_r", unit = "counts/s" }}
[commands]
setpoint = {{ column = "sp_rad_s", unit = "rad/s" }}
"""
    return Log("d", "deadband 1.5 rad/s, tab, wrapping us counter, counts/s", "log.tsv",
               "\n".join(lines) + "\n", map_toml, _noise_rpm(meas, tm),
               {"deadband": f"between 1.2 and 4 rad/s ({1.2 / RAD_S_PER_RPM:.1f}-"
                f"{4 / RAD_S_PER_RPM:.1f} rpm)"},
               ["micros wraps 1.2 s into the log"])


MAKERS = {"a": make_a, "b": make_b, "c": make_c, "d": make_d, "e": make_e}


# --------------------------------------------------------------------------- the loop


@dataclass
class Cmd:
    args: list
    rc: int
    seconds: float
    stdout: str
    stderr: str


def cli(*args) -> Cmd:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "mecanum_hil", *map(str, args)],
                       capture_output=True, text=True, timeout=1800, cwd=ROOT)
    return Cmd([str(a) for a in args], r.returncode, time.perf_counter() - t0, r.stdout,
               r.stderr)


def run_loop(d: Path, log: Log, extra_cal: Path | None = None) -> dict:
    """import -> fit -> diagnose -> simulate (fit alone, diagnosed); records every command."""
    (d / log.file).write_text(log.text)
    (d / "map.toml").write_text(log.map_toml)
    (d / "robot.toml").write_text(ROBOT_TOML)
    rec, robot = d / "rec.csv", d / "robot.toml"
    out: dict = {"cmds": {}, "failed": []}

    def step(name, *args) -> Cmd | None:
        c = cli(*args)
        out["cmds"][name] = c
        if c.rc != 0:
            out["failed"].append((name, c))
            return None
        return c

    if not step("import", "import", d / log.file, "--map", d / "map.toml", "--out", rec):
        return out
    out["import_warnings"] = [ln for ln in (out["cmds"]["import"].stdout
                                            + out["cmds"]["import"].stderr).splitlines()
                              if "warning" in ln.lower()]
    if not step("fit", "fit", rec, "--robot", robot, "-o", d / "fit.toml", "--no-report"):
        return out
    dg = step("diagnose", "diagnose", rec, "--robot", robot, "-c", d / "fit.toml", "-o",
              d / "diag.toml", "--json")
    if dg is not None:
        try:
            out["doc"] = json.loads(dg.stdout)
        except json.JSONDecodeError as exc:
            out["failed"].append(("diagnose --json parse", Cmd([], 0, 0, dg.stdout[:500],
                                                               str(exc))))
    cals = [("fit alone", d / "fit.toml")]
    if (d / "diag.toml").exists():
        cals.append(("diagnosed", d / "diag.toml"))
    if extra_cal is not None and extra_cal.exists():
        cals.append(("(a)'s diagnosed", extra_cal))
    for label, cal in cals:
        sim = d / f"sim-{label.replace(' ', '-').replace(chr(39), '')}.csv"
        if step(f"simulate {label}", "simulate", "--commands", rec, "--robot", robot, "-c",
                cal, "-o", sim):
            out.setdefault("sims", {})[label] = sim
    return out


def judge(d: Path, log: Log, res: dict) -> dict:
    """The per-step criteria (tests/identify/test_real_logs.py, check_every_step)."""
    from mecanum_hil.identify.regimes import wheel_targets
    from mecanum_hil.identify.steps import step_table
    from mecanum_hil.io.recording import read_recording
    from mecanum_hil.model import load_robot_profile

    robot = load_robot_profile(d / "robot.toml")
    measured = read_recording(d / "rec.csv")
    preds = {k: read_recording(p) for k, p in res.get("sims", {}).items()}
    noise = log.noise_rpm
    j: dict = {"noise": noise}
    err = {k: float(np.sqrt(np.nanmean((measured.wheel_rpm - p.wheel_rpm) ** 2)))
           for k, p in preds.items()}
    j["rmse"] = err
    if "diagnosed" not in preds:
        return j
    rows = step_table(measured.t_s, wheel_targets(measured, robot),
                      {"measured": measured.wheel_rpm,
                       **{k: p.wheel_rpm for k, p in preds.items()}}, noise)
    period = float(np.median(np.diff(measured.t_s)))
    j["rows"] = rows
    j["period"] = period
    for lab in [k for k in preds if k != "(a)'s diagnosed"]:
        worst_t = worst_l = (0.0, None, 0.0, 0.0, 0.0)
        bad_t = bad_l = timed = 0
        for r in rows:
            me, di = r.figures["measured"], r.figures[lab]
            if math.isfinite(me.t50_s):
                timed += 1
                tol = max(0.2 * me.t50_s, 2 * period)
                e = abs(di.t50_s - me.t50_s) if math.isfinite(di.t50_s) else math.inf
                bad_t += e > tol
                if e / tol > worst_t[0]:
                    worst_t = (e / tol, r, me.t50_s, di.t50_s, tol)
            tol = max(0.03 * abs(r.step.target_rpm), 1.5 * noise)
            e = abs(di.level_rpm - me.level_rpm)
            bad_l += not e <= tol
            if not e <= worst_l[0] * tol:
                worst_l = (e / tol if math.isfinite(e) else math.inf, r, me.level_rpm,
                           di.level_rpm, tol)
        j[lab] = {"bad_t": bad_t, "bad_l": bad_l, "timed": timed, "n": len(rows),
                  "worst_t": worst_t, "worst_l": worst_l}
    fa, dg = err.get("fit alone", math.nan), err.get("diagnosed", math.nan)
    if fa > 1.5 * noise:
        j["rmse_ok"] = dg <= 0.7 * fa
        j["rmse_rule"] = f"diag <= 0.7 x fit ({0.7 * fa:.3f})"
    else:
        j["rmse_ok"] = dg <= 1.5 * noise
        j["rmse_rule"] = f"fit within 1.5 noise: diag <= {1.5 * noise:.3f}"
    return j


def effects_check(log: Log, doc: dict | None) -> tuple[bool, str]:
    if doc is None:
        return False, "no diagnosis"
    names = [e["effect"] for e in doc["effects"]]
    ok = True
    msgs = []
    for eff in log.expect:
        if eff == "proportional_only":
            hit = "proportional_only" in names or "wheel_gain" in names
        else:
            hit = eff in names
        ok &= hit
        msgs.append(f"{eff}: {'named' if hit else 'MISSING'}")
    if not log.expect:
        msgs.append("none expected")
    return ok, "; ".join(msgs)


def _where(r) -> str:
    if r is None:
        return "-"
    return (f"w{r.step.wheel + 1} s{r.step.index + 1} ({r.step.before_rpm:.4g}->"
            f"{r.step.target_rpm:.4g} rpm)")


def report(log: Log, res: dict, j: dict | None) -> list[str]:
    out = [f"\n=== ({log.key}) {log.title}", f"  generated in {log.gen_s:.1f} s; "
           + "; ".join(log.notes)]
    for name, c in res["cmds"].items():
        out.append(f"  {name:<28s} rc={c.rc} {c.seconds:6.1f} s")
    for w in res.get("import_warnings", []):
        out.append(f"  import: {w.strip()}")
    for name, c in res["failed"]:
        msg = c.stderr.strip().splitlines()
        out.append(f"  FAILED {name}: {' | '.join(msg[-6:])}")
    doc = res.get("doc")
    if doc is not None:
        for e in doc["effects"]:
            out.append(f"  named: {e['effect']} {json.dumps(e['parameters'])}")
        if not doc["effects"]:
            out.append("  named: (nothing)")
        out.append(f"  diagnose: noise {doc['noise_rpm']:.3f} rpm, rmse {doc['rmse_initial']:.3f}"
                   f" -> {doc['rmse_final']:.3f}, unexplained {doc['unexplained']}, reference "
                   f"{doc['rmse_reference']}")
        if doc.get("residual"):
            out.append(f"  residual: {json.dumps(doc['residual'])[:300]}")
    for cal in ("fit.toml", "diag.toml"):
        p = res.get("dir") and res["dir"] / cal
        if p and p.exists():
            import tomllib

            t = tomllib.loads(p.read_text())
            out.append(f"  {cal}: A={t['motor']['A']:.4g} B={t['motor']['B']:.4g} "
                       f"C={t['motor']['C']:.4g} effects={json.dumps(t.get('effects', {}))}")
    out.append(f"  expected: {json.dumps(log.expect)}")
    if j is None:
        return out
    rm = j["rmse"]
    out.append("  wheel RMSE [rpm]: " + ", ".join(f"{k} {v:.3f}" for k, v in rm.items())
               + f"; noise (truth) {j['noise']:.3f} rpm")
    for lab in ("fit alone", "diagnosed"):
        if lab not in j:
            continue
        s = j[lab]
        wt, wl = s["worst_t"], s["worst_l"]
        out.append(f"  {lab:<9s}: t50 outside tol {s['bad_t']}/{s['timed']} timed "
                   f"(of {s['n']} steps); worst {_where(wt[1])} measured "
                   f"{1000 * wt[2]:.2f} ms model {1000 * wt[3]:.2f} ms tol {1000 * wt[4]:.2f} ms"
                   f" ({wt[0]:.2f}x)")
        out.append(f"  {'':<9s}  level outside tol {s['bad_l']}/{s['n']}; worst {_where(wl[1])}"
                   f" measured {wl[2]:.4g} model {wl[3]:.4g} rpm tol {wl[4]:.3f} "
                   f"({wl[0]:.2f}x)")
    return out


def table_row(log: Log, res: dict, j: dict | None) -> str:
    def pf(b):
        return "-" if b is None else ("pass" if b else "FAIL")

    d = (j or {}).get("diagnosed")
    t_ok = None if d is None else d["bad_t"] == 0
    l_ok = None if d is None else d["bad_l"] == 0
    timed_ok = None if d is None else d["timed"] >= 0.5 * d["n"]
    r_ok = (j or {}).get("rmse_ok")
    e_ok, e_msg = effects_check(log, res.get("doc"))
    rm = (j or {}).get("rmse", {})
    rmse = (f"{rm.get('fit alone', math.nan):.2f} -> {rm.get('diagnosed', math.nan):.2f}"
            if rm else "-")
    dn = res.get("doc", {}).get("noise_rpm") if res.get("doc") else None
    return (f"| {log.key} | {pf(t_ok)} ({d['bad_t'] if d else '-'}/{d['timed'] if d else '-'})"
            f" | {pf(l_ok)} ({d['bad_l'] if d else '-'}/{d['n'] if d else '-'}) | "
            f"{pf(timed_ok)} | {pf(r_ok)} {rmse} | {log.noise_rpm:.3f} / "
            f"{'-' if dn is None else f'{dn:.3f}'} | {pf(e_ok)} {e_msg} | "
            f"{'none' if not res['failed'] else ', '.join(n for n, _ in res['failed'])} | "
            f"{sum(c.seconds for c in res['cmds'].values()):.0f} s |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="a,b,c,d,e", help="comma-separated logs (a..e)")
    ap.add_argument("--keep", type=Path, default=None, help="write everything here and keep it")
    args = ap.parse_args()
    keys = [k.strip() for k in args.only.split(",") if k.strip()]
    base = args.keep if args.keep else Path(tempfile.mkdtemp(prefix="foreign-"))
    base.mkdir(parents=True, exist_ok=True)
    lines, rows = [], []
    for key in keys:
        rng = np.random.default_rng(ord(key))
        t0 = time.perf_counter()
        log = MAKERS[key](rng)
        log.gen_s = time.perf_counter() - t0
        d = base / key
        d.mkdir(exist_ok=True)
        extra = base / "a" / "diag.toml" if key == "e" else None
        res = run_loop(d, log, extra)
        res["dir"] = d
        j = judge(d, log, res) if (d / "rec.csv").exists() and res.get("sims") else None
        block = report(log, res, j)
        print("\n".join(block), flush=True)
        lines += block
        rows.append(table_row(log, res, j))
    head = ["", "| log | t50 (bad/timed) | level (bad/steps) | >=50 % timed | RMSE fit -> diag "
            "[rpm] | noise truth / diagnose [rpm] | effects | failed commands | CLI time |",
            "|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(head + rows))
    if not args.keep:
        shutil.rmtree(base, ignore_errors=True)
    else:
        print(f"kept in {base}")


if __name__ == "__main__":
    main()
