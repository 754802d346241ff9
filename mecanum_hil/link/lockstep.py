"""Recording from the simulated controller in simulated time: the same robot, no waiting.

``record`` against ``sim-robot`` runs in real time: a campaign of a dozen profiles takes as long
as on the robot. For work that needs many campaigns (diagnose's proof, studies of an
identification method), :func:`record_lockstep` runs the *same* simulated controller on a
virtual clock instead of the wall clock:

- the firmware is :class:`~mecanum_hil.link.simulated.SimulatedController` (HELLO, commands
  applied from the first tick after they arrive, the dead time through the controller's command
  schedule, the 250 ms watchdog, STOP) and the robot is its
  :class:`~mecanum_hil.link.simulated.ControllerModel` with an effects file's hidden effects,
  noise and faults;
- every message in both directions is encoded into serial frames (COBS + CRC) and decoded back
  with the protocol's :class:`~mecanum_hil.link.protocol.StreamDecoder`, so values are exactly
  what the wire carries;
- the rows are those ``record`` writes (same columns, events, sequence numbers, controller time
  and sidecar keys), with the host's receive time of telemetry one link delay after the
  controller sent it.

What it leaves out is what real time adds: the host's scheduling jitter and bursts (which
``fit``/``diagnose`` remove by timing telemetry on the controller's clock) and lost frames.
The pose columns hold the simulated pose as a camera would measure it (the wire protocol
carries none), with optional Gaussian noise; leave ``pose_noise`` at ``None`` for none.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError
from ..io.recording import Recording
from ..model.calibration import Calibration
from ..model.robot import RobotProfile
from .effects_file import SimEffects
from .protocol import PROTOCOL_VERSION, Hello, HelloAck, Message, Stop, StreamDecoder, encode
from .session import COLUMN_NOTES, EXTRA_COLUMNS, check_command_stream, next_row_time
from .simulated import ControllerModel, SimulatedController
from .transport import Transport


class FramedLoopback(Transport):
    """A link in memory: every message sent is framed for the serial wire and decoded back.

    Messages sent on it are what the other end receives, in :attr:`delivered`.
    """

    name = "lockstep"

    def __init__(self) -> None:
        super().__init__()
        self._decoder = StreamDecoder()
        self.delivered: deque[Message] = deque()

    def _send(self, msg: Message) -> None:
        self.delivered.extend(self._decoder.feed(encode(msg)))

    def _recv(self, timeout_s: float) -> Message | None:
        return None

    def _close(self) -> None:
        pass


class MemoryLink(Transport):
    """The controller's end of a serial link in memory, for driving the firmware in simulated
    time: :meth:`feed` gives it the host's bytes (anything: frames, damage, garbage), decoded
    by the protocol's stream decoder; what the controller sends is framed, decoded back and
    kept in :attr:`out`."""

    name = "memory"

    def __init__(self) -> None:
        super().__init__()
        self._decoder = StreamDecoder()
        self._inbox: deque[tuple[Message, int]] = deque()
        self._host = StreamDecoder()
        self.out: list[Message] = []

    def feed(self, data: bytes) -> None:
        """Bytes from the host, as they would arrive on the wire."""
        self._inbox.extend(self._decoder.feed_counted(data))
        c = self._decoder.counts
        self.stats.crc_errors, self.stats.malformed = c.crc, c.malformed
        self.stats.unknown_types, self.stats.version_errors = c.unknown_type, c.version
        self.stats.garbage_bytes = c.garbage_bytes
        while self._decoder.rejected:
            self.rejected.append(self._decoder.rejected.popleft())

    def _send(self, msg: Message) -> None:
        self.out.extend(self._host.feed(encode(msg)))

    def _recv(self, timeout_s: float) -> Message | None:
        if not self._inbox:
            return None
        msg, drops = self._inbox.popleft()
        self._dropped(drops)
        return msg

    def _close(self) -> None:
        pass


class VirtualClock:
    """A clock that moves only when told [s]."""

    def __init__(self, start_s: float = 0.0) -> None:
        self.now_s = float(start_s)

    def __call__(self) -> float:
        return self.now_s


def record_lockstep(
    t_s: np.ndarray,
    commands: np.ndarray,
    robot: RobotProfile,
    *,
    calibration: Calibration | None = None,
    sim_effects: SimEffects | None = None,
    telemetry_rate_hz: float = 100.0,
    internal_rate_hz: float = 1000.0,
    link_delay_s: float = 0.00015,
    pose_noise: Sequence[float] | None = None,
    pose_seed: int = 0,
    tail_s: float = 0.2,
    metadata: dict[str, Any] | None = None,
) -> Recording:
    """Send ``commands`` at ``t_s`` to the simulated controller in simulated time and record.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Send times from the first command [s], increasing (as ``record`` takes them).
    commands : array_like, shape (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])``; checked against ``robot``'s limits.
    robot : RobotProfile
        Geometry and limits.
    calibration : Calibration, optional
        The simulated truth's coefficients and effects (default: the paper's, none).
    sim_effects : SimEffects, optional
        An effects file's content (:func:`~mecanum_hil.link.effects_file.load_sim_effects`).
    telemetry_rate_hz, internal_rate_hz : float
        Telemetry rate and the controller's tick rate [Hz].
    link_delay_s : float
        Transit time of a message in either direction [s]. The default is a pseudo-terminal's
        (``record`` measures a PING round trip of 0.3 ms to ``sim-robot``); a 30-byte frame on
        a UART at 115 200 baud takes 2.6 ms. The host sees the round trip as extra dead time.
    pose_noise : (float, float, float), optional
        Standard deviation of the camera's X, Y [m] and heading [deg]; ``None`` records no
        pose.
    pose_seed : int
        Seed of the pose noise.
    tail_s : float
        Telemetry kept after STOP [s] (``record``'s default tail).
    metadata : dict, optional
        Added to the recording's metadata.

    Returns
    -------
    Recording
        Rows as ``record`` writes them: ``cmd`` rows at the send times, ``tlm`` rows at the
        receive times with the controller's time, a ``stop`` row after the last command.

    Raises
    ------
    ConfigError
        As ``record``: times and commands of different lengths, times not increasing, a gap
        the watchdog would stop the wheels in; or a rate or delay out of range.
    LimitError
        A command beyond ``robot``'s limits (before anything is simulated).
    """
    _check_rates(telemetry_rate_hz, internal_rate_hz, link_delay_s)
    to_ctrl = FramedLoopback()
    t, cmd = check_command_stream(t_s, commands, robot, to_ctrl)
    cal = calibration or Calibration()
    fx = sim_effects or SimEffects()
    model = ControllerModel(cal, robot, fx, rate_hz=internal_rate_hz)
    clock = VirtualClock()
    to_host = FramedLoopback()
    ctrl = SimulatedController(to_host, model, telemetry_rate_hz, clock=clock)
    d = float(link_delay_s)
    hello_ack = _handshake(to_ctrl, ctrl, to_host)
    pose_sd = None if pose_noise is None else np.asarray(pose_noise, dtype=float)
    rows = _exchange(t, cmd, to_ctrl, ctrl, to_host, model, clock, d, tail_s, pose_sd,
                     np.random.default_rng(pose_seed))
    times, cmds, wheels, poses, extra = _rows_as_written(rows)
    meta = {**_sidecar(robot, hello_ack, ctrl, fx, d, pose_sd), **(metadata or {})}
    return Recording(times, cmds, wheels, poses, extra, meta)


def _sidecar(robot: RobotProfile, hello_ack: HelloAck, ctrl: SimulatedController,
             fx: SimEffects, d: float, pose_sd: np.ndarray | None) -> dict[str, Any]:
    """The metadata ``record`` writes to the sidecar, for a lockstep run that completed."""
    return {
        "source": "mecanum-hil record_lockstep",
        "tool_version": __version__,
        "transport": "lockstep",
        "protocol_version": PROTOCOL_VERSION,
        "robot_profile": robot.source,
        "controller": hello_ack.name,
        "telemetry_rate_hz": ctrl.telemetry_rate_hz,
        "sample_rate_hz": ctrl.telemetry_rate_hz,
        "link_delay_s": d,
        "columns": dict(COLUMN_NOTES),
        "simulated_controller": {"effects": fx.source,
                                 "pose_noise": None if pose_sd is None else pose_sd.tolist()},
        "end_reason": "completed",
        "exit_code": 0,
        "stops_received": ctrl.stops_received,
    }


def _check_rates(telemetry_rate_hz: float, internal_rate_hz: float,
                 link_delay_s: float) -> None:
    if not (math.isfinite(internal_rate_hz) and internal_rate_hz > 0
            and math.isfinite(telemetry_rate_hz) and telemetry_rate_hz >= 0
            and math.isfinite(link_delay_s) and link_delay_s >= 0):
        raise ConfigError(f"rates must be positive and the link delay >= 0, got "
                          f"{internal_rate_hz!r} Hz, {telemetry_rate_hz!r} Hz, "
                          f"{link_delay_s!r} s")


def _handshake(to_ctrl: FramedLoopback, ctrl: SimulatedController,
               to_host: FramedLoopback) -> HelloAck:
    """HELLO and its answer; HELLO is seq 0, so the first command is seq 1."""
    to_ctrl.send(Hello(PROTOCOL_VERSION))
    ctrl.handle(to_ctrl.delivered.popleft())
    return to_host.delivered.popleft()


def _exchange(t: np.ndarray, cmd: np.ndarray, to_ctrl: FramedLoopback,
              ctrl: SimulatedController, to_host: FramedLoopback, model: ControllerModel,
              clock: VirtualClock, d: float, tail_s: float, pose_sd: np.ndarray | None,
              rng: np.random.Generator) -> list[tuple]:
    """Run commands, STOP and telemetry in the order of their controller times.

    Returns the rows ``(host time [s], command in force or None, wheels [rpm], pose, extra
    columns)`` in the order they happened (not yet sorted by host time).
    """
    # as with record, HELLO leaves the host one round trip before the first command (its
    # answer comes back just as the first command leaves); its arrival is controller time 0,
    # so host time h and controller time c are related by c = h + lead - d = h + d
    lead = 2.0 * d
    rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, tuple]] = []
    nan3, nan4 = np.full(3, np.nan), np.full(4, np.nan)
    stop_h = float(t[-1]) + 1e-6
    end_h = stop_h + tail_s
    sends = [(float(h), "cmd", cmd[i]) for i, h in enumerate(t)] + [(stop_h, "stop", None)]
    tick_step = ctrl.telemetry_ticks
    dt = model.dt_s
    in_force = np.array([math.nan, math.nan, math.nan])
    k = 0  # next send
    tick = 0  # next telemetry tick
    while True:
        c_send = sends[k][0] + lead if k < len(sends) else math.inf
        c_tlm = tick * dt if tick_step else math.inf
        if k >= len(sends) and (not tick_step or c_tlm - lead + 2 * d > end_h):
            break
        if c_send <= c_tlm:
            h, kind, value = sends[k]
            k += 1
            msg = to_ctrl.send(Stop() if kind == "stop" else to_ctrl.wire_command(*value))
            if kind == "stop":
                theta = in_force[2] if np.isfinite(in_force[2]) else 90.0
                in_force = np.array([0.0, 0.0, theta])
            else:
                in_force = np.array([msg.n_rpm, msg.omega_dps, msg.theta_deg])
            rows.append((h, in_force.copy(), nan4, nan3, (kind, msg.seq, "", "")))
            clock.now_s = c_send
            ctrl.handle(to_ctrl.delivered.popleft())
            continue
        clock.now_s = c_tlm
        ctrl.check_watchdog()
        ctrl.send_telemetry(tick)
        tlm = to_host.delivered.popleft()
        h = c_tlm - lead + 2 * d
        if k > 0 or h > 0.0:  # the host records telemetry received after its first command
            pose = nan3
            if pose_sd is not None:
                pose = model.pose(tick) + rng.normal(0.0, 1.0, 3) * pose_sd
            rows.append((h, None, np.array(tlm.wheel_rpm, dtype=float), pose,
                         ("tlm", tlm.seq, f"{tlm.time_us * 1e-6:.6f}", tlm.status)))
        tick += tick_step
    return rows


def _rows_as_written(rows: list[tuple]) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                 np.ndarray, dict[str, list[str]]]:
    """Sort the rows by host time and fill them in as ``record`` writes them.

    A telemetry row carries the command in force; equal host times are nudged apart
    (:func:`~mecanum_hil.link.session.next_row_time`).
    """
    rows.sort(key=lambda r: r[0])
    n = len(rows)
    times = np.empty(n)
    cmds, wheels, poses = np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3))
    extra: dict[str, list[str]] = {name: [] for name in EXTRA_COLUMNS}
    last_t = -math.inf
    force = np.full(3, np.nan)
    for i, (h, c, w, p, ex) in enumerate(rows):
        last_t = times[i] = next_row_time(h, last_t)  # as record writes them
        if c is not None:
            force = c
        cmds[i], wheels[i], poses[i] = force, w, p
        for name, v in zip(EXTRA_COLUMNS, ex, strict=True):
            extra[name].append(str(v))
    return times, cmds, wheels, poses, extra
