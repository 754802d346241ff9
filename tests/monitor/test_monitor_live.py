"""Shadow mode on live links: ``record --shadow`` against the simulated controller (a separate
process, real pseudo-terminal, its timed fault schedule) and passive listening on a CAN bus."""

import json
import subprocess
import sys
import threading
import uuid

import numpy as np
import pytest

from mecanum_hil.io.recording import read_recording
from mecanum_hil.link.can_link import CanTransport
from mecanum_hil.link.effects_file import Fault, SimEffects
from mecanum_hil.link.session import SessionConfig, run_record_session
from mecanum_hil.link.sim_process import spawn_sim_robot
from mecanum_hil.link.simulated import ControllerModel, SimulatedController
from mecanum_hil.model import Calibration, RobotProfile
from mecanum_hil.monitor import ShadowConfig, replay
from mecanum_hil.monitor.live import listen_can
from mecanum_hil.profiles import CommandProfile, Segment

FAULT_AT_S = 2.5
# Steady speed when the fault strikes, on purpose: the observer protocol gives host receive
# times only, and on a loaded 2-core machine the host can stall for ~100 ms, then send late
# and receive a burst; while the wheels accelerate that reads as divergence (see
# docs/shadow.md, "Limits"). At steady speed timing does not matter, so this tests the wiring
# (process, fault schedule, observer thread, stop, event log) without timing luck; detection
# quality itself is tested offline in test_monitor_faults.py.
PROFILE_TOML = """
[profile]
name = "shadow-e2e"
[[segments]]
kind = "hold"
duration_s = 0.3
[[segments]]
kind = "step"
duration_s = 3.7
n_rpm = 30.0
"""
EFFECTS_TOML = f"""
[noise]
wheel_rpm_std = 0.5
seed = 3
[[faults]]
at_s = {FAULT_AT_S}
[faults.effects.wheel_gain]
gains = [1.0, 0.0, 1.0, 1.0]   # wheel 2 stalls
"""


def _record_with_shadow(tmp_path, profile_toml, effects_toml):
    """``record --shadow paper --on-divergence stop`` against ``sim-robot --serial`` with
    ``effects_toml`` (its fault schedule), both real processes on a real pty."""
    prof = tmp_path / "p.toml"
    prof.write_text(profile_toml)
    fx = tmp_path / "fx.toml"
    fx.write_text(effects_toml)
    out = tmp_path / "run.csv"
    with spawn_sim_robot("--serial", "--effects", str(fx)) as sim:
        r = subprocess.run(
            [sys.executable, "-m", "mecanum_hil", "record", "--transport", "serial", "--port",
             sim.path, "--profile", str(prof), "--out", str(out), "--shadow", "paper",
             "--on-divergence", "stop", "--no-progress"],
            capture_output=True, text=True, timeout=120)
    return r, out


@pytest.mark.slow
def test_record_shadow_stops_the_run_when_the_sim_robot_stalls_a_wheel(tmp_path):
    r, out = _record_with_shadow(tmp_path, PROFILE_TOML, EFFECTS_TOML)
    assert r.returncode == 3, r.stdout + r.stderr
    assert "shadow: ALARM" in r.stdout and "wheel2_rpm" in r.stdout
    events = [json.loads(x) for x in out.with_name("run.shadow.jsonl").read_text().splitlines()]
    alarms = [e for e in events if e["event"] == "alarm"]
    rec = read_recording(out)
    fault_t = _fault_time(rec)
    assert alarms[0]["channel"] == "wheel2_rpm" and alarms[0]["action"] == "stop"
    assert fault_t - 1e-5 <= alarms[0]["t_s"] <= fault_t + 0.3  # the CSV keeps 6 decimals
    assert {e["channel"] for e in alarms} == {"wheel2_rpm"}
    assert rec.metadata["end_reason"] == "observer_stop"
    assert rec.t_s[-1] < fault_t + 0.6  # stopped at the alarm, not at the profile's end
    # the recording reproduces the detection offline
    again = replay(rec, Calibration())
    assert again.alarms[0].channel == "wheel2_rpm"
    assert abs(again.alarms[0].t_s - alarms[0]["t_s"]) <= 0.05


# Two more faults through the same path: a wheel's gain dropping by 20 %, and a
# dead time appearing (visible only when the command changes after it: the profile steps from
# 30 to 60 rpm at 4.0 s, 1.5 s after the fault).
PROFILE_STEP_AFTER_FAULT = PROFILE_TOML + """
[[segments]]
kind = "step"
duration_s = 1.5
n_rpm = 60.0
"""


