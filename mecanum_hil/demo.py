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
6. **shadow**: a live run with the extended model beside the robot; wheel 2 drops to 80 % of
   its gain mid-run and shadow mode flags it and stops the robot. (With the linear fit of
   step 4 the monitor would rightly flag the model's own gap instead: that is why diagnose
   comes first.)
7. **pose**: a robot that slips (its body moves less than its wheels say), filmed from above;
   ``measure-pose`` fills the recordings' pose columns from the videos alone and ``diagnose``
   names slip; the paper's whole-robot experiments plotted measured against the model
   (:func:`pose_story`).

The default demo is the loop in miniature (:func:`run_demo`): two recorded experiments, six
overhead runs at 480x360 and 15 frames/s, and the compiled work (diagnose) in a worker process
that compiles numba's simulator while this process runs the other stages in the interpreter.
``full=True`` records all seven experiments and films seven runs at 640x480, 30 frames/s.
Everything is written under one folder, with ``REPORT.md`` tying it together.
"""

from __future__ import annotations

import contextlib
import time
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

#: The default (miniature) demo's recorded experiments; ``--full`` records all seven.
MINI_EXPERIMENTS = ("paper-step-120", "paper-turn")
QUICK_EXPERIMENTS = MINI_EXPERIMENTS

#: The miniature's pose runs: the paper's step and turn plus forward, sideways and turning
#: runs at other speeds (diagnose holds whole recordings out: each direction needs two).
MINI_POSE_RUNS = ("paper-step-120", "paper-turn", "forward-60", "sideways-40", "sideways-80",
                  "turn-30")

#: The miniature's overhead videos: 480x360 at 15 frames/s (the full demo: 640x480 at 30).
MINI_POSE_VIDEO = {"size": (480, 360), "fps": 15.0}

#: The simulated controller's environment in the miniature: its simulator in the interpreter
#: (a 1 kHz tick of one robot costs it about 13 % of a core), without numba's first compile.
INTERPRETED_ENV = {"MECANUM_HIL_JIT": "never"}


class _Clock:
    """Stage times for the progress lines and the report."""

    def __init__(self, echo: Callable[[str], None]) -> None:
        self.echo = echo
        self.t0 = time.perf_counter()
        self.times: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, key: str):
        start = time.perf_counter()
        yield
        now = time.perf_counter()
        self.times[key] = self.times.get(key, 0.0) + now - start
        self.echo(f"   [{key}: {now - start:.1f} s; {now - self.t0:.1f} s since the start]")

    def total(self) -> float:
        return time.perf_counter() - self.t0


def _model_stage(out: Path, echo, names=None) -> Path:
    robot = load_robot_profile()
    cal = load_calibration()
    echo(f"1. model: {robot.name}, A={cal.A:g} B={cal.B:g} C={cal.C:g} ({cal.source})")
    names = list(names or PAPER_EXPERIMENTS)
    for name in names:
        t, cmd = PAPER_EXPERIMENTS[name].sample(100.0)
        robot.check_commands(cmd, name)
        rec = predict(empty_like_times(t).with_values(commands=cmd), cal, robot, source=name)
        write_recording(rec, out / "model" / f"{name}.csv")
        plot_recordings({"model": rec}, out / "model" / f"{name}.png",
                        title=f"{name}: the paper's model")
    echo(f"   {len(names)} experiments predicted -> {out / 'model'}")
    return out / "model" / f"{'paper-step-120' if 'paper-step-120' in names else names[0]}.png"


def _interrupted(result) -> None:
    """A record session that Ctrl-C or a signal ended (it sent STOP and closed its recording)
    ends the demo as it would any command: exit 130 or 143, not a stage's error or a run that
    goes on to write its report."""
    if result.reason == "interrupted":
        raise KeyboardInterrupt
    if result.reason == "terminated":
        raise SessionTerminated()


def _record_stage(out: Path, names, echo, env: dict[str, str] | None = None) -> list[Path]:
    from .link.record import format_summary
    from .link.sim_process import record_profile_to_simulated_controller

    truth = out / "robot" / "truth.toml"
    truth.parent.mkdir(parents=True, exist_ok=True)
    truth.write_text(DEMO_TRUTH)
    echo(f"2. record: over the serial protocol to the simulated controller ({truth})")
    paths = []
    kwargs = {"env": env} if env else {}
    for name in names:
        path = out / "recorded" / f"{name}.csv"
        result = record_profile_to_simulated_controller(name, path, effects=truth, **kwargs)
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


def _video_stage(out: Path, recorded: Path, echo) -> Path:
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
    wheels = [w["wheel"] for w in summary["wheels"]]
    video_rec = loop.measurement.recording
    keep = np.zeros(4, dtype=bool)
    keep[[w - 1 for w in wheels]] = True
    shown = {"recorded (telemetry)": rec.with_values(wheel_rpm=np.where(keep, rec.wheel_rpm,
                                                                        np.nan)),
             "measured from the video": video_rec}
    return plot_recordings(shown, video.with_suffix(".png"),
                           title=f"{recorded.stem}: wheel speed from the video",
                           styles={"recorded (telemetry)": "-",
                                   "measured from the video": "."})


def _shadow_stage(out: Path, calibration: Path, echo, env: dict[str, str] | None = None) -> dict:
    from .link.sim_process import record_profile_to_simulated_controller
    from .monitor.live import record_shadow
    from .monitor.plot import plot_shadow

    fault = out / "shadow" / "fault.toml"
    fault.parent.mkdir(parents=True, exist_ok=True)
    fault.write_text(DEMO_FAULT)
    name = "paper-step-60"
    path = out / "shadow" / f"{name}-fault.csv"
    echo(f"6. shadow: {name} with the extended model beside the robot; wheel 2 drops to 80 % "
         "of its gain at 2.5 s")
    robot = load_robot_profile()
    t, cmd = PAPER_EXPERIMENTS[name].sample(50.0)
    obs = record_shadow(calibration, robot, t, cmd, path, on_divergence="stop", echo=echo)
    kwargs = {"env": env} if env else {}
    result = record_profile_to_simulated_controller(name, path, effects=fault, observers=[obs],
                                                    **kwargs)
    _interrupted(result)
    alarms = list(obs.monitor.alarms)
    echo("   " + obs.close().replace("\n", "\n   "))
    echo(f"   the run ended: {result.reason} (exit code {result.exit_code}) -> {path}")
    rec = read_recording(path)
    rec = rec.select(np.isfinite(rec.wheel_rpm[:, 0]))
    model = predict(rec, load_calibration(calibration), robot)
    png = plot_shadow(rec, model, alarms, path.with_suffix(".png"),
                      title=f"shadow mode: wheel 2 at 80 % of its gain from 2.5 s "
                            f"(run ended: {result.reason})", fault_t_s=2.5)
    return {"reason": result.reason, "path": path, "alarms": alarms, "plot": png}


def _diagnose_job(paths: list[Path], calibration: Path | None, names: list[str],
                  jobs: int | None = None) -> tuple:
    """``diagnose`` of recordings ``paths`` from ``calibration`` (default: the paper's);
    returns the diagnosis and its progress lines. A module-level function: the demo's worker
    process runs it."""
    from .identify.diagnose import diagnose
    from .io.timing import read_for_analysis

    lines: list[str] = []
    recs = [read_for_analysis(p) for p in paths]
    cal = load_calibration(calibration) if calibration is not None else load_calibration()
    diag = diagnose(recs, cal, load_robot_profile(), names=names, echo=lines.append, jobs=jobs)
    return diag, lines


def _diagnose_stage(out: Path, recorded: list[Path], calibration: Path, echo,
                    found: tuple | None = None) -> dict:
    """Diagnose the recordings (or take ``found``: the diagnosis and its lines from the
    worker) and write its calibration and report."""
    from .identify.diagnose_report import write_report
    from .io.timing import read_for_analysis
    from .model import save_calibration

    echo("5. diagnose: where the fitted model and the recordings disagree, and why")
    if found is None:
        from .identify.diagnose import diagnose

        recs = [read_for_analysis(p) for p in recorded]
        diag = diagnose(recs, load_calibration(calibration), load_robot_profile(),
                        names=[p.stem for p in recorded], echo=lambda m: echo("   " + m))
    else:
        diag, lines = found
        recs = [read_for_analysis(p) for p in recorded]
        for line in lines:
            echo("   " + line)
    robot = load_robot_profile()
    extended = save_calibration(diag.calibration, out / "diagnose" / "calibration.toml",
                                "extended by mecanum-hil diagnose (demo)")
    report = write_report(diag, recs, out / "diagnose", robot,
                          title="demo: the effect the model lacked")
    named = ", ".join(f"{s.effect} {s.parameters}" for s in diag.steps) or "nothing"
    echo(f"   named: {named}; unexplained: {str(diag.unexplained).lower()}")
    echo(f"   wheel RMSE {diag.rmse_initial:.3f} -> {diag.rmse_final:.3f} rpm "
         f"(the simulated robot's noise: 0.5 rpm); report {report}")
    first = sorted((out / "diagnose").glob("step1-*.png"))
    return {"diagnosis": diag, "report": report, "calibration": extended,
            "plot": first[0] if first else None}


def _worker_warm_up() -> None:
    """The worker's first job: numba's batch simulator compiled once (or loaded from its
    cache), for commands of any layout.

    ``fit`` and ``diagnose`` hand the simulator two kinds of command arrays, a robot's own
    (contiguous, writable) and one stream shared by many coefficient sets (a read-only
    broadcast view), and numba compiles each kind on its own (about 45 s of CPU each on the
    2-core machine). Compiled for the shared kind first, with no further compiling allowed,
    the kernel takes both: numba converts a contiguous array to that type (the same
    arithmetic, the same results). Only this process does so: it runs nothing but the demo's
    diagnoses.
    """
    from ._jit import compiled, load_compiled
    from .model import Calibration, RobotProfile
    from .model.simulate import simulate_batch

    load_compiled("mecanum_hil.model._kernels")
    t = np.arange(50) * 0.01
    cmd = np.tile([60.0, 0.0, 90.0], (t.size, 1))
    simulate_batch(cmd, t, [Calibration(), Calibration(A=15.0)], RobotProfile())
    from .model import _kernels

    compiled(_kernels.simulate_kernel).disable_compile()


class _Worker:
    """A second process for the miniature's compiled work (:class:`~.identify.diagnose.helper
    .Helper`), started first: it compiles numba's simulator while this process records,
    films and fits in the interpreter, then runs the diagnoses. When it fails, a job runs
    here instead (compiled: slower, the same result)."""

    def __init__(self, echo) -> None:
        from .identify.diagnose.helper import Helper

        self.echo = echo
        self.helper = Helper(warm=_worker_warm_up)
        self.waited_s = 0.0

    def submit(self, fn, *args):
        return (self.helper.submit(fn, *args), fn, args)

    def result(self, job):
        from ._jit import forced

        fut, fn, args = job
        start = time.perf_counter()
        try:
            return fut.result()
        except Exception as err:  # the worker failed: the job here
            self.echo(f"   (the worker process failed: {err}; running the job here)")
            with forced("auto"):
                return fn(*args)
        finally:
            self.waited_s += time.perf_counter() - start

    def close(self, interrupted: bool) -> None:
        from .identify.diagnose.helper import release

        release([self.helper], interrupted)


def run_demo(out_dir: str | Path, echo: Callable[[str], None] = print,
             quick: bool = False, full: bool = False) -> dict:
    """Run the demo into ``out_dir``.

    Parameters
    ----------
    out_dir : str or Path
        Folder for every file the demo writes.
    echo : callable
        Prints one line of progress.
    quick : bool
        The default, miniature demo (kept as a name for it).
    full : bool
        The complete demo: all seven of the paper's experiments recorded, the pose stage on
        seven runs at 640x480 and 30 frames/s (several minutes on a 2-core machine).

    Returns
    -------
    dict
        What each stage produced (paths, the diagnosis, how the shadow run ended, the stage
        times in seconds).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    echo(f"mecanum-hil demo{' --full' if full else ''}: writing into {out.resolve()}")
    clock = _Clock(echo)
    if full:
        res = _run_full(out, echo, clock)
    else:
        res = _run_miniature(out, echo, clock)
    report = _write_report(out, res, clock)
    echo(f"done in {clock.total():.0f} s: {report}")
    return {**res, "report": report, "times": dict(clock.times)}


def _model_to_fit(out: Path, names, echo, clock: _Clock, env=None) -> dict:
    """Stages 1-4: model, record, video, fit. Returns the recordings, the fitted
    calibration's path and the pictures."""
    from .identify.files import fit_demo

    with clock.stage("model"):
        model_png = _model_stage(out, echo, names)
    with clock.stage("record"):
        recorded = _record_stage(out, names, echo, env=env)
    with clock.stage("video"):
        video_png = _video_stage(out, recorded[names.index("paper-step-120")], echo)
    with clock.stage("fit"):
        echo("4. fit: A, B, C from the recordings")
        fitted = fit_demo(recorded, out / "fit", echo=lambda m: echo("   " + m))
    return {"recorded": recorded, "calibration": fitted["fit/calibration"],
            "plots": {"model": model_png, "video": video_png, "fit": fitted["fit/report"]}}


def _run_full(out: Path, echo, clock: _Clock) -> dict:
    names = tuple(PAPER_EXPERIMENTS)
    first = _model_to_fit(out, names, echo, clock)
    recorded, cal_path = first["recorded"], first["calibration"]
    with clock.stage("diagnose"):
        diag = _diagnose_stage(out, recorded, cal_path, echo)
    with clock.stage("shadow"):
        shadow = _shadow_stage(out, diag["calibration"], echo)
    with clock.stage("pose"):
        pose = _pose_stage(out, echo)
    return {**first, "names": names, "shadow": shadow, "diagnose": diag, "pose": pose}


def _run_miniature(out: Path, echo, clock: _Clock) -> dict:
    """The loop in miniature. Only diagnose needs numba's compiled simulator (its searches
    run thousands of simulations), and compiling it takes most of a minute: a worker process
    starts compiling at once, on the other core, while this process runs every other stage
    in the interpreter (numba never loaded here: the simulated controller, the fit's numpy
    path and the shadow monitor each cost less than their compile would)."""
    from ._jit import forced

    names = MINI_EXPERIMENTS
    worker = _Worker(echo)
    interrupted = False
    try:
        with forced("never"):
            echo("   (a worker process compiles numba's simulator for diagnose meanwhile)")
            first = _model_to_fit(out, names, echo, clock, env=INTERPRETED_ENV)
            recorded, cal_path = first["recorded"], first["calibration"]
            wheel_job = worker.submit(_diagnose_job, recorded, cal_path,
                                      [p.stem for p in recorded], 1)
            pose_dir = out / "pose"
            with clock.stage("pose videos"):
                echo("7. pose (first half, while diagnose's simulator compiles): a robot that "
                     "slips, filmed from above; measure-pose on each video")
                runs = {p.name: p for p in pose_profiles()}
                measured, errors = pose_videos(
                    pose_dir, lambda m: echo("   " + m),
                    profiles=[runs[n] for n in MINI_POSE_RUNS], **MINI_POSE_VIDEO)
            pose_job = worker.submit(_diagnose_job, measured, None,
                                     [p.stem for p in measured], 1)
            with clock.stage("diagnose"):
                diag = _diagnose_stage(out, recorded, cal_path, echo,
                                       found=worker.result(wheel_job))
            with clock.stage("shadow"):
                shadow = _shadow_stage(out, diag["calibration"], echo, env=INTERPRETED_ENV)
            with clock.stage("pose"):
                echo("7. pose (second half): diagnose on the recordings filled from the videos")
                pdiag = worker.result(pose_job)[0]
                plots = pose_plots(pose_dir, measured, pdiag, lambda m: echo("   " + m))
        echo(f"   (waited {worker.waited_s:.1f} s for the worker in all)")
    except (KeyboardInterrupt, SessionTerminated):
        interrupted = True
        raise
    finally:
        worker.close(interrupted)
    pose = {"measured": measured, "diagnosis": pdiag, "errors": errors, "plots": plots}
    return {**first, "names": names, "shadow": shadow, "diagnose": diag, "pose": pose}


def _rel(out: Path, path) -> str:
    return Path(path).resolve().relative_to(out.resolve()).as_posix()


def _write_report(out: Path, res: dict, clock: _Clock) -> Path:
    """``REPORT.md``: each stage in a sentence with its picture, then the summary table."""
    cal = load_calibration(res["calibration"])
    d = res["diagnose"]["diagnosis"]
    lines = [*_report_intro(out, res, clock), *_report_fit_diagnose(out, res, cal, d),
             *_report_shadow_pose(out, res), *_report_summary(res, cal, d)]
    path = out / "REPORT.md"
    path.write_text("\n".join(lines))
    return path


def _first_alarm(shadow: dict):
    """The shadow run's first alarm, or None."""
    return shadow["alarms"][0] if shadow["alarms"] else None


def _pose_named(pose: dict) -> tuple[str, tuple]:
    """The effects the pose stage's diagnosis named ("nothing" for none) and its fitted
    efficiency (vx, vy, wz) [-]."""
    pd = pose["diagnosis"]
    return ", ".join(s.effect for s in pd.steps) or "nothing", pd.calibration.effects.efficiency


def _report_intro(out: Path, res: dict, clock: _Clock) -> list[str]:
    """The report's title, what the demo took [s], and its stages 1 to 3 (model, record,
    video)."""
    names, plots = res["names"], res["plots"]
    took = ", ".join(f"{k} {v:.0f} s" for k, v in clock.times.items())
    return [
        "# mecanum-hil demo",
        "",
        "The whole loop on the simulated robot. Its hidden truth (`robot/truth.toml`, read only "
        "by the simulated controller) is the paper's model plus a drive ceiling at 115 rpm and "
        "0.5 rpm of encoder noise; fit and diagnose have to find the ceiling from the "
        "recordings.",
        f"The demo took {clock.total():.0f} s ({took}).",
        "",
        "## 1. model",
        "",
        f"The paper's model predicts the paper's experiments ({len(names)} here): wheel "
        "speeds, path and heading.",
        "",
        f"![the paper's model]({_rel(out, plots['model'])})",
        "",
        "## 2. record",
        "",
        f"{len(names)} experiments ({', '.join(names)}) go over the serial protocol, through a "
        "pseudo-terminal, to the simulated controller in another process; it answers with "
        "telemetry at 100 Hz. At 120 rpm the wheels stop near 115 rpm: the ceiling.",
        "",
        f"![recorded]({_rel(out, _named(res['recorded'], 'paper-step-120').with_suffix('.png'))})",
        "",
        "## 3. video",
        "",
        "The 120 rpm recording is rendered as a camera video of a wheel marker "
        "(`video/paper-step-120.mp4`) and measured back: the wheel speed from the video "
        "follows the telemetry.",
        "",
        f"![video]({_rel(out, plots['video'])})",
        "",
    ]


def _report_fit_diagnose(out: Path, res: dict, cal, d) -> list[str]:
    """The report's stages 4 and 5: the linear fit ``cal`` and the diagnosis ``d``."""
    named = ", ".join(f"{s.effect} ({_params_text(s.parameters)})" for s in d.steps) or "nothing"
    lines = [
        "## 4. fit",
        "",
        f"The paper's linear model fitted to the recordings: A = {cal.A:.4g}, "
        f"B = {cal.B:.4g}, C = {cal.C:.4g} (fit {cal.info.get('fit_percent', float('nan')):.1f} "
        "%). It cannot follow the ceiling, so it settles short of the turn's level: a gap.",
        "",
        f"![fit]({_rel(out, res['plots']['fit'])})",
        "",
        "## 5. diagnose",
        "",
        f"diagnose names {named}: wheel RMSE {d.rmse_initial:.3f} -> {d.rmse_final:.3f} rpm "
        f"against 0.5 rpm of noise (report: `diagnose/report.md`).",
        "",
    ]
    if res["diagnose"].get("plot") is not None:
        lines += [f"![diagnose]({_rel(out, res['diagnose']['plot'])})", ""]
    return lines


def _report_shadow_pose(out: Path, res: dict) -> list[str]:
    """The report's stages 6 and 7: the shadow run with its injected fault, and the pose
    measured from video."""
    shadow, pose = res["shadow"], res["pose"]
    first = _first_alarm(shadow)
    pnamed, eff = _pose_named(pose)
    lines = [
        "## 6. shadow",
        "",
        "A live run with the diagnosed model beside the robot; wheel 2 drops to 80 % of its "
        "gain at 2.5 s. "
        + (f"Shadow mode raises an alarm on {first.channel} at {first.t_s:.2f} s "
           f"(residual {first.residual:+.2f} {first.unit}) and the run ends: "
           f"{shadow['reason']}." if first else
           f"Shadow mode raises no alarm; the run ends: {shadow['reason']}."),
        "",
        f"![shadow]({_rel(out, shadow['plot'])})",
        "",
        "## 7. pose",
        "",
        f"A second simulated robot slips (its body moves at 90 / 80 / 85 % of what its wheels "
        f"say); {len(pose['measured'])} runs are filmed from above, measure-pose fills each "
        f"recording's pose from its video alone, and diagnose names {pnamed} (efficiency "
        f"{eff[0]:.3f}, {eff[1]:.3f}, {eff[2]:.3f}).",
        "",
    ]
    for png in pose["plots"]:
        lines += [f"![pose]({_rel(out, png)})", ""]
    return lines


def _report_summary(res: dict, cal, d) -> list[str]:
    """The report's summary table, a row per stage."""
    shadow = res["shadow"]
    first = _first_alarm(shadow)
    pnamed, eff = _pose_named(res["pose"])
    return [
        "## Summary",
        "",
        "| stage | result | files |",
        "|---|---|---|",
        "| 1. model | the paper's experiments on the paper's model | `model/` |",
        f"| 2. record | {len(res['names'])} experiments over the serial protocol | `recorded/` |",
        "| 3. video | a recording rendered and measured back | `video/` |",
        f"| 4. fit | A = {cal.A:.4g}, B = {cal.B:.4g}, C = {cal.C:.4g}, "
        f"fit {cal.info.get('fit_percent', float('nan')):.2f} % | `fit/` |",
        f"| 5. diagnose | named: {', '.join(s.effect for s in d.steps) or 'nothing'}; "
        f"RMSE {d.rmse_initial:.3f} -> {d.rmse_final:.3f} rpm | `diagnose/report.md` |",
        "| 6. shadow | fault injected; "
        + (f"alarm {first.channel} at {first.t_s:.2f} s; " if first else "no alarm; ")
        + f"run ended: {shadow['reason']} | `shadow/` |",
        f"| 7. pose | slip hidden, pose from overhead videos only; diagnose named: {pnamed}, "
        f"efficiency ({eff[0]:.3f}, {eff[1]:.3f}, {eff[2]:.3f}) | `pose/` |",
        "",
    ]


def _named(paths: list[Path], stem: str) -> Path:
    """The path among ``paths`` named ``stem`` (else the first)."""
    return next((p for p in paths if p.stem == stem), paths[0])


def _params_text(params: dict) -> str:
    return ", ".join(f"{k} = {v:.4g}" if isinstance(v, float) else f"{k} = {v}"
                     for k, v in params.items())


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
               size: tuple[int, int] = (640, 480), profiles=None, fps: float = 30.0) -> dict:
    """Slip seen only by an overhead camera.

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
    measured, errors = pose_videos(out_dir, echo, size=size, profiles=profiles, fps=fps)
    diag = _diagnose_pose(measured)
    return {"measured": measured, "diagnosis": diag, "errors": errors,
            "plots": pose_plots(out_dir, measured, diag, echo)}


def pose_videos(out_dir: str | Path, echo: Callable[[str], None] = print, *,
                size: tuple[int, int] = (640, 480), profiles=None,
                fps: float = 30.0) -> tuple[list[Path], dict]:
    """Steps 1-3 of :func:`pose_story`: the recordings with their pose measured from the
    videos (paths under ``measured/``) and each run's pose error against the simulator's."""
    from .identify.campaign import paper_campaign
    from .io.pose_track import fill_pose, onset_offset
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
            width_px=size[0], height_px=size[1], fps=fps, tilt_deg=30.0, noise_std=2.0,
            seed=k, camera_start_s=0.2))
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
    return measured, errors


def _diagnose_pose(measured: list[Path]):
    """Step 4 of :func:`pose_story`: ``diagnose`` on the recordings filled from the videos."""
    from .identify.diagnose import diagnose
    from .io.timing import read_for_analysis

    recs = [read_for_analysis(p) for p in measured]
    return diagnose(recs, load_calibration(), load_robot_profile(),
                    names=[Path(p).stem for p in measured])


def pose_plots(out_dir: str | Path, measured: list[Path], diag,
               echo: Callable[[str], None] = print) -> list[Path]:
    """The end of :func:`pose_story`: what ``diagnose`` found, and the paper's whole-robot
    experiments among ``measured`` plotted against the model without and with it."""
    from .identify.diagnose import initial_pose_at_rest
    from .io.timing import read_for_analysis

    out = Path(out_dir)
    rob, cal = load_robot_profile(), load_calibration()
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
    return plots


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
