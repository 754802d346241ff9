"""Shadow mode on a live link: beside ``record`` (an observer) and listening passively.

The stateful edge around :class:`~mecanum_hil.monitor.core.ShadowMonitor`: the JSON-lines
event log next to the recording, alarm lines on the terminal, the status line, and (passive
listening) the link itself through one seam, :class:`HeardSource`, with a CAN bus
(:class:`CanSource`) and a ROS 2 graph (:mod:`.ros2_listen`) behind it.
"""

from __future__ import annotations

import math
import sys
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..model.calibration import Calibration
from ..model.robot import RobotProfile
from .core import ShadowConfig, ShadowMonitor
from .eventlog import EventLog, alarm_line, event_log_path


def _alarm_echo(echo: Callable[[str], None]) -> Callable[[dict[str, Any]], None]:
    def listener(event: dict[str, Any]) -> None:
        if event["event"] in ("alarm", "recovered"):
            echo("shadow: " + alarm_line(event))

    return listener


class ControllerClock:
    """Maps a controller's telemetry clock onto the listener's clock (both [s]).

    The offset is the smallest (arrival - controller time) seen, the sample that waited least
    on its way; it may grow by ``drift`` seconds per second so a controller clock running slow
    is followed, and it restarts when the controller clock does not advance (a new HELLO) or on
    :meth:`reset` (the listener sees a HELLO_ACK).
    Telemetry timed this way carries the controller's sampling instants instead of the
    listener's receive jitter.
    """

    def __init__(self, drift: float = 2e-4) -> None:
        self.drift = drift
        self.offset: float | None = None
        self._last: float | None = None

    def reset(self) -> None:
        """Forget the offset (the controller restarted its clock: HELLO_ACK)."""
        self.offset = None
        self._last = None

    def __call__(self, controller_s: float, arrival_s: float) -> float:
        d = arrival_s - controller_s
        # a clock that does not advance has restarted (a controller answering a backlog of
        # HELLOs restarts at 0 each time): start over rather than keep a stale offset
        if self.offset is None or self._last is None or controller_s <= self._last:
            self.offset = d
        else:
            self.offset = min(d, self.offset + self.drift * (controller_s - self._last))
        self._last = controller_s
        return controller_s + self.offset


class LiveShadow:
    """A shadow monitor with its event log and terminal output; a link ``TelemetryObserver``.

    Parameters
    ----------
    calibration : Calibration
    robot : RobotProfile
    config : ShadowConfig
    event_log : str or Path, optional
        JSON-lines log to write (``None``: none).
    stop_on_divergence : bool
        Request a stop at the first alarm.
    echo : callable, optional
        Prints one alarm / recovery line (``None``: silent).
    header : dict, optional
        More fields for the log's ``start`` line.
    """

    def __init__(self, calibration: Calibration, robot: RobotProfile, config: ShadowConfig,
                 event_log: str | Path | None = None, *, stop_on_divergence: bool = False,
                 echo: Callable[[str], None] | None = None,
                 header: dict[str, Any] | None = None) -> None:
        self.log = (EventLog(event_log, calibration, config, header)
                    if event_log is not None else None)
        listeners = [] if self.log is None else [self.log]
        if echo is not None:
            listeners.append(_alarm_echo(echo))
        self.monitor = ShadowMonitor(calibration, robot, config,
                                     stop_on_divergence=stop_on_divergence, listeners=listeners)
        self._clock = ControllerClock()

    @property
    def stop_requested(self) -> bool:
        """True once an alarm asked for a stop (``--on-divergence stop``)."""
        return self.monitor.stop_requested

    def on_telemetry(self, t_s: float, commands: np.ndarray, wheel_rpm: np.ndarray,
                     controller_time_s: float | None = None) -> None:
        """One telemetry sample (see :meth:`ShadowMonitor.on_telemetry`).

        With ``controller_time_s`` (a session that passes it), the sample is timed by the
        controller's clock mapped onto the host's (:class:`ControllerClock`) instead of by its
        receive time, which a stalled host delays.
        """
        if controller_time_s is not None:
            t_s = min(t_s, self._clock(controller_time_s, t_s))
        self.monitor.on_telemetry(t_s, commands, wheel_rpm)

    def on_command(self, t_s: float, commands: np.ndarray) -> None:
        """A command as actually sent at ``t_s`` (a session that reports its sends).

        Actual send times replace the profile's schedule from then on.
        """
        self.monitor.clear_command_schedule()
        self.monitor.on_command(t_s, commands)

    def status_line(self) -> str:
        """The monitor's one-line status."""
        return self.monitor.status_line()

    def close(self, **summary: Any) -> str:
        """Close the event log (writing ``summary`` into its ``end`` line); a summary text."""
        alarms = self.monitor.alarms
        if self.log is not None:
            self.log.close({"samples": self.monitor.samples, "alarms": len(alarms),
                            "first_alarm_t_s": alarms[0].t_s if alarms else None, **summary})
        text = f"shadow: {self.monitor.samples} samples, {len(alarms)} alarm(s)"
        if alarms:
            a = alarms[0]
            text += (f", first {a.channel} at {a.t_s:.3f} s (residual {a.residual:+.3g} "
                     f"{a.unit})")
        if self.log is not None:
            text += f"; events in {self.log.path}"
        return text


