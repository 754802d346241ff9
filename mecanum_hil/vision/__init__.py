"""Camera video in (``measure-video``) and rendered video out (``render-video``)."""

from __future__ import annotations

from .detect import MarkerSpec, parse_hsv, parse_roi
from .loop import LoopResult, render_and_measure
from .measure import MeasureOptions, VideoMeasurement, align_with_recording, measure_video
from .render import RenderResult, RenderSettings, render_video, wheel_placements

__all__ = [
    "LoopResult", "MarkerSpec", "MeasureOptions", "RenderResult", "RenderSettings",
    "VideoMeasurement", "align_with_recording", "measure_video", "parse_hsv", "parse_roi",
    "render_and_measure", "render_video", "wheel_placements",
]
