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
    bytes: garbage, damaged frames ...). ``skip(i)`` true makes sample i a sequence gap."""

    def __init__(self, master: int, telemetry: int = 40, period_s: float = 0.004,
                 before=lambda i: b"", skip=lambda i: False, hello_version: int = 1,
                 then=None) -> None:
        self.master = master
        self.telemetry = telemetry
        self.period_s = period_s
        self.before = before
        self.skip = skip
        self.hello_version = hello_version
        self.then = then
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
        while not self.stop.is_set():
            try:
                data = os.read(self.master, 4096)
            except BlockingIOError:
                data = b""
            except OSError:
                return
            for msg in dec.feed(data):
                self.received.append(msg)
                if isinstance(msg, proto.Hello):
                    ack = proto.HelloAck(self.hello_version, 250, 250, "scripted")
                    self._write(proto.encode(ack))
                    seq = 1
                elif isinstance(msg, proto.Command) and not streaming:
                    streaming = True
                    next_t = time.monotonic()
            if streaming and i < self.telemetry and time.monotonic() >= next_t:
                if self.skip(i):
                    seq += 1
                wheels = (float(i), float(i) + 0.5, -float(i), 1.0)
                self._write(self.before(i) + proto.encode(
                    proto.Telemetry(i * 4000, wheels, 0, 0, seq)))
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