def record_shadow(calibration: str | Path, robot: RobotProfile, t_s, commands,
                  out: str | Path, on_divergence: str = "none",
                  config: ShadowConfig | None = None,
                  echo: Callable[[str], None] | None = None) -> LiveShadow:
    """The observer ``record --shadow CAL`` adds to its session.

    The monitor knows the profile's send schedule, so a command acts from its own send time
    rather than from the next telemetry sample, as in a replay of the recording; the STOP that
    ends a completed profile is part of the schedule. The event log is ``OUT.shadow.jsonl``.
    """
    from ..errors import ConfigError
    from ..model import load_calibration

    if on_divergence not in ("none", "stop"):
        raise ConfigError(f"--on-divergence must be 'none' or 'stop', got '{on_divergence}'")
    cal = load_calibration(calibration)
    cfg = config or ShadowConfig()
    t = np.asarray(t_s, dtype=float).reshape(-1)
    cmd = np.asarray(commands, dtype=float).reshape(-1, 3)
    t = t - t[0]
    # the session sends STOP right after the last command: (0, 0, theta in force)
    sched_t = np.append(t, t[-1])
    sched_cmd = np.vstack([cmd, [0.0, 0.0, cmd[-1, 2]]])
    live = LiveShadow(cal, robot, cfg, event_log_path(out),
                      stop_on_divergence=on_divergence == "stop", echo=echo,
                      header={"mode": "record", "recording": str(out),
                              "on_divergence": on_divergence})
    live.monitor.set_command_schedule(sched_t, sched_cmd)
    return live


class HeardSource(ABC):
    """A link heard passively: the commands someone else sends and the wheel speeds the robot
    reports, each as a protocol message (:class:`~mecanum_hil.link.protocol.Command`,
    ``Stop``, ``HelloAck``, ``Telemetry``) stamped on the source's clock.

    The one seam of a passive ``shadow``: a CAN bus and a ROS 2 graph are heard through it.
    """

    #: Where it listens, for messages (``virtual:x``, ``ROS 2 domain 0``).
    name: str = ""
    #: What to check when nothing was heard.
    hint: str = "is the robot there?"

    @abstractmethod
    def receive(self, timeout_s: float) -> list[tuple[Any, float]]:
        """The messages heard within ``timeout_s`` [s], each with its stamp [s, epoch];
        raise :class:`~mecanum_hil.errors.LinkLostError` when the link is gone."""

    def send_stop(self) -> None:
        """Command the robot to stop (only sources that may send; see ``can_stop``)."""
        raise NotImplementedError(f"{self.name}: this listener sends nothing")

    #: Whether :meth:`send_stop` works (``--on-divergence stop``).
    can_stop: bool = False

    def on_status(self, live: LiveShadow, now_s: float) -> None:
        """Called at least every 0.1 s while listening (a health report to publish)."""
        return None

    def counts(self) -> dict[str, int]:
        """Counters of the source itself (bad frames ...), for the summary."""
        return {}

    def close(self) -> None:
        """Release the bus or the participant."""
        return None


