"""Fit recordings on disk: read them, fit, write the calibration and the report plot (the edge).

:func:`fit_files` is what ``mecanum-hil fit`` and the demo call.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.recording import Recording, read_recording
from ..io.timing import read_for_analysis
from ..model.calibration import Calibration, save_calibration
from ..model.robot import RobotProfile
from ..model.simulate import simulate
from ..prediction import start_pose
from .fit import FitResult, fit


@dataclass(frozen=True)
class FitOutput:
    """A fit and the files written for it."""

    result: FitResult
    calibration_path: Path
    report_path: Path | None


def plot_fit(result: FitResult, recordings: Sequence[Recording], robot: RobotProfile,
             path: str | Path, labels: Sequence[str] | None = None) -> Path:
    """Measured (dots) against fitted (lines) wheel speeds, one panel per recording.

    Drawn with Pillow (:mod:`mecanum_hil.plots.raster`): ``fit`` writes it on every run, and
    matplotlib's import alone would double the command's time.

    Parameters
    ----------
    result : FitResult
        The fit; its calibration drives the model.
    recordings : sequence of Recording
        The recordings that were fitted.
    robot : RobotProfile
        Geometry for the kinematics.
    path : str or Path
        PNG to write.
    labels : sequence of str, optional
        Panel titles (default: the fit's data sources).
    """
    from ..plots.raster import COLOURS, Panel, Series, write_chart

    cal = result.calibration
    labels = list(labels or cal.info.get("sources", []))
    per = list(cal.info.get("fit_percent_per_recording", []))
    panels = []
    for k, rec in enumerate(recordings):
        model = simulate(rec.commands, rec.t_s, cal, robot,
                         initial_pose=start_pose(rec)).wheel_rpm[0]
        series = []
        for i in range(4):
            meas = rec.wheel_rpm[:, i]
            if not np.isfinite(meas).any():
                continue
            series += [Series(rec.t_s, meas, COLOURS[i], f"wheel {i + 1} measured", dots=True),
                       Series(rec.t_s, model[:, i], COLOURS[i], f"wheel {i + 1} fitted")]
        title = labels[k] if k < len(labels) else f"recording {k + 1}"
        if k < len(per):
            title = f"{Path(title).name}: fit {per[k]:.1f} %"
        panels.append(Panel(tuple(series), title, "t [s]", "wheel speed [rpm]"))
    return write_chart(path, panels, ncols=min(len(panels), 3),
                       title=f"fit ({result.method}): A={cal.A:.4g} B={cal.B:.4g} C={cal.C:.4g}, "
                             f"RMSE {result.rmse_rpm:.3g} rpm, fit {result.fit_percent:.1f} %")


def fit_files(paths: Sequence[str | Path], out: str | Path, robot: RobotProfile,
              method: str = "lsq", calibration: Calibration | None = None,
              report: str | Path | None = None, **grid_options) -> FitOutput:
    """Fit recordings (CSV files) and write the calibration TOML and a report PNG.

    Nothing is written when the fit fails.

    Parameters
    ----------
    paths : sequence of str or Path
        Recording CSV files.
    out : str or Path
        Calibration TOML to write (readable by every ``--calibration``).
    robot : RobotProfile
        Geometry for the kinematics.
    method : {"lsq", "paper-grid"}
        Fitting method.
    calibration : Calibration, optional
        Effects held fixed during the fit.
    report : str or Path, optional
        Report PNG to write; ``None`` writes none.
    **grid_options
        Grid settings for ``paper-grid`` (see :func:`mecanum_hil.identify.grid.paper_grid`).

    Returns
    -------
    FitOutput
    """
    if report is not None and Path(report).suffix.lower() != ".png":
        # checked before the fit: the report is drawn as PNG only (plots/raster.py)
        raise ConfigError(f"{report}: the report is a PNG image: give a name ending in .png")
    recordings = [read_for_analysis(p) for p in paths]
    sources = [str(p) for p in paths]
    result = fit(recordings, robot, method, calibration, sources=sources, **grid_options)
    header = (f"Written by mecanum-hil fit ({result.method}) from {len(sources)} recording(s).\n"
              f"Fit {result.fit_percent:.2f} %, RMSE {result.rmse_rpm:.4g} rpm over "
              f"{result.n_samples} wheel samples.")
    cal_path = save_calibration(result.calibration, out, header=header)
    report_path = (plot_fit(result, recordings, robot, report, sources)
                   if report is not None else None)
    return FitOutput(result, cal_path, report_path)


def fit_demo(recording_paths: Sequence[str | Path], out_dir: str | Path,
             robot: RobotProfile | None = None, echo=print,
             method: str = "lsq") -> dict[str, Path]:
    """The demo's fitting step: fit its recordings, write ``calibration.toml`` and ``report.png``.

    Recordings without any measured wheel speed (pure command profiles) are left out.

    Parameters
    ----------
    recording_paths : sequence of str or Path
        The recordings the demo made.
    out_dir : str or Path
        Folder for ``calibration.toml`` and ``report.png``.
    robot : RobotProfile, optional
        Geometry (default: the shipped robot profile).
    echo : callable
        Prints one progress line.
    method : {"lsq", "paper-grid"}
        Fitting method.

    Returns
    -------
    dict
        ``{"fit/calibration": path, "fit/report": path}``.
    """
    from ..errors import FitError
    from ..model import load_robot_profile

    robot = robot or load_robot_profile()
    usable = [Path(p) for p in recording_paths
              if np.isfinite(read_recording(p).wheel_rpm).any()]
    if not usable:
        raise FitError("the demo made no recording with measured wheel speeds to fit")
    out = Path(out_dir)
    res = fit_files(usable, out / "calibration.toml", robot, method, report=out / "report.png")
    c = res.result.calibration
    echo(f"   fit ({method}) of {len(usable)} recordings: A={c.A:.4g} B={c.B:.4g} C={c.C:.4g}, "
         f"fit {res.result.fit_percent:.1f} %, RMSE {res.result.rmse_rpm:.3g} rpm -> "
         f"{res.calibration_path} , {res.report_path.name}")
    for w in res.result.warnings:
        echo(f"   warning: {w}")
    return {"fit/calibration": res.calibration_path, "fit/report": res.report_path}
