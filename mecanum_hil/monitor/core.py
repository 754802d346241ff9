"""Shadow mode: the model beside the robot, divergence detection per channel.

:class:`ShadowMonitor` is the stateful shell: it is fed one telemetry sample at a time (it
satisfies the link layer's ``TelemetryObserver`` protocol: ``on_telemetry(t_s, commands,
wheel_rpm)`` and ``stop_requested``), runs the compiled per-sample core
(:mod:`mecanum_hil.monitor._kernel`) and turns its events into :class:`Alarm` records, event
dictionaries for listeners (the JSON-lines log, the terminal) and, optionally, a stop request.
:func:`replay` runs the very same monitor over a recording, sample by sample, as if live.

Method (see docs/shadow.md for the reasoning behind the defaults):

* prediction: the model (calibration incl. effects) fed the same commands, advanced exactly from
  the previous sample time to this one; wheel channels compare the open-loop wheel speeds, pose
  channels the pose over a window of ``pose_window_s`` re-anchored on the measured pose;
* normalisation: residual / sigma, sigma given or estimated once per channel as 1.4826 MAD of
  the residuals of the first ``warmup_s`` (at least ``min_warmup_samples``), raised by
  ``noise_margin`` standard errors, not below a floor;
* detection: two-sided CUSUM ``S+ = max(0, S+ + z - k)``, ``S- = max(0, S- - z - k)``, alarm when
  either exceeds ``h``; the alarm reports the mean residual since the statistic left zero (the
  size of the shift) and that time (the onset estimate). A channel then stays diverged, without
  new alarms, until no threshold crossing happened for ``clear_s``; a ``recovered`` event says so.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .._jit import pick
from ..errors import ConfigError
from ..io.recording import Recording
from ..model.calibration import Calibration
from ..model.robot import RobotProfile
from . import _kernel as kn

#: Channels the monitor can watch (recording column names), and their units.
CHANNELS = kn.CHANNELS
UNITS = ("rpm", "rpm", "rpm", "rpm", "m", "m", "deg")

#: Event listener: receives one event dictionary (see docs/shadow.md, "Event log").
Listener = Callable[[dict[str, Any]], None]


@dataclass(frozen=True)
class ShadowConfig:
    """Detection settings of the shadow monitor.

    Attributes
    ----------
    drift_k : float
        CUSUM reference value (allowance) [noise sigmas]: half the smallest persistent shift the
        test is tuned to detect fastest (k = 1 for shifts of 2 sigma and more).
    threshold_h : float
        CUSUM decision threshold [noise sigmas].
    warmup_s : float
        Length of the initial window whose residuals give the noise estimate [s]; the channel is
        not tested before its estimate exists.
    min_warmup_samples : int
        Fewest residuals per channel for the noise estimate (pose channels, one residual per
        window, start testing after ``min_warmup_samples * pose_window_s``).
    noise_margin : float
        The estimate is raised by this many of its standard errors (``1.17 sigma / sqrt(n)``
        for the MAD): an underestimate inflates every normalised residual, and the CUSUM's
        false-alarm rate depends steeply on it.
    clear_s : float
        A diverged channel recovers (and may alarm again) after this long without a threshold
        crossing [s].
    pose_window_s : float
        Window over which pose residuals are formed [s].
    noise_rpm, noise_m, noise_deg : float or None
        Given noise levels (1 sigma) of wheel speeds [rpm], positions [m] and heading [deg];
        ``None`` estimates them.
    noise_floor_rpm, noise_floor_m, noise_floor_deg : float
        Smallest noise level used when estimating [rpm], [m], [deg] (a quantised, noise-free
        signal would otherwise give sigma = 0).
    start_from_measured : bool
        Start the model in steady state at the first measured wheel speeds and command (a monitor
        joining a running robot); ``False`` starts it at rest with zero command, as ``simulate``.
    max_substep_s : float
        Longest sub-step with saturation or rate limit, as in the simulator [s].
    timing_tolerance_s : float
        Clock and latency offset between commands and measurements that is not divergence [s]:
        a wheel residual shrinks by the model's slope times this (a live link's host clock
        sees commands act and measurements arrive up to ~1-2 ms off the controller's).
    """

    drift_k: float = 1.0
    threshold_h: float = 10.0
    warmup_s: float = 2.0
    min_warmup_samples: int = 100
    noise_margin: float = 1.5
    clear_s: float = 1.0
    pose_window_s: float = 0.1
    noise_rpm: float | None = None
    noise_m: float | None = None
    noise_deg: float | None = None
    noise_floor_rpm: float = 0.2
    noise_floor_m: float = 0.001
    noise_floor_deg: float = 0.1
    start_from_measured: bool = True
    max_substep_s: float = 1e-3
    timing_tolerance_s: float = 0.002

    def __post_init__(self) -> None:
        for name in ("drift_k", "threshold_h", "warmup_s", "clear_s", "pose_window_s",
                     "noise_margin", "noise_floor_rpm", "noise_floor_m", "noise_floor_deg",
                     "max_substep_s", "timing_tolerance_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"shadow setting {name} must be a finite number >= 0, got {v}")
        for name in ("threshold_h", "max_substep_s"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"shadow setting {name} must be > 0, got {getattr(self, name)}")
        if self.min_warmup_samples < 2:
            raise ConfigError("shadow setting min_warmup_samples must be >= 2")
        for name in ("noise_rpm", "noise_m", "noise_deg"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ConfigError(f"shadow setting {name} must be > 0, got {v}")


@dataclass(frozen=True)
class Alarm:
    """One detected divergence.

    Attributes
    ----------
    t_s : float
        Time of the sample at which the CUSUM crossed its threshold [s].
    channel : str
        Recording column that diverged (``wheel2_rpm``, ``x_m`` ...).
    residual : float
        Mean of measured - predicted since the statistic last left zero [channel unit].
    onset_t_s : float
        When the statistic last left zero: the change-point estimate [s].
    direction : int
        +1 measured above the model, -1 below.
    statistic : float
        CUSUM value at the alarm [noise sigmas].
    noise : float
        Noise level used for the channel [channel unit].
    predicted, measured : float
        Model and measurement at the alarm sample [channel unit].
    """

    t_s: float
    channel: str
    residual: float
    onset_t_s: float
    direction: int
    statistic: float
    noise: float
    predicted: float
    measured: float

    @property
    def unit(self) -> str:
        """Unit of the channel."""
        return UNITS[CHANNELS.index(self.channel)]

    def summary(self) -> dict[str, Any]:
        """The public three-field form used by ``shadow --json``."""
        return {"t_s": self.t_s, "channel": self.channel, "residual": self.residual}


def _params(cal: Calibration, robot: RobotProfile, cfg: ShadowConfig) -> np.ndarray:
    e = cal.effects
    pp = np.zeros(kn.P_WIDTH)
    pp[kn.P_A], pp[kn.P_B], pp[kn.P_C] = cal.A, cal.B, cal.C
    pp[kn.P_K], pp[kn.P_R] = robot.k, robot.wheel_radius_m
    pp[kn.P_DB] = e.deadband_rpm
    pp[kn.P_GAIN:kn.P_GAIN + 4] = e.gains
    pp[kn.P_TOP], pp[kn.P_RL] = e.output_limit_rpm, e.rate_limit_rpm_per_s
    pp[kn.P_WINDUP] = float(e.windup)
    pp[kn.P_FRIC] = e.friction_rpm_per_s
    pp[kn.P_DBOFF] = e.drive_deadband_rpm
    pp[kn.P_EFF:kn.P_EFF + 3] = e.efficiency
    pp[kn.P_DELAY], pp[kn.P_SUB] = e.dead_time_s, cfg.max_substep_s
    pp[kn.P_PER], pp[kn.P_LAG], pp[kn.P_BRK] = (e.controller_period_s, e.drive_lag_s,
                                               e.breakaway_rpm_per_s)
    pp[kn.P_BRAKE] = e.braking_limit_rpm_per_s
    pp[kn.P_U0], pp[kn.P_Y0] = e.coast_decel_rpm_per_s, e.no_load_rpm
    pp[kn.P_DRIFT], pp[kn.P_THRESH] = cfg.drift_k, cfg.threshold_h
    pp[kn.P_WARM], pp[kn.P_MINN], pp[kn.P_CLEAR] = cfg.warmup_s, cfg.min_warmup_samples, cfg.clear_s
    pp[kn.P_PWIN] = cfg.pose_window_s
    pp[kn.P_FROM_MEAS] = 1.0 if cfg.start_from_measured else 0.0
    pp[kn.P_TOL] = cfg.timing_tolerance_s
    pp[kn.P_SAFETY] = cfg.noise_margin
    given = [cfg.noise_rpm] * 4 + [cfg.noise_m] * 2 + [cfg.noise_deg]
    pp[kn.P_NOISE:kn.P_NOISE + kn.N_CH] = [0.0 if g is None else g for g in given]
    pp[kn.P_FLOOR:kn.P_FLOOR + kn.N_CH] = ([cfg.noise_floor_rpm] * 4 + [cfg.noise_floor_m] * 2
                                        + [cfg.noise_floor_deg])
    return pp


class ShadowMonitor:
    """The model running beside the robot; flags persistent divergence per channel.

    Feed it samples with :meth:`on_telemetry` (live, one call per telemetry frame) or run
    :func:`replay`. Each call costs a few microseconds and never waits on anything; events reach
    the listeners synchronously, so a listener must be quick (the JSON-lines log appends a line).

    Parameters
    ----------
    calibration : Calibration
        The model (coefficients and effects) the robot is expected to follow.
    robot : RobotProfile, optional
        Geometry (default: the paper's robot).
    config : ShadowConfig, optional
        Detection settings.
    stop_on_divergence : bool
        Set :attr:`stop_requested` at the first alarm (``--on-divergence stop``).
    listeners : sequence of callables, optional
        Called with each event dictionary (``alarm``, ``recovered``, ``noise``).

    Attributes
    ----------
    stop_requested : bool
        True once an alarm asked the command stream to stop (read by the record session).
    alarms : list of Alarm
        Alarms so far, in time order.
    noise : dict
        Noise level per channel once known [channel unit].
    samples : int
        Samples processed.
    """

    def __init__(self, calibration: Calibration, robot: RobotProfile | None = None,
                 config: ShadowConfig | None = None, *, stop_on_divergence: bool = False,
                 listeners: list[Listener] | tuple[Listener, ...] = (),
                 warm_up: bool = True) -> None:
        self.calibration = calibration
        self.robot = robot or RobotProfile()
        self.config = config or ShadowConfig()
        self.stop_on_divergence = stop_on_divergence
        self.listeners: list[Listener] = list(listeners)
        self._pp = _params(calibration, self.robot, self.config)
        self.reset()
        if warm_up:
            self._compile()

    def reset(self) -> None:
        """Forget everything seen; the next sample starts the model afresh."""
        self.stop_requested = False
        self.alarms: list[Alarm] = []
        self.noise: dict[str, float] = {}
        self.samples = 0
        self._fs = np.zeros(kn.S_WIDTH)
        self._fs[kn.S_TPREV] = np.nan
        self._ch = np.zeros((kn.N_CH, kn.C_WIDTH))
        self._ch[:, kn.C_SIGMA] = self._pp[kn.P_NOISE:kn.P_NOISE + kn.N_CH]
        for c, s in enumerate(self._ch[:, kn.C_SIGMA]):
            if s > 0:
                self.noise[CHANNELS[c]] = float(s)
        self._buf = np.zeros((kn.N_CH, 4096))
        self._queue = np.zeros((64, 4))
        self._qi = np.zeros(2, dtype=np.int64)
        self._ev = np.zeros((kn.MAX_EVENTS, kn.E_WIDTH))
        self._tab = np.zeros(11)  # a discretisation row and its step length (model/motor.py)
        self._q = np.zeros(4)
        self._row = np.full(11, np.nan)
        self._schedule: np.ndarray | None = None
        self._sched_i = 0

    def _compile(self) -> None:
        # the first call of a numba function loads (or compiles) it: do that now, on a throw-away
        # state, so the first live sample does not pay for it
        fs = self._fs.copy()
        ch = self._ch.copy()
        rows = np.zeros((2, 11))
        rows[1, 0] = 1e-3
        kn.monitor_run(rows, 0, self._pp, fs, ch, self._buf.copy(), self._queue.copy(),
                      self._qi.copy(), self._ev.copy(), self._tab, self._q)
        kn.monitor_step(rows[0], self._pp, fs, ch, self._buf.copy(), self._queue.copy(),
                       self._qi.copy(), self._ev.copy(), self._tab, self._q)

    # -- live -------------------------------------------------------------------------------

    def on_telemetry(self, t_s: float, commands, wheel_rpm, pose=None) -> None:
        """One sample: commands in force at ``t_s`` and the measured values.

        Parameters
        ----------
        t_s : float
            Sample time, strictly increasing [s].
        commands : array_like, shape (3,)
            ``(n [rpm], omega [deg/s], theta [deg])`` in force from ``t_s`` on.
        wheel_rpm : array_like, shape (4,)
            Measured wheel speeds [rpm]; NaN for a wheel not measured.
        pose : array_like, shape (3,), optional
            Measured ``(X [m], Y [m], phi [deg])``.
        """
        sched = self._schedule
        if sched is not None:
            # commands sent between the previous sample and this one act from their send times
            while self._sched_i < sched.shape[0] and sched[self._sched_i, 0] < t_s:
                self._step(sched[self._sched_i])
                self._sched_i += 1
        row = self._row
        row[0] = t_s
        row[1:4] = commands
        row[4:8] = wheel_rpm
        row[8:11] = np.nan if pose is None else pose
        self._step(row)

    def on_command(self, t_s: float, commands) -> None:
        """A command sent (or heard) at ``t_s``, with nothing measured: it acts from ``t_s``."""
        row = self._row
        row[0] = t_s
        row[1:4] = commands
        row[4:11] = np.nan
        self._step(row)

    def set_command_schedule(self, t_s, commands) -> None:
        """Times [s] and commands a sender will send (a record session's profile).

        Live telemetry carries only the command in force when it arrives; with the schedule,
        :meth:`on_telemetry` first applies the commands sent since the previous sample at their
        own times, as a replay of the recording (which has a row per command sent) does.
        """
        t = np.asarray(t_s, dtype=float).reshape(-1, 1)
        cmd = np.asarray(commands, dtype=float).reshape(-1, 3)
        rows = np.full((t.shape[0], 11), np.nan)
        rows[:, :1] = t
        rows[:, 1:4] = cmd
        self._schedule = rows
        self._sched_i = 0

    def clear_command_schedule(self) -> None:
        """Forget the schedule given by :meth:`set_command_schedule`."""
        self._schedule = None

    def _step(self, row: np.ndarray) -> None:
        if self._qi[1] >= self._queue.shape[0]:
            self._grow_queue()
        n = kn.monitor_step(row, self._pp, self._fs, self._ch, self._buf, self._queue, self._qi,
                           self._ev, self._tab, self._q)
        self.samples += 1
        if n:
            self._handle(n)

    # -- shared -----------------------------------------------------------------------------

    def _grow_queue(self) -> None:
        cap = self._queue.shape[0]
        head, count = int(self._qi[0]), int(self._qi[1])
        order = (head + np.arange(count)) % cap
        new = np.zeros((2 * cap, 4))
        new[:count] = self._queue[order]
        self._queue = new
        self._qi[0] = 0

    def _handle(self, n: int) -> None:
        for e in self._ev[:n]:
            kind, c = e[kn.E_KIND], int(e[kn.E_CH])
            name = CHANNELS[c]
            if kind == kn.EV_NOISE:
                self.noise[name] = float(e[kn.E_SIGMA])
                event = {"event": "noise", "t_s": float(e[kn.E_T]), "channel": name,
                         "noise": float(e[kn.E_SIGMA]), "unit": UNITS[c]}
            elif kind == kn.EV_ALARM:
                alarm = Alarm(float(e[kn.E_T]), name, float(e[kn.E_RESID]), float(e[kn.E_ONSET]),
                              int(e[kn.E_DIR]), float(e[kn.E_STAT]), float(e[kn.E_SIGMA]),
                              float(e[kn.E_PRED]), float(e[kn.E_MEAS]))
                self.alarms.append(alarm)
                if self.stop_on_divergence:
                    self.stop_requested = True
                event = {"event": "alarm", **asdict(alarm), "unit": UNITS[c],
                         "action": "stop" if self.stop_on_divergence else "none"}
            else:
                event = {"event": "recovered", "t_s": float(e[kn.E_T]), "channel": name,
                         "last_crossing_t_s": float(e[kn.E_ONSET]), "unit": UNITS[c]}
            for listener in self.listeners:
                listener(event)

    def run(self, rows: np.ndarray) -> None:
        """Process many samples ``rows (T, 11) = (t, n, omega, theta, w1..w4, x, y, phi)``.

        The same per-sample core as :meth:`on_telemetry`, looped in compiled code; events are
        handled after the sample that raised them, exactly as live.
        """
        rows = np.ascontiguousarray(rows, dtype=float)
        if rows.ndim != 2 or rows.shape[1] != 11:
            raise ConfigError(f"rows must have shape (T, 11), got {rows.shape}")
        # a short replay runs in the interpreter: numba's start-up costs more (_jit.py)
        monitor_run = pick(kn.monitor_run, rows.shape[0])
        start = 0
        while start < rows.shape[0]:
            nxt, n = monitor_run(rows, start, self._pp, self._fs, self._ch, self._buf,
                                 self._queue, self._qi, self._ev, self._tab, self._q)
            if n < 0:
                self._grow_queue()
            self.samples += nxt - start
            start = nxt
            if n > 0:
                self._handle(n)

    def status(self) -> dict[str, Any]:
        """A snapshot for a status line: per channel the larger CUSUM side [sigmas] and state."""
        ch = self._ch
        out: dict[str, Any] = {"samples": self.samples, "alarms": len(self.alarms),
                               "t_s": float(self._fs[kn.S_TPREV]), "channels": {}}
        for c, name in enumerate(CHANNELS):
            if ch[c, kn.C_SIGMA] == 0.0 and ch[c, kn.C_COUNT] == 0.0:
                continue  # never measured
            state = ("warm-up" if ch[c, kn.C_SIGMA] == 0.0
                     else "DIVERGED" if ch[c, kn.C_DIVERGED] else "ok")
            out["channels"][name] = {
                "state": state,
                "cusum": float(max(ch[c, kn.C_SPOS], ch[c, kn.C_SNEG])),
                "residual": float(ch[c, kn.C_RESID]),
            }
        return out

    def status_line(self) -> str:
        """One terminal line: ``shadow t=12.3s w1 ok 0.4 | w2 DIVERGED ... | alarms 1``."""
        st = self.status()
        parts = []
        for name, s in st["channels"].items():
            short = name.replace("wheel", "w").replace("_rpm", "").replace("_m", "").replace(
                "_deg", "")
            parts.append(f"{short} {s['state']}" if s["state"] != "ok"
                         else f"{short} {s['cusum'] / self.config.threshold_h:4.0%}")
        t = st["t_s"]
        return (f"shadow t={t:7.2f}s " if math.isfinite(t) else "shadow ") + " | ".join(parts) + (
            f" | alarms {st['alarms']}")

    @property
    def predicted(self) -> np.ndarray:
        """Model values of the seven channels at the last sample [rpm x4, m, m, deg]."""
        return self._fs[kn.S_PRED:kn.S_PRED + kn.N_CH].copy()


@dataclass(frozen=True)
class ShadowResult:
    """Result of a replay.

    Attributes
    ----------
    alarms : tuple of Alarm
    noise : dict
        Noise level per channel [channel unit].
    samples : int
    events : tuple of dict
        Every event, in order (what the JSON-lines log holds after its header).
    """

    alarms: tuple[Alarm, ...]
    noise: dict[str, float]
    samples: int
    events: tuple[dict[str, Any], ...] = field(default=())

    @property
    def first_alarm_t_s(self) -> float | None:
        """Time of the first alarm [s], or None."""
        return self.alarms[0].t_s if self.alarms else None

    def summary(self) -> dict[str, Any]:
        """``{"alarms": [{"t_s", "channel", "residual"}...], "first_alarm_t_s": ..}``."""
        return {"alarms": [a.summary() for a in self.alarms],
                "first_alarm_t_s": self.first_alarm_t_s}


def nothing_compared(result: ShadowResult, rec: Recording, config: ShadowConfig) -> str | None:
    """Why a replay's "no alarm" says nothing of the robot: the monitor armed only on channels
    without measurements (a noise level given for empty wheels), or never armed (its warm-up
    did not complete); ``None`` when something was compared.

    Parameters
    ----------
    result : ShadowResult
        The replay of ``rec``.
    rec : Recording
    config : ShadowConfig
        The settings of the replay (its warm-up, for the message).
    """
    measured = dict(zip(CHANNELS, [*np.isfinite(rec.wheel_rpm).any(axis=0),
                                    *np.isfinite(rec.pose).any(axis=0)], strict=True))
    if result.noise and not any(measured.get(ch, False) for ch in result.noise):
        return (f"nothing was compared: the monitor was armed on {', '.join(result.noise)}, "
                "which have no measurements, and the measured channels "
                f"({', '.join(ch for ch, m in measured.items() if m)}) never finished their "
                "warm-up")
    if not result.noise and result.samples:
        return (f"the monitor never armed: its warm-up (at least {config.warmup_s:g} s and "
                f"{config.min_warmup_samples} samples of each channel) did not complete, so no "
                "divergence could be flagged; give the noise level with --noise-rpm, or a "
                "longer recording")
    return None


def recording_rows(rec: Recording) -> np.ndarray:
    """A recording as the monitor's sample rows ``(t, n, omega, theta, w1..w4, x, y, phi)``."""
    return np.column_stack([rec.t_s, rec.commands, rec.wheel_rpm, rec.pose])


def replay(rec: Recording, calibration: Calibration, robot: RobotProfile | None = None,
           config: ShadowConfig | None = None, listeners: list[Listener] | tuple = (),
           source: str = "recording") -> ShadowResult:
    """Run the shadow monitor over a recording as if live.

    Parameters
    ----------
    rec : Recording
        Needs commands on every row (the model's input) from the first row that has them on
        (leading rows without commands are skipped) and at least one measured channel.
    calibration, robot, config, listeners
        As for :class:`ShadowMonitor`.
    source : str
        Name used in error messages.

    Returns
    -------
    ShadowResult
    """
    from ..errors import RecordingError
    from ..prediction import require_commands

    known = np.flatnonzero(np.isfinite(rec.commands).all(axis=1))
    if known.size and known[0] > 0:
        # a listener joining a running robot records telemetry before it hears a command:
        # the model starts at the first row whose command is known
        k = int(known[0])
        rec = rec.with_values(t_s=rec.t_s[k:], commands=rec.commands[k:],
                              wheel_rpm=rec.wheel_rpm[k:], pose=rec.pose[k:],
                              extra={n: list(v)[k:] for n, v in rec.extra.items()})
    require_commands(rec, source)
    if not (np.isfinite(rec.wheel_rpm).any() or np.isfinite(rec.pose).all(axis=1).any()):
        raise RecordingError(f"{source}: nothing measured to compare (wheel and pose columns "
                             "are empty)")
    events: list[dict[str, Any]] = []
    mon = ShadowMonitor(calibration, robot, config, listeners=[events.append, *listeners],
                        warm_up=False)
    mon.run(recording_rows(rec))
    return ShadowResult(tuple(mon.alarms), dict(mon.noise), mon.samples, tuple(events))
