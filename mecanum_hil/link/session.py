"""The record session: a command stream out, telemetry in, a recording on disk, safely.

:func:`run_record_session` sends commands at a fixed rate over any
:class:`~mecanum_hil.link.transport.Transport`, writes commands as sent and telemetry as
received into a recording (incrementally, flushed at least every 0.2 s), and on every way out
(normal end, Ctrl-C, SIGTERM, exception, lost link, an observer's stop request) sends STOP
(best effort) and closes the recording. The result's ``exit_code`` says which way it ended:

====================  =====  ===========================================================
reason                code   meaning
====================  =====  ===========================================================
``completed``         0      the whole profile was sent
``error``             1      an exception (the error's own exit code when it is ours)
``observer_stop``     3      an observer (shadow mode) asked to stop
``link_lost``         4      the port vanished, or the controller's telemetry stopped
``telemetry_rate``    5      telemetry far from the announced rate (or some when none was)
``controller_reset``  6      the controller clock went back, its seq restarted, an unasked
                             HELLO_ACK came, or it answers PING after its telemetry stopped:
                             it restarted behind the host's back
``estop``             7      the controller reported ``ESTOP`` during the run (stops at once)
``drive_fault``       8      the controller reported ``FAULT`` during the run (stops at once)
``not_acknowledged``  9      ``ack_seq`` stopped following the commands (stops at once)
``invalid_readings``  10     too many wheel readings not finite (judged at the end)
``clock_drift``       11     the controller clock drifted from the host's (judged at the end)
``host_stall``        12     the host's own command stream paused longer than half the
                             watchdog (judged at the end)
``interrupted``       130    Ctrl-C
``terminated``        143    SIGTERM or SIGHUP
====================  =====  ===========================================================

Reasons 7 to 9 stop the run at once: the robot is not doing what was asked. Reasons 10 to 12
let the profile run to its end (the robot did what was asked, the recording is not what was
asked) and only set the reason and exit code; the first one found is the one reported, the
others are ``link_events``. Each limit is a constant below.

Observers (shadow mode) see every telemetry sample on their own thread, so a slow observer
never delays a command; see :class:`TelemetryObserver`.
"""

from __future__ import annotations

import datetime as _dt
import math
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .. import __version__
from ..errors import (
    ConfigError,
    LimitError,
    LinkError,
    LinkLostError,
    MecanumHILError,
    ProtocolError,
    SessionTerminated,
)
from ..io.recording import MAX_ABS_VALUE, RecordingWriter
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from .protocol import (
    LIMIT_SLACK,
    PROTOCOL_VERSION,
    STATUS_DEFINED,
    THETA_LIMIT_DEG,
    WATCHDOG_S,
    ErrorMsg,
    Hello,
    HelloAck,
    Ping,
    Pong,
    Status,
    Stop,
    Telemetry,
)
from .transport import PoseReading, Transport

#: Exit code of each way a session can end.
EXIT_CODES = {"completed": 0, "error": 1, "observer_stop": 3, "link_lost": 4,
              "telemetry_rate": 5, "controller_reset": 6, "estop": 7, "drive_fault": 8,
              "not_acknowledged": 9, "invalid_readings": 10, "clock_drift": 11,
              "host_stall": 12, "interrupted": 130, "terminated": 143}

#: Reasons that end the run at once (STOP, then the tail of telemetry is kept).
STOP_AT_ONCE = ("estop", "drive_fault", "not_acknowledged")
#: Reasons judged while the profile runs to its end: they only set the reason and exit code.
NOT_AS_ASKED = ("invalid_readings", "clock_drift", "host_stall")

#: Commands left unacknowledged (``ack_seq`` not reaching them) after which, when the oldest
#: was sent more than :data:`ACK_FROZEN_S` before a telemetry sample, the run ends with
#: ``not_acknowledged``.
ACK_FROZEN_COMMANDS = 10
#: See :data:`ACK_FROZEN_COMMANDS` [s]: twice the watchdog time, so a controller that stalls
#: for less than its watchdog and then takes the commands sent meanwhile passes.
ACK_FROZEN_S = 2 * WATCHDOG_S

#: Share of telemetry samples with a wheel reading not finite (or beyond
#: :data:`WHEEL_READING_MAX_RPM`) above which the run ends with ``invalid_readings``.
INVALID_SHARE_MAX = 0.01
#: Longest run of such samples [s] (host time) before the run ends with ``invalid_readings``.
INVALID_RUN_MAX_S = 0.1

#: The controller clock may drift from the host's by this share of the elapsed time plus
#: :data:`CLOCK_DRIFT_SLACK_S` before the run ends with ``clock_drift``. It is measured on the
#: earliest arrival in each second (a late arrival is the host's or the link's delay).
CLOCK_DRIFT_MAX = 0.02
#: See :data:`CLOCK_DRIFT_MAX` [s].
CLOCK_DRIFT_SLACK_S = 0.1
#: Window of :data:`CLOCK_DRIFT_MAX`'s earliest arrivals [s].
CLOCK_DRIFT_WINDOW_S = 1.0

#: Share of the announced watchdog time the host's own command stream may pause (two commands
#: sent further apart) before the run ends with ``host_stall``.
HOST_STALL_SHARE = 0.5

#: Telemetry rate (observed over windows of at least 1 s) outside this factor of the
#: announced one ends the run with ``telemetry_rate``.
RATE_TOLERANCE = 2.0

#: The link timeout must cover this many announced telemetry periods (a damaged frame and
#: jitter on top of one period); a slower controller is refused at the handshake.
LINK_TIMEOUT_PERIODS = 3.0

#: Largest wheel reading a recording holds [rpm] (a larger one is a corrupt field there).
WHEEL_READING_MAX_RPM = MAX_ABS_VALUE["wheel1_rpm"]

#: After telemetry stopped for the link timeout (and STOP went out), the host sends PING every
#: 0.1 s for this long [s]: PONGs and no telemetry mean the controller restarted (a power-cycle:
#: it answers PING before a HELLO but sends no telemetry), ``controller_reset``; nothing, or
#: telemetry again (a stall), leaves it ``link_lost``.
RESTART_PROBE_S = 1.0

#: Non-telemetry frames in a row after which the link timeout is checked even though frames
#: keep arriving (fewer could be a backlog read after the host itself stalled).
_OTHER_FRAMES_BEFORE_CHECK = 8

#: Extra columns of a recording made by a session, after the pinned ones.
EXTRA_COLUMNS = ("event", "seq", "controller_time_s", "status")
#: What the sidecar says of the columns a recording session adds or redefines.
COLUMN_NOTES = {"t_s": "host time since the first command",
                "controller_time_s": "controller clock of a telemetry row",
                "event": "cmd: command sent, tlm: telemetry received, stop: STOP sent"}


def next_row_time(t_s: float, last_t_s: float) -> float:
    """The time written for a row at ``t_s`` after one at ``last_t_s`` [s]: six decimals on
    disk, so rows closer than 1 us are pushed apart to keep the times increasing there."""
    t = round(max(t_s, last_t_s + 1e-6), 6)
    return t if t > last_t_s else round(last_t_s + 1e-6, 6)


