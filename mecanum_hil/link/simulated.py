"""The simulated controller: the project's model behind the wire protocol.

:class:`ControllerModel` is the robot: it runs :func:`mecanum_hil.model.simulate` on a fixed
internal tick (default 1 kHz), continuing each piece exactly from the previous piece's
``final_state``. Commands take effect at the first tick after they arrive, delayed by the
effects' dead time through the model's own schedule of pending commands (the simulator's
``dead_time`` is exact within one call, but a controller stepping in real time must delay
its inputs itself, so the calibration is simulated with ``dead_time_s = 0``).

To keep up with 1 kHz telemetry the model simulates ahead: one call covers the next
``lookahead`` ticks under the commands known so far, and telemetry reads from it until a
command changes the future (then one more call, from the last anchor, recomputes it).

:class:`SimulatedController` is the controller's firmware: a loop that answers HELLO and
PING, takes COMMAND/STOP/HEARTBEAT, runs the 250 ms watchdog, and sends telemetry at its rate
through any :class:`~mecanum_hil.link.transport.Transport`.
"""

from __future__ import annotations

import math
import threading
import time
from bisect import bisect_right
from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np

from ..errors import ConfigError, LinkError, LinkLostError
from ..model.calibration import Calibration
from ..model.robot import RobotProfile
from ..model.simulate import DEFAULT_POSE, simulate
from .effects_file import Fault, SimEffects
from .protocol import (
    PROTOCOL_VERSION,
    WATCHDOG_S,
    Command,
    ErrorCode,
    ErrorMsg,
    EstopReset,
    Heartbeat,
    Hello,
    HelloAck,
    MsgType,
    Ping,
    Pong,
    Status,
    Stop,
    Telemetry,
    command_problem,
)
from .transport import Transport

_ZERO = (0.0, 0.0, 0.0)


class UnmodelledSensor:
    """Effects outside the model's library, between the true and the reported wheel speeds.

    ``resonance`` (``natural_hz``, ``damping``): the reported speed is the true one through
    ``wn^2 / (s^2 + 2 zeta wn s + wn^2)``, a lightly damped mode between drive and encoder
    (a flexible coupling); ``roller_ripple`` (``amplitude``, ``per_turn``): it is multiplied by
    ``1 + amplitude sin(per_turn * wheel angle)``, the Mecanum rollers taking over one after
    the other. Both advance on every controller tick (exact for the true speed held over the
    tick), so what is reported does not depend on the telemetry rate.

    Parameters
    ----------
    params : Mapping[str, Mapping[str, float]]
        :attr:`SimEffects.unmodelled`.
    dt_s : float
        Duration of one tick [s].
    rng : numpy.random.Generator
        Draws the rollers' initial phases.
    """

    def __init__(self, params: Mapping[str, Mapping[str, float]], dt_s: float,
                 rng: np.random.Generator) -> None:
        self.resonance = params.get("resonance")
        self.ripple = params.get("roller_ripple")
        self.dt_s = float(dt_s)
        self._angle = rng.uniform(0.0, 2.0 * np.pi, 4) if self.ripple else np.zeros(4)
        self._ad = self._bd = None
        if self.resonance:
            from scipy.linalg import expm

            wn = 2.0 * np.pi * self.resonance["natural_hz"]
            m = np.zeros((3, 3))
            m[:2, :2] = [[0.0, 1.0], [-wn * wn, -2.0 * self.resonance["damping"] * wn]]
            m[:2, 2] = [0.0, wn * wn]
            e = expm(m * self.dt_s)
            self._ad, self._bd = e[:2, :2], e[:2, 2]
        self.reset()

    @property
    def active(self) -> bool:
        """Whether any effect is switched on."""
        return bool(self.resonance or self.ripple)

    def reset(self) -> None:
        """Forget the tick count (the clock restarts at HELLO); the next call starts afresh."""
        self._tick: int | None = None
        self._x = np.zeros((2, 4))
        self._out = np.zeros(4)

    def __call__(self, tick: int, true_rpm: Callable[[int], np.ndarray]) -> np.ndarray:
        """The reported wheel speeds at ``tick`` [rpm].

        ``true_rpm(k)`` gives the true wheel speeds at tick ``k`` [rpm]; it is called for every
        tick since the previous call, in order. A call for an earlier tick than the previous
        one starts afresh (in the steady state of that tick's speed).
        """
        if self._tick is not None and tick == self._tick:
            return self._out.copy()
        if self._tick is None or tick < self._tick:
            w = np.asarray(true_rpm(tick), dtype=float)
            self._x = np.array([w, np.zeros(4)])
        else:
            u = np.asarray(true_rpm(self._tick), dtype=float)
            for k in range(self._tick + 1, tick + 1):
                if self.resonance:
                    self._x = self._ad @ self._x + np.outer(self._bd, u)
                self._angle += 2.0 * np.pi * u / 60.0 * self.dt_s
                u = np.asarray(true_rpm(k), dtype=float)
            w = u
            if not self.resonance:
                self._x[0] = w
        self._tick = tick
        out = self._x[0].copy() if self.resonance else w.copy()
        if self.ripple:
            out *= 1.0 + self.ripple["amplitude"] * np.sin(self.ripple["per_turn"] * self._angle)
        self._out = out
        return out.copy()


