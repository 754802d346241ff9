"""The CAN transport: the protocol's messages as the frames of ``drivers/mecanum_hil.dbc``.

Signals are scaled integers encoded and decoded with cantools; the bus is any python-can
interface (socketcan, slcan, pcan, kvaser, virtual, ...). A telemetry sample is two frames,
``MC_STATUS`` then ``MC_WHEELS``; the receiver pairs each ``MC_WHEELS`` with the status
frame just before it (a CAN node's frames stay in order on the bus).
"""

from __future__ import annotations

import time
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, LimitError, LinkError, LinkLostError
from ..io.resources import resource_dir
from .protocol import (
    PROTOCOL_VERSION,
    Command,
    ErrorMsg,
    EstopReset,
    FrameError,
    Heartbeat,
    Hello,
    HelloAck,
    Message,
    MsgType,
    Ping,
    Pong,
    Stop,
    Telemetry,
)
from .transport import Transport

#: The CAN database shipped in ``drivers/``.
DBC_NAME = "mecanum_hil.dbc"

_NAME_OF = {Stop: "MH_STOP", Command: "MH_COMMAND", Heartbeat: "MH_HEARTBEAT",
            Hello: "MH_HELLO", Ping: "MH_PING", EstopReset: "MH_ESTOP_RESET",
            ErrorMsg: "MC_ERROR", HelloAck: "MC_HELLO_ACK", Pong: "MC_PONG"}

#: Identifiers of host frames and controller frames (the DBC's ranges).
HOST_IDS = range(0x100, 0x180)
CONTROLLER_IDS = range(0x180, 0x200)


def dbc_path() -> Path:
    """Path of the shipped CAN database."""
    return resource_dir("drivers") / DBC_NAME


@lru_cache(maxsize=1)
def load_database():
    """The shipped CAN database (cantools), loaded once."""
    import cantools

    try:
        return cantools.database.load_file(str(dbc_path()))
    except Exception as err:  # cantools raises several parse error types
        raise ConfigError(f"{dbc_path()}: cannot load the CAN database: {err}") from err