@runtime_checkable
class TelemetryObserver(Protocol):
    """Something that watches the telemetry of a running session (e.g. shadow mode).

    ``on_telemetry`` is called on the session's observer thread, in order, once per telemetry
    sample: ``t_s`` host receive time since the first command [s], ``commands`` the
    ``(n [rpm], omega [deg/s], theta [deg])`` in force as sent, shape (3,), ``wheel_rpm`` the
    reported wheel speeds 1..4 [rpm], shape (4,). It must not keep the arrays (they are not
    reused, but copying is cheap). The session reads ``stop_requested`` before every command;
    once it is true the session sends STOP and ends with reason ``observer_stop`` (exit 3).
    An exception raised by an observer ends the session with reason ``error``.

    Optionally an observer also defines ``on_command(t_s, commands)``: it is then told every
    command (and the final stop) at its actual send time, in order with the telemetry, and its
    ``on_telemetry`` receives ``controller_time_s=`` (the controller's clock for the sample [s]),
    which lets it time samples by the controller instead of by a possibly stalled host.
    """

    stop_requested: bool

    def on_telemetry(self, t_s: float, commands: np.ndarray, wheel_rpm: np.ndarray) -> None:
        """See the class docstring."""


@dataclass(frozen=True)
class SessionConfig:
    """Settings of a record session.

    Attributes
    ----------
    connect_timeout_s : float
        How long HELLO is repeated (every 0.1 s) before giving up [s].
    link_timeout_s : float
        Telemetry silence after which the link counts as lost, whatever other frames arrive
        (when the controller announced telemetry) [s].
    ping_rate_hz : float
        Rate of PING frames for the round-trip latency [Hz]; 0 for none.
    tail_s : float
        Telemetry kept after the STOP at the end of a completed profile [s].
    max_send_failures : int
        Consecutive failed sends after which the link counts as lost.
    handle_sigterm : bool
        Turn SIGTERM into a clean stop (main thread only).
    observer_queue : int
        Samples buffered for observers before the oldest are dropped (and counted).
    host_stall_share : float or None
        Share of the announced watchdog time the host's command stream may pause before the
        run ends with ``host_stall``; None reads :data:`HOST_STALL_SHARE` when the run checks
        it (the test suite raises that to infinity so that a loaded machine does not end tests
        of other behaviour).
    """

    connect_timeout_s: float = 2.0
    link_timeout_s: float = 0.5
    ping_rate_hz: float = 5.0
    tail_s: float = 0.2
    max_send_failures: int = 5
    handle_sigterm: bool = True
    observer_queue: int = 10000
    host_stall_share: float | None = None


@dataclass(frozen=True)
class RecordResult:
    """How a session ended and what it counted.

    Attributes
    ----------
    reason : str
        One of :data:`EXIT_CODES`.
    exit_code : int
        Process exit code for ``reason``.
    path : Path
        The recording written.
    rows : int
        Rows in the recording.
    commands_sent, telemetry_received : int
        Command frames sent and telemetry samples recorded.
    duration_s : float
        Time from the first command to the end [s].
    stats : dict
        The transport's counters (:class:`~mecanum_hil.link.transport.LinkStats`).
    latency_ms : dict
        ``rtt_*`` PING round trip and ``ack_*`` command-to-acknowledgement latency
        percentiles (``p50``, ``p90``, ``p99``, ``max``, ``n``) [ms].
    message : str
        The error's text for ``error``/``link_lost``, else empty.
    observer_dropped : int
        Telemetry samples observers did not see because they lagged.
    controller : str
        Name the controller gave in HELLO_ACK.
    signal_at_end : int or None
        A signal that came while STOP was being sent and the recording closed: kept, not
        raised, so that neither was cut short (``record --policy`` then runs no further
        episode).
    """

    reason: str
    exit_code: int
    path: Path
    rows: int
    commands_sent: int
    telemetry_received: int
    duration_s: float
    stats: dict[str, int]
    latency_ms: dict[str, float]
    message: str = ""
    observer_dropped: int = 0
    controller: str = ""
    error: BaseException | None = field(default=None, compare=False, repr=False)
    signal_at_end: int | None = None


class TelemetrySilenceError(LinkLostError):
    """No telemetry for the link timeout (the port itself still works)."""