#: Time of the truth kept behind the model's anchor [s]: what telemetry still owed and the
#: unmodelled sensor may ask for after a fault moved the anchor on (a pass that late is far past
#: the watchdog's 250 ms).
PAST_S = 1.0


class ControllerModel:
    """The simulated robot on a fixed tick: commands in at ticks, wheel speeds out at ticks.

    Parameters
    ----------
    calibration : Calibration
        Coefficients and effects of the simulated truth.
    robot : RobotProfile
        Geometry.
    sim_effects : SimEffects, optional
        Effects switched on at start, noise, and the fault schedule.
    rate_hz : float
        Internal tick rate [Hz].
    lookahead : int
        Ticks simulated ahead per call.
    """

    def __init__(self, calibration: Calibration, robot: RobotProfile,
                 sim_effects: SimEffects | None = None, rate_hz: float = 1000.0,
                 lookahead: int = 100) -> None:
        self.sim_effects = sim_effects or SimEffects()
        self.base = calibration
        self.robot = robot
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.lookahead = int(lookahead)
        self.calls = 0
        self._rng = np.random.default_rng(self.sim_effects.seed)
        self.sensor = UnmodelledSensor(self.sim_effects.unmodelled, self.dt_s, self._rng)
        self._state = np.zeros((1, 12))
        self._pose = np.array(DEFAULT_POSE, dtype=float)
        self._anchor_cmd = _ZERO
        self.restart()
        # a robot serves for as long as it runs: compile its simulator now, before the first
        # HELLO, not when the interpreter's budget runs out in the middle of a session (a
        # multi-second pause the host sees as a silent controller)
        self._warm_up()

    def _warm_up(self) -> None:
        from .._jit import compiled, mode
        from ..model._kernels import simulate_kernel

        if mode() == "never":  # told to interpret everything: nothing to compile
            return
        compiled(simulate_kernel)
        simulate(np.zeros((2, 3)), np.array([0.0, self.dt_s]), self._calibration(), self.robot)

    # -- timeline ----------------------------------------------------------------------------
    def restart(self) -> None:
        """Restart the clock at tick 0 (at HELLO); the robot keeps moving as it was."""
        self.anchor = 0
        # the truth at ticks behind the anchor, from its first tick: a fault moves the anchor
        # on when a message is read, and telemetry still owed, or the sensor's walk, may ask
        # for the ticks before it
        self._past_start = 0
        self._past = np.zeros((0, 4))
        self._past_poses = np.zeros((0, 3))
        self._sched_ticks: list[int] = []
        self._sched_cmds: list[tuple[float, float, float]] = []
        self.effects = self.sim_effects.initial_effects(self.base.effects)
        self._faults = list(self.sim_effects.faults)
        # a latched e-stop survives HELLO: only the controller's ESTOP_RESET clears it
        self.estop = getattr(self, "estop", False)
        if self._state.shape[-1] > 20:
            # a controller_period's loop restarts with the clock: its next tick is due now
            self._state[:, 20] = 0.0
        self._invalidate()
        self.sensor.reset()

    @property
    def dead_time_ticks(self) -> int:
        """The current dead time in whole ticks."""
        return round(self.effects.dead_time_s * self.rate_hz)

    def _invalidate(self, from_tick: int | None = None) -> None:
        if from_tick is None:
            self._cache_end = self.anchor - 1
            self._wheels = np.zeros((0, 4))
            self._poses = np.zeros((0, 3))
        else:
            self._cache_end = min(self._cache_end, from_tick)

    def command_at(self, tick: int) -> tuple[float, float, float]:
        """The command in force at the drive at ``tick`` (after the dead time)."""
        i = bisect_right(self._sched_ticks, tick) - 1
        return self._sched_cmds[i] if i >= 0 else self._anchor_cmd

    def set_command(self, tick: int, command, delayed: bool = True) -> None:
        """A command received at ``tick``; in force from ``tick`` plus the dead time.

        A stop from the e-stop or the watchdog goes through the same path (``delayed``) unless
        told otherwise.
        """
        cmd = tuple(float(c) for c in command)
        if self.estop and cmd != _ZERO:
            return
        eff = max(tick + (self.dead_time_ticks if delayed else 0), self.anchor)
        # a later command supersedes pending ones that would act at or after it
        while self._sched_ticks and self._sched_ticks[-1] >= eff:
            self._sched_ticks.pop()
            self._sched_cmds.pop()
            self._invalidate(eff)
        if self.command_at(eff) == cmd:
            return
        self._sched_ticks.append(eff)
        self._sched_cmds.append(cmd)
        self._invalidate(eff)

    def _calibration(self) -> Calibration:
        # the dead time is applied by the schedule, so the simulator must not add it again
        return replace(self.base, effects=replace(self.effects, dead_time_s=0.0))

    def _simulate(self, end: int):
        ticks = np.arange(self.anchor, end + 1)
        idx = np.searchsorted(self._sched_ticks, ticks, side="right") - 1
        table = np.array([self._anchor_cmd, *self._sched_cmds], dtype=float)
        cmds = table[idx + 1]
        self.calls += 1
        return simulate(cmds, ticks * self.dt_s, self._calibration(), self.robot,
                        initial_state=self._state, initial_pose=self._pose)

    def _move_anchor(self, tick: int) -> None:
        if tick > self.anchor:
            traj = self._simulate(tick)
            self._state = traj.final_state.copy()
            self._pose = traj.pose[0, -1].copy()
            self._keep_past(traj.wheel_rpm[0, :-1], traj.pose[0, :-1])
        self._anchor_cmd = self.command_at(tick)
        keep = bisect_right(self._sched_ticks, tick)
        del self._sched_ticks[:keep]
        del self._sched_cmds[:keep]
        self.anchor = tick
        self._invalidate()

    def _keep_past(self, wheels: np.ndarray, poses: np.ndarray) -> None:
        """Keep the truth from the anchor up to the next one (at most :data:`PAST_S`)."""
        keep = math.ceil(PAST_S * self.rate_hz)
        if self._past_start + len(self._past) != self.anchor:
            self._past_start, self._past = self.anchor, self._past[:0]
            self._past_poses = self._past_poses[:0]
        self._past = np.concatenate([self._past, wheels])[-keep:]
        self._past_poses = np.concatenate([self._past_poses, poses])[-keep:]
        self._past_start = self.anchor + len(wheels) - len(self._past)

    def _truth_before_anchor(self, tick: int) -> int:
        """Row of ``tick`` (behind the anchor) in the kept past."""
        row = tick - self._past_start
        if not 0 <= row < len(self._past):
            raise ValueError(f"tick {tick} is before the model's anchor {self.anchor} and "
                             "its kept past")
        return row

    def apply_due_faults(self, tick: int) -> None:
        """Let the scheduled faults due at or before ``tick`` happen (each once a session)."""
        while self._faults:
            fault: Fault = self._faults[0]
            fault_tick = math.ceil(fault.at_s * self.rate_hz - 1e-9)
            if fault_tick > tick:
                return
            self._faults.pop(0)
            self._move_anchor(max(fault_tick, self.anchor))
            self.effects = fault.apply(self.effects)
            if fault.estop:
                self.set_command(self.anchor, _ZERO, delayed=False)
                self.estop = True

    def wheel_rpm(self, tick: int) -> np.ndarray:
        """The true wheel speeds at ``tick`` (no noise) [rpm]."""
        if tick < self.anchor:
            return self._past[self._truth_before_anchor(tick)]
        self.apply_due_faults(tick)
        if tick > self._cache_end:
            if tick - self.anchor > 2 * self.lookahead:
                self._move_anchor(tick)
            traj = self._simulate(tick + self.lookahead)
            self._wheels = traj.wheel_rpm[0]
            self._poses = traj.pose[0]
            self._cache_end = tick + self.lookahead
        return self._wheels[tick - self.anchor]

    def pose(self, tick: int) -> np.ndarray:
        """The true pose ``(X [m], Y [m], phi [deg])`` at ``tick``: what a camera or motion
        capture would measure (the wire protocol carries none)."""
        if tick < self.anchor:
            return self._past_poses[self._truth_before_anchor(tick)].copy()
        self.wheel_rpm(tick)
        return self._poses[tick - self.anchor].copy()

    def measured_rpm(self, tick: int) -> np.ndarray:
        """Wheel speeds at ``tick`` as the controller reports them: through the effects outside
        the library (:class:`UnmodelledSensor`), with noise [rpm]. Call in increasing ``tick``
        order."""
        # the sensor walks the ticks since its last call in order, before the model's anchor
        # may move on to this one
        w = self.sensor(tick, self.wheel_rpm) if self.sensor.active else self.wheel_rpm(tick)
        std = self.sim_effects.wheel_rpm_std
        return w + self._rng.normal(0.0, std, 4) if std > 0 else w.copy()


