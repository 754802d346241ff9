"""fit refuses data it cannot trust: a recording in motion at its start, a model worse than
the mean (issue 5, bad input) — a clear error, exit 1, and no calibration written."""

import subprocess
import sys

import numpy as np
import pytest

from mecanum_hil.errors import FitError
from mecanum_hil.identify.fit import fit
from mecanum_hil.io.recording import Recording, write_recording
from mecanum_hil.model import RobotProfile

ROBOT = RobotProfile()


def steady(n_rpm=60.0, seconds=2.0, rate=100.0, seed=0):
    t = np.arange(int(seconds * rate) + 1) / rate
    rng = np.random.default_rng(seed)
    wheels = n_rpm + rng.normal(0, 0.5, (t.size, 4))
    cmds = np.tile([n_rpm, 0.0, 90.0], (t.size, 1))
    return Recording(t, cmds, wheels, np.full((t.size, 3), np.nan))


def test_a_recording_already_in_motion_is_refused():
    with pytest.raises(FitError, match="starts in motion"):
        fit([steady()], ROBOT)


def test_one_noisy_first_sample_at_rest_is_not_motion():
    # 1 rpm of encoder noise: a first sample of 2.5 rpm on one wheel is noise, not motion
    t = np.arange(301) / 100.0
    rng = np.random.default_rng(1)
    cmds = np.tile([0.0, 0.0, 90.0], (t.size, 1))
    cmds[30:, 0] = 30.0
    clean = np.where(t[:, None] >= 0.3, 30.0 * (1 - np.exp(-(t[:, None] - 0.3) / 0.1)), 0.0)
    wheels = clean + rng.normal(0, 1.0, (t.size, 4))
    wheels[0, 2] = 2.5
    res = fit([Recording(t, cmds, wheels, np.full((t.size, 3), np.nan))], ROBOT)
    assert res.fit_percent > 80


def test_a_model_worse_than_the_mean_is_refused():
    rec = steady()
    t = rec.t_s
    # the wheels move, but nothing like the commands: a step command, a sine response
    sine = np.where(t >= 0.5, 20 * np.sin(2 * np.pi * 3 * t), 0.0)
    wheels = np.zeros((t.size, 4)) + sine[:, None]
    cmds = rec.commands.copy()
    cmds[:50, 0] = 0.0
    with pytest.raises(FitError, match="worse than their mean"):
        fit([rec.with_values(wheel_rpm=wheels, commands=cmds)], ROBOT)


def test_cli_writes_nothing(tmp_path):
    src = write_recording(steady(), tmp_path / "moving.csv")
    out = tmp_path / "cal.toml"
    r = subprocess.run([sys.executable, "-m", "mecanum_hil", "fit", str(src), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stderr.startswith("error: ") and "starts in motion" in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