class TelemetryCheckError(LinkError):
    """The telemetry is not sane: the run ends with STOP and ``reason``'s exit code.

    Attributes
    ----------
    reason : str
        ``"telemetry_rate"``, ``"controller_reset"`` or one of :data:`STOP_AT_ONCE` (see
        :data:`EXIT_CODES`).
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.exit_code = EXIT_CODES[reason]


def percentiles_ms(samples_s: Sequence[float], prefix: str) -> dict[str, float]:
    """``p50``, ``p90``, ``p99``, ``max`` [ms] and ``n`` of latency samples [s]."""
    out: dict[str, float] = {f"{prefix}_n": float(len(samples_s))}
    if len(samples_s):
        arr = np.asarray(samples_s) * 1e3
        for q in (50, 90, 99):
            out[f"{prefix}_p{q}"] = float(np.percentile(arr, q))
        out[f"{prefix}_max"] = float(arr.max())
    return out


class _ObserverPump:
    """Feeds observers on their own thread so they never slow the command stream."""

    def __init__(self, observers: Sequence[TelemetryObserver], maxlen: int) -> None:
        self.observers = list(observers)
        self._queue: deque = deque(maxlen=maxlen)
        self._event = threading.Event()
        self._done = False
        self.dropped = 0
        self.error: BaseException | None = None
        self._thread = None
        if self.observers:
            self._thread = threading.Thread(target=self._run, name="telemetry-observers",
                                            daemon=True)
            self._thread.start()

    def _put(self, item: tuple) -> None:
        if self._thread is None:
            return
        if len(self._queue) == self._queue.maxlen:
            self.dropped += 1
        self._queue.append(item)
        self._event.set()

    def push(self, t_s: float, commands: np.ndarray, wheels: np.ndarray,
             controller_time_s: float | None = None) -> None:
        """A telemetry sample for the observers."""
        self._put((t_s, commands, wheels, controller_time_s))

    def push_command(self, t_s: float, commands: np.ndarray) -> None:
        """A command as sent, for the observers that take commands."""
        self._put((t_s, commands, None, None))

    @property
    def stop_requested(self) -> bool:
        return any(getattr(o, "stop_requested", False) for o in self.observers)

    def _run(self) -> None:
        while True:
            self._event.wait(0.05)
            self._event.clear()
            while self._queue:
                t_s, cmd, wheels, ctrl_t = self._queue.popleft()
                for obs in self.observers:
                    try:
                        takes_commands = hasattr(obs, "on_command")
                        if wheels is None:
                            if takes_commands:
                                obs.on_command(t_s, cmd)
                        elif takes_commands:
                            obs.on_telemetry(t_s, cmd, wheels, controller_time_s=ctrl_t)
                        else:
                            obs.on_telemetry(t_s, cmd, wheels)
                    except Exception as err:  # reported by the session, which then stops
                        self.error = err
                        return
            if self._done:
                return

    def close(self, timeout_s: float = 2.0) -> None:
        if self._thread is not None:
            self._done = True
            self._event.set()
            self._thread.join(timeout_s)


class _Session:
    def __init__(self, transport: Transport, t_s: np.ndarray, commands: np.ndarray,
                 writer: RecordingWriter, config: SessionConfig,
                 observers: Sequence[TelemetryObserver],
                 progress: Callable[[float, float, dict[str, Any]], None] | None,
                 peak_wheel_rpm: float = 0.0) -> None:
        self.tr = transport
        transport.set_role("host")
        self.peak_wheel_rpm = peak_wheel_rpm
        self.t_s = t_s
        self.commands = commands
        self.writer = writer
        self.config = config
        self.pump = _ObserverPump(observers, config.observer_queue)
        self.progress = progress
        self.t0: float | None = None
        self.last_t = -math.inf
        self.cmd_in_force = np.full(3, np.nan)
        self.commands_sent = 0
        self.telemetry = 0
        self.telemetry_rate_hz = 0
        self.watchdog_ms = 0
        self.wheel_limit_rpm = math.nan
        self.last_tlm = time.perf_counter()
        #: Telemetry silence that counts as a lost link [s] (a link may ask for more).
        self.link_timeout_s = config.link_timeout_s
        self._other_frames = 0
        self.send_failures = 0
        self.controller = ""
        #: Whether :meth:`stop` has been called (STOP sent or tried).
        self.stop_attempted = False
        #: What happened on the link that did not end the run (the sidecar's ``link_events``).
        self.events: list[dict[str, Any]] = []
        self._tlm_seq: int | None = None
        self._status_seen = 0
        #: Wheel readings a recording cannot hold (NaN, infinite, beyond MAX_ABS_VALUE),
        #: written empty; which wheels sent one last time (an event when one starts).
        self.invalid_readings = 0
        self._invalid = np.zeros(4, dtype=bool)
        self._win: tuple[float, float, int] | None = None  # host time, controller time, count
        self._first = (0.0, 0.0)  # host and controller time of the first sample
        self._ping_token = 0
        self._pings: dict[int, float] = {}
        self._acks: dict[int, float] = {}
        self.rtt: list[float] = []
        self.ack: list[float] = []
        self._ctrl_wrap = 0
        self._ctrl_last = None
        self._last_progress = 0.0
        #: The profile is over (STOP sent): the run's checks no longer apply to the tail.
        self.run_over = False
        #: The first reason of :data:`NOT_AS_ASKED` found, and its message.
        self.not_as_asked: tuple[str, str] | None = None
        #: Telemetry samples with an invalid wheel reading; when the current run of them began.
        self.invalid_samples = 0
        self._invalid_since: float | None = None
        self.longest_invalid_s = 0.0
        # clock drift: host and controller time of the first sample, the earliest arrival of
        # the first window (host - controller time), the current window (start, earliest)
        self._drift0: tuple[float, float] | None = None
        self._drift_first: float | None = None
        self._drift_win: tuple[float, float] = (0.0, math.inf)
        self.clock_drift_s = 0.0
        self._last_cmd_sent: float | None = None
        self.widest_command_gap_s = 0.0

    # -- rows --------------------------------------------------------------------------------
    def _row_time(self, now: float) -> float:
        self.last_t = next_row_time(now - self.t0, self.last_t)
        return self.last_t

    def _controller_time_s(self, time_us: int) -> float:
        last = self._ctrl_last
        if last is not None:
            step = (time_us - last) % (1 << 32)
            if step == 0 or step >= 1 << 31:
                raise TelemetryCheckError(
                    "controller_reset", f"{self.tr.port}: the controller clock went back from "
                    f"{last * 1e-6:.6f} s to {time_us * 1e-6:.6f} s (the controller restarted?)")
            if time_us < last:
                self._ctrl_wrap += 1 << 32
        self._ctrl_last = time_us
        return (time_us + self._ctrl_wrap) * 1e-6

    def _event(self, now: float, event: str, detail: str) -> None:
        t = None if self.t0 is None else round(now - self.t0, 6)
        if len(self.events) < 1000:
            self.events.append({"t_s": t, "event": event, "detail": detail})

    def _check_sequence(self, msg: Telemetry) -> None:
        last = self._tlm_seq
        self._tlm_seq = msg.seq
        if last is None:
            return
        gap = (msg.seq - last) % self.tr.seq_modulus
        if gap == 0 or gap >= self.tr.seq_modulus // 2:
            raise TelemetryCheckError(
                "controller_reset", f"{self.tr.port}: the controller's sequence numbers went "
                f"back from {last} to {msg.seq} (the controller restarted?)")

    def _check_rate(self, now: float, ctrl_t: float) -> None:
        rate = self.telemetry_rate_hz
        if rate <= 0:
            raise TelemetryCheckError(
                "telemetry_rate", f"{self.tr.port}: telemetry arrives although the controller "
                "announced none (rate 0 in HELLO_ACK)")
        if self._win is None:
            self._win = (now, ctrl_t, 0)
            self._first = (now, ctrl_t)
            return
        # a controller clock running ahead of the host's (its samples claim more time than
        # passed): a stalled host only ever makes the host's elapsed time longer
        ctrl_elapsed, host_elapsed = ctrl_t - self._first[1], now - self._first[0]
        if ctrl_elapsed > RATE_TOLERANCE * host_elapsed + 1.0:
            raise TelemetryCheckError(
                "telemetry_rate", f"{self.tr.port}: the controller clock advanced "
                f"{ctrl_elapsed:.2f} s while the host's advanced {host_elapsed:.2f} s")
        h0, c0, count = self._win
        count += 1
        span = now - h0
        if span < max(1.0, 20.0 / rate):
            self._win = (h0, c0, count)
            return
        host_rate = count / span
        ctrl_span = ctrl_t - c0
        ctrl_rate = count / ctrl_span if ctrl_span > 0 else math.inf
        # too fast by the samples' own times (a backlog read after a host stall arrives
        # bunched, but its times are right); too slow by both clocks
        if ctrl_rate > RATE_TOLERANCE * rate or max(host_rate, ctrl_rate) < rate / RATE_TOLERANCE:
            raise TelemetryCheckError(
                "telemetry_rate", f"{self.tr.port}: telemetry at {ctrl_rate:.1f} Hz by the "
                f"controller clock and {host_rate:.1f} Hz by the host's, announced {rate:g} Hz")
        self._win = (now, ctrl_t, 0)

    def _note_status(self, now: float, status: int) -> None:
        # bits switching on are events; STOPPED is the host's own doing (HELLO, STOP)
        # plain ints: the complement of an IntFlag member keeps only the defined bits, which
        # would hide the reserved ones
        new = int(status) & ~int(self._status_seen) & ~int(Status.STOPPED)
        self._status_seen = int(status)
        for bit in (Status.ESTOP, Status.WATCHDOG, Status.FAULT):
            if new & bit:
                self._event(now, f"status_{bit.name.lower()}",
                            f"the controller set status bit {bit.name}")
        if new & ~STATUS_DEFINED:
            self._event(now, "status_reserved",
                        f"reserved status bits 0x{new & ~STATUS_DEFINED:04X} set (a later "
                        "protocol version's?): recorded, otherwise ignored")

    def _valid_readings(self, now: float, wheels: np.ndarray) -> np.ndarray:
        # a controller may send NaN, or infinity for a value beyond float32 (protocol.md); a
        # recording holds neither (nor a magnitude beyond any robot's, a corrupt field), and
        # one such value would make the whole file unreadable: written empty, counted
        bad = ~(np.abs(wheels) <= WHEEL_READING_MAX_RPM)
        started = bad & ~self._invalid
        self._invalid = bad
        if not bad.any():
            self._invalid_since = None
            return wheels
        self.invalid_readings += int(bad.sum())
        self.invalid_samples += 1
        if self._invalid_since is None:
            self._invalid_since = now
        lasted = now - self._invalid_since
        self.longest_invalid_s = max(self.longest_invalid_s, lasted)
        if lasted > INVALID_RUN_MAX_S:
            self._flag("invalid_readings", now, f"{self.tr.port}: wheel readings not finite "
                       f"for {lasted:.3f} s in a row (more than {INVALID_RUN_MAX_S:g} s)")
        if started.any():
            which = ", ".join(f"wheel {i + 1}: {float(wheels[i]):g}"
                              for i in np.flatnonzero(started))
            self._event(now, "invalid_reading",
                        f"{which} rpm is not a speed a recording holds: written empty "
                        "(counted in the sidecar's invalid_readings)")
        return np.where(bad, np.nan, wheels)

    # -- receiving ---------------------------------------------------------------------------
    def handle(self, msg, now: float) -> None:
        if isinstance(msg, Telemetry):
            self.last_tlm = now
            self._other_frames = 0
            self._check_sequence(msg)
            ctrl_t = self._controller_time_s(msg.time_us)
            self._check_rate(now, ctrl_t)
            self._note_status(now, msg.status)
            if self.tr.acknowledges:
                self._take_acks(msg.ack_seq, now)
            if self.t0 is None:
                return  # before the first command: nothing is in force yet
            self.telemetry += 1
            wheels = self._valid_readings(now, np.array(msg.wheel_rpm, dtype=float))
            t = self._row_time(now)
            self.writer.write(t, self.cmd_in_force, wheels,
                              extra=("tlm", msg.seq, f"{ctrl_t:.6f}", msg.status))
            self.pump.push(t, self.cmd_in_force.copy(), wheels, ctrl_t)
            if not self.run_over:  # the sample is kept first, then judged
                self._check_drift(now, ctrl_t)
                self._check_stopped_by_controller(t, msg.status)
        elif isinstance(msg, PoseReading):
            if self.t0 is None:
                return
            # a row of its own, at its receive time: the robot's odometry and joint states
            # may share a stamp, which the controller-clock column must not repeat
            self.writer.write(self._row_time(now), self.cmd_in_force,
                              pose=(msg.x_m, msg.y_m, msg.phi_deg),
                              extra=("odom", msg.seq, "", ""))
        elif isinstance(msg, Pong):
            sent = self._pings.pop(msg.token, None)
            if sent is not None:
                self.rtt.append(now - sent)
        elif isinstance(msg, ErrorMsg):
            raise ProtocolError(f"{self.tr.port}: the controller reported error {msg.code}: "
                                f"{msg.text or '(no text)'}")
        elif isinstance(msg, HelloAck):
            raise TelemetryCheckError(
                "controller_reset", f"{self.tr.port}: a HELLO_ACK came in the middle of the "
                "run: the controller restarted its session")

    def _flag(self, reason: str, now: float, message: str) -> None:
        """A reason of :data:`NOT_AS_ASKED`: a link event; the run's reason if the first."""
        if self.not_as_asked is None:
            self.not_as_asked = (reason, message)
            self._event(now, reason, message)

    def _check_stopped_by_controller(self, t_s: float, status: int) -> None:
        if status & Status.ESTOP:
            raise TelemetryCheckError(
                "estop", f"{self.tr.port}: the controller reported ESTOP at {t_s:.3f} s: the "
                "wheels are held at zero, not doing what was asked")
        if status & Status.FAULT:
            raise TelemetryCheckError(
                "drive_fault", f"{self.tr.port}: the controller reported FAULT at {t_s:.3f} s: "
                "the drive is not doing what was asked")

    def _check_drift(self, now: float, ctrl_t: float) -> None:
        """Compare the controller clock with the host's on the earliest arrival of each window
        (a late arrival is delay on the host or the link, not the controller's clock)."""
        offset = now - ctrl_t
        if self._drift0 is None:
            self._drift0 = (now, ctrl_t)
            self._drift_win = (now, offset)
            return
        start, earliest = self._drift_win
        earliest = min(earliest, offset)
        if now - start < CLOCK_DRIFT_WINDOW_S:
            self._drift_win = (start, earliest)
            return
        self._judge_drift(now, ctrl_t, earliest)
        self._drift_win = (now, offset)

    def _judge_drift(self, now: float, ctrl_t: float, earliest: float) -> None:
        if self._drift_first is None:
            self._drift_first = earliest
            return
        assert self._drift0 is not None
        drift = earliest - self._drift_first
        if abs(drift) > abs(self.clock_drift_s):
            self.clock_drift_s = drift
        host_s, ctrl_s = now - self._drift0[0], ctrl_t - self._drift0[1]
        if abs(drift) > CLOCK_DRIFT_MAX * host_s + CLOCK_DRIFT_SLACK_S:
            self._flag("clock_drift", now, f"{self.tr.port}: the controller clock advanced "
                       f"{ctrl_s:.2f} s while the host's advanced {host_s:.2f} s (a drift of "
                       f"{drift:+.3f} s, more than {CLOCK_DRIFT_MAX:.0%} + "
                       f"{CLOCK_DRIFT_SLACK_S:g} s)")

    def finish_checks(self) -> None:
        """The checks judged at the end of a profile run to its end."""
        now = time.perf_counter()
        earliest = self._drift_win[1]
        if self._drift0 is not None and math.isfinite(earliest) and self._ctrl_last is not None:
            self._judge_drift(now, self._controller_time_s_last(), earliest)
        if self.telemetry and self.invalid_samples > INVALID_SHARE_MAX * self.telemetry:
            self._flag("invalid_readings", now, f"{self.tr.port}: {self.invalid_samples} of "
                       f"{self.telemetry} telemetry samples had a wheel reading not finite "
                       f"(more than {INVALID_SHARE_MAX:.0%}; written empty)")

    def _controller_time_s_last(self) -> float:
        return ((self._ctrl_last or 0) + self._ctrl_wrap) * 1e-6

    def _take_acks(self, ack_seq: int, now: float) -> None:
        """Count the latency of every command a sample acknowledges.

        ``ack_seq`` is the last frame the controller accepted, and it handles frames in order:
        a sample acknowledges every command sent up to it, not only the one of that ``seq``.
        A controller that handled several commands between two samples (after a stall, all
        of them at once) acknowledges the earlier ones only through the last one's ``seq``;
        counting that one alone lost the longest latencies, ``ack_max`` under load most of
        all. Pending commands are kept in the order sent; ``seq`` wraps.
        """
        modulus = self.tr.seq_modulus
        while self._acks:
            seq, sent = next(iter(self._acks.items()))
            if (ack_seq - seq) % modulus >= modulus // 2:
                break  # sent after what the sample acknowledges: still pending
            del self._acks[seq]
            self.ack.append(now - sent)
        if self.run_over or len(self._acks) < ACK_FROZEN_COMMANDS:
            return
        oldest = next(iter(self._acks.values()))
        if now - oldest > ACK_FROZEN_S:
            raise TelemetryCheckError(
                "not_acknowledged", f"{self.tr.port}: {len(self._acks)} commands unacknowledged, "
                f"the oldest sent {now - oldest:.3f} s ago (ack_seq stays at {ack_seq}): the "
                "controller is not taking the commands")

    def pump_until(self, deadline: float) -> None:
        while True:
            now = time.perf_counter()
            remaining = deadline - now
            if remaining <= 0:
                break
            msg = self.tr.recv(remaining)
            now = time.perf_counter()
            self.writer.tick()
            if msg is not None:
                self.handle(msg, now)
                if not isinstance(msg, Telemetry):
                    self._other_frames += 1
            # a lost link is telemetry that stopped, whatever else keeps arriving
            if self.telemetry_rate_hz > 0 and now - self.last_tlm > self.link_timeout_s \
                    and (msg is None or self._other_frames >= _OTHER_FRAMES_BEFORE_CHECK):
                raise TelemetrySilenceError(
                    f"{self.tr.port}: link lost: no telemetry from the controller for "
                    f"{now - self.last_tlm:.2f} s" + (
                        f" ({self._other_frames} other frames came meanwhile)"
                        if self._other_frames else ""))
        self._report_progress()

    def _report_progress(self) -> None:
        if self.progress is None or self.t0 is None:
            return
        now = time.perf_counter()
        if now - self._last_progress >= 0.1:
            self._last_progress = now
            self.progress(now - self.t0, float(self.t_s[-1]),
                          {**self.tr.stats.as_dict(), "telemetry": self.telemetry})

    # -- sending -----------------------------------------------------------------------------
    def send(self, msg):
        try:
            sent = self.tr.send(msg)
        except LinkLostError:
            raise
        except LinkError as err:
            self.send_failures += 1
            if self.send_failures >= self.config.max_send_failures:
                raise LinkLostError(f"{self.tr.port}: link lost: {self.send_failures} sends in "
                                    f"a row failed ({err})") from err
            return None
        self.send_failures = 0
        return sent

    def _accept_hello_ack(self, msg: HelloAck) -> None:
        if msg.version != PROTOCOL_VERSION:
            raise ProtocolError(
                f"{self.tr.port}: the controller speaks protocol version {msg.version}, this "
                f"host speaks {PROTOCOL_VERSION} (update the firmware or mecanum-hil)")
        self.telemetry_rate_hz = msg.telemetry_rate_hz
        if msg.telemetry_rate_hz > 0:
            self.link_timeout_s = max(self.config.link_timeout_s,
                                      self.tr.min_link_timeout_s(msg.telemetry_rate_hz))
        self.watchdog_ms = msg.watchdog_ms
        self.wheel_limit_rpm = msg.wheel_limit_rpm
        self.controller = msg.name
        # the HELLO was seq 0; the controller's next frame after its HELLO_ACK is ack.seq + 1
        self.tr.expect_next(msg.seq + 1)
        self.tr.stats.lost = 0  # gaps before the session are not the session's
        self._tlm_seq = None
        self._ctrl_last = None
        self._ctrl_wrap = 0
        self._win = None
        self.last_tlm = time.perf_counter()

    def _check_announcement(self) -> None:
        gaps = np.diff(self.t_s)
        widest = float(gaps.max()) if gaps.size else 0.0
        if self.watchdog_ms <= 0 or widest >= self.watchdog_ms / 1000.0:
            raise ProtocolError(
                f"{self.tr.port}: the controller's watchdog is {self.watchdog_ms} ms but "
                f"commands are up to {widest * 1000:.0f} ms apart")
        rate = self.telemetry_rate_hz
        if rate > 0 and LINK_TIMEOUT_PERIODS / rate > self.link_timeout_s:
            # a slower stream cannot show a live link within the timeout: refused here, not
            # found out as a lost link half a second into the run
            raise ProtocolError(
                f"{self.tr.port}: the controller announces telemetry at {rate:g} Hz, too slow "
                f"for the {self.config.link_timeout_s:g} s link timeout (it must cover "
                f"{LINK_TIMEOUT_PERIODS:g} telemetry periods): give --link-timeout "
                f"{LINK_TIMEOUT_PERIODS / rate:g} or more, or a faster telemetry rate")
        limit = self.wheel_limit_rpm
        if not (math.isfinite(limit) and limit > 0):
            raise ProtocolError(f"{self.tr.port}: the controller announced no valid wheel "
                                f"speed limit ({limit!r} rpm in HELLO_ACK)")
        if self.peak_wheel_rpm > limit * (1 + LIMIT_SLACK):
            raise LimitError(
                f"{self.tr.port}: the commands need a wheel speed of {self.peak_wheel_rpm:.1f} "
                f"rpm, beyond the controller's announced limit of {limit:g} rpm (nothing "
                "was commanded)")

    def handshake(self) -> None:
        deadline = time.perf_counter() + self.config.connect_timeout_s
        hellos = 0
        while time.perf_counter() < deadline:
            self.tr.restart_sequences()  # every HELLO carries seq 0; the first command seq 1
            self.send(Hello(PROTOCOL_VERSION))
            hellos += 1
            until = min(deadline, time.perf_counter() + 0.1)
            while (now := time.perf_counter()) < until:
                msg = self.tr.recv(until - now)
                if isinstance(msg, HelloAck):
                    self._accept_hello_ack(msg)
                    if hellos > 1:
                        self._drain_late_answers()
                    self._check_announcement()
                    return
                if isinstance(msg, ErrorMsg):
                    raise ProtocolError(f"{self.tr.port}: the controller refused HELLO "
                                        f"(error {msg.code}: {msg.text or 'no text'})")
        raise LinkError(f"{self.tr.port}: no answer to HELLO within "
                        f"{self.config.connect_timeout_s:g} s (is the controller running, "
                        "is it the right port?)")

    def _drain_late_answers(self, quiet_s: float = 0.15) -> None:
        """After repeated HELLOs, wait until no answer to an earlier one can still come: each
        restarts the controller, which must not happen once commands flow."""
        until = time.perf_counter() + quiet_s
        while (now := time.perf_counter()) < until:
            msg = self.tr.recv(until - now)
            if isinstance(msg, HelloAck):
                self._accept_hello_ack(msg)
                self._event(now, "repeated_hello_ack",
                            "a repeated HELLO was answered too: the controller restarted "
                            "again before the first command")
                until = time.perf_counter() + quiet_s
            elif isinstance(msg, ErrorMsg):
                raise ProtocolError(f"{self.tr.port}: the controller refused HELLO "
                                    f"(error {msg.code}: {msg.text or 'no text'})")

    def run(self) -> None:
        self.handshake()
        ping_period = (1.0 / self.config.ping_rate_hz
                       if self.config.ping_rate_hz > 0 and self.tr.acknowledges else math.inf)
        self.t0 = time.perf_counter()
        next_ping = self.t0
        for i in range(len(self.t_s)):
            self.pump_until(self.t0 + float(self.t_s[i]))
            if self.pump.error is not None:
                raise MecanumHILError(f"observer failed: {type(self.pump.error).__name__}: "
                                      f"{self.pump.error}") from self.pump.error
            if self.pump.stop_requested:
                raise _ObserverStopError()
            now = self._send_command(self.commands[i])
            if now >= next_ping:
                self._ping_token = (self._ping_token + 1) & 0xFFFFFFFF
                if self.send(Ping(self._ping_token)) is not None:
                    self._pings[self._ping_token] = time.perf_counter()
                next_ping += ping_period

    def _send_command(self, command: np.ndarray) -> float:
        """Send one checked command, record it as in force; return when it was sent [s]."""
        wire = self.tr.wire_command(*command)
        now = time.perf_counter()
        if self._last_cmd_sent is not None:
            gap = now - self._last_cmd_sent
            self.widest_command_gap_s = max(self.widest_command_gap_s, gap)
            watchdog_s = self.watchdog_ms / 1000.0 if self.watchdog_ms > 0 else WATCHDOG_S
            share = self.config.host_stall_share
            if gap > (HOST_STALL_SHARE if share is None else share) * watchdog_s:
                at = now - (self.t0 or now)
                self._flag("host_stall", now, f"{self.tr.port}: the host's command stream "
                           f"paused {gap * 1000:.0f} ms at {at:.3f} s (more than half the "
                           f"controller's {watchdog_s * 1000:.0f} ms watchdog)")
        self._last_cmd_sent = now
        sent = self.send(wire)
        if sent is not None:
            self.commands_sent += 1
            self._acks[sent.seq] = now
            if len(self._acks) > 64:
                self._acks.pop(next(iter(self._acks)))
        self.cmd_in_force = np.array([wire.n_rpm, wire.omega_dps, wire.theta_deg])
        t_row = self._row_time(now)
        self.writer.write(t_row, self.cmd_in_force,
                          extra=("cmd", "" if sent is None else sent.seq, "", ""))
        self.pump.push_command(t_row, self.cmd_in_force.copy())
        return now

    def restarted(self, probe_s: float = RESTART_PROBE_S) -> str | None:
        """After the STOP of a run whose telemetry stopped: PING every 0.1 s for ``probe_s``.

        Returns why the controller restarted (it answers PING, yet sends no telemetry: it has
        no session), or None (no answer, telemetry again after a stall, or no PING on this
        transport). Never raises: the run is over whatever this finds.
        """
        if not self.tr.acknowledges:
            return None
        start = time.perf_counter()
        end, next_ping, tokens, pongs = start + probe_s, start, set(), 0
        try:
            while (now := time.perf_counter()) < end:
                if now >= next_ping:
                    self._ping_token = (self._ping_token + 1) & 0xFFFFFFFF
                    self.tr.send(Ping(self._ping_token))
                    tokens.add(self._ping_token)
                    next_ping += 0.1
                msg = self.tr.recv(max(0.0, min(end, next_ping) - now))
                if isinstance(msg, Telemetry):
                    return None  # the session lives on: a stall, not a restart
                if isinstance(msg, Pong) and msg.token in tokens:
                    pongs += 1
        except Exception:  # the port went away meanwhile: a lost link
            return None
        if not pongs:
            return None
        return (f"{self.tr.port}: no telemetry from the controller for "
                f"{self.link_timeout_s:g} s, yet it answered {pongs} PINGs in the "
                f"{probe_s:g} s after the STOP without sending telemetry: it restarted (a "
                "power-cycle or a reset) and has no session")

    def stop(self, keep_receiving_s: float) -> None:
        """Send STOP (best effort) and record it, then keep the tail.

        A Ctrl-C or SIGTERM while STOP is being sent (a link slow to take it) does not skip
        the STOP: it is sent again, recorded, and the interrupt is raised after that (it used
        to be swallowed, and the run went on: the next episode of ``record --policy``). Other
        failures to send are not raised (best effort)."""
        self.stop_attempted = True
        self.run_over = True
        sent = None
        interrupt: BaseException | None = None
        for _ in range(3):
            try:
                sent = self.tr.send(Stop())
                break
            except (KeyboardInterrupt, SessionTerminated) as err:
                interrupt = interrupt or err
            except Exception:
                continue
        if self.t0 is not None:
            now = time.perf_counter()
            theta = self.cmd_in_force[2] if np.isfinite(self.cmd_in_force[2]) else 90.0
            self.cmd_in_force = np.array([0.0, 0.0, theta])
            try:
                t_row = self._row_time(now)
                self.writer.write(t_row, self.cmd_in_force,
                                  extra=("stop", "" if sent is None else sent.seq, "", ""))
                self.pump.push_command(t_row, self.cmd_in_force.copy())
                if keep_receiving_s > 0 and sent is not None and interrupt is None:
                    self.pump_until(now + keep_receiving_s)
            except Exception:  # the tail is a courtesy; the recording is already complete
                pass
        if interrupt is not None:
            raise interrupt


