"""Property tests (hypothesis) of the firmware's core through ctypes, on a test board whose
clock the test sets: arbitrary byte streams keep the output well-formed and the controller
answering; COMMANDs are refused exactly as the host's own rule (``command_problem``) refuses
them; the watchdog fires exactly after 250 ms without a valid frame that feeds it."""

from __future__ import annotations

import ctypes
import itertools
import math
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mecanum_hil.link import protocol as proto
from mecanum_hil.model.kinematics import command_to_wheels

LIMIT = 130.0
K = 0.465 / 0.102
RATE_HZ = 100
COUNTERS = ("received", "malformed", "crc", "unknown_types", "version_errors", "echoes",
            "lost", "garbage_bytes", "refused_commands", "dropped_output", "telemetry_sent",
            "telemetry_skipped")
f32 = ctypes.c_float
# the core runs in microseconds; one harness serves every example
QUICK = {"deadline": None,
         "suppress_health_check": [HealthCheck.too_slow, HealthCheck.function_scoped_fixture]}


class Harness:
    """One controller on the test board of drivers/firmware/tests/harness.c."""

    def __init__(self, path: Path) -> None:
        lib = ctypes.CDLL(str(path))
        lib.h_start.argtypes = [ctypes.c_uint16, f32, f32, ctypes.c_int]
        lib.h_set_time.argtypes = [ctypes.c_uint32]
        lib.h_feed.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
        lib.h_take.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
        lib.h_take.restype = ctypes.c_size_t
        lib.h_targets.argtypes = [ctypes.POINTER(f32)]
        lib.h_status.restype = ctypes.c_uint16
        lib.h_ack_seq.restype = ctypes.c_uint16
        lib.h_counters.argtypes = [ctypes.POINTER(ctypes.c_uint32)]
        self.lib = lib
        self.now_us = 0

    def start(self, rate_hz: int = RATE_HZ, estop: bool = False) -> None:
        self.lib.h_start(rate_hz, LIMIT, K, int(estop))
        self.now_us = 0
        self.lib.h_set_time(0)

    def advance(self, us: int) -> None:
        self.now_us = (self.now_us + us) % (1 << 32)
        self.lib.h_set_time(self.now_us)
        self.lib.h_poll()

    def feed(self, data: bytes) -> None:
        self.lib.h_feed(data, len(data))

    def take(self) -> bytes:
        out = bytearray()
        buf = ctypes.create_string_buffer(65536)
        while n := self.lib.h_take(buf, len(buf)):
            out += buf.raw[:n]
        return bytes(out)

    def messages(self) -> list:
        dec = proto.StreamDecoder()
        msgs = dec.feed(self.take())
        assert dec.counts.frames == 0 and dec.counts.garbage_bytes == 0, dec.counts
        return msgs

    def targets(self) -> np.ndarray:
        out = (f32 * 4)()
        self.lib.h_targets(out)
        return np.array(out[:], dtype=float)

    def status(self) -> int:
        return self.lib.h_status()

    def ack_seq(self) -> int:
        return self.lib.h_ack_seq()

    def counters(self) -> dict[str, int]:
        out = (ctypes.c_uint32 * len(COUNTERS))()
        self.lib.h_counters(out)
        return dict(zip(COUNTERS, out[:], strict=True))


@pytest.fixture(scope="module")
def harness(request) -> Harness:
    """The shared library of ``MH_FIRMWARE_LIB`` (``make fuzz`` sets it), or the one built
    for this test run."""
    path = os.environ.get("MH_FIRMWARE_LIB")
    if not path:
        path = request.getfixturevalue("firmware_build") / "libmh_harness.so"
    return Harness(Path(path))


# what a host sends, well-formed (seq and fields arbitrary)
seqs = st.integers(0, 0xFFFF)
host_messages = st.one_of(
    st.builds(proto.Hello, version=st.sampled_from([2, 2, 2, 1, 3]), seq=st.just(0)),
    st.builds(proto.Command, n_rpm=st.floats(-200, 200), omega_dps=st.floats(-300, 300),
              theta_deg=st.floats(-700, 700), seq=seqs),
    st.builds(proto.Stop, seq=seqs),
    st.builds(proto.Heartbeat, seq=seqs),
    st.builds(proto.Ping, token=st.integers(0, 2**32 - 1), seq=seqs),
    st.builds(proto.EstopReset, seq=seqs),
)
steps = st.lists(st.one_of(
    st.tuples(st.just("bytes"), st.binary(max_size=90)),
    st.tuples(st.just("frame"), host_messages.map(proto.encode)),
    st.tuples(st.just("damaged"), st.tuples(host_messages.map(proto.encode), st.integers(0, 10**6),
                                            st.integers(0, 7))),
    st.tuples(st.just("time"), st.integers(0, 400_000)),
    st.tuples(st.just("estop"), st.booleans()),
), max_size=60)


