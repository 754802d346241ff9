"""A policy driving the robot in closed loop: ``record --policy``.

The policy acts every control period it was trained with. Its observation is built from the
telemetry exactly as the environment builds it from the model's state: wheel speeds as
measured, the pose by odometry (the measured wheel speeds through the model's forward
kinematics, with the calibration's slip efficiencies, integrated on the controller's clock), the
task's entries from the episode's draw (:func:`mecanum_hil.policy.episode_draw`: the same
targets and strikes as ``evaluate`` with the same seed) relative to where the episode started.
Its action goes through the environment's limiter, then through ``record``'s checks (the robot
profile's limits and the transport's ranges) before it is sent.

Two drivers run the same :class:`EpisodeController`:

- :func:`run_policy_episode` on a real link, in real time, with every safety rule of ``record``
  (it is :class:`~mecanum_hil.link.session.RecordSession` with a closed-loop ``run``): STOP on every
  way out (end of episode, Ctrl-C, SIGTERM/SIGHUP, exception, lost link, an observer's stop),
  the recording flushed as it grows, observers (shadow mode) beside it;
- :func:`run_policy_lockstep`: the simulated controller (``sim-robot``'s firmware and robot,
  an effects file's hidden truth) on a virtual clock, every message through the serial framing,
  for studies that need many episodes (``bench/sim_to_real.py``).

Between episodes the robot is brought to rest (STOP, then wait for the measured wheel speeds to
settle); each episode starts where the robot stands, its odometry reset to the task's start
pose, so targets are relative to the start. One recording per episode, and ``summary.json``
with the figures ``evaluate`` prints.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, LimitError, MecanumHILError, SessionTerminated
from ..io.recording import RecordingWriter
from ..model import Calibration, RobotProfile, wheels_to_twist
from ..units import DPS_TO_RPM, RPM_TO_RAD_S
from .observers import ObserverStopError
from .protocol import PROTOCOL_VERSION, Hello, Stop, Telemetry
from .session import (
    EXTRA_COLUMNS,
    RecordResult,
    RecordSession,
    SessionConfig,
    _start_metadata,
)
from .session_types import EXIT_CODES
from .signals import SignalGuard, signal_end_reason, signal_reason
from .stop_path import stream_stop_close
from .transport import Transport

#: Wheel speed below which the robot counts as at rest between episodes [rpm].
REST_RPM = 1.0


@dataclass
class EpisodeOutcome:
    """How one episode on the robot went (the environment's figures, from odometry).

    Attributes
    ----------
    success : bool
    episode_return : float
    end_time_s : float
        Episode time at its end [s].
    steps : int
        Control periods run.
    final_pose : ndarray
        Odometry pose at the end ``(X [m], Y [m], phi [deg])``, start at the task's start pose.
    task_state : ndarray
        The episode's draw.
    path : list
        ``(t [s], X [m], Y [m], phi [deg])`` by odometry at every control step.
    ended : str
        ``success``, ``failure``, ``truncated``, or how the run was cut short.
    """

    success: bool = False
    episode_return: float = 0.0
    end_time_s: float = 0.0
    steps: int = 0
    final_pose: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    task_state: np.ndarray = field(default_factory=lambda: np.zeros(0))
    path: list = field(default_factory=list)
    ended: str = ""

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (the sidecar's ``policy_episode``)."""
        return {"success": bool(self.success), "return": float(self.episode_return),
                "end_time_s": float(self.end_time_s), "steps": int(self.steps),
                "ended": self.ended, "final_pose": [float(v) for v in self.final_pose],
                "task_state": [float(v) for v in self.task_state],
                "odometry": [[round(float(v), 6) for v in row] for row in self.path]}


class EpisodeController:
    """One episode of a policy on telemetry: odometry, observation, action, reward, end.

    Parameters
    ----------
    policy : NetworkPolicy or ScriptedPolicy
        Gives the task and the control period.
    robot : RobotProfile
        Geometry and limits.
    calibration : Calibration
        Its slip efficiencies turn wheel speeds into body velocity (as in the environment).
    task_state : ndarray
        The episode's draw (:func:`mecanum_hil.policy.episode_draw`).
    """

    def __init__(self, policy, robot: RobotProfile, calibration: Calibration,
                 task_state: np.ndarray) -> None:
        from ..envs import _kernels

        self.policy = policy
        self.task = policy.task
        self.robot = robot
        self.period_s = float(policy.control_period_s)
        self.episode_steps = max(1, round(self.task.episode_s / self.period_s))
        self.task_state = np.asarray(task_state, dtype=float).reshape(1, -1)
        self._params = self.task.kernel_parameters(robot)
        eff = calibration.effects.efficiency
        r = robot.wheel_radius_m
        self._fk = np.ascontiguousarray(wheels_to_twist(np.eye(4), robot.k) * np.array(
            [eff[0] * RPM_TO_RAD_S * r, eff[1] * RPM_TO_RAD_S * r, eff[2] / DPS_TO_RPM]))
        self._limit = _kernels.limit_actions
        self._low = np.array([0.0, -robot.omega_max_dps, -180.0])
        self._high = np.array([robot.wheel_speed_max_rpm, robot.omega_max_dps, 180.0])
        self.pose = np.array(self.task.start_pose, dtype=float)
        self.wheels = np.zeros(4)
        self._last_t: float | None = None
        self.step = 0
        self.outcome = EpisodeOutcome(task_state=self.task_state[0].copy())
        self._potential = 0.0
        self.done = False
        # compile (or load) the kernels now: once the link is up, a pause longer than the
        # watchdog's would stop the wheels
        self._evaluate()
        self._limit(np.zeros((1, 3)), self._low, self._high, 1.0, 1.0, np.empty((1, 3)))

    # -- odometry ----------------------------------------------------------------------------
    def on_telemetry(self, controller_time_s: float, wheel_rpm) -> None:
        """A telemetry sample: integrate the pose from the previous one (trapezoid on the wheel
        speeds, the heading at the interval's middle)."""
        w = np.asarray(wheel_rpm, dtype=float)
        if self._last_t is not None:
            dt = controller_time_s - self._last_t
            if 0 < dt < 1.0:
                vx, vy, wz = 0.5 * (self.wheels + w) @ self._fk
                phi = math.radians(self.pose[2] + 0.5 * wz * dt)
                self.pose[0] += (vx * math.cos(phi) - vy * math.sin(phi)) * dt
                self.pose[1] += (vx * math.sin(phi) + vy * math.cos(phi)) * dt
                self.pose[2] += wz * dt
        self._last_t = controller_time_s
        self.wheels = w

    # -- the loop ----------------------------------------------------------------------------
    def _evaluate(self):
        obs = np.empty((1, 13))
        potential, success, failed = np.empty(1), np.empty(1, dtype=bool), np.empty(1,
                                                                                     dtype=bool)
        state = np.zeros((1, 12))
        state[0, :4] = self.wheels
        self.task.evaluate(self.pose[None].copy(), state, self.task_state, self._fk,
                           self._params, np.array([self.step * self.period_s]), obs, potential,
                           success, failed)
        return obs, float(potential[0]), bool(success[0]), bool(failed[0])

    def _note_path(self) -> None:
        self.outcome.path.append((self.step * self.period_s, *self.pose))

    def begin(self) -> None:
        """Start the episode here: odometry at the task's start pose."""
        self.pose = np.array(self.task.start_pose, dtype=float)
        self.step = 0
        _, self._potential, _, _ = self._evaluate()
        self._note_path()

    def next_command(self) -> np.ndarray | None:
        """Score the period just ended (after the first) and give the next command, limited as
        the environment limits it; ``None`` once the episode is over."""
        obs, potential, success, failed = self._evaluate()
        if self.step > 0:
            t = self.task
            reward = potential - self._potential - t.time_cost_per_s * self.period_s
            reward += t.success_bonus if success else 0.0
            reward -= t.failure_penalty if failed else 0.0
            self._potential = potential
            o = self.outcome
            o.episode_return += reward
            self._note_path()
            if success or failed or self.step >= self.episode_steps:
                self.done = True
                o.success = success
                o.ended = "success" if success else "failure" if failed else "truncated"
                o.end_time_s = self.step * self.period_s
                o.steps = self.step
                o.final_pose = self.pose.copy()
                return None
        action = np.asarray(self.policy.act(obs), dtype=float).reshape(1, 3)
        cmd = np.empty((1, 3))
        if not self._limit(action, self._low, self._high, self.robot.k / 6.0,
                           self.robot.wheel_speed_max_rpm, cmd):
            raise LimitError(f"the policy gave a non-finite action {action[0].tolist()}")
        self.step += 1
        return cmd[0]

    def cut_short(self, reason: str) -> None:
        """The run ended before the episode did."""
        if not self.done:
            o = self.outcome
            o.ended, o.end_time_s, o.steps = reason, self.step * self.period_s, self.step
            o.final_pose = self.pose.copy()
            self.done = True


class _PolicySession(RecordSession):
    """The record session with a closed-loop ``run``: commands come from the controller."""

    def __init__(self, transport: Transport, controller: EpisodeController, robot: RobotProfile,
                 writer: RecordingWriter, config: SessionConfig, observers, progress) -> None:
        ctl = controller
        t = np.arange(ctl.episode_steps + 1) * ctl.period_s  # for the progress bar's total
        # the handshake refuses a controller announcing a lower wheel limit than the profile's
        super().__init__(transport, t, np.zeros((len(t), 3)), writer, config, observers,
                         progress, peak_wheel_rpm=robot.wheel_speed_max_rpm)
        self.ctl = controller
        self.robot = robot
        self._tlm_wrap = 0
        self._tlm_last: int | None = None

    def handle(self, msg, now: float) -> None:
        super().handle(msg, now)
        if isinstance(msg, Telemetry) and self.t0 is not None:
            if self._tlm_last is not None and msg.time_us < self._tlm_last - (1 << 31):
                self._tlm_wrap += 1 << 32
            self._tlm_last = msg.time_us
            self.ctl.on_telemetry((msg.time_us + self._tlm_wrap) * 1e-6, msg.wheel_rpm)

    def _send_command(self, command: np.ndarray) -> float:
        # as the record session sends a profile's command (its checks come first)
        self.robot.check_commands(command, "policy command")
        self.tr.check_commands(command[None], "policy command")
        return super()._send_command(command)

    def run(self) -> None:
        from .protocol import Ping

        self.handshake()
        if self.telemetry_rate_hz <= 0:
            raise ConfigError(f"{self.tr.port}: the controller sends no telemetry; a policy "
                              "needs measured wheel speeds to act on")
        ping_period = (1.0 / self.config.ping_rate_hz
                       if self.config.ping_rate_hz > 0 and self.tr.acknowledges else math.inf)
        self.t0 = time.perf_counter()
        # the first observation: the latest state of the robot at rest (recorded from t0)
        self.pump_until(self.t0 + min(0.05, 5.0 / self.telemetry_rate_hz))
        start = time.perf_counter()
        self.ctl.begin()
        next_ping = start
        k = 0
        while True:
            self.pump_until(start + k * self.ctl.period_s)
            if self.pump.error is not None:
                raise MecanumHILError(f"observer failed: {type(self.pump.error).__name__}: "
                                      f"{self.pump.error}") from self.pump.error
            if self.pump.stop_requested:
                raise ObserverStopError()
            command = self.ctl.next_command()
            if command is None:
                return
            self._send_command(command)
            now = time.perf_counter()
            if now >= next_ping:
                self._ping_token = (self._ping_token + 1) & 0xFFFFFFFF
                if self.send(Ping(self._ping_token)) is not None:
                    self._pings[self._ping_token] = time.perf_counter()
                next_ping += ping_period
            k += 1

    def wait_for_rest(self, timeout_s: float) -> bool:
        """Keep receiving until every measured wheel speed is below :data:`REST_RPM`."""
        end = time.perf_counter() + timeout_s
        while time.perf_counter() < end:
            self.pump_until(min(end, time.perf_counter() + 0.05))
            if np.abs(self.ctl.wheels).max() < REST_RPM:
                return True
        return False


def run_policy_episode(transport: Transport, controller: EpisodeController, out: str | Path,
                       robot: RobotProfile, *, config: SessionConfig | None = None,
                       observers: Sequence[Any] = (), metadata: dict[str, Any] | None = None,
                       progress: Callable[[float, float, dict[str, Any]], None] | None = None,
                       rest_timeout_s: float = 3.0) -> RecordResult:
    """One episode over ``transport`` in real time, recorded to ``out``; STOP at every way out.

    The ways out and exit codes are ``record``'s (:mod:`mecanum_hil.link.session`). After a
    completed episode the robot is brought to rest (STOP, then telemetry until the wheels
    settle, at most ``rest_timeout_s``). The sidecar gets ``policy_episode``
    (:meth:`EpisodeOutcome.as_dict`, with the odometry path).
    """
    config = config or SessionConfig()
    meta = _start_metadata(transport, robot, metadata, source="mecanum-hil record --policy")
    writer = RecordingWriter(out, EXTRA_COLUMNS, meta, fsync=True)
    sess = _PolicySession(transport, controller, robot, writer, config, observers, progress)
    return stream_stop_close(
        sess, transport, writer, out, config,
        settle=lambda: sess.wait_for_rest(rest_timeout_s), cut_short=controller.cut_short,
        end_extra=lambda: {"policy_episode": controller.outcome.as_dict()})


@dataclass(frozen=True)
class PolicyRun:
    """Episodes of a policy on the robot: the per-episode results and the summary.

    Attributes
    ----------
    results : list of RecordResult
        One per episode run (the last may have been cut short).
    outcomes : list of EpisodeOutcome
    summary : dict
        What ``summary.json`` holds: ``evaluate``'s figures over the completed episodes, plus
        ``end_reason`` and ``exit_code`` of the run.
    exit_code : int
    """

    results: list
    outcomes: list
    summary: dict
    exit_code: int


def summary_of(policy, robot: RobotProfile, outcomes: Sequence[EpisodeOutcome],
               extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """``evaluate``'s figures over the episodes that ran to their end."""
    from ..policy.evaluate import summarise

    done = [o for o in outcomes if o.ended in ("success", "failure", "truncated")]
    ev = summarise(policy.task, robot, [o.success for o in done],
                   [o.episode_return for o in done], [o.end_time_s for o in done],
                   np.array([o.final_pose for o in done]).reshape(-1, 3),
                   np.array([o.task_state for o in done]).reshape(
                       len(done), len(policy.task.state_names)))
    return {**ev.as_dict(), "control_period_s": policy.control_period_s, **(extra or {})}


@dataclass(frozen=True)
class _EpisodeRun:
    """What every episode of a ``record --policy`` run shares (see
    :func:`run_policy_episodes`)."""

    transport: Transport
    policy: Any
    robot: RobotProfile
    calibration: Calibration
    seed: int
    out_dir: Path
    config: SessionConfig
    make_observers: Callable[[Path], Sequence[Any]] | None
    close_observers: Callable[[Sequence[Any]], None] | None
    metadata: dict[str, Any] | None
    progress: Callable[[int, float, float, dict], None] | None
    echo: Callable[[str], None] | None


def _run_episode(run: _EpisodeRun, i: int) -> tuple[RecordResult, EpisodeOutcome]:
    """Episode ``i``: its draw, observers and recording; STOP at its every way out."""
    from ..policy.evaluate import episode_draw
    from ..policy.policies import task_name

    policy = run.policy
    ctl = EpisodeController(policy, run.robot, run.calibration,
                            episode_draw(policy.task, run.seed, i))
    out = run.out_dir / f"episode_{i:03d}.csv"
    observers = list(run.make_observers(out)) if run.make_observers else []
    meta = {**(run.metadata or {}), "episode": i, "seed": run.seed,
            "task": task_name(policy.task), "command_rate_hz": 1.0 / ctl.period_s}
    progress = run.progress
    prog = None if progress is None else (
        lambda el, tot, counts: progress(i, el, tot, counts))
    try:
        res = run_policy_episode(run.transport, ctl, out, run.robot, config=run.config,
                                 observers=observers, metadata=meta, progress=prog)
    finally:
        if run.close_observers is not None:
            run.close_observers(observers)
    return res, ctl.outcome


def _echo_episode(run: _EpisodeRun, i: int, res: RecordResult, o: EpisodeOutcome) -> None:
    """One line on how episode ``i`` went, when the run echoes."""
    if run.echo is not None:
        run.echo(f"episode {i}: {o.ended} after {o.end_time_s:.2f} s, return "
                 f"{o.episode_return:+.3f} ({res.reason}, {res.path.name})")


def _end_after_episode(res: RecordResult) -> tuple[str, int] | None:
    """``(reason, exit_code)`` when no further episode may run after ``res``, else None."""
    if res.exit_code != 0:
        return res.reason, res.exit_code
    if res.signal_at_end is not None:  # the episode ended whole; no further one
        reason = signal_end_reason(res.signal_at_end)
        return reason, EXIT_CODES[reason]
    return None


def _write_summary(out_dir: Path, summary: dict[str, Any]) -> None:
    """``summary.json``, atomically: a reader never sees half of it."""
    path = out_dir / "summary.json"
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
        os.replace(tmp, path)
    except OSError as err:
        raise ConfigError(f"{out_dir}: cannot write summary.json: "
                          f"{err.strerror or err}") from err


def _run_episodes(run: _EpisodeRun, episodes: int, guard: SignalGuard,
                  results: list, outcomes: list) -> tuple[str, int]:
    """Run episodes until ``episodes`` ran or one did not complete; the run's reason and
    exit code. A signal kept by ``guard`` between episodes ends the run before the next."""
    for i in range(episodes):
        if guard.pending is not None:
            kept = signal_end_reason(guard.pending)
            return kept, EXIT_CODES[kept]
        res, outcome = _run_episode(run, i)
        results.append(res)
        outcomes.append(outcome)
        _echo_episode(run, i, res, outcome)
        if (end := _end_after_episode(res)) is not None:
            return end
    return "completed", 0


def run_policy_episodes(transport: Transport, policy, robot: RobotProfile,
                        calibration: Calibration, *, episodes: int, seed: int,
                        out_dir: str | Path, config: SessionConfig | None = None,
                        make_observers: Callable[[Path], Sequence[Any]] | None = None,
                        close_observers: Callable[[Sequence[Any]], None] | None = None,
                        metadata: dict[str, Any] | None = None,
                        progress: Callable[[int, float, float, dict], None] | None = None,
                        echo: Callable[[str], None] | None = None) -> PolicyRun:
    """``record --policy``: ``episodes`` episodes, one recording each, then ``summary.json``.

    Episode ``i`` draws its target or strike from ``seed + i`` as ``evaluate`` does. The run
    stops at the first episode that does not complete (its exit code is the run's); STOP has
    then been sent. ``make_observers(out_csv)`` builds an episode's observers (shadow mode)
    and ``close_observers`` closes them.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{out_dir}: cannot create: {err.strerror or err}") from err
    config = config or SessionConfig()
    run = _EpisodeRun(transport, policy, robot, calibration, seed, out_dir, config,
                      make_observers, close_observers, metadata, progress, echo)
    results: list[RecordResult] = []
    outcomes: list[EpisodeOutcome] = []
    # between episodes a signal is kept (observers closed, the episode counted, the summary
    # written whole) and ends the run at the next check; inside an episode the episode's own
    # guard ends it with STOP (it takes over this guard's handlers)
    guard = SignalGuard(config.handle_sigterm)
    guard.defer()
    try:
        try:
            reason, exit_code = _run_episodes(run, episodes, guard, results, outcomes)
        except (KeyboardInterrupt, SessionTerminated) as exc:  # raised between episodes
            reason = signal_reason(exc)
            exit_code = EXIT_CODES[reason]
        summary = summary_of(policy, robot, outcomes, {
            "seed": seed, "episodes_requested": episodes, "end_reason": reason,
            "exit_code": exit_code, "policy": policy.describe(),
            "recordings": [r.path.name for r in results]})
        _write_summary(out_dir, summary)
    finally:
        guard.restore()
    return PolicyRun(results, outcomes, summary, exit_code)


# -- the same loop in simulated time ----------------------------------------------------------
@dataclass(frozen=True)
class LockstepEpisode:
    """One closed-loop episode against the simulated controller in simulated time.

    Attributes
    ----------
    outcome : EpisodeOutcome
        As on the robot (from odometry).
    true_path : ndarray, shape (T, 3)
        The simulated robot's true pose at every control step (it starts at the default pose,
        the tasks' start pose).
    """

    outcome: EpisodeOutcome
    true_path: np.ndarray


class _LockstepLink:
    """``sim-robot``'s firmware and the serial framing to it, advanced in host time.

    Parameters
    ----------
    ctl : EpisodeController
        Gets every telemetry sample as it reaches the host.
    model : ControllerModel
        The simulated robot.
    telemetry_rate_hz : float
        The firmware's telemetry rate [Hz].
    link_delay_s : float
        Time a message takes either way [s].
    """

    def __init__(self, ctl: EpisodeController, model, telemetry_rate_hz: float,
                 link_delay_s: float) -> None:
        from .lockstep import FramedLoopback, VirtualClock
        from .simulated import SimulatedController

        self.ctl, self.model = ctl, model
        self.clock = VirtualClock()
        self.to_ctrl, self.to_host = FramedLoopback(), FramedLoopback()
        self.fw = SimulatedController(self.to_host, model, telemetry_rate_hz, clock=self.clock)
        self.delay_s = float(link_delay_s)
        self.to_ctrl.send(Hello(PROTOCOL_VERSION))
        self.fw.handle(self.to_ctrl.delivered.popleft())
        self.to_host.delivered.clear()
        self.to_ctrl.restart_sequences()
        self.dt_s, self.ticks_per_sample = model.dt_s, self.fw.telemetry_ticks
        self.tick = 0
        self.pending: list[tuple[float, Any]] = []  # (controller arrival time [s], message)

    def send(self, msg, at_s: float) -> None:
        """Send ``msg`` at host time ``at_s`` [s]: it reaches the controller a delay later."""
        self.to_ctrl.send(msg)
        self.pending.append((at_s + self.delay_s, self.to_ctrl.delivered.popleft()))

    def advance(self, until_s: float) -> None:
        """Controller events up to host time ``until_s`` [s]: command arrivals, telemetry
        ticks (a sample reaches the host a delay after it is sent)."""
        fw, to_host = self.fw, self.to_host
        while True:
            c_tlm = self.tick * self.dt_s
            if self.pending and self.pending[0][0] <= c_tlm:
                self.clock.now_s = self.pending[0][0]
                fw.handle(self.pending.pop(0)[1])
                continue
            if c_tlm + self.delay_s > until_s:
                return
            self.clock.now_s = c_tlm
            fw.check_watchdog()
            fw.send_telemetry(self.tick)
            for msg in list(to_host.delivered):
                if isinstance(msg, Telemetry):
                    self.ctl.on_telemetry(msg.time_us * 1e-6, msg.wheel_rpm)
            to_host.delivered.clear()
            self.tick += self.ticks_per_sample


def run_policy_lockstep(policy, robot: RobotProfile, task_state: np.ndarray, *,
                        calibration: Calibration, truth: Calibration | None = None,
                        sim_effects=None, telemetry_rate_hz: float = 100.0,
                        internal_rate_hz: float = 1000.0,
                        link_delay_s: float = 0.00015) -> LockstepEpisode:
    """One episode of ``policy`` against ``sim-robot``'s firmware and robot on a virtual clock.

    The host side is :class:`EpisodeController` as in :func:`run_policy_episode`: it acts at
    the control period on the telemetry received by then (sent by the controller every
    telemetry period, reaching the host ``link_delay_s`` later), every message framed and
    decoded as on the serial wire. The robot starts at rest; the truth is ``truth`` (default:
    the paper's coefficients) with ``sim_effects`` (an effects file's content: the hidden
    effects, noise, faults).

    Parameters
    ----------
    calibration : Calibration
        What the host believes (its slip efficiencies for odometry), as for the robot.
    """
    from .effects_file import SimEffects
    from .simulated import ControllerModel

    if not (internal_rate_hz > 0 and telemetry_rate_hz > 0 and link_delay_s >= 0):
        raise ConfigError("rates must be positive and the link delay >= 0")
    ctl = EpisodeController(policy, robot, calibration, task_state)
    model = ControllerModel(truth or Calibration(), robot, sim_effects or SimEffects(),
                            rate_hz=internal_rate_hz, lookahead=20)
    link = _LockstepLink(ctl, model, telemetry_rate_hz, link_delay_s)
    true_path = []
    link.advance(0.0)
    ctl.begin()
    k = 0
    while True:
        h = k * ctl.period_s
        link.advance(h)
        # the simulated robot starts at the default pose, the tasks' start pose
        true_path.append(model.pose(max(round(h / link.dt_s), model.anchor)))
        command = ctl.next_command()
        if command is None:
            break
        robot.check_commands(command, "policy command")
        link.send(link.to_ctrl.wire_command(*command), h)
        k += 1
    link.send(Stop(), k * ctl.period_s)
    link.advance(k * ctl.period_s + 2 * link.delay_s)
    return LockstepEpisode(ctl.outcome, np.array(true_path))
