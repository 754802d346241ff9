"""The vectorised ``MecanumHIL-v0``: thousands of robots stepped in one compiled call."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..errors import ConfigError
from ..model import Calibration, RobotProfile
from ..model.stepper import DEFAULT_MAX_SUBSTEP_S
from ._core import BatchCore
from .mecanum_env import observation_space
from .task import DodgeTask, ReachTask


class MecanumHILVectorEnv(VectorEnv):
    """``num_envs`` robots of :class:`~mecanum_hil.envs.MecanumHILEnv` in one batch.

    Equal, step for step, to ``gymnasium.vector.SyncVectorEnv`` over ``num_envs`` single
    environments with the same arguments and seeds (robot ``i`` is seeded with ``seed + i``, as
    ``SyncVectorEnv`` seeds its sub-environments), with next-step autoreset: the step after a
    robot's episode ended resets it, returns its first observation, reward 0 and ignores its
    action. ``infos`` is empty: per-robot details would cost more than the step itself; the
    applied commands, poses and episode draws are the attributes ``commands``, ``pose``,
    ``task_state``.

    Parameters
    ----------
    num_envs : int
        Number of robots.
    calibration, robot, control_period_s, task, randomize, coefficient_ranges, max_substep_s
        As for :class:`~mecanum_hil.envs.MecanumHILEnv`; with ``randomize`` every robot draws
        its own coefficients at each of its resets.
    num_threads : int, optional
        Threads of the compiled step (default 1, see
        :class:`~mecanum_hil.model.stepper.BatchStepper`; ``None`` for numba's default).
    """

    metadata: ClassVar[dict[str, Any]] = {
        "render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, calibration: Calibration | str | Path = "paper",
                 robot: RobotProfile | str | Path = "tdam-stm", *,
                 control_period_s: float = 0.02,
                 task: ReachTask | DodgeTask | str | None = None,
                 randomize: bool = False,
                 coefficient_ranges: Mapping[str, tuple[float, float]] | None = None,
                 max_substep_s: float = DEFAULT_MAX_SUBSTEP_S, num_threads: int | None = 1,
                 render_mode: str | None = None) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode {render_mode!r} is not supported (none is)")
        if int(num_envs) < 1:
            raise ConfigError(f"num_envs must be at least 1, got {num_envs!r}")
        self.num_envs = int(num_envs)
        self.render_mode = None
        self.core = BatchCore(self.num_envs, calibration, robot,
                              control_period_s=control_period_s, task=task, randomize=randomize,
                              coefficient_ranges=coefficient_ranges, max_substep_s=max_substep_s,
                              num_threads=num_threads)
        self.single_action_space = spaces.Box(self.core.action_low, self.core.action_high,
                                              dtype=np.float64)
        self.single_observation_space = observation_space()
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.core.control_period_s}
        self._rngs: list[np.random.Generator] | None = None
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._all = np.arange(self.num_envs)

    @property
    def commands(self) -> np.ndarray:
        """Commands sent at the last step, after limiting (N, 3)."""
        return self.core.commands

    @property
    def pose(self) -> np.ndarray:
        """Poses (N, 3) ``(X [m], Y [m], phi [deg])``, phi not wrapped (live array)."""
        return self.core.stepper.pose

    @property
    def task_state(self) -> np.ndarray:
        """What the resets drew for the current episodes, (N, W) (live array)."""
        return self.core.task_state

    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None):
        """Reset every robot; ``seed`` an int (robot i gets ``seed + i``) or one per robot."""
        if seed is None:
            if self._rngs is None:
                root = np.random.SeedSequence()
                self._rngs = [np.random.Generator(np.random.PCG64(s))
                              for s in root.spawn(self.num_envs)]
        else:
            seeds = ([seed + i for i in range(self.num_envs)] if isinstance(seed, int)
                     else list(seed))
            if len(seeds) != self.num_envs:
                raise ConfigError(f"{len(seeds)} seeds for {self.num_envs} robots")
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        obs = self.core.reset_robots(self._all, self._rngs)
        self._autoreset[:] = False
        return obs, {}

    def step(self, actions):
        """Hold one action per robot for one control period (next-step autoreset)."""
        if self._rngs is None:
            raise ConfigError("call reset() before step()")
        obs, reward, terminated, truncated = self.core.step(actions)
        if self._autoreset.any():
            idx = np.flatnonzero(self._autoreset)
            obs[idx] = self.core.reset_robots(idx, [self._rngs[i] for i in idx])
            reward[idx] = 0.0
            terminated[idx] = False
            truncated[idx] = False
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, {}
