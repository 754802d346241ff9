"""The controller wire protocol: messages, and their serial framing (pure, no I/O).

The byte-by-byte definition with worked example frames is ``drivers/protocol.md``; the CAN
mapping of the same messages is ``drivers/mecanum_hil.dbc`` (see :mod:`mecanum_hil.link.can`).

Serial frame (before framing), all integers little-endian::

    version u8 | type u8 | seq u16 | body ... | crc u16

``crc`` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor) over
everything before it. The frame is COBS-encoded (no 0x00 byte inside) and sent between 0x00
delimiters, ``00 <cobs> 00``: a receiver resynchronises at the next 0x00 after any garbage.
"""

from __future__ import annotations

import binascii
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

#: Protocol version spoken by this package (byte 0 of every serial frame, HELLO on CAN).
#: Version 2 added the wheel speed limit to HELLO_ACK, ESTOP_RESET, empty-bodied HELLO and
#: the sequence rules at HELLO (drivers/protocol.md, "Changes from version 1").
PROTOCOL_VERSION = 2

#: The controller stops the wheels when no valid command or heartbeat came for this long [s].
WATCHDOG_S = 0.25

#: Longest frame before COBS encoding (header + body + CRC) [bytes].
MAX_FRAME_BYTES = 64

#: Longest encoded frame a receiver buffers before it drops the bytes as garbage [bytes].
MAX_ENCODED_BYTES = MAX_FRAME_BYTES + MAX_FRAME_BYTES // 254 + 2

#: Commanded direction of travel a controller accepts [deg] (the CAN signal's range).
THETA_LIMIT_DEG = 655.36

#: Relative slack on the wheel speed limit, so that a command at the limit survives float32.
LIMIT_SLACK = 1e-6

#: Largest finite float32; larger finite values are sent as infinity of the same sign.
FLOAT32_MAX = 3.4028234663852886e38

_HEADER = struct.Struct("<BBH")


class MsgType(IntEnum):
    """Message type byte. Host to controller below 0x80, controller to host from 0x80."""

    HELLO = 0x01
    COMMAND = 0x02
    STOP = 0x03
    HEARTBEAT = 0x04
    PING = 0x05
    ESTOP_RESET = 0x06
    HELLO_ACK = 0x81
    TELEMETRY = 0x82
    PONG = 0x85
    ERROR = 0x8F


class Status(IntFlag):
    """Bits of the telemetry status word (the others are reserved and sent as 0)."""

    ESTOP = 0x0001       #: e-stop latched: wheels held at zero until ESTOP_RESET
    WATCHDOG = 0x0002    #: stopped by the watchdog, waiting for a new COMMAND
    STOPPED = 0x0004     #: a STOP (or the HELLO) is in force, until the next COMMAND
    FAULT = 0x0008       #: the controller reports a drive fault


#: Status bits version 2 defines; a controller sends the others as 0.
STATUS_DEFINED = 0x000F


class ErrorCode(IntEnum):
    """Code byte of an ERROR message."""

    VERSION_MISMATCH = 1
    BAD_COMMAND = 2
    ESTOP_HELD = 3
    OTHER = 255


@dataclass(frozen=True)
class Hello:
    """Host -> controller at connect; its header carries the host's protocol version."""

    version: int = PROTOCOL_VERSION
    seq: int = 0


@dataclass(frozen=True)
class Command:
    """Host -> controller: the motion command in force from now on.

    Attributes
    ----------
    n_rpm : float
        Translation speed in wheel-rpm units [rpm].
    omega_dps : float
        Turning speed, CCW positive [deg/s].
    theta_deg : float
        Direction of travel, 0 = right, 90 = ahead [deg].
    """

    n_rpm: float
    omega_dps: float
    theta_deg: float
    seq: int = 0


@dataclass(frozen=True)
class Stop:
    """Host -> controller: stop the wheels now (in force until the next command)."""

    seq: int = 0


@dataclass(frozen=True)
class Heartbeat:
    """Host -> controller: keep the watchdog fed without changing the command."""

    seq: int = 0


@dataclass(frozen=True)
class Ping:
    """Host -> controller: answer at once with a PONG carrying the same token."""

    token: int
    seq: int = 0


@dataclass(frozen=True)
class EstopReset:
    """Host -> controller: clear a latched e-stop (once the button is released); the wheels
    stay stopped (``STOPPED``) until the next COMMAND. The only message that clears it."""

    seq: int = 0


