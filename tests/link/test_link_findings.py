"""One test per numbered finding of a firmware engineer's review of the protocol (as it was, it
left a 100 kg robot unsafe); each failed on the code before the fix. A few more live beside the
code they exercise: finding 6's HELLO body and float32 overflow in test_link_protocol.py, the
watchdog bit in test_link_sim.py, the telemetry rates in test_link_properties.py."""

from __future__ import annotations

import json
import math
import re
import threading
import time

import numpy as np
import pytest

from mecanum_hil.link import protocol as proto
from mecanum_hil.link.effects_file import load_sim_effects
from mecanum_hil.link.lockstep import MemoryLink, VirtualClock
from mecanum_hil.link.session import SessionConfig, run_record_session
from mecanum_hil.link.simulated import ControllerModel, SimulatedController
from mecanum_hil.model import Calibration, RobotProfile

ROBOT = RobotProfile()
LIMIT = ROBOT.wheel_speed_max_rpm


def _virtual(sim_effects=None):
    """sim-robot's firmware on a virtual clock behind an in-memory serial link, connected."""
    link, clock = MemoryLink(), VirtualClock()
    ctrl = SimulatedController(link, ControllerModel(Calibration(), ROBOT, sim_effects),
                               clock=clock)
    link.feed(proto.encode(proto.Hello()))
    ctrl.run_once()
    return link, clock, ctrl


def _advance(clock, ctrl, seconds, link=None, every=None):
    for _ in range(round(seconds / 0.005)):
        clock.now_s += 0.005
        if every is not None:
            link.feed(proto.encode(every()))
        ctrl.run_once()


def _stream(duration_s=1.2, rate_hz=50.0, n_rpm=30.0):
    t = np.arange(int(duration_s * rate_hz) + 1) / rate_hz
    return t, np.tile([n_rpm, 0.0, 90.0], (t.size, 1))


# -- 1: a COMMAND with NaN, inf or 3.4e38 killed sim-robot -----------------------------------
def test_1_non_finite_and_huge_commands_get_error_2_and_sim_robot_lives():
    from mecanum_hil.link.serial_link import SerialTransport
    from mecanum_hil.link.sim_process import spawn_sim_robot

    with spawn_sim_robot("--serial", "--quiet") as sim, SerialTransport(port=sim.path) as host:
        host.send(proto.Hello())
        deadline = time.monotonic() + 5
        while not isinstance(host.recv(0.1), proto.HelloAck):
            assert time.monotonic() < deadline
        errors = []
        for fields in ((math.nan, 0.0, 90.0), (0.0, math.inf, 90.0), (0.0, 0.0, -math.inf),
                       (3.4e38, 0.0, 90.0)):
            sent = host.send(proto.Command(*fields))
            deadline = time.monotonic() + 2
            while time.monotonic() < deadline:
                msg = host.recv(0.05)
                if isinstance(msg, proto.ErrorMsg):
                    errors.append(msg)
                    break
                assert not (isinstance(msg, proto.Telemetry) and msg.ack_seq == sent.seq)
        tlm = [m for m in (host.recv(0.05) for _ in range(30)) if isinstance(m, proto.Telemetry)]
        assert sim.proc.poll() is None  # alive
        assert [e.code for e in errors] == [proto.ErrorCode.BAD_COMMAND] * 4
        assert tlm and all(max(abs(w) for w in m.wheel_rpm) < 1.0 for m in tlm)


# -- 2: no range check on the controller side -------------------------------------------------
@pytest.mark.parametrize("n_rpm", [5000.0, 1e30, LIMIT * 1.01])
def test_2_commands_beyond_the_announced_limit_are_refused_by_the_controller(n_rpm):
    link, clock, ctrl = _virtual()
    assert link.out[0].wheel_limit_rpm == LIMIT  # announced in HELLO_ACK
    link.feed(proto.encode(proto.Command(60.0, 0.0, 90.0, seq=1)))
    ctrl.run_once()
    _advance(clock, ctrl, 0.1)
    link.feed(proto.encode(proto.Command(n_rpm, 0.0, 90.0, seq=2)))
    ctrl.run_once()
    errors = [m for m in link.out if isinstance(m, proto.ErrorMsg)]
    assert [e.code for e in errors] == [proto.ErrorCode.BAD_COMMAND]
    _advance(clock, ctrl, 1.0)
    tlm = [m for m in link.out if isinstance(m, proto.Telemetry)]
    assert all(m.ack_seq != 2 for m in tlm)  # ignored: never acknowledged
    assert max(abs(w) for m in tlm for w in m.wheel_rpm) < 62.0  # the last valid one, then 0
    assert tlm[-1].status & proto.Status.WATCHDOG  # the watchdog took over