#: Fastest internal tick of the simulated controller [Hz]: it steps its model in real time,
#: and at 1 MHz it fell behind (190 of 1000 telemetry samples a second; 200 kHz kept pace).
MAX_INTERNAL_RATE_HZ = 100_000.0


def telemetry_ticks_for(telemetry_rate_hz: float, internal_rate_hz: float) -> int:
    """Internal ticks between telemetry samples for a rate; 0 for none.

    The sample rate is ``internal_rate_hz / ticks``, announced in HELLO_ACK in whole Hz, so a
    rate that cannot be announced honestly is refused instead of being changed silently.

    Raises
    ------
    ConfigError
        A rate that is not finite, negative, below 1 Hz (other than 0: HELLO_ACK would
        announce 0, "sends none"), or above the internal tick rate (or 65535 Hz).
    """
    rate = float(telemetry_rate_hz)
    internal = float(internal_rate_hz)
    if not (math.isfinite(internal) and 0 < internal <= MAX_INTERNAL_RATE_HZ):
        raise ConfigError(f"the internal tick rate must be a positive number of Hz up to "
                          f"{MAX_INTERNAL_RATE_HZ:g}, got {internal_rate_hz!r}")
    if not (math.isfinite(rate) and rate >= 0):
        raise ConfigError(f"telemetry rate must be 0 (none) or a positive number of Hz, got "
                          f"{telemetry_rate_hz!r}")
    if rate == 0:
        return 0
    if rate > internal * (1 + 1e-9):
        raise ConfigError(f"telemetry rate {rate:g} Hz is above the internal tick rate "
                          f"{internal:g} Hz: samples are taken on ticks (raise the internal "
                          "rate)")
    ticks = max(1, round(internal / rate))
    sent = internal / ticks
    if round(sent) < 1 or sent > 0xFFFF:
        raise ConfigError(f"telemetry rate {rate:g} Hz cannot be announced: HELLO_ACK carries "
                          "whole Hz from 1 to 65535 (0 means none)")
    return ticks


