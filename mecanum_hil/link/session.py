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

The parts, by concern: this module holds the session (:class:`RecordSession`: handshake,
commands, telemetry and its checks); :mod:`~mecanum_hil.link.stop_path` the ways out (STOP,
the close, the result); :mod:`~mecanum_hil.link.signals` turns signals into clean stops;
:mod:`~mecanum_hil.link.observers` feeds the observers; :mod:`~mecanum_hil.link.session_types`
holds the config, the end reasons and the result. Their public names are importable from here.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

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
from .observers import ObserverPump, ObserverStopError, TelemetryObserver
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
from .session_types import (
    EXIT_CODES,
    NOT_AS_ASKED,
    STOP_AT_ONCE,
    RecordResult,
    SessionConfig,
    TelemetryCheckError,
    TelemetrySilenceError,
    percentiles_ms,
)
from .signals import ENDING_SIGNALS, SignalGuard, signal_end_reason, signal_reason
from .stop_path import stream_stop_close
from .transport import PoseReading, Transport

__all__ = [
    "ACK_FROZEN_COMMANDS", "ACK_FROZEN_S", "CLOCK_DRIFT_MAX", "CLOCK_DRIFT_SLACK_S",
    "CLOCK_DRIFT_WINDOW_S", "COLUMN_NOTES", "ENDING_SIGNALS", "EXIT_CODES", "EXTRA_COLUMNS",
    "HOST_STALL_SHARE", "INVALID_RUN_MAX_S", "INVALID_SHARE_MAX", "LINK_TIMEOUT_PERIODS",
    "NOT_AS_ASKED", "RATE_TOLERANCE", "RESTART_PROBE_S", "STOP_AT_ONCE", "WATCHDOG_S",
    "WHEEL_READING_MAX_RPM", "RecordResult", "RecordSession", "SessionConfig",
    "SessionTerminated", "SignalGuard", "TelemetryCheckError", "TelemetryObserver",
    "TelemetrySilenceError", "check_command_stream", "next_row_time", "percentiles_ms",
    "run_record_session", "signal_end_reason", "signal_reason",
]

#: The observer pump under the name tests patch it by.
_ObserverPump = ObserverPump

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
#: See :data:`CLOCK_DRIFT_MAX` [s]. The environment variable ``MECANUM_HIL_CLOCK_DRIFT_SLACK_S``
#: overrides it, and ``SessionConfig.clock_drift_slack_s`` overrides both.
CLOCK_DRIFT_SLACK_S = 0.1
#: Window of :data:`CLOCK_DRIFT_MAX`'s earliest arrivals [s].
CLOCK_DRIFT_WINDOW_S = 1.0

#: Share of the announced watchdog time the host's own command stream may pause (two commands
#: sent further apart) before the run ends with ``host_stall``. The environment variable
#: ``MECANUM_HIL_HOST_STALL_SHARE`` overrides it (a host that also runs other work, or a test
#: suite on a loaded machine: ``inf`` judges no pause), and ``SessionConfig.host_stall_share``
#: overrides both.
HOST_STALL_SHARE = 0.5


def run_check_limit(given: float | None, variable: str, default: float) -> float:
    """A run check's limit: ``given`` (a ``SessionConfig`` field), else the environment
    variable ``variable``, else ``default``.

    Raises
    ------
    ConfigError
        The environment variable is not a number >= 0 (``inf`` allowed).
    """
    if given is not None:
        return float(given)
    text = os.environ.get(variable)
    if text is None or not text.strip():
        return default
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value >= 0:
        raise ConfigError(f"{variable} must be a number >= 0 (inf: no limit), got {text!r}")
    return value

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


