"""The diagnose report (markdown + PNG plots) and the demo's story of a hidden effect found.

:func:`write_report` turns a :class:`~mecanum_hil.identify.diagnose.Diagnosis` into
``report.md`` with, per step, the effect named, its parameters with 95 % intervals, every
candidate's held-out score, the RMSE before and after per recording, and a plot of measured,
old model and new model on the recording where the gap shrank most.
:func:`diagnose_story` is the demo's end: a simulated robot with an effect the model lacks, the
gap, the named effect and the gap shrunk, in one report.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ...errors import MecanumHILError
from ...io.paths import staged_folder
from ...io.recording import Recording
from ...model.calibration import EFFECTS, Effects, save_calibration
from ...model.robot import RobotProfile
from ...prediction import predict
from ..fit import UNBOUNDED_FACTOR
from ..regimes import pose_residual, rmse
from .candidates import effect_parameters
from .localise import STRUCTURE_RATIO, STRUCTURE_RHO, Finding, initial_pose_at_rest
from .reference import reference_comparison
from .selection import MIN_EXPLAINED, MIN_RELATIVE, DiagnoseStep, Diagnosis


def plot_comparison(measured: Recording, curves: dict[str, Recording], path: str | Path,
                    title: str = "") -> Path:
    """Measured wheel speeds (dots) against model curves, one panel per measured wheel, plus
    the path in the plane when the recording has a pose.

    Parameters
    ----------
    measured : Recording
    curves : dict of str to Recording
        Label -> model prediction (same times), drawn in order (e.g. old model, new model).
    path : str or Path
        PNG to write.
    title : str
    """
    from ...plots import _pyplot, save_figure

    plt = _pyplot()
    wheels = [i for i in range(4) if np.isfinite(measured.wheel_rpm[:, i]).any()]
    has_pose = bool(np.isfinite(measured.pose[:, :2]).any())
    n = len(wheels) + (1 if has_pose else 0)
    cols = 2 if n > 1 else 1
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.0 * cols, 3.2 * rows), squeeze=False)
    styles = ["--", "-", ":", "-."]
    for k, i in enumerate(wheels):
        ax = axes.flat[k]
        ax.plot(measured.t_s, measured.wheel_rpm[:, i], ".", ms=2, color="0.45", label="measured")
        for j, (label, rec) in enumerate(curves.items()):
            ax.plot(rec.t_s, rec.wheel_rpm[:, i], styles[j % 4], lw=1.3, label=label)
        ax.set_title(f"wheel {i + 1}", fontsize=9)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("speed [rpm]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    if has_pose:
        ax = axes.flat[len(wheels)]
        ax.plot(measured.pose[:, 0], measured.pose[:, 1], ".", ms=2, color="0.45",
                label="measured")
        for j, (label, rec) in enumerate(curves.items()):
            ax.plot(rec.pose[:, 0], rec.pose[:, 1], styles[j % 4], lw=1.3, label=label)
        ax.set_title("path", fontsize=9)
        ax.set_xlabel("X [m]")
        ax.set_ylabel("Y [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path, dpi=100)


#: Most steps drawn in one per-step figure (one small panel each); the table lists them all.
MAX_STEP_PANELS = 24


def step_rows(recording: Recording, curves: dict[str, Recording], robot: RobotProfile,
              noise_rpm: float = 0.0):
    """Per step and per measured wheel: time to 50 % and level of the measured speeds and of
    each model's prediction (:func:`mecanum_hil.identify.steps.step_table`)."""
    from ..regimes import wheel_targets
    from ..steps import step_table

    series = {"measured": recording.wheel_rpm, **{k: c.wheel_rpm for k, c in curves.items()}}
    return step_table(recording.t_s, wheel_targets(recording, robot), series, noise_rpm)


