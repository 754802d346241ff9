"""The robot-link seam: one small abstract base, backends by name, an entry-point group.

Following python-can's ``BusABC``: a backend implements three protected hooks
(:meth:`Transport._send`, :meth:`Transport._recv`, :meth:`Transport._close`); the base does
the shared work (sequence numbers, loss counting, statistics, error wrapping). Backends are
found by name in :data:`TRANSPORTS` (``"module:Class"``, imported lazily) and in the
entry-point group ``mecanum_hil.transports``, so a controller of another make plugs in from
its own package::

    [project.entry-points."mecanum_hil.transports"]
    acme = "acme_robot.link:AcmeTransport"

Both ends of a link use the same classes: the host (``record``) and the simulated controller
(``sim-robot``) send and receive :mod:`~mecanum_hil.link.protocol` messages through them.
"""

from __future__ import annotations

import dataclasses
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import import_module, metadata
from typing import Any, ClassVar

from ..errors import ConfigError, LinkError
from .protocol import CONTROLLER_MESSAGES, HOST_MESSAGES, Command, FrameError, Message

#: Entry-point group through which other packages add transports.
ENTRY_POINT_GROUP = "mecanum_hil.transports"

#: Built-in transports by name.
TRANSPORTS: dict[str, str] = {
    "serial": "mecanum_hil.link.serial_link:SerialTransport",
    "can": "mecanum_hil.link.can_link:CanTransport",
    "ros2": "mecanum_hil.link.ros2.transport:Ros2Transport",
}


@dataclass(frozen=True)
class PoseReading:
    """A pose the robot measured itself (its odometry), from transports that carry one.

    Attributes
    ----------
    x_m, y_m : float
        Position in the odometry frame [m].
    phi_deg : float
        Heading [deg].
    seq : int
        Counts the readings from 0.
    """

    x_m: float
    y_m: float
    phi_deg: float
    seq: int = 0


@dataclass
class LinkStats:
    """Counters of one end of a link [frames] (mutable: the stateful shell).

    A received frame is counted once, by its first failure: ``malformed`` (not a frame, too
    long, wrong body length, on CAN a wrong length or an unpaired telemetry half), then
    ``crc_errors``, ``unknown_types``, ``version_errors``. ``lost`` is a gap in the peer's
    ``seq`` less the frames dropped just before it (those are counted already). ``echoes``
    are this end's own frames heard back (a shared CAN bus, a half-duplex line): dropped and
    counted nowhere else.
    """

    sent: int = 0
    received: int = 0
    lost: int = 0
    crc_errors: int = 0
    malformed: int = 0
    unknown_types: int = 0
    version_errors: int = 0
    bus_errors: int = 0
    send_errors: int = 0
    garbage_bytes: int = 0
    echoes: int = 0

    def as_dict(self) -> dict[str, int]:
        """The counters by name."""
        return dataclasses.asdict(self)