class SimulatedController:
    """The simulated controller's firmware loop on a transport: drivers/protocol.md's duties.

    It refuses (ERROR 2, counted in :attr:`bad_commands`, command ignored) every COMMAND that
    is malformed, not finite, or beyond the robot's wheel speed limit (announced in HELLO_ACK),
    keeps a watchdog stop until the next valid COMMAND, keeps a latched e-stop until
    ESTOP_RESET (never cleared by HELLO), and never ends on input: an unexpected error while
    handling a frame is answered with ERROR 255 and counted (:attr:`internal_errors`).

    Parameters
    ----------
    transport : Transport
        The controller's end of the link.
    model : ControllerModel
        The simulated robot; its robot profile gives the wheel speed limit and ``k``.
    telemetry_rate_hz : float
        Telemetry rate [Hz]; 0 sends none (see :func:`telemetry_ticks_for`).
    name : str
        Name sent in HELLO_ACK.
    version : int
        Protocol version the controller speaks (another value lets tests exercise a mismatch).
    log : callable, optional
        Called with one line per notable event (HELLO, STOP, watchdog, refused commands).
    clock : callable, optional
        Monotonic clock [s] (default :func:`time.monotonic`); a virtual one runs the firmware in
        simulated time (:mod:`mecanum_hil.link.lockstep`, :meth:`run_once`).
    """

    def __init__(self, transport: Transport, model: ControllerModel,
                 telemetry_rate_hz: float = 100.0, name: str = "mecanum-hil sim-robot",
                 version: int = PROTOCOL_VERSION,
                 log: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.transport = transport
        transport.set_role("controller")
        self.model = model
        self.telemetry_ticks = telemetry_ticks_for(telemetry_rate_hz, model.rate_hz)
        self.telemetry_rate_hz = (model.rate_hz / self.telemetry_ticks if self.telemetry_ticks
                                  else 0.0)
        self.wheel_limit_rpm = float(model.robot.wheel_speed_max_rpm)
        self.name = name
        self.version = version
        self.log = log or (lambda line: None)
        self.stop_event = threading.Event()
        self.connected = False
        self.status = 0
        self.ack_seq = 0
        self.stops_received = 0
        self.commands_received = 0
        #: COMMANDs refused with ERROR 2 (malformed, not finite, beyond the limit).
        self.bad_commands = 0
        #: Unexpected errors while handling a frame (answered with ERROR 255).
        self.internal_errors = 0
        self._t0 = clock()
        self._last_valid = -math.inf
        self._next_tlm_tick = 0

    def now_s(self) -> float:
        """Controller time since the last HELLO [s]."""
        return self.clock() - self._t0

    def _tick_now(self, rounding=math.floor) -> int:
        return max(int(rounding(self.now_s() * self.model.rate_hz - 1e-9)), self.model.anchor)

    def _error(self, code: int, text: str) -> None:
        try:
            self.transport.send(ErrorMsg(code, text))
        except LinkLostError:
            raise
        except LinkError:
            pass  # a controller never stalls on its output

    def _refuse_command(self, reason: str) -> None:
        self.bad_commands += 1
        self._error(ErrorCode.BAD_COMMAND, reason)
        self.log(f"COMMAND refused: {reason}")

    def _status_now(self) -> int:
        return int(self.status | (Status.ESTOP if self.model.estop else 0))

    def handle(self, msg) -> None:
        """Act on one received message (drivers/protocol.md, "The controller's duties")."""
        if isinstance(msg, Hello):
            if msg.version != self.version:
                self._error(ErrorCode.VERSION_MISMATCH,
                            f"controller speaks version {self.version}")
                self.log(f"HELLO of protocol version {msg.version} refused")
                return
            self.transport.restart_sequences()
            self._t0 = self.clock()
            self.model.restart()
            self._next_tlm_tick = 0
            self.connected = True
            self.status = Status.STOPPED  # also ends a watchdog stop; never an e-stop
            self.model.set_command(0, _ZERO)
            self._last_valid = 0.0
            self.ack_seq = msg.seq
            self.transport.send(HelloAck(self.version, round(self.telemetry_rate_hz),
                                         int(WATCHDOG_S * 1000), self.name,
                                         wheel_limit_rpm=self.wheel_limit_rpm))
            self.log("HELLO: session started")
            return
        if isinstance(msg, Ping):
            self.transport.send(Pong(msg.token))
            return
        if not self.connected or not isinstance(msg, Command | Stop | Heartbeat | EstopReset):
            return  # before the first HELLO only HELLO and PING are answered
        # what happened before this message is acted on first: an ESTOP_RESET handled before
        # the telemetry loop had applied an e-stop pressed at 0 s was undone by it a tick later
        self.model.apply_due_faults(self._tick_now())
        if isinstance(msg, Command):
            problem = self.command_problem(msg)
            if problem is not None:
                self._refuse_command(problem)
                return  # ignored: the last valid command stays, or the watchdog takes over
        self.ack_seq = msg.seq
        self._last_valid = self.now_s()
        if isinstance(msg, Command):
            self.commands_received += 1
            self.status &= ~(Status.STOPPED | Status.WATCHDOG)
            self.model.set_command(self._tick_now(math.ceil),
                                   (msg.n_rpm, msg.omega_dps, msg.theta_deg))
        elif isinstance(msg, Stop):
            self.stops_received += 1
            self.status |= Status.STOPPED
            self.model.set_command(self._tick_now(math.ceil), _ZERO)
            self.log("STOP received")
        elif isinstance(msg, EstopReset):
            if self.model.estop:
                # the simulated button is released at once: the latch is what is cleared
                self.model.estop = False
                self.status |= Status.STOPPED
                self.model.set_command(self._tick_now(math.ceil), _ZERO, delayed=False)
                self.log("ESTOP_RESET: e-stop cleared, wheels stopped until a COMMAND")
        # a HEARTBEAT only feeds the watchdog: a watchdog stop waits for a new COMMAND

    def command_problem(self, msg: Command) -> str | None:
        """Why ``msg`` must be refused (:func:`~mecanum_hil.link.protocol.command_problem`
        with the robot's ``k`` and the announced limit), or ``None``."""
        return command_problem(msg.n_rpm, msg.omega_dps, msg.theta_deg, self.model.robot.k,
                               self.wheel_limit_rpm)

    def take_rejected(self) -> None:
        """Answer refused frames the transport dropped: a COMMAND with ERROR 2."""
        rejected = self.transport.rejected
        while rejected:
            err = rejected.popleft()
            # a wrong version or unknown type is dropped unanswered, like damage
            if err.mtype == MsgType.COMMAND and err.kind in ("malformed", "bad_command") \
                    and self.connected:
                self._refuse_command(str(err)[:40])

    def check_watchdog(self) -> None:
        """Stop the wheels when no valid command came for the watchdog time."""
        if self.connected and not self.status & Status.WATCHDOG and \
                self.now_s() - self._last_valid > WATCHDOG_S:
            self.status |= Status.WATCHDOG
            self.model.set_command(self._tick_now(math.ceil), _ZERO)
            self.log("watchdog: no command for 250 ms, wheels stopped until a new COMMAND")

    def send_telemetry(self, tick: int) -> None:
        """Send the telemetry sample of ``tick``."""
        wheels = self.model.measured_rpm(tick)
        self.transport.send(Telemetry(round(tick * self.model.dt_s * 1e6),
                                      tuple(float(w) for w in wheels), self._status_now(),
                                      self.ack_seq))

    def _receive(self, wait_s: float) -> None:
        msg = self.transport.recv(max(0.0, wait_s))
        while msg is not None:
            try:
                self.handle(msg)
            except LinkError:
                raise
            except Exception as err:  # never end on input; say so on the wire
                self.internal_errors += 1
                self.log(f"error while handling {type(msg).__name__}: {err!r}")
                self._error(ErrorCode.OTHER, f"internal error: {type(err).__name__}")
            msg = self.transport.recv(0.0)
        self.take_rejected()

    def _send_due_telemetry(self) -> None:
        now_tick = self._tick_now()
        while now_tick >= self._next_tlm_tick:
            if now_tick - self._next_tlm_tick > 50 * self.telemetry_ticks:
                self._next_tlm_tick = now_tick  # a long stall: skip, not burst
            # a sample is due: report it at its own tick, even if sent late
            tick = self._next_tlm_tick
            self._next_tlm_tick += self.telemetry_ticks
            self.send_telemetry(tick)

    def run_once(self, wait_s: float = 0.0) -> None:
        """One pass of the firmware loop: take what arrived within ``wait_s`` [s], run the
        watchdog, send the telemetry samples due by the clock. A frame the transport cannot
        send is dropped (a controller never stalls on its output).

        Raises
        ------
        LinkLostError
            When the link is gone.
        """
        try:
            self._receive(wait_s)
            self.check_watchdog()
            if self.connected and self.telemetry_ticks:
                self._send_due_telemetry()
        except LinkLostError:
            raise
        except LinkError as err:
            self.log(f"dropped a frame: {err}")

    def serve(self, duration_s: float | None = None) -> None:
        """Serve until :attr:`stop_event` is set (or ``duration_s`` passed) [s].

        A lost link ends the loop with :class:`~mecanum_hil.errors.LinkLostError`.
        """
        self.model.wheel_rpm(self.model.anchor)  # load the compiled simulator before serving
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        while not self.stop_event.is_set() and time.monotonic() < end:
            wait = 0.02
            if self.connected and self.telemetry_ticks:
                wait = min(wait, self._next_tlm_tick * self.model.dt_s - self.now_s())
            self.run_once(wait)


def open_controller_end(kind: str, can_spec: str | None = None):
    """Open the controller's end of a link for ``sim-robot``.

    Parameters
    ----------
    kind : str
        ``"serial"`` (a new pseudo-terminal, framed protocol), ``"slcan"`` (a new
        pseudo-terminal playing an SLCAN adapter) or ``"can"`` (a python-can bus).
    can_spec : str, optional
        ``INTERFACE:CHANNEL`` for ``"can"`` (``virtual:bench``, ``socketcan:can0``).

    Returns
    -------
    transport : Transport
    where : str
        The device path (serial, slcan) or ``INTERFACE:CHANNEL``.
    keep : list
        Objects to keep alive (the slave descriptor) and close with :func:`os.close`.
    """
    import os
    import tty

    if kind in ("serial", "slcan"):
        master, slave = os.openpty()
        # raw at once: with the default line discipline the pty would echo our own telemetry
        tty.setraw(slave)
        path = os.ttyname(slave)
        if kind == "serial":
            from .serial_link import SerialTransport

            return SerialTransport(fd=master), path, [slave]
        from .slcan_adapter import SlcanAdapterTransport

        return SlcanAdapterTransport(master), path, [slave]
    if kind == "can":
        from ..errors import ConfigError
        from .can_link import CanTransport

        if not can_spec or ":" not in can_spec:
            raise ConfigError(f"--can needs INTERFACE:CHANNEL (e.g. socketcan:can0), "
                              f"got {can_spec!r}")
        interface, channel = can_spec.split(":", 1)
        return CanTransport(interface=interface, channel=channel), can_spec, []
    raise ValueError(f"unknown controller link kind {kind!r}")