def step_table_lines(rows, labels: Sequence[str], period_s: float, noise_rpm: float
                     ) -> list[str]:
    """The per-step markdown table and one line on the worst step of the last model."""
    head = " / ".join(["measured", *labels])
    md = [f"| wheel | step | t [s] | target [rpm] | time to 50 % [ms] {head} | "
          f"level [rpm] {head} |", "|---|---|---|---|---|---|"]

    def ms(v: float) -> str:
        return "-" if not np.isfinite(v) else f"{1000 * v:.1f}"

    def rpm(v: float) -> str:
        return "-" if not np.isfinite(v) else f"{v:.4g}"

    for r in rows:
        s = r.step
        keys = ["measured", *labels]
        md.append(f"| {s.wheel + 1} | {s.index + 1} | {s.t_start_s:.3f} | {s.target_rpm:.4g} | "
                  + " / ".join(ms(r.figures[k].t50_s) for k in keys) + " | "
                  + " / ".join(rpm(r.figures[k].level_rpm) for k in keys) + " |")
    if labels and rows:
        last = labels[-1]
        worst_t = worst_l = 0.0
        for r in rows:
            me, mo = r.figures["measured"], r.figures[last]
            if np.isfinite(me.t50_s) and np.isfinite(mo.t50_s):
                worst_t = max(worst_t, abs(mo.t50_s - me.t50_s)
                              / max(0.2 * me.t50_s, 2.0 * period_s))
            if np.isfinite(me.level_rpm) and np.isfinite(mo.level_rpm):
                worst_l = max(worst_l, abs(mo.level_rpm - me.level_rpm)
                              / max(0.03 * abs(r.step.target_rpm), 1.5 * noise_rpm, 1e-12))
        md += ["", f"Worst step of `{last}`: time-to-50 % error {worst_t:.2f} x its tolerance "
               "(max(20 % of the measured time, 2 samples)), level error "
               f"{worst_l:.2f} x its tolerance (max(3 % of the target, 1.5 noise levels)); "
               "1 or less: every step within both."]
    return md


def plot_steps(recording: Recording, curves: dict[str, Recording], rows, path: str | Path,
               title: str = "") -> Path:
    """Measured speeds (dots) and model curves step by step: one small panel per step of the
    first measured wheel (at most :data:`MAX_STEP_PANELS`), each from just before the step to
    where it has settled (the whole step, or ten measured times to 50 % when that is shorter,
    at least a quarter of the step), with the target dotted and the step's level marked."""
    from ...plots import _pyplot, save_figure

    plt = _pyplot()
    wheel = rows[0].step.wheel if rows else 0
    mine = [r for r in rows if r.step.wheel == wheel][:MAX_STEP_PANELS]
    n = max(len(mine), 1)
    cols = min(5, n)
    nrows = math.ceil(n / cols)
    # at least 6.4 in wide: one panel's figure still holds its title whole
    fig, axes = plt.subplots(nrows, cols, figsize=(max(3.2 * cols, 6.4), 2.8 * nrows),
                             squeeze=False)
    t = recording.t_s
    y = recording.wheel_rpm[:, wheel]
    styles = ["--", "-", ":", "-."]
    for ax, r in zip(axes.flat, mine, strict=False):
        s = r.step
        dur = s.t_end_s - s.t_start_s
        t50 = r.figures["measured"].t50_s
        span = dur if not np.isfinite(t50) else min(dur, max(10.0 * t50, 0.25 * dur))
        lo, hi = s.t_start_s - 0.1 * span, s.t_start_s + span
        sel = (t >= lo) & (t <= hi)
        ax.plot(1000 * (t[sel] - s.t_start_s), y[sel], ".", ms=2, color="0.45")
        for j, c in enumerate(curves.values()):
            ax.plot(1000 * (c.t_s[sel] - s.t_start_s), c.wheel_rpm[sel, wheel],
                    styles[j % 4], lw=1.1)
        ax.axhline(s.target_rpm, color="k", lw=0.6, ls=":")
        ax.axvline(0.0, color="k", lw=0.5)
        ax.set_title(f"step {s.index + 1}: {s.before_rpm:.4g} -> {s.target_rpm:.4g} rpm",
                     fontsize=9)
        ax.tick_params(labelsize=8)
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[len(mine):]:
        ax.set_visible(False)
    axes.flat[0].legend(["measured", *curves], fontsize=8)
    fig.supxlabel("time since the step [ms]", fontsize=9)
    fig.supylabel(f"wheel {wheel + 1} speed [rpm]", fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path, dpi=100)


def _fmt(v: float, digits: int = 4) -> str:
    return "n/a" if not np.isfinite(v) else f"{v:.{digits}g}"


