"""The monitor's streamed model equals the simulator, sample by sample, for any sample times."""

import numpy as np
import pytest

from mecanum_hil.model import Calibration, Effects, simulate
from mecanum_hil.model.motor import discretise
from mecanum_hil.monitor import ShadowConfig, ShadowMonitor
from mecanum_hil.monitor._kernel import discretise_step


@pytest.mark.parametrize("coeffs", [(14.7, 16.1, 303.0), (10.0, 10.0, 100.0), (0.0, 5.0, 6.25),
                                    (1.0, 1.0, 100.0), (30.0, 20.0, 100.0), (5.0, 0.0, 1.0)])
@pytest.mark.parametrize("h", [1e-5, 1e-3, 0.00731, 0.02, 0.5])
def test_closed_form_discretisation_equals_expm(coeffs, h):
    # real, repeated (0, 5, 6.25) and complex poles
    out = np.zeros(10)
    discretise_step(*coeffs, h, out)
    ref = discretise(*coeffs, h)[:10]
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-15)


def _random_run(seed, n=400):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.002, 0.02, n))
    t -= t[0]
    cmd = np.column_stack([np.repeat(rng.uniform(-80, 80, n // 10), 10),
                           np.repeat(rng.uniform(-30, 30, n // 10), 10),
                           np.repeat(rng.uniform(0, 360, n // 10), 10)])
    return t, cmd


EFFECT_CASES = {
    "none": Effects(),
    "dead_time": Effects(dead_time_s=0.037),
    "saturation": Effects(top_speed_rpm=70.0),
    "rate_limit": Effects(rate_limit_rpm_per_s=300.0),
    "all": Effects(dead_time_s=0.05, top_speed_rpm=70.0, rate_limit_rpm_per_s=300.0,
                   deadband_rpm=5.0, gains=(1.0, 0.8, 1.1, 1.0), efficiency=(0.9, 0.8, 0.95)),
    # the drive's own dynamics: shadow plays the model simulate plays
    "controller_period": Effects(controller_period_s=0.007),
    "drive_lag": Effects(drive_lag_s=0.03),
    "breakaway": Effects(breakaway_rpm_per_s=2500.0),
    "drive_all": Effects(controller_period_s=0.005, drive_lag_s=0.02, breakaway_rpm_per_s=1500.0,
                         dead_time_s=0.02, top_speed_rpm=70.0, rate_limit_rpm_per_s=300.0),
    "braking_limit": Effects(braking_limit_rpm_per_s=600.0),
    "braking_all": Effects(braking_limit_rpm_per_s=800.0, controller_period_s=0.006,
                           breakaway_rpm_per_s=1200.0, drive_lag_s=0.015, dead_time_s=0.02),
    "fast_decay": Effects(coast_decel_rpm_per_s=600.0, no_load_rpm=150.0),
    "fast_decay_all": Effects(coast_decel_rpm_per_s=600.0, no_load_rpm=150.0,
                              controller_period_s=0.006, breakaway_rpm_per_s=300.0,
                              drive_lag_s=0.015, dead_time_s=0.02, top_speed_rpm=70.0),
    "windup": Effects(windup_top_speed_rpm=70.0),
    "windup_all": Effects(windup_top_speed_rpm=70.0, controller_period_s=0.006,
                          breakaway_rpm_per_s=300.0, drive_lag_s=0.015, dead_time_s=0.02,
                          braking_limit_rpm_per_s=800.0),
    "friction": Effects(friction_rpm_per_s=500.0),
    "friction_all": Effects(friction_rpm_per_s=500.0, controller_period_s=0.006,
                            breakaway_rpm_per_s=800.0, drive_lag_s=0.015, dead_time_s=0.02,
                            windup_top_speed_rpm=70.0),
    "drive_deadband": Effects(drive_deadband_rpm=20.0, friction_rpm_per_s=300.0),
    "drive_deadband_all": Effects(drive_deadband_rpm=20.0, controller_period_s=0.006,
                                  drive_lag_s=0.015, dead_time_s=0.02, rate_limit_rpm_per_s=900.0,
                                  coast_decel_rpm_per_s=400.0, no_load_rpm=300.0),
}


@pytest.mark.parametrize("name", list(EFFECT_CASES))
def test_streamed_prediction_equals_simulate_on_irregular_times(name):
    t, cmd = _random_run(1)
    cal = Calibration(effects=EFFECT_CASES[name])
    traj = simulate(cmd, t, cal)
    mon = ShadowMonitor(cal, config=ShadowConfig(start_from_measured=False, noise_rpm=1.0,
                                                 noise_m=1.0, noise_deg=1.0))
    pred = np.empty((len(t), 7))
    for i in range(len(t)):
        mon.on_telemetry(t[i], cmd[i], traj.wheel_rpm[0, i])
        pred[i] = mon.predicted
    np.testing.assert_allclose(pred[:, :4], traj.wheel_rpm[0], atol=1e-9)
    np.testing.assert_allclose(pred[:, 4:], traj.pose[0], atol=1e-9)
    assert mon.alarms == []


@pytest.mark.parametrize("effects", [
    Effects(), Effects(coast_decel_rpm_per_s=2900.0, no_load_rpm=700.0),
    Effects(coast_decel_rpm_per_s=2900.0, no_load_rpm=700.0, controller_period_s=0.005,
            drive_lag_s=0.01)])
def test_a_robot_joined_in_motion_starts_the_model_holding_its_speed(effects):
    # joining a robot that runs steadily at 300 rpm: the model starts there, its drive holding
    # it (a fast-decay drive needs a larger push than B y: a second reading found the monitor
    # started it at B y, predicted a slowdown to 229 rpm and raised alarms on every wheel)
    cal = Calibration(effects=effects)
    mon = ShadowMonitor(cal, config=ShadowConfig(noise_rpm=1.0))
    for t in np.arange(200) / 200.0:
        mon.on_telemetry(t, (300.0, 0.0, 90.0), (300.0,) * 4)
        assert np.abs(mon.predicted[:4] - 300.0).max() < 1e-6
    assert mon.alarms == []


def test_long_dead_time_grows_the_command_queue_live_and_in_replay():
    # 0.5 s dead time at 1 kHz: 500 commands pending, far beyond the initial queue of 64
    t = np.arange(3001) / 1000.0
    cmd = np.column_stack([40 + 20 * np.sin(t * 5), np.zeros_like(t), np.full_like(t, 90.0)])
    cal = Calibration(effects=Effects(dead_time_s=0.5))
    traj = simulate(cmd, t, cal)
    cfg = ShadowConfig(start_from_measured=False, noise_rpm=1.0)
    live = ShadowMonitor(cal, config=cfg)
    for i in range(len(t)):
        live.on_telemetry(t[i], cmd[i], traj.wheel_rpm[0, i])
    np.testing.assert_allclose(live.predicted[:4], traj.wheel_rpm[0, -1], atol=1e-9)
    batch = ShadowMonitor(cal, config=cfg)
    batch.run(np.column_stack([t, cmd, traj.wheel_rpm[0], np.full((len(t), 3), np.nan)]))
    np.testing.assert_allclose(batch.predicted, live.predicted, atol=1e-12)
    assert live.alarms == [] and batch.alarms == []