# -- 3: a telemetry stall ends the run, whatever else arrives --------------------------------
@pytest.mark.parametrize(("pong", "reason", "code"), [(True, "controller_reset", 6),
                                                      (False, "link_lost", 4)])
def test_3_telemetry_stall_ends_the_run_pongs_without_telemetry_are_a_restart(
        pong, reason, code, pty_pair, scripted, host_serial, tmp_path):
    p = pty_pair()
    # 0.16 s of telemetry, then nothing but (with pong) PONGs: a controller that answers PING
    # and sends no telemetry has no session (a power-cycled one answers PING before a HELLO)
    scripted(p.master, telemetry=40, pong=pong)
    t, cmd = _stream(3.0)
    cfg = SessionConfig(connect_timeout_s=1.0, link_timeout_s=0.3, tail_s=0.05,
                        ping_rate_hz=20.0)
    res = run_record_session(host_serial(p.path), t, cmd, tmp_path / "r.csv", ROBOT,
                             config=cfg)
    assert (res.reason, res.exit_code) == (reason, code), res.message
    assert "no telemetry" in res.message
    assert res.duration_s < 2.0  # ended at the link timeout, not at the profile's end
    meta = json.loads((tmp_path / "r.json").read_text())
    assert meta["end_reason"] == reason and meta["exit_code"] == code


# -- 4: telemetry that is not sane ends the run with STOP and its own exit code --------------
@pytest.mark.parametrize(("kind", "reason", "code"), [
    ("rate", "telemetry_rate", 5), ("clock_ahead", "telemetry_rate", 5),
    ("clock_back", "controller_reset", 6),
    ("seq_reset", "controller_reset", 6)])
def test_4_insane_telemetry_stops_the_run(kind, reason, code, pty_pair, scripted, host_serial,
                                          tmp_path):
    p = pty_pair()
    if kind == "rate":  # 250 Hz sent, 25 Hz announced
        ctrl = scripted(p.master, telemetry=500, rate_hz=25)
    elif kind == "clock_ahead":  # 25 Hz announced and stamped, but sent at 250 Hz
        ctrl = scripted(p.master, telemetry=500, rate_hz=25, time_step_us=40_000)
    elif kind == "clock_back":  # the controller restarts: its clock goes from 0.5 s to 0.0007 s
        ctrl = scripted(p.master, telemetry=300,
                        time_of=lambda i: i * 4000 if i < 126 else 700 + (i - 126) * 4000)
    else:
        ctrl = scripted(p.master, telemetry=300, seq_of=lambda i, s: s if i < 126 else s - 120)
    t, cmd = _stream(2.0)
    res = run_record_session(host_serial(p.path), t, cmd, tmp_path / "r.csv", ROBOT,
                             config=SessionConfig(connect_timeout_s=1.0, tail_s=0.05))
    assert (res.reason, res.exit_code) == (reason, code)
    deadline = time.monotonic() + 2.0
    while not isinstance(ctrl.received[-1], proto.Stop) and time.monotonic() < deadline:
        time.sleep(0.01)  # the controller's thread reads the STOP just sent
    assert isinstance(ctrl.received[-1], proto.Stop)
    meta = json.loads((tmp_path / "r.json").read_text())
    assert meta["end_reason"] == reason and meta["exit_code"] == code and meta["end_message"]


# -- 5: sequence and counter rules -----------------------------------------------------------
def test_5a_hello_is_seq_0_and_the_first_command_seq_1(pty_pair, scripted, host_serial,
                                                        tmp_path):
    p = pty_pair()
    ctrl = scripted(p.master, telemetry=20)
    t, cmd = _stream(0.3)
    run_record_session(host_serial(p.path), t, cmd, tmp_path / "r.csv", ROBOT,
                       config=SessionConfig(connect_timeout_s=1.0, tail_s=0.05))
    hello = next(m for m in ctrl.received if isinstance(m, proto.Hello))
    first = next(m for m in ctrl.received if isinstance(m, proto.Command))
    assert (hello.seq, first.seq) == (0, 1)


def test_5b_ack_seq_restarts_at_every_hello():
    link, clock, ctrl = _virtual()
    for seq in range(1, 40):
        link.feed(proto.encode(proto.Heartbeat(seq)))
        _advance(clock, ctrl, 0.005)
    before = len(link.out)
    link.feed(proto.encode(proto.Hello()))
    ctrl.run_once()
    first = next(m for m in link.out[before:] if isinstance(m, proto.Telemetry))
    assert (first.seq, first.ack_seq, first.time_us) == (1, 0, 0)


