"""batch and fleet-report with bad input: one error line and a non-zero exit, never an input
overwritten, a KeyError, or exit 0 with no result (every group failed, a table with no rows)."""

from __future__ import annotations

import shutil

import pytest

from mecanum_hil.cli import main
from mecanum_hil.fleet.results import COLUMNS, normalise, write_results


@pytest.fixture()
def small_archive(fleet_archive, tmp_path):
    root = tmp_path / "archive"
    shutil.copytree(fleet_archive / "robot-b" / "w1", root / "robot-b")
    return root


def _one_error(argv, capsys) -> str:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code != 0 and err.startswith("error: ") and "\n" not in err, err
    assert "internal error" not in err
    return err


def test_results_table_over_an_archive_recording_is_refused(small_archive, capsys):
    rec = next((small_archive / "robot-b").glob("*.csv"))
    before = rec.read_bytes()
    err = _one_error(["batch", "fit", small_archive, "-o", rec, "--no-resume"], capsys)
    assert "would overwrite an input of the archive" in err
    assert rec.read_bytes() == before


def test_a_new_results_csv_inside_the_archive_is_refused(small_archive, capsys):
    """It would join the archive's recordings: the next run reads it as one."""
    out = small_archive / "robot-b" / "results.csv"
    err = _one_error(["batch", "fit", small_archive, "-o", out, "--no-resume"], capsys)
    assert "would be read as one of its recordings" in err and not out.exists()


def test_an_unknown_calibration_placeholder_names_the_known_ones(small_archive, tmp_path,
                                                                 capsys):
    err = _one_error(["batch", "fit", small_archive, "-o", tmp_path / "r.csv", "-c",
                      "cals/{nope}.toml"], capsys)
    assert "{nope}" in err and "{group}" in err and "{period}" in err
    assert not (tmp_path / "r.csv").exists()


def test_a_period_level_no_file_has_is_refused_before_running(small_archive, tmp_path, capsys):
    err = _one_error(["batch", "fit", small_archive, "-o", tmp_path / "r.csv",
                      "--period-level", "7"], capsys)
    assert "--period-level 7" in err and not (tmp_path / "r.csv").exists()


@pytest.mark.parametrize("args", [["--drift-threshold", "nan"], ["--drift-threshold", "-5"]])
def test_bad_drift_threshold_is_refused(small_archive, tmp_path, capsys, args):
    assert "--drift-threshold" in _one_error(
        ["batch", "fit", small_archive, "-o", tmp_path / "r.csv", *args], capsys)


@pytest.mark.parametrize("fps", ["1e-5", "1e-300", "inf"])
def test_batch_measure_video_fps_has_the_bounds_of_measure_video(small_archive, tmp_path,
                                                                 capsys, fps):
    assert "--fps must be within 0.1" in _one_error(
        ["batch", "measure-video", small_archive, "-o", tmp_path / "r.csv", "--fps", fps],
        capsys)


def test_every_group_failed_is_a_non_zero_exit(dask_client, tmp_path, capsys):
    root = tmp_path / "archive"
    (root / "robot-x").mkdir(parents=True)
    (root / "robot-x" / "run.csv").write_text("not,a,recording\n1,2,3\n")
    out = tmp_path / "r.csv"
    code = main(["batch", "fit", str(root), "-o", str(out), "--scheduler",
                 dask_client.scheduler.address])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and err[-1].startswith("error: every group failed (1)")
    assert "robot-x" in err[-1] and out.exists()  # the table still says why


def _table(tmp_path):
    row = normalise({"group": "robot-a", "period": "w1", "command": "fit", "status": "ok",
                     "n_inputs": 1, "inputs": "robot-a/r.csv", "A": 14.7, "A_lo": 14.6,
                     "A_hi": 14.8, "B": 16.1, "B_lo": 16.0, "B_hi": 16.2, "C": 303.0,
                     "C_lo": 302.0, "C_hi": 304.0})
    return write_results([row], tmp_path / "res.csv")


def test_fleet_report_refuses_tables_without_rows(tmp_path, capsys):
    good = _table(tmp_path)
    header = good.read_text().splitlines()[0]
    cases = {"empty.csv": "", "header.csv": header + "\n", "cut.csv": header[:40]}
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        err = _one_error(["fleet-report", tmp_path / name, "-o", tmp_path / "rep"], capsys)
        assert name in err and "no rows" in err
    assert not (tmp_path / "rep" / "summary.md").exists()


def test_fleet_report_names_text_in_a_number_column(tmp_path, capsys):
    good = _table(tmp_path)
    lines = good.read_text().splitlines()
    cells = lines[1].split(",")
    cells[COLUMNS.index("A")] = "abc"
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join([lines[0], ",".join(cells)]) + "\n")
    err = _one_error(["fleet-report", bad, "-o", tmp_path / "rep"], capsys)
    assert "line 2, column A: 'abc' is not a number" in err


def test_fleet_report_bad_threshold_and_out_onto_the_table(tmp_path, capsys):
    good = _table(tmp_path)
    for value in ("nan", "-5", "inf"):
        assert "--drift-threshold" in _one_error(
            ["fleet-report", good, "-o", tmp_path / "rep", "--drift-threshold", value], capsys)
    before = good.read_bytes()
    assert "results table given" in _one_error(["fleet-report", good, "-o", good], capsys)
    assert good.read_bytes() == before
    assert main(["fleet-report", str(good), "-o", str(tmp_path / "rep")]) == 0
