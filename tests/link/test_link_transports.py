"""Every transport backend passes one conformance test (python-can style), and the registry
finds built-ins and entry-point plug-ins."""

from __future__ import annotations

import collections
import time
from importlib import metadata
from typing import ClassVar

import pytest

from mecanum_hil.errors import ConfigError, LinkError
from mecanum_hil.link import protocol as proto
from mecanum_hil.link import transport as tr
from mecanum_hil.link.can_link import CanTransport
from mecanum_hil.link.serial_link import SerialTransport
from mecanum_hil.link.slcan_adapter import SlcanAdapterTransport


class LoopbackTransport(tr.Transport):
    """A third-party-style backend: an in-memory pair, registered through the entry point."""

    name = "loopback"
    _queues: ClassVar[dict] = {}

    def __init__(self, channel: str = "a", peer: str = "b") -> None:
        super().__init__()
        self._rx = self._queues.setdefault(channel, collections.deque())
        self._tx = self._queues.setdefault(peer, collections.deque())

    def _send(self, msg):
        self._tx.append(msg)

    def _recv(self, timeout_s):
        deadline = time.monotonic() + timeout_s
        while not self._rx:
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.0005)
        return self._rx.popleft()

    def _close(self):
        pass


@pytest.fixture
def plugin_entry_point(monkeypatch):
    ep = metadata.EntryPoint(name="loopback", value="test_link_transports:LoopbackTransport",
                             group=tr.ENTRY_POINT_GROUP)
    monkeypatch.setattr(tr, "_entry_points", lambda: {"loopback": ep})
    return ep


def _pair(kind, pty_pair, channel):
    if kind == "serial":
        p = pty_pair()
        return SerialTransport(port=p.path), SerialTransport(fd=p.master), 1e-5
    if kind == "can-virtual":
        return (tr.open_transport("can", {"interface": "virtual", "channel": channel}),
                CanTransport(interface="virtual", channel=channel), 0.006)
    if kind == "can-slcan":
        p = pty_pair()
        ctrl = SlcanAdapterTransport(p.master)
        host = tr.open_transport("can", {"interface": "slcan", "channel": p.path,
                                        "sleep_after_open": 0})
        return host, ctrl, 0.006
    if kind == "plugin":
        cls = tr.transport_class("loopback")
        return cls(channel=f"h{channel}", peer=f"c{channel}"), \
            cls(channel=f"c{channel}", peer=f"h{channel}"), 0.0
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["serial", "can-virtual", "can-slcan", "plugin"])
def test_conformance(kind, pty_pair, virtual_channel, plugin_entry_point):
    host, ctrl, tol = _pair(kind, pty_pair, virtual_channel)
    with host, ctrl:
        assert host.send(proto.Hello()) == proto.Hello(seq=0)
        assert ctrl.recv(2.0) == proto.Hello(seq=0)
        ctrl.send(proto.HelloAck(proto.PROTOCOL_VERSION, 100, 250, "x", wheel_limit_rpm=130.0))
        ack = host.recv(2.0)
        assert isinstance(ack, proto.HelloAck)
        assert (ack.version, ack.telemetry_rate_hz, ack.watchdog_ms, ack.wheel_limit_rpm) == \
            (proto.PROTOCOL_VERSION, 100, 250, 130.0)
        wire = host.wire_command(60.123, -10.555, 90.01)
        assert abs(wire.n_rpm - 60.123) <= max(tol, 1e-5) * 1.01
        sent = host.send(wire)
        assert sent.seq == 1
        got = ctrl.recv(2.0)
        assert got == sent  # the controller sees exactly what wire_command promised
        ctrl._tx_seq += 2  # two controller frames lost on the way
        tlm = proto.Telemetry(123456, (1.25, -2.5, 100.0, -130.0), int(proto.Status.STOPPED), 1)
        ctrl.send(tlm)
        back = host.recv(2.0)
        assert isinstance(back, proto.Telemetry)
        assert (back.time_us, back.status, back.ack_seq) == (123456, 4, 1)
        assert back.wheel_rpm == pytest.approx(tlm.wheel_rpm, abs=tol + 1e-9)
        assert host.stats.lost == 2
        assert host.recv(0.01) is None
        ctrl.send(proto.Pong(99))
        assert host.recv(2.0) == proto.Pong(99, seq=4)
        assert (host.stats.sent, host.stats.received) == (2, 3)
        assert host.stats.crc_errors == host.stats.malformed == 0
    host.close()  # idempotent


def test_registry_names_and_errors(plugin_entry_point):
    names = tr.available_transports()
    assert names["serial"].endswith("SerialTransport") and names["can"].endswith("CanTransport")
    assert names["loopback"] == plugin_entry_point.value
    with pytest.raises(ConfigError, match=r"unknown transport .nope.*loopback"):
        tr.open_transport("nope")
    with pytest.raises(ConfigError, match="unknown options: colour"):
        tr.open_transport("serial", {"port": "loop://", "colour": "red"})
    with pytest.raises(LinkError, match="cannot open serial port"):
        tr.open_transport("serial", {"port": "/dev/does-not-exist"})
    assert [tr.parse_option_value(v) for v in ("0", "1.5", "true", "x")] == [0, 1.5, True, "x"]


def test_serial_over_a_pyserial_url_without_descriptor():
    with SerialTransport(port="loop://") as link:  # loopback: what we send comes back
        link.send(proto.Heartbeat())
        assert link.recv(1.0) == proto.Heartbeat(seq=0)


def test_entry_point_in_pyproject(repo):
    text = (repo / "pyproject.toml").read_text()
    assert '[project.entry-points."mecanum_hil.transports"]' in text