def _equivalent_lines(step) -> list[str]:
    """The drive lag's twin, which wheel speeds cannot tell from it, or why it is left out."""
    problem = step.equivalent_problem
    if problem is not None:
        return [f"No equivalent model: degenerate ({problem}). Exchanging the lag and the "
                "motor's time constant gives no model a calibration can hold, so none is "
                "given.", ""]
    q = step.equivalent
    if q is None:
        return []
    return [f"Equally: a lag of {q['drive_lag_s']:.4g} s with A = {q['A']:.5g} 1/s, "
            f"B = {q['B']:.5g} 1/s, C = {q['C']:.5g} 1/s^2 gives exactly the same wheel speeds "
            "(the lag and the motor's time constant exchanged, the PI gains rescaled): wheel "
            "speeds cannot tell which is the drive's and which the motor's. A current or "
            "voltage measurement, or breakaway, can.", ""]


def _param_lines(step) -> list[str]:
    out = []
    for name in effect_parameters(step.effect):
        base, _, idx = name.partition("[")
        value = step.parameters.get(base)
        v = (value[int(idx[:-1])] if idx else value) if value is not None else math.nan
        lo, hi = step.ci95.get(name, (math.nan, math.nan))
        if not (math.isfinite(lo) and math.isfinite(hi)):
            interval = "unidentifiable" if name in step.ci95 else "n/a"
        else:
            interval = f"[{_fmt(lo, 5)}, {_fmt(hi, 5)}]"
        out.append(f"| `{name}` | {_fmt(float(v), 5)} | {interval} |")
    return out


def _pose_rmse(rec: Recording, pred: Recording) -> float:
    """Position RMSE [m] (NaN without pose)."""
    return rmse(pose_residual(rec, pred)[:, :2])


def write_report(diagnosis: Diagnosis, recordings: Sequence[Recording], out_dir: str | Path,
                 robot: RobotProfile | None = None, title: str = "diagnose report") -> Path:
    """Write ``report.md`` and its PNG plots into ``out_dir``; return the markdown's path."""
    rob = robot or RobotProfile()
    folder = _report_folder(out_dir)
    d = diagnosis
    names = list(d.names)
    recordings = [initial_pose_at_rest(r) for r in recordings]
    md = _summary_lines(d, recordings, title)
    with staged_folder(folder, last=("report.md",)) as out:  # seen whole or not at all
        for k, step in enumerate(d.steps, start=1):
            md += _step_lines(d, k, step, recordings, names, rob, out)
        for f in d.findings:
            md += _finding_lines(f)
        md += _remainder_lines(d)
        if d.unexplained:
            md += _unexplained_lines(d, recordings, names, rob, out)
        md += _step_section(d, recordings, names, rob, out)
        _write_markdown(out / "report.md", md)
    return folder / "report.md"


