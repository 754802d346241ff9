"""Robot profiles, calibrations and command profiles as files."""

import json
import math
from dataclasses import replace
from pathlib import PurePosixPath, PureWindowsPath

import numpy as np
import pytest

from mecanum_hil.errors import ConfigError, LimitError
from mecanum_hil.model import (
    Calibration,
    Effects,
    load_calibration,
    load_robot_profile,
    save_calibration,
)
from mecanum_hil.profiles import PAPER_EXPERIMENTS, load_profile, resolve_profile


def test_shipped_robot_profile_is_the_papers():
    robot = load_robot_profile()
    assert robot.name == "TDAM-STM"
    assert (robot.wheel_radius_m, robot.lx_plus_ly_m, robot.wheel_speed_max_rpm) == (
        0.102, 0.465, 130.0)
    assert (robot.body_length_m, robot.body_width_m, robot.mass_kg) == (0.977, 0.775, 100.0)


def test_shipped_calibration_is_the_papers():
    cal = load_calibration()
    assert cal.coefficients == (14.7, 16.1, 303.0)
    assert cal.effects == Effects()


def test_calibration_round_trip_with_effects(tmp_path):
    cal = replace(
        Calibration(12.5, 18.25, 280.0),
        effects=Effects(dead_time_s=0.02, top_speed_rpm=125.0, gains=(1.0, 0.8, 1.0, 1.0),
                        efficiency=(0.9, 0.8, 0.95)),
        ci95={"A": (12.0, 13.0)}, info={"rmse_rpm": 0.5, "method": "lsq"})
    path = save_calibration(cal, tmp_path / "cal.toml", header="test")
    back = load_calibration(path)
    assert back.coefficients == cal.coefficients
    assert back.effects == cal.effects
    assert back.ci95 == {"A": (12.0, 13.0)}
    assert back.info["method"] == "lsq"


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("[motor]\nA = 1\nB = 2\n", "key 'motor.C' is missing"),
        ("[motor]\nA = 1\nB = 2\nC = -3\n", "key 'motor.C' must be > 0"),
        ("[motor]\nA = 1\nB = 2\nC = 'x'\n", "key 'motor.C' must be a number"),
        ("[motor]\nA = 1\nB = 2\nC = 3\nD = 4\n", "key 'motor.D' is not a known key"),
        ("[motor]\nA = 1\nB = 2\nC = 3\n[effects.saturation]\ntop_speed_rpm = 0\n",
         "key 'effects.saturation.top_speed_rpm' must be > 0"),
        ("[motor]\nA = 1\nB = 2\nC = 3\n[effects.wheel_gain]\ngains = [1, 2]\n",
         "key 'effects.wheel_gain.gains' must be a list of 4"),
        ("[motor]\nA = 1\nB = 2\nC = 3\n[effects.stiction]\nx = 1\n",
         "key 'effects.stiction' is not a known key"),
        ("[motor\n", "not valid TOML"),
        # a coefficient whose discretised model overflows (C = 1e300 simulated empty values)
        ("[motor]\nA = 1\nB = 2\nC = 1e300\n", "key 'motor.C' must be at most 1e+12"),
        ("[motor]\nA = 1e13\nB = 2\nC = 3\n", "key 'motor.A' must be at most 1e+12"),
        ("[motor]\nA = 1\nB = 2\nC = 3\n[ci95]\nunidentifiable = 'A'\n",
         "key 'ci95.unidentifiable' must be a list of parameter names"),
        ("[motor]\nA = 1\nB = 2\nC = 3\n[ci95]\nA = [0.5, 1.5]\nunidentifiable = ['A']\n",
         "key 'ci95.unidentifiable' names 'A', which has an interval"),
    ],
)
def test_bad_calibration_names_file_and_key(tmp_path, text, fragment):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_calibration(p)
    assert fragment in str(err.value) and str(p) in str(err.value)


def test_an_unidentifiable_interval_is_listed_by_name_and_reads_back(tmp_path):
    # TOML has no null: a parameter the data cannot bound has no interval key, and its name
    # is in [ci95]'s unidentifiable list
    cal = Calibration(ci95={"A": (12.0, 13.0), "dead_time_s": None, "gains_1": None})
    path = save_calibration(cal, tmp_path / "cal.toml")
    text = path.read_text()
    assert 'unidentifiable = ["dead_time_s", "gains_1"]' in text
    assert "dead_time_s = " not in text
    assert load_calibration(path).ci95 == {"A": (12.0, 13.0), "dead_time_s": None,
                                           "gains_1": None}


def test_a_calibration_made_in_memory_is_refused_without_naming_a_file(tmp_path):
    # the file's values are fine; the model made from them in memory is not: the error must
    # not send the user to the file
    path = save_calibration(Calibration(), tmp_path / "mine.toml")
    cal = load_calibration(path)
    with pytest.raises(ConfigError) as err:
        replace(cal, A=4.8e22)
    assert "mine.toml" not in str(err.value) and "motor.A" not in str(err.value)
    assert "A must be at most 1e+12" in str(err.value)
    with pytest.raises(ConfigError) as err:
        cal.with_coefficients(14.7, -1.0, 303.0, "the refitted model")
    assert str(err.value) == "the refitted model: B must be >= 0, got -1"


