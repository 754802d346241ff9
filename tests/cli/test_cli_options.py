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