class CanCodec:
    """Protocol messages to and from ``(arbitration_id, data)`` pairs (pure, no bus)."""

    def __init__(self) -> None:
        self.db = load_database()
        self._by_name = {m.name: m for m in self.db.messages}
        self._by_id = {m.frame_id: m for m in self.db.messages}
        self._pending_status: dict[str, int] | None = None

    def encode(self, msg: Message) -> list[tuple[int, bytes]]:
        """The frames that carry ``msg`` (two for telemetry, one otherwise)."""
        seq = msg.seq & 0xFF
        if isinstance(msg, Telemetry):
            status = self._by_name["MC_STATUS"].encode(
                {"time_us": msg.time_us & 0xFFFFFFFF, "status": msg.status & 0xFFFF,
                 "ack_seq": msg.ack_seq & 0xFF, "seq": seq})
            wheels = self._by_name["MC_WHEELS"].encode(
                {f"wheel{i + 1}": _clamp(v, 327.67) for i, v in enumerate(msg.wheel_rpm)})
            return [(self._by_name["MC_STATUS"].frame_id, bytes(status)),
                    (self._by_name["MC_WHEELS"].frame_id, bytes(wheels))]
        spec = self._by_name[_NAME_OF[type(msg)]]
        values: dict[str, Any] = {"seq": seq}
        if isinstance(msg, Command):
            values.update(n_cmd=msg.n_rpm, omega_cmd=msg.omega_dps, theta_cmd=msg.theta_deg,
                          reserved=0)
        elif isinstance(msg, Hello):
            values["version"] = msg.version
        elif isinstance(msg, Ping | Pong):
            values["token"] = msg.token & 0xFFFFFFFF
        elif isinstance(msg, HelloAck):
            values.update(version=msg.version,
                          telemetry_rate=min(max(int(msg.telemetry_rate_hz), 0), 0xFFFF),
                          watchdog=min(max(int(msg.watchdog_ms), 0), 0xFFFF),
                          # a larger limit is announced as the signal's end
                          wheel_limit=min(max(float(msg.wheel_limit_rpm), 0.0), 655.35))
        elif isinstance(msg, ErrorMsg):
            values["code"] = msg.code & 0xFF
        try:
            data = spec.encode(values)
        except Exception as err:  # cantools EncodeError: a value outside the signal's range
            raise LinkError(f"{spec.name}: cannot encode {msg}: {err}") from err
        return [(spec.frame_id, bytes(data))]

    def decode(self, arbitration_id: int, data: bytes) -> Message | None:
        """The message a received frame completes; ``None`` for the first half of telemetry.

        Raises
        ------
        FrameError
            ``kind`` ``"unknown_type"`` for an id not in the database, ``"malformed"`` for a
            wrong length or an ``MC_WHEELS`` without its ``MC_STATUS``.
        """
        spec = self._by_id.get(arbitration_id)
        if spec is None:
            raise FrameError("unknown_type", f"unknown CAN id 0x{arbitration_id:03X}")
        name = spec.name
        if len(data) != spec.length:
            if name == "MC_HELLO_ACK" and data and data[0] != PROTOCOL_VERSION:
                # another version's answer: its first byte is the version, the rest not ours
                return HelloAck(int(data[0]), 0, 0, "", 0)
            raise FrameError("malformed", f"{spec.name} with {len(data)} bytes, expected "
                             f"{spec.length}", MsgType.COMMAND if name == "MH_COMMAND" else None)
        v = spec.decode(bytes(data), decode_choices=False)
        if name == "MC_STATUS":
            lost_half = self._pending_status is not None
            self._pending_status = {k: int(v[k]) for k in ("time_us", "status", "ack_seq", "seq")}
            if lost_half:
                raise FrameError("malformed", "MC_STATUS without its MC_WHEELS")
            return None
        if name == "MC_WHEELS":
            st = self._pending_status
            self._pending_status = None
            if st is None:
                raise FrameError("malformed", "MC_WHEELS without its MC_STATUS")
            wheels = tuple(float(v[f"wheel{i}"]) for i in range(1, 5))
            return Telemetry(st["time_us"], wheels, st["status"], st["ack_seq"], st["seq"])
        seq = int(v["seq"])
        if name == "MH_COMMAND":
            if int(v["reserved"]) != 0:
                # a later version may give the byte a meaning this controller cannot honour
                raise FrameError("bad_command", "MH_COMMAND with reserved byte "
                                 f"{int(v['reserved'])}, must be 0", MsgType.COMMAND, seq)
            return Command(float(v["n_cmd"]), float(v["omega_cmd"]), float(v["theta_cmd"]), seq)
        if name == "MH_STOP":
            return Stop(seq)
        if name == "MH_HEARTBEAT":
            return Heartbeat(seq)
        if name == "MH_HELLO":
            return Hello(int(v["version"]), seq)
        if name == "MH_PING":
            return Ping(int(v["token"]), seq)
        if name == "MH_ESTOP_RESET":
            return EstopReset(seq)
        if name == "MC_PONG":
            return Pong(int(v["token"]), seq)
        if name == "MC_HELLO_ACK":
            return HelloAck(int(v["version"]), int(v["telemetry_rate"]), int(v["watchdog"]),
                            "", seq, float(v["wheel_limit"]))
        return ErrorMsg(int(v["code"]), "", seq)

    def check_commands(self, commands, what: str = "commands to send") -> None:
        """Refuse commands outside the ``MH_COMMAND`` signals' ranges (the DBC's min/max).

        Parameters
        ----------
        commands : array_like, shape (T, 3)
            ``(n [rpm], omega [deg/s], theta [deg])``.
        what : str
            Name used in the error message.

        Raises
        ------
        LimitError
            Naming the first row outside a range, and the range.
        """
        c = np.asarray(commands, dtype=float).reshape(-1, 3)
        spec = self._by_name["MH_COMMAND"]
        for col, (name, unit) in enumerate((("n_cmd", "rpm"), ("omega_cmd", "deg/s"),
                                             ("theta_cmd", "deg"))):
            sig = spec.get_signal_by_name(name)
            bad = (c[:, col] < sig.minimum) | (c[:, col] > sig.maximum)
            if bad.any():
                i = int(np.argmax(bad))
                raise LimitError(
                    f"{what}: row {i} has {name.removesuffix('_cmd')} = {c[i, col]:g} {unit}, "
                    f"outside what the CAN command carries [{sig.minimum:g}, {sig.maximum:g}]")

    def wire_command(self, n_rpm: float, omega_dps: float, theta_deg: float) -> Command:
        """The command after the DBC's scaling, as the controller will decode it."""
        ((fid, data),) = self.encode(Command(n_rpm, omega_dps, theta_deg))
        self_state = self._pending_status
        try:
            msg = self.decode(fid, data)
        finally:
            self._pending_status = self_state
        assert isinstance(msg, Command)
        return msg


