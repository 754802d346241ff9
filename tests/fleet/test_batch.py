"""``batch`` on a two-worker LocalCluster against the serial commands, on the fleet archive."""

from __future__ import annotations

import json
import math
import shutil

import pytest

pytest.importorskip("dask.distributed")
pytest.importorskip("fsspec")
pytest.importorskip("pyarrow")

from mecanum_hil.cli import main
from mecanum_hil.errors import ConfigError
from mecanum_hil.fleet.results import add_drift, read_results, write_results
from mecanum_hil.fleet.runner import BatchSettings, journal_path, run_batch

#: The corrupt file of the fleet archive (conftest.py).
CORRUPT = "robot-a/w2/paper-turn.csv"

W1, W2 = "2026-W46", "2026-W47"


def _inputs(root, row):
    """The files the serial command gets: the row's inputs without the corrupt one."""
    return [str(root / rel) for rel in row["inputs"].split(";") if rel != CORRUPT]


def _serial_json(capsys, *args):
    capsys.readouterr()
    code = main([str(a) for a in args])
    out = capsys.readouterr().out
    return code, json.loads(out)


def _same(a, b):
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-12)


@pytest.fixture(scope="module")
def fit_run(fleet_archive, dask_client, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "results.parquet"
    cals = out.parent / "cals"
    settings = BatchSettings("fit", str(fleet_archive), out, period="week", write_to=str(cals))
    return settings, run_batch(settings, client=dask_client)


def test_fit_batch_equals_serial_fit_and_flags_the_drifted_robots(fit_run, fleet_archive,
                                                                   capsys, tmp_path):
    settings, outcome = fit_run
    rows = read_results(settings.out)
    assert [(r["group"], r["period"]) for r in rows] == [
        (g, w) for g in ("robot-a", "robot-b", "robot-c") for w in (W1, W2)]
    assert outcome.counts.done == 6 and outcome.counts.failed == 0
    for r in rows:
        code, doc = _serial_json(capsys, "fit", *_inputs(fleet_archive, r), "--out",
                                 tmp_path / "cal.toml", "--no-report", "--json")
        assert code == 0
        for k in ("A", "B", "C"):
            assert _same(r[k], doc[k]), (r["group"], r["period"], k)
            assert _same(r[f"{k}_lo"], doc["ci95"][k][0])
            assert _same(r[f"{k}_hi"], doc["ci95"][k][1])
        assert _same(r["rmse_rpm"], doc["rmse_rpm"])
        assert _same(r["fit_percent"], doc["fit_percent"])
    by = {(r["group"], r["period"]): r for r in rows}
    # drift against the previous week: the changed robots, not the unchanged one
    assert by[("robot-b", W2)]["drifted"] is True
    assert by[("robot-c", W2)]["drifted"] is True
    assert by[("robot-a", W2)]["drifted"] is False
    assert all(by[(g, W1)]["drifted"] is None for g in ("robot-a", "robot-b", "robot-c"))
    b1, b2 = by[("robot-b", W1)], by[("robot-b", W2)]
    assert _same(b2["drift_A"], b2["A"] - b1["A"])
    assert b2["drift_A_pct"] < -10  # the truth's A went from 14.7 to 11
    assert "A " in b2["drift_note"]
    # the corrupt file: left out, named in its row, the rest of the group fitted
    a2 = by[("robot-a", W2)]
    assert a2["status"] == "partial" and a2["A"] is not None
    assert CORRUPT in a2["error"] and "line 41" in a2["error"] and "12.5x" in a2["error"]
    assert all(r["status"] == "ok" for r in rows if r is not a2)
    # robot-c's first week has no started_utc: dated by the files' modification time
    assert by[("robot-c", W1)]["n_inputs"] == 2
    # each group's calibration was written, and reads back as a calibration
    from mecanum_hil.model import load_calibration

    cal = load_calibration(settings.write_to + f"/robot-b/{W2}.toml")
    assert _same(cal.A, b2["A"])


def test_fleet_report_joins_one_table_per_period(fit_run, tmp_path, capsys):
    settings, _ = fit_run
    rows = read_results(settings.out)
    tables = []
    for week in (W1, W2):  # as a daily or weekly batch over that period's folder writes them
        tables.append(write_results(add_drift([r for r in rows if r["period"] == week]),
                                    tmp_path / f"{week}.csv"))
    assert not any(r["drifted"] for r in read_results(tables[1]) if r["group"] == "robot-b")
    capsys.readouterr()
    assert main(["fleet-report", *map(str, tables), "--out", str(tmp_path / "rep")]) == 0
    assert "drifted: robot-b, robot-c" in capsys.readouterr().out
    summary = (tmp_path / "rep" / "summary.md").read_text()
    assert "**Drifted: 2 robot(s)**: robot-b, robot-c" in summary


def test_fleet_report_cut_short_leaves_the_earlier_report(fit_run, tmp_path, monkeypatch):
    # an interrupted report over an earlier one must not leave a summary beside newer plots
    import mecanum_hil.fleet.report as report

    settings, _ = fit_run
    rows = read_results(settings.out)
    first = report.write_report(rows, tmp_path / "rep")
    assert first["summary"] == tmp_path / "rep" / "summary.md" and first["trends"].exists()
    before = {p.name: p.read_bytes() for p in (tmp_path / "rep").iterdir()}
    real = report.plot_trends

    def plot_then_interrupt(*args, **kwargs):
        real(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "plot_trends", plot_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        report.write_report(rows, tmp_path / "rep", source="second")
    assert {p.name: p.read_bytes() for p in (tmp_path / "rep").iterdir()} == before


def test_resume_skips_unchanged_groups_and_reruns_changed_ones(fleet_archive, dask_client,
                                                               tmp_path):
    out = tmp_path / "results.csv"
    shutil.copytree(fleet_archive, tmp_path / "archive")
    root = tmp_path / "archive"
    s = BatchSettings("fit", str(root), out, period="week")
    run_batch(s, client=dask_client)
    again = run_batch(s, client=dask_client)
    assert again.counts.unchanged == 6 and again.counts.done == 0
    # a new modification time alone is no change; new content is
    path = root / "robot-b" / "w1" / "paper-turn.csv"
    path.touch()
    side = path.with_suffix(".json")
    doc = json.loads(side.read_text())
    side.write_text(json.dumps({**doc, "notes": "re-labelled"}))
    third = run_batch(s, client=dask_client)
    assert third.counts.unchanged == 5 and third.counts.done == 1
    assert [(r["group"], r["period"]) for r in third.rows] == \
        [(r["group"], r["period"]) for r in again.rows]
    # an interrupted batch: only its journal exists; the journaled groups are not run again
    rows = read_results(out)
    out.unlink()
    with journal_path(out).open("w") as fh:
        for r in rows[:4]:
            fh.write(json.dumps(r) + "\n")
        fh.write('{"group": "robot-c", "per')  # the line the interruption cut
    resumed = run_batch(s, client=dask_client)
    assert resumed.counts.unchanged == 4 and resumed.counts.done == 2
    assert not journal_path(out).exists()
    assert [r["A"] for r in read_results(out)] == [r["A"] for r in rows]


@pytest.mark.slow
def test_diagnose_batch_equals_serial_fit_then_diagnose(fleet_archive, dask_client, capsys,
                                                        tmp_path):
    # robot-c alone (diagnose costs ~5 s of CPU a group): the dead time of its second week
    root = tmp_path / "archive"
    shutil.copytree(fleet_archive / "robot-c", root / "robot-c")
    out = tmp_path / "diag.csv"
    outcome = run_batch(BatchSettings("diagnose", str(root), out, period="week"),
                        client=dask_client)
    by = {(r["group"], r["period"]): r for r in outcome.rows}
    r = by[("robot-c", W2)]
    assert r["effects"] == "dead_time" and r["effects_appeared"] == "dead_time"
    assert r["drifted"] is True
    assert by[("robot-c", W1)]["effects"] == ""
    files = _inputs(root, r)
    cal = tmp_path / "cal.toml"
    assert main(["fit", *files, "--out", str(cal), "--no-report"]) == 0
    code, doc = _serial_json(capsys, "diagnose", *files, "--calibration", cal, "--json")
    assert code == 0
    assert r["effects"] == ",".join(e["effect"] for e in doc["effects"])
    assert _same(r["rmse_rpm"], doc["rmse_final"])
    assert _same(r["rmse_initial_rpm"], doc["rmse_initial"])
    # the same search in another process (a Dask worker, this one with or without a helper,
    # by the machine's load): the converged values agree to the last digits a search can give
    got = json.loads(r["details"])["diagnosis"]["effects"][0]["parameters"]
    want = doc["effects"][0]["parameters"]
    assert got.keys() == want.keys()
    assert all(math.isclose(got[k], want[k], rel_tol=1e-9) for k in got)


def test_shadow_batch_replays_against_each_robots_calibration(fit_run, fleet_archive,
                                                              dask_client, capsys, tmp_path):
    settings, _ = fit_run
    template = settings.write_to + f"/{{group}}/{W1}.toml"
    out = tmp_path / "shadow.parquet"
    outcome = run_batch(BatchSettings("shadow", str(fleet_archive), out, period="week",
                                      calibration=template), client=dask_client)
    by = {(r["group"], r["period"]): r for r in outcome.rows}
    assert by[("robot-b", W2)]["alarms"] > 0  # the changed robot against its old model
    assert by[("robot-a", W1)]["alarms"] == 0
    assert by[("robot-a", W2)]["status"] == "partial"
    r = by[("robot-b", W2)]
    total = 0
    for f in _inputs(fleet_archive, r):
        code, doc = _serial_json(capsys, "shadow", "--replay", f, "--calibration",
                                 template.format(group="robot-b"), "--json", "--no-events")
        total += len(doc["alarms"])
        assert code == (3 if doc["alarms"] else 0)
    assert r["alarms"] == total


def test_a_failing_group_fails_alone(fleet_archive, dask_client, tmp_path):
    root = tmp_path / "archive"
    shutil.copytree(fleet_archive / "robot-b", root / "robot-b")
    (root / "robot-x").mkdir()
    (root / "robot-x" / "run.csv").write_text("not,a,recording\n1,2,3\n")
    (root / "loose.csv").write_text("t_s\n")
    outcome = run_batch(BatchSettings("fit", str(root), tmp_path / "r.csv"), client=dask_client)
    by = {r["group"]: r for r in outcome.rows}
    assert by["robot-b"]["status"] == "ok"
    assert by["robot-x"]["status"] == "failed"
    assert "robot-x/run.csv" in by["robot-x"]["error"]
    assert by["(outside any robot folder)"]["status"] == "failed"
    assert "loose.csv" in by["(outside any robot folder)"]["error"]
    assert outcome.counts.failed == 2 and outcome.counts.done == 1


@pytest.mark.slow
def test_batch_and_fleet_report_from_the_command_line(fleet_archive, tmp_path, capsys):
    out = tmp_path / "results.csv"
    code = main(["batch", "fit", f"file://{fleet_archive}", "--out", str(out), "--period", "week",
                 "--workers", "2", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert code == 0
    assert doc["groups"] == 6 and doc["partial"] == 1
    assert doc["drifted"] == ["robot-b", "robot-c"]
    report = tmp_path / "report"
    assert main(["fleet-report", str(out), "--out", str(report)]) == 0
    summary = (report / "summary.md").read_text()
    assert "**Drifted: 2 robot(s)**: robot-b, robot-c" in summary
    assert CORRUPT in summary
    for png in ("trends.png", "robot-robot-b.png", "robot-robot-c.png"):
        assert (report / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_arguments_are_one_line_errors(fleet_archive, tmp_path, capsys):
    assert main(["batch", "fit", str(fleet_archive), "--out", str(tmp_path / "r.txt")]) == 1
    assert "error: " in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["batch", "fit", str(tmp_path / "empty"), "--out",
                 str(tmp_path / "r.csv")]) == 1
    assert "no recordings" in capsys.readouterr().err
    assert main(["batch", "fit", str(fleet_archive), "--out", str(tmp_path / "r.csv"),
                 "--period", "month"]) == 1
    with pytest.raises(ConfigError, match="cannot reach the Dask scheduler"):
        run_batch(BatchSettings("fit", str(fleet_archive), tmp_path / "r.csv",
                                scheduler="tcp://127.0.0.1:9", connect_timeout_s=1.0))


def test_a_replay_that_compared_nothing_is_left_out_not_counted_as_no_alarm(fit_run,
                                                                           fleet_archive):
    # shadow --replay refuses such a replay (exit 1); the batch's "0 alarms" would read as a
    # robot that matched its model
    from mecanum_hil.fleet import stages
    from mecanum_hil.io.recording import read_recording
    from mecanum_hil.model import RobotProfile, load_calibration

    settings, _ = fit_run
    cal = load_calibration(settings.write_to + f"/robot-a/{W1}.toml")
    whole = read_recording(next((fleet_archive / "robot-a" / "w1").glob("*.csv")))
    short = whole.select(whole.t_s < 1.0)  # shorter than the monitor's warm-up
    row, bad = stages.run_shadow([whole, short], ["whole.csv", "short.csv"], RobotProfile(), cal)
    assert list(row["details"]["replays"]) == ["whole.csv"]
    assert len(bad) == 1 and bad[0].startswith("short.csv: the monitor never armed"), bad


def test_a_stage_whose_rows_changed_meaning_is_run_again_on_resume(fleet_archive, dask_client,
                                                                   tmp_path, monkeypatch):
    # a table written before a stage changed what it writes must not keep its old rows as
    # "unchanged" (the shadow stage's 0 alarms for replays that compared nothing)
    from mecanum_hil.fleet import stages
    from mecanum_hil.fleet.tasks import COMMANDS

    assert set(stages.REVISIONS) == set(COMMANDS)
    shutil.copytree(fleet_archive / "robot-b", tmp_path / "archive" / "robot-b")
    s = BatchSettings("fit", str(tmp_path / "archive"), tmp_path / "r.csv", period="week")
    run_batch(s, client=dask_client)
    assert run_batch(s, client=dask_client).counts.unchanged == 2
    monkeypatch.setitem(stages.REVISIONS, "fit", stages.REVISIONS["fit"] + 1)
    again = run_batch(s, client=dask_client)
    assert again.counts.unchanged == 0 and again.counts.done == 2