class CanSource(HeardSource):
    """A CAN bus heard through the protocol's CAN mapping (``link/can_link.py``)."""

    can_stop = True
    hint = "is the controller on this bus, at this bitrate?"

    def __init__(self, interface: str, channel: str | None, bitrate: int | None,
                 bus=None) -> None:
        from ..link.can_link import CanCodec, CanTransport

        self.link = CanTransport(interface, channel, bitrate, bus=bus)
        self.name = self.link.port
        self.codec = CanCodec()
        self.bad_frames = 0

    def receive(self, timeout_s: float) -> list[tuple[Any, float]]:
        import can

        from ..errors import LinkLostError
        from ..link.protocol import FrameError

        try:
            frame = self.link.bus.recv(timeout=timeout_s)
        except (can.CanError, OSError, ValueError) as err:
            raise LinkLostError(f"CAN {self.link.port}: link lost: {err}") from err
        if frame is None or frame.is_error_frame or frame.is_remote_frame:
            return []
        try:
            msg = self.codec.decode(frame.arbitration_id, bytes(frame.data))
        except FrameError:
            self.bad_frames += 1
            return []
        return [] if msg is None else [(msg, frame.timestamp or time.time())]

    def send_stop(self) -> None:
        from ..link.protocol import Stop

        self.link.send(Stop())

    def counts(self) -> dict[str, int]:
        return {"bad_frames": self.bad_frames}

    def close(self) -> None:
        self.link.close()


def _send_stop(source: HeardSource, live: LiveShadow, t_s: float, cmd: np.ndarray,
               heard: dict) -> None:
    """Send STOP (best effort) and tell the model: a bus does not echo one's own frames."""
    from ..errors import LinkError

    try:
        source.send_stop()
    except LinkError as err:
        if live.log is not None:
            live.log.write({"event": "stop_failed", "t_s": t_s, "error": str(err)})
        return
    heard["stops_sent"] += 1
    cmd[:] = (0.0, 0.0, cmd[2])
    live.monitor.on_command(t_s, cmd)


def listen_can(interface: str, channel: str | None, bitrate: int | None,
               calibration: str | Path, robot: str | Path, config: ShadowConfig, *,
               out: str | Path | None = None, events: str | Path | None = None,
               duration_s: float | None = None, stop_on_divergence: bool = False,
               echo: Callable[[str], None] = print, bus=None,
               status_every_s: float = 0.5, foxglove: str | None = None) -> int:
    """Listen passively to a CAN bus where another host commands the controller.

    Commands (``MH_COMMAND``, ``MH_STOP``) act from their frames' bus timestamps; telemetry
    (``MC_STATUS`` + ``MC_WHEELS``) is timed by the controller's clock mapped onto the bus
    clock (:class:`ControllerClock`), then compared with the model. Nothing is sent, except
    with ``stop_on_divergence``: then STOP goes out at the first alarm and again after every
    command heard from then on, until listening ends. See :func:`listen` for the rest of
    the parameters.

    Parameters
    ----------
    interface, channel, bitrate
        The python-can bus (or ``bus``, an open one, for tests).

    Returns
    -------
    int
        Number of alarms.
    """
    import can  # noqa: F401  (python-can missing fails here, before the bus is opened)

    from ..errors import ConfigError

    if bus is None and not channel:
        raise ConfigError("passive CAN listening needs --channel (and --interface)")
    return len(listen(lambda: CanSource(interface, channel, bitrate, bus=bus), calibration,
                      robot, config, out=out, events=events, duration_s=duration_s,
                      stop_on_divergence=stop_on_divergence, echo=echo,
                      status_every_s=status_every_s, foxglove=foxglove,
                      name=f"{interface}:{channel}"))


