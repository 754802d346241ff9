"""Camera video in (``measure-video``) and rendered video out (``render-video``)."""

from __future__ import annotations

from .detect import MarkerSpec, parse_hsv, parse_roi
from .measure import MeasureOptions, VideoMeasurement, measure_video
from .render import RenderResult, RenderSettings, render_video, wheel_placements

__all__ = [
    "MarkerSpec", "MeasureOptions", "RenderResult", "RenderSettings", "VideoMeasurement",
    "measure_video", "parse_hsv", "parse_roi", "render_video", "wheel_placements",
]