class _ObserverStopError(Exception):
    pass


def check_command_stream(t_s, commands, robot: RobotProfile,
                         transport: Transport | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Check a command stream before anything is sent; return it with times from 0.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Send times [s].
    commands : array_like, shape (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])``.
    robot : RobotProfile
        Limits every command is checked against.
    transport : Transport, optional
        Its encoding's ranges are checked too (:meth:`Transport.check_commands`).

    Returns
    -------
    t_s : ndarray, shape (T,)
        Send times from the first command [s].
    commands : ndarray, shape (T, 3)

    Raises
    ------
    ConfigError
        Lengths that differ, times not finite and increasing, or a gap the controller's
        watchdog would stop the wheels in.
    LimitError
        A command beyond the robot's limits or the transport's ranges.
    """
    t = np.asarray(t_s, dtype=float).reshape(-1)
    cmd = np.asarray(commands, dtype=float).reshape(-1, 3)
    if t.size == 0 or t.size != cmd.shape[0]:
        raise ConfigError(f"{t.size} send times for {cmd.shape[0]} commands")
    if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise ConfigError("command times must be finite and increasing")
    if t.size > 1 and np.diff(t).max() >= WATCHDOG_S:
        raise ConfigError(f"commands are {np.diff(t).max():.3f} s apart somewhere: the "
                          f"controller's watchdog stops the wheels after {WATCHDOG_S:g} s; use "
                          "a command rate of at least 5 Hz")
    robot.check_commands(cmd, "commands to send")
    if transport is not None:
        transport.check_commands(cmd, "commands to send")
    beyond = np.abs(cmd[:, 2]) > THETA_LIMIT_DEG
    if beyond.any():
        i = int(np.argmax(beyond))
        raise LimitError(f"commands to send: row {i} has theta = {cmd[i, 2]:g} deg, beyond the "
                         f"protocol's +-{THETA_LIMIT_DEG:g} deg (a controller refuses it)")
    return t - t[0], cmd


def run_record_session(
    transport: Transport,
    t_s,
    commands,
    out: str | Path,
    robot: RobotProfile,
    *,
    config: SessionConfig | None = None,
    observers: Sequence[TelemetryObserver] = (),
    metadata: dict[str, Any] | None = None,
    progress: Callable[[float, float, dict[str, Any]], None] | None = None,
) -> RecordResult:
    """Send ``commands`` at times ``t_s`` over ``transport`` and record everything.

    Parameters
    ----------
    transport : Transport
        Open link to the controller (not closed here).
    t_s : array_like, shape (T,)
        Send times from the first command [s], increasing.
    commands : array_like, shape (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])`` to send at ``t_s``.
    out : str or Path
        Recording to write (CSV + JSON sidecar).
    robot : RobotProfile
        Limits every command is checked against before the first byte is sent.
    config : SessionConfig, optional
    observers : sequence of TelemetryObserver
        Called with every telemetry sample on a separate thread (shadow mode).
    metadata : dict, optional
        Added to the recording's sidecar.
    progress : callable, optional
        ``progress(elapsed_s, total_s, counters)``, at most every 0.1 s.

    Returns
    -------
    RecordResult
        Never raises for a way out in the table of the module docstring except bad input:

    Raises
    ------
    LimitError
        A command exceeds the robot's limits (nothing was sent).
    ConfigError
        Times that do not increase, or gaps longer than the controller's watchdog.
    """
    config = config or SessionConfig()
    t, cmd = check_command_stream(t_s, commands, robot, transport)
    # fsync at every flush (at least every 0.2 s): a power loss keeps what was received
    writer = RecordingWriter(out, EXTRA_COLUMNS, _start_metadata(transport, robot, metadata),
                             fsync=True)
    peak = float(np.abs(command_to_wheels(cmd[:, 0], cmd[:, 1], cmd[:, 2], robot.k)).max())
    sess = _Session(transport, t, cmd, writer, config, observers, progress, peak)
    return _stream_stop_close(sess, transport, writer, out, config)


def _stream_stop_close(sess: _Session, transport: Transport, writer: RecordingWriter,
                       out: str | Path, config: SessionConfig, *,
                       settle: Callable[[], None] | None = None,
                       cut_short: Callable[[str], None] | None = None,
                       end_extra: Callable[[], dict[str, Any]] | None = None) -> RecordResult:
    """Run ``sess`` to its end, STOP at every way out, close the recording; the result.

    The one place the ways out of a command stream are handled (``record`` and
    ``record --policy``): SIGTERM/SIGHUP end the stream while it runs, how it ended is
    classified (:func:`_stream_until_end`), STOP is sent whatever happened (guarded against a
    Ctrl-C or SIGTERM meanwhile), the handlers are put back and the sidecar is closed.

    Parameters
    ----------
    settle : callable, optional
        After the STOP of a completed stream, in place of keeping ``config.tail_s`` of
        telemetry (``record --policy`` waits for the wheels to come to rest). A Ctrl-C or
        SIGTERM in it ends the run as ``interrupted`` (STOP again), a link error as
        ``link_lost``.
    cut_short : callable, optional
        ``cut_short(reason)`` before the STOP of a stream that did not complete.
    end_extra : callable, optional
        Keys added to the sidecar's end (called as the recording is closed).
    """
    reason, message, error = "completed", "", None
    failing: BaseException | None = None  # an exception on its way out of the stream
    guard = SignalGuard(config.handle_sigterm)
    try:
        try:
            guard.check()
            reason, message, error, tail = _stream_until_end(sess, config)
            # from here a signal is kept, not raised: nothing may cut STOP or the close short
            guard.defer()
        except (KeyboardInterrupt, SessionTerminated) as exc:  # as the stream was ending
            reason, tail = signal_reason(exc), 0.0
            guard.defer()
        ran_to_end = reason == "completed" or reason in NOT_AS_ASKED
        if not ran_to_end and cut_short is not None:
            cut_short(reason)
        # every way out: STOP first, then the recording is closed cleanly
        try:
            sess.stop(tail if settle is None else 0.0)
            if isinstance(error, TelemetrySilenceError):  # silence: a restart or a lost link
                why = sess.restarted()
                if why is not None:
                    reason, message = "controller_reset", why
        except (KeyboardInterrupt, SessionTerminated) as exc:
            # raised after STOP went out, where no guard defers signals (not the main
            # thread, handle_sigterm off): during the tail a courtesy, the run still
            # completed; with episodes to come (settle) the run ends here
            if settle is not None:
                reason = signal_reason(exc)
            settle = None
        if settle is not None and ran_to_end and sess.t0 is not None:
            try:
                with guard.raising():  # waiting for rest may be cut short: STOP is out
                    settle()
            except (KeyboardInterrupt, SessionTerminated) as exc:
                reason = signal_reason(exc)
                sess.stop(0.0)
            except LinkError as err:  # only settling receives on its own (STOP never raises)
                reason, message, error = "link_lost", str(err), err
            except Exception as err:  # a row that cannot be written while settling, ...
                reason, message, error = "error", str(err), err
    except BaseException as exc:  # what no end of the stream takes (SystemExit, a callback's)
        guard.defer()  # nothing may cut STOP or the close short from here
        failing = exc
        if reason == "completed" or reason in NOT_AS_ASKED:  # the sidecar must not say the
            # stream ran to its end
            if isinstance(exc, (KeyboardInterrupt, SessionTerminated)):
                reason = signal_reason(exc)  # no guard (handle_sigterm off): raised here
            else:
                reason, message = "error", f"ended by {type(exc).__name__}: {exc}"
        raise
    finally:
        # Without a guard (handle_sigterm off, not the main thread) a signal raises where it
        # lands: one that lands in the fallback STOP, the observers' close or the end's
        # metadata is kept and raised once the recording is closed, not in place of its close
        # (and not in place of an exception already on its way out: STOP has gone out)
        late: BaseException | None = None
        try:
            guard.defer()
            if not sess.stop_attempted:  # an exception (or a signal) before the STOP above
                try:
                    sess.stop(0.0)
                except (KeyboardInterrupt, SessionTerminated) as exc:
                    late = exc
            try:
                sess.pump.close()
            except (KeyboardInterrupt, SessionTerminated) as exc:
                late = late or exc
            except Exception:  # the observers' thread: the recording is closed all the same
                pass
            duration = 0.0 if sess.t0 is None else time.perf_counter() - sess.t0
            latency = {**percentiles_ms(sess.rtt, "rtt"), **percentiles_ms(sess.ack, "ack")}
            try:
                end_meta = _end_metadata(sess, transport, reason, message, latency)
                if end_extra is not None:
                    end_meta.update(end_extra())
            except (KeyboardInterrupt, SessionTerminated, Exception) as err:
                # the end is written, whatever failed (or was cut short) in making it
                if isinstance(err, (KeyboardInterrupt, SessionTerminated)):
                    late = late or err
                end_meta = {"end_reason": reason, "exit_code": EXIT_CODES[reason],
                            "end_message": f"{message} (end metadata failed: {err!r})"}
            writer.close(end_meta)
        finally:
            guard.restore()
        if late is not None and failing is None:
            raise late
    if sess.pump.error is not None and reason == "error" and error is None:
        error = sess.pump.error
    exit_code = EXIT_CODES[reason]
    if reason == "error" and isinstance(error, MecanumHILError):
        exit_code = error.exit_code
    return RecordResult(reason, exit_code, Path(out), writer.rows, sess.commands_sent,
                        sess.telemetry, duration, transport.stats.as_dict(), latency, message,
                        sess.pump.dropped, sess.controller, error, guard.pending)


def _start_metadata(transport: Transport, robot: RobotProfile,
                    metadata: dict[str, Any] | None,
                    source: str = "mecanum-hil record") -> dict[str, Any]:
    """The sidecar's keys known before the first byte is sent."""
    return {
        "source": source,
        "tool_version": __version__,
        "transport": transport.name,
        "port": str(getattr(transport, "port", "")),
        "protocol_version": PROTOCOL_VERSION,
        "robot_profile": robot.source,
        "started_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "columns": dict(COLUMN_NOTES),
        "notes": "",
        **(metadata or {}),
    }