class Transport(ABC):
    """One end of a link to a robot controller (or, for the simulator, to a host).

    Subclasses set :attr:`name` and :attr:`seq_modulus` and implement the three hooks.
    """

    #: Registry name of the backend.
    name: ClassVar[str] = "abstract"
    #: Sequence numbers run modulo this (2**16 on serial, 2**8 on CAN).
    seq_modulus: ClassVar[int] = 1 << 16
    #: Whether the peer acknowledges commands (telemetry's ``ack_seq``) and answers PING;
    #: a link without (ROS 2) has no command-to-acknowledgement latency to measure.
    acknowledges: ClassVar[bool] = True

    def __init__(self) -> None:
        self.stats = LinkStats()
        self._tx_seq = 0
        self._rx_expected: int | None = None
        self._closed = False
        #: Message types this end receives (``None``: all); see :meth:`set_role`.
        self.receives: tuple[type, ...] | None = None
        #: Dropped frames whose header was trustworthy (:class:`FrameError` with ``mtype``),
        #: the latest 64; a controller answers a refused COMMAND among them with ERROR 2.
        self.rejected: deque[FrameError] = deque(maxlen=64)
        #: Frames a backend dropped since the last valid message (explain a seq gap).
        self._drops_since_valid = 0

    # -- the hooks a backend implements ------------------------------------------------------
    @abstractmethod
    def _send(self, msg: Message) -> None:
        """Put one message on the wire; raise :class:`LinkError` on failure."""

    @abstractmethod
    def _recv(self, timeout_s: float) -> Message | None:
        """The next valid message, waiting at most ``timeout_s`` [s]; ``None`` on timeout.

        Count dropped input in :attr:`stats`; raise :class:`LinkLostError` when the link is gone.
        """

    @abstractmethod
    def _close(self) -> None:
        """Release the port or bus."""

    # -- shared logic ------------------------------------------------------------------------
    @classmethod
    def from_options(cls, **options: Any) -> Transport:
        """Build the transport from command-line options (``port``, ``channel``, ...)."""
        return cls(**options)

    def wire_command(self, n_rpm: float, omega_dps: float, theta_deg: float) -> Command:
        """The command exactly as this transport's encoding will carry it (quantised)."""
        return Command(float(n_rpm), float(omega_dps), float(theta_deg))

    def check_commands(self, commands: Any, what: str = "commands to send") -> None:
        """Refuse commands this transport's encoding cannot carry, before anything is sent.

        ``commands`` is ``(T, 3)``: ``(n [rpm], omega [deg/s], theta [deg])``. The base
        accepts every finite value (the serial frame carries float32).

        Raises
        ------
        LimitError
            Naming the row and the range the encoding carries.
        """
        return None

    def send(self, msg: Message) -> Message:
        """Send ``msg`` with the next sequence number; return it as sent.

        Raises
        ------
        LinkError
            When the backend cannot send (counted in ``stats.send_errors``).
        """
        msg = dataclasses.replace(msg, seq=self._tx_seq)
        try:
            self._send(msg)
        except LinkError:
            self.stats.send_errors += 1
            raise
        self._tx_seq = (self._tx_seq + 1) % self.seq_modulus
        self.stats.sent += 1
        return msg

    def set_role(self, role: str) -> None:
        """``"host"`` or ``"controller"``: from then on, messages only the other side sends are
        received; this side's own (echoed) frames are dropped and counted as ``echoes``."""
        if role not in ("host", "controller"):
            raise ValueError(f"role must be 'host' or 'controller', got {role!r}")
        self.receives = CONTROLLER_MESSAGES if role == "host" else HOST_MESSAGES

    def min_link_timeout_s(self, telemetry_rate_hz: float) -> float:
        """The shortest telemetry silence this link may count as lost at ``telemetry_rate_hz``
        [s] (0: the configured timeout holds)."""
        return 0.0

    def link_metadata(self) -> dict[str, Any]:
        """What the recording's sidecar says of this link at the end of a run (none here)."""
        return {}

    def send_raw(self, data: Any) -> None:
        """Put ``data`` on the wire as it is, bypassing framing and numbering (conformance
        tests send damaged frames with it): bytes on serial, ``(id, bytes)`` on CAN.

        Raises
        ------
        NotImplementedError
            When the backend cannot send raw data (such conformance rules are skipped).
        """
        raise NotImplementedError(f"the {self.name} transport sends no raw frames")

    def _dropped(self, n: int = 1) -> None:
        """Backends call this for every frame they drop, in order with the valid ones."""
        self._drops_since_valid += n

    def recv(self, timeout_s: float = 0.0) -> Message | None:
        """The next valid message within ``timeout_s`` [s], or ``None``; counts sequence gaps.

        A gap is counted as lost frames less the frames dropped just before the message (a
        frame is counted once, by its first failure); a jump backwards (a restarted peer, a
        duplicate) is not a loss: the count resynchronises.
        """
        deadline = time.monotonic() + max(0.0, timeout_s)
        while True:
            msg = self._recv(max(0.0, deadline - time.monotonic()))
            if msg is None:
                return None
            if self.receives is None or isinstance(msg, self.receives):
                break
            self.stats.echoes += 1
        self.stats.received += 1
        expected = self._rx_expected
        if expected is not None:
            gap = (msg.seq - expected) % self.seq_modulus
            if gap < self.seq_modulus // 2:
                self.stats.lost += max(0, gap - self._drops_since_valid)
        self._drops_since_valid = 0
        self._rx_expected = (msg.seq + 1) % self.seq_modulus
        return msg

    def restart_sequences(self) -> None:
        """Start both directions' sequence numbering afresh (at HELLO)."""
        self._tx_seq = 0
        self._rx_expected = None
        self._drops_since_valid = 0

    def expect_next(self, seq: int) -> None:
        """The peer's next frame carries ``seq`` (after a HELLO_ACK with ``seq - 1``)."""
        self._rx_expected = seq % self.seq_modulus
        self._drops_since_valid = 0

    @property
    def next_seq(self) -> int:
        """The ``seq`` the next frame sent will carry."""
        return self._tx_seq

    def set_next_seq(self, seq: int) -> None:
        """Number the next frame ``seq`` (conformance tests of the wrap-around)."""
        self._tx_seq = seq % self.seq_modulus

    def close(self) -> None:
        """Close the link (idempotent)."""
        if not self._closed:
            self._closed = True
            self._close()

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available_transports() -> dict[str, str]:
    """Every transport name with where it comes from (``module:Class``)."""
    names = dict(TRANSPORTS)
    for name, ep in _entry_points().items():
        names.setdefault(name, ep.value)
    return names