@settings(max_examples=150, **QUICK)
@given(steps=steps)
def test_any_input_keeps_the_output_well_formed(harness, steps):
    harness.start()
    harness.feed(proto.encode(proto.Hello()))
    out = bytearray()
    for kind, value in steps:
        if kind == "bytes":
            harness.feed(value)
        elif kind == "frame":
            harness.feed(value)
        elif kind == "damaged":
            frame, at, bit = value
            damaged = bytearray(frame)
            damaged[1 + at % (len(frame) - 2)] ^= 1 << bit
            harness.feed(bytes(damaged))
        elif kind == "time":
            harness.advance(value)
        else:
            harness.lib.h_set_estop(int(value))
            harness.advance(0)
        out += harness.take()
    # after anything, a delimiter and a PING are answered
    harness.feed(b"\x00" + proto.encode(proto.Ping(0xC0FFEE, seq=1)))
    out += harness.take()
    dec = proto.StreamDecoder()
    msgs = dec.feed(bytes(out))
    assert dec.counts.frames == 0 and dec.counts.garbage_bytes == 0, dec.counts
    assert isinstance(msgs[-1], proto.Pong) and msgs[-1].token == 0xC0FFEE
    # every frame carries the previous one's seq + 1; a HELLO_ACK restarts at 0
    for a, b in itertools.pairwise(msgs):
        expected = 0 if isinstance(b, proto.HelloAck) else (a.seq + 1) % 65536
        assert b.seq == expected, (a, b)
    # telemetry steps whole periods, from 0 at each HELLO_ACK
    last_t = None
    for m in msgs:
        if isinstance(m, proto.HelloAck):
            last_t = -10_000
        elif isinstance(m, proto.Telemetry):
            assert last_t is not None and m.time_us > last_t and m.time_us % 10_000 == 0
            assert m.status & ~0xF == 0
            last_t = m.time_us
    # the wheels never get a target beyond the limit
    assert np.max(np.abs(harness.targets())) <= LIMIT * (1 + 1e-5)


def _as_f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


float32s = st.one_of(
    st.floats(width=32, allow_nan=True, allow_infinity=True),
    st.integers(0, 2**32 - 1).map(lambda b: struct.unpack("<f", struct.pack("<I", b))[0]),
)


def _at_the_limit(omega: float, theta: float, sign: float, e: float) -> tuple:
    """A command whose peak wheel target is the limit times (1 + e)."""
    n = sign * (LIMIT * (1 + e) - K * abs(omega) / 6.0)
    return _as_f32(n), omega, theta


near_limit = st.builds(_at_the_limit, st.floats(-170, 170, width=32),
                       st.floats(-655.0, 655.0, width=32), st.sampled_from([1.0, -1.0]),
                       st.floats(-2e-3, 2e-3))
commands = st.one_of(st.tuples(float32s, float32s, float32s), near_limit,
                     st.tuples(st.floats(-130, 130, width=32), st.floats(-300, 300, width=32),
                               st.floats(-700, 700, width=32)))


@settings(max_examples=400, **QUICK)
@given(command=commands)
def test_commands_are_refused_exactly_by_the_rule(harness, command):
    n, omega, theta = command
    problem = proto.command_problem(n, omega, theta, K, LIMIT)
    if problem is not None and problem.startswith("wheel target"):
        # the float32 arithmetic of the core and the float64 of the host may disagree only
        # within 1 ppm of the threshold
        peak = max(abs(float(w)) for w in command_to_wheels(n, omega, theta, K))
        if abs(peak / (LIMIT * (1 + 1e-6)) - 1) < 1e-6:
            return
    elif problem is None and all(math.isfinite(v) for v in command):
        peak = max(abs(float(w)) for w in command_to_wheels(n, omega, theta, K))
        if abs(peak / (LIMIT * (1 + 1e-6)) - 1) < 1e-6:
            return
    harness.start()
    harness.feed(proto.encode(proto.Hello()))
    harness.messages()
    harness.feed(proto.encode(proto.Command(n, omega, theta, seq=1)))
    answers = harness.messages()
    errors = [m for m in answers if isinstance(m, proto.ErrorMsg)]
    if problem is None:
        assert not errors and harness.ack_seq() == 1
        assert harness.status() == 0
        expected = np.asarray(command_to_wheels(n, omega, theta, K), dtype=float)
        assert np.allclose(harness.targets(), expected, rtol=0, atol=2e-6 * max(1.0, LIMIT))
    else:
        assert [e.code for e in errors] == [proto.ErrorCode.BAD_COMMAND], (problem, answers)
        assert harness.ack_seq() == 0 and harness.counters()["refused_commands"] == 1
        assert not harness.targets().any()


@settings(max_examples=100, **QUICK)
@given(gaps_us=st.lists(st.integers(1, 300_000), min_size=1, max_size=12),
       feeder=st.sampled_from(["command", "heartbeat", "stop", "ping", "refused"]))
def test_the_watchdog_fires_exactly_after_250_ms(harness, gaps_us, feeder):
    harness.start()
    harness.feed(proto.encode(proto.Hello()))
    harness.feed(proto.encode(proto.Command(50.0, 0.0, 90.0, seq=1)))
    fed_at = 0
    fired = False
    for i, gap in enumerate(gaps_us, start=2):
        harness.advance(gap)
        fired = fired or harness.now_us - fed_at >= 250_000
        assert bool(harness.status() & proto.Status.WATCHDOG) == fired
        msg = {"command": proto.Command(50.0, 0.0, 90.0, seq=i),
               "heartbeat": proto.Heartbeat(seq=i), "stop": proto.Stop(seq=i),
               "ping": proto.Ping(1, seq=i),
               "refused": proto.Command(500.0, 0.0, 90.0, seq=i)}[feeder]
        harness.feed(proto.encode(msg))
        if feeder in ("command", "heartbeat", "stop"):
            fed_at = harness.now_us
        if feeder == "command":
            fired = False  # a valid COMMAND releases the watchdog stop
    if fired:
        assert not harness.targets().any()
    harness.take()