#: Signals that end a command stream, each of which would otherwise end the process with no
#: STOP: SIGTERM (kill, a service manager), SIGHUP (a closed terminal or SSH session) and
#: SIGINT (Ctrl-C) always; SIGQUIT (Ctrl-\) and the others that terminate by default where
#: nothing else handles them. SIGKILL cannot be caught: the controller's watchdog stops then.
ENDING_SIGNALS = ("SIGTERM", "SIGHUP", "SIGINT", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM",
                  "SIGXCPU", "SIGVTALRM", "SIGPROF")


def signal_reason(exc: BaseException) -> str:
    """The end reason of a signal's exception: ``interrupted`` for Ctrl-C, else
    ``terminated``."""
    return "interrupted" if isinstance(exc, KeyboardInterrupt) else "terminated"


def signal_end_reason(signum: int) -> str:
    """The end reason of a signal kept by a :class:`SignalGuard` (as :func:`signal_reason`)."""
    return "interrupted" if signum == signal.SIGINT else "terminated"


def _signal_exception(signum: int) -> BaseException:
    """What a signal raises in a stream: ``KeyboardInterrupt`` for Ctrl-C, else
    :class:`SessionTerminated`."""
    return KeyboardInterrupt() if signum == signal.SIGINT else SessionTerminated()


