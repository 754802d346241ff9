"""``conformance`` tells the truth about the reference firmware and deliberately broken builds
of it: each watchdog bug fails the rule it breaks, no telemetry is a failure, the whole suite
runs with the e-stop pressed, a rule whose own timing slipped is repeated or inconclusive, and
every verdict names the sentence of protocol.md it checks."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
from controller_checks import ControllerProcess, conformance, outcomes
from firmware_make import FIRMWARE, make

from mecanum_hil.link import protocol as proto
from mecanum_hil.link.conformance import RULES, run_conformance
from mecanum_hil.link.serial_link import SerialTransport
from mecanum_hil.model import RobotProfile

#: The compile-time bugs of drivers/firmware/core/mh_core.c.
BUGS = ("MH_BUG_PING_FEEDS_WATCHDOG", "MH_BUG_WATCHDOG_ONLY_WHILE_MOVING",
        "MH_BUG_ESTOP_ERROR_FEEDS_WATCHDOG", "MH_BUG_BYTES_FEED_WATCHDOG")


@pytest.fixture(scope="session")
def builds(tmp_path_factory, firmware_build) -> dict[str, Path]:
    """``mh-controller`` of the correct core (sanitized) and of each bug, by name."""
    out = {"": firmware_build / "mh-controller"}
    for bug in BUGS:
        folder = tmp_path_factory.mktemp(bug.lower())
        make(folder, "host", HOST_CFLAGS=f"-D{bug}")
        out[bug] = folder / "mh-controller"
    return out


def _conformance(tmp_path, build: Path, ctl_args=(), *args):
    with ControllerProcess([str(build), *ctl_args]) as ctl:
        code, report = conformance(tmp_path, ctl.path, *args)
    return code, report


def _failed(report) -> set[str]:
    return {r for r, o in outcomes(report).items() if o == "FAIL" or o == "fail"}


@pytest.mark.slow
@pytest.mark.parametrize(("bug", "broken"), [
    ("MH_BUG_PING_FEEDS_WATCHDOG", {"watchdog.ping"}),
    ("MH_BUG_WATCHDOG_ONLY_WHILE_MOVING", {"watchdog.idle"}),
    ("MH_BUG_BYTES_FEED_WATCHDOG", {"watchdog.ping", "watchdog.damaged", "watchdog.refused"}),
])
def test_each_watchdog_bug_fails_the_rule_it_breaks(bug, broken, builds, tmp_path):
    code, report = _conformance(tmp_path, builds[bug], (), "--rule", "watchdog")
    assert code == 1
    assert broken <= _failed(report) <= {r for r in RULES if r.startswith("watchdog.")}, report
    # the correct build passes the same rules
    code, report = _conformance(tmp_path, builds[""], (), "--rule", "watchdog")
    assert code == 0 and not _failed(report), report


def test_an_error_3_that_feeds_the_watchdog_fails_watchdog_estop_error(builds, tmp_path):
    held = ("--estop-pressed", "--estop-held-s", "600")
    rules = ("--estop-pressed", "--rule", "estop", "--rule", "watchdog.estop_error")
    code, report = _conformance(tmp_path, builds["MH_BUG_ESTOP_ERROR_FEEDS_WATCHDOG"], held,
                                *rules)
    assert code == 1 and _failed(report) == {"watchdog.estop_error"}, report
    code, report = _conformance(tmp_path, builds[""], held, *rules)
    assert code == 0 and outcomes(report)["watchdog.estop_error"] == "pass", report


def test_a_controller_without_telemetry_fails_instead_of_skipping(builds, tmp_path):
    code, report = _conformance(tmp_path, builds[""], ("--telemetry-rate", "0"))
    assert code == 1 and not report["ok"]
    seen = outcomes(report)
    # only the rules that need a pressed e-stop skip; every rule that watches the controller
    # through its samples fails, naming why
    assert {r for r, o in seen.items() if o == "skip"} == {"estop.held", "estop.reset",
                                                           "watchdog.estop_error"}
    assert report["failed"] >= 12, report
    assert "announced no telemetry (0 Hz)" in next(
        r["detail"] for r in report["rules"] if r["rule"] == "watchdog.fed")


@pytest.mark.slow
@pytest.mark.parametrize(("held", "skipped"), [
    ((), {"watchdog.estop_error"}),
    (("--estop-held-s", "600"), {"estop.reset", "command.valid", "stop", "watchdog.fed",
                                 "estop.harmless"}),
])
def test_the_whole_suite_runs_with_the_e_stop_pressed(held, skipped, builds, tmp_path):
    code, report = _conformance(tmp_path, builds[""], ("--estop-pressed", *held),
                                "--estop-pressed")
    assert code == 0 and report["ok"], report
    seen = outcomes(report)
    assert len(seen) == len(RULES)
    assert {r for r, o in seen.items() if o != "pass"} == skipped, report
    why = {r["rule"]: r["detail"] for r in report["rules"]}
    if "command.valid" in skipped:  # the motion rules say why they did not run
        assert "the e-stop is latched" in why["command.valid"]


class LateHeartbeats(SerialTransport):
    """The host's end, whose fourth HEARTBEAT of the first ``attempts`` runs of a rule is
    sent 0.35 s late (a loaded host)."""

    def __init__(self, *args, attempts: int, **kw) -> None:
        super().__init__(*args, **kw)
        self.attempts = attempts
        self.heartbeats = 0

    def send(self, msg):
        if isinstance(msg, proto.Hello):
            self.heartbeats = 0
        elif isinstance(msg, proto.Heartbeat):
            self.heartbeats += 1
            if self.heartbeats == 4 and self.attempts > 0:
                self.attempts -= 1
                time.sleep(0.35)  # longer than the 250 ms watchdog: it trips
        return super().send(msg)


@pytest.mark.parametrize(("late", "outcome", "attempts"), [(1, "pass", 2),
                                                           (3, "inconclusive", 3)])
def test_a_rule_whose_own_heartbeats_were_late_is_repeated_never_failed(
        late, outcome, attempts, builds):
    with ControllerProcess([str(builds[""])]) as ctl, \
            LateHeartbeats(port=ctl.path, attempts=late) as host:
        report = run_conformance(host, RobotProfile(), rules=["watchdog.fed"], answer_s=2.0)
    (result,) = report.results
    assert (result.outcome, result.attempts) == (outcome, attempts), result
    assert "ms apart" in result.detail and report.failed == []
    assert report.ok == (outcome == "pass")


def test_every_verdict_names_a_sentence_of_the_protocol():
    text = " ".join((FIRMWARE.parent / "protocol.md").read_text().split())
    for name, (_, _, section) in RULES.items():
        heading, quote = re.fullmatch(r'([^:]+): "(.+)"', section).groups()
        assert heading in text and quote in text, (name, section)
