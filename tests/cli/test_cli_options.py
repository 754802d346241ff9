"""Options that make no sense are refused in one line before anything is opened: NaN passes
every comparison (``--link-timeout nan`` switched lost-link detection off), 0 or a negative
time, a network port URL pyserial would answer with its parser's text."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("argv, fragment", [
    (["record", "--link-timeout", "nan"], "--link-timeout must be a finite number > 0"),
    (["record", "--link-timeout", "0"], "--link-timeout must be a finite number > 0"),
    (["record", "--link-timeout", "-1"], "--link-timeout must be a finite number > 0"),
    (["record", "--connect-timeout", "-1"], "--connect-timeout must be a finite number > 0"),
    (["record", "--connect-timeout", "nan"], "--connect-timeout must be a finite number > 0"),
    (["record", "--port", "socket://127.0.0.1:99999"], "give socket://HOST:PORT"),
    (["record", "--port", "socket://localhost"], "give socket://HOST:PORT"),
    (["conformance", "--port", "rfc2217://:80"], "give rfc2217://HOST:PORT"),
])
def test_record_options_that_make_no_sense(tmp_path, one_line_error, argv, fragment):
    if argv[0] == "record":
        argv = [*argv, "--profile", "paper-step-60", "-o", str(tmp_path / "r.csv")]
        if "--port" not in argv:
            argv += ["--port", str(tmp_path / "no-port")]
    err = one_line_error(argv)
    assert fragment in err, err
    assert not (tmp_path / "r.csv").exists()


@pytest.mark.parametrize("value", ["nan", "-1", "0"])
def test_sim_robot_duration_that_makes_no_sense(one_line_error, value):
    err = one_line_error(["sim-robot", "--serial", "--duration", value])
    assert "--duration must be a finite number > 0" in err


@pytest.mark.parametrize("argv, fragment", [
    (["record", "--rate", "abc"], "Invalid value for '--rate'"),
    (["diagnose", "--jobs", "0"], "Invalid value for '--jobs'"),
    (["fit", "--bogus"], "No such option: --bogus"),
    (["simulate", "--profile", "paper-step-60"], "Missing option '--out'"),
    (["nope"], "No such command 'nope'"),
    # the package's own usage errors: a name that does not exist, a choice left out
    (["simulate", "--profile", "nonexistent", "--out", "x.csv"], "unknown profile 'nonexistent'"),
    (["record", "--profile", "nonexistent", "--out", "x.csv", "--dry-run"], "unknown profile"),
    (["campaign", "--profile", "nonexistent", "--out", "c"], "unknown profile"),
    (["shadow"], "give exactly one of --replay REC.csv and --transport can"),
    (["shadow", "--replay", "x.csv", "--transport", "can"], "give exactly one of --replay"),
    (["simulate", "--out", "x.csv"], "give exactly one of --commands REC.csv and --profile"),
    (["record", "--out", "x.csv"], "give exactly one of --profile NAME_OR_FILE, --commands"),
    (["record", "--out", "x", "--policy", "p.npz", "--profile", "paper-turn"], "exactly one"),
    (["sim-robot"],
     "give exactly one of --serial, --slcan, --can INTERFACE:CHANNEL and --transport ros2"),
    (["sim-robot", "--serial", "--slcan"], "give exactly one of --serial"),
    (["import", "log.csv"], "give --out REC.csv (or --dry-run)"),
    (["export", "x.csv", "--out", "x.mcap", "--events", "e", "--no-events"], "not both"),
    (["campaign", "--out", "c", "--profile", "paper-turn", "--short"], "not both"),
])
def test_usage_errors_are_one_line_with_where_the_help_is(capsys, tmp_path, monkeypatch,
                                                          argv, fragment):
    # click's four-line usage block (exit 2) became one line, still exit 2
    from mecanum_hil.cli import main

    monkeypatch.chdir(tmp_path)  # nothing a refused command might write lands in the tree

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and fragment in err, err
    assert "--help')" in err
    if argv[0] != "nope":
        assert err.endswith(f"(see 'mecanum-hil {argv[0]} --help')"), err
    assert list(tmp_path.iterdir()) == []


def test_help_and_exit_codes_of_commands_are_kept(capsys):
    from mecanum_hil.cli import main

    assert main(["fit", "--help"]) == 0
    assert "Usage: mecanum-hil fit" in capsys.readouterr().out
    assert main([]) == 2  # no command: the command list, as before
    assert "Commands" in capsys.readouterr().err


@pytest.mark.parametrize("option, value, fragment", [
    ("--threshold", "0", "--threshold must be a finite number > 0"),
    ("--drift", "nan", "--drift must be a finite number >= 0"),
    ("--noise-rpm", "-1", "--noise-rpm must be a finite number > 0"),
    ("--warmup", "inf", "--warmup must be a finite number >= 0"),
])
def test_shadow_settings_are_refused_by_their_option(repo, one_line_error, option, value,
                                                     fragment):
    # the monitor's own message named its fields (threshold_h and max_substep_s)
    rec = repo / "recordings" / "samples" / "paper-step-60.csv"
    err = one_line_error(["shadow", "--replay", str(rec), "--no-events", option, value])
    assert fragment in err


def test_sim_robot_internal_rate_it_cannot_keep(one_line_error):
    err = one_line_error(["sim-robot", "--serial", "--internal-rate", "1e9"])
    assert "internal tick rate must be a positive number of Hz up to 100000" in err
