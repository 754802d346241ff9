"""The protocol document is enough: a controller written from drivers/protocol.md alone
(``independent_controller.py``, which imports nothing of mecanum_hil) passes ``mecanum-hil
conformance`` and serves ``mecanum-hil record``."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mecanum_hil.cli import main

CONTROLLER = Path(__file__).with_name("independent_controller.py")
EVERY_RULE = 21


class IndependentController:
    """The independent controller in its own process, serving on a pseudo-terminal."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen([sys.executable, str(CONTROLLER), *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.path = self.proc.stdout.readline().strip()
        assert self.path.startswith("/dev/"), self.proc.stderr.read()

    def __enter__(self) -> IndependentController:
        return self

    def __exit__(self, *exc) -> None:
        self.counters = self.stop()

    def stop(self) -> dict:
        """SIGTERM; the controller's counters (its last stderr line)."""
        self.proc.send_signal(signal.SIGTERM)
        _, err = self.proc.communicate(timeout=10)
        assert self.proc.returncode == 0, err
        return json.loads(err.strip().splitlines()[-1])


def _conformance(tmp_path: Path, path: str, *extra: str) -> tuple[int, dict]:
    report = tmp_path / "report.json"
    # the rules, not this machine's load, are tested: a generous answer time
    code = main(["conformance", "--port", path, "--json", str(report), "--answer-timeout", "2",
                 *extra])
    return code, json.loads(report.read_text())


def _outcomes(report: dict) -> dict[str, str]:
    return {r["rule"]: r["outcome"] for r in report["rules"]}


@pytest.mark.slow
def test_independent_controller_passes_every_rule(tmp_path):
    with IndependentController() as ctl:
        code, report = _conformance(tmp_path, ctl.path)
    outcomes = _outcomes(report)
    assert code == 0 and report["ok"], report
    assert len(outcomes) == EVERY_RULE
    assert {r for r, o in outcomes.items() if o != "pass"} == {"estop.held", "estop.reset"}
    assert report["announced"] == {"version": 2, "telemetry_rate_hz": 100, "watchdog_ms": 250,
                                   "wheel_limit_rpm": 130.0}
    # the suite's damaged frames and refused commands reached the controller as such
    assert ctl.counters["malformed"] > 0 and ctl.counters["crc"] > 0
    assert ctl.counters["refused_commands"] > 0 and ctl.counters["dropped_output"] == 0


def test_e_stop_rules_with_the_e_stop_pressed(tmp_path):
    with IndependentController("--estop-pressed") as ctl:
        code, report = _conformance(tmp_path, ctl.path, "--estop-pressed", "--rule", "estop")
    assert code == 0, report
    assert _outcomes(report) == {"estop.harmless": "skip", "estop.held": "pass",
                                 "estop.reset": "pass"}


def test_e_stop_reset_while_the_button_is_held_skips(tmp_path):
    # ERROR 3 answers an ESTOP_RESET at once and does not acknowledge it: the rule must see
    # the ERROR (it used to read past it waiting for the ack, and failed)
    with IndependentController("--estop-pressed", "--estop-held-s", "600") as ctl:
        code, report = _conformance(tmp_path, ctl.path, "--estop-pressed", "--rule", "estop")
    assert code == 0, report
    assert _outcomes(report) == {"estop.harmless": "skip", "estop.held": "pass",
                                 "estop.reset": "skip"}
    assert "ERROR 3" in report["rules"][-1]["detail"], report


def test_record_against_the_independent_controller_ends_with_stop(tmp_path):
    out = tmp_path / "x.csv"
    with IndependentController() as ctl:
        code = main(["record", "--port", ctl.path, "--profile", "paper-step-60", "--out",
                     str(out), "--no-progress"])
    assert code == 0
    rows = out.read_text().splitlines()
    header = rows[0].split(",")
    events = [dict(zip(header, r.split(","), strict=True)) for r in rows[1:]]
    stops = [i for i, e in enumerate(events) if e["event"] == "stop"]
    assert len(stops) == 1
    after = [e for e in events[stops[0]:] if e["event"] == "tlm"]
    assert after and int(after[-1]["status"]) & 0x4  # STOPPED after the run's STOP
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["end_reason"] == "completed" and side["link_stats"]["lost"] == 0
    assert side["controller_wheel_limit_rpm"] == 130.0
    # everything record sent arrived whole: commands, PINGs, HELLO and the STOP
    assert ctl.counters["received"] == side["link_stats"]["sent"]
    assert ctl.counters["crc"] == ctl.counters["malformed"] == ctl.counters["lost"] == 0
