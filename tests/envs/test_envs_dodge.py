"""The dodge task: geometry of the line of attack, deadline, reward, a policy that dodges."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from mecanum_hil.envs import DodgeTask, MecanumHILEnv, MecanumHILVectorEnv, observation_layout
from mecanum_hil.envs._kernels import evaluate_dodge
from mecanum_hil.errors import ConfigError
from mecanum_hil.model import RobotProfile


def _dodge_policy(obs, n_max):
    # run across the line, away from it: the normal to the left of the strike is at the
    # attacker's bearing in the theta convention (0 right, 90 ahead)
    theta = np.where(obs[:, 10] >= 0, obs[:, 12], obs[:, 12] + 180.0)
    return np.column_stack([np.full(len(obs), n_max), np.zeros(len(obs)),
                            (theta + 180.0) % 360.0 - 180.0])


def test_passes_the_env_checker():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        check_env(MecanumHILEnv(task="dodge"), skip_render_check=True)
    assert [name for name, _ in observation_layout("dodge")][10:] == [
        "line_offset_m", "time_to_strike_s", "attacker_bearing_deg"]


def test_clearance_depends_on_the_heading_of_the_body():
    robot = RobotProfile()  # body 0.977 m x 0.775 m
    task = DodgeTask(margin_m=0.05)
    par = task.kernel_parameters(robot)
    fk = np.zeros((4, 3))
    strike = np.array([[0.0, 1.0]])  # along world +X through the start (0, 0), lands at 1 s
    out = [np.empty((1, 13)), np.empty(1), np.empty(1, bool), np.empty(1, bool)]
    # 0.5 m off the line, long side across it: 0.4885 + 0.05 > 0.5, not clear
    evaluate_dodge(np.array([[0.0, 0.5, 90.0]]), np.zeros((1, 12)), strike, fk, par,
                   np.array([1.0]), *out)
    assert out[3][0] and not out[2][0]
    assert out[1][0] == pytest.approx(-(0.4885 + 0.05 - 0.5))
    assert out[0][0, 10] == pytest.approx(0.5)
    # turned to lie along the line: 0.3875 + 0.05 < 0.5, clear
    evaluate_dodge(np.array([[0.0, 0.5, 0.0]]), np.zeros((1, 12)), strike, fk, par,
                   np.array([1.0]), *out)
    assert out[2][0] and not out[3][0] and out[1][0] == 0.0
    # the strike comes from behind the robot (world -X while heading 0)
    assert out[0][0, 12] == pytest.approx(-180.0)
    # before the deadline neither outcome
    evaluate_dodge(np.array([[0.0, 0.5, 0.0]]), np.zeros((1, 12)), strike, fk, par,
                   np.array([0.98]), *out)
    assert not out[2][0] and not out[3][0]
    assert out[0][0, 11] == pytest.approx(0.02)


def test_standing_still_is_hit_at_the_deadline():
    env = MecanumHILEnv(task=DodgeTask(min_deadline_s=0.3, max_deadline_s=0.5))
    obs, info = env.reset(seed=2)
    deadline = info["task_state"][1]
    assert obs[10] == pytest.approx(0.0) and obs[11] == pytest.approx(deadline)
    steps, terminated, reward = 0, False, 0.0
    while not terminated:
        _, reward, terminated, truncated, info = env.step([0.0, 0.0, 0.0])
        assert not truncated
        steps += 1
    assert steps == int(np.ceil(deadline / 0.02 - 1e-9))
    assert not info["success"] and reward == pytest.approx(-1.0)


def test_a_scripted_dodge_mostly_succeeds_in_the_vector_env():
    n = 256
    envs = gym.make_vec("MecanumHIL-v0", num_envs=n, task="dodge")
    obs, _ = envs.reset(seed=0)
    done = np.zeros(n, dtype=bool)
    success = np.zeros(n, dtype=bool)
    while not done.all():
        obs, _, terminated, truncated, _ = envs.step(
            _dodge_policy(obs, envs.single_action_space.high[0]))
        assert not truncated.any()
        success |= terminated & ~done & envs.core.success
        done |= terminated
    assert success.mean() > 0.85


def test_vector_env_equals_sync_vector_env():
    kwargs = {"task": DodgeTask(min_deadline_s=0.1, max_deadline_s=0.4)}
    n = 4
    ours = MecanumHILVectorEnv(n, **kwargs)
    ref = gym.vector.SyncVectorEnv([lambda: MecanumHILEnv(**kwargs) for _ in range(n)])
    np.testing.assert_array_equal(ours.reset(seed=3)[0], ref.reset(seed=3)[0])
    rng = np.random.default_rng(1)
    for _ in range(40):
        a = rng.uniform(ours.single_action_space.low, ours.single_action_space.high, (n, 3))
        for x, y in zip(ours.step(a)[:4], ref.step(a)[:4], strict=True):
            np.testing.assert_array_equal(x, y)


def test_bad_task_is_refused():
    with pytest.raises(ConfigError, match="unknown task"):
        MecanumHILEnv(task="parry")
    with pytest.raises(ConfigError):
        DodgeTask(min_deadline_s=1.0, max_deadline_s=0.5)