def listen(open_source: Callable[[], HeardSource], calibration: str | Path,
           robot: str | Path, config: ShadowConfig, *, out: str | Path | None = None,
           events: str | Path | None = None, duration_s: float | None = None,
           stop_on_divergence: bool = False, echo: Callable[[str], None] = print,
           status_every_s: float = 0.5, foxglove: str | None = None, name: str = "",
           mode: str = "listen-can") -> tuple:
    """Listen passively to a source where someone else commands the robot.

    Commands act from their stamps; telemetry is timed by the robot's clock mapped onto the
    source's (:class:`ControllerClock`), then compared with the model.

    Parameters
    ----------
    open_source : callable
        Opens the :class:`HeardSource` (after the monitor and its log exist).
    calibration, robot
        Names or files.
    config : ShadowConfig
    out : str or Path, optional
        Also record what was heard (the ``record`` format); the event log goes next to it.
    events : str or Path, optional
        Event log path (default: next to ``out``; none without ``out``).
    duration_s : float, optional
        Stop listening after this long [s]; default until Ctrl-C.
    stop_on_divergence : bool
        Send STOP at the first alarm (sources that may send).
    echo : callable
        Terminal output (alarm lines, the status line, the summary).
    status_every_s : float
        Period of the status line [s].
    foxglove : str, optional
        Also serve the live view for Foxglove at ``HOST:PORT`` ("": localhost:8765).
    name, mode : str
        The source's name and the event log's mode, for its header.

    Returns
    -------
    tuple of Alarm
        The alarms raised.
    """
    from ..errors import ConfigError
    from ..model import load_calibration

    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise ConfigError(f"--duration must be a finite number of seconds > 0, got {duration_s}")
    cal = load_calibration(calibration)
    live = _listening_shadow(cal, robot, config, out, events, stop_on_divergence, echo,
                             name, mode)
    source = None
    writer = None
    view = None
    heard = {"commands": 0, "stops": 0, "telemetry": 0, "stops_sent": 0, "bad_frames": 0}
    try:
        if foxglove is not None:
            from .foxglove import start_live_view

            view = start_live_view(foxglove, live, echo=echo)
        source = open_source()
        if stop_on_divergence and not source.can_stop:
            raise ConfigError(f"{source.name}: this listener never commands the robot; "
                              "--on-divergence stop is not available here")
        if out is not None:
            writer = _open_heard_recording(out, source.name, cal)
        echo(f"shadow: listening on {source.name} (sending nothing"
             + (", STOP on divergence)" if stop_on_divergence else ")"))
        _listen(source, _Listening(live, source, view, writer, heard), duration_s,
                status_every_s)
    except KeyboardInterrupt:
        pass  # Ctrl-C is how an open-ended listen ends
    finally:
        summary = _end_listening(live, source, writer, view, heard)
    _report_heard(heard, summary, name, source, echo)
    return tuple(live.monitor.alarms)


def _end_listening(live: LiveShadow, source: HeardSource | None, writer, view,
                   heard: dict) -> str:
    """Close what a listen opened (the status line, the recording with the ``heard`` counts,
    the source, the live view, the shadow) and return the shadow's summary."""
    if sys.stderr.isatty():
        print("", file=sys.stderr)  # end the status line
    if source is not None:
        heard.update(source.counts())
    if writer is not None:
        writer.close({"heard": heard})
    if source is not None:
        source.close()
    if view is not None:
        view.live.close()
    return live.close(**heard)


def _report_heard(heard: dict, summary: str, name: str, source: HeardSource | None,
                  echo: Callable[[str], None]) -> None:
    """Say what a listen heard and its ``summary``.

    Raises
    ------
    MecanumHILError
        No telemetry was heard: nothing was compared with the model.
    """
    from ..errors import MecanumHILError

    echo(f"heard {heard['commands']} commands, {heard['stops']} stops, {heard['telemetry']} "
         f"telemetry samples" + (f"; sent {heard['stops_sent']} STOP" if heard["stops_sent"]
                                 else ""))
    echo(summary)
    if not heard["telemetry"]:
        # no alarm because nothing was compared: not a robot that matched its model
        raise MecanumHILError(
            f"heard no telemetry on {name or source.name}: nothing was compared with the "
            f"model ({source.hint if source is not None else 'is the robot there?'})")


def _listening_shadow(cal: Calibration, robot: str | Path, config: ShadowConfig,
                      out: str | Path | None, events: str | Path | None,
                      stop_on_divergence: bool, echo: Callable[[str], None],
                      bus_name: str, mode: str = "listen-can") -> LiveShadow:
    """The shadow monitor of a passive listen, its event log next to ``out`` by default."""
    from ..model import load_robot_profile

    rob = load_robot_profile(robot)
    log_path = events if events is not None else (event_log_path(out) if out else None)
    return LiveShadow(cal, rob, config, log_path, stop_on_divergence=stop_on_divergence,
                      echo=echo, header={"mode": mode, "bus": bus_name,
                                         "recording": str(out) if out else None})