def _report_folder(out_dir: str | Path) -> Path:
    """The report's folder, created where missing."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise MecanumHILError(f"{out}: cannot create report folder: {err.strerror or err}"
                              ) from err
    return out


def _summary_lines(d: Diagnosis, recordings: Sequence[Recording], title: str) -> list[str]:
    """The title, the gap closed, the refits, where the model as given fails, the baseline and
    the selection rules."""
    ini = d.initial
    return [f"# {title}", "",
            f"{len(recordings)} recordings, {sum(len(r) for r in recordings)} time rows, "
            f"{d.localisation_initial.n_samples} measured wheel samples. Model as given: "
            f"A = {ini.A:.5g} 1/s, B = {ini.B:.5g} 1/s, C = {ini.C:.5g} 1/s^2 "
            f"({ini.source}); effects: {', '.join(ini.effects.active()) or 'none'}.", "",
            f"**Wheel RMSE {d.rmse_initial:.4g} rpm -> {d.rmse_final:.4g} rpm** "
            f"(noise level about {d.noise_rpm:.3g} rpm). Effects named: "
            f"{', '.join(d.effects) or 'none'}. Unexplained structured residual: "
            f"{'**yes**' if d.unexplained else 'no'}.", "",
            *[f"A longer search, not the effect of the round's best candidate ({r.candidate}), "
              f"took the wheel RMSE from {r.rmse_before:.4g} to {r.rmse_after:.4g} rpm: the "
              "model was refitted and nothing named for it." for r in d.refits],
            *([""] if d.refits else []),
            "## Where the model as given fails", "", "```", *d.localisation_initial.lines(),
            "```", "",
            f"Refitting its own parameters alone gives a wheel RMSE of {d.rmse_baseline:.4g} "
            f"rpm (A = {d.baseline.A:.5g}, B = {d.baseline.B:.5g}, C = {d.baseline.C:.5g}).",
            "",
            "Candidates are fitted together with A, B, C and scored on held-out data "
            "(approximate leave-one-recording-out, or held-out time blocks when there is one "
            "recording); the score is the held-out mean square divided by the noise level "
            "squared (1 = noise floor). A candidate is kept if it lowers the held-out score by "
            f"at least {100 * MIN_RELATIVE:.0f} % and removes at least "
            f"{100 * MIN_EXPLAINED:.0f} % of the in-sample excess over the floor.", ""]


def _step_lines(d: Diagnosis, k: int, step: DiagnoseStep, recordings: Sequence[Recording],
                names: Sequence[str], robot: RobotProfile, out: Path) -> list[str]:
    """Step ``k``'s section: the effect, its parameters, every candidate, the RMSE before and
    after, and its plot."""
    spec = EFFECTS[step.effect]
    md = [f"## Step {k}: {step.effect}", "", f"*{spec.description}*", "",
          "| parameter | value | 95 % interval |", "|---|---|---|", *_param_lines(step), "",
          *_unidentifiable_lines(step),
          *_equivalent_lines(step), *_candidate_table(step), "",
          *_rmse_table(names, step), "",
          f"Share of the gap over the noise floor this step removed: "
          f"{_fmt(100 * d.share(step), 3)} %."]
    if np.isfinite(step.pose_rmse_before).any():
        b, a = step.pose_rmse_before, step.pose_rmse_after
        md += ["", f"Pose RMSE before: X {b[0]:.4g} m, Y {b[1]:.4g} m, heading "
               f"{b[2]:.4g} deg; after: X {a[0]:.4g} m, Y {a[1]:.4g} m, heading "
               f"{a[2]:.4g} deg."]
    if step.warnings:
        md += ["", "Fit warnings: " + "; ".join(step.warnings)]
    return md + _step_plot_lines(k, step, recordings, names, robot, out)


def _unidentifiable_lines(step: DiagnoseStep) -> list[str]:
    """A note under the parameter table when an interval is unidentifiable."""
    if not any(not all(map(math.isfinite, v)) for v in step.ci95.values()):
        return []
    return ["Unidentifiable: the data cannot bound the parameter (its 95 % interval is not "
            "finite, or its half-width is at least its whole admissible range or exceeds "
            f"{UNBOUNDED_FACTOR:g} times its magnitude; docs/fit.md).", ""]


def _candidate_table(step: DiagnoseStep) -> list[str]:
    """Every candidate of the step's round: held-out RMS, share explained, parameters."""
    md = ["| candidate | held-out RMS | explains of excess (held out / in sample) | "
          "of score | parameters |",
          "|---|---|---|---|---|"]
    for c in step.candidates:
        mark = " **(added)**" if c.accepted else ""
        md.append(f"| {c.effect}{mark} | {_fmt(c.heldout_rmse)} | "
                  f"{_fmt(100 * c.explained, 3)} % / {_fmt(100 * c.in_sample, 3)} % | "
                  f"{_fmt(100 * c.relative, 3)} % | {c.note or c.parameters} |")
    return md


def _rmse_table(names: Sequence[str], step: DiagnoseStep) -> list[str]:
    """The step's wheel RMSE before and after, per recording and over all."""
    md = ["| recording | wheel RMSE before [rpm] | after [rpm] |", "|---|---|---|"]
    for name, b, a in zip(names, step.rmse_before_per_recording,
                          step.rmse_after_per_recording, strict=True):
        md.append(f"| {name} | {b:.4g} | {a:.4g} |")
    md.append(f"| **all** | **{step.rmse_before:.4g}** | **{step.rmse_after:.4g}** |")
    return md


def _step_plot_lines(k: int, step: DiagnoseStep, recordings: Sequence[Recording],
                     names: Sequence[str], robot: RobotProfile, out: Path) -> list[str]:
    """Plot old and new model on the recording where the step shrank the gap most (pose RMSE
    for slip, wheel RMSE otherwise); return the lines that show it."""
    old = [predict(r, step.calibration_before, robot) for r in recordings]
    new = [predict(r, step.calibration_after, robot) for r in recordings]
    if step.effect == "slip":
        gain = [_pose_rmse(r, o) - _pose_rmse(r, n)
                for r, o, n in zip(recordings, old, new, strict=True)]
    else:
        gain = [b - a for b, a in zip(step.rmse_before_per_recording,
                                      step.rmse_after_per_recording, strict=True)]
    i = _largest(gain)
    png = plot_comparison(recordings[i], {"old model": old[i], f"with {step.effect}": new[i]},
                          out / f"step{k}-{step.effect}.png",
                          f"step {k}: {step.effect} on {names[i]}")
    return ["", f"Where the gap shrank most ({names[i]}):", "", f"![step {k}]({png.name})", ""]


