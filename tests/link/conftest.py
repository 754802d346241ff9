"""Real stand-ins for the link tests: pseudo-terminal pairs, python-can virtual buses, an
in-process simulated controller, and a scripted controller for fault injection."""

from __future__ import annotations

import os
import threading
import time
import tty
import uuid

import pytest

from mecanum_hil.link import protocol as proto
from mecanum_hil.link.serial_link import SerialTransport


class Pty:
    """A pseudo-terminal: ``master`` fd (the controller's end), ``path`` of the slave."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


@pytest.fixture
def pty_pair():
    """A pseudo-terminal, closed at the end."""
    made = []

    def make() -> Pty:
        p = Pty()
        made.append(p)
        return p

    yield make
    for p in made:
        p.close()


@pytest.fixture
def virtual_channel() -> str:
    """A fresh python-can virtual channel name."""
    return f"mh-test-{uuid.uuid4().hex[:8]}"


class ScriptedController:
    """A controller played by the test on a pty master: answers HELLO, then after the first
    COMMAND sends ``telemetry`` samples, each preceded by whatever ``before(i)`` returns (raw
    bytes: garbage, damaged frames ...). ``skip(i)`` true makes sample i a sequence gap.
    ``acks`` (the default) makes each sample acknowledge the last COMMAND read (else 0);
    ``stall_of(i)`` [s] stops the controller, reading nothing, before sample i."""

    def __init__(self, master: int, telemetry: int = 40, period_s: float = 0.004,
                 before=lambda i: b"", skip=lambda i: False,
                 hello_version: int = proto.PROTOCOL_VERSION, then=None, rate_hz: int = 250,
                 wheel_limit_rpm: float = 130.0, time_step_us: int = 4000, seq_of=None,
                 time_of=None, status_of=None, pong: bool = False, wheels_of=None,
                 acks: bool = True, stall_of=None) -> None:
        self.master = master
        self.telemetry = telemetry
        self.period_s = period_s
        self.before = before
        self.skip = skip
        self.hello_version = hello_version
        self.then = then
        self.rate_hz = rate_hz
        self.wheel_limit_rpm = wheel_limit_rpm
        self.time_step_us = time_step_us
        self.seq_of = seq_of  # seq_of(i, seq) -> the seq sample i carries (resets ...)
        self.time_of = time_of  # time_of(i) -> time_us of sample i (a clock that jumps ...)
        self.status_of = status_of or (lambda i: 0)
        # wheels_of(i) -> the four wheel readings of sample i
        self.wheels_of = wheels_of or (lambda i: (float(i), float(i) + 0.5, -float(i), 1.0))
        self.pong = pong  # answer PINGs (also after the telemetry ran out)
        self.acks = acks
        self.stall_of = stall_of or (lambda i: 0.0)
        self.sent_values: list[tuple[float, ...]] = []
        self.received: list = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> ScriptedController:
        self.thread.start()
        return self

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view)
            except BlockingIOError:
                time.sleep(0.001)
                continue
            except OSError:
                return
            view = view[n:]

    def _run(self) -> None:
        os.set_blocking(self.master, False)
        dec = proto.StreamDecoder()
        seq = 0
        streaming = False
        i = 0
        next_t = 0.0
        ack_seq = 0
        stalled = -1  # the last sample stalled before
        while not self.stop.is_set():
            try:
                data = os.read(self.master, 4096)
            except BlockingIOError:
                data = b""
            except OSError:
                return
            for msg in dec.feed(data):
                self.received.append(msg)
                if isinstance(msg, proto.Command):
                    ack_seq = msg.seq
                if isinstance(msg, proto.Hello):
                    ack = proto.HelloAck(self.hello_version, self.rate_hz, 250, "scripted",
                                         wheel_limit_rpm=self.wheel_limit_rpm)
                    self._write(proto.encode(ack))
                    seq = 1
                elif isinstance(msg, proto.Command) and not streaming:
                    streaming = True
                    next_t = time.monotonic()
                elif isinstance(msg, proto.Ping) and self.pong:
                    self._write(proto.encode(proto.Pong(msg.token, seq=seq)))
                    seq += 1
            if streaming and i < self.telemetry and time.monotonic() >= next_t:
                if stalled < i and self.stall_of(i) > 0:
                    stalled = i
                    time.sleep(self.stall_of(i))
                    continue  # read what came meanwhile first
                if self.skip(i):
                    seq += 1
                wheels = self.wheels_of(i)
                tseq = self.seq_of(i, seq) if self.seq_of else seq
                t_us = self.time_of(i) if self.time_of else i * self.time_step_us
                self._write(self.before(i) + proto.encode(
                    proto.Telemetry(t_us, wheels, self.status_of(i),
                                    ack_seq if self.acks else 0, tseq)))
                self.sent_values.append(wheels)
                seq += 1
                i += 1
                next_t += self.period_s
                if i == self.telemetry and self.then is not None:
                    self.then()
            time.sleep(0.0005)

    def join(self) -> None:
        self.stop.set()
        self.thread.join(2)


@pytest.fixture
def scripted():
    """Factory of scripted controllers, stopped at the end."""
    made = []

    def make(master, **kw) -> ScriptedController:
        c = ScriptedController(master, **kw).start()
        made.append(c)
        return c

    yield make
    for c in made:
        c.join()


@pytest.fixture
def host_serial():
    """Factory of host-side serial transports, closed at the end."""
    made = []

    def make(path: str) -> SerialTransport:
        t = SerialTransport(port=path)
        made.append(t)
        return t

    yield make
    for t in made:
        t.close()

