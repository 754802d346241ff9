"""Rendered videos with known truth, shared by the vision tests."""

from __future__ import annotations

import pytest

from mecanum_hil.io.recording import Recording, empty_like_times
from mecanum_hil.model import load_calibration, load_robot_profile
from mecanum_hil.prediction import predict
from mecanum_hil.profiles import PAPER_EXPERIMENTS


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

