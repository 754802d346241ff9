"""diagnose's outputs (JSON, report, extended calibration, summary) when a number derived from
the fitted model is degenerate or an interval is one the data cannot bound."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

import mecanum_hil.identify.diagnose as diagnose_package
from mecanum_hil.cli import main
from mecanum_hil.identify.diagnose import diagnose
from mecanum_hil.identify.diagnose.selection import _final_calibration, _Model
from mecanum_hil.identify.diagnose_report import write_report
from mecanum_hil.identify.fit import fit
from mecanum_hil.io.recording import Recording, write_recording
from mecanum_hil.model import (
    Calibration,
    Effects,
    RobotProfile,
    load_calibration,
    save_calibration,
    simulate,
    uniform_time,
)

ROBOT = RobotProfile()


@pytest.fixture(scope="module")
def lag_case(tmp_path_factory):
    """A drive lag named on two steps measured on wheels 1 and 2 only, from a user's file
    that holds wheel gains: the recording, the file and the diagnosis."""
    folder = tmp_path_factory.mktemp("lag")
    t = uniform_time(4.0, 100.0)
    cmd = np.zeros((t.size, 3))
    cmd[:, 2] = 90.0
    cmd[(t >= 0.3) & (t < 2.0), 0] = 60.0
    cmd[(t >= 2.0) & (t < 3.2), 0] = 100.0
    truth = Calibration(effects=Effects(drive_lag_s=0.12))
    w = simulate(cmd, t, truth, ROBOT).wheel_rpm[0]
    w = w + np.random.default_rng(3).normal(0.0, 0.25, w.shape)
    w[:, 2:] = np.nan
    rec = Recording(t, cmd, w, np.full((t.size, 3), np.nan))
    user = replace(fit([rec], ROBOT).calibration, effects=Effects(gains=(1.0, 1.0, 1.0, 0.9)))
    path = save_calibration(user, folder / "user.toml")
    d = diagnose([rec], load_calibration(path), ROBOT, names=["steps"],
                 candidates=("drive_lag",), jobs=1)
    assert d.effects == ["drive_lag"], d.to_json()
    return write_recording(rec, folder / "steps.csv"), path, d


def _degenerate(d):
    """``d`` with the fitted motor pole B near zero: a valid model whose drive-lag twin has a
    lag of 1e20 s and A, C times 1e21."""
    step = d.steps[0]
    after = replace(step.calibration_after, B=1e-20)
    step = replace(step, calibration_after=after,
                   ci95={"drive_lag_s": (math.nan, math.nan)})
    return replace(d, steps=(step,), calibration=replace(d.calibration, B=1e-20))


def test_a_diagnosed_drive_lag_has_its_twin(lag_case):
    step = lag_case[2].steps[0]
    assert step.equivalent_problem is None
    assert step.equivalent["drive_lag_s"] == pytest.approx(0.12, rel=0.05)


def test_a_degenerate_twin_is_left_out_and_every_output_is_written(lag_case, tmp_path):
    _, user, d = lag_case
    bad = _degenerate(d)
    step = bad.steps[0]
    assert step.equivalent is None
    assert step.equivalent_problem.startswith(
        "the drive_lag exchange of the fitted model: its drive_lag_s = 1 / B = 1e+20 s")
    assert user.name not in step.equivalent_problem
    doc = json.loads(json.dumps(bad.to_json(), allow_nan=False))
    assert "equivalent" not in doc["effects"][0]
    out = save_calibration(bad.calibration, tmp_path / "cal2.toml")
    assert load_calibration(out).B == 1e-20


def test_the_report_says_the_twin_is_degenerate_and_the_interval_unidentifiable(lag_case,
                                                                                tmp_path):
    csv, _, d = lag_case
    from mecanum_hil.io.timing import read_for_analysis

    text = write_report(_degenerate(d), [read_for_analysis(csv)], tmp_path / "rep",
                        ROBOT).read_text()
    assert ("No equivalent model: degenerate (the drive_lag exchange of the fitted model: "
            "its drive_lag_s = 1 / B = 1e+20 s exceeds 5 s") in text
    assert "Equally: a lag of" not in text
    assert "| `drive_lag_s` |" in text and "| unidentifiable |" in text
    assert "[n/a, n/a]" not in text


@pytest.mark.parametrize("as_json", [False, True])
def test_the_command_ends_well_after_a_degenerate_twin(lag_case, tmp_path, monkeypatch,
                                                       capsys, as_json):
    # the analysis done, the outputs are written and the command ends with exit code 0
    csv, user, d = lag_case
    bad = _degenerate(d)
    monkeypatch.setattr(diagnose_package, "diagnose", lambda *a, **k: bad)
    out, rep = tmp_path / "cal2.toml", tmp_path / "rep"
    capsys.readouterr()
    code = main(["diagnose", str(csv), "--calibration", str(user), "--out", str(out),
                 "--report", str(rep), *(["--json"] if as_json else [])])
    said = capsys.readouterr()
    assert code == 0, said.err
    assert load_calibration(out).effects.drive_lag_s == bad.calibration.effects.drive_lag_s
    assert (rep / "report.md").is_file()
    if as_json:
        assert "equivalent" not in json.loads(said.out)["effects"][0]
    else:
        assert ("drive_lag: no equivalent model: degenerate (the drive_lag exchange of the "
                "fitted model: ") in said.out
    assert str(user) not in said.out + said.err


def test_parameters_the_data_cannot_bound_are_listed_in_the_extended_calibration(lag_case,
                                                                                 tmp_path):
    # wheels 3 and 4 were never measured: their gains are unidentifiable, not left out
    d = lag_case[2]
    assert d.calibration.ci95["gains_2"] is None and d.calibration.ci95["gains_3"] is None
    lo, hi = d.calibration.ci95["drive_lag_s"]
    assert lo < d.calibration.effects.drive_lag_s < hi
    path = save_calibration(d.calibration, tmp_path / "cal2.toml")
    assert 'unidentifiable = ["gains_2", "gains_3"]' in path.read_text()
    assert load_calibration(path).ci95 == d.calibration.ci95


def test_an_interval_past_the_admissible_range_is_written_unidentifiable(tmp_path):
    # the dead time a real diagnosis wrote as [-4672, 4673] s, and an interval of A that
    # reaches below 0 (clipped there)
    cal = Calibration(A=14.7, effects=Effects(dead_time_s=0.5))
    model = _Model(cal, ["A", "B", "C", "dead_time_s"],
                   {"A": (-1.0, 30.4), "B": (15.0, 17.2), "dead_time_s": (-4672.0, 4673.0)})
    final = _final_calibration(model, 1.0, False)
    assert final.ci95 == {"A": (0.0, 30.4), "B": (15.0, 17.2), "dead_time_s": None}
    path = save_calibration(final, tmp_path / "cal2.toml")
    text = path.read_text()
    assert "4672" not in text and 'unidentifiable = ["dead_time_s"]' in text
    assert load_calibration(path).ci95 == final.ci95