@dataclass(frozen=True)
class HelloAck:
    """Controller -> host: answer to HELLO.

    Attributes
    ----------
    version : int
        The controller's protocol version.
    telemetry_rate_hz : int
        Telemetry rate the controller will send at [Hz]; 0 for none.
    watchdog_ms : int
        The controller's command watchdog [ms].
    name : str
        Free-form controller name (UTF-8, at most 32 bytes on serial, absent on CAN).
    wheel_limit_rpm : float
        The largest wheel speed target the controller accepts [rpm] (its robot profile's
        ``wheel_speed_max_rpm``); a command needing more is refused with ERROR 2. Only parsed
        from a HELLO_ACK of this package's version (0 for another version).
    """

    version: int = PROTOCOL_VERSION
    telemetry_rate_hz: int = 100
    watchdog_ms: int = int(WATCHDOG_S * 1000)
    name: str = ""
    seq: int = 0
    wheel_limit_rpm: float = 0.0


@dataclass(frozen=True)
class Telemetry:
    """Controller -> host: one sample of the wheel speeds.

    Attributes
    ----------
    time_us : int
        Controller clock, modulo 2**32 [us]; restarts at 0 on each accepted HELLO.
    wheel_rpm : tuple of 4 float
        Measured wheel speeds 1 FL, 2 FR, 3 RL, 4 RR [rpm].
    status : int
        :class:`Status` bits.
    ack_seq : int
        Sequence number of the last host message the controller accepted.
    """

    time_us: int
    wheel_rpm: tuple[float, float, float, float]
    status: int = 0
    ack_seq: int = 0
    seq: int = 0


@dataclass(frozen=True)
class Pong:
    """Controller -> host: answer to PING."""

    token: int
    seq: int = 0


@dataclass(frozen=True)
class ErrorMsg:
    """Controller -> host: the controller refused something (see :class:`ErrorCode`)."""

    code: int
    text: str = ""
    seq: int = 0


Message = (Hello | Command | Stop | Heartbeat | Ping | EstopReset | HelloAck | Telemetry | Pong
           | ErrorMsg)

#: Messages a host sends and a controller sends.
HOST_MESSAGES = (Hello, Command, Stop, Heartbeat, Ping, EstopReset)
CONTROLLER_MESSAGES = (HelloAck, Telemetry, Pong, ErrorMsg)

_TYPE_OF = {Hello: MsgType.HELLO, Command: MsgType.COMMAND, Stop: MsgType.STOP,
            Heartbeat: MsgType.HEARTBEAT, Ping: MsgType.PING, EstopReset: MsgType.ESTOP_RESET,
            HelloAck: MsgType.HELLO_ACK, Telemetry: MsgType.TELEMETRY, Pong: MsgType.PONG,
            ErrorMsg: MsgType.ERROR}
_COMMAND = struct.Struct("<fff")
_TOKEN = struct.Struct("<I")
_HELLO_ACK = struct.Struct("<HHf")
_TELEMETRY = struct.Struct("<IffffHH")
#: Types that keep their layout in every protocol version, so versions can be negotiated.
_VERSION_FREE = (MsgType.HELLO, MsgType.HELLO_ACK, MsgType.ERROR)


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``crc16(b"123456789") == 0x29B1``)."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: ``data`` without 0x00 bytes, one byte longer per 254."""
    out = bytearray()
    block = bytearray()
    for byte in data:
        if byte == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
        else:
            block.append(byte)
            if len(block) == 254:
                out.append(255)
                out += block
                block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes | None:
    """Inverse of :func:`cobs_encode`; ``None`` for a block that is not valid COBS."""
    out = bytearray()
    i = 0
    n = len(data)
    while i < n:
        code = data[i]
        if code == 0 or i + code > n:
            return None
        out += data[i + 1:i + code]
        i += code
        if code < 255 and i < n:
            out.append(0)
    return bytes(out)


def f32(value: float) -> float:
    """``value`` as a float32 field carries it: finite values beyond the float32 range become
    infinity of their sign (packing never raises; the receiver refuses them as non-finite)."""
    v = float(value)
    if math.isfinite(v) and abs(v) > FLOAT32_MAX:
        return math.copysign(math.inf, v)
    return v


def _body(msg: Message) -> bytes:
    if isinstance(msg, Command):
        return _COMMAND.pack(f32(msg.n_rpm), f32(msg.omega_dps), f32(msg.theta_deg))
    if isinstance(msg, Ping | Pong):
        return _TOKEN.pack(msg.token & 0xFFFFFFFF)
    if isinstance(msg, HelloAck):
        return _HELLO_ACK.pack(min(max(int(msg.telemetry_rate_hz), 0), 0xFFFF),
                               min(max(int(msg.watchdog_ms), 0), 0xFFFF),
                               f32(msg.wheel_limit_rpm)) + _utf8_prefix(msg.name, 32)
    if isinstance(msg, Telemetry):
        return _TELEMETRY.pack(msg.time_us & 0xFFFFFFFF, *(f32(w) for w in msg.wheel_rpm),
                               msg.status & 0xFFFF, msg.ack_seq & 0xFFFF)
    if isinstance(msg, ErrorMsg):
        return bytes([msg.code & 0xFF]) + _utf8_prefix(msg.text, 40)
    return b""