def transport_class(name: str) -> type[Transport]:
    """The transport class registered as ``name`` (built-in first, then entry points)."""
    if name in TRANSPORTS:
        module, _, attr = TRANSPORTS[name].partition(":")
        return getattr(import_module(module), attr)
    eps = _entry_points()
    if name not in eps:
        raise ConfigError(f"unknown transport '{name}' (available: "
                          f"{', '.join(sorted(available_transports()))})")
    try:
        cls = eps[name].load()
    except Exception as err:  # a third-party plug-in can fail in any way
        raise ConfigError(f"transport '{name}' ({eps[name].value}) cannot be loaded: "
                          f"{err}") from err
    if not (isinstance(cls, type) and issubclass(cls, Transport)):
        raise ConfigError(f"transport '{name}' ({eps[name].value}) is not a Transport subclass")
    return cls


def open_transport(name: str, options: Mapping[str, Any] | None = None) -> Transport:
    """Open the transport ``name`` with ``options`` (unset ones dropped).

    Raises
    ------
    ConfigError
        For an unknown name or options the backend does not take.
    LinkError
        When the port or bus cannot be opened.
    """
    cls = transport_class(name)
    opts = {k: v for k, v in (options or {}).items() if v is not None}
    try:
        return cls.from_options(**opts)
    except TypeError as err:
        raise ConfigError(f"transport '{name}': {err}") from err


def parse_option_value(text: str) -> Any:
    """A ``--link-option KEY=VALUE`` value: int, float, true/false, or the text itself."""
    low = text.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def transport_options(transport: str, *, port: str | None = None,
                      interface: str | None = None, channel: str | None = None,
                      bitrate: int | None = None, link_options: list[str] | None = None
                      ) -> dict[str, Any]:
    """The options a command line's link flags give ``open_transport``.

    ``link_options`` are ``KEY=VALUE`` strings (:func:`parse_option_value`).

    Raises
    ------
    ConfigError
        A link option without ``=``.
    """
    options: dict[str, Any] = {}
    if transport == "serial":
        options.update(port=port, baudrate=bitrate)
    elif transport == "can":
        options.update(interface=interface, channel=channel, bitrate=bitrate)
    else:
        options.update(port=port, interface=interface, channel=channel, bitrate=bitrate)
    for item in link_options or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--link-option needs KEY=VALUE, got {item!r}")
        options[key.strip()] = parse_option_value(value)
    return options