def _listen(source: HeardSource, listening: _Listening, duration_s: float | None,
            status_every_s: float) -> None:
    """Receive until ``duration_s`` has passed (or forever), refreshing the status line."""
    live = listening.live
    tty = sys.stderr.isatty()
    start = time.perf_counter()
    end = math.inf if duration_s is None else start + duration_s
    next_status = start + status_every_s
    while (now := time.perf_counter()) < end:
        items = source.receive(min(0.1, end - now))
        now = time.perf_counter()
        if now >= next_status:
            next_status = now + status_every_s
            if tty:
                print("\r" + live.status_line()[:150], end="", file=sys.stderr, flush=True)
        for msg, stamp in items:
            listening.on_message(msg, stamp)
        source.on_status(live, now)


def _open_heard_recording(out: str | Path, port: str, cal: Calibration):
    """The recording of what is heard, in the ``record`` format."""
    from ..io.recording import RecordingWriter
    from ..link.session import EXTRA_COLUMNS

    return RecordingWriter(out, EXTRA_COLUMNS, {
        "source": "mecanum-hil shadow (listen)", "bus": port,
        "calibration": cal.source,
        "columns": {"t_s": "bus time since the first frame heard (telemetry: controller "
                           "time mapped onto it)"}})


class _Listening:
    """What a passive listen has heard so far: the bus time origin, the command in force.

    Each message heard goes to the model, the live view and the recording in bus time
    since the first frame; with ``stop_on_divergence``, STOP goes out from the first alarm
    and after every command heard from then on.
    """

    def __init__(self, live: LiveShadow, source: HeardSource, view, writer,
                 heard: dict) -> None:
        self.live, self.source, self.view, self.writer = live, source, view, writer
        self.heard = heard
        self.clock = ControllerClock()
        self.t0: float | None = None
        self.last_t = -math.inf
        self.cmd: np.ndarray | None = None

    def on_message(self, msg, stamp: float) -> None:
        """Take one decoded message stamped at ``stamp`` on the bus clock [s]."""
        from ..link.protocol import Command, HelloAck, Stop, Telemetry

        if self.t0 is None:
            self.t0 = stamp
        if isinstance(msg, Command | Stop):
            self._on_command(msg, stamp, isinstance(msg, Command))
        elif isinstance(msg, HelloAck):
            self.clock.reset()  # the controller's clock restarts at the HELLO it answers
        elif isinstance(msg, Telemetry):
            self._on_telemetry(msg, stamp)

    def _on_command(self, msg, stamp: float, is_command: bool) -> None:
        live, heard = self.live, self.heard
        t = max(stamp - self.t0, self.last_t)
        if is_command:
            heard["commands"] += 1
            self.cmd = np.array([msg.n_rpm, msg.omega_dps, msg.theta_deg])
        else:
            heard["stops"] += 1
            self.cmd = np.array([0.0, 0.0, 90.0 if self.cmd is None else self.cmd[2]])
        live.monitor.on_command(t, self.cmd)
        if self.view is not None:
            self.view.on_command(t, self.cmd)
        if self.writer is not None and t > self.last_t:
            self.writer.write(t, self.cmd, extra=("cmd" if is_command else "stop",
                                                  msg.seq, "", ""))
        self.last_t = t
        if live.stop_requested and is_command:
            # python-can stamps frames on the epoch clock: our STOP goes out now
            _send_stop(self.source, live, max(time.time() - self.t0, t), self.cmd, heard)

    def _on_telemetry(self, msg, stamp: float) -> None:
        live, cmd = self.live, self.cmd
        self.heard["telemetry"] += 1
        t = max(self.clock(msg.time_us * 1e-6, stamp - self.t0), self.last_t)
        wheels = np.array(msg.wheel_rpm, dtype=float)
        if self.writer is not None and t > self.last_t:
            self.writer.write(t, cmd if cmd is not None else (math.nan,) * 3, wheels,
                              extra=("tlm", msg.seq, f"{msg.time_us * 1e-6:.6f}", msg.status))
        self.last_t = t
        if cmd is None:
            return  # the command in force is unknown until one is heard
        was = live.stop_requested
        live.on_telemetry(t, cmd, wheels)
        if self.view is not None:
            self.view.on_telemetry(t, cmd, wheels)
        if live.stop_requested and not was:
            _send_stop(self.source, live, max(time.time() - self.t0, t), cmd, self.heard)
