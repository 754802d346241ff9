"""An independent controller ("firmware") for the mecanum-hil serial protocol, version 2.

Written from the documents alone (drivers/protocol.md, drivers/mecanum_hil.dbc, docs/link.md,
docs/formats.md, docs/conventions.md, drivers/tdam-stm.toml), without the package's link code,
to check that the protocol document is enough to build a controller that passes
``mecanum-hil conformance``. Self-contained: the standard library and numpy only; it does not
import ``mecanum_hil``.

Run it as a script: it opens a pseudo-terminal, prints the path of its slave end as the first
line of standard output, and serves the protocol on it until SIGTERM / SIGINT, when it prints
its counters as one JSON line on standard error::

    python tests/link/independent_controller.py [--telemetry-rate 100] [--estop-pressed]
        [--estop-held-s S] [--robot drivers/tdam-stm.toml] [--tau-s 0.05]

The wheels are a first-order lag per wheel (time constant ``--tau-s`` [s]) following the
wheel targets of the project's kinematics (docs/conventions.md).
"""

from __future__ import annotations

import argparse
import binascii
import errno
import json
import math
import os
import select
import signal
import struct
import sys
import time
import tomllib
import tty

import numpy as np

VERSION = 2

# Message types (drivers/protocol.md, "Messages").
HELLO, COMMAND, STOP, HEARTBEAT, PING, ESTOP_RESET = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
HELLO_ACK, TELEMETRY, PONG, ERROR = 0x81, 0x82, 0x85, 0x8F
HOST_BODY_LEN = {HELLO: 0, COMMAND: 12, STOP: 0, HEARTBEAT: 0, PING: 4, ESTOP_RESET: 0}
CONTROLLER_TYPES = {HELLO_ACK, TELEMETRY, PONG, ERROR}

# Status bits.
ST_ESTOP, ST_WATCHDOG, ST_STOPPED, ST_FAULT = 1 << 0, 1 << 1, 1 << 2, 1 << 3

# Error codes.
E_VERSION, E_BAD_COMMAND, E_ESTOP_HELD, E_OTHER = 1, 2, 3, 255

MAX_FRAME = 64          # bytes before framing
MAX_RUN = 67            # bytes between delimiters before a run is dropped as one frame
THETA_MAX_DEG = 655.36
LIMIT_PPM = 1e-6
WATCHDOG_S = 0.250
OUT_BUFFER_MAX = 16384  # bytes queued towards the host before frames are dropped
SKIP_AHEAD_SAMPLES = 50  # after a stall this long, skip ahead instead of sending a burst


# ---------------------------------------------------------------------------------------------
# Framing: CRC-16/CCITT-FALSE and COBS
# ---------------------------------------------------------------------------------------------

