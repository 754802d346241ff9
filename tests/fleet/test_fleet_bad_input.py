"""batch and fleet-report with bad input, the second sweep: a bad option or calibration is one
error line before any cluster starts and leaves the results table as it was; a group that fails
in a re-run does not replace its earlier result; --out, --write and --scheduler are checked
before the work; fleet-report refuses a table with columns cut out."""

from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("fsspec")
pytest.importorskip("pyarrow")

from mecanum_hil.cli import main
from mecanum_hil.fleet import runner
from mecanum_hil.fleet.results import normalise, read_results, write_results
from mecanum_hil.fleet.tasks import run_group

BAD_CAL = "[motor]\nA = -1\nB = 1\nC = 1\n"


@pytest.fixture()
def small_archive(fleet_archive, tmp_path):
    root = tmp_path / "archive"
    shutil.copytree(fleet_archive / "robot-b" / "w1", root / "robot-b")
    return root


@pytest.fixture()
def no_cluster(monkeypatch):
    """Starting the local cluster is a failure of the test (exit 70, 'internal error')."""
    def refuse(*_a, **_k):
        raise AssertionError("a local Dask cluster was started")

    monkeypatch.setattr(runner, "local_cluster", refuse)


def _one_error(argv, capsys) -> str:
    capsys.readouterr()
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 1 and err.startswith("error: ") and "\n" not in err, (code, err)
    assert "internal error" not in err and "Traceback" not in err
    return err


def _table(path: Path, command: str = "fit", **extra) -> Path:
    row = normalise({"group": "robot-b", "period": "", "command": command, "status": "ok",
                     "n_inputs": 1, "inputs": "robot-b/r.csv", "A": 14.7, "A_lo": 14.6,
                     "A_hi": 14.8, "B": 16.1, "B_lo": 16.0, "B_hi": 16.2, "C": 303.0,
                     "C_lo": 302.0, "C_hi": 304.0, "content_hash": "abc", **extra})
    return write_results([row], path)


def test_a_bad_calibration_is_refused_before_dask_and_the_table_kept(small_archive, tmp_path,
                                                                     dask_client, no_cluster,
                                                                     capsys):
    out = tmp_path / "fits.csv"
    assert main(["batch", "fit", str(small_archive), "-o", str(out), "--scheduler",
                 dask_client.scheduler.address]) == 0
    before = out.read_bytes()
    assert [r["status"] for r in read_results(out)] == ["ok"]
    bad = tmp_path / "bad.toml"
    bad.write_text(BAD_CAL)
    for extra in ([], ["--no-resume"]):
        err = _one_error(["batch", "fit", small_archive, "-o", out, "-c", bad, *extra], capsys)
        assert "bad.toml" in err and "motor.A" in err
        assert out.read_bytes() == before
    assert "no drivers file" in _one_error(
        ["batch", "fit", small_archive, "-o", out, "--robot", "nope"], capsys)
    assert out.read_bytes() == before


@pytest.mark.parametrize(("stage", "args", "says"), [
    ("measure-video", ["--min-found", "5"], "--min-found must be within 0..1"),
    ("measure-video", ["--roi", "9:1,2,3"], "--roi '9:1,2,3'"),
    ("shadow", ["--threshold", "-1"], "threshold_h"),
    ("shadow", ["--noise-rpm", "0"], "noise_rpm"),
    ("diagnose", ["--candidates", "nope,dead_time"], "unknown effect(s) 'nope'"),
    ("diagnose", ["--candidates", ","], "--candidates names no effect"),
])
def test_a_bad_stage_option_is_refused_before_dask_and_the_table_kept(
        small_archive, tmp_path, no_cluster, capsys, stage, args, says):
    out = _table(tmp_path / "res.csv", command=stage)
    before = out.read_bytes()
    err = _one_error(["batch", stage, small_archive, "-o", out, *args], capsys)
    assert says in err
    assert out.read_bytes() == before


def test_a_failing_group_keeps_its_earlier_result(small_archive, tmp_path, dask_client,
                                                  no_cluster, capsys):
    """The table holds robot-b's ok row; a re-run in which robot-b fails (its calibration
    unreadable while planning, or its recordings ruined on the worker) keeps that row, says so
    in a warning and in the row's details, and ends with exit 1 (every group failed)."""
    out = tmp_path / "fits.csv"
    address = dask_client.scheduler.address
    assert main(["batch", "fit", str(small_archive), "-o", str(out), "--scheduler",
                 address]) == 0
    ok = read_results(out)[0]
    assert ok["status"] == "ok"
    (tmp_path / "cals").mkdir()
    (tmp_path / "cals" / "robot-b.toml").write_text(BAD_CAL)
    capsys.readouterr()
    # planning failure: no worker is needed (no_cluster), the earlier row survives
    for extra in ([], ["--no-resume"]):
        code = main(["batch", "fit", str(small_archive), "-o", str(out), "-c",
                     str(tmp_path / "cals" / "{group}.toml"), *extra])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1
        assert err[-2].startswith("warning: robot-b: calibration: ") and \
            err[-2].endswith("(the table keeps its earlier row)")
        assert err[-1].startswith("error: every group failed (1)") and \
            "keeps the earlier rows of 1 of them" in err[-1]
        row = read_results(out)[0]
        assert row["status"] == "ok" and row["A"] == ok["A"]
        assert row["content_hash"] == ok["content_hash"]
        assert "motor.A" in json.loads(row["details"])["rerun_failed"]["error"]
    # a failure on the worker: every recording of the group unreadable
    for rec in (small_archive / "robot-b").glob("*.csv"):
        rec.write_text("not,a,recording\n1,2,3\n")
    code = main(["batch", "fit", str(small_archive), "-o", str(out), "--scheduler", address])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and "(the table keeps its earlier row)" in err[-2]
    row = read_results(out)[0]
    assert row["status"] == "ok" and row["A"] == ok["A"]
    assert "no readable recording" in json.loads(row["details"])["rerun_failed"]["error"]
    assert not runner.journal_path(out).exists()


