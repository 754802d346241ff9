"""Compiled per-robot arithmetic of the environments: action limits, observation, reward.

Written as plain loops over robots (serial: a step of 4096 robots is far below a millisecond,
less than the threads' meeting would cost) so that one robot's numbers do not depend on how
many robots share the batch: the vector environment equals N single ones bit for bit.
"""

from __future__ import annotations

import math

from numba import njit

# Layout of the task parameter vector passed to the kernels.
X0, Y0, POS_SCALE, HEAD_SCALE, POS_TOL, HEAD_TOL, ARENA = range(7)
TASK_WIDTH = 7


@njit(cache=True, inline="always")
def _wrap(a):
    # floor, not Python's float %, which numba implements with extra sign fix-ups
    return a - 360.0 * math.floor((a + 180.0) / 360.0)


@njit(cache=True)
def limit_actions(actions, low, high, k_over_6, wheel_max_rpm, out):
    """Clip to the box, then scale ``(n, omega)`` so ``|n| + k |omega| / 6 <= wheel_max_rpm``.

    Returns False (leaving ``out`` partly written) if an action is not finite.
    """
    for i in range(actions.shape[0]):
        for j in range(3):
            a = actions[i, j]
            if not math.isfinite(a):
                return False
            out[i, j] = min(max(a, low[j]), high[j])
        peak = abs(out[i, 0]) + k_over_6 * abs(out[i, 1])
        if peak > wheel_max_rpm:
            scale = wheel_max_rpm / peak
            out[i, 0] *= scale
            out[i, 1] *= scale
    return True


@njit(cache=True)
def evaluate(pose, state, targets, fk, task, obs, potential, success, left):
    """Observation, shaping potential and outcome of each robot.

    Parameters
    ----------
    pose : (N, 3)  ``(X [m], Y [m], phi [deg])``;  state : (N, 12) wheel state (rpm first)
    targets : (N, 3) target poses;  fk : (4, 3) wheels [rpm] -> (vx, vy [m/s], omega [deg/s])
    task : (7,) task parameters (see the module's index constants)
    obs : (N, 13), potential : (N,), success, left : (N,) bool  (written)
    """
    for i in range(pose.shape[0]):
        X = pose[i, 0]
        Y = pose[i, 1]
        phid = pose[i, 2]
        obs[i, 0] = X
        obs[i, 1] = Y
        obs[i, 2] = _wrap(phid)
        for j in range(3):
            v = 0.0
            for w in range(4):
                v += state[i, w] * fk[w, j]
            obs[i, 3 + j] = v
        for w in range(4):
            obs[i, 6 + w] = state[i, w]
        dx = targets[i, 0] - X
        dy = targets[i, 1] - Y
        phi = math.radians(phid)
        c = math.cos(phi)
        s = math.sin(phi)
        obs[i, 10] = c * dx + s * dy
        obs[i, 11] = c * dy - s * dx
        dphi = _wrap(targets[i, 2] - phid)
        obs[i, 12] = dphi
        dist = math.sqrt(dx * dx + dy * dy)
        potential[i] = -(dist / task[POS_SCALE] + abs(dphi) / task[HEAD_SCALE])
        ok = dist < task[POS_TOL] and abs(dphi) < task[HEAD_TOL]
        success[i] = ok
        ox = X - task[X0]
        oy = Y - task[Y0]
        left[i] = (not ok) and ox * ox + oy * oy > task[ARENA] * task[ARENA]


@njit(cache=True)
def reward_and_ends(potential, previous, success, left, steps, episode_steps, step_cost,
                    success_bonus, leave_penalty, reward, terminated, truncated):
    """Reward, termination and truncation after a step; ``previous`` becomes ``potential``."""
    for i in range(potential.shape[0]):
        r = potential[i] - previous[i] - step_cost
        if success[i]:
            r += success_bonus
        if left[i]:
            r -= leave_penalty
        reward[i] = r
        previous[i] = potential[i]
        steps[i] += 1
        terminated[i] = success[i] or left[i]
        truncated[i] = (not terminated[i]) and steps[i] >= episode_steps