def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR)."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data`` (the result holds no zero byte)."""
    out = bytearray()
    block = bytearray()
    for b in data:
        if b == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
        else:
            block.append(b)
            if len(block) == 254:
                out.append(255)
                out += block
                block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes | None:
    """Decode one COBS piece; None when it is not valid COBS."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0 or i + code > n:
            return None
        out += data[i + 1:i + code]
        i += code
        if code != 255 and i < n:
            out.append(0)
    return bytes(out)


def frame(msg_type: int, seq: int, body: bytes = b"") -> bytes:
    """A complete wire frame: ``00 COBS(version type seq body crc) 00``."""
    raw = struct.pack("<BBH", VERSION, msg_type, seq & 0xFFFF) + body
    raw += struct.pack("<H", crc16(raw))
    return b"\x00" + cobs_encode(raw) + b"\x00"


# ---------------------------------------------------------------------------------------------
# Kinematics and the wheel model (pure)
# ---------------------------------------------------------------------------------------------

def command_to_wheels(n_rpm: float, omega_dps: float, theta_deg: float, k: float) -> np.ndarray:
    """Wheel speed targets [rpm] (1 FL, 2 FR, 3 RL, 4 RR) of a command (docs/conventions.md)."""
    th = math.radians(theta_deg)
    s, c = math.sin(th), math.cos(th)
    v = n_rpm / (abs(s) + abs(c))
    vx, vy, wz = v * s, -v * c, omega_dps / 6.0
    return np.array([vx - vy - k * wz, vx + vy + k * wz, vx + vy - k * wz, vx - vy + k * wz])


def advance_wheels(y_rpm: np.ndarray, u_rpm: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """First-order lag advanced exactly over ``dt_s`` [s] with the target held."""
    if dt_s <= 0.0:
        return y_rpm
    return u_rpm + (y_rpm - u_rpm) * math.exp(-dt_s / tau_s)


def f32_or_inf(x: float) -> float:
    """A float as float32 carries it: beyond its range, infinity of its sign (never wrapped)."""
    with np.errstate(over="ignore"):
        return float(np.float32(x))


# ---------------------------------------------------------------------------------------------
# The controller
# ---------------------------------------------------------------------------------------------


def sample_time_us(k: int, rate_hz: int) -> int:
    """``time_us`` of telemetry sample ``k`` after the HELLO: k * 10^6 / rate rounded half up
    to the microsecond, in integer arithmetic, modulo 2^32 (protocol.md, "Telemetry")."""
    return (k * 1_000_000 + rate_hz // 2) // rate_hz % (1 << 32)

class Controller:
    """The firmware state machine; I/O is the caller's (``feed`` bytes in, ``take_output``)."""

    def __init__(self, *, telemetry_rate_hz: int, wheel_limit_rpm: float, k: float,
                 tau_s: float, name: str, estop_pressed: bool, estop_held_s: float,
                 clock=time.monotonic) -> None:
        self.rate_hz = telemetry_rate_hz
        self.limit_rpm = wheel_limit_rpm
        self.k = k
        self.tau_s = tau_s
        self.name = name.encode()[:32]
        self.clock = clock
        self.out = bytearray()
        self.rx = bytearray()
        self.in_overflow = False
        self.counters = {
            "received": 0, "malformed": 0, "crc": 0, "unknown_types": 0, "version_errors": 0,
            "echoes": 0, "lost": 0, "garbage_bytes": 0, "refused_commands": 0,
            "dropped_output": 0, "telemetry_sent": 0, "telemetry_skipped": 0,
        }
        self.dropped_since_valid = 0
        self.expected_rx_seq: int | None = None
        self.tx_seq = 0
        self.session = False
        self.t0 = 0.0
        self.sample_index = 0
        self.ack_seq = 0
        self.command: tuple[float, float, float] | None = None
        self.stopped = True
        self.watchdog = False
        now = clock()
        self.estop = estop_pressed
        self.button_release_at = now + estop_held_s if estop_pressed else now
        self.last_feed = now
        self.wheels = np.zeros(4)
        self.model_t = now

    # -- output ---------------------------------------------------------------------------
    def send(self, msg_type: int, body: bytes = b"", seq: int | None = None) -> None:
        if seq is None:
            seq = self.tx_seq
            self.tx_seq = (self.tx_seq + 1) & 0xFFFF
        data = frame(msg_type, seq, body)
        if len(self.out) + len(data) > OUT_BUFFER_MAX:
            self.counters["dropped_output"] += 1  # never block: drop whole frames
            return
        self.out += data

    def send_error(self, code: int, text: str) -> None:
        self.send(ERROR, bytes([code]) + text.encode()[:40])

    # -- state ----------------------------------------------------------------------------
    def button_pressed(self, now: float) -> bool:
        return self.estop and now < self.button_release_at

    def target(self) -> np.ndarray:
        if (not self.session or self.estop or self.stopped or self.watchdog
                or self.command is None):
            return np.zeros(4)
        return command_to_wheels(*self.command, self.k)

    def advance_model(self, now: float) -> None:
        self.wheels = advance_wheels(self.wheels, self.target(), now - self.model_t, self.tau_s)
        self.model_t = now

    def status(self) -> int:
        return ((ST_ESTOP if self.estop else 0) | (ST_WATCHDOG if self.watchdog else 0)
                | (ST_STOPPED if self.stopped else 0))

    def feed_watchdog(self, now: float) -> None:
        self.last_feed = now

    # -- input ----------------------------------------------------------------------------
    def feed(self, data: bytes, now: float) -> None:
        """Bytes from the host, split at 0x00 delimiters."""
        for b in data:
            if b == 0:
                if self.in_overflow:
                    self.in_overflow = False
                elif self.rx:
                    self.handle_piece(bytes(self.rx), now)
                self.rx.clear()
                continue
            if self.in_overflow:
                self.counters["garbage_bytes"] += 1
                continue
            self.rx.append(b)
            if len(self.rx) > MAX_RUN:
                # one malformed frame for the whole run, up to the next delimiter
                self.counters["garbage_bytes"] += len(self.rx)
                self.drop("malformed")
                self.rx.clear()
                self.in_overflow = True

    def drop(self, counter: str) -> None:
        self.counters[counter] += 1
        self.dropped_since_valid += 1

    def handle_piece(self, piece: bytes, now: float) -> None:
        raw = cobs_decode(piece)
        if raw is None or len(raw) < 6 or len(raw) > MAX_FRAME:
            self.counters["garbage_bytes"] += len(piece)
            self.drop("malformed")
            return
        version, msg_type, seq = struct.unpack_from("<BBH", raw)
        body = raw[4:-2]
        crc_ok = struct.unpack_from("<H", raw, len(raw) - 2)[0] == crc16(raw[:-2])
        if msg_type in CONTROLLER_TYPES:
            if crc_ok:
                self.counters["echoes"] += 1  # our own frames heard back: counted nowhere else
            else:
                self.drop("crc")
            return
        wrong_length = msg_type in HOST_BODY_LEN and len(body) != HOST_BODY_LEN[msg_type]
        if wrong_length:
            self.drop("malformed")
            # A COMMAND whose CRC is right has a trustworthy type: answer it (protocol.md).
            if (crc_ok and msg_type == COMMAND and version == VERSION and self.session):
                self.account_seq(seq)
                self.refuse(f"COMMAND body {len(body)} bytes, not 12")
            return
        if not crc_ok:
            self.drop("crc")
            return
        if msg_type not in HOST_BODY_LEN:
            self.drop("unknown_types")
            return
        if msg_type == HELLO:
            self.on_hello(version, now)
            return
        if version != VERSION:
            self.drop("version_errors")
            return
        self.counters["received"] += 1
        self.account_seq(seq)
        if msg_type == PING:
            self.send(PONG, body)
            return
        if not self.session:
            return  # before the first HELLO only HELLO and PING are answered
        if msg_type == COMMAND:
            self.on_command(seq, body, now)
        elif msg_type == STOP:
            self.ack_seq = seq
            self.feed_watchdog(now)
            self.command = None
            self.stopped = True
        elif msg_type == HEARTBEAT:
            self.ack_seq = seq
            self.feed_watchdog(now)
        elif msg_type == ESTOP_RESET:
            self.on_estop_reset(seq, now)

    def account_seq(self, seq: int) -> None:
        if self.expected_rx_seq is not None:
            gap = (seq - self.expected_rx_seq) & 0xFFFF
            if gap < 0x8000:
                self.counters["lost"] += max(0, gap - self.dropped_since_valid)
            # a jump backwards is the host restarting: not lost
        self.expected_rx_seq = (seq + 1) & 0xFFFF
        self.dropped_since_valid = 0

    def on_hello(self, version: int, now: float) -> None:
        if version != VERSION:
            self.counters["received"] += 1
            self.send_error(E_VERSION, f"controller speaks protocol version {VERSION}")
            return
        self.counters["received"] += 1
        self.account_seq(0)
        self.advance_model(now)
        self.session = True
        self.t0 = now
        self.sample_index = 0
        self.tx_seq = 0
        self.command = None
        self.stopped = True
        self.watchdog = False
        self.feed_watchdog(now)
        self.ack_seq = 0
        limit = f32_or_inf(self.limit_rpm)
        self.send(HELLO_ACK, struct.pack("<HHf", self.rate_hz, int(WATCHDOG_S * 1000), limit)
                  + self.name)
        if self.rate_hz > 0:
            self.send_telemetry(now)

    def refuse(self, reason: str) -> None:
        self.counters["refused_commands"] += 1
        self.send_error(E_BAD_COMMAND, reason)

    def on_command(self, seq: int, body: bytes, now: float) -> None:
        n, omega, theta = struct.unpack("<fff", body)
        for name, value in (("n", n), ("omega", omega), ("theta", theta)):
            if not math.isfinite(value):
                self.refuse(f"{name} not finite")
                return
        if abs(theta) > THETA_MAX_DEG:
            self.refuse("|theta| > 655.36 deg")
            return
        peak = float(np.max(np.abs(command_to_wheels(n, omega, theta, self.k))))
        if not peak <= self.limit_rpm * (1.0 + LIMIT_PPM):
            self.refuse(f"wheel {peak:.6g} rpm > limit")
            return
        self.advance_model(now)
        self.ack_seq = seq
        self.feed_watchdog(now)
        self.command = (n, omega, theta)
        self.stopped = False
        self.watchdog = False

    def on_estop_reset(self, seq: int, now: float) -> None:
        if self.estop and self.button_pressed(now):
            self.send_error(E_ESTOP_HELD, "e-stop still held")
            return
        self.ack_seq = seq
        self.feed_watchdog(now)
        if self.estop:
            self.advance_model(now)
            self.estop = False
            self.command = None
            self.stopped = True

    # -- time -----------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        """Watchdog and telemetry due at ``now``."""
        if not self.session:
            return
        if not self.watchdog and now - self.last_feed >= WATCHDOG_S:
            self.advance_model(self.last_feed + WATCHDOG_S)
            self.watchdog = True
            self.command = None
        if self.rate_hz <= 0:
            return
        due = int((now - self.t0) * self.rate_hz)  # the last sample index due by now
        if due - self.sample_index > SKIP_AHEAD_SAMPLES:
            self.counters["telemetry_skipped"] += due - self.sample_index
            self.sample_index = due
        while self.sample_index <= due:
            self.send_telemetry(self.t0 + self.sample_index / self.rate_hz)

    def send_telemetry(self, t_sample: float) -> None:
        """The next sample, taken at ``t_sample`` on the announced period."""
        if t_sample > self.model_t:
            self.advance_model(t_sample)
        time_us = sample_time_us(self.sample_index, self.rate_hz)
        wheels = [f32_or_inf(w) for w in self.wheels]
        body = struct.pack("<I4fHH", time_us, *wheels, self.status(), self.ack_seq & 0xFFFF)
        self.send(TELEMETRY, body)
        self.counters["telemetry_sent"] += 1
        self.sample_index += 1

    def next_deadline(self, now: float) -> float:
        if not self.session:
            return now + 0.05
        deadlines = []
        if not self.watchdog:
            deadlines.append(self.last_feed + WATCHDOG_S)
        if self.rate_hz > 0:
            deadlines.append(self.t0 + self.sample_index / self.rate_hz)
        return min(deadlines) if deadlines else now + 0.05


