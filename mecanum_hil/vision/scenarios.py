"""Wheel-speed scenarios for the renderer: how real filming sessions move a wheel (pure).

The paper's experiments start every run from standstill; users film wheels that ramp up slowly,
stop and restart, turn backwards, or for a moment turn faster than the camera can follow. Each
scenario is a recording with all four wheel columns filled (the same speed on each), for
``render-video --scenario NAME`` and the tests.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import VideoError
from ..io.recording import Recording, empty_like_times

#: Breakpoints ``(times [s], speeds [rpm])`` of each scenario; linear in between.
SCENARIOS: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    # At rest for 1 s, then 12 rpm/s up to 60 rpm (a slow start measure-video must follow), held.
    "slow-start": ((0.0, 1.0, 6.0, 10.0), (0.0, 0.0, 60.0, 60.0)),
    # Up, a stop, a restart backwards.
    "stop-restart": ((0.0, 1.0, 4.0, 5.0, 7.0, 8.0, 10.0, 12.0),
                     (0.0, 0.0, 36.0, 36.0, 0.0, 0.0, -30.0, -30.0)),
    # Forwards, through zero, backwards.
    "reverse": ((0.0, 2.0, 4.0, 6.0), (45.0, 45.0, -45.0, -45.0)),
    # 300 rpm, briefly up to 1100 rpm (beyond 900 rpm, the limit at 30 fps) and back.
    "through-limit": ((0.0, 2.0, 3.0, 4.0, 6.0), (300.0, 300.0, 1100.0, 300.0, 300.0)),
}


def scenario_recording(name: str, rate_hz: float = 100.0) -> Recording:
    """The recording of a named scenario, sampled at ``rate_hz`` [Hz].

    Raises
    ------
    VideoError
        Unknown scenario name.
    """
    if name not in SCENARIOS:
        raise VideoError(f"unknown scenario '{name}' (one of {', '.join(SCENARIOS)})")
    times, speeds = SCENARIOS[name]
    t = np.arange(0.0, times[-1] + 0.5 / rate_hz, 1.0 / rate_hz)
    rpm = np.interp(t, times, speeds)
    return empty_like_times(t, {"source": f"mecanum-hil scenario {name}"}).with_values(
        wheel_rpm=np.repeat(rpm[:, None], 4, axis=1))


def recording_or_scenario(text: str | Path) -> Recording:
    """``scenario:NAME`` as :func:`scenario_recording`, anything else read as a recording."""
    from ..io.recording import read_recording

    name = str(text)
    if name.startswith("scenario:"):
        return scenario_recording(name.split(":", 1)[1])
    return read_recording(Path(text))


def parse_hide(items: list[str]) -> tuple[tuple[float, float], ...]:
    """``["A-B", ...]`` (seconds, video clock) as occlusion intervals."""
    out = []
    for item in items:
        try:
            a, b = (float(v) for v in item.split("-", 1))
        except ValueError:
            raise VideoError(f"--hide '{item}': expected A-B in seconds, e.g. 2-2.5") from None
        if not b > a >= 0:
            raise VideoError(f"--hide '{item}': need 0 <= A < B")
        out.append((a, b))
    return tuple(out)


def truth_extra(result) -> dict[str, list[str]]:
    """Extra truth columns of a :class:`~mecanum_hil.vision.render.RenderResult`: each shown
    wheel's ``wheelN_marker_visible`` (share in view) and ``camera_dx_px``/``camera_dy_px``."""
    extra = {}
    for k, wheel in enumerate(result.settings.wheels):
        extra[f"wheel{wheel}_marker_visible"] = [f"{v:.3f}" for v in result.marker_visible[:, k]]
    for j, axis in enumerate("xy"):
        extra[f"camera_d{axis}_px"] = [f"{v:.3f}" for v in result.camera_offset_px[:, j]]
    return extra
