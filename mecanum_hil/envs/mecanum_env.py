"""``MecanumHIL-v0``: one Mecanum robot on a fitted model, reaching a target pose."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..model import Calibration, RobotProfile
from ..model.stepper import DEFAULT_MAX_SUBSTEP_S
from ._core import OBS_SIZE, BatchCore
from .task import DodgeTask, ReachTask

_ONE = np.zeros(1, dtype=np.int64)


def observation_space() -> spaces.Box:
    """The observation box (layout: ``mecanum_hil.envs.observation_layout(task)``)."""
    low = np.full(OBS_SIZE, -np.inf)
    high = np.full(OBS_SIZE, np.inf)
    low[[2, 12]] = -180.0
    high[[2, 12]] = 180.0
    return spaces.Box(low, high, dtype=np.float64)


class MecanumHILEnv(gym.Env):
    """A Mecanum robot on a fitted wheel model (with its effects), reaching a target pose.

    Action ``(n [rpm], omega [deg/s], theta [deg])`` in the box ``[0, wheel_speed_max_rpm] x
    [-omega_max_dps, omega_max_dps] x [-180, 180]`` of the robot profile, held for one control
    period; actions outside the box are clipped and a pair ``(n, omega)`` whose fastest wheel
    target ``|n| + k |omega| / 6`` exceeds ``wheel_speed_max_rpm`` is scaled down to the limit
    (``info["command"]`` is what was sent). Observation: 13 float64 values, see
    ``mecanum_hil.envs.observation_layout(task)``. Tasks and reward:
    :mod:`mecanum_hil.envs.task`.

    Parameters
    ----------
    calibration : Calibration, str or Path
        Fitted calibration (shipped name such as ``"paper"`` or a TOML path), with any effects
        ``diagnose`` added.
    robot : RobotProfile, str or Path
        Robot profile (geometry and wheel speed limit).
    control_period_s : float
        How long each action is held [s] (a 50 Hz command stream by default).
    task : ReachTask, DodgeTask, "reach" or "dodge", optional
        The task and its parameters (default: reach with :class:`ReachTask`'s defaults).
    randomize : bool
        Draw ``A, B, C`` within the calibration's 95 % intervals at each reset
        (:mod:`mecanum_hil.envs.randomisation`).
    coefficient_ranges : Mapping[str, (float, float)], optional
        Intervals replacing or adding to the calibration's ``[ci95]`` for randomisation.
    max_substep_s : float
        Longest sub-step of the simulator when saturation or a rate limit is present [s].
    render_mode : None
        No rendering (plot recorded poses instead, see ``examples/``).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, calibration: Calibration | str | Path = "paper",
                 robot: RobotProfile | str | Path = "tdam-stm", *,
                 control_period_s: float = 0.02,
                 task: ReachTask | DodgeTask | str | None = None,
                 randomize: bool = False,
                 coefficient_ranges: Mapping[str, tuple[float, float]] | None = None,
                 max_substep_s: float = DEFAULT_MAX_SUBSTEP_S,
                 render_mode: str | None = None) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} is not supported (none is)")
        self.render_mode = None
        self.core = BatchCore(1, calibration, robot, control_period_s=control_period_s,
                              task=task, randomize=randomize,
                              coefficient_ranges=coefficient_ranges, max_substep_s=max_substep_s)
        self.action_space = spaces.Box(self.core.action_low, self.core.action_high,
                                       dtype=np.float64)
        self.observation_space = observation_space()
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.core.control_period_s}

    @property
    def pose(self) -> np.ndarray:
        """Current pose ``(X [m], Y [m], phi [deg])`` with phi not wrapped (a copy)."""
        return self.core.stepper.pose[0].copy()

    @property
    def task_state(self) -> np.ndarray:
        """What the reset drew for the episode (a copy): the target pose ``(X [m], Y [m],
        phi [deg])`` for reach, ``(strike direction [deg], deadline [s])`` for dodge."""
        return self.core.task_state[0].copy()

    @property
    def coefficients(self) -> np.ndarray:
        """Coefficients ``(A, B, C)`` of the episode (drawn when randomising) (a copy)."""
        return self.core.stepper.coefficients[0].copy()

    def _info(self, success: bool = False) -> dict[str, Any]:
        return {"command": self.core.commands[0].copy(), "pose": self.pose,
                "task_state": self.task_state, "coefficients": self.coefficients,
                "success": success}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode: robot at the task's start pose at rest, a new target drawn."""
        super().reset(seed=seed)
        obs = self.core.reset_robots(_ONE, [self.np_random])
        return obs[0], self._info()

    def step(self, action):
        """Hold ``action`` for one control period."""
        obs, reward, terminated, truncated = self.core.step(
            np.asarray(action, dtype=float).reshape(1, 3))
        return (obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]),
                self._info(bool(self.core.success[0])))
