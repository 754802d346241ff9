"""Injected faults are flagged on the right channel within 0.3 s; nominal runs stay silent."""

import json
import time

import numpy as np
import pytest

from mecanum_hil.model import Calibration, Effects
from mecanum_hil.monitor import ShadowConfig, ShadowMonitor, replay
from mecanum_hil.monitor.eventlog import EventLog, event_log_path
from mecanum_hil.monitor.scenarios import (
    FAULT_KINDS,
    driving_commands,
    make_fault,
    shadow_fault_demo,
    simulate_run,
)

CAL = Calibration()
FAULT_T = 20.0


@pytest.mark.parametrize("rate_hz", [100.0, 1000.0])
@pytest.mark.parametrize("kind", FAULT_KINDS)
@pytest.mark.parametrize("wheel", [2, 4])
def test_fault_is_flagged_on_the_right_channel_within_300_ms(kind, wheel, rate_hz):
    t, cmd = driving_commands(26.0, rate_hz)
    fault = make_fault(kind, FAULT_T, wheel=wheel)
    rec = simulate_run(t, cmd, CAL, fault, noise_rpm=1.0, seed=wheel)
    result = replay(rec, CAL)
    assert result.alarms, "fault not flagged"
    first = result.alarms[0]
    assert FAULT_T <= first.t_s <= FAULT_T + 0.3
    assert first.channel in fault.channels
    if kind != "dead-time":
        # a per-wheel fault: only that wheel diverges, in the direction of the fault (slower)
        assert {a.channel for a in result.alarms} == {f"wheel{wheel}_rpm"}
        assert first.direction * np.sign(rec.wheel_rpm[rec.t_s > FAULT_T, wheel - 1].mean()) < 0
        assert FAULT_T - 0.05 <= first.onset_t_s <= first.t_s


@pytest.mark.parametrize("rate_hz", [100.0, 1000.0])
def test_ten_minutes_nominal_with_noise_and_pose_raise_no_alarm(rate_hz):
    t, cmd = driving_commands(600.0, rate_hz)
    rec = simulate_run(t, cmd, CAL, None, noise_rpm=1.0, pose_noise_m=0.002, seed=7)
    start = time.perf_counter()
    result = replay(rec, CAL)
    elapsed = time.perf_counter() - start
    assert result.alarms == ()
    assert set(result.noise) == {"wheel1_rpm", "wheel2_rpm", "wheel3_rpm", "wheel4_rpm", "x_m",
                                 "y_m", "phi_deg"}
    for w in range(1, 5):  # the MAD estimate finds the injected noise
        assert result.noise[f"wheel{w}_rpm"] == pytest.approx(1.0, rel=0.35)
    # 600 s of samples in well under their duration: the per-sample cost is microseconds
    assert elapsed < 10.0


def test_nominal_with_effects_in_the_calibration_raises_no_alarm():
    cal = Calibration(effects=Effects(dead_time_s=0.03, top_speed_rpm=90.0,
                                      rate_limit_rpm_per_s=400.0, gains=(1, 0.9, 1, 1)))
    t, cmd = driving_commands(600.0, 100.0)
    assert replay(simulate_run(t, cmd, cal, None, noise_rpm=0.7, seed=3), cal).alarms == ()


def test_slip_shows_on_the_pose_channels_only():
    t, cmd = driving_commands(30.0, 100.0)
    fault = make_fault("gain-drop", 15.0)  # placeholder to reuse the two-piece generator
    slip = type(fault)("slip", 15.0, Effects(efficiency=(0.7, 0.7, 0.7)), ("x_m", "y_m"))
    rec = simulate_run(t, cmd, CAL, slip, noise_rpm=1.0, pose_noise_m=0.002, seed=1)
    result = replay(rec, CAL)
    assert result.alarms
    assert {a.channel for a in result.alarms} <= {"x_m", "y_m", "phi_deg"}
    assert 15.0 <= result.alarms[0].t_s <= 16.0


