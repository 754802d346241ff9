"""MecanumHIL-v0: Gymnasium conformance, agreement with simulate(), the vector env, seeding."""

from __future__ import annotations

import subprocess
import sys
import warnings
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import mecanum_hil.envs
from mecanum_hil.envs import MecanumHILEnv, MecanumHILVectorEnv, ReachTask
from mecanum_hil.errors import ConfigError, LimitError
from mecanum_hil.model import Calibration, Effects, load_robot_profile, save_calibration, simulate

DIAGNOSED = Calibration(
    A=12.0, B=14.0, C=280.0,
    effects=Effects(dead_time_s=0.031, top_speed_rpm=120.0, deadband_rpm=2.0,
                    gains=(1.0, 0.95, 1.0, 1.05), efficiency=(0.95, 0.85, 0.9)),
    ci95={"A": (11.0, 13.0), "B": (13.0, 15.0), "C": (260.0, 300.0), "dead_time_s": (0.02, 0.04)},
    source="diagnosed.toml")


@pytest.fixture
def cal_file(tmp_path):
    return save_calibration(DIAGNOSED, tmp_path / "cal.toml")


@pytest.mark.parametrize("kwargs", [{}, {"calibration": DIAGNOSED, "randomize": True,
                                         "control_period_s": 0.05}])
def test_passes_gymnasiums_env_checker(kwargs):
    with warnings.catch_warnings():
        # the checker recommends a normalised action box and finite observation bounds; the
        # action is in physical units on purpose and positions are unbounded
        warnings.simplefilter("ignore", UserWarning)
        check_env(MecanumHILEnv(**kwargs), skip_render_check=True)


def test_registered_id_takes_a_calibration_file(cal_file):
    env = gym.make("MecanumHIL-v0", calibration=str(cal_file), control_period_s=0.01)
    assert isinstance(env.unwrapped, MecanumHILEnv)
    assert env.unwrapped.core.calibration.effects == DIAGNOSED.effects
    assert env.unwrapped.core.control_period_s == 0.01
    envs = gym.make_vec("MecanumHIL-v0", num_envs=3, calibration=str(cal_file))
    assert isinstance(envs, MecanumHILVectorEnv) and envs.num_envs == 3