@pytest.mark.slow
@pytest.mark.parametrize(
    ("effects", "channels", "visible_from_s"),
    [
        ("[faults.effects.wheel_gain]\ngains = [1.0, 0.8, 1.0, 1.0]", {"wheel2_rpm"}, 0.0),
        ("[faults.effects.dead_time]\ndead_time_s = 0.08",
         {"wheel1_rpm", "wheel2_rpm", "wheel3_rpm", "wheel4_rpm"}, 4.0 - FAULT_AT_S),
    ],
    ids=["gain-drop-20%", "dead-time-appears"],
)
def test_record_shadow_flags_gain_drop_and_dead_time_from_the_sim_robot(
        tmp_path, effects, channels, visible_from_s):
    r, out = _record_with_shadow(
        tmp_path, PROFILE_STEP_AFTER_FAULT,
        f"[noise]\nwheel_rpm_std = 0.5\nseed = 4\n[[faults]]\nat_s = {FAULT_AT_S}\n{effects}\n")
    assert r.returncode == 3, r.stdout + r.stderr
    events = [json.loads(x) for x in out.with_name("run.shadow.jsonl").read_text().splitlines()]
    alarms = [e for e in events if e["event"] == "alarm"]
    rec = read_recording(out)
    fault_t = _fault_time(rec)
    # no alarm before the fault; the first within 0.3 s of when the fault can be seen
    assert alarms[0]["channel"] in channels
    assert fault_t - 1e-5 <= alarms[0]["t_s"] <= fault_t + visible_from_s + 0.3
    assert {e["channel"] for e in alarms} <= channels


def _fault_time(rec):
    """Host time of the first telemetry row at or after the fault's controller time [s]."""
    ctrl = rec.extra_numeric("controller_time_s")
    return float(rec.t_s[np.flatnonzero(ctrl >= FAULT_AT_S)[0]])


def _profile_stream(rate_hz=50.0):
    prof = CommandProfile("listen", (Segment("hold", 0.3), Segment("step", 3.2, n_rpm=30.0)))
    return prof.sample(rate_hz)


@pytest.mark.slow
@pytest.mark.parametrize("stop", [False, True])
def test_passive_can_listener_flags_the_fault_and_sends_only_when_told(tmp_path, stop):
    channel = f"mh-shadow-{uuid.uuid4().hex[:8]}"
    fx = SimEffects(wheel_rpm_std=0.5, seed=1,
                    faults=(Fault(FAULT_AT_S, {"wheel_gain": {"gains": [1.0, 1.0, 0.0, 1.0]}}),))
    ctrl = SimulatedController(CanTransport("virtual", channel),
                               ControllerModel(Calibration(), RobotProfile(), fx))
    server = threading.Thread(target=ctrl.serve, daemon=True)
    server.start()
    t, cmd = _profile_stream()
    results = {}

    def commander():
        with CanTransport("virtual", channel) as link:
            results["run"] = run_record_session(
                link, t, cmd, tmp_path / "cmd.csv", RobotProfile(),
                config=SessionConfig(handle_sigterm=False, tail_s=0.05))

    lines = []
    listener_bus = CanTransport("virtual", channel).bus  # open before the commander starts
    sender = threading.Thread(target=commander, daemon=True)
    sender.start()
    try:
        n = listen_can("virtual", channel, None, "paper", "tdam-stm", ShadowConfig(),
                       out=tmp_path / "heard.csv", duration_s=t[-1] + 0.6,
                       stop_on_divergence=stop, echo=lines.append, bus=listener_bus)
    finally:
        sender.join(10)
        ctrl.stop_event.set()
        server.join(5)
    assert n >= 1
    events = [json.loads(x) for x in (tmp_path / "heard.shadow.jsonl").read_text().splitlines()]
    alarms = [e for e in events if e["event"] == "alarm"]
    heard = read_recording(tmp_path / "heard.csv")
    fault_t = _fault_time(heard)
    if not stop:  # what was heard replays to the same verdict
        again = replay(heard, Calibration())
        assert again.alarms[0].channel == "wheel3_rpm"
        assert abs(again.alarms[0].t_s - alarms[0]["t_s"]) <= 0.011
    assert alarms[0]["channel"] == "wheel3_rpm"
    # the simulated controller switches faults on at its 1 ms ticks and reports every 10 ms:
    # the first faulty sample may carry a controller time up to one report before at_s
    assert fault_t - 0.011 <= alarms[0]["t_s"] <= fault_t + 0.3
    assert np.isfinite(heard.wheel_rpm).any() and list(heard.extra["event"]).count("cmd") > 100
    if stop:
        assert ctrl.stops_received >= 2  # the listener's STOP, then the commander's own at the end
        assert any("sent" in line and "STOP" in line for line in lines)
    else:
        assert ctrl.stops_received == 1  # only the commander's STOP: the listener sent nothing