class RecordSession:
    """One command stream over a link: handshake, commands out, telemetry in, checks, STOP.

    :func:`run_record_session` builds it and hands it to
    :func:`~mecanum_hil.link.stop_path.stream_stop_close`, which runs it (:meth:`run`) and
    sends STOP (:meth:`stop`) at every way out. Host times are ``time.perf_counter()``.

    Parameters
    ----------
    transport : Transport
        Open link to the controller (its role is set to ``host``).
    t_s : ndarray, shape (T,)
        Send times from the first command [s].
    commands : ndarray, shape (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])`` to send at ``t_s``.
    writer : RecordingWriter
        The recording rows go to.
    config : SessionConfig
    observers : sequence of TelemetryObserver
        Fed on their own thread (:class:`~mecanum_hil.link.observers.ObserverPump`).
    progress : callable or None
        ``progress(elapsed_s, total_s, counters)``, at most every 0.1 s.
    peak_wheel_rpm : float
        Largest wheel speed the commands need [rpm], checked against the announced limit.

    Attributes
    ----------
    tr : Transport
        The link.
    pump : ObserverPump
        The observers' queue and thread.
    t0 : float or None
        Host time of the first command [s]; None before it.
    last_t : float
        Time of the last row written [s] since ``t0``.
    cmd_in_force : ndarray, shape (3,)
        The command last sent ``(n [rpm], omega [deg/s], theta [deg])``; NaN before one.
    commands_sent, telemetry : int
        Command frames sent, telemetry samples recorded.
    telemetry_rate_hz : int
        Telemetry rate the controller announced [Hz] (0: none).
    watchdog_ms : int
        The controller's announced watchdog [ms].
    wheel_limit_rpm : float
        The controller's announced wheel speed limit [rpm].
    link_timeout_s : float
        Telemetry silence that counts as a lost link [s] (a link may ask for more than the
        config's).
    last_tlm : float
        Host time of the last telemetry sample [s].
    send_failures : int
        Failed sends in a row.
    controller : str
        Name the controller gave in HELLO_ACK.
    stop_attempted : bool
        Whether :meth:`stop` has been called (STOP sent or tried).
    run_over : bool
        The profile is over (STOP sent): the run's checks no longer apply to the tail.
    events : list of dict
        What happened on the link that did not end the run (the sidecar's ``link_events``,
        ``t_s`` [s] since ``t0``).
    not_as_asked : tuple of (str, str) or None
        The first reason of :data:`NOT_AS_ASKED` found, and its message.
    invalid_readings, invalid_samples : int
        Wheel readings a recording cannot hold (written empty), and samples with one.
    longest_invalid_s : float
        Longest run of samples with an invalid reading [s].
    clock_drift_s : float
        Largest drift of the controller clock from the host's [s].
    widest_command_gap_s : float
        Longest pause between two commands sent [s].
    rtt, ack : list of float
        PING round trips and command-to-acknowledgement latencies [s].
    """

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
        self.stall_share = run_check_limit(config.host_stall_share,
                                           "MECANUM_HIL_HOST_STALL_SHARE", HOST_STALL_SHARE)
        self.drift_slack_s = run_check_limit(config.clock_drift_slack_s,
                                             "MECANUM_HIL_CLOCK_DRIFT_SLACK_S",
                                             CLOCK_DRIFT_SLACK_S)
        self.pump = ObserverPump(observers, config.observer_queue)
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
        """Take one received frame at host time ``now`` [s]: record it, check it.

        Raises :class:`TelemetryCheckError` (or :class:`~mecanum_hil.errors.ProtocolError`)
        when the telemetry shows the run must end."""
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
        if abs(drift) > CLOCK_DRIFT_MAX * host_s + self.drift_slack_s:
            self._flag("clock_drift", now, f"{self.tr.port}: the controller clock advanced "
                       f"{ctrl_s:.2f} s while the host's advanced {host_s:.2f} s (a drift of "
                       f"{drift:+.3f} s, more than {CLOCK_DRIFT_MAX:.0%} + "
                       f"{self.drift_slack_s:g} s)")

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
        """Receive and handle frames until host time ``deadline`` [s]; raise
        :class:`TelemetrySilenceError` when telemetry stopped for the link timeout."""
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
        """Send ``msg``; the frame sent, or None when the send failed (the link counts as
        lost, :class:`~mecanum_hil.errors.LinkLostError`, after
        ``config.max_send_failures`` failures in a row)."""
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
        """HELLO every 0.1 s until HELLO_ACK, then check what the controller announced."""
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
        """Handshake, then send every command at its time (PING beside them)."""
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
                raise ObserverStopError()
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
            if gap > self.stall_share * watchdog_s:
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
    # the limits from the environment are refused before a file is made or a byte is sent
    run_check_limit(config.host_stall_share, "MECANUM_HIL_HOST_STALL_SHARE", HOST_STALL_SHARE)
    run_check_limit(config.clock_drift_slack_s, "MECANUM_HIL_CLOCK_DRIFT_SLACK_S",
                    CLOCK_DRIFT_SLACK_S)
    # fsync at every flush (at least every 0.2 s): a power loss keeps what was received
    writer = RecordingWriter(out, EXTRA_COLUMNS, _start_metadata(transport, robot, metadata),
                             fsync=True)
    peak = float(np.abs(command_to_wheels(cmd[:, 0], cmd[:, 1], cmd[:, 2], robot.k)).max())
    sess = RecordSession(transport, t, cmd, writer, config, observers, progress, peak)
    return stream_stop_close(sess, transport, writer, out, config)


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