def test_5c_a_damaged_frame_is_counted_once():
    link = MemoryLink()
    frames = [proto.encode(proto.Telemetry(i, (0.0,) * 4, seq=i)) for i in range(1, 6)]
    raw = proto.pack_frame(proto.Telemetry(3, (0.0,) * 4, seq=3))
    bad = b"\x00" + proto.cobs_encode(raw[:-1] + bytes([raw[-1] ^ 0xFF])) + b"\x00"
    link.feed(b"".join([frames[0], frames[1], bad, frames[3], frames[4]]))  # 3 damaged
    got = [link.recv() for _ in range(4)]
    assert all(isinstance(m, proto.Telemetry) for m in got)
    assert (link.stats.crc_errors, link.stats.lost) == (1, 0)
    link.feed(proto.encode(proto.Telemetry(9, (0.0,) * 4, seq=9)))  # 6, 7, 8 really lost
    link.recv()
    assert link.stats.lost == 3


def _controller_on_bus(bus_kwargs_ctrl):
    from mecanum_hil.link.can_link import CanTransport

    ctrl = SimulatedController(CanTransport(**bus_kwargs_ctrl),
                               ControllerModel(Calibration(), ROBOT))
    ctrl.model.wheel_rpm(0)
    thread = threading.Thread(target=ctrl.serve, daemon=True)
    thread.start()
    return ctrl, thread


@pytest.mark.parametrize("bus", ["virtual", "udp_multicast"])
def test_5d_own_echoed_frames_on_a_shared_bus_are_never_counted(bus, virtual_channel, tmp_path):
    import random

    from mecanum_hil.link.can_link import CanTransport

    if bus == "virtual":
        ctrl_kw = {"interface": "virtual", "channel": virtual_channel}
        host_kw = {**ctrl_kw, "receive_own_messages": True}
    else:
        port = random.Random().randrange(20000, 60000)  # no other test's traffic
        ctrl_kw = host_kw = {"interface": "udp_multicast", "channel": "239.74.163.2",
                             "port": port}
    try:
        host = CanTransport(**host_kw)
    except Exception as err:  # no multicast route on this machine
        pytest.skip(f"{bus} not available: {err}")
    ctrl, thread = _controller_on_bus(ctrl_kw)
    try:
        t, cmd = _stream(0.6)
        res = run_record_session(host, t, cmd, tmp_path / "r.csv", ROBOT,
                                 config=SessionConfig(connect_timeout_s=2.0, tail_s=0.05))
    finally:
        ctrl.stop_event.set()
        thread.join(2)
        host.close()
        ctrl.transport.close()
    assert res.reason == "completed", res.message
    # the host's own frames came back (one per frame sent) and were not received
    assert res.stats["lost"] == 0 and res.stats["echoes"] >= t.size
    assert res.stats["received"] <= ctrl.transport.stats.sent


# -- 6: the smaller gaps -----------------------------------------------------------------------
def test_6a_stop_is_sent_once_as_documented(pty_pair, scripted, host_serial, tmp_path, repo):
    p = pty_pair()
    ctrl = scripted(p.master, telemetry=20)
    t, cmd = _stream(0.3)
    run_record_session(host_serial(p.path), t, cmd, tmp_path / "r.csv", ROBOT,
                       config=SessionConfig(connect_timeout_s=1.0, tail_s=0.1))
    assert sum(isinstance(m, proto.Stop) for m in ctrl.received) == 1
    for doc in ("docs/link.md", "drivers/protocol.md", "drivers/mecanum_hil.dbc"):
        text = (repo / doc).read_text()
        assert not re.search(r"STOP[^.|]{0,60}twice", text), doc  # it once said "twice"


def test_6d_the_can_ranges_in_the_document_are_the_dbc_s(repo):
    from mecanum_hil.link.can_link import load_database

    text = (repo / "drivers" / "protocol.md").read_text()
    sig = {s.name: s for s in load_database().get_message_by_name("MH_COMMAND").signals}
    for name in ("n_cmd", "theta_cmd"):
        rng = f"[{sig[name].minimum:g}, {sig[name].maximum:g}]"
        assert rng in text, rng
    assert "±327.67" not in text


def test_6e_can_command_with_reserved_byte_set_gets_error_2(pty_pair):
    from mecanum_hil.link.can_link import CanCodec
    from mecanum_hil.link.slcan_adapter import SlcanAdapterTransport

    link, clock = SlcanAdapterTransport(pty_pair().master), VirtualClock()
    link.opened = True
    ctrl = SimulatedController(link, ControllerModel(Calibration(), ROBOT), clock=clock)
    ctrl.handle(proto.Hello())
    ((fid, data),) = CanCodec().encode(proto.Command(60.0, 0.0, 90.0, seq=1))
    reserved_set = (data[:7] + b"\x01").hex().upper()
    link._line_in(f"t{fid:03X}8{reserved_set}")  # as the adapter reads it from the host
    assert link.recv(0.0) is None  # not delivered as a command
    ctrl.take_rejected()
    assert ctrl.bad_commands == 1 and ctrl.ack_seq == 0


