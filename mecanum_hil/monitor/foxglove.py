"""Shadow mode in Foxglove: a live view over the Foxglove WebSocket protocol, and alarms as logs.

:class:`FoxgloveLive` serves the channels of ``export`` (:data:`mecanum_hil.io.mcap_export.
CHANNELS`: commands, wheel speeds measured and predicted, alarms as ``foxglove.Log``) with the
``foxglove-sdk`` server, bound to localhost unless told otherwise. :class:`FoxgloveObserver`
feeds it from a running session (``record --foxglove``) or a passive listener
(``shadow --transport can --foxglove``): it is a link ``TelemetryObserver`` placed after the
shadow observer, whose model prediction it publishes beside the measurement and whose alarms
it forwards. Publishing never waits on a viewer: the server queues per client and drops the
oldest data when a viewer lags.

``foxglove-sdk`` (the ``foxglove`` extra) is imported when a server starts, never before.
"""

from __future__ import annotations

import json
import math
import numbers
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, MecanumHILError
from ..io.mcap_export import (
    CHANNELS,
    LOG_DEBUG,
    LOG_ERROR,
    LOG_INFO,
    LOG_WARNING,
    SCHEMAS,
    LogEntry,
    log_message,
    values_message,
)
from ..io.recording import COMMAND_COLUMNS, WHEEL_COLUMNS
from .eventlog import alarm_line

#: Default bind address: this machine only (a viewer elsewhere needs an explicit HOST:PORT).
DEFAULT_HOST = "127.0.0.1"
#: Foxglove's default WebSocket port.
DEFAULT_PORT = 8765

#: The roles the live view serves (the export's, less those only a whole recording has).
LIVE_ROLES = ("commands", "wheels", "wheels_predicted", "alarms")


