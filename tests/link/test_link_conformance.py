"""``mecanum-hil conformance``: sim-robot passes every rule over a pseudo-terminal and over
SLCAN (in its own process, as a real controller would be driven), the e-stop rules with an
e-stop pressed, and deliberately broken controllers each fail with the rule they break."""

from __future__ import annotations

import json
import math
import threading
import time

import pytest

from mecanum_hil.cli import main
from mecanum_hil.errors import LinkError
from mecanum_hil.link import protocol as proto
from mecanum_hil.link.conformance import RULES, run_conformance, select_rules
from mecanum_hil.link.effects_file import load_sim_effects
from mecanum_hil.link.serial_link import SerialTransport
from mecanum_hil.link.sim_process import spawn_sim_robot
from mecanum_hil.link.simulated import ControllerModel, SimulatedController
from mecanum_hil.model import Calibration, RobotProfile

ROBOT = RobotProfile()
#: The answer time given where the rules, not this machine's load, are tested.
SLOW_MACHINE = ("--answer-timeout", "2")


def _check_report(path, skipped_ok=()):
    report = json.loads(path.read_text())
    outcomes = {r["rule"]: r["outcome"] for r in report["rules"]}
    assert set(outcomes) == set(RULES)
    assert report["failed"] == 0 and report["ok"], report
    skipped = {name for name, outcome in outcomes.items() if outcome == "skip"}
    assert skipped <= set(skipped_ok), skipped
    assert report["announced"]["wheel_limit_rpm"] == ROBOT.wheel_speed_max_rpm
    return report


@pytest.mark.slow
def test_sim_robot_passes_every_rule_over_a_pty(tmp_path, capsys):
    with spawn_sim_robot("--serial", "--quiet") as sim:
        # an answer's time is the machine's too: on a loaded CI machine the sim-robot missed
        # the default 0.3 s for an ERROR (command.non_finite); the rules, not the load, are
        # tested here
        code = main(["conformance", "--port", sim.path, "--json", str(tmp_path / "r.json"),
                     *SLOW_MACHINE])
        assert sim.proc.poll() is None
    out = capsys.readouterr().out
    assert code == 0, out
    assert "pass  command.non_finite" in out and "0 failed" in out
    _check_report(tmp_path / "r.json", skipped_ok={"estop.held", "estop.reset",
                                                        "watchdog.estop_error"})


@pytest.mark.slow
def test_sim_robot_passes_every_rule_over_slcan(tmp_path, capsys):
    with spawn_sim_robot("--slcan", "--quiet") as sim:
        code = main(["conformance", "--transport", "can", "--interface", "slcan", "--channel",
                     sim.path, "--link-option", "sleep_after_open=0", "--json",
                     str(tmp_path / "r.json"), *SLOW_MACHINE])
    assert code == 0, capsys.readouterr().out
    # NaN and infinity have no CAN encoding: that rule is the only one that cannot run
    _check_report(tmp_path / "r.json",
                  skipped_ok={"command.non_finite", "estop.held", "estop.reset",
                              "watchdog.estop_error"})


def test_e_stop_rules_with_the_e_stop_pressed(tmp_path, capsys):
    fx = tmp_path / "estop.toml"
    fx.write_text("[[faults]]\nat_s = 0.0\nestop = true\n")
    with spawn_sim_robot("--serial", "--quiet", "--effects", str(fx)) as sim:
        code = main(["conformance", "--port", sim.path, "--estop-pressed", "--rule", "estop",
                     "--json", "-"])
    report = json.loads(capsys.readouterr().out)
    assert code == 0, report
    # the e-stop rules run first; once estop.reset cleared it, estop.harmless runs too
    assert {r["rule"]: r["outcome"] for r in report["rules"]} == {
        "estop.harmless": "pass", "estop.held": "pass", "estop.reset": "pass"}


# -- deliberately broken controllers -----------------------------------------------------------
class NoRangeCheck(SimulatedController):
    """Refuses non-finite commands but has no limit check (finding 2's controller)."""

    def command_problem(self, msg):
        ok = all(map(math.isfinite, (msg.n_rpm, msg.omega_dps, msg.theta_deg)))
        return None if ok else "not finite"


