"""``mecanum-hil import`` (format text) through the CLI, then ``fit`` on what it wrote."""

import subprocess
import sys

import numpy as np
import pytest

from mecanum_hil.cli import main
from mecanum_hil.io.recording import COLUMNS, read_recording

MAP = """
[time]
column = "time_s"
unit = "s"
[wheels]
wheel1 = { column = "w_left", unit = "rad/s" }
wheel2 = { column = "w_right", unit = "rad/s" }
[commands]
setpoint = { column = "setpoint", unit = "rad/s" }
"""


def lab_log(tmp_path, n=970, repeats=(100, 500, 800)):
    """A 1 kHz log as a lab writes it: % header, 1 ms stamps, 2 wheels, signed setpoints."""
    t = np.round(np.arange(n) * 1e-3, 3)
    t[list(repeats)] = t[[r - 1 for r in repeats]]
    k = np.arange(n)
    sp = np.where(k < n // 2, 16.0, -30.0)
    rng = np.random.default_rng(0)
    w = np.where(k < n // 2, 16.0 * (1 - np.exp(-k / 15)),
                 16.0 + (-46.0) * (1 - np.exp(-(k - n // 2) / 15)))
    log = tmp_path / "lab.txt"
    with log.open("w") as fh:
        fh.write("% speed test\n% time_s setpoint w_left w_right\n")
        for i in range(n):
            fh.write(f"{t[i]:.3f} {sp[i]:.1f} {w[i] + rng.normal(0, 0.05):.3f} "
                     f"{w[i] + rng.normal(0, 0.05):.3f}\n")
    m = tmp_path / "map.toml"
    m.write_text(MAP)
    return log, m


def cli(*args):
    return subprocess.run([sys.executable, "-m", "mecanum_hil", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_import_then_fit_runs_on_the_imported_log(tmp_path):
    log, m = lab_log(tmp_path)
    out = tmp_path / "rec.csv"
    r = cli("import", log, "--map", m, "--out", out)
    assert r.returncode == 0, r.stderr
    assert r.stderr == ("warning: time (median period 1.000 ms, resolution 1.000 ms): 3 repeated "
                        "stamps spread up to the next stamp\n")
    assert "wrote" in r.stdout and "970 samples" in r.stdout
    rec = read_recording(out)
    assert len(rec) == 970 and rec.metadata["format"] == "text"
    assert rec.metadata["notes"] == [r.stderr.removeprefix("warning: ").strip()]
    r = cli("fit", out, "--out", tmp_path / "cal.toml")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "cal.toml").exists()
    assert "does not increase" not in r.stderr


def test_fit_no_longer_refuses_a_recording_with_repeated_stamps(tmp_path):
    log, _ = lab_log(tmp_path)
    rec_path = tmp_path / "raw.csv"
    # the recording a hand-written converter made: stamps copied as they were
    rows = []
    for line in log.read_text().splitlines()[2:]:
        t, sp, w1, w2 = line.split()
        n, theta = abs(float(sp)) * 60 / (2 * np.pi), 90 if float(sp) >= 0 else 270
        rows.append(f"{t},{n},0,{theta},{float(w1) * 60 / (2 * np.pi)},"
                    f"{float(w2) * 60 / (2 * np.pi)},,,,,")
    rec_path.write_text(",".join(COLUMNS) + "\n" + "\n".join(rows) + "\n")
    r = cli("fit", rec_path, "--out", tmp_path / "cal.toml")
    assert r.returncode == 0, r.stderr
    assert f"warning: {rec_path}: time (median period 1.000 ms" in r.stderr
    assert r.stderr.count("repeated stamps") == 1


def test_dry_run_prints_the_first_rows_and_writes_nothing(tmp_path, capsys):
    log, m = lab_log(tmp_path)
    out = tmp_path / "rec.csv"
    assert main(["import", str(log), "--map", str(m), "--out", str(out), "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == ",".join(COLUMNS)
    assert lines[1].startswith("0.000000,152.788745,0,90,")
    assert lines[-1] == "(970 rows; nothing written)"
    assert len(lines) == 12 and not out.exists()


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--map", "MAP"], "line 4, column w_left: not a number: 'abc'"),
        ([], "format 'text' needs --map MAP.toml"),
        (["--map", "MISSING"], "missing.toml: file not found"),
        (["--map", "MAP", "--format", "nope"], "unknown import format 'nope'"),
    ],
)
def test_malformed_input_is_one_error_line(tmp_path, capsys, args, fragment):
    log, m = lab_log(tmp_path, n=20, repeats=())
    lines = log.read_text().splitlines(True)
    lines[3] = lines[3].replace(lines[3].split()[2], "abc", 1)
    log.write_text("".join(lines))
    args = [str(m) if a == "MAP" else str(tmp_path / "missing.toml") if a == "MISSING" else a
            for a in args]
    code = main(["import", str(log), "--out", str(tmp_path / "o.csv"), *args])
    err = capsys.readouterr().err
    assert code == 1
    assert err.startswith("error: ") and err.count("\n") == 1 and fragment in err
    assert "Traceback" not in err and not (tmp_path / "o.csv").exists()


def test_a_backward_jump_fails_the_import_naming_the_line(tmp_path, capsys):
    log, m = lab_log(tmp_path, n=50, repeats=())
    lines = log.read_text().splitlines(True)
    lines[30] = "0.010" + lines[30][5:]  # line 31 of the file
    log.write_text("".join(lines))
    assert main(["import", str(log), "--map", str(m), "--out", str(tmp_path / "o.csv")]) == 1
    err = capsys.readouterr().err
    assert "lab.txt, line 31: time 0.01 s does not increase: it runs back 17.000 ms" in err
    assert err.count("\n") == 1


def test_a_sidecar_that_cannot_be_written_leaves_the_old_recording_whole(tmp_path, capsys):
    """Nothing half-written: the CSV and its sidecar are both complete before either replaces
    what was there, and no temporary file is left behind."""
    log, m = lab_log(tmp_path, n=50, repeats=())
    out = tmp_path / "rec.csv"
    out.write_text("old\n")
    (tmp_path / "rec.json").mkdir()  # the sidecar's place is taken
    assert main(["import", str(log), "--map", str(m), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "rec.json" in err
    assert out.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lab.txt", "map.toml", "rec.csv",
                                                          "rec.json"]
