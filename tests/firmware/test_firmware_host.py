"""The reference controller firmware (drivers/firmware): its C unit tests, its core built
freestanding, and its POSIX host port against ``mecanum-hil conformance`` and ``record``
over a pseudo-terminal."""

from __future__ import annotations

import json
import re
import subprocess

import pytest
from controller_checks import conformance, outcomes, passes_every_rule, record_ends_with_stop
from firmware_make import make

from mecanum_hil.cli import main


def test_unit_tests_of_the_worked_examples_pass(firmware_build):
    # built and run under AddressSanitizer and UBSan by the Makefile
    done = make(firmware_build, "test")
    checks, failed = map(int, re.search(r"(\d+) checks, (\d+) failed", done.stdout).groups())
    assert failed == 0 and checks > 3000, done.stdout


def test_core_compiles_freestanding(firmware_build):
    make(firmware_build, "core-freestanding")
    assert all((firmware_build / f"fs_{name}.o").stat().st_size > 0
               for name in ("mh_wire", "mh_kinematics", "mh_core"))


def test_standalone_fuzz_driver_finds_nothing(firmware_build):
    # pseudo-random frames, damage, clock steps and e-stop presses, each output frame checked
    make(firmware_build, str(firmware_build / "fuzz_core"))
    run = subprocess.run([str(firmware_build / "fuzz_core"), "1500"], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    counts = dict(zip(("HELLO_ACK", "TELEMETRY", "PONG", "ERROR"),
                      map(int, re.findall(r"(\d+) (?:HELLO_ACK|TELEMETRY|PONG|ERROR)",
                                          run.stdout)), strict=True))
    assert all(n > 100 for n in counts.values()), counts


@pytest.mark.slow
def test_host_port_passes_every_rule(tmp_path, host_controller):
    counters = passes_every_rule(tmp_path, host_controller())
    assert counters["unknown_types"] > 0 and counters["version_errors"] > 0


def test_e_stop_rules_with_the_e_stop_pressed(tmp_path, host_controller):
    with host_controller("--estop-pressed") as ctl:
        code, report = conformance(tmp_path, ctl.path, "--estop-pressed", "--rule", "estop")
    assert code == 0, report
    # the e-stop rules run first; once estop.reset cleared it, estop.harmless runs too
    assert outcomes(report) == {"estop.harmless": "pass", "estop.held": "pass",
                                 "estop.reset": "pass"}


def test_e_stop_reset_while_the_button_is_held_is_refused(tmp_path, host_controller):
    with host_controller("--estop-pressed", "--estop-held-s", "600") as ctl:
        code, report = conformance(tmp_path, ctl.path, "--estop-pressed", "--rule", "estop")
    assert code == 0, report
    assert outcomes(report) == {"estop.harmless": "skip", "estop.held": "pass",
                                 "estop.reset": "skip"}
    assert "ERROR 3" in report["rules"][1]["detail"], report


def test_record_against_the_host_port_ends_with_stop(tmp_path, host_controller):
    ctl = host_controller()
    events, _ = record_ends_with_stop(tmp_path, ctl)
    # the wheels followed the 60 rpm step during the run
    moving = [float(e["wheel1_rpm"]) for e in events if e["event"] == "tlm" and e["wheel1_rpm"]]
    assert max(moving) > 55.0
    # the last frame the controller read was the host's STOP
    assert ctl.counters["last_type"] == 0x03


def _record(tmp_path, host_controller, *options: str):
    """``record --profile paper-step-60`` against the host port with ``options``: the exit
    code, the sidecar and the controller (stopped, its counters read)."""
    out = tmp_path / "x.csv"
    with host_controller(*options) as ctl:
        code = main(["record", "--port", ctl.path, "--profile", "paper-step-60", "--out",
                     str(out), "--no-progress"])
    return code, json.loads(out.with_suffix(".json").read_text()), ctl


def test_a_stalled_controller_is_a_lost_link(tmp_path, host_controller):
    # the controller stalls for 1 s at 2 s: record sees no telemetry for its 0.5 s link
    # timeout, sends STOP and exits 4
    code, side, ctl = _record(tmp_path, host_controller, "--stall-at-s", "2", "--stall-s", "1")
    assert code == 4 and side["end_reason"] == "link_lost"
    # (a sample read after the stall may carry WATCHDOG: 1 s without a command)
    assert {e["event"] for e in side["link_events"]} <= {"status_watchdog"}, side
    # the STOP sent during the stall was read after it, then the PINGs that looked for a
    # restart (telemetry came again: a stall, not a restart); the late samples were skipped
    assert ctl.counters["last_type"] == 0x05 and ctl.counters["telemetry_skipped"] > 0


def test_a_drive_fault_mid_run_stops_it_at_once(tmp_path, host_controller, capsys):
    # the drive reports a fault 0.5 s after the HELLO: record sends STOP then and exits 8
    code, side, ctl = _record(tmp_path, host_controller, "--fault-at-s", "0.5")
    assert code == 8
    assert capsys.readouterr().out.startswith("drive_fault (exit 8) after ")
    assert side["end_reason"] == "drive_fault" and "FAULT" in side["end_message"]
    events = side["link_events"]
    assert events[0]["event"] == "status_fault" and 0.0 < events[0]["t_s"] < 1.0
    assert ctl.counters["last_type"] == 0x03  # STOP, and no command after it


def test_a_power_cycled_controller_is_a_controller_reset(tmp_path, host_controller, capsys):
    # the controller restarts 1 s after the HELLO as at power-up: no telemetry, no session,
    # PING still answered. record sees the telemetry stop, sends STOP, then PINGs: PONGs
    # without telemetry are a restart (exit 6), not a lost link (exit 4)
    code, side, _ = _record(tmp_path, host_controller, "--restart-at-s", "1")
    assert code == 6
    assert capsys.readouterr().out.startswith("controller_reset (exit 6) after ")
    assert side["end_reason"] == "controller_reset" and "restarted" in side["end_message"]


@pytest.mark.parametrize(("fault", "reason", "code", "says"), [
    ("--nan-at-s", "invalid_readings", 10, "in a row"),
    ("--freeze-ack-at-s", "not_acknowledged", 9, "unacknowledged")])
def test_a_nan_sensor_or_a_frozen_ack_is_not_a_completed_run(fault, reason, code, says,
                                                            tmp_path, host_controller,
                                                            capsys):
    # from 1 s after the HELLO wheel 2 reads NaN, or ack_seq stays where it was: the first
    # lets the profile run to its end (exit 10), the second stops it at once (exit 9)
    code_seen, side, ctl = _record(tmp_path, host_controller, fault, "1")
    assert code_seen == code
    assert capsys.readouterr().out.startswith(f"{reason} (exit {code}) after ")
    assert side["end_reason"] == reason and says in side["end_message"]
    assert ctl.counters["last_type"] == 0x03  # the STOP came last
