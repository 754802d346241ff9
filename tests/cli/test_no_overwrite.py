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
    # a recording named otherwise still writes its sidecar, run.json: the input's
    (["simulate", "--commands", "{rec}", "-o", "{dir}/run.txt"], "--out"),
    # record creates its recording before the first command: --commands would be lost
    (["record", "--port", "{dir}/no-port", "--commands", "{rec}", "-o", "{rec}"], "--out"),
    (["train", "-c", "{dir}/cal.toml", "-o", "{dir}/cal.toml"], "--out"),
])
def test_an_output_that_names_an_input_is_refused(run_csv, one_line_error, argv, option):
    (run_csv.parent / "cal.toml").write_text("[motor]\nA = 14.7\nB = 16.1\nC = 303.0\n")
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


def test_calibrate_camera_does_not_write_over_its_images(tmp_path, one_line_error):
    folder = tmp_path / "views"
    folder.mkdir()
    (folder / "v0.png").write_bytes(b"not really an image")
    before = (folder / "v0.png").read_bytes()
    err = one_line_error(["calibrate-camera", str(folder), "--board", "charuco:7x5:0.04:0.03",
                          "-o", str(folder / "v0.png")])
    assert "--out would overwrite an image of the board" in err, err
    assert (folder / "v0.png").read_bytes() == before


def test_a_recording_is_never_written_as_json(run_csv, one_line_error):
    keep = run_csv.parent / "keep.json"
    keep.write_text('{"mine": 1}')
    err = one_line_error(["simulate", "--commands", str(run_csv), "-o", str(keep)])
    assert "a recording cannot be named .json" in err, err
    assert keep.read_text() == '{"mine": 1}'


def test_record_does_not_replace_a_recording_made_before(run_csv, one_line_error, tmp_path):
    # refused before the port is opened (there is none here: --force reaches the port)
    before = {p.name: p.read_bytes() for p in run_csv.parent.iterdir()}
    port = str(tmp_path / "no-port")
    err = one_line_error(["record", "--port", port, "--profile", "paper-step-60", "-o",
                          str(run_csv)])
    assert "a recording is already there" in err and "--force" in err
    assert {p.name: p.read_bytes() for p in run_csv.parent.iterdir()} == before
    # the sidecar or the event log alone count too
    other = tmp_path / "other.csv"
    (tmp_path / "other.shadow.jsonl").write_text("{}\n")
    err = one_line_error(["record", "--port", port, "--profile", "paper-step-60", "-o",
                          str(other)])
    assert "a recording is already there" in err
    err = one_line_error(["record", "--port", port, "--profile", "paper-step-60", "-o",
                          str(other), "--force"])
    assert "already there" not in err and "no-port" in err
    # a folder of episodes
    (tmp_path / "eps").mkdir()
    (tmp_path / "eps" / "episode_000.csv").write_text("t_s\n")
    err = one_line_error(["record", "--port", port, "--policy", "scripted", "--task", "reach",
                          "-o", str(tmp_path / "eps")])
    assert "a folder with recordings is already there" in err


@pytest.mark.skipif(not __import__("os").path.isdir("/proc/self"), reason="needs /proc")
@pytest.mark.parametrize("argv, option", [
    # the first output was written, or the fit ran, before the second failed
    (["fit", "{rec}", "-o", "{dir}/ok.toml", "--report", "/proc/r.png"], "--report"),
    (["simulate", "--profile", "paper-step-60", "-o", "{dir}/ok.csv", "--plot", "/proc/y.png"],
     "--plot"),
    (["conformance", "--port", "{dir}/no-port", "--json", "/proc/c.json"], "--json"),
    (["diagnose", "{rec}", "-o", "/proc/d.toml"], "--out"),
    (["simulate", "--profile", "paper-step-60", "-o", "{dir}"], "--out"),
])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(run_csv, one_line_error,
                                                                      argv, option):
    before = sorted(p.name for p in run_csv.parent.iterdir())
    argv = [a.format(rec=run_csv, dir=run_csv.parent) for a in argv]
    err = one_line_error(argv)
    assert err.startswith(f"error: {option} "), err
    assert "cannot write in /proc" in err or "a folder is there" in err
    assert sorted(p.name for p in run_csv.parent.iterdir()) == before


def test_an_output_that_exists_and_may_be_written_needs_no_folder_probe(run_csv, one_line_error):
    # /dev/null, /dev/stdout, >(jq .) are written in place; nobody can make a file in /dev
    err = one_line_error(["conformance", "--port", str(run_csv.parent / "no-port"), "--json",
                          "/dev/null"])
    assert "--json" not in err and "no-port" in err


def test_force_clears_a_former_runs_episodes_and_nothing_else(tmp_path):
    from mecanum_hil.cli.record import clear_former_run

    for name in ("episode_000.csv", "episode_000.json", "episode_001.shadow.jsonl",
                 "summary.json", "notes.txt", "episode_plan.md"):
        (tmp_path / name).write_text("x")
    clear_former_run(tmp_path, folder=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_plan.md", "notes.txt"]
