"""Plain helpers of the vision tests (a module of its own: ``from conftest import`` picks
whichever ``conftest`` was imported first when other test folders run in the same session)."""

from __future__ import annotations

import numpy as np

from mecanum_hil.io.recording import Recording, empty_like_times


def steady(rpm: float, duration_s: float = 2.0) -> Recording:
    """All four wheels at a constant speed."""
    t = np.arange(0.0, duration_s + 1e-9, 0.01)
    return empty_like_times(t).with_values(wheel_rpm=np.full((t.size, 4), float(rpm)))


def rms(a: np.ndarray, b: np.ndarray) -> float:
    err = a - b
    return float(np.sqrt(np.nanmean(err ** 2)))
