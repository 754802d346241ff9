"""Runs with an injected fault, generated with the model itself (tests, bench, demo).

A run is simulated in two pieces: before the fault with the nominal calibration, after it with
the fault's effects, the second piece continuing exactly from the first one's final wheel
state, pose and command (``initial_state``, ``initial_pose``, ``initial_command``). Gaussian
measurement noise is then added to the channels "measured".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..io.recording import Recording
from ..model.calibration import Calibration, Effects
from ..model.robot import RobotProfile
from ..model.simulate import simulate


@dataclass(frozen=True)
class Fault:
    """A change of the robot at ``t_s``, expressed as the effects the robot has from then on.

    Attributes
    ----------
    name : str
        ``gain-drop``, ``stall``, ``dead-time`` ...
    t_s : float
        When the fault appears [s].
    effects : Effects
        The robot's effects after the fault (the calibration's effects before it).
    channels : tuple of str
        Channels the fault acts on directly (the ones that should alarm).
    """

    name: str
    t_s: float
    effects: Effects
    channels: tuple[str, ...]


def make_fault(kind: str, t_s: float, base: Effects = Effects(), wheel: int = 2,
               gain_drop: float = 0.2, dead_time_s: float = 0.05) -> Fault:
    """One of the standard faults on top of the nominal effects ``base``.

    Parameters
    ----------
    kind : str
        ``gain-drop`` (wheel ``wheel``'s gain falls by ``gain_drop``), ``stall`` (the wheel's
        drive gives up: its target becomes 0 and it coasts to a stop through the wheel dynamics)
        or ``dead-time`` (a transport delay of ``dead_time_s`` appears on every wheel).
    t_s : float
        Time of the fault [s].
    base : Effects
        Effects of the nominal robot.
    wheel : int
        Wheel 1..4 for the per-wheel faults.
    """
    if wheel not in (1, 2, 3, 4):
        raise ConfigError(f"wheel must be 1..4, got {wheel}")
    gains = list(base.gains)
    if kind == "gain-drop":
        gains[wheel - 1] *= 1.0 - gain_drop
        return Fault(kind, t_s, replace(base, gains=tuple(gains)), (f"wheel{wheel}_rpm",))
    if kind == "stall":
        gains[wheel - 1] = 0.0
        return Fault(kind, t_s, replace(base, gains=tuple(gains)), (f"wheel{wheel}_rpm",))
    if kind == "dead-time":
        return Fault(kind, t_s, replace(base, dead_time_s=base.dead_time_s + dead_time_s),
                     tuple(f"wheel{i}_rpm" for i in range(1, 5)))
    raise ConfigError(f"unknown fault '{kind}': use gain-drop, stall or dead-time")


#: The fault kinds of :func:`make_fault`.
FAULT_KINDS = ("gain-drop", "stall", "dead-time")


def driving_commands(duration_s: float, rate_hz: float, ramp_in_s: float = 2.0):
    """A drive that keeps every wheel busy: speed, direction and turn all vary smoothly.

    Starts at rest and fades in over ``ramp_in_s``; after that every wheel target of the
    paper's robot stays between ~12 and ~100 rpm, so a 20 % gain drop of any wheel at any time
    is a shift of at least ~2.4 rpm. Returns ``(t_s (T,), commands (T, 3))``.
    """
    n = round(duration_s * rate_hz)
    t = np.arange(n + 1) / float(rate_hz)
    fade = np.clip(t / ramp_in_s, 0.0, 1.0) if ramp_in_s > 0 else np.ones_like(t)
    speed = fade * (65.0 + 20.0 * np.sin(2 * np.pi * 0.23 * t)
                    + 8.0 * np.sin(2 * np.pi * 0.71 * t + 1.0))
    theta = 90.0 + 20.0 * np.sin(2 * np.pi * 0.11 * t)
    omega = fade * 8.0 * np.sin(2 * np.pi * 0.17 * t + 0.5)
    return t, np.column_stack([speed, omega, theta])


def simulate_run(t_s, commands, calibration: Calibration, fault: Fault | None = None, *,
                 robot: RobotProfile | None = None, noise_rpm: float = 1.0,
                 pose_noise_m: float | None = None, pose_noise_deg: float = 0.2,
                 seed: int = 0) -> Recording:
    """A recording of the model robot, with an optional fault and measurement noise.

    Parameters
    ----------
    t_s : array_like, shape (T,)
        Sample times [s].
    commands : array_like, shape (T, 3)
        Commands in force from each sample.
    calibration : Calibration
        The nominal robot.
    fault : Fault, optional
        Switched on at ``fault.t_s`` (the second piece starts at the first sample at or after
        it).
    robot : RobotProfile, optional
    noise_rpm : float
        Standard deviation of the wheel speed noise [rpm].
    pose_noise_m : float, optional
        Standard deviation of position noise [m]; ``None`` leaves the pose columns empty.
    pose_noise_deg : float
        Standard deviation of heading noise [deg] (with ``pose_noise_m``).
    seed : int
        Seed of the noise.
    """
    t = np.asarray(t_s, dtype=float)
    cmd = np.asarray(commands, dtype=float)
    robot = robot or RobotProfile()
    if fault is None or fault.t_s >= t[-1]:
        traj = simulate(cmd, t, calibration, robot)
        wheels, pose = traj.wheel_rpm[0], traj.pose[0]
    else:
        i = max(1, int(np.searchsorted(t, fault.t_s)))
        first = simulate(cmd[:i + 1], t[:i + 1], calibration, robot)
        second = simulate(cmd[i:], t[i:], replace(calibration, effects=fault.effects), robot,
                          initial_state=first.final_state, initial_pose=first.pose[0, -1],
                          initial_command=cmd[i - 1])
        wheels = np.concatenate([first.wheel_rpm[0, :i], second.wheel_rpm[0]])
        pose = np.concatenate([first.pose[0, :i], second.pose[0]])
    rng = np.random.default_rng(seed)
    wheels = wheels + rng.normal(0.0, noise_rpm, wheels.shape) if noise_rpm > 0 else wheels
    if pose_noise_m is None:
        pose = np.full_like(pose, np.nan)
    else:
        pose = pose + rng.normal(0.0, 1.0, pose.shape) * [pose_noise_m, pose_noise_m,
                                                          pose_noise_deg]
    meta: dict[str, Any] = {"source": "mecanum_hil.monitor.scenarios.simulate_run",
                            "calibration": calibration.source, "noise_rpm": noise_rpm,
                            "seed": seed}
    if fault is not None:
        meta["fault"] = {"name": fault.name, "t_s": fault.t_s,
                         "effects": fault.effects.active(), "channels": list(fault.channels)}
    return Recording(t.copy(), cmd.copy(), wheels, pose, {}, meta)


@dataclass(frozen=True)
class FaultDemo:
    """What :func:`shadow_fault_demo` produced.

    Attributes
    ----------
    alarms : tuple of Alarm
    fault : Fault
    recording, event_log, plot : Path
        Files written.
    """

    alarms: tuple
    fault: Fault
    recording: Path
    event_log: Path
    plot: Path

    @property
    def detection_delay_s(self) -> float | None:
        """First alarm on a channel the fault acts on, minus the fault time [s]."""
        hits = [a.t_s for a in self.alarms if a.channel in self.fault.channels]
        return (min(hits) - self.fault.t_s) if hits else None


def shadow_fault_demo(out_dir: str | Path, kind: str = "gain-drop", *, wheel: int = 2,
                      fault_t_s: float = 12.0, duration_s: float = 20.0, rate_hz: float = 100.0,
                      calibration: Calibration | None = None, seed: int = 0,
                      echo: Callable[[str], None] = print) -> FaultDemo:
    """A run with an injected fault, replayed through the shadow monitor, which flags it.

    Writes ``shadow-<kind>.csv`` (the noisy run), ``shadow-<kind>.shadow.jsonl`` (the event
    log) and ``shadow-<kind>.png`` (measured against the model, alarms marked) into
    ``out_dir``; returns the alarms and paths.
    """
    from ..io.recording import write_recording
    from ..model import load_calibration
    from ..prediction import predict
    from .core import ShadowConfig, replay
    from .eventlog import EventLog, event_log_path
    from .plot import plot_shadow

    cal = calibration or load_calibration()
    out = Path(out_dir)
    fault = make_fault(kind, fault_t_s, cal.effects, wheel=wheel)
    t, cmd = driving_commands(duration_s, rate_hz)
    rec = simulate_run(t, cmd, cal, fault, noise_rpm=1.0, seed=seed)
    path = write_recording(rec, out / f"shadow-{kind}.csv")
    log_path = event_log_path(path)
    config = ShadowConfig()
    with EventLog(log_path, cal, config, {"mode": "replay", "recording": str(path)}) as log:
        result = replay(rec, cal, config=config, listeners=[log])
    model = predict(rec, cal, RobotProfile())
    png = plot_shadow(rec, model, result.alarms, out / f"shadow-{kind}.png",
                      title=f"shadow mode: {kind} on wheel {wheel} at t = {fault_t_s:g} s",
                      fault_t_s=fault_t_s)
    demo = FaultDemo(result.alarms, fault, path, log_path, png)
    delay = demo.detection_delay_s
    first = result.alarms[0] if result.alarms else None
    echo(f"   shadow: {kind} injected at {fault_t_s:g} s -> "
         + (f"flagged {first.channel} at {first.t_s:.2f} s (delay {delay * 1e3:.0f} ms, "
            f"residual {first.residual:+.1f} {first.unit})" if first and delay is not None
            else "NOT flagged")
         + f" -> {path.name}, {log_path.name}, {png.name}")
    return demo
