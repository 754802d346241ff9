"""CAN: the DBC codec and a python-can virtual bus that reports errors and carries junk."""

from __future__ import annotations

import can
import pytest

from mecanum_hil.errors import LinkError
from mecanum_hil.link import protocol as proto
from mecanum_hil.link.can_link import CanCodec, CanTransport, load_database


def test_database_ids_rates_and_scaling():
    db = load_database()
    ids = {m.name: m.frame_id for m in db.messages}
    assert ids["MH_STOP"] == 0x100 and min(ids.values()) == ids["MH_STOP"]  # STOP wins
    assert all(v < 0x180 for k, v in ids.items() if k.startswith("MH_"))
    assert all(v >= 0x180 for k, v in ids.items() if k.startswith("MC_"))
    assert db.get_message_by_name("MH_COMMAND").cycle_time == 20
    assert db.get_message_by_name("MH_COMMAND").get_signal_by_name("n_cmd").unit == "rpm"
    codec = CanCodec()
    wire = codec.wire_command(59.996, 33.333, -270.01)
    assert (wire.n_rpm, wire.omega_dps) == pytest.approx((60.0, 33.33), abs=1e-9)
    assert abs(wire.theta_deg + 270.01) <= 0.01 + 1e-9  # half the 0.02 deg resolution


def test_codec_rejects_unknown_ids_wrong_lengths_and_lone_halves():
    codec = CanCodec()
    with pytest.raises(proto.FrameError) as err:
        codec.decode(0x7FF, b"")
    assert err.value.kind == "unknown_type"
    with pytest.raises(proto.FrameError) as err:
        codec.decode(0x101, b"\x00" * 3)
    assert err.value.kind == "malformed"
    with pytest.raises(proto.FrameError) as err:
        codec.decode(0x182, b"\x00" * 8)  # wheels without their status
    assert err.value.kind == "malformed"
    with pytest.raises(LinkError, match="cannot encode"):
        codec.encode(proto.Command(400.0, 0.0, 90.0))


def test_bus_errors_and_junk_are_counted_and_nothing_valid_is_lost(virtual_channel):
    host = CanTransport(interface="virtual", channel=virtual_channel)
    noise = can.Bus(interface="virtual", channel=virtual_channel)
    ctrl = CanTransport(interface="virtual", channel=virtual_channel)
    try:
        codec = CanCodec()
        sent = []
        for i in range(20):
            if i % 4 == 0:
                noise.send(can.Message(is_error_frame=True, arbitration_id=0, data=b""))
            if i % 5 == 1:
                junk = can.Message(arbitration_id=0x3AB, data=b"\x01\x02", is_extended_id=False)
                noise.send(junk)
            if i % 7 == 2:
                noise.send(can.Message(arbitration_id=0x181, data=b"\x00", is_extended_id=False))
            tlm = proto.Telemetry(i * 10000, (i, -i, 0.5 * i, 1.0), 0, 0)
            sent.append(ctrl.send(tlm))
        got = [host.recv(1.0) for _ in range(20)]
        assert [g.time_us for g in got] == [s.time_us for s in sent]
        assert host.recv(0.01) is None
        assert host.stats.bus_errors == 5
        assert host.stats.unknown_types == 4
        assert host.stats.malformed == 3
        assert host.stats.lost == 0
        assert codec.db is load_database()
    finally:
        host.close()
        ctrl.close()
        noise.shutdown()


def test_send_on_a_failed_bus_raises_link_error_and_counts(virtual_channel):
    link = CanTransport(interface="virtual", channel=virtual_channel)
    link.bus.shutdown()  # the adapter went away under us
    with pytest.raises(LinkError):
        link.send(proto.Stop())
    assert link.stats.send_errors == 1 and link.stats.sent == 0
    link.close()


def test_a_command_the_can_frame_cannot_carry_is_refused_before_sending(virtual_channel,
                                                                        tmp_path):
    import numpy as np

    from mecanum_hil.errors import LimitError
    from mecanum_hil.link.session import run_record_session
    from mecanum_hil.model import RobotProfile

    listener = can.Bus(interface="virtual", channel=virtual_channel)
    host = CanTransport(interface="virtual", channel=virtual_channel)
    try:
        t = np.arange(10) * 0.02
        cmd = np.tile([10.0, 0.0, 90.0], (10, 1))
        cmd[5, 2] = 700.0  # a direction the robot can drive, beyond the signal's range
        with pytest.raises(LimitError, match=r"row 5 has theta = 700 deg.*\[-655\.36, 655\.34\]"):
            run_record_session(host, t, cmd, tmp_path / "r.csv", RobotProfile())
        assert listener.recv(0.1) is None  # not one frame left: not even a HELLO
        assert not (tmp_path / "r.csv").exists()
    finally:
        host.close()
        listener.shutdown()
