"""The demo: the whole loop on the simulated robot, as a user would run it on a real one.

1. **model**: the paper's experiments on the paper's model (predictions and plots).
2. **record**: the same experiments sent over the serial protocol (a pseudo-terminal) to the
   simulated controller, whose "robot" has a drive ceiling the paper's model lacks plus encoder
   noise (``robot/truth.toml``; read only by the simulated controller, never by fit/diagnose).
3. **video**: one recording rendered as camera video of a wheel marker and measured back.
4. **fit**: A, B, C from the recordings (calibration + report). The paper's linear model cannot
   follow the ceiling, so the best A, B, C are a compromise that leaves a gap.
5. **diagnose**: where the fitted model and the recordings disagree, the missing effect named,
   added, and the gap shrunk (report).
6. **shadow**: a live run with the extended model beside the robot; a wheel loses 20 % of its
   gain mid-run and shadow mode flags it and stops the robot. (With the linear fit of step 4
   the monitor would rightly flag the model's own gap instead: that is why diagnose comes first.)
7. **pose** (not in ``--quick``): a robot that slips (its body moves less than its wheels say),
   filmed from above; ``measure-pose`` fills the recordings' pose columns from the videos alone
   and ``diagnose`` names slip; the paper's three whole-robot experiments plotted measured
   against the model (:func:`pose_story`).

Everything is written under one folder, with ``REPORT.md`` tying it together.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from .errors import LinkError, SessionTerminated
from .io.recording import empty_like_times, read_recording, write_recording
from .model import load_calibration, load_robot_profile
from .plots import plot_recordings
from .prediction import predict
from .profiles import PAPER_EXPERIMENTS

#: The simulated robot's truth in the demo: what the paper saw and its model lacks.
DEMO_TRUTH = """\
# The simulated robot of `mecanum-hil demo`: the paper's coefficients plus a drive ceiling the
# paper's model lacks (it saw a slower rise above ~100 rpm and a ceiling near 130 rpm), and
# encoder noise. Read only by the simulated controller (sim-robot --effects), never by fit or
# diagnose: they have to find it.
[effects.saturation]
top_speed_rpm = 115.0

[noise]
wheel_rpm_std = 0.5
seed = 1
"""

#: The shadow-mode run: wheel 2 loses 20 % of its gain 2.5 s after the start.
DEMO_FAULT = """\
[noise]
wheel_rpm_std = 0.5
seed = 2