class SignalGuard:
    """The stream's signal handlers, from its start until its recording is closed.

    While raising (the stream runs), the first signal of :data:`ENDING_SIGNALS` ends it:
    SIGINT raises ``KeyboardInterrupt`` (also where the process was started with SIGINT
    ignored: Python then installs no handler, and Ctrl-C did nothing while the robot drove
    on), the others :class:`SessionTerminated`. After that, and once :meth:`defer` is called
    (STOP and the close), a signal is kept in :attr:`pending` and nothing is raised: a second
    Ctrl-C used to land in the close and lose the sidecar's end. Installed only in the main
    thread and when ``active``; guards nest (the inner restores the outer's handlers).

    Parameters
    ----------
    active : bool
        Install the handlers (``SessionConfig.handle_sigterm``).
    """

    def __init__(self, active: bool = True) -> None:
        self.pending: int | None = None
        # installed keeping signals: one that comes while the handlers go in is raised by
        # check() inside the caller's try, not out of this constructor (handlers orphaned)
        self._raise = False
        self._saved: dict[int, Any] = {}
        if active and threading.current_thread() is threading.main_thread():
            for name in ENDING_SIGNALS:
                sig = getattr(signal, name, None)
                if sig is None:
                    continue
                current = signal.getsignal(sig)
                if (name not in ("SIGTERM", "SIGHUP", "SIGINT") and current is not signal.SIG_DFL
                        and getattr(current, "__func__", None) is not SignalGuard._on_signal):
                    continue  # someone else handles (or ignores) it; an outer guard's we take
                self._saved[sig] = signal.signal(sig, self._on_signal)
        self._raise = True

    def check(self) -> None:
        """Raise a signal kept so far (while raising), as its handler would have."""
        if self.pending is not None and self._raise:
            signum, self.pending = self.pending, None
            self._raise = False
            raise _signal_exception(signum)

    def _on_signal(self, signum, frame) -> None:
        if not self._raise:
            self.pending = self.pending or signum
            return
        self._raise = False  # once: the way out that follows must not be cut short
        self.pending = None
        raise _signal_exception(signum)

    def defer(self) -> None:
        """From now on keep a signal in :attr:`pending` instead of raising."""
        self._raise = False

    def rearm(self) -> None:
        """Raise again from now on; a signal kept meanwhile is raised at once."""
        self._raise = True
        self.check()

    @contextmanager
    def raising(self):
        """Raise again while inside (a wait after STOP that a signal may cut short); a signal
        already pending is raised on entry."""
        if self.pending is not None:
            signum, self.pending = self.pending, None
            raise _signal_exception(signum)
        self._raise = True
        try:
            yield
        finally:
            self._raise = False

    def restore(self) -> None:
        """Put back the handlers found at the start."""
        for sig, handler in self._saved.items():
            signal.signal(sig, handler)
        self._saved.clear()


