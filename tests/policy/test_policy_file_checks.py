"""A policy file with bad contents is one error line naming the file and the key, not a
traceback, a numpy warning, a hang or a run with a network this tool does not compute."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.envs import DodgeTask, ReachTask
from mecanum_hil.envs.task import MAX_EPISODE_S
from mecanum_hil.errors import ConfigError
from mecanum_hil.model import Calibration, load_robot_profile
from mecanum_hil.policy import NetworkPolicy, load_policy

ROBOT = load_robot_profile("tdam-stm")


@pytest.fixture()
def good(tmp_path):
    return NetworkPolicy.initial(ROBOT, ReachTask(), 0.02, Calibration()).save(
        tmp_path / "good.npz")


def _variant(good, tmp_path, name, meta_change=None, **arrays):
    d = dict(np.load(good))
    meta = json.loads(str(d["meta"][()]))
    if meta_change is not None:
        meta_change(meta)
    d["meta"] = np.array(json.dumps(meta))
    d.update(arrays)
    path = tmp_path / name
    np.savez(path, **d)
    return path


def _set_task(key, value):
    def change(meta):
        meta["task"]["parameters"][key] = value
    return change


def test_files_that_are_no_zip_archive_are_named_as_such(good, tmp_path, capsys):
    data = good.read_bytes()
    cases = {"trunc.npz": data[: len(data) // 2], "empty.npz": b"", "text.npz": b"hello"}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        assert main(["evaluate", str(tmp_path / name), "--episodes", "2"]) == 1
        err = capsys.readouterr().err
        assert err.startswith(f"error: {tmp_path / name}: not a mecanum-hil policy file")
        assert err.count("\n") == 1 and "pickle" not in err and "Aborted" not in err


@pytest.mark.parametrize(("name", "change", "arrays", "expect"), [
    ("zeroscale.npz", None, {"input_scale": np.zeros(11)}, "input_scale"),
    ("infscale.npz", None, {"input_scale": np.full(11, np.inf)}, "input_scale"),
    ("nanoffset.npz", None, {"input_offset": np.full(11, np.nan)}, "input_offset"),
    ("nanweights.npz", None, {"params": "nan"}, "weights are not finite"),
    ("relu6.npz", lambda m: m["network"].update(activation="relu6"), {}, "network.activation"),
    ("nanbox.npz", lambda m: m.update(action_low=[float("nan")] * 3), {}, "action_low"),
    ("longep.npz", _set_task("episode_s", 1e9), {}, "episode_s"),
    ("infep.npz", _set_task("episode_s", float("inf")), {}, "episode_s"),
    ("nanscale.npz", _set_task("position_scale_m", float("nan")), {}, "position_scale_m"),
    ("period.npz", lambda m: m.update(control_period_s=1e9), {}, "control_period_s"),
    ("robot.npz", lambda m: m["robot"].update(wheel_radius_m=float("nan")), {},
     "robot.wheel_radius_m"),
])
def test_bad_numbers_and_unknown_networks_are_one_line_naming_the_key(
        good, tmp_path, capsys, name, change, arrays, expect):
    if arrays.get("params") == "nan":  # the network's own size, every weight NaN
        arrays = {"params": np.full(np.load(good)["params"].shape, np.nan)}
    path = _variant(good, tmp_path, name, change, **arrays)
    with pytest.raises(ConfigError, match=expect):
        load_policy(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert main(["evaluate", str(path), "--episodes", "2"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {path}: ") and err.count("\n") == 1 and expect in err


def test_tasks_bound_the_episode_to_an_hour():
    with pytest.raises(ConfigError, match="at most 3600 s"):
        ReachTask(episode_s=MAX_EPISODE_S + 1)
    with pytest.raises(ConfigError, match="max_deadline_s"):
        DodgeTask(max_deadline_s=MAX_EPISODE_S)
    with pytest.raises(ConfigError, match="finite"):
        ReachTask(time_cost_per_s=float("nan"))
    assert ReachTask(episode_s=MAX_EPISODE_S).episode_s == MAX_EPISODE_S
