"""The simulated controller in simulated time (``record_lockstep``): the same robot as
``sim-robot`` behind ``record``, rows as ``record`` writes them, effects inside and outside the
model's library from the effects file."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.errors import ConfigError
from mecanum_hil.io.recording import read_recording, write_recording
from mecanum_hil.io.timing import read_for_analysis
from mecanum_hil.link.effects_file import (
    SimEffects,
    load_sim_effects,
    save_sim_effects,
    sim_effects_for,
)
from mecanum_hil.link.lockstep import record_lockstep
from mecanum_hil.link.session import EXTRA_COLUMNS
from mecanum_hil.link.sim_process import spawn_sim_robot
from mecanum_hil.model import Calibration, Effects, RobotProfile, simulate
from mecanum_hil.profiles import step

ROBOT = RobotProfile()
HIDDEN = Effects(dead_time_s=0.03, gains=(1.0, 0.9, 1.0, 1.05), top_speed_rpm=100.0)


def _profile():
    p = step(90.0, omega_dps=20.0, theta_deg=60.0, duration_s=1.0, rest_s=0.2, stop_s=0.5)
    return p.sample(50.0)


def _tick_reference(t, cmd, effects: Effects, lead_s=0.0, rate=1000.0):
    """The controller's robot, rebuilt by hand: each command acts from the first 1 ms tick
    after it arrives (controller time = send time + lead, the round trip: 0 for a link
    without delay), then the model on the tick grid (STOP after the last command)."""
    sent_s = np.append(t, t[-1] + 1e-6)
    sent = np.vstack([cmd, [0.0, 0.0, cmd[-1, 2]]])
    arrive = np.ceil((sent_s + lead_s) * rate - 1e-9).astype(int)
    ticks = np.arange(0, int(arrive.max()) + 400)
    idx = np.searchsorted(arrive, ticks, side="right") - 1
    cmds = np.where((idx >= 0)[:, None], sent[np.clip(idx, 0, None)], [0.0, 0.0, 90.0])
    return simulate(cmds, ticks / rate, Calibration(effects=effects), ROBOT).wheel_rpm[0]


@pytest.mark.parametrize("delay_s", [0.0, 0.0026])
def test_lockstep_equals_the_controllers_robot_tick_for_tick(delay_s):
    t, cmd = _profile()
    fx = sim_effects_for(HIDDEN)
    rec = record_lockstep(t, cmd, ROBOT, sim_effects=fx, link_delay_s=delay_s,
                          telemetry_rate_hz=1000.0)
    ev = np.asarray(rec.extra["event"])
    tlm = ev == "tlm"
    # the controller's clock runs one link delay ahead of the host's: a command arrives two
    # link delays after the host's clock says it was sent; telemetry is kept from the first
    # sample received after the first command (the first tick after the first command)
    ref = _tick_reference(t, cmd, HIDDEN, lead_s=2 * delay_s)
    ctrl_t = rec.extra_numeric("controller_time_s")[tlm]
    assert ctrl_t[0] == pytest.approx(0.0 if delay_s == 0 else 0.001)
    ticks = np.round(rec.extra_numeric("controller_time_s")[tlm] * 1000).astype(int)
    # what the wire carries (float32) equals the robot simulated on its ticks
    np.testing.assert_allclose(rec.wheel_rpm[tlm], ref[ticks], atol=1e-4)
    assert rec.wheel_rpm[tlm].max() > 50.0
    # and the effects file's effects are in it: without them the robot is another one
    plain = _tick_reference(t, cmd, Effects())
    assert np.abs(plain[ticks] - rec.wheel_rpm[tlm]).max() > 10.0


def test_rows_are_what_record_writes_and_the_robot_is_stopped(tmp_path):
    t, cmd = _profile()
    fx = sim_effects_for(Effects(), wheel_rpm_std=0.5, seed=4)
    rec = record_lockstep(t, cmd, ROBOT, sim_effects=fx, pose_noise=(0.003, 0.003, 0.3),
                          metadata={"profile": "p"})
    assert tuple(rec.extra) == EXTRA_COLUMNS
    ev = list(rec.extra["event"])
    assert ev.count("cmd") == len(t) and ev.count("stop") == 1
    assert ev.count("tlm") == pytest.approx(100 * (t[-1] + 0.2), abs=3)
    # STOP after the last command, telemetry for the 0.2 s tail, in force: zero
    k = ev.index("stop")
    assert all(e == "tlm" for e in ev[k + 1:]) and len(ev) - k - 1 >= 18
    np.testing.assert_array_equal(rec.commands[k:, :2], 0.0)
    assert np.all(np.diff(rec.t_s) > 0)
    assert rec.metadata["stops_received"] == 1 and rec.metadata["controller"]
    # the noise is the effects file's, the pose the camera's (on telemetry rows)
    tlm = np.array([e == "tlm" for e in ev])
    rest = tlm & (rec.t_s < 0.15)
    assert np.std(rec.wheel_rpm[rest]) == pytest.approx(0.5, rel=0.25)
    assert np.isfinite(rec.pose[tlm]).all() and np.isnan(rec.pose[~tlm]).all()
    # written and read back as fit and diagnose read a recording
    path = write_recording(rec, tmp_path / "lock.csv")
    back = read_for_analysis(path)
    assert back.metadata["retimed"]["by"] == "controller_time_s"
    np.testing.assert_allclose(np.nanmax(back.wheel_rpm), np.nanmax(rec.wheel_rpm), rtol=1e-6)
    # and another seed draws other noise, the same seed the same
    again = record_lockstep(t, cmd, ROBOT, sim_effects=fx)
    np.testing.assert_array_equal(again.wheel_rpm[tlm], rec.wheel_rpm[tlm])


def test_lockstep_agrees_with_sim_robot_over_a_pty(tmp_path):
    # the same commands through the real serial path to sim-robot in another process, and in
    # simulated time: where the robot is in a steady state (timing does not matter), the two
    # report the same wheel speeds to the wire's float32
    t, cmd = _profile()
    fx_path = save_sim_effects(sim_effects_for(HIDDEN), tmp_path / "fx.toml")
    prof = tmp_path / "p.csv"
    write_recording(record_lockstep(t, cmd, ROBOT), prof)  # a commands file for record
    out = tmp_path / "real.csv"
    with spawn_sim_robot("--serial", "--effects", str(fx_path)) as sim:
        assert main(["record", "--port", sim.path, "--commands", str(prof), "--out", str(out),
                     "--no-progress"]) == 0
    real = read_recording(out)
    lock = record_lockstep(t, cmd, ROBOT, sim_effects=load_sim_effects(fx_path))
    for rec in (real, lock):
        tlm = np.asarray(rec.extra["event"]) == "tlm"
        steady = tlm & (rec.t_s > 1.0) & (rec.t_s < 1.15)
        rec.metadata["steady"] = np.median(rec.wheel_rpm[steady], axis=0)
    np.testing.assert_allclose(real.metadata["steady"], lock.metadata["steady"], atol=0.05)


def test_unmodelled_effects_do_not_depend_on_the_telemetry_rate():
    # they advance on every controller tick, whatever the rate the speeds are reported at
    t, cmd = _profile()
    fx = SimEffects(unmodelled={"resonance": {"natural_hz": 3.0, "damping": 0.15},
                                "roller_ripple": {"amplitude": 0.05, "per_turn": 8.0}}, seed=3)
    by_tick = []
    for rate in (50.0, 1000.0):
        rec = record_lockstep(t, cmd, ROBOT, sim_effects=fx, telemetry_rate_hz=rate)
        tlm = np.asarray(rec.extra["event"]) == "tlm"
        ticks = np.round(rec.extra_numeric("controller_time_s")[tlm] * 1000).astype(int)
        by_tick.append(dict(zip(ticks.tolist(), rec.wheel_rpm[tlm], strict=True)))
    common = sorted(set(by_tick[0]) & set(by_tick[1]))
    assert len(common) > 50
    np.testing.assert_array_equal([by_tick[0][k] for k in common],
                                  [by_tick[1][k] for k in common])


def test_unmodelled_effects_from_the_effects_file(tmp_path):
    t, cmd = _profile()
    base = record_lockstep(t, cmd, ROBOT)
    tlm = np.asarray(base.extra["event"]) == "tlm"
    ring = SimEffects(unmodelled={"resonance": {"natural_hz": 3.0, "damping": 0.15}})
    res = record_lockstep(t, cmd, ROBOT, sim_effects=ring)
    # a 3 Hz mode lightly damped: the step overshoots by about exp(-pi z / sqrt(1 - z^2))
    over = res.wheel_rpm[tlm, 0].max() / base.wheel_rpm[tlm, 0].max() - 1.0
    assert 0.3 < over < 0.7
    ripple = SimEffects(unmodelled={"roller_ripple": {"amplitude": 0.05, "per_turn": 8.0}},
                        seed=2)
    rip = record_lockstep(t, cmd, ROBOT, sim_effects=ripple)
    ratio = rip.wheel_rpm[tlm] / np.where(np.abs(base.wheel_rpm[tlm]) > 20,
                                          base.wheel_rpm[tlm], np.nan)
    assert np.nanmax(ratio) == pytest.approx(1.05, abs=0.003)
    assert np.nanmin(ratio) == pytest.approx(0.95, abs=0.003)
    # the file round-trips, and a bad key names the file
    path = save_sim_effects(ripple, tmp_path / "fx.toml")
    assert load_sim_effects(path).unmodelled == ripple.unmodelled
    path.write_text("[unmodelled.resonance]\nnatural_hz = 3.0\n")
    with pytest.raises(ConfigError, match=r"fx\.toml.*damping.*missing"):
        load_sim_effects(path)
    path.write_text("[unmodelled.backlash]\ngap = 1.0\n")
    with pytest.raises(ConfigError, match="backlash"):
        load_sim_effects(path)
    assert math.isfinite(over)