def test_a_calibration_saved_with_a_bom_is_read_and_one_not_in_utf8_is_one_error(tmp_path):
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf[motor]\nA = 1\nB = 2\nC = 3\n")  # as Notepad saves it
    assert load_calibration(p).C == 3.0
    p.write_bytes(b"# caf\xe9\n[motor]\nA = 1\nB = 2\nC = 3\n")  # Latin-1
    with pytest.raises(ConfigError, match=r"bom.toml: not valid TOML: not UTF-8 text"):
        load_calibration(p)


def test_bad_robot_profile_names_file_and_key(tmp_path, repo):
    text = (repo / "drivers" / "tdam-stm.toml").read_text().replace(
        "wheel_radius_m = 0.102", "wheel_radius_m = -0.1")
    p = tmp_path / "robot.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"robot.toml: key 'robot.wheel_radius_m' must be > 0"):
        load_robot_profile(p)


def test_a_robot_profile_with_an_unknown_table_is_refused(tmp_path, repo):
    # an extra table ([motor] pasted from a calibration) is a mistake to say, not to ignore
    p = tmp_path / "robot.toml"
    p.write_text((repo / "drivers" / "tdam-stm.toml").read_text() + "\n[motor]\nA = 1\n")
    with pytest.raises(ConfigError, match=r"robot.toml: key 'motor' is not a known key "
                       r"\(known: limits, robot\)"):
        load_robot_profile(p)


def test_unknown_names():
    with pytest.raises(ConfigError, match="shipped: paper"):
        load_calibration("nonexistent")
    with pytest.raises(ConfigError, match="unknown profile"):
        resolve_profile("no-such-profile")


def test_limits_refuse_a_profile_beyond_the_robot():
    robot = load_robot_profile()
    robot.check_commands([[130.0, 0.0, 90.0], [0.0, robot.omega_max_dps, 90.0]])
    with pytest.raises(LimitError, match="beyond the robot's limit of 130 rpm"):
        robot.check_commands([[100.0, 40.0, 90.0]])  # 100 + 30.4 rpm on two wheels
    with pytest.raises(LimitError, match="not a finite number"):
        robot.check_commands([[math.nan, 0.0, 90.0]])


def test_paper_experiments():
    assert set(PAPER_EXPERIMENTS) == {
        "paper-step-30", "paper-step-60", "paper-step-90", "paper-step-100", "paper-step-120",
        "paper-ramp", "paper-turn"}
    _, cmd = PAPER_EXPERIMENTS["paper-ramp"].sample(10.0)
    assert cmd[:, 0].max() == pytest.approx(130.0)
    slope = np.diff(cmd[:, 0]) * 10.0
    assert slope.max() == pytest.approx(5.0)
    _, cmd = PAPER_EXPERIMENTS["paper-turn"].sample(10.0)
    assert set(cmd[:, 1]) == {0.0, 60.0} and (cmd[:, 0] == 0).all()
    _, cmd = PAPER_EXPERIMENTS["paper-step-60"].sample(100.0)
    assert cmd[50, 0] == 60.0 and cmd[49, 0] == 0.0


def test_profile_file(tmp_path):
    p = tmp_path / "prof.toml"
    p.write_text(
        '[profile]\nname = "mine"\ninitial = { theta_deg = 0.0 }\n'
        '[[segments]]\nkind = "hold"\nduration_s = 0.5\n'
        '[[segments]]\nkind = "ramp"\nrate_rpm_per_s = 20.0\nn_rpm = 40.0\n'
        '[[segments]]\nkind = "step"\nduration_s = 1.0\nomega_dps = 30.0\n')
    prof = load_profile(p)
    assert prof.name == "mine" and prof.duration_s == pytest.approx(3.5)
    cmd = prof.command_at([0.1, 1.5, 2.6, 10.0])
    np.testing.assert_allclose(cmd, [[0, 0, 0], [20, 0, 0], [40, 30, 0], [40, 30, 0]])


def test_bad_profile_file(tmp_path):
    p = tmp_path / "prof.toml"
    p.write_text('[[segments]]\nkind = "jump"\nduration_s = 1\n')
    with pytest.raises(ConfigError, match=r"key 'segments\[0\].kind' must be one of"):
        load_profile(p)


# --- what a sidecar says of the files it came from ------------------------------------------

def _strings(value, key=""):
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _strings(v, k)
    elif isinstance(value, list):
        for v in value:
            yield from _strings(v, key)
    elif isinstance(value, str):
        yield key, value


def _absolute(text: str) -> bool:
    return PurePosixPath(text).is_absolute() or PureWindowsPath(text).is_absolute()


def test_no_shipped_sidecar_holds_an_absolute_path(repo):
    sidecars = sorted((repo / "recordings").rglob("*.json"))
    assert sidecars
    for path in sidecars:
        doc = json.loads(path.read_text(encoding="utf-8"))
        # a port names the device the link opened (/dev/pts/0), not a file of the machine
        found = [(k, v) for k, v in _strings(doc) if k != "port" and _absolute(v)]
        assert not found, f"{path.name}: {found}"


@pytest.mark.parametrize("given", ["tdam-stm", "drivers/tdam-stm.toml"])
def test_robot_profile_source_is_the_name_or_the_path_as_given(repo, monkeypatch, given):
    monkeypatch.chdir(repo)
    assert load_robot_profile(given).source == given
