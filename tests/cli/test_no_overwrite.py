"""An output that names an input is refused in one line, before anything is written: the data
already recorded (a recording, a raw log, its sidecar) stays as it was."""

from __future__ import annotations

import shutil

import pytest

SAMPLE = "recordings/samples/paper-step-60"


@pytest.fixture
def run_csv(repo, tmp_path):
    for ext in (".csv", ".json"):
        shutil.copy(repo / f"{SAMPLE}{ext}", tmp_path / f"run{ext}")
    return tmp_path / "run.csv"


@pytest.mark.parametrize("argv, option", [
    (["fit", "{rec}", "-o", "{rec}", "--no-report"], "--out"),
    (["fit", "{rec}", "-o", "{dir}/cal.toml", "--report", "{rec}"], "--report"),
    (["diagnose", "{rec}", "-o", "{rec}"], "--out"),
    (["simulate", "--commands", "{rec}", "-o", "{rec}"], "--out"),
    (["simulate", "--commands", "{rec}", "-o", "{dir}/sim.csv", "--plot", "{dir}/run.json"],
     "--plot"),
    (["shadow", "--replay", "{rec}", "--events", "{rec}"], "--events"),
    (["shadow", "--replay", "{rec}", "--events", "{dir}/run.json"], "--events"),
    (["export", "{rec}", "-o", "{rec}"], "--out"),
])
def test_an_output_that_names_an_input_is_refused(run_csv, one_line_error, argv, option):
    before = {p.name: p.read_bytes() for p in run_csv.parent.iterdir()}
    argv = [a.format(rec=run_csv, dir=run_csv.parent) for a in argv]
    err = one_line_error(argv)
    assert f"{option} would overwrite" in err and "write to another file" in err, err
    assert {p.name: p.read_bytes() for p in run_csv.parent.iterdir()} == before


def test_import_does_not_overwrite_its_log(tmp_path, one_line_error):
    log = tmp_path / "log.csv"
    log.write_text("t,speed\n0.000,0\n0.002,1\n0.004,2\n0.006,3\n")
    mp = tmp_path / "map.toml"
    mp.write_text('format = "text"\n[time]\ncolumn = "t"\nunit = "s"\n'
                  '[wheel_setpoint]\nvalue = 100.0\nunit = "rpm"\n'
                  '[wheel1]\ncolumn = "speed"\nunit = "rpm"\n')
    before = log.read_bytes()
    err = one_line_error(["import", str(log), "--map", str(mp), "-o", str(log)])
    assert "--out would overwrite the log" in err
    assert log.read_bytes() == before


def test_an_unsupported_plot_extension_is_one_line(run_csv, one_line_error):
    err = one_line_error(["simulate", "--commands", str(run_csv), "-o",
                          str(run_csv.parent / "sim.csv"), "--plot",
                          str(run_csv.parent / "sim.xyz")])
    assert "cannot write plot" in err and "use .png" in err
