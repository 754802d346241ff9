"""The closed loop for tests and the demo: a recording -> a rendered video -> measured back."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.recording import Recording
from .measure import MeasureOptions, VideoMeasurement, align_with_recording, measure_video
from .render import RenderResult, RenderSettings, render_video


@dataclass(frozen=True)
class LoopResult:
    """What :func:`render_and_measure` produced.

    Attributes
    ----------
    render : RenderResult
        The video and its truth.
    measurement : VideoMeasurement
        The measured recording (video clock) and the summary.
    merged : Recording or None
        The input recording with the measured wheels merged in (when aligned).
    rms_error_rpm : dict
        RMS error of each shown wheel against the truth, over frames with a speed [rpm].
    """

    render: RenderResult
    measurement: VideoMeasurement
    merged: Recording | None
    rms_error_rpm: dict[int, float]


def render_and_measure(rec: Recording, video_path: str | Path,
                       settings: RenderSettings | None = None,
                       options: MeasureOptions | None = None, align: bool = True,
                       calibration=None, robot=None, progress=None) -> LoopResult:
    """Render a recording's wheels to a video, measure it back, and align it with the recording.

    Parameters
    ----------
    rec : Recording
        Needs the shown wheels' columns (e.g. a recording from ``record`` on the simulated robot,
        or a prediction).
    video_path : str or Path
        Video to write (``.mp4`` or ``.avi``).
    settings : RenderSettings, optional
        Camera and realism knobs; by default wheel 1 at 320x240, 30 fps.
    options : MeasureOptions, optional
        By default one region per shown wheel (the renderer's placement) and automatic markers.
    align : bool
        Also estimate the clock offset against ``rec`` and merge (the model's prediction is the
        reference when ``calibration`` and ``robot`` are given and ``rec`` has commands).
    """
    s = settings or RenderSettings()
    res = render_video(rec, video_path, s, progress=progress)
    if options is None:
        options = MeasureOptions(rois=tuple((p.wheel, p.roi) for p in res.placements),
                                 invert=s.mirror)
    meas = measure_video(video_path, options)
    merged = None
    if align:
        merged, meas = align_with_recording(meas, rec, calibration, robot)
    rms = {}
    for k, wheel in enumerate(s.wheels):
        err = meas.recording.wheel_rpm[:, wheel - 1] - res.wheel_rpm[:, k]
        rms[wheel] = float(np.sqrt(np.nanmean(err ** 2))) if np.isfinite(err).any() else np.nan
    return LoopResult(res, meas, merged, rms)
