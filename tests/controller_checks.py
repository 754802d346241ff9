"""Checks shared by the tests of controllers that run in their own process on a
pseudo-terminal (the independent Python controller, the C firmware's host port): start one,
stop it and read its counters, run ``conformance`` and ``record`` against it."""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

from mecanum_hil.cli import main

#: Rules of ``mecanum-hil conformance`` on serial.
EVERY_RULE = 26


class ControllerProcess:
    """A controller process that prints its pty path as its first line and, on SIGTERM, its
    counters as one JSON line on standard error (exit 0)."""

    def __init__(self, argv: list[str], env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env)
        self.path = self.proc.stdout.readline().strip()
        assert self.path.startswith("/dev/"), self.proc.stderr.read()
        self.counters: dict = {}

    def __enter__(self) -> ControllerProcess:
        return self

    def __exit__(self, *exc) -> None:
        if self.proc.poll() is None:
            self.counters = self.stop()

    def stop(self) -> dict:
        """SIGTERM; the controller's counters (its last standard error line)."""
        self.proc.send_signal(signal.SIGTERM)
        _, err = self.proc.communicate(timeout=10)
        assert self.proc.returncode == 0, err
        return json.loads(err.strip().splitlines()[-1])


def conformance(tmp_path: Path, path: str, *extra: str) -> tuple[int, dict]:
    """``mecanum-hil conformance`` on ``path``: exit code and the JSON report."""
    report = tmp_path / "report.json"
    # the rules, not this machine's load, are tested: a generous answer time
    code = main(["conformance", "--port", path, "--json", str(report), "--answer-timeout", "2",
                 *extra])
    return code, json.loads(report.read_text())


def outcomes(report: dict) -> dict[str, str]:
    """Rule -> pass / FAIL / skip."""
    return {r["rule"]: r["outcome"] for r in report["rules"]}


def passes_every_rule(tmp_path: Path, ctl: ControllerProcess) -> dict:
    """Every rule of ``conformance`` passes against ``ctl`` (stopped afterwards) but the three
    that need the e-stop pressed, which skip; the damaged frames and refused commands reached
    the controller as such. Returns the controller's counters."""
    with ctl:
        code, report = conformance(tmp_path, ctl.path)
    seen = outcomes(report)
    assert code == 0 and report["ok"], report
    assert len(seen) == EVERY_RULE
    assert {r for r, o in seen.items() if o != "pass"} == {"estop.held", "estop.reset",
                                                           "watchdog.estop_error"}
    assert report["announced"] == {"version": 2, "telemetry_rate_hz": 100, "watchdog_ms": 250,
                                   "wheel_limit_rpm": 130.0}
    assert ctl.counters["malformed"] > 0 and ctl.counters["crc"] > 0
    assert ctl.counters["refused_commands"] > 0 and ctl.counters["dropped_output"] == 0
    return ctl.counters


def record_ends_with_stop(tmp_path: Path, ctl: ControllerProcess) -> tuple[list[dict], dict]:
    """``record --profile paper-step-60`` against ``ctl`` (stopped afterwards): it completes,
    sends STOP once, the controller reports STOPPED after it and no frame was lost. Returns
    the recording's rows and its sidecar."""
    out = tmp_path / "x.csv"
    with ctl:
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
    return events, side
