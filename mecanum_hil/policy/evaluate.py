"""Evaluating policies in simulation: success rate, return, time to target, margin.

Episode ``i`` of an evaluation with seed ``S`` draws its target (reach) or strike (dodge) from
the generator ``gymnasium.utils.seeding.np_random(S + i)`` exactly as the vector environment's
robot ``i`` does after ``reset(seed=S)``; ``record --policy`` draws its episodes the same way
(:func:`episode_draw`), so simulation and robot see the same targets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..model import Calibration, RobotProfile


def episode_draw(task, seed: int, episode: int) -> np.ndarray:
    """What episode ``episode`` of seed ``seed`` draws: the target ``(X [m], Y [m], phi [deg])``
    or the strike ``(direction [deg], deadline [s])``, relative to the task's start pose."""
    from gymnasium.utils import seeding

    rng, _ = seeding.np_random(int(seed) + int(episode))
    return task.draw(rng)


def dodge_clearance_m(pose: np.ndarray, task_state: np.ndarray, task, robot: RobotProfile
                      ) -> np.ndarray:
    """Clearance of the body from the line of attack beyond the margin [m] (> 0: clear).

    Parameters
    ----------
    pose : (N, 3) ``(X [m], Y [m], phi [deg])``;  task_state : (N, 2) strike direction [deg],
    deadline [s].
    """
    beta = np.radians(task_state[:, 0])
    x0, y0, _ = task.start_pose
    offset = -np.sin(beta) * (pose[:, 0] - x0) + np.cos(beta) * (pose[:, 1] - y0)
    rel = np.radians(pose[:, 2]) - beta
    half = (robot.body_length_m / 2 * np.abs(np.sin(rel))
            + robot.body_width_m / 2 * np.abs(np.cos(rel)))
    return np.abs(offset) - half - task.margin_m


@dataclass(frozen=True)
class Evaluation:
    """Figures of a set of episodes (the same keys as ``record --policy``'s ``summary.json``).

    Attributes
    ----------
    task : str
        ``reach`` or ``dodge``.
    episodes : int
    success_rate : float
        Share of episodes that succeeded [-].
    mean_return : float
    time_to_target_s : float
        Reach: mean time to success over the successful episodes [s] (NaN if none).
    margin_m : float
        Dodge: mean clearance beyond the margin at the deadline [m] (> 0 clear).
    success, returns, end_time_s : ndarray
        Per episode.
    paths : list of ndarray
        Pose sequences ``(T, 3)`` of the first episodes (when asked for).
    task_states : ndarray
        Per episode draw.
    """

    task: str
    episodes: int
    success_rate: float
    mean_return: float
    time_to_target_s: float
    margin_m: float
    success: np.ndarray
    returns: np.ndarray
    end_time_s: np.ndarray
    task_states: np.ndarray
    paths: list = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """The summary (JSON-ready)."""
        def num(v):
            return None if not np.isfinite(v) else float(v)

        return {"task": self.task, "episodes": self.episodes,
                "success_rate": float(self.success_rate), "mean_return": float(self.mean_return),
                "time_to_target_s": num(self.time_to_target_s), "margin_m": num(self.margin_m),
                "successes": int(self.success.sum())}


def summarise(task, robot: RobotProfile, success, returns, end_time_s, final_pose,
              task_states, paths=()) -> Evaluation:
    """Figures from per-episode outcomes (simulation or robot alike)."""
    from .policies import task_name

    success = np.asarray(success, dtype=bool)
    returns = np.asarray(returns, dtype=float)
    end_time_s = np.asarray(end_time_s, dtype=float)
    task_states = np.atleast_2d(np.asarray(task_states, dtype=float))
    name = task_name(task)
    ttt = float(end_time_s[success].mean()) if name == "reach" and success.any() else np.nan
    margin = np.nan
    if name == "dodge" and len(success):
        margin = float(dodge_clearance_m(np.atleast_2d(final_pose), task_states, task,
                                         robot).mean())
    return Evaluation(name, len(success), float(success.mean()) if len(success) else 0.0,
                      float(returns.mean()) if len(returns) else 0.0, ttt, margin, success,
                      returns, end_time_s, task_states, list(paths))


def rollout(envs, act: Callable[[np.ndarray], np.ndarray], seeds, keep_paths: int = 0):
    """Run one episode on every robot of a vector environment.

    Returns per robot: returns, success, end step, final pose, task draw, and the paths of the
    first ``keep_paths`` robots. Robots whose episode ended keep being stepped (autoreset) until
    all ended; their later rewards are ignored.
    """
    n = envs.num_envs
    obs, _ = envs.reset(seed=list(seeds))
    core = envs.core
    task_states = core.task_state.copy()
    returns = np.zeros(n)
    done = np.zeros(n, dtype=bool)
    success = np.zeros(n, dtype=bool)
    end_step = np.zeros(n, dtype=np.int64)
    final_pose = core.stepper.pose.copy()
    paths = [[core.stepper.pose[i].copy()] for i in range(keep_paths)]
    step = 0
    while not done.all():
        obs, reward, terminated, truncated, _ = envs.step(act(obs))
        step += 1
        live = ~done
        returns[live] += reward[live]
        ended = (terminated | truncated) & live
        success[ended] = core.success[ended]
        end_step[ended] = step
        final_pose[ended] = core.stepper.pose[ended]
        for i in range(keep_paths):
            if live[i]:
                paths[i].append(core.stepper.pose[i].copy())
        done |= ended
    return returns, success, end_step, final_pose, task_states, [np.array(p) for p in paths]


def evaluate(policy, calibration: Calibration | str, robot: RobotProfile, *, episodes: int = 256,
             seed: int = 0, randomize: bool = False, keep_paths: int = 0,
             num_threads: int | None = 1) -> Evaluation:
    """Run ``episodes`` episodes of ``policy`` on ``calibration``'s model (every effect on).

    Parameters
    ----------
    policy : ScriptedPolicy or NetworkPolicy
        Its task and control period are used.
    calibration : Calibration or str
        The model to evaluate on (shipped name or TOML path).
    robot : RobotProfile
    episodes, seed : int
        Episode ``i`` is drawn from seed ``seed + i`` (:func:`episode_draw`).
    randomize : bool
        Draw A, B, C within the calibration's intervals per episode.
    keep_paths : int
        Keep the pose sequences of this many first episodes.
    """
    from ..envs import MecanumHILVectorEnv

    envs = MecanumHILVectorEnv(episodes, calibration, robot,
                               control_period_s=policy.control_period_s, task=policy.task,
                               randomize=randomize, num_threads=num_threads)
    returns, success, end_step, final_pose, states, paths = rollout(
        envs, policy.act, [seed + i for i in range(episodes)], keep_paths)
    return summarise(policy.task, robot, success, returns, end_step * policy.control_period_s,
                     final_pose, states, paths)
