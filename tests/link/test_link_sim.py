"""The simulated controller: the model stepped in real time equals the batch simulator, the
effects file (dead time, saturation, gains, noise, timed faults), watchdog, STOP, PING,
version mismatch."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from mecanum_hil.errors import ConfigError
from mecanum_hil.link import protocol as proto
from mecanum_hil.link.effects_file import load_sim_effects
from mecanum_hil.link.serial_link import SerialTransport
from mecanum_hil.link.simulated import ControllerModel, SimulatedController
from mecanum_hil.model import Calibration, Effects, RobotProfile, simulate

CAL = Calibration()
ROBOT = RobotProfile()
RATE = 1000.0


def _schedule(n_ticks: int) -> np.ndarray:
    """Piecewise-constant commands on the tick grid, changing at irregular ticks."""
    cmd = np.zeros((n_ticks, 3))
    cmd[:, 2] = 90.0
    for start, value in ((13, (60.0, 0.0, 90.0)), (170, (60.0, 30.0, 45.0)),
                         (171, (90.0, 30.0, 45.0)), (420, (0.0, -20.0, 90.0))):
        cmd[start:] = value
    return cmd


def _drive(model: ControllerModel, cmd: np.ndarray, read_every: list[int]) -> dict[int, np.ndarray]:
    """Feed commands at their ticks and read wheels at irregular ticks, as the firmware does."""
    out = {}
    last = None
    reads = iter(sorted(read_every))
    nxt = next(reads, None)
    for k in range(cmd.shape[0]):
        while nxt is not None and nxt <= k:
            out[nxt] = model.wheel_rpm(nxt).copy()
            nxt = next(reads, None)
        if last is None or (cmd[k] != last).any():
            model.set_command(k, cmd[k])
            last = cmd[k]
    return out


def _reference(cmd, cal):
    t = np.arange(cmd.shape[0]) / RATE
    return simulate(cmd, t, cal, ROBOT).wheel_rpm[0]


def _write(tmp_path, text):
    p = tmp_path / "fx.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("fx", ["", "[effects.dead_time]\ndead_time_s = 0.03\n",
                                "[effects.saturation]\ntop_speed_rpm = 70.0\n"
                                "[effects.rate_limit]\nrate_limit_rpm_per_s = 400.0\n"])
def test_stepped_model_equals_the_batch_simulator(tmp_path, fx):
    sim_fx = load_sim_effects(_write(tmp_path, fx)) if fx else None
    model = ControllerModel(CAL, ROBOT, sim_fx, rate_hz=RATE, lookahead=37)
    cmd = _schedule(700)
    reads = [0, 5, 12, 13, 14, 99, 170, 171, 172, 300, 301, 419, 420, 421, 555, 699]
    got = _drive(model, cmd, reads)
    truth_cal = replace(CAL, effects=model.effects)  # the simulator applies the dead time
    ref = _reference(cmd, truth_cal)
    for k, w in got.items():
        np.testing.assert_allclose(w, ref[k], atol=1e-7, err_msg=f"tick {k}")
    assert model.calls < 40  # simulating ahead: far fewer calls than reads + commands


def test_timed_fault_continues_exactly_and_stalls_a_wheel(tmp_path):
    fx = load_sim_effects(_write(tmp_path, """
[noise]
wheel_rpm_std = 0.0
[[faults]]
at_s = 0.25
[faults.effects.wheel_gain]
gains = [1.0, 0.0, 1.0, 1.0]
"""))
    model = ControllerModel(CAL, ROBOT, fx, rate_hz=RATE)
    cmd = np.tile([60.0, 0.0, 90.0], (600, 1))
    got = _drive(model, cmd, list(range(0, 600, 7)))
    first = simulate(cmd[:251], np.arange(251) / RATE, CAL, ROBOT)
    stalled = replace(CAL, effects=Effects(gains=(1.0, 0.0, 1.0, 1.0)))
    second = simulate(cmd[250:], np.arange(250, 600) / RATE, stalled, ROBOT,
                      initial_state=first.final_state, initial_pose=first.pose[0, -1])
    ref = np.concatenate([first.wheel_rpm[0, :250], second.wheel_rpm[0]])
    for k, w in got.items():
        np.testing.assert_allclose(w, ref[k], atol=1e-7, err_msg=f"tick {k}")
    assert abs(got[595][1]) < 2.0 and got[595][0] == pytest.approx(60.0, abs=1.0)


def test_a_fault_switching_a_braking_limit_on_replaces_a_fast_decay_drive(tmp_path):
    # the two are not in one model: the effect a fault names replaces the other (a second
    # reading found the simulated robot died at the fault's time with a ConfigError)
    fx = load_sim_effects(_write(tmp_path, """
