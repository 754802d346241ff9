"""Compiled per-robot arithmetic of the environments: action limits, observation, reward.

Written as plain loops over robots (serial: a step of 4096 robots is far below a millisecond,
less than the threads' meeting would cost) so that one robot's numbers do not depend on how
many robots share the batch: the vector environment equals N single ones bit for bit.

Each task has one ``evaluate_*`` kernel with the same signature: it writes the observation
(10 common entries, 3 of the task), the shaping potential, and whether the episode ends in
success or in failure.
"""

from __future__ import annotations

import math

from .._jit import njit

# Layout of the reach task's parameter vector.
R_X0, R_Y0, R_POS_SCALE, R_HEAD_SCALE, R_POS_TOL, R_HEAD_TOL, R_ARENA = range(7)
# Layout of the dodge task's parameter vector.
D_X0, D_Y0, D_POS_SCALE, D_MARGIN, D_ARENA, D_HALF_LENGTH, D_HALF_WIDTH = range(7)


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


@njit(cache=True, inline="always")
def _common(i, pose, state, fk, obs):
    obs[i, 0] = pose[i, 0]
    obs[i, 1] = pose[i, 1]
    obs[i, 2] = _wrap(pose[i, 2])
    for j in range(3):
        v = 0.0
        for w in range(4):
            v += state[i, w] * fk[w, j]
        obs[i, 3 + j] = v
    for w in range(4):
        obs[i, 6 + w] = state[i, w]


@njit(cache=True)
def evaluate_reach(pose, state, task_state, fk, par, time_s, obs, potential, success, failed):
    """Reach a target pose; ``task_state`` rows are the targets ``(X [m], Y [m], phi [deg])``.

    Parameters
    ----------
    pose : (N, 3)  ``(X [m], Y [m], phi [deg])``;  state : (N, 12) wheel state (rpm first)
    task_state : (N, W) the episode's draw;  fk : (4, 3) wheels [rpm] -> (m/s, m/s, deg/s)
    par : (7,) task parameters (``R_*`` indices);  time_s : (N,) time since reset [s]
    obs : (N, 13), potential : (N,), success, failed : (N,) bool  (written)
    """
    for i in range(pose.shape[0]):
        _common(i, pose, state, fk, obs)
        X = pose[i, 0]
        Y = pose[i, 1]
        dx = task_state[i, 0] - X
        dy = task_state[i, 1] - Y
        phi = math.radians(pose[i, 2])
        c = math.cos(phi)
        s = math.sin(phi)
        obs[i, 10] = c * dx + s * dy
        obs[i, 11] = c * dy - s * dx
        dphi = _wrap(task_state[i, 2] - pose[i, 2])
        obs[i, 12] = dphi
        dist = math.sqrt(dx * dx + dy * dy)
        potential[i] = -(dist / par[R_POS_SCALE] + abs(dphi) / par[R_HEAD_SCALE])
        ok = dist < par[R_POS_TOL] and abs(dphi) < par[R_HEAD_TOL]
        success[i] = ok
        ox = X - par[R_X0]
        oy = Y - par[R_Y0]
        failed[i] = (not ok) and ox * ox + oy * oy > par[R_ARENA] * par[R_ARENA]


@njit(cache=True)
def evaluate_dodge(pose, state, task_state, fk, par, time_s, obs, potential, success, failed):
    """Dodge a strike; ``task_state`` rows are ``(attack bearing [deg], deadline [s])``.

    The strike runs along the line through the start position with direction ``bearing``;
    the body (a rectangle) is clear when the centre's distance from the line exceeds the body's
    half-extent across the line plus the margin. Same parameters as :func:`evaluate_reach`
    (``D_*`` indices).
    """
    for i in range(pose.shape[0]):
        _common(i, pose, state, fk, obs)
        X = pose[i, 0]
        Y = pose[i, 1]
        beta = math.radians(task_state[i, 0])
        nx = -math.sin(beta)  # unit normal of the line, to the left of the strike
        ny = math.cos(beta)
        offset = nx * (X - par[D_X0]) + ny * (Y - par[D_Y0])
        rel = math.radians(pose[i, 2]) - beta
        half = (par[D_HALF_LENGTH] * abs(math.sin(rel))
                + par[D_HALF_WIDTH] * abs(math.cos(rel)))
        shortfall = half + par[D_MARGIN] - abs(offset)
        obs[i, 10] = offset
        obs[i, 11] = task_state[i, 1] - time_s[i]
        # where the strike comes from, seen from the robot (0 ahead, CCW positive)
        obs[i, 12] = _wrap(task_state[i, 0] + 180.0 - pose[i, 2])
        potential[i] = -max(shortfall, 0.0) / par[D_POS_SCALE]
        ox = X - par[D_X0]
        oy = Y - par[D_Y0]
        outside = ox * ox + oy * oy > par[D_ARENA] * par[D_ARENA]
        at_deadline = time_s[i] >= task_state[i, 1] - 1e-9
        success[i] = at_deadline and shortfall < 0.0 and not outside
        failed[i] = outside or (at_deadline and shortfall >= 0.0)


@njit(cache=True)
def reward_and_ends(potential, previous, success, failed, steps, episode_steps, step_cost,
                    success_bonus, failure_penalty, reward, terminated, truncated):
    """Reward, termination and truncation after a step; ``previous`` becomes ``potential``."""
    for i in range(potential.shape[0]):
        r = potential[i] - previous[i] - step_cost
        if success[i]:
            r += success_bonus
        if failed[i]:
            r -= failure_penalty
        reward[i] = r
        previous[i] = potential[i]
        terminated[i] = success[i] or failed[i]
        truncated[i] = (not terminated[i]) and steps[i] >= episode_steps