def count_frame_error(transport: Transport, err: FrameError) -> None:
    """Count a dropped CAN frame once, by its first failure, and keep a trustworthy one in
    ``transport.rejected`` (a refused command is answered with ERROR 2)."""
    if err.kind == "unknown_type":
        transport.stats.unknown_types += 1
    elif err.kind == "malformed":
        transport.stats.malformed += 1
    if err.kind != "bad_command":
        transport._dropped()
    if err.mtype is not None:
        transport.rejected.append(err)


def _clamp(value: float, limit: float) -> float:
    # a wheel faster than the signal's range is reported at the range's end, not refused
    return max(-limit - 0.01, min(limit, float(value)))


class CanTransport(Transport):
    """The protocol on a python-can bus.

    Parameters
    ----------
    interface : str, optional
        python-can interface name (``socketcan``, ``slcan``, ``pcan``, ``virtual``, ...).
    channel : str, optional
        The interface's channel (``can0``, ``/dev/ttyACM0``, ...).
    bitrate : int, optional
        Bus bitrate [bit/s], for interfaces that set it.
    bus : can.BusABC, optional
        An already open bus instead of ``interface``/``channel`` (closed with the transport).
    **bus_options
        Passed to :class:`can.Bus` (e.g. ``sleep_after_open=0`` for slcan).
    """

    name = "can"
    seq_modulus = 1 << 8

    def __init__(self, interface: str | None = None, channel: str | None = None,
                 bitrate: int | None = None, bus=None, **bus_options: Any) -> None:
        super().__init__()
        import can

        self._can = can
        self._codec = CanCodec()
        if bus is None:
            if interface is None or channel is None:
                raise LinkError("the CAN transport needs --interface I and --channel C")
            kwargs = dict(bus_options)
            if bitrate is not None:
                kwargs["bitrate"] = int(bitrate)
            try:
                bus = can.Bus(interface=interface, channel=channel, **kwargs)
            except (can.CanError, OSError, ValueError, ImportError) as err:
                raise LinkError(f"CAN {interface}:{channel}: cannot open the bus: {err}") from err
        self.bus = bus
        self.port = f"{interface}:{channel}" if interface else str(bus.channel_info)

    def wire_command(self, n_rpm: float, omega_dps: float, theta_deg: float) -> Command:
        return self._codec.wire_command(n_rpm, omega_dps, theta_deg)

    def check_commands(self, commands, what: str = "commands to send") -> None:
        self._codec.check_commands(commands, what)

    def _send(self, msg: Message) -> None:
        for fid, data in self._codec.encode(msg):
            self._put(fid, data)

    def _put(self, fid: int, data: bytes) -> None:
        frame = self._can.Message(arbitration_id=fid, data=data, is_extended_id=False)
        try:
            self.bus.send(frame, timeout=0.05)
        except self._can.CanError as err:
            self.stats.bus_errors += 1
            raise LinkError(f"CAN {self.port}: send failed: {err}") from err

    def send_raw(self, data: tuple[int, bytes]) -> None:
        """Send one CAN frame ``(arbitration_id, data)`` as it is (conformance tests)."""
        fid, payload = data
        self._put(int(fid), bytes(payload))

    def _own_ids(self) -> range | None:
        if self.receives is None:
            return None
        return HOST_IDS if Command not in self.receives else CONTROLLER_IDS

    def _recv(self, timeout_s: float) -> Message | None:
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = max(0.0, deadline - time.monotonic())
            try:
                frame = self.bus.recv(timeout=remaining)
            except self._can.CanError as err:
                raise LinkLostError(f"CAN {self.port}: link lost: {err}") from err
            except (OSError, ValueError) as err:  # the adapter's serial port vanished
                raise LinkLostError(f"CAN {self.port}: link lost: {err}") from err
            if frame is None:
                return None
            if frame.is_error_frame:
                self.stats.bus_errors += 1
                continue
            own = self._own_ids()
            if not getattr(frame, "is_rx", True) or (
                    own is not None and not frame.is_extended_id
                    and frame.arbitration_id in own):
                # our own frame heard back (receive_own_messages, udp_multicast's loopback):
                # not received, not a gap in the peer's numbering
                self.stats.echoes += 1
                continue
            if frame.is_remote_frame or frame.is_extended_id:
                self.stats.unknown_types += 1
                self._dropped()
                continue
            try:
                msg = self._codec.decode(frame.arbitration_id, bytes(frame.data))
            except FrameError as err:
                count_frame_error(self, err)
                continue
            if msg is not None:
                return msg
            if remaining <= 0:
                return None

    def _close(self) -> None:
        try:
            self.bus.shutdown()
        except Exception:  # an adapter that vanished must not mask the real error
            pass