def test_module_prefixed_id_works_in_a_fresh_interpreter(cal_file):
    code = ("import gymnasium as gym; "
            f"e = gym.make('mecanum_hil.envs:MecanumHIL-v0', calibration={str(cal_file)!r}); "
            "o, _ = e.reset(seed=0); print(o.shape)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "(13,)"


def test_trajectory_equals_simulate_on_the_commands_sent():
    env = MecanumHILEnv(DIAGNOSED, task=ReachTask(arena_radius_m=50.0, episode_s=100.0))
    env.reset(seed=4)
    rng = np.random.default_rng(0)
    # beyond the box and beyond the wheel limit too: what is sent is limited, then simulated
    actions = rng.uniform([-20.0, -120.0, -200.0], [160.0, 120.0, 200.0], size=(150, 3))
    poses, wheels, commands = [env.pose], [np.zeros(4)], []
    for a in actions:
        obs, _, terminated, truncated, info = env.step(a)
        assert not (terminated or truncated)
        poses.append(info["pose"])
        wheels.append(obs[6:10])
        commands.append(info["command"])
    commands = np.array(commands)
    robot = load_robot_profile("tdam-stm")
    robot.check_commands(commands, "env commands")  # never beyond the limit
    peak = np.abs(commands[:, 0]) + robot.k / 6 * np.abs(commands[:, 1])
    assert np.isclose(peak.max(), robot.wheel_speed_max_rpm)
    t = np.arange(len(actions) + 1) * 0.02
    ref = simulate(np.vstack([commands, commands[-1:]]), t, DIAGNOSED, robot)
    np.testing.assert_allclose(poses, ref.pose[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(wheels, ref.wheel_rpm[0], rtol=0, atol=1e-9)


def test_observation_layout_and_units():
    env = MecanumHILEnv(task=ReachTask(episode_s=100.0, arena_radius_m=50.0))
    obs, info = env.reset(seed=1)
    assert len(mecanum_hil.envs.observation_layout()) == obs.size == 13
    np.testing.assert_array_equal(obs[:3], [0.0, 0.0, 90.0])
    # target error in the robot frame: heading 90 deg, so "ahead" is world +Y
    tx, ty, tphi = info["task_state"]
    np.testing.assert_allclose(obs[10:13], [ty, -tx, (tphi - 90.0 + 180.0) % 360.0 - 180.0])
    for _ in range(100):  # straight ahead at 60 rpm for 2 s: steady state
        obs, *_ = env.step([60.0, 0.0, 90.0])
    np.testing.assert_allclose(obs[6:10], 60.0, atol=1e-3)
    speed = 60.0 * 2 * np.pi / 60.0 * 0.102  # rpm -> m/s on the wheel radius
    np.testing.assert_allclose(obs[3:6], [speed, 0.0, 0.0], atol=1e-5)
    assert obs[1] > 0.9 * speed and abs(obs[0]) < 1e-9  # moved along world +Y


def test_vector_env_equals_sync_vector_env_of_single_envs():
    kwargs = {"calibration": DIAGNOSED, "randomize": True,
              "task": ReachTask(episode_s=0.3, min_distance_m=0.0, max_distance_m=0.2,
                                position_tolerance_m=0.08, heading_tolerance_deg=90.0)}
    n = 6
    ours = MecanumHILVectorEnv(n, **kwargs)
    ref = gym.vector.SyncVectorEnv([lambda: MecanumHILEnv(**kwargs) for _ in range(n)])
    o1, _ = ours.reset(seed=11)
    o2, _ = ref.reset(seed=11)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(5)
    ends = 0
    for _ in range(60):
        a = rng.uniform(ours.single_action_space.low, ours.single_action_space.high, (n, 3))
        r1 = ours.step(a)
        r2 = ref.step(a)
        for x, y in zip(r1[:4], r2[:4], strict=True):
            np.testing.assert_array_equal(x, y)
        ends += int(r1[2].sum() + r1[3].sum())
    assert ends > n  # autoresets happened, by success and by truncation
    assert ref.envs[0].unwrapped.coefficients[0] == ours.core.stepper.coefficients[0, 0]


def test_seeding_reproduces_and_seeds_differ():
    def rollout(seed):
        env = MecanumHILEnv(DIAGNOSED, randomize=True)
        obs, info = env.reset(seed=seed)
        env.action_space.seed(seed)
        out = [obs]
        for _ in range(20):
            out.append(env.step(env.action_space.sample())[0])
        return np.array(out), info["coefficients"]

    a, ca = rollout(3)
    b, cb = rollout(3)
    c, cc = rollout(4)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ca, cb)
    assert not np.array_equal(ca, cc) and not np.array_equal(a, c)
    v = MecanumHILVectorEnv(4, DIAGNOSED, randomize=True)
    first = v.reset(seed=9)[0]
    v.step(v.single_action_space.high[None].repeat(4, 0))
    np.testing.assert_array_equal(v.reset(seed=9)[0], first)


def test_randomisation_stays_within_the_intervals():
    env = MecanumHILEnv(DIAGNOSED, randomize=True)
    draws = np.array([env.reset(seed=s)[1]["coefficients"] for s in range(30)])
    lo = [DIAGNOSED.ci95[k][0] for k in "ABC"]
    hi = [DIAGNOSED.ci95[k][1] for k in "ABC"]
    assert (draws >= lo).all() and (draws <= hi).all()
    assert (draws.std(axis=0) > 0).all()
    assert env.core.ranges.ignored == ("dead_time_s",)


def test_randomising_a_calibration_without_intervals_is_refused():
    with pytest.raises(ConfigError, match="ci95"):
        MecanumHILEnv("paper", randomize=True)
    env = MecanumHILEnv("paper", randomize=True, coefficient_ranges={"C": (250.0, 350.0)})
    _, info = env.reset(seed=0)
    assert info["coefficients"][:2].tolist() == [14.7, 16.1]
    assert 250.0 <= info["coefficients"][2] <= 350.0


def test_randomising_a_coefficient_the_data_cannot_bound_is_refused(tmp_path):
    # no interval to draw from, and the fitted value is no better than any other
    loose = save_calibration(replace(DIAGNOSED, ci95={**DIAGNOSED.ci95, "B": None}),
                             tmp_path / "loose.toml")
    with pytest.raises(ConfigError, match=r"cannot bound B \(unidentifiable"):
        MecanumHILEnv(loose, randomize=True)
    env = MecanumHILEnv(loose, randomize=True, coefficient_ranges={"B": (13.0, 15.0)})
    assert 13.0 <= env.reset(seed=0)[1]["coefficients"][1] <= 15.0


def test_success_terminates_with_the_bonus():
    task = ReachTask(min_distance_m=0.0, max_distance_m=0.0, position_tolerance_m=0.05,
                     heading_tolerance_deg=400.0)
    env = MecanumHILEnv(task=task)
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step([0.0, 0.0, 0.0])
    assert terminated and info["success"]
    assert reward == pytest.approx(task.success_bonus - task.time_cost_per_s * 0.02, abs=1e-9)


def test_truncation_after_the_episode_length():
    env = MecanumHILEnv(task=ReachTask(episode_s=0.1))
    env.reset(seed=0)
    flags = [env.step([0.0, 0.0, 0.0])[3] for _ in range(5)]
    assert flags == [False, False, False, False, True]


def test_non_finite_action_is_refused():
    env = MecanumHILEnv()
    env.reset(seed=0)
    with pytest.raises(LimitError):
        env.step([np.nan, 0.0, 0.0])