def _largest(values: Sequence[float]) -> int:
    """The index of the largest finite value; 0 when none is finite (nothing to choose by)."""
    v = np.asarray(values, dtype=float)
    return int(np.nanargmax(v)) if np.isfinite(v).any() else 0


def _finding_lines(f: Finding) -> list[str]:
    """A named property of the final model (``proportional_only``, ``creeping_level``) and
    its figures."""
    carried = "carried by A, B, C; " if f.effect == "proportional_only" else ""
    return [f"## Named: {f.effect}", "", f"{f.description[0].upper()}{f.description[1:]} "
            f"(`docs/diagnose.md`: {carried}nothing is added to the calibration).", "",
            "| figure | value |", "|---|---|",
            *[f"| `{k}` | {_fmt(v, 5)} |" for k, v in f.parameters.items()], ""]


def _remainder_lines(d: Diagnosis) -> list[str]:
    """What remains: where, its shape, the reference model, whether it is structured, and the
    last round's candidates when none qualified."""
    c = d.check
    md = ["## What remains", "", "```", *d.localisation_final.lines(), "```", ""]
    if d.shape is not None:
        md += [f"Shape of the remaining residual: {d.shape.describe()}.", ""]
    md += [f"Generic reference model (output error of higher order, "
           "`identify/diagnose/reference.py`): wheel RMSE "
           f"{_fmt(d.rmse_reference)} rpm, the refitted model {d.rmse_baseline:.4g} rpm; "
           f"{reference_comparison(d.rmse_baseline, d.rmse_final, d.rmse_reference)} "
           f"(explained share {_fmt(d.explained_share, 3)}).", "",
           f"Remaining wheel RMSE {c.rmse_rpm:.4g} rpm = {c.ratio:.3g} x the noise level; lag-1 "
           f"autocorrelation {c.lag1_autocorrelation:.3g} (white noise: about 0). Structured "
           f"means RMSE > {STRUCTURE_RATIO} x noise and autocorrelation > {STRUCTURE_RHO}: "
           f"{'yes' if c.structured else 'no'}."]
    if d.rejected:
        md += ["", "Candidates of the last round (none qualified):", "",
               "| candidate | held-out RMS | explains of excess | of score |", "|---|---|---|---|"]
        md += [f"| {s.effect} | {_fmt(s.heldout_rmse)} | {_fmt(100 * s.explained, 3)} % | "
               f"{_fmt(100 * s.relative, 3)} % |" for s in d.rejected]
    return md


def _unexplained_lines(d: Diagnosis, recordings: Sequence[Recording], names: Sequence[str],
                       robot: RobotProfile, out: Path) -> list[str]:
    """The unexplained residual: where it is largest, and the final model plotted on the
    recording it fits worst."""
    final = [predict(r, d.calibration, robot) for r in recordings]
    worst = _largest([rs.rmse_rpm for rs in d.localisation_final.recordings])
    png = plot_comparison(recordings[worst], {"final model": final[worst]},
                          out / "unexplained.png", f"unexplained residual on {names[worst]}")
    return ["", "**Unexplained:** structured residual remains that no effect of the library "
            "explains; it is largest in: "
            + (", ".join(d.localisation_final.worst_regimes()) or "no single regime")
            + ".", "", f"![unexplained]({png.name})"]


def _write_markdown(path: Path, md: Sequence[str]) -> Path:
    """Write the report's lines to ``path``."""
    try:
        path.write_text("\n".join(md) + "\n")
    except OSError as err:
        raise MecanumHILError(f"{path}: cannot write report: {err.strerror or err}") from err
    return path


