"""Training improves on the random policy; the policy file is portable and refuses misuse;
``train`` and ``evaluate`` on the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.envs import DodgeTask, ReachTask
from mecanum_hil.errors import ConfigError
from mecanum_hil.model import Calibration, RobotProfile, load_robot_profile
from mecanum_hil.policy import (
    NetworkPolicy,
    ScriptedPolicy,
    episode_draw,
    evaluate,
    load_policy,
    resolve_policy,
)
from mecanum_hil.policy.train import train

ROBOT = load_robot_profile("tdam-stm")
SHORT_DODGE = DodgeTask(min_deadline_s=0.6, max_deadline_s=0.8)


class UniformRandomPolicy:
    """Uniformly random actions in the action box (the reference a training must beat)."""

    def __init__(self, robot, task, seed):
        self.robot, self.task, self.control_period_s = robot, task, 0.02
        self.rng = np.random.default_rng(seed)

    def act(self, obs):
        r = self.robot
        low = np.array([0.0, -r.omega_max_dps, -180.0])
        high = np.array([r.wheel_speed_max_rpm, r.omega_max_dps, 180.0])
        return self.rng.uniform(low, high, size=(len(obs), 3))


def test_a_short_training_beats_the_random_policy():
    pytest.importorskip("cma")
    start = NetworkPolicy.initial(ROBOT, SHORT_DODGE, 0.02, Calibration(), hidden=())
    result = train(start, Calibration(), generations=15, episodes=8, popsize=8, seed=3,
                   validation_episodes=16)
    assert result.generations == 15 and result.evaluations == 120
    trained = evaluate(result.policy, Calibration(), ROBOT, episodes=64, seed=100)
    rand = evaluate(UniformRandomPolicy(ROBOT, SHORT_DODGE, 0), Calibration(), ROBOT,
                    episodes=64, seed=100)
    assert trained.mean_return > rand.mean_return + 0.5
    # measured: return -0.18 against -0.98, success 20 % against 0 %
    assert trained.success_rate > rand.success_rate + 0.1
    # the same seed and number of generations give the same policy
    again = train(start, Calibration(), generations=15, episodes=8, popsize=8, seed=3,
                  validation_episodes=16)
    np.testing.assert_array_equal(again.policy.params, result.policy.params)


def test_policy_file_round_trip_gives_the_same_actions(tmp_path):
    rng = np.random.default_rng(0)
    pol = NetworkPolicy.initial(ROBOT, ReachTask(), 0.02, Calibration(), hidden=(5,))
    pol = pol.with_params(rng.normal(size=pol.arch.n_params), seed=1)
    path = pol.save(tmp_path / "p.npz")
    back = load_policy(path)
    obs = rng.normal(size=(7, 13))
    np.testing.assert_array_equal(back.act(obs), pol.act(obs))
    assert back.task == pol.task and back.control_period_s == 0.02
    assert back.calibration().coefficients == Calibration().coefficients
    with np.load(path, allow_pickle=False) as z:  # no pickled objects
        meta = json.loads(str(z["meta"][()]))
    assert meta["format"] == "mecanum-hil-policy" and meta["action_map"] == "polar"
    assert meta["observation_layout"][10] == "target_forward_m"
    assert meta["robot"]["wheel_speed_max_rpm"] == 130.0


def test_a_policy_for_another_robot_or_task_is_refused_with_one_line(tmp_path, capsys):
    other = RobotProfile(name="small", wheel_speed_max_rpm=200.0, source="small.toml")
    pol = NetworkPolicy.initial(other, ReachTask(), 0.02, Calibration()).save(
        tmp_path / "small.npz")
    with pytest.raises(ConfigError, match="trained for robot profile 'small'"):
        resolve_policy(pol, ROBOT)
    dodge = NetworkPolicy.initial(ROBOT, DodgeTask(), 0.02, Calibration()).save(
        tmp_path / "dodge.npz")
    assert main(["evaluate", str(dodge), "--task", "reach", "--episodes", "2"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert "trained for task 'dodge', not 'reach'" in err
    assert main(["record", "--port", "/dev/does-not-exist", "--policy", str(pol), "--out",
                 str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "'small'" in err
    assert not (tmp_path / "run").exists()
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    assert main(["evaluate", str(bad)]) == 1
    assert "not a mecanum-hil policy file" in capsys.readouterr().err


def test_episode_draws_are_those_of_the_vector_env():
    from mecanum_hil.envs import MecanumHILVectorEnv

    envs = MecanumHILVectorEnv(3, task="dodge")
    envs.reset(seed=11)
    for i in range(3):
        np.testing.assert_array_equal(episode_draw(DodgeTask(), 11, i), envs.task_state[i])


def test_scripted_reach_reaches_every_target():
    ev = evaluate(ScriptedPolicy(ROBOT, ReachTask()), Calibration(), ROBOT, episodes=32)
    assert ev.success_rate == 1.0 and 1.0 < ev.time_to_target_s < 5.0


def test_train_and_evaluate_on_the_command_line(tmp_path, capsys):
    pytest.importorskip("cma")
    out = tmp_path / "dodge.npz"
    code = main(["train", "--task", "dodge", "--out", str(out), "--generations", "2",
                 "--episodes", "4", "--hidden", "3", "--seed", "1", "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["generations"] == 2 and doc["policy"] == str(out) and out.exists()
    code = main(["evaluate", str(out), "--episodes", "8", "--seed", "5", "--json"])
    assert code == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["task"] == "dodge" and ev["episodes"] == 8 and 0 <= ev["success_rate"] <= 1
    assert set(ev) >= {"mean_return", "margin_m", "time_to_target_s"}
    assert main(["evaluate", "scripted", "--episodes", "8"]) == 0
    text = capsys.readouterr().out
    assert "success     100.0 % (8 of 8)" in text and "time to target" in text
    assert main(["train", "--task", "parry", "--out", str(out)]) == 1
    assert "unknown task 'parry'" in capsys.readouterr().err
