"""mecanum-hil fit as a user runs it: JSON shape, files written, bad input, real data."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.identify.files import fit_files
from mecanum_hil.io.recording import Recording, read_recording, write_recording
from mecanum_hil.model import Calibration, RobotProfile, load_calibration, simulate, uniform_time


def cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "mecanum_hil", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


@pytest.fixture
def run(capsys):
    """The CLI in this process (as the console script runs it), for the quick cases."""
    def go(*args):
        capsys.readouterr()
        code = main([str(a) for a in args])
        out = capsys.readouterr()
        return code, out.out, out.err
    return go


@pytest.fixture
def step_csv(tmp_path):
    t = uniform_time(1.0, 100.0)
    cmd = np.tile([60.0, 0.0, 90.0], (t.size, 1))
    w = simulate(cmd, t, Calibration(A=27.0, B=8.5, C=610.0)).wheel_rpm[0]
    w = w + np.random.default_rng(0).normal(0.0, 0.5, w.shape)
    return write_recording(Recording(t, cmd, w, np.full((t.size, 3), np.nan)),
                           tmp_path / "step.csv")


def test_json_output_calibration_and_report(step_csv, tmp_path):
    out = tmp_path / "cal" / "fitted.toml"
    r = cli("fit", step_csv, "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert list(doc) == ["A", "B", "C", "rmse_rpm", "fit_percent", "ci95", "method"]
    assert list(doc["ci95"]) == ["A", "B", "C"]
    assert all(len(v) == 2 and v[0] < v[1] for v in doc["ci95"].values())
    assert doc["method"] == "lsq" and doc["fit_percent"] > 90
    assert doc["A"] == pytest.approx(27.0, rel=0.05)
    cal = load_calibration(out)
    assert (cal.A, cal.B, cal.C) == (doc["A"], doc["B"], doc["C"])
    assert cal.info["sources"] == [str(step_csv)]
    assert out.with_suffix(".png").stat().st_size > 10_000
    # every --calibration accepts it
    r = cli("simulate", "--profile", "paper-step-60", "-c", out, "--out", tmp_path / "s.csv")
    assert r.returncode == 0, r.stderr


def test_paper_grid_with_configured_grids(step_csv, tmp_path, run):
    out = tmp_path / "grid.toml"
    code, stdout, err = run("fit", step_csv, "--out", out, "--method", "paper-grid", "--a-grid",
                            "0:60:1", "--b-grid", "5.5:25.5:0.5", "--c-grid", "0:1000:5",
                            "--json", "--no-report")
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["method"] == "paper-grid"
    assert doc["A"] == int(doc["A"]) and doc["C"] % 5 == 0
    assert not out.with_suffix(".png").exists()
    assert load_calibration(out).info["grid_c"] == "0:1000:5"


def test_bad_input_is_one_line_and_writes_nothing(step_csv, tmp_path, run):
    rec = read_recording(step_csv)
    blind = write_recording(rec.with_values(wheel_rpm=np.full_like(rec.wheel_rpm, np.nan)),
                            tmp_path / "blind.csv")
    still = write_recording(rec.with_values(commands=np.tile([0.0, 0, 90], (len(rec), 1))),
                            tmp_path / "still.csv")
    bad_time = tmp_path / "bad_time.csv"
    lines = step_csv.read_text().splitlines()
    lines[5], lines[6] = lines[6], lines[5]
    bad_time.write_text("\n".join(lines) + "\n")
    for src, msg in [(blind, "no measured wheel speed"), (still, "no excitation"),
                     (bad_time, "does not increase")]:
        out = tmp_path / f"{src.stem}.toml"
        code, _, err = run("fit", src, "--out", out)
        assert code == 1
        assert err.startswith("error: ") and msg in err
        assert len(err.strip().splitlines()) == 1
        assert not out.exists() and not out.with_suffix(".png").exists()
    code, _, err = run("fit", step_csv, "--out", tmp_path / "x.toml", "--a-grid", "0:10:1")
    assert code == 1 and "paper-grid" in err
    # the same through the console script: one line, exit 1
    r = cli("fit", blind, "--out", tmp_path / "blind.toml")
    assert r.returncode == 1 and r.stderr.startswith("error: ")
    assert not (tmp_path / "blind.toml").exists()


def test_coefficients_the_data_cannot_bound_are_null_in_json_and_listed_in_toml(tmp_path, run):
    # a step sampled every 2 s: every sample is settled, so the model's level (the target,
    # with integral action) fits them whatever A, B and C are
    t = np.array([0.0, 2.0, 4.0, 6.0])
    cmd = np.tile([60.0, 0.0, 90.0], (4, 1))
    w = np.tile([0.0, 60.1, 59.9, 60.0], (4, 1)).T + np.array([0, 0.1, -0.1, 0.05])
    rec = write_recording(Recording(t, cmd, w, np.full((4, 3), np.nan)),
                          tmp_path / "settled.csv")
    out = tmp_path / "cal.toml"
    code, stdout, stderr = run("fit", rec, "--out", out, "--no-report", "--json")
    assert code == 0, stderr
    doc = json.loads(stdout)
    assert doc["ci95"] == {"A": None, "B": None, "C": None}
    assert "A is not identifiable from these data" in stderr
    text = out.read_text()
    assert 'unidentifiable = ["A", "B", "C"]' in text and "\nA = [" not in text
    assert load_calibration(out).ci95 == {"A": None, "B": None, "C": None}
    code, stdout, _ = run("fit", rec, "--out", tmp_path / "again.toml", "--no-report")
    assert code == 0 and "A = " in stdout
    assert "(unidentifiable: the data cannot bound it)" in stdout and "nan" not in stdout


def test_real_micromouse_step_responses(shared_real_data, tmp_path):
    robot = RobotProfile()
    figures = {}
    for name in ("testPid7", "testPid8", "controllerDelayImpact1ms"):
        path = shared_real_data / "micromouse" / f"{name}.csv"
        png = tmp_path / f"{name}.png" if name == "testPid7" else None
        lsq = fit_files([path], tmp_path / f"{name}.toml", robot, report=png)
        figures[name] = lsq.result.fit_percent
        assert load_calibration(lsq.calibration_path).info["fit_percent"] == lsq.result.fit_percent
    # closed-loop step responses of a real robot: the two tuned runs fit well, the one with a
    # steady-state offset (a delay inside the control task) less so
    assert figures["testPid7"] > 60 and figures["testPid8"] > 65
    assert figures["controllerDelayImpact1ms"] > 25
    assert (tmp_path / "testPid7.png").stat().st_size > 10_000


def test_a_report_named_other_than_png_is_refused_before_the_fit(step_csv, tmp_path, run):
    code, _, err = run("fit", step_csv, "--out", tmp_path / "c.toml", "--report",
                         tmp_path / "r.svg")
    assert code != 0 and err.startswith("error: ") and ".png" in err
    assert err.count("\n") == 1 and not (tmp_path / "c.toml").exists()


def test_fit_demo_writes_calibration_and_report(step_csv, tmp_path):
    from mecanum_hil.identify.files import fit_demo

    rec = read_recording(step_csv)
    profile_only = write_recording(rec.with_values(wheel_rpm=np.full_like(rec.wheel_rpm, np.nan)),
                                   tmp_path / "profile.csv")
    lines = []
    written = fit_demo([step_csv, profile_only], tmp_path / "fit", RobotProfile(), lines.append)
    cal = load_calibration(written["fit/calibration"])
    assert cal.info["sources"] == [str(step_csv)]
    assert cal.A == pytest.approx(27.0, rel=0.05)
    assert written["fit/report"].stat().st_size > 10_000
    assert "fit (lsq) of 1 recordings" in lines[0]