class HeartbeatReleasesWatchdog(SimulatedController):
    """A HEARTBEAT clears the watchdog bit (the old sim-robot)."""

    def handle(self, msg):
        super().handle(msg)
        if isinstance(msg, proto.Heartbeat):
            self.status &= ~proto.Status.WATCHDOG


class StaleAckAfterHello(SimulatedController):
    """Keeps the old session's ack_seq after a HELLO (the old sim-robot)."""

    def handle(self, msg):
        kept = self.ack_seq
        super().handle(msg)
        if isinstance(msg, proto.Hello):
            self.ack_seq = kept


class HelloClearsEstop(SimulatedController):
    """A HELLO clears a latched e-stop (the old sim-robot)."""

    def handle(self, msg):
        super().handle(msg)
        if isinstance(msg, proto.Hello):
            self.model.estop = False
            self.model._faults = []


class LateError(SimulatedController):
    """Answers a refused command 0.5 s late."""

    def _refuse_command(self, *args, **kwargs):
        time.sleep(0.5)
        return super()._refuse_command(*args, **kwargs)


class LateErrorThenTakesIt(SimulatedController):
    """Answers a bad COMMAND with ERROR 2 0.5 s late, then obeys it anyway (acknowledges it):
    a late ERROR must not end the watch before the samples that show it."""

    def handle(self, msg):
        if isinstance(msg, proto.Command) and self.connected and self.command_problem(msg):
            time.sleep(0.5)
            self._refuse_command("late")
            self.ack_seq = msg.seq
            return
        super().handle(msg)


def _run_against(cls, pty_pair, rules, sim_effects=None, estop=False, answer_s=0.3,
                 host=lambda path: SerialTransport(port=path)):
    p = pty_pair()
    ctrl = cls(SerialTransport(fd=p.master),
               ControllerModel(Calibration(), ROBOT, sim_effects, rate_hz=1000.0))
    ctrl.model.wheel_rpm(0)
    thread = threading.Thread(target=ctrl.serve, daemon=True)
    thread.start()
    try:
        with host(p.path) as link:
            return run_conformance(link, ROBOT, rules=rules, estop_pressed=estop,
                                   answer_s=answer_s)
    finally:
        ctrl.stop_event.set()
        thread.join(2)


@pytest.mark.parametrize(("cls", "rules", "broken"), [
    # without a range check, the rotation command.k needs refused is taken too
    (NoRangeCheck, ["command"], ["command.beyond_limit", "command.k"]),
    (HeartbeatReleasesWatchdog, ["watchdog"], ["watchdog.latched"]),
    (StaleAckAfterHello, ["hello", "ping"], ["hello.restart"]),
])
def test_a_broken_controller_fails_with_the_rule_it_breaks(cls, rules, broken, pty_pair):
    report = _run_against(cls, pty_pair, rules)
    assert report.failed == broken, report.format()
    assert len(report.results) == len(select_rules(rules)) > 1


def test_a_hello_that_clears_the_e_stop_fails_estop_held(pty_pair, tmp_path):
    fx = tmp_path / "estop.toml"
    fx.write_text("[[faults]]\nat_s = 0.0\nestop = true\n")
    report = _run_against(HelloClearsEstop, pty_pair, ["estop"], load_sim_effects(fx),
                          estop=True)
    assert report.failed == ["estop.held"], report.format()
    assert "HELLO cleared the e-stop" in report.results[0].detail, report.format()


@pytest.mark.slow
def test_the_whole_suite_against_a_controller_without_range_check(pty_pair):
    report = _run_against(NoRangeCheck, pty_pair, [])
    assert report.failed == ["command.beyond_limit", "command.k"], report.format()


class Recorded(SimulatedController):
    """The simulated controller, keeping every message it handled."""

    def handle(self, msg):
        self.received = getattr(self, "received", [])
        self.received.append(msg)
        super().handle(msg)