def _step_section(d: Diagnosis, recordings: Sequence[Recording], names: Sequence[str],
                  robot: RobotProfile, out: Path) -> list[str]:
    """The "step by step" section: per recording, the per-step table of measured, fit alone (A, B, C
    refitted alone) and diagnosed, and ``steps-<n>.png``."""
    from ..steps import LEVEL_SHARE

    md = ["", "## Step by step", "",
          "Each recording cut at the jumps of each wheel's target "
          "(`mecanum_hil/identify/steps.py`). Time to 50 %: from the step to the crossing of "
          "half the way from the level before to the level reached, each series against its "
          "own levels, linearly interpolated (`-`: the step does not move the wheel); level: "
          f"the mean over the last {100 * LEVEL_SHARE:.0f} % of the step. `fit alone` is A, B, "
          "C refitted alone (the baseline), `diagnosed` the final model.", ""]
    for k, (rec, name) in enumerate(zip(recordings, names, strict=True), start=1):
        curves = {"fit alone": predict(rec, d.baseline, robot),
                  "diagnosed": predict(rec, d.calibration, robot)}
        rows = step_rows(rec, curves, robot, d.noise_rpm)
        if not rows:
            continue
        period = rec.measured_period_s if math.isfinite(rec.measured_period_s) else 0.0
        png = plot_steps(rec, curves, rows, out / f"steps-{k}.png",
                         f"{name}: measured, fit alone, diagnosed, step by step")
        md += [f"### {name}", "", *step_table_lines(rows, list(curves), period, d.noise_rpm),
               "", f"![steps of {name}]({png.name})", ""]
    return md


#: The demo's hidden effect: the drive's ceiling the paper's data show near the top speed.
STORY_EFFECTS = Effects(top_speed_rpm=115.0)


def diagnose_story(out_dir: str | Path, echo: Callable[[str], None] = print, *,
                   hidden: Effects = STORY_EFFECTS, rate_hz: float = 100.0, seed: int = 0,
                   noise_rpm: float = 1.0, profiles=None) -> dict[str, Path]:
    """The demo's end: a simulated robot with an effect the model lacks, found and added.

    1. A campaign like the paper's (:func:`~mecanum_hil.identify.campaign.paper_campaign`)
       recorded from the simulated controller with the paper's coefficients, whose effects
       file (written as ``robot-effects.toml``) hides ``hidden`` and adds ``noise_rpm`` of
       wheel noise; telemetry at ``rate_hz``.
    2. A, B, C fitted on it as a user would (``fit``): the gap that remains.
    3. ``diagnose``: where the model fails, the effect named, its parameters, the gap shrunk.

    ``profiles`` are the campaign's (default: the paper-like campaign). Writes the campaign's
    recordings, the user's and the extended calibration, and ``report.md`` with plots into
    ``out_dir``; returns the files by name.
    """
    from ...io.recording import write_recording
    from ...link.effects_file import save_sim_effects, sim_effects_for
    from ..campaign import paper_campaign
    from ..fit import fit
    from .selection import diagnose

    out = Path(out_dir)
    robot = RobotProfile()
    echo(f"diagnose story: a simulated robot with {', '.join(hidden.active()) or 'no'} "
         f"effect(s) the model lacks ({hidden.active()})")
    files: dict[str, Path] = {}
    files["effects"] = save_sim_effects(
        sim_effects_for(hidden, wheel_rpm_std=noise_rpm, seed=seed),
        out / "robot-effects.toml", "The simulated robot's hidden truth (sim-robot --effects); "
        "fit and diagnose never read it.")
    recs = paper_campaign(files["effects"], robot, telemetry_rate_hz=rate_hz, seed=seed,
                          profiles=profiles)
    names = [str(r.metadata["profile"]) for r in recs]
    for rec, name in zip(recs, names, strict=True):
        files[f"campaign/{name}"] = write_recording(rec, out / "campaign" / f"{name}.csv")
    user = fit(recs, robot, sources=names).calibration
    files["fitted"] = save_calibration(user, out / "fitted.toml",
                                       "A, B, C fitted on the campaign (mecanum-hil fit)")
    echo(f"fit A, B, C as a user would: A={user.A:.4g} B={user.B:.4g} C={user.C:.4g}, "
         f"wheel RMSE {user.info.get('rmse_rpm', float('nan')):.3f} rpm")
    diag = diagnose(recs, user, robot, names=names, echo=lambda m: echo("  " + m))
    files["diagnosed"] = save_calibration(diag.calibration, out / "diagnosed.toml",
                                          "extended by mecanum-hil diagnose")
    files["report"] = write_report(diag, recs, out, robot,
                                   title="diagnose: a hidden effect found and added")
    found = ", ".join(f"{s.effect} {s.parameters}" for s in diag.steps) or "nothing"
    echo(f"named: {found}; wheel RMSE {diag.rmse_initial:.3f} -> {diag.rmse_final:.3f} rpm "
         f"(hidden: {hidden.active()}); report {files['report']}")
    return files