# ---------------------------------------------------------------------------------------------
# The pseudo-terminal shell
# ---------------------------------------------------------------------------------------------

def load_robot(path: str | None) -> tuple[float, float]:
    """(k = (lx + ly) / r, wheel limit [rpm]) from a robot profile TOML, or the paper robot's."""
    if path is None:
        return 0.465 / 0.102, 130.0
    with open(path, "rb") as f:
        doc = tomllib.load(f)
    k = doc["robot"]["lx_plus_ly_m"] / doc["robot"]["wheel_radius_m"]
    return k, float(doc["limits"]["wheel_speed_max_rpm"])


def serve(ctl: Controller, master: int, stop_flag: list[bool]) -> None:
    os.set_blocking(master, False)
    while not stop_flag[0]:
        now = ctl.clock()
        ctl.tick(now)
        timeout = max(0.0, min(ctl.next_deadline(now) - ctl.clock(), 0.05))
        wlist = [master] if ctl.out else []
        try:
            readable, _, _ = select.select([master], wlist, [], timeout)
        except InterruptedError:
            continue
        if readable:
            try:
                data = os.read(master, 65536)
            except BlockingIOError:
                data = b""
            except OSError as err:
                if err.errno != errno.EIO:
                    raise
                time.sleep(0.02)  # no slave open right now
                data = b""
            if data:
                ctl.feed(data, ctl.clock())
        if ctl.out:
            try:
                written = os.write(master, ctl.out)
                del ctl.out[:written]
            except (BlockingIOError, OSError):
                pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--telemetry-rate", type=int, default=100, help="[Hz], 0 = none")
    parser.add_argument("--robot", default=None, help="robot profile TOML (default: TDAM-STM)")
    parser.add_argument("--tau-s", type=float, default=0.05, help="wheel time constant [s]")
    parser.add_argument("--name", default="independent")
    parser.add_argument("--estop-pressed", action="store_true",
                        help="the e-stop is pressed at start (latched)")
    parser.add_argument("--estop-held-s", type=float, default=0.0,
                        help="with --estop-pressed: the button is released after this [s]")
    args = parser.parse_args(argv)
    k, limit = load_robot(args.robot)
    ctl = Controller(telemetry_rate_hz=args.telemetry_rate, wheel_limit_rpm=limit, k=k,
                     tau_s=args.tau_s, name=args.name, estop_pressed=args.estop_pressed,
                     estop_held_s=args.estop_held_s)
    master, slave = os.openpty()
    tty.setraw(slave)
    print(os.ttyname(slave), flush=True)
    stop_flag = [False]

    def on_signal(signum, frame_):
        stop_flag[0] = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        serve(ctl, master, stop_flag)
    finally:
        print(json.dumps(ctl.counters), file=sys.stderr, flush=True)
        os.close(master)
        os.close(slave)
    return 0


if __name__ == "__main__":
    sys.exit(main())