def parse_address(text: str | None) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST``, ``:PORT`` or ``PORT`` (empty: the defaults) to ``(host, port)``."""
    text = (text or "").strip()
    if not text:
        return DEFAULT_HOST, DEFAULT_PORT
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = ("", text) if text.isdigit() else (text, "")
    host = host.strip("[]") or DEFAULT_HOST
    try:
        number = int(port) if port else DEFAULT_PORT
    except ValueError:
        raise ConfigError(f"--foxglove needs HOST:PORT, got {text!r}") from None
    if not 0 <= number <= 65535:
        raise ConfigError(f"--foxglove port must be 0..65535, got {number}")
    return host, number


def event_entry(event: dict[str, Any]) -> LogEntry | None:
    """A shadow-mode event as a log message (None for the log's own start and end lines).

    ``alarm`` is a warning (an error when it stops the robot), ``recovered`` information,
    ``noise`` (the warm-up's estimate) debug, a failed STOP an error.
    """
    kind = event.get("event")
    t = event.get("t_s")
    if t is None or kind in ("start", "end"):
        return None
    t = _event_time(t)
    if kind in ("alarm", "recovered", "noise") and not isinstance(event.get("channel"), str):
        raise ValueError(f"an event {kind!r} needs a \"channel\" (text), got "
                         f"{event.get('channel')!r}")
    if kind == "alarm":
        level = LOG_ERROR if event.get("action") == "stop" else LOG_WARNING
        return LogEntry(t, level, _line(event, lambda: alarm_line(event)))
    if kind == "recovered":
        return LogEntry(t, LOG_INFO, _line(event, lambda: alarm_line(event)))
    if kind == "noise":
        return LogEntry(t, LOG_DEBUG, _line(event, lambda: f"noise {event['channel']}: "
                                                        f"{event['noise']:.3g} {event['unit']}"))
    if kind == "stop_failed":
        return LogEntry(float(t), LOG_ERROR, f"STOP failed: {event.get('error', '')}")
    return LogEntry(t, LOG_INFO, json.dumps(event, default=str))


#: Largest event time [s] from the recording's start (|t_s|; 31 years): the MCAP log time,
#: the recording's start plus t_s in nanoseconds, must fit its 64 bits.
MAX_EVENT_T_S = 1e9


def _event_time(t: Any) -> float:
    """An event's ``t_s`` as seconds; ValueError (the reason) for anything else."""
    if isinstance(t, bool) or not isinstance(t, numbers.Real):
        raise ValueError(f"\"t_s\" must be a number of seconds, got {t!r}")
    t = float(t)
    if not (math.isfinite(t) and abs(t) <= MAX_EVENT_T_S):
        raise ValueError(f"\"t_s\" must be a finite number of seconds within "
                         f"+-{MAX_EVENT_T_S:g}, got {t!r}")
    return t


def _line(event: dict[str, Any], text: Callable[[], str]) -> str:
    """The event's line; its JSON when a field is missing or not a number (a NaN written as
    null by the monitor), so one odd field does not lose the event."""
    try:
        return text()
    except (KeyError, TypeError, ValueError):
        return json.dumps(event, default=str)


def read_event_log(path: str | Path) -> list[LogEntry]:
    """The log messages of a shadow-mode event log (``REC.shadow.jsonl``)."""
    p = Path(path)
    entries = []
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as err:
        raise MecanumHILError(f"{p}: cannot read the event log: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raise MecanumHILError(f"{p}: not an event log (JSON lines): not UTF-8 text at byte "
                              f"{err.start}") from err
    for i, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            event = json.loads(line)
        except json.JSONDecodeError as err:
            if i == len(lines) and any(x.strip() for x in lines[:i - 1]):
                break  # a last line cut off mid-write (the process died): everything before
            raise MecanumHILError(f"{p}, line {i}: not JSON: {err}") from err
        if not isinstance(event, dict):
            raise MecanumHILError(f"{p}, line {i}: not an event (a JSON object), got "
                                  f"{type(event).__name__}")
        try:
            entry = event_entry(event)
        except ValueError as err:
            raise MecanumHILError(f"{p}, line {i}: {err}") from err
        if entry is not None:
            entries.append(entry)
    return entries


class FoxgloveLive:
    """A Foxglove WebSocket server with the live channels.

    Parameters
    ----------
    host : str
        Address to bind (default localhost only).
    port : int
        TCP port; 0 picks a free one (see :attr:`port`).
    name : str
        Server name shown in Foxglove.

    Attributes
    ----------
    published : dict
        Messages published per role.
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 name: str = "mecanum-hil") -> None:
        try:
            import foxglove
        except ImportError as err:
            raise ConfigError("the Foxglove live view needs the 'foxglove' extra: pip install "
                              "'mecanum-hil[foxglove]'") from err
        self._ctx = foxglove.Context()
        self._subscribed: dict[str, int] = {}
        self._cond = threading.Condition()
        self.published: dict[str, int] = dict.fromkeys(LIVE_ROLES, 0)
        self._channels = {}
        for role in LIVE_ROLES:
            spec = CHANNELS[role]
            schema = foxglove.Schema(name=spec.schema, encoding="jsonschema",
                                     data=json.dumps(SCHEMAS[spec.schema]).encode("utf-8"))
            self._channels[role] = foxglove.Channel(spec.topic, schema=schema,
                                                    message_encoding="json", context=self._ctx)
        try:
            self._server = foxglove.start_server(name=name, host=host, port=port,
                                                 context=self._ctx,
                                                 server_listener=self._listener())
        except Exception as err:  # the sdk raises its own error for a port in use
            raise ConfigError(f"cannot serve Foxglove on {host}:{port}: {err}") from err
        self.host = host
        self._t0_ns: int | None = None

    def _listener(self):
        outer = self

        class Listener:
            def on_subscribe(self, client, channel) -> None:
                with outer._cond:
                    outer._subscribed[channel.topic] = outer._subscribed.get(channel.topic, 0) + 1
                    outer._cond.notify_all()

            def on_unsubscribe(self, client, channel) -> None:
                with outer._cond:
                    outer._subscribed[channel.topic] = max(
                        0, outer._subscribed.get(channel.topic, 0) - 1)

        return Listener()

    @property
    def port(self) -> int:
        """The TCP port served."""
        return int(self._server.port)

    @property
    def url(self) -> str:
        """``ws://HOST:PORT`` for Foxglove's "Open connection"."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def wait_for_subscribers(self, topics: Iterable[str], timeout_s: float) -> bool:
        """Wait until every topic has a subscriber (a viewer opened them); False on timeout."""
        wanted = list(topics)
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not all(self._subscribed.get(t, 0) for t in wanted):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def _ns(self, t_s: float) -> int:
        # the run's t_s = 0 is "now" at the first message: Foxglove shows live data on the
        # wall clock
        if self._t0_ns is None:
            self._t0_ns = time.time_ns() - round(t_s * 1e9)
        return self._t0_ns + round(t_s * 1e9)

    def _log(self, role: str, msg: dict, ns: int) -> None:
        self._channels[role].log(msg, log_time=ns)
        self.published[role] += 1

    def publish_command(self, t_s: float, commands) -> None:
        """Commands in force from ``t_s`` [s]."""
        ns = self._ns(t_s)
        self._log("commands", values_message(ns, t_s, COMMAND_COLUMNS, commands), ns)

    def publish_sample(self, t_s: float, wheel_rpm, predicted_rpm=None) -> None:
        """Measured wheel speeds at ``t_s`` [s] and, in shadow mode, the model's [rpm]."""
        ns = self._ns(t_s)
        self._log("wheels", values_message(ns, t_s, WHEEL_COLUMNS, wheel_rpm), ns)
        if predicted_rpm is not None:
            self._log("wheels_predicted",
                      values_message(ns, t_s, WHEEL_COLUMNS, predicted_rpm), ns)

    def publish_event(self, event: dict[str, Any]) -> None:
        """A shadow-mode event (a monitor listener): alarms and recoveries as log messages."""
        entry = event_entry(event)
        if entry is not None:
            ns = self._ns(entry.t_s)
            self._log("alarms", log_message(ns, entry.level, entry.text), ns)

    def close(self, wait_s: float = 2.0) -> None:
        """Stop serving, and wait (at most ``wait_s`` [s]) until the port takes no connection:
        the sdk closes its listener in the background, and a caller may serve there again."""
        import socket

        port = self.port
        self._server.stop()
        host = "127.0.0.1" if self.host in ("", "0.0.0.0") else self.host
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as c:
                c.settimeout(0.2)
                if c.connect_ex((host, port)) != 0:
                    return
            time.sleep(0.02)


class FoxgloveObserver:
    """Feeds a :class:`FoxgloveLive` from a session or listener (a ``TelemetryObserver``).

    Parameters
    ----------
    live : FoxgloveLive
    shadow : LiveShadow, optional
        The shadow observer running before this one on the same thread: its prediction is
        published beside the measurement and its events as log messages.
    """

    stop_requested = False

    def __init__(self, live: FoxgloveLive, shadow=None) -> None:
        self.live = live
        self.shadow = shadow
        self._cmd = np.full(3, np.nan)
        if shadow is not None:
            shadow.monitor.listeners.append(live.publish_event)

    def on_command(self, t_s: float, commands) -> None:
        """A command at its send (or hearing) time."""
        self._cmd = np.asarray(commands, dtype=float).copy()
        self.live.publish_command(t_s, self._cmd)

    def on_telemetry(self, t_s: float, commands, wheel_rpm,
                     controller_time_s: float | None = None) -> None:
        """A telemetry sample; the command in force is published when it changed."""
        cmd = np.asarray(commands, dtype=float)
        if not np.array_equal(cmd, self._cmd):
            self.on_command(t_s, cmd)
        predicted = None
        if self.shadow is not None and self.shadow.monitor.samples:
            predicted = self.shadow.monitor.predicted[:4]
        self.live.publish_sample(t_s, wheel_rpm, predicted)

    def status_line(self) -> str:
        """For the progress line: where the view is served."""
        return f"foxglove {self.live.url}"


def start_live_view(address: str | None, shadow=None,
                    echo: Callable[[str], None] | None = None) -> FoxgloveObserver:
    """Serve the live view at ``address`` (``HOST:PORT``; localhost:8765 by default)."""
    host, port = parse_address(address)
    live = FoxgloveLive(host, port)
    if echo is not None:
        echo(f"foxglove: serving {live.url} (Foxglove: Open connection > Foxglove WebSocket)")
    return FoxgloveObserver(live, shadow)