def test_a_signal_in_a_moving_rule_still_ends_it_with_stop(pty_pair):
    """SIGTERM (or Ctrl-\\) while a rule streams commands used to end the process with the
    wheels turning (only Ctrl-C unwound through the rule's STOP); now every such signal does,
    and the CLI ends with 143."""
    import os
    import signal

    from mecanum_hil.errors import SessionTerminated

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers live in the main thread")
    p = pty_pair()
    ctrl = Recorded(SerialTransport(fd=p.master),
                    ControllerModel(Calibration(), ROBOT, None, rate_hz=1000.0))
    thread = threading.Thread(target=ctrl.serve, daemon=True)
    thread.start()
    try:
        with SerialTransport(port=p.path) as host:
            send, commands = host.send, []

            def send_then_signal(msg):
                out = send(msg)
                if isinstance(msg, proto.Command):
                    commands.append(msg)
                    if len(commands) == 5:
                        os.kill(os.getpid(), signal.SIGTERM)
                return out

            host.send = send_then_signal
            with pytest.raises(SessionTerminated):
                run_conformance(host, ROBOT, rules=["watchdog.fed"])
            ctrl_seen = len(commands)
    finally:
        import time

        time.sleep(0.1)
        ctrl.stop_event.set()
        thread.join(2)
    assert ctrl_seen >= 5
    assert isinstance(ctrl.received[-1], proto.Stop), ctrl.received[-3:]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # put back


def test_rule_selection_and_listing(capsys):
    assert select_rules(["watchdog"]) == [n for n in RULES if n.startswith("watchdog.")]
    assert select_rules(["ping"]) == ["ping"]
    assert main(["conformance", "--list"]) == 0
    assert "command.non_finite" in capsys.readouterr().out
    assert main(["conformance", "--port", "/dev/null", "--rule", "nope"]) == 1


def test_an_answer_timeout_that_is_not_a_time_is_one_line(capsys):
    assert main(["conformance", "--port", "/dev/null", "--answer-timeout", "nan"]) == 1
    err = capsys.readouterr().err
    assert err == "error: --answer-timeout must be a finite number > 0 [s], got nan\n"


def test_a_late_error_is_waited_for_up_to_the_answer_time(pty_pair):
    # a controller that answers a refused command after 0.5 s fails at the default 0.3 s and
    # passes with --answer-timeout 1; the listening ends at the ERROR, not at the timeout
    report = _run_against(LateError, pty_pair, ["command.non_finite"])
    assert report.failed == ["command.non_finite"]
    report = _run_against(LateError, pty_pair, ["command.non_finite"], answer_s=1.0)
    assert report.ok and report.results[0].duration_s < 9 * 1.0, report.results


def test_a_late_error_does_not_hide_a_refused_command_taken(pty_pair):
    report = _run_against(LateErrorThenTakesIt, pty_pair, ["command.non_finite"], answer_s=1.0)
    assert report.failed == ["command.non_finite"]
    assert "acknowledged (ack_seq)" in report.results[0].detail, report.results


class FailsToWrite(SerialTransport):
    """The host's end, whose first ``failures`` sends of a HEARTBEAT fail (a full output
    buffer, an adapter that refused a write)."""

    def __init__(self, *args, failures: int, **kw) -> None:
        super().__init__(*args, **kw)
        self.failures = failures

    def send(self, msg):
        if isinstance(msg, proto.Heartbeat) and self.failures > 0:
            self.failures -= 1
            raise LinkError("send failed: could not write (test)")
        return super().send(msg)


@pytest.mark.parametrize(("failures", "outcome"), [(1, "pass"), (3, "fail")])
def test_a_rule_the_host_could_not_send_is_tried_again(failures, outcome, pty_pair):
    report = _run_against(SimulatedController, pty_pair, ["watchdog.fed"], answer_s=2.0,
                          host=lambda path: FailsToWrite(port=path, failures=failures))
    (result,) = report.results
    assert result.outcome == outcome, result
    assert result.attempts == min(failures + 1, 3)
    if outcome == "fail":
        assert "link error" in result.detail and "in each of 3 attempts" in result.detail