def test_6f_a_hello_never_clears_the_e_stop(tmp_path):
    fx_path = tmp_path / "fx.toml"
    fx_path.write_text("[[faults]]\nat_s = 0.1\nestop = true\n")
    link, clock, ctrl = _virtual(load_sim_effects(fx_path))
    _advance(clock, ctrl, 0.2)
    assert link.out[-1].status & proto.Status.ESTOP
    link.feed(proto.encode(proto.Hello()))
    _advance(clock, ctrl, 0.05)
    link.feed(proto.encode(proto.Command(60.0, 0.0, 90.0, seq=1)))
    _advance(clock, ctrl, 0.3, link, lambda: proto.Heartbeat(2))
    tlm = [m for m in link.out if isinstance(m, proto.Telemetry)][-20:]
    assert all(m.status & proto.Status.ESTOP for m in tlm)
    assert max(abs(w) for m in tlm for w in m.wheel_rpm) < 0.5
    link.feed(proto.encode(proto.EstopReset(3)))  # the only way out
    _advance(clock, ctrl, 0.02)
    last = link.out[-1]
    assert not last.status & proto.Status.ESTOP and last.status & proto.Status.STOPPED


def test_6g_an_e_stop_reset_read_with_the_hello_clears_an_e_stop_pressed_at_0_s(tmp_path):
    """CI found it: under load the firmware read HELLO and ESTOP_RESET in one pass, before its
    telemetry had let the fault at 0 s happen; the reset cleared nothing and the fault then
    latched the e-stop again."""
    fx_path = tmp_path / "fx.toml"
    fx_path.write_text("[[faults]]\nat_s = 0.0\nestop = true\n")
    link, clock, ctrl = _virtual(load_sim_effects(fx_path))
    _advance(clock, ctrl, 0.05)
    assert link.out[-1].status & proto.Status.ESTOP
    link.feed(proto.encode(proto.Hello()) + proto.encode(proto.EstopReset(1)))
    _advance(clock, ctrl, 0.05)
    last = link.out[-1]
    assert isinstance(last, proto.Telemetry) and last.ack_seq == 1
    assert not last.status & proto.Status.ESTOP and last.status & proto.Status.STOPPED


def _telemetry(link):
    return {m.time_us: m for m in link.out if isinstance(m, proto.Telemetry)}


def test_6h_a_message_read_late_after_a_fault_still_gets_the_telemetry_owed(tmp_path):
    """A fault applied when a message is read moves the model on; telemetry still owed from
    before it (a pass 30 ms late) is the truth of its own tick, as without the message
    (review of 6g: it raised ValueError and ended sim-robot)."""
    fx_path = tmp_path / "fx.toml"
    fx_path.write_text("[[faults]]\nat_s = 0.11\nestop = true\n")
    runs = []
    for message in (None, proto.Heartbeat(2)):
        link, clock, ctrl = _virtual(load_sim_effects(fx_path))
        link.feed(proto.encode(proto.Command(60.0, 0.0, 90.0, seq=1)))
        _advance(clock, ctrl, 0.095)
        clock.now_s += 0.030  # a late pass
        if message is not None:
            link.feed(proto.encode(message))
        ctrl.run_once()
        runs.append(_telemetry(link))
    quiet, late = runs
    for t_us in (100_000, 110_000, 120_000):
        np.testing.assert_allclose(late[t_us].wheel_rpm, quiet[t_us].wheel_rpm, atol=1e-9)
    assert late[100_000].wheel_rpm[0] > 20 and late[120_000].status & proto.Status.ESTOP


def test_6i_the_unmodelled_sensor_walks_across_a_fault_applied_on_a_message(tmp_path):
    fx_path = tmp_path / "fx.toml"
    fx_path.write_text("[unmodelled.roller_ripple]\namplitude = 0.05\nper_turn = 6\n"
                       "[[faults]]\nat_s = 0.11\nestop = true\n")
    link, clock, ctrl = _virtual(load_sim_effects(fx_path))
    _advance(clock, ctrl, 0.3, link, lambda: proto.Command(30.0, 0.0, 90.0))
    tlm = _telemetry(link)
    assert len(tlm) == 30 and ctrl.internal_errors == 0
    assert tlm[100_000].wheel_rpm[0] > 5 and tlm[290_000].status & proto.Status.ESTOP


def test_documented_exit_codes_match_the_session(repo):
    from mecanum_hil.link.session import EXIT_CODES

    text = (repo / "docs" / "link.md").read_text()
    for reason, code in EXIT_CODES.items():
        assert re.search(rf"`{reason}`\s*\|\s*{code}\s*\|", text), reason