def test_out_that_cannot_be_written_is_refused_before_starting(small_archive, tmp_path,
                                                               no_cluster, capsys):
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    err = _one_error(["batch", "fit", small_archive, "-o", a_file / "b.csv"], capsys)
    assert err.startswith("error: --out ") and "is a file, not a folder" in err
    (tmp_path / "folder.csv").mkdir()
    assert "--out is a folder" in _one_error(
        ["batch", "fit", small_archive, "-o", tmp_path / "folder.csv"], capsys)
    if Path("/proc/self").is_dir():
        err = _one_error(["batch", "fit", small_archive, "-o", "/proc/b.csv"], capsys)
        assert "--out /proc/b.csv: cannot write in /proc" in err


@pytest.mark.parametrize("address", ["foo", "tcp://host", "tcp://host:0", "tcp://host:99999",
                                     "udp://host:8786", "tcp://:8786", "tcp://h/x:1"])
def test_a_scheduler_that_is_no_address_names_what_is_accepted(small_archive, tmp_path,
                                                               capsys, address):
    err = _one_error(["batch", "fit", small_archive, "-o", tmp_path / "o.csv", "--scheduler",
                      address], capsys)
    assert f"--scheduler {address!r}" in err and "tcp://HOST:PORT" in err
    assert not (tmp_path / "o.csv").exists()


def test_write_that_cannot_take_the_outputs_is_refused_before_starting(small_archive, tmp_path,
                                                                       no_cluster, capsys):
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    cases = {str(a_file): "a file, not a folder", str(a_file / "sub"): "is a file, not a folder",
             "nope://x/y": "Protocol not known"}
    if Path("/proc/self").is_dir():
        cases["/proc/w"] = "cannot write in /proc:"
    for write, says in cases.items():
        err = _one_error(["batch", "fit", small_archive, "-o", tmp_path / "o.csv", "--write",
                          write], capsys)
        assert err.startswith(f"error: --write {write}: ") and says in err, err
    assert not (tmp_path / "o.csv").exists() and a_file.read_text() == "x"


def test_a_group_whose_output_cannot_be_written_fails_in_one_line(small_archive, tmp_path):
    """--write checked before starting can still go wrong later (a file put in the way): the
    group's row says so in one line, not 'internal error'."""
    specs, _ = runner.plan(runner.BatchSettings("fit", str(small_archive), tmp_path / "o.csv"))
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    row = run_group(dataclasses.replace(specs[0], write_to=str(blocker / "cals")))
    assert row["status"] == "failed" and "internal error" not in row["error"]
    assert row["error"].startswith("--write: cannot write ") and "\n" not in row["error"]


def _drop_columns(src: Path, dst: Path, drop: set[str]) -> Path:
    with src.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    keep = [c for c in rows[0] if c not in drop]
    with dst.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keep, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return dst


def test_fleet_report_refuses_a_table_with_columns_cut_out(tmp_path, capsys):
    good = _table(tmp_path / "res.csv")
    no_a = _drop_columns(good, tmp_path / "no-a.csv", {"A"})
    err = _one_error(["fleet-report", no_a, "-o", tmp_path / "rep"], capsys)
    assert "no-a.csv" in err and "(no 'A' column)" in err
    several = _drop_columns(good, tmp_path / "cut.csv", {"B_lo", "drifted", "worker"})
    err = _one_error(["fleet-report", good, several, "-o", tmp_path / "rep"], capsys)
    assert "cut.csv" in err and "(no 'B_lo', 'drifted' columns)" in err
    import pyarrow.parquet as pq

    pq_good = _table(tmp_path / "res.parquet")
    pq.write_table(pq.read_table(pq_good).drop_columns(["C"]), tmp_path / "no-c.parquet")
    assert "(no 'C' column)" in _one_error(
        ["fleet-report", tmp_path / "no-c.parquet", "-o", tmp_path / "rep"], capsys)
    assert not (tmp_path / "rep" / "summary.md").exists()


def test_batch_refuses_to_resume_from_a_table_with_columns_cut_out(small_archive, tmp_path,
                                                                    no_cluster, capsys):
    no_a = _drop_columns(_table(tmp_path / "res.csv"), tmp_path / "no-a.csv", {"A"})
    before = no_a.read_bytes()
    err = _one_error(["batch", "fit", small_archive, "-o", no_a], capsys)
    assert "(no 'A' column)" in err and no_a.read_bytes() == before
