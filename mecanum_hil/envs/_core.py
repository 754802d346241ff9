"""The batch core both environments share: N robots, their tasks, limits and rewards.

One code path serves the single environment (N = 1) and the vector environment, so the vector
environment equals N single ones by construction; the numbers come from
:class:`mecanum_hil.model.stepper.BatchStepper`, i.e. the simulator's compiled kernel.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import LimitError
from ..model import (
    Calibration,
    RobotProfile,
    load_calibration,
    load_robot_profile,
    wheels_to_twist,
)
from ..model.stepper import DEFAULT_MAX_SUBSTEP_S, BatchStepper
from ..units import DPS_TO_RPM, RPM_TO_RAD_S
from . import _kernels
from .randomisation import CoefficientRanges
from .task import DodgeTask, ReachTask, resolve_task

#: Observation entries 0..9, common to the tasks: name and meaning (units in brackets).
COMMON_OBSERVATION = (
    ("x_m", "X position, world frame [m]"),
    ("y_m", "Y position, world frame [m]"),
    ("phi_deg", "heading, CCW from world X, wrapped to [-180, 180) [deg]"),
    ("vx_mps", "body velocity forward, robot frame [m/s]"),
    ("vy_mps", "body velocity to the left, robot frame [m/s]"),
    ("omega_dps", "turning speed, CCW positive [deg/s]"),
    ("wheel1_rpm", "wheel 1 (front left) speed [rpm]"),
    ("wheel2_rpm", "wheel 2 (front right) speed [rpm]"),
    ("wheel3_rpm", "wheel 3 (rear left) speed [rpm]"),
    ("wheel4_rpm", "wheel 4 (rear right) speed [rpm]"),
)
OBS_SIZE = len(COMMON_OBSERVATION) + 3


def observation_layout(task: ReachTask | DodgeTask | str | None = None):
    """Names and meanings of the 13 observation entries for ``task`` (default reach)."""
    return COMMON_OBSERVATION + resolve_task(task).observation_names


def as_calibration(calibration: Calibration | str | Path) -> Calibration:
    """A calibration object, or one loaded from a shipped name or TOML path."""
    return calibration if isinstance(calibration, Calibration) else load_calibration(calibration)


def as_robot(robot: RobotProfile | str | Path) -> RobotProfile:
    """A robot profile object, or one loaded from a shipped name or TOML path."""
    return robot if isinstance(robot, RobotProfile) else load_robot_profile(robot)


class BatchCore:
    """State, limits, observation and reward of N robots on one calibration."""

    def __init__(self, n: int, calibration: Calibration | str | Path = "paper",
                 robot: RobotProfile | str | Path = "tdam-stm", *,
                 control_period_s: float = 0.02,
                 task: ReachTask | DodgeTask | str | None = None,
                 randomize: bool = False,
                 coefficient_ranges: Mapping[str, tuple[float, float]] | None = None,
                 max_substep_s: float = DEFAULT_MAX_SUBSTEP_S,
                 num_threads: int | None = 1) -> None:
        self.calibration = as_calibration(calibration)
        self.robot = as_robot(robot)
        self.task = resolve_task(task)
        self.control_period_s = float(control_period_s)
        self.ranges = (CoefficientRanges.from_calibration(self.calibration, coefficient_ranges)
                       if randomize else None)
        self.stepper = BatchStepper(n, self.control_period_s, self.calibration, self.robot,
                                    max_substep_s=max_substep_s, num_threads=num_threads)
        self.n = n
        self.episode_steps = max(1, round(self.task.episode_s / self.control_period_s))
        nmax = self.robot.wheel_speed_max_rpm
        self.action_low = np.array([0.0, -self.robot.omega_max_dps, -180.0])
        self.action_high = np.array([nmax, self.robot.omega_max_dps, 180.0])
        self.task_state = np.zeros((n, len(self.task.state_names)))
        self.steps = np.zeros(n, dtype=np.int64)
        self.commands = np.zeros((n, 3))
        self._potential = np.zeros(n)
        self.success = np.zeros(n, dtype=bool)
        self._task_params = self.task.kernel_parameters(self.robot)
        self._evaluate_kernel = self.task.evaluate
        eff = self.calibration.effects
        r = self.robot.wheel_radius_m
        # forward kinematics as a matrix (rows: unit wheel speeds), with slip, in the
        # observation's units (m/s, m/s, deg/s)
        self._fk = np.ascontiguousarray(wheels_to_twist(np.eye(4), self.robot.k) * np.array(
            [eff.efficiency[0] * RPM_TO_RAD_S * r, eff.efficiency[1] * RPM_TO_RAD_S * r,
             eff.efficiency[2] / DPS_TO_RPM]))

    def _evaluate(self, pose, state, task_state, steps):
        m = pose.shape[0]
        obs = np.empty((m, OBS_SIZE))
        potential = np.empty(m)
        success = np.empty(m, dtype=bool)
        failed = np.empty(m, dtype=bool)
        self._evaluate_kernel(pose, state, task_state, self._fk, self._task_params,
                              steps * self.control_period_s, obs, potential, success, failed)
        return obs, potential, success, failed

    def reset_robots(self, index: np.ndarray, rngs: Sequence[np.random.Generator]) -> np.ndarray:
        """Start new episodes for the robots in ``index``, drawing from their generators.

        Returns their first observations, shape (len(index), 13).
        """
        m = len(index)
        coeffs = np.empty((m, 3)) if self.ranges is not None else None
        drawn = np.empty((m, self.task_state.shape[1]))
        for j, rng in enumerate(rngs):
            if coeffs is not None:
                coeffs[j] = self.ranges.draw(rng)
            drawn[j] = self.task.draw(rng)
        if coeffs is not None:
            self.stepper.set_coefficients(coeffs, index)
        self.stepper.reset(index, pose=self.task.start_pose)
        self.task_state[index] = drawn
        self.steps[index] = 0
        self.commands[index] = 0.0
        self.success[index] = False
        obs, potential, _, _ = self._evaluate(self.stepper.pose[index],
                                              self.stepper.state[index], drawn, np.zeros(m))
        self._potential[index] = potential
        return obs

    def limit(self, actions) -> np.ndarray:
        """Commands actually sent: actions clipped to the box, then kept within the wheel limit.

        The fastest wheel target of ``(n, omega, theta)`` is ``|n| + k |omega| / 6`` whatever
        ``theta``; when it exceeds ``wheel_speed_max_rpm``, ``n`` and ``omega`` are scaled down
        by the same factor so that it equals the limit (direction and the ratio of translation to
        turning kept). No command beyond the limit is ever sent.
        """
        a = np.ascontiguousarray(actions, dtype=float)
        if a.shape != (self.n, 3):
            a = np.ascontiguousarray(a.reshape(self.n, 3))
        cmd = np.empty((self.n, 3))
        if not _kernels.limit_actions(a, self.action_low, self.action_high,
                                      self.robot.k / 6.0, self.robot.wheel_speed_max_rpm, cmd):
            raise LimitError("action contains NaN or infinite values")
        return cmd

    def step(self, actions):
        """Advance every robot one control period.

        Returns
        -------
        obs : (N, 13);  reward : (N,);  terminated, truncated : (N,) bool
            Fresh arrays (not overwritten by later steps).
        """
        cmd = self.limit(actions)
        self.commands = cmd
        st = self.stepper
        st.step(cmd)
        self.steps += 1
        obs, potential, success, failed = self._evaluate(st.pose, st.state, self.task_state,
                                                         self.steps)
        reward = np.empty(self.n)
        terminated = np.empty(self.n, dtype=bool)
        truncated = np.empty(self.n, dtype=bool)
        t = self.task
        _kernels.reward_and_ends(potential, self._potential, success, failed, self.steps,
                                 self.episode_steps, t.time_cost_per_s * self.control_period_s,
                                 t.success_bonus, t.failure_penalty, reward, terminated,
                                 truncated)
        self.success = success
        return obs, reward, terminated, truncated
