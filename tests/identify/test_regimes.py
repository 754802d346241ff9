"""The localisation's counts: the wheel samples it shares out, in three groupings."""

from __future__ import annotations

import numpy as np

from mecanum_hil.identify.regimes import REGIME_GROUPS, localise
from mecanum_hil.io.recording import empty_like_times
from mecanum_hil.model import Calibration, RobotProfile
from mecanum_hil.prediction import predict
from mecanum_hil.profiles import step

ROBOT = RobotProfile()


def _measured_on_every_other_row():
    """A recorded run's shape: command rows without measurements between telemetry rows."""
    t, cmd = step(60.0, duration_s=1.0, rest_s=0.2, stop_s=0.5).sample(100.0)
    rec = empty_like_times(t).with_values(commands=cmd)
    model = predict(rec, Calibration(), ROBOT)
    wheels = model.wheel_rpm + np.random.default_rng(0).normal(0, 0.3, model.wheel_rpm.shape)
    wheels[::2] = np.nan
    wheels[1::4, 3] = np.nan  # a wheel that misses some readings
    return rec.with_values(wheel_rpm=wheels), model


def test_every_grouping_shares_out_all_measured_wheel_samples():
    rec, model = _measured_on_every_other_row()
    loc = localise([rec], [model], ROBOT)
    measured = int(np.isfinite(rec.wheel_rpm).sum())
    assert measured not in (len(rec), 4 * len(rec))  # rows and wheel samples differ here
    assert loc.n_samples == measured
    for group, names in REGIME_GROUPS.items():
        assert sum(loc.regimes[n].n_samples for n in names) == measured, group
    assert set(loc.regimes) == {n for names in REGIME_GROUPS.values() for n in names}
    lines = loc.lines()
    header = next(line for line in lines if line.startswith("per regime"))
    assert f"all {measured} wheel samples" in header
    assert [line for line in lines if line.startswith(" by ")] == [
        f" by {group}:" for group in REGIME_GROUPS]
