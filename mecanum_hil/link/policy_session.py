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
from .protocol import PROTOCOL_VERSION, Telemetry
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
    from ..policy.evaluate import episode_draw
    from ..policy.policies import task_name

    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"{out_dir}: cannot create: {err.strerror or err}") from err
    config = config or SessionConfig()
    results, outcomes = [], []
    exit_code, reason = 0, "completed"
    # between episodes a signal is kept (observers closed, the episode counted, the summary
    # written whole) and ends the run at the next check; inside an episode the episode's own
    # guard ends it with STOP (it takes over this guard's handlers)
    guard = SignalGuard(config.handle_sigterm)
    guard.defer()

    def signalled() -> str | None:
        if guard.pending is None:
            return None
        return signal_end_reason(guard.pending)

    try:
        try:
            for i in range(episodes):
                if (kept := signalled()) is not None:
                    exit_code, reason = EXIT_CODES[kept], kept
                    break
                ctl = EpisodeController(policy, robot, calibration,
                                        episode_draw(policy.task, seed, i))
                out = out_dir / f"episode_{i:03d}.csv"
                observers = list(make_observers(out)) if make_observers else []
                meta = {**(metadata or {}), "episode": i, "seed": seed,
                        "task": task_name(policy.task), "command_rate_hz": 1.0 / ctl.period_s}
                prog = None if progress is None else (
                    lambda el, tot, counts, i=i: progress(i, el, tot, counts))
                try:
                    res = run_policy_episode(transport, ctl, out, robot, config=config,
                                             observers=observers, metadata=meta, progress=prog)
                finally:
                    if close_observers is not None:
                        close_observers(observers)
                results.append(res)
                outcomes.append(ctl.outcome)
                if echo is not None:
                    o = ctl.outcome
                    echo(f"episode {i}: {o.ended} after {o.end_time_s:.2f} s, return "
                         f"{o.episode_return:+.3f} ({res.reason}, {out.name})")
                if res.exit_code != 0:
                    exit_code, reason = res.exit_code, res.reason
                    break
                if res.signal_at_end is not None:  # the episode ended whole; no further one
                    reason = signal_end_reason(res.signal_at_end)
                    exit_code = EXIT_CODES[reason]
                    break
        except (KeyboardInterrupt, SessionTerminated) as exc:  # raised between episodes
            reason = signal_reason(exc)
            exit_code = EXIT_CODES[reason]
        summary = summary_of(policy, robot, outcomes, {
            "seed": seed, "episodes_requested": episodes, "end_reason": reason,
            "exit_code": exit_code, "policy": policy.describe(),
            "recordings": [r.path.name for r in results]})
        path = out_dir / "summary.json"
        tmp = path.with_name(path.name + ".tmp")
        try:  # atomically: a reader never sees half of it
            tmp.write_text(json.dumps(summary, indent=2) + "\n")
            os.replace(tmp, path)
        except OSError as err:
            raise ConfigError(f"{out_dir}: cannot write summary.json: "
                              f"{err.strerror or err}") from err
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
    from .lockstep import FramedLoopback, VirtualClock
    from .protocol import Hello, Stop
    from .simulated import ControllerModel, SimulatedController

    if not (internal_rate_hz > 0 and telemetry_rate_hz > 0 and link_delay_s >= 0):
        raise ConfigError("rates must be positive and the link delay >= 0")
    ctl = EpisodeController(policy, robot, calibration, task_state)
    model = ControllerModel(truth or Calibration(), robot, sim_effects or SimEffects(),
                            rate_hz=internal_rate_hz, lookahead=20)
    clock = VirtualClock()
    to_ctrl, to_host = FramedLoopback(), FramedLoopback()
    fw = SimulatedController(to_host, model, telemetry_rate_hz, clock=clock)
    d = float(link_delay_s)
    to_ctrl.send(Hello(PROTOCOL_VERSION))
    fw.handle(to_ctrl.delivered.popleft())
    to_host.delivered.clear()
    to_ctrl.restart_sequences()
    dt, step = model.dt_s, fw.telemetry_ticks
    tick = 0
    pending: list[tuple[float, Any]] = []  # (controller arrival time, message)
    true_path = []

    def advance(until_s: float) -> None:
        # controller events up to host time until_s: command arrivals, telemetry ticks
        nonlocal tick
        while True:
            c_tlm = tick * dt
            if pending and pending[0][0] <= c_tlm:
                clock.now_s = pending[0][0]
                fw.handle(pending.pop(0)[1])
                continue
            if c_tlm + d > until_s:
                return
            clock.now_s = c_tlm
            fw.check_watchdog()
            fw.send_telemetry(tick)
            for msg in list(to_host.delivered):
                if isinstance(msg, Telemetry):
                    ctl.on_telemetry(msg.time_us * 1e-6, msg.wheel_rpm)
            to_host.delivered.clear()
            tick += step

    advance(0.0)
    ctl.begin()
    k = 0
    while True:
        h = k * ctl.period_s
        advance(h)
        # the simulated robot starts at the default pose, the tasks' start pose
        true_path.append(model.pose(max(round(h / dt), model.anchor)))
        command = ctl.next_command()
        if command is None:
            break
        robot.check_commands(command, "policy command")
        to_ctrl.send(to_ctrl.wire_command(*command))
        pending.append((h + d, to_ctrl.delivered.popleft()))
        k += 1
    to_ctrl.send(Stop())
    pending.append((k * ctl.period_s + d, to_ctrl.delivered.popleft()))
    advance(k * ctl.period_s + 2 * d)
    return LockstepEpisode(ctl.outcome, np.array(true_path))