def _stream_until_end(sess: _Session, config: SessionConfig
                      ) -> tuple[str, str, BaseException | None, float]:
    """Handshake and stream until the profile ends or something ends it first.

    Returns ``(reason, message, error, tail_s)``: how it ended (a key of :data:`EXIT_CODES`)
    and the telemetry to keep after STOP [s] (only after a completed profile). The caller
    sends STOP whatever this returns or raises.
    """
    try:
        sess.run()
        sess.finish_checks()
        if sess.not_as_asked is not None:  # the profile ran to its end, not as asked
            reason, message = sess.not_as_asked
            return reason, message, None, config.tail_s
        return "completed", "", None, config.tail_s
    except _ObserverStopError:
        return "observer_stop", "", None, 0.0
    except TelemetryCheckError as err:
        # the controller stopped (or ignores) the commands: the tail shows the wheels at rest
        return err.reason, str(err), err, config.tail_s if err.reason in STOP_AT_ONCE else 0.0
    except LinkLostError as err:
        return "link_lost", str(err), err, 0.0
    except KeyboardInterrupt:
        return "interrupted", "", None, 0.0
    except SessionTerminated:
        return "terminated", "", None, 0.0
    except Exception as err:
        return "error", str(err), err, 0.0


def _end_metadata(sess: _Session, transport: Transport, reason: str, message: str,
                  latency: dict[str, float]) -> dict[str, Any]:
    """The sidecar's keys known once the stream has ended: how, and what the link did."""
    result_meta = {"end_reason": reason, "exit_code": EXIT_CODES[reason],
                   "link_stats": transport.stats.as_dict(), "latency_ms": latency,
                   "link_events": sess.events,
                   **transport.link_metadata(),
                   "invalid_readings": sess.invalid_readings,
                   "run_checks": {
                       "invalid_samples": sess.invalid_samples,
                       "longest_invalid_s": round(sess.longest_invalid_s, 6),
                       "clock_drift_s": round(sess.clock_drift_s, 6),
                       "widest_command_gap_s": round(sess.widest_command_gap_s, 6),
                       "unacknowledged_commands": len(sess._acks)},
                   "controller": sess.controller,
                   "controller_wheel_limit_rpm": (sess.wheel_limit_rpm
                                                  if math.isfinite(sess.wheel_limit_rpm)
                                                  else None),
                   "telemetry_rate_hz": sess.telemetry_rate_hz,
                   # the recording's sample rate is the telemetry's (commands interleave)
                   "sample_rate_hz": sess.telemetry_rate_hz or None}
    if message:
        result_meta["end_message"] = message
    return result_meta