def test_live_feed_equals_replay_and_stop_is_requested():
    t, cmd = driving_commands(24.0, 100.0)
    rec = simulate_run(t, cmd, CAL, make_fault("stall", FAULT_T), seed=2)
    ref = replay(rec, CAL)
    live = ShadowMonitor(CAL, stop_on_divergence=True)
    stopped_at = None
    for i in range(len(rec)):
        live.on_telemetry(rec.t_s[i], rec.commands[i], rec.wheel_rpm[i])
        if live.stop_requested and stopped_at is None:
            stopped_at = rec.t_s[i]
    assert tuple(live.alarms) == ref.alarms
    assert stopped_at == ref.alarms[0].t_s
    assert "w2 DIVERGED" in live.status_line()


def test_command_rows_between_samples_act_at_their_own_time():
    # commands at 50 Hz, telemetry at 100 Hz with an offset: fed as command rows (what a
    # record session's recording holds) the prediction is the simulator's on the merged grid
    from mecanum_hil.model import simulate

    tc = np.arange(0, 5, 0.02) + 0.0037
    cmd = np.column_stack([60 * np.sign(np.sin(tc * 3)), np.zeros_like(tc), np.full_like(tc, 90)])
    tt = np.arange(0, 5, 0.01)
    grid = np.union1d(tc, tt)
    gcmd = np.vstack([np.zeros((1, 3)), cmd])[np.searchsorted(tc, grid, side="right")]
    truth = simulate(gcmd, grid, CAL).wheel_rpm[0][np.searchsorted(grid, tt)]
    mon = ShadowMonitor(CAL, config=ShadowConfig(start_from_measured=False, noise_rpm=0.5))
    mon.set_command_schedule(tc, cmd)
    in_force = np.zeros(3)
    pred = []
    for i, ti in enumerate(tt):
        j = np.searchsorted(tc, ti, side="right") - 1
        in_force = cmd[j] if j >= 0 else in_force
        mon.on_telemetry(ti, in_force, truth[i])
        pred.append(mon.predicted[:4])
    np.testing.assert_allclose(np.array(pred), truth, atol=1e-9)
    assert mon.alarms == []


def test_recovery_event_after_the_fault_clears(tmp_path):
    from dataclasses import replace

    from mecanum_hil.model import simulate

    t, cmd = driving_commands(20.0, 100.0)
    i1, i2 = 1000, 1200  # wheel 3 stalls from 10 s to 12 s
    a = simulate(cmd[:i1 + 1], t[:i1 + 1], CAL)
    stall = replace(CAL, effects=Effects(gains=(1, 1, 0, 1)))
    b = simulate(cmd[i1:i2 + 1], t[i1:i2 + 1], stall, initial_state=a.final_state,
                 initial_pose=a.pose[0, -1], initial_command=cmd[i1 - 1])
    c = simulate(cmd[i2:], t[i2:], CAL, initial_state=b.final_state,
                 initial_pose=b.pose[0, -1], initial_command=cmd[i2 - 1])
    wheels = np.concatenate([a.wheel_rpm[0, :i1], b.wheel_rpm[0, :-1], c.wheel_rpm[0]])
    wheels += np.random.default_rng(0).normal(0, 1.0, wheels.shape)
    rec = simulate_run(t, cmd, CAL, None).with_values(wheel_rpm=wheels)
    path = tmp_path / "run.csv"
    log_path = event_log_path(path)
    assert log_path.name == "run.shadow.jsonl"
    with EventLog(log_path, CAL, ShadowConfig(), {"mode": "replay"}) as log:
        result = replay(rec, CAL, listeners=[log])
    events = [json.loads(line) for line in log_path.read_text().splitlines()]
    kinds = [e["event"] for e in events]
    assert kinds[0] == "start" and kinds[-1] == "end"
    alarms = [e for e in events if e["event"] == "alarm"]
    assert alarms[0]["channel"] == "wheel3_rpm" and 10.0 <= alarms[0]["t_s"] <= 10.3
    assert {"t_s", "channel", "residual", "onset_t_s", "direction", "statistic", "noise",
            "predicted", "measured", "unit", "action"} <= set(alarms[0])
    recovered = [e for e in events if e["event"] == "recovered"]
    assert recovered and recovered[0]["channel"] == "wheel3_rpm"
    assert 12.0 < recovered[0]["t_s"] < 14.5
    assert len(result.alarms) == len(alarms)