[effects.fast_decay]
coast_decel_rpm_per_s = 800.0
[noise]
wheel_rpm_std = 0.0
[[faults]]
at_s = 0.25
[faults.effects.braking_limit]
braking_limit_rpm_per_s = 600.0
"""))
    model = ControllerModel(CAL, ROBOT, fx, rate_hz=RATE)
    cmd = np.tile([60.0, 0.0, 90.0], (400, 1))
    _drive(model, cmd, list(range(0, 400, 9)))
    assert model.effects.braking_limit_rpm_per_s == 600.0 and not model.effects.fast_decay


def test_an_effects_file_without_a_no_load_speed_saves_and_loads(tmp_path):
    from mecanum_hil.link.effects_file import save_sim_effects, sim_effects_for

    fx = sim_effects_for(Effects(coast_decel_rpm_per_s=200.0))
    path = save_sim_effects(fx, tmp_path / "fx.toml")
    assert "inf" not in path.read_text()
    assert load_sim_effects(path).effects == fx.effects


def test_estop_fault_holds_the_wheels_at_zero(tmp_path):
    fx = load_sim_effects(_write(tmp_path, "[[faults]]\nat_s = 0.1\nestop = true\n"))
    model = ControllerModel(CAL, ROBOT, fx, rate_hz=RATE)
    model.set_command(0, (60.0, 0.0, 90.0))
    assert model.wheel_rpm(90)[0] > 20
    model.wheel_rpm(100)
    assert model.estop
    model.set_command(150, (90.0, 0.0, 90.0))  # ignored while the e-stop is pressed
    assert np.abs(model.wheel_rpm(900)).max() < 0.5


def test_noise_has_the_configured_spread_and_is_repeatable(tmp_path):
    path = _write(tmp_path, "[noise]\nwheel_rpm_std = 2.0\nseed = 7\n")
    samples = []
    for _ in range(2):
        model = ControllerModel(CAL, ROBOT, load_sim_effects(path), rate_hz=RATE)
        samples.append(np.array([model.measured_rpm(k) for k in range(0, 1200, 3)]))
    np.testing.assert_array_equal(samples[0], samples[1])
    assert samples[0].std() == pytest.approx(2.0, rel=0.1)


@pytest.mark.parametrize("text, match", [
    ("[effects.dead_tim]\ndead_time_s = 1\n", "dead_tim"),
    ("[effects.wheel_gain]\ngains = [1, 1]\n", "gains"),
    ("[noise]\nwheel_rpm_std = -1\n", "wheel_rpm_std"),
    ("[noise]\nseed = 1.5\n", "key 'noise.seed' must be a whole number, got 1.5"),
    ("[[faults]]\nat_s = 1.0\n", "changes nothing"),
    ("[[faults]]\nat_s = 1.0\nestop = 1\n", "estop"),
    ("[colour]\nx = 1\n", "colour"),
    ("not toml ===", "not valid TOML"),
])
def test_bad_effects_files_name_file_and_key(tmp_path, text, match):
    with pytest.raises(ConfigError, match=match) as err:
        load_sim_effects(_write(tmp_path, text))
    assert "fx.toml" in str(err.value)


@pytest.fixture
def live_controller(pty_pair):
    """A SimulatedController serving on a pty in a thread; yields (host transport, ctrl)."""
    made = []

    def start(**kw):
        p = pty_pair()
        ctrl = SimulatedController(SerialTransport(fd=p.master),
                                   ControllerModel(CAL, ROBOT, rate_hz=RATE), **kw)
        ctrl.model.wheel_rpm(0)  # load the compiled simulator before the host connects
        thread = threading.Thread(target=ctrl.serve, daemon=True)
        thread.start()
        host = SerialTransport(port=p.path)
        made.append((ctrl, thread, host))
        return host, ctrl

    yield start
    for ctrl, thread, host in made:
        ctrl.stop_event.set()
        thread.join(2)
        host.close()


def _until(host, predicate, timeout_s=2.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = host.recv(0.05)
        if msg is not None and predicate(msg):
            return msg
    raise AssertionError("expected message did not come")


def test_watchdog_stop_ping_and_hello(live_controller):
    host, ctrl = live_controller(telemetry_rate_hz=200)
    host.send(proto.Hello())
    ack = _until(host, lambda m: isinstance(m, proto.HelloAck))
    assert (ack.telemetry_rate_hz, ack.watchdog_ms) == (200, 250)
    first = _until(host, lambda m: isinstance(m, proto.Telemetry))
    assert first.status & proto.Status.STOPPED  # stopped until the first command
    sent = host.send(proto.Command(60.0, 0.0, 90.0))
    moving = _until(host, lambda m: isinstance(m, proto.Telemetry) and m.ack_seq == sent.seq
                    and m.wheel_rpm[0] > 30)
    assert moving.status == 0
    # no command, no heartbeat: the watchdog stops the wheels after 250 ms
    tripped = _until(host, lambda m: isinstance(m, proto.Telemetry)
                     and m.status & proto.Status.WATCHDOG)
    assert tripped.time_us - moving.time_us >= 150_000
    assert ctrl.model.command_at(ctrl.model.anchor + 10_000) == (0.0, 0.0, 0.0)
    # finding 6: a HEARTBEAT feeds the watchdog but does not release its stop, and the
    # status keeps saying why the wheels stand still until a new COMMAND
    hb = host.send(proto.Heartbeat())
    fed = _until(host, lambda m: isinstance(m, proto.Telemetry) and m.ack_seq == hb.seq)
    later = _until(host, lambda m: isinstance(m, proto.Telemetry)
                   and m.time_us >= fed.time_us + 300_000)
    assert fed.status & later.status & proto.Status.WATCHDOG
    assert max(abs(w) for w in later.wheel_rpm) < 1.0
    again = host.send(proto.Command(60.0, 0.0, 90.0))
    _until(host, lambda m: isinstance(m, proto.Telemetry) and m.ack_seq == again.seq
           and not m.status & proto.Status.WATCHDOG)
    host.send(proto.Stop())
    _until(host, lambda m: isinstance(m, proto.Telemetry) and m.status & proto.Status.STOPPED)
    assert ctrl.stops_received == 1
    host.send(proto.Ping(4242))
    assert _until(host, lambda m: isinstance(m, proto.Pong)).token == 4242


def test_hello_of_another_version_gets_an_error(live_controller):
    host, ctrl = live_controller()
    host.send(proto.Hello(version=9))
    err = _until(host, lambda m: isinstance(m, proto.ErrorMsg))
    assert err.code == proto.ErrorCode.VERSION_MISMATCH
    assert not ctrl.connected


def test_a_dead_time_appearing_mid_run_delays_later_commands(tmp_path):
    fx = load_sim_effects(_write(tmp_path, """
[[faults]]
at_s = 0.2
[faults.effects.dead_time]
dead_time_s = 0.05
"""))
    model = ControllerModel(CAL, ROBOT, fx, rate_hz=RATE)
    model.set_command(100, (60.0, 0.0, 90.0))  # before the fault: acts at once
    assert model.wheel_rpm(150)[0] > 20
    model.wheel_rpm(250)  # the fault is in force from tick 200
    model.set_command(300, (0.0, 0.0, 90.0))  # after it: acts 50 ticks later
    cmd = np.zeros((400, 3))
    cmd[:, 2] = 90.0
    cmd[100:350, 0] = 60.0
    ref = _reference(cmd, CAL)
    for k in (299, 320, 349, 350, 360, 399):
        np.testing.assert_allclose(model.wheel_rpm(k), ref[k], atol=1e-7, err_msg=f"tick {k}")