[[faults]]
at_s = 2.5
[faults.effects.wheel_gain]
gains = [1.0, 0.8, 1.0, 1.0]
"""

QUICK_EXPERIMENTS = ("paper-step-120", "paper-turn")


def _model_stage(out: Path, echo) -> None:
    robot = load_robot_profile()
    cal = load_calibration()
    echo(f"1. model: {robot.name}, A={cal.A:g} B={cal.B:g} C={cal.C:g} ({cal.source})")
    for name, prof in PAPER_EXPERIMENTS.items():
        t, cmd = prof.sample(100.0)
        robot.check_commands(cmd, name)
        rec = predict(empty_like_times(t).with_values(commands=cmd), cal, robot, source=name)
        write_recording(rec, out / "model" / f"{name}.csv")
        plot_recordings({"model": rec}, out / "model" / f"{name}.png", title=name)
    echo(f"   {len(PAPER_EXPERIMENTS)} experiments predicted -> {out / 'model'}")


def _interrupted(result) -> None:
    """A record session that Ctrl-C or a signal ended (it sent STOP and closed its recording)
    ends the demo as it would any command: exit 130 or 143, not a stage's error or a run that
    goes on to write its report."""
    if result.reason == "interrupted":
        raise KeyboardInterrupt
    if result.reason == "terminated":
        raise SessionTerminated()


def _record_stage(out: Path, names, echo) -> list[Path]:
    from .link.record import format_summary
    from .link.sim_process import record_profile_to_simulated_controller

    truth = out / "robot" / "truth.toml"
    truth.parent.mkdir(parents=True, exist_ok=True)
    truth.write_text(DEMO_TRUTH)
    echo(f"2. record: over the serial protocol to the simulated controller ({truth})")
    paths = []
    for name in names:
        path = out / "recorded" / f"{name}.csv"
        result = record_profile_to_simulated_controller(name, path, effects=truth)
        _interrupted(result)
        if result.exit_code != 0:
            raise LinkError(f"demo: recording {name} ended with {result.reason}: "
                            f"{result.message or 'see ' + str(path)}")
        rec = read_recording(path)
        plot_recordings({"recorded": rec}, path.with_suffix(".png"), title=f"recorded: {name}",
                        styles={"recorded": "."})
        lost = result.stats.get("lost", 0) if isinstance(result.stats, dict) else 0
        echo(f"   {name:16s} {result.commands_sent:4d} commands, {result.telemetry_received:4d} "
             f"telemetry samples, {lost} lost -> {path}")
        paths.append(path)
    echo("   last run: " + format_summary(result).replace("\n", "\n   "))
    return paths


def _video_stage(out: Path, recorded: Path, echo) -> None:
    from .vision import render_and_measure

    rec = read_recording(recorded)
    # the telemetry rows: `record` interleaves command rows, whose wheel columns are empty
    rec = rec.select(np.isfinite(rec.wheel_rpm[:, 0]))
    video = out / "video" / f"{recorded.stem}.mp4"
    video.parent.mkdir(parents=True, exist_ok=True)
    echo(f"3. video: {recorded.name} rendered as camera video of a wheel marker, measured back")
    loop = render_and_measure(rec, video, calibration=load_calibration(),
                              robot=load_robot_profile())
    measured = write_recording(loop.measurement.recording, video.with_suffix(".csv"))
    if loop.merged is not None:
        write_recording(loop.merged, out / "video" / f"{recorded.stem}-merged.csv")
    summary = loop.measurement.summary
    rms = ", ".join(f"wheel {w}: {v:.2f} rpm" for w, v in loop.rms_error_rpm.items())
    echo(f"   {video} -> {measured}; RMS error against the rendered truth: {rms}")
    for w in summary["wheels"]:
        echo(f"   wheel {w['wheel']}: marker found in {100 * w['found_fraction']:.0f} % of "
             f"{summary['frames']} frames")


def _shadow_stage(out: Path, calibration: Path, echo) -> dict:
    from .link.sim_process import record_profile_to_simulated_controller
    from .monitor.live import record_shadow

    fault = out / "shadow" / "fault.toml"
    fault.parent.mkdir(parents=True, exist_ok=True)
    fault.write_text(DEMO_FAULT)
    name = "paper-step-60"
    path = out / "shadow" / f"{name}-fault.csv"
    echo(f"6. shadow: {name} with the extended model beside the robot; wheel 2 loses 20 % of "
         "its gain at 2.5 s")
    robot = load_robot_profile()
    t, cmd = PAPER_EXPERIMENTS[name].sample(50.0)
    obs = record_shadow(calibration, robot, t, cmd, path, on_divergence="stop", echo=echo)
    result = record_profile_to_simulated_controller(name, path, effects=fault, observers=[obs])
    _interrupted(result)
    echo("   " + obs.close().replace("\n", "\n   "))
    echo(f"   the run ended: {result.reason} (exit code {result.exit_code}) -> {path}")
    return {"reason": result.reason, "path": path}


def _diagnose_stage(out: Path, recorded: list[Path], calibration: Path, echo) -> dict:
    from .identify.diagnose import diagnose
    from .identify.diagnose_report import write_report
    from .io.timing import read_for_analysis
    from .model import save_calibration

    echo("5. diagnose: where the fitted model and the recordings disagree, and why")
    robot = load_robot_profile()
    recs = [read_for_analysis(p) for p in recorded]
    cal = load_calibration(calibration)
    diag = diagnose(recs, cal, robot, names=[p.stem for p in recorded],
                    echo=lambda m: echo("   " + m))
    extended = save_calibration(diag.calibration, out / "diagnose" / "calibration.toml",
                                "extended by mecanum-hil diagnose (demo)")
    report = write_report(diag, recs, out / "diagnose", robot,
                          title="demo: the effect the model lacked")
    named = ", ".join(f"{s.effect} {s.parameters}" for s in diag.steps) or "nothing"
    echo(f"   named: {named}; unexplained: {str(diag.unexplained).lower()}")
    echo(f"   wheel RMSE {diag.rmse_initial:.3f} -> {diag.rmse_final:.3f} rpm "
         f"(the simulated robot's noise: 0.5 rpm); report {report}")
    return {"diagnosis": diag, "report": report, "calibration": extended}


def run_demo(out_dir: str | Path, echo: Callable[[str], None] = print,
             quick: bool = False) -> dict:
    """Run the demo into ``out_dir``.

    Parameters
    ----------
    out_dir : str or Path
        Folder for every file the demo writes.
    echo : callable
        Prints one line of progress.
    quick : bool
        Record three experiments instead of all seven (for tests; about a third of the time).

    Returns
    -------
    dict
        What each stage produced (paths, the diagnosis, how the shadow run ended).
    """
    from .identify.files import fit_demo

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    echo(f"mecanum-hil demo: writing into {out.resolve()}")
    _model_stage(out, echo)
    names = QUICK_EXPERIMENTS if quick else tuple(PAPER_EXPERIMENTS)
    recorded = _record_stage(out, names, echo)
    _video_stage(out, recorded[names.index("paper-step-120")], echo)
    echo("4. fit: A, B, C from the recordings")
    fitted = fit_demo(recorded, out / "fit", echo=lambda m: echo("   " + m))
    cal_path = fitted["fit/calibration"]
    diag = _diagnose_stage(out, recorded, cal_path, echo)
    shadow = _shadow_stage(out, diag["calibration"], echo)
    # the overhead camera's chain renders seven runs: left out of the quick demo (tests run it
    # on its own, tests/vision/test_pose_slip.py)
    pose = None if quick else _pose_stage(out, echo)
    report = _write_report(out, names, cal_path, shadow, diag, pose)
    echo(f"done: {report}")
    return {"recorded": recorded, "calibration": cal_path, "shadow": shadow,
            "diagnose": diag, "pose": pose, "report": report}


def _write_report(out: Path, names, cal_path: Path, shadow: dict, diag: dict,
                  pose: dict | None = None) -> Path:
    cal = load_calibration(cal_path)
    d = diag["diagnosis"]
    lines = [
        "# mecanum-hil demo",
        "",
        "The whole loop on the simulated robot (`robot/truth.toml` is its hidden truth).",
        "",
        "| stage | result | files |",
        "|---|---|---|",
        "| 1. model | the paper's experiments on the paper's model | `model/` |",
        f"| 2. record | {len(names)} experiments over the serial protocol | `recorded/` |",
        "| 3. video | a recording rendered and measured back | `video/` |",
        f"| 4. fit | A = {cal.A:.4g}, B = {cal.B:.4g}, C = {cal.C:.4g}, "
        f"fit {cal.info.get('fit_percent', float('nan')):.2f} % | `fit/` |",
        f"| 5. diagnose | named: {', '.join(s.effect for s in d.steps) or 'nothing'}; "
        f"RMSE {d.rmse_initial:.3f} -> {d.rmse_final:.3f} rpm | `diagnose/report.md` |",
        f"| 6. shadow | fault injected; run ended: {shadow['reason']} | `shadow/` |",
    ]
    if pose is not None:
        pd = pose["diagnosis"]
        eff = pd.calibration.effects.efficiency
        lines.append(f"| 7. pose | slip hidden, pose from overhead videos only; diagnose named: "
                     f"{', '.join(s.effect for s in pd.steps) or 'nothing'}, efficiency "
                     f"({eff[0]:.3f}, {eff[1]:.3f}, {eff[2]:.3f}) | `pose/` |")
    lines.append("")
    path = out / "REPORT.md"
    path.write_text("\n".join(lines))
    return path



#: The pose stage's simulated robot: its body moves at 90 / 80 / 85 % of what its wheels say
#: (forward, sideways, turning): slip, which no wheel speed shows and an overhead camera does.
DEMO_SLIP = """\
# The simulated robot of the demo's pose stage: the body moves at 90 % / 80 % / 85 % of the
# wheels' forward, sideways and turning speed (slip). Read only by the simulated controller.
[effects.slip]
efficiency = [0.9, 0.8, 0.85]