def test_given_noise_skips_the_warm_up_so_an_early_fault_is_caught():
    t, cmd = driving_commands(6.0, 100.0)
    rec = simulate_run(t, cmd, CAL, make_fault("stall", 0.5, wheel=1), seed=4)
    assert replay(rec, CAL).alarms == () or replay(rec, CAL).alarms[0].t_s >= 1.0
    early = replay(rec, CAL, config=ShadowConfig(noise_rpm=1.0)).alarms
    assert early and early[0].channel == "wheel1_rpm" and early[0].t_s <= 0.8


def test_demo_function_flags_the_fault_and_writes_its_files(tmp_path):
    demo = shadow_fault_demo(tmp_path, "gain-drop", duration_s=14.0, fault_t_s=10.0,
                             echo=lambda s: None)
    assert demo.alarms and demo.alarms[0].channel == "wheel2_rpm"
    assert 0.0 <= demo.detection_delay_s <= 0.3
    assert demo.recording.exists() and demo.plot.stat().st_size > 10_000
    assert '"event": "alarm"' in demo.event_log.read_text()


def test_controller_clock_undoes_a_host_stall_and_live_shadow_uses_it(tmp_path):
    from mecanum_hil.model import RobotProfile
    from mecanum_hil.monitor.live import ControllerClock, LiveShadow

    clock = ControllerClock()
    ctrl = np.arange(6) * 0.01
    arrival = np.array([0.0105, 0.0203, 0.1302, 0.1303, 0.1304, 0.0605])  # a 90 ms stall
    mapped = [clock(c, a) for c, a in zip(ctrl, arrival, strict=True)]
    # the least-delayed sample sets the offset (it may creep by the drift allowance, 2e-4 s/s)
    np.testing.assert_allclose(mapped[1:], ctrl[1:] + 0.0103, atol=2e-5)
    assert all(m <= a + 1e-12 for m, a in zip(mapped, arrival, strict=True))
    # a session passing send times and controller times: a host stall changes nothing
    t, cmd = driving_commands(24.0, 100.0)
    rec = simulate_run(t, cmd, CAL, make_fault("gain-drop", FAULT_T, wheel=1), seed=5)
    live = LiveShadow(CAL, RobotProfile(), ShadowConfig(), tmp_path / "x.shadow.jsonl")
    live.monitor.set_command_schedule(t + 5.0, cmd)  # a wrong schedule: on_command replaces it
    ideal = ShadowMonitor(CAL)
    for i in range(len(rec)):
        live.on_command(rec.t_s[i], rec.commands[i])
        late = rec.t_s[i] + (0.09 if 1500 <= i < 1510 else 0.0)  # host stalled, burst after
        live.on_telemetry(late, rec.commands[i], rec.wheel_rpm[i], controller_time_s=rec.t_s[i])
        ideal.on_command(rec.t_s[i], rec.commands[i])
        ideal.on_telemetry(rec.t_s[i], rec.commands[i], rec.wheel_rpm[i])
    text = live.close()
    assert live.monitor.alarms == ideal.alarms
    assert live.monitor.alarms[0].channel == "wheel1_rpm"
    assert FAULT_T <= live.monitor.alarms[0].t_s <= FAULT_T + 0.3
    assert "wheel1_rpm" in text
