"""Rendered videos with known truth, shared by the vision tests."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.io.recording import Recording, empty_like_times
from mecanum_hil.model import load_calibration, load_robot_profile
from mecanum_hil.prediction import predict
from mecanum_hil.profiles import PAPER_EXPERIMENTS


def steady(rpm: float, duration_s: float = 2.0) -> Recording:
    """All four wheels at a constant speed."""
    t = np.arange(0.0, duration_s + 1e-9, 0.01)
    return empty_like_times(t).with_values(wheel_rpm=np.full((t.size, 4), float(rpm)))


@pytest.fixture(scope="session")
def model():
    return load_calibration(), load_robot_profile()


@pytest.fixture(scope="session")
def paper(model):
    """The model's prediction of a paper experiment by name (the truth the videos show)."""
    cal, rob = model
    cache: dict[str, Recording] = {}

    def get(name: str) -> Recording:
        if name not in cache:
            t, cmd = PAPER_EXPERIMENTS[name].sample(100.0)
            cache[name] = predict(empty_like_times(t).with_values(commands=cmd), cal, rob)
        return cache[name]

    return get


def rms(a: np.ndarray, b: np.ndarray) -> float:
    err = a - b
    return float(np.sqrt(np.nanmean(err ** 2)))
