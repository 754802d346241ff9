"""fit refuses data it cannot trust: a model worse than the mean (bad input), a
recording in motion at its start for the paper's grid — a clear error, exit 1, and no
calibration written; lsq starts a recording in motion in steady state at its measured speeds,
and a frozen reading at the start is not motion."""

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


def test_a_recording_already_in_motion_is_refused_by_the_paper_grid():
    with pytest.raises(FitError, match="starts in motion"):
        fit([steady()], ROBOT, method="paper-grid")


def _moving_start(frozen: int = 0, seed: int = 2):
    """The paper's model in steady state at 40 rpm, a step to 80 rpm at 0.5 s; optionally the
    first ``frozen`` readings stuck at a stale 55 rpm."""
    from mecanum_hil.model import Calibration
    from mecanum_hil.model.kinematics import command_to_wheels
    from mecanum_hil.model.simulate import simulate, steady_state

    t = np.arange(301) / 100.0
    cmds = np.tile([40.0, 0.0, 90.0], (t.size, 1))
    cmds[50:, 0] = 80.0
    cal = Calibration()
    tg = command_to_wheels(cmds[:1, 0], cmds[:1, 1], cmds[:1, 2], ROBOT.k)[0]
    truth = simulate(cmds, t, cal, ROBOT, initial_state=steady_state(cal, tg, tg)[None],
                     initial_command=cmds[0]).wheel_rpm[0]
    wheels = truth + np.random.default_rng(seed).normal(0, 0.3, truth.shape)
    wheels[:frozen] = 55.0
    return Recording(t, cmds, wheels, np.full((t.size, 3), np.nan))


def test_a_recording_in_motion_starts_in_steady_state():
    res = fit([_moving_start()], ROBOT)
    assert res.rmse_rpm < 0.4
    assert res.calibration.A == pytest.approx(14.7, rel=0.05)
    assert res.calibration.C == pytest.approx(303.0, rel=0.05)


def test_a_frozen_reading_at_the_start_is_not_motion():
    from mecanum_hil.prediction import frozen_start, initial_wheel_rpm

    rec = _moving_start(frozen=12)
    assert frozen_start(rec)[:12].all() and not frozen_start(rec)[12:].any()
    # the frozen wheels are not taken as moving at 55 rpm: they start at rest
    np.testing.assert_array_equal(initial_wheel_rpm(rec), 0.0)
    res = fit([rec], ROBOT)  # the stale samples are left out of the fit
    assert res.n_samples == 4 * (len(rec) - 12)


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
    r = subprocess.run([sys.executable, "-m", "mecanum_hil", "fit", str(src), "--out", str(out),
                        "--method", "paper-grid"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and r.stderr.startswith("error: ") and "starts in motion" in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