def _utf8_prefix(text: str, limit: int) -> bytes:
    # cut on a character boundary: a cut inside a character would make the frame malformed
    data = text.encode("utf-8")
    while len(data) > limit:
        text = text[:-1]
        data = text.encode("utf-8")
    return data


def pack_frame(msg: Message) -> bytes:
    """The unframed bytes of ``msg``: header, body and CRC (before COBS)."""
    version = msg.version if isinstance(msg, Hello | HelloAck) else PROTOCOL_VERSION
    raw = _HEADER.pack(version & 0xFF, _TYPE_OF[type(msg)], msg.seq & 0xFFFF) + _body(msg)
    return raw + struct.pack("<H", crc16(raw))


def encode(msg: Message) -> bytes:
    """The bytes to put on the wire for ``msg``: ``00 <COBS(frame)> 00``."""
    return b"\x00" + cobs_encode(pack_frame(msg)) + b"\x00"


class FrameError(ValueError):
    """Why a frame was dropped; ``kind`` is the counter it goes to.

    ``mtype`` and ``seq`` are set when the frame's header can be trusted (its CRC was right):
    a controller answers a refused COMMAND with ERROR 2 (``kind`` ``"malformed"`` for a wrong
    body length, ``"bad_command"`` for a reserved byte that is not 0 on CAN).
    """

    def __init__(self, kind: str, message: str, mtype: int | None = None,
                 seq: int | None = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.mtype = mtype
        self.seq = seq


def unpack_frame(raw: bytes) -> Message:
    """Parse one unframed frame (after COBS decoding).

    Raises
    ------
    FrameError
        ``kind`` is ``"malformed"`` (too short, wrong body length), ``"crc"``, ``"version"``
        or ``"unknown_type"``.
    """
    if len(raw) < _HEADER.size + 2:
        raise FrameError("malformed", f"frame of {len(raw)} bytes is shorter than 6")
    if crc16(raw[:-2]) != struct.unpack_from("<H", raw, len(raw) - 2)[0]:
        raise FrameError("crc", "CRC mismatch")
    version, mtype, seq = _HEADER.unpack_from(raw)
    body = raw[_HEADER.size:-2]
    try:
        kind = MsgType(mtype)
    except ValueError:
        raise FrameError("unknown_type", f"unknown message type 0x{mtype:02X}", mtype,
                         seq) from None
    if version != PROTOCOL_VERSION and kind not in _VERSION_FREE:
        raise FrameError("version", f"protocol version {version}, expected {PROTOCOL_VERSION}",
                         mtype, seq)
    try:
        return _parse_body(kind, version, seq, body)
    except (struct.error, UnicodeDecodeError) as err:
        raise FrameError("malformed", f"{kind.name} body of {len(body)} bytes: {err}", mtype,
                         seq) from None


def _exact(body: bytes, size: int) -> None:
    if len(body) != size:
        raise struct.error(f"expected {size} bytes")


def _parse_body(kind: MsgType, version: int, seq: int, body: bytes) -> Message:
    if kind is MsgType.HELLO:
        _exact(body, 0)  # empty in every version, so that versions can be told apart
        return Hello(version, seq)
    if kind is MsgType.COMMAND:
        _exact(body, _COMMAND.size)
        return Command(*_COMMAND.unpack(body), seq=seq)
    if kind in (MsgType.STOP, MsgType.HEARTBEAT, MsgType.ESTOP_RESET):
        _exact(body, 0)
        return {MsgType.STOP: Stop, MsgType.HEARTBEAT: Heartbeat,
                MsgType.ESTOP_RESET: EstopReset}[kind](seq)
    if kind in (MsgType.PING, MsgType.PONG):
        _exact(body, _TOKEN.size)
        (token,) = _TOKEN.unpack(body)
        return Ping(token, seq) if kind is MsgType.PING else Pong(token, seq)
    if kind is MsgType.HELLO_ACK:
        if version != PROTOCOL_VERSION:
            return HelloAck(version, 0, 0, "", seq)  # another version's body: not ours to read
        if len(body) < _HELLO_ACK.size or len(body) > _HELLO_ACK.size + 32:
            raise struct.error("HELLO_ACK body of the wrong length")
        rate, watchdog, limit = _HELLO_ACK.unpack_from(body)
        return HelloAck(version, rate, watchdog, body[_HELLO_ACK.size:].decode("utf-8"), seq,
                        limit)
    if kind is MsgType.TELEMETRY:
        _exact(body, _TELEMETRY.size)
        t, w1, w2, w3, w4, status, ack = _TELEMETRY.unpack(body)
        return Telemetry(t, (w1, w2, w3, w4), status, ack, seq)
    # ERROR
    if len(body) < 1 or len(body) > 41:
        raise struct.error("ERROR body of the wrong length")
    return ErrorMsg(body[0], body[1:].decode("utf-8", errors="replace"), seq)


def command_problem(n_rpm: float, omega_dps: float, theta_deg: float, k: float,
                    wheel_limit_rpm: float) -> str | None:
    """Why a controller must refuse a COMMAND, or ``None`` when it is valid.

    The rule of drivers/protocol.md: every field finite, ``|theta|`` at most
    :data:`THETA_LIMIT_DEG`, and every wheel speed target the command needs within
    ``wheel_limit_rpm`` (with :data:`LIMIT_SLACK`).

    Parameters
    ----------
    n_rpm, omega_dps, theta_deg : float
        The command's fields [rpm], [deg/s], [deg].
    k : float
        The robot's ``(lx + ly) / r`` [-].
    wheel_limit_rpm : float
        The limit announced in HELLO_ACK [rpm].

    Returns
    -------
    str or None
        A short reason (at most 40 bytes, the ERROR text), or ``None``.
    """
    from ..model.kinematics import command_to_wheels

    for name, value in (("n", n_rpm), ("omega", omega_dps), ("theta", theta_deg)):
        if not math.isfinite(value):
            return f"{name} not finite"
    if abs(theta_deg) > THETA_LIMIT_DEG:
        return "theta out of range"
    wheels = command_to_wheels(float(n_rpm), float(omega_dps), float(theta_deg), k)
    peak = max(abs(float(w)) for w in wheels)
    if not peak <= wheel_limit_rpm * (1.0 + LIMIT_SLACK):
        return f"wheel target {peak:.6g} rpm > limit"[:40]
    return None


@dataclass
class DecodeCounts:
    """What a :class:`StreamDecoder` dropped, by reason [frames]."""

    malformed: int = 0
    crc: int = 0
    version: int = 0
    unknown_type: int = 0
    garbage_bytes: int = 0

    @property
    def frames(self) -> int:
        """Frames dropped for any reason [frames]."""
        return self.malformed + self.crc + self.version + self.unknown_type


@dataclass
class StreamDecoder:
    """Incremental serial frame decoder: bytes in, messages out, garbage counted and skipped.

    Feed it any chunks of the received byte stream; every frame between two 0x00 delimiters
    is COBS-decoded, CRC-checked and parsed. Bad frames are counted in :attr:`counts` (once
    each, by their first failure) and dropped; the decoder never raises on input and holds at
    most ``MAX_ENCODED_BYTES``. A dropped frame whose CRC was right (so its type and seq can
    be trusted) is also kept in :attr:`rejected` (the last 64): a controller answers a refused
    COMMAND with ERROR 2.
    """

    counts: DecodeCounts = field(default_factory=DecodeCounts)
    rejected: deque = field(default_factory=lambda: deque(maxlen=64))
    _buf: bytearray = field(default_factory=bytearray)
    _discarding: bool = False
    _drops: int = 0

    def feed(self, data: bytes) -> list[Message]:
        """Decode ``data`` appended to what came before; return the complete messages."""
        return [msg for msg, _ in self.feed_counted(data)]

    def feed_counted(self, data: bytes) -> list[tuple[Message, int]]:
        """As :meth:`feed`, each message with the number of frames dropped just before it
        (so a receiver counts a sequence gap those explain only once)."""
        out: list[tuple[Message, int]] = []
        start = 0
        while True:
            end = data.find(b"\x00", start)
            if end < 0:
                self._append(data[start:])
                return out
            self._append(data[start:end])
            chunk = bytes(self._buf)
            discarded = self._discarding
            self._buf.clear()
            self._discarding = False
            start = end + 1
            if discarded:
                continue
            if chunk:
                msg = self._decode(chunk)
                if msg is not None:
                    out.append((msg, self._drops))
                    self._drops = 0

    def _append(self, piece: bytes) -> None:
        if self._discarding:
            self.counts.garbage_bytes += len(piece)
            return
        self._buf += piece
        if len(self._buf) > MAX_ENCODED_BYTES:
            # longer than any frame: garbage until the next delimiter
            self.counts.garbage_bytes += len(self._buf)
            self.counts.malformed += 1
            self._drops += 1
            self._buf.clear()
            self._discarding = True

    def _decode(self, chunk: bytes) -> Message | None:
        raw = cobs_decode(chunk)
        if raw is None:
            self.counts.malformed += 1
            self.counts.garbage_bytes += len(chunk)
            self._drops += 1
            return None
        try:
            return unpack_frame(raw)
        except FrameError as err:
            setattr(self.counts, err.kind, getattr(self.counts, err.kind) + 1)
            self.counts.garbage_bytes += len(chunk)
            self._drops += 1
            if err.mtype is not None:
                self.rejected.append(err)
            return None