[noise]
wheel_rpm_std = 0.5
seed = 3
"""

#: The paper's three whole-robot experiments as the pose stage films them (its Figures 13-15):
#: the ramp only to 40 rpm (8 s): the whole ramp drives ~21 m, beyond one camera's view.
PAPER_POSE_EXPERIMENTS = ("paper-step-120", "paper-turn", "paper-ramp-to-40")


def pose_profiles():
    """The pose stage's runs: the paper's three whole-robot experiments plus forward, sideways
    and turning runs at other speeds (diagnose compares models on recordings they were not
    fitted to: each direction needs two)."""
    from .profiles import ramp, step

    return [PAPER_EXPERIMENTS["paper-step-120"], PAPER_EXPERIMENTS["paper-turn"],
            ramp(40.0, 5.0, hold_s=0.0, name="paper-ramp-to-40"),
            step(60.0, duration_s=2.0, name="forward-60"),
            step(40.0, duration_s=2.0, theta_deg=180.0, name="sideways-40"),
            step(80.0, duration_s=2.0, theta_deg=180.0, name="sideways-80"),
            step(0.0, duration_s=2.0, omega_dps=30.0, name="turn-30")]


def pose_story(out_dir: str | Path, echo: Callable[[str], None] = print, *,
               size: tuple[int, int] = (640, 480), profiles=None) -> dict:
    """Slip seen only by an overhead camera: the chain of issue 20.

    1. A campaign from the simulated controller whose robot slips (:data:`DEMO_SLIP`).
    2. Each run rendered as an overhead camera's video (lens distortion, a 30 deg oblique view,
       the robot's marker 0.23 m up, noise; the camera starting 0.2 s late); the recordings'
       own pose columns are then thrown away.
    3. ``measure-pose`` on each video fills the recording's pose columns (start found from the
       robot's motion onset).
    4. ``diagnose`` on those recordings names slip; the paper's three whole-robot experiments
       are plotted measured (video) against the model without and with the slip found.

    Returns
    -------
    dict
        ``measured`` (paths), ``diagnosis``, ``errors`` (per run: the video's pose against the
        simulator's), ``plots``.
    """
    from .identify.campaign import paper_campaign
    from .identify.diagnose import diagnose, initial_pose_at_rest
    from .io.pose_track import fill_pose, onset_offset
    from .io.timing import read_for_analysis
    from .vision.overhead import OverheadSettings, render_overhead
    from .vision.pose import measure_pose, pose_errors

    out = Path(out_dir)
    for sub in ("recorded", "video", "measured"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    fx = out / "robot-slip.toml"
    fx.write_text(DEMO_SLIP)
    rob, cal = load_robot_profile(), load_calibration()
    profs = list(profiles or pose_profiles())
    recs = paper_campaign(fx, rob, pose_noise=(0.0, 0.0, 0.0), seed=3, profiles=profs,
                          retime=False)
    measured, errors = [], {}
    for k, rec in enumerate(recs):
        name = str(rec.metadata["profile"])
        meta = {key: v for key, v in rec.metadata.items() if not key.startswith("true_")}
        src = write_recording(rec.with_values(metadata=meta), out / "recorded" / f"{name}.csv")
        res = render_overhead(rec, out / "video" / f"{name}.mp4", OverheadSettings(
            width_px=size[0], height_px=size[1], tilt_deg=30.0, noise_std=2.0, seed=k,
            camera_start_s=0.2))
        m = measure_pose(res.path, res.camera, res.scene)
        errors[name] = pose_errors(m.t_s, m.pose, res.pose)
        base = rec.with_values(pose=np.full_like(rec.pose, np.nan), metadata=meta)
        model = predict(base, cal, rob, source=str(src))
        start = onset_offset(m.t_s, m.pose, model.t_s, model.pose, source=str(res.path))
        path = write_recording(fill_pose(base, m.t_s, m.pose, start, {
            "pose_source": f"measure-pose {res.path}", "video_start_s": start,
            "video_start_method": "auto", "pose_measurement": m.summary}),
            out / "measured" / f"{name}.csv")
        measured.append(path)
        echo(f"{name:18s} video {res.frame_t_s.size} frames; pose error "
             f"{1000 * errors[name]['position_rmse_m']:.1f} mm / "
             f"{errors[name]['heading_rmse_deg']:.2f} deg RMS; start {start:.3f} s "
             f"(true 0.200 s)")
    recs_m = [read_for_analysis(p) for p in measured]
    diag = diagnose(recs_m, cal, rob, names=[p.stem for p in measured])
    found = diag.calibration
    named = ", ".join(s.effect for s in diag.steps) or "nothing"
    eff = found.effects.efficiency
    echo(f"diagnose on the video's pose: named {named}; slip efficiency "
         f"({eff[0]:.3f}, {eff[1]:.3f}, {eff[2]:.3f}) (hidden: 0.9, 0.8, 0.85)")
    plots = []
    for name in PAPER_POSE_EXPERIMENTS:
        if (out / "measured" / f"{name}.csv").exists():
            rec = read_for_analysis(out / "measured" / f"{name}.csv")
            # the model starts where the video saw the robot rest (mean over the rest), as
            # diagnose starts it: one frame's heading noise would turn the whole path
            rest = initial_pose_at_rest(rec)
            plots.append(_plot_pose(rec, predict(rest, cal, rob), predict(rest, found, rob),
                                    out / f"{name}-pose.png", name))
    return {"measured": measured, "diagnosis": diag, "errors": errors, "plots": plots}


def _plot_pose(measured, model, model_slip, path: Path, title: str) -> Path:
    """X, Y and phi against time: the video's measurement and the model without / with slip."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plots import save_figure

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    keep = np.isfinite(measured.pose).all(axis=1)
    for ax, col, label in zip(axes, range(3), ("X [m]", "Y [m]", "heading phi [deg]"),
                              strict=True):
        ax.plot(model.t_s, model.pose[:, col], "--", color="grey", lw=1.2,
                label="model (paper, no slip)")
        ax.plot(model_slip.t_s, model_slip.pose[:, col], "-", color="C1", lw=1.2,
                label="model + slip found by diagnose")
        ax.plot(measured.t_s[keep][::5], measured.pose[keep, col][::5], ".", color="C0",
                ms=3, label="measured (overhead video)")
        ax.set_xlabel("t [s]")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{title}: pose measured by measure-pose vs the model")
    return save_figure(fig, path, dpi=100)


def _pose_stage(out: Path, echo) -> dict:
    echo("7. pose: a robot that slips, filmed from above; measure-pose, then diagnose")
    result = pose_story(out / "pose", echo=lambda m: echo("   " + m))
    echo(f"   plots: {', '.join(str(p) for p in result['plots'])}")
    return result
