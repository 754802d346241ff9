"""The stop path: every way out of a command stream leaves the robot commanded to stop.

Each step of :mod:`mecanum_hil.link.stop_path` on a stand-in session, then whole runs on an
in-memory controller: STOP goes out on a normal end, an exception mid-stream, failing sends, a
lost link and SIGTERM; it is the last motion frame sent; what was recorded before is kept.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import threading
import time
from collections import deque

import numpy as np
import pytest

from mecanum_hil.errors import LinkError, LinkLostError, SessionTerminated
from mecanum_hil.io.recording import read_recording
from mecanum_hil.link import protocol as proto
from mecanum_hil.link import stop_path as sp
from mecanum_hil.link.observers import ObserverStopError
from mecanum_hil.link.session import (
    EXIT_CODES,
    SessionConfig,
    SignalGuard,
    TelemetryCheckError,
    TelemetrySilenceError,
    run_record_session,
)
from mecanum_hil.link.transport import Transport
from mecanum_hil.model import RobotProfile

ROBOT = RobotProfile()
CONFIG = SessionConfig(connect_timeout_s=1.0, link_timeout_s=0.3, tail_s=0.05,
                       handle_sigterm=False)
MAIN_THREAD = threading.current_thread() is threading.main_thread()


# -- a stand-in session for the steps -------------------------------------------------------
class _Pump:
    def __init__(self, close_raises: BaseException | None = None) -> None:
        self.error: BaseException | None = None
        self.dropped = 0
        self.closed = False
        self._close_raises = close_raises

    def close(self) -> None:
        self.closed = True
        if self._close_raises is not None:
            raise self._close_raises


class FakeSession:
    """What the stop path reads of a session; ``run_raises`` ends :meth:`run`."""

    def __init__(self, run_raises: BaseException | None = None,
                 stop_raises: BaseException | None = None, restarted: str | None = None,
                 not_as_asked: tuple[str, str] | None = None) -> None:
        self.run_raises, self.stop_raises = run_raises, stop_raises
        self._restarted = restarted
        self.not_as_asked = not_as_asked
        self.stops: list[float] = []
        self.stop_attempted = False
        self.pump = _Pump()
        self.t0: float | None = time.perf_counter()
        self.rtt: list[float] = []
        self.ack: list[float] = []
        self.events: list = []
        self.invalid_readings = self.invalid_samples = 0
        self.longest_invalid_s = self.clock_drift_s = self.widest_command_gap_s = 0.0
        self._acks: dict = {}
        self.controller, self.wheel_limit_rpm, self.telemetry_rate_hz = "fake", 130.0, 100
        self.commands_sent = self.telemetry = 0

    def run(self) -> None:
        if self.run_raises is not None:
            raise self.run_raises

    def finish_checks(self) -> None:
        pass

    def stop(self, keep_receiving_s: float) -> None:
        self.stop_attempted = True
        self.stops.append(keep_receiving_s)
        if self.stop_raises is not None:
            raise self.stop_raises

    def restarted(self) -> str | None:
        return self._restarted


class FakeWriter:
    rows = 0

    def __init__(self) -> None:
        self.end: dict | None = None

    def close(self, end: dict) -> None:
        self.end = end


class _Stats:
    def as_dict(self) -> dict[str, int]:
        return {"sent": 0}


class FakeTransport:
    stats = _Stats()

    def link_metadata(self) -> dict:
        return {}


# -- the steps ------------------------------------------------------------------------------
@pytest.mark.parametrize(("raised", "reason", "tail"), [
    (None, "completed", CONFIG.tail_s),
    (ObserverStopError(), "observer_stop", 0.0),
    (TelemetryCheckError("estop", "held"), "estop", CONFIG.tail_s),
    (TelemetryCheckError("telemetry_rate", "slow"), "telemetry_rate", 0.0),
    (LinkLostError("gone"), "link_lost", 0.0),
    (KeyboardInterrupt(), "interrupted", 0.0),
    (SessionTerminated(), "terminated", 0.0),
    (ValueError("bad"), "error", 0.0),
])
def test_stream_until_end_names_every_way_out(raised, reason, tail):
    ending, tail_s = sp.stream_until_end(FakeSession(run_raises=raised), CONFIG)
    assert ending.reason == reason and tail_s == tail
    assert ending.error is (raised if reason in ("estop", "telemetry_rate", "link_lost",
                                                  "error") else None)


def test_stream_until_end_reports_a_profile_run_to_its_end_not_as_asked():
    sess = FakeSession(not_as_asked=("clock_drift", "drifted"))
    ending, tail_s = sp.stream_until_end(sess, CONFIG)
    assert (ending.reason, ending.message, tail_s) == ("clock_drift", "drifted", CONFIG.tail_s)
    assert ending.ran_to_end


def test_end_stream_raises_a_kept_signal_as_the_end_and_keeps_signals_after():
    guard = SignalGuard(active=False)
    guard.pending = signal.SIGTERM  # came while the handlers went in
    ending, tail_s = sp.end_stream(FakeSession(), CONFIG, guard)
    assert ending.reason == "terminated" and tail_s == 0.0
    guard._on_signal(signal.SIGINT, None)  # kept from now on, not raised
    assert guard.pending == signal.SIGINT


def test_send_stop_sends_stop_with_the_tail_and_finds_a_restart_after_silence():
    sess = FakeSession(restarted="it restarted")
    silence = sp.Ending("link_lost", "no telemetry", TelemetrySilenceError("quiet"))
    ending, settling = sp.send_stop(sess, silence, 0.05, settling=False)
    assert sess.stops == [0.05] and not settling
    assert (ending.reason, ending.message) == ("controller_reset", "it restarted")


def test_send_stop_probes_for_a_restart_only_after_silence():
    sess = FakeSession(restarted="it restarted")
    lost = sp.Ending("link_lost", "port gone", LinkLostError("port gone"))
    ending, _ = sp.send_stop(sess, lost, 0.0, settling=False)
    assert ending == lost and sess.stops == [0.0]


@pytest.mark.parametrize("settling", [True, False])
def test_a_signal_in_the_stop_ends_the_run_only_with_episodes_to_come(settling):
    sess = FakeSession(stop_raises=KeyboardInterrupt())
    ending, still = sp.send_stop(sess, sp.Ending(), 0.0, settling=settling)
    assert sess.stops == [0.0] and still is False
    assert ending.reason == ("interrupted" if settling else "completed")


@pytest.mark.parametrize(("raised", "reason", "again"), [
    (None, "completed", False), (SessionTerminated(), "terminated", True),
    (KeyboardInterrupt(), "interrupted", True), (LinkError("gone"), "link_lost", False),
    (OSError("disk"), "error", False)])
def test_settle_after_stop_asks_for_stop_again_after_a_signal(raised, reason, again):
    def settle():
        if raised is not None:
            raise raised

    ending, stop_again = sp.settle_after_stop(SignalGuard(active=False), settle, sp.Ending())
    assert ending.reason == reason and stop_again is again


def test_settle_after_stop_raises_a_signal_kept_before_it():
    guard = SignalGuard(active=False)
    guard.defer()
    guard._on_signal(signal.SIGTERM, None)
    ran = []
    ending, stop_again = sp.settle_after_stop(guard, lambda: ran.append(1), sp.Ending())
    assert ran == [] and ending.reason == "terminated" and stop_again


@pytest.mark.parametrize(("before", "exc", "reason"), [
    (sp.Ending(), ValueError("x"), "error"), (sp.Ending(), KeyboardInterrupt(), "interrupted"),
    (sp.Ending("host_stall", "paused"), SystemExit(2), "error"),
    (sp.Ending("link_lost", "gone"), SystemExit(2), "link_lost")])
def test_a_failure_never_leaves_the_ending_saying_the_stream_ran_to_its_end(before, exc, reason):
    ending = sp.ending_of_failure(before, exc)
    assert ending.reason == reason
    if reason == "error":
        assert ending.message.startswith("ended by ")


def test_stop_if_not_yet_sends_stop_once_and_keeps_a_signal():
    sess = FakeSession()
    assert sp.stop_if_not_yet(sess) is None and sess.stops == [0.0]
    assert sp.stop_if_not_yet(sess) is None and sess.stops == [0.0]  # not twice
    interrupted = FakeSession(stop_raises=SessionTerminated())
    assert isinstance(sp.stop_if_not_yet(interrupted), SessionTerminated)
    assert interrupted.stops == [0.0]


def test_close_observers_keeps_a_signal_and_ignores_other_failures():
    sess = FakeSession()
    sess.pump = _Pump(close_raises=RuntimeError("thread"))
    assert sp.close_observers(sess) is None and sess.pump.closed
    sess.pump = _Pump(close_raises=KeyboardInterrupt())
    assert isinstance(sp.close_observers(sess), KeyboardInterrupt)


def test_the_end_is_written_when_making_it_fails():
    def broken():
        raise KeyError("episode")

    meta, late = sp.end_metadata_or_fallback(FakeSession(), FakeTransport(),
                                             sp.Ending("link_lost", "gone"), {}, broken)
    assert late is None and meta["end_reason"] == "link_lost" and meta["exit_code"] == 4
    assert "end metadata failed" in meta["end_message"]
    meta, _ = sp.end_metadata_or_fallback(FakeSession(), FakeTransport(), sp.Ending(), {},
                                          lambda: {"policy_episode": 1})
    assert meta["end_reason"] == "completed" and meta["policy_episode"] == 1


def test_close_recording_sends_a_missing_stop_and_closes_whatever_raised():
    sess, writer = FakeSession(stop_raises=KeyboardInterrupt()), FakeWriter()
    sess.pump = _Pump(close_raises=SessionTerminated())
    closed = sp.close_recording(sess, FakeTransport(), writer, SignalGuard(active=False),
                                sp.Ending("error", "boom"), None)
    assert sess.stops == [0.0] and sess.pump.closed
    assert writer.end is not None and writer.end["end_reason"] == "error"
    assert isinstance(closed.late, KeyboardInterrupt)  # the first one kept
    assert closed.duration_s >= 0 and closed.latency_ms["rtt_n"] == 0.0


def test_stream_stop_close_stops_and_closes_when_an_exception_escapes():
    sess, writer = FakeSession(run_raises=SystemExit(3)), FakeWriter()
    with pytest.raises(SystemExit):
        sp.stream_stop_close(sess, FakeTransport(), writer, "r.csv", CONFIG)
    assert sess.stops == [0.0]
    assert writer.end["end_reason"] == "error" and "SystemExit" in writer.end["end_message"]


def test_stream_stop_close_stops_again_when_settling_is_cut_short():
    sess, writer = FakeSession(), FakeWriter()

    def settle():
        raise SessionTerminated()

    res = sp.stream_stop_close(sess, FakeTransport(), writer, "r.csv", CONFIG, settle=settle)
    assert sess.stops == [0.0, 0.0]  # STOP, then STOP again after the cut-short wait
    assert res.reason == "terminated" and res.exit_code == EXIT_CODES["terminated"]


# -- whole runs on an in-memory controller -----------------------------------------------------
class MemoryController(Transport):
    """The host's end of a link to a controller played in memory, in real time.

    Answers HELLO, sends telemetry at ``rate_hz`` acknowledging the last command, answers PING.
    After ``silent_after`` samples it sends nothing more (a lost link); ``failing`` are the
    indices of sends that raise :class:`LinkError`.
    """

    name = "memory-controller"
    port = "memory"

    def __init__(self, rate_hz: int = 100, silent_after: int | None = None,
                 failing: frozenset[int] = frozenset()) -> None:
        super().__init__()
        self.rate_hz, self.silent_after, self.failing = rate_hz, silent_after, failing
        self.sent: list = []
        self._inbox: deque = deque()
        self._start: float | None = None
        self._samples = 0
        self._out_seq = 0
        self._last_cmd = 0
        self._sends = 0

    def _reply(self, msg) -> None:
        self._inbox.append(msg)

    def _send(self, msg) -> None:
        index, self._sends = self._sends, self._sends + 1
        if index in self.failing:
            raise LinkError("memory link: send failed")
        self.sent.append(msg)
        if isinstance(msg, proto.Hello):
            self._reply(proto.HelloAck(telemetry_rate_hz=self.rate_hz, name="memory",
                                       seq=0, wheel_limit_rpm=130.0))
            self._out_seq, self._start = 1, time.perf_counter()
        elif isinstance(msg, proto.Command):
            self._last_cmd = msg.seq
        elif isinstance(msg, proto.Ping) and not self._silent():
            self._reply(proto.Pong(msg.token))

    def _silent(self) -> bool:
        return self.silent_after is not None and self._samples >= self.silent_after

    def _next_sample(self, until: float):
        if self._start is None or self._silent():
            return None
        due = self._start + (self._samples + 1) / self.rate_hz
        if due > until:
            return None
        time.sleep(max(0.0, due - time.perf_counter()))
        self._samples += 1
        return proto.Telemetry(int((due - self._start) * 1e6), (10.0, 10.0, 10.0, 10.0), 0,
                               self._last_cmd)

    def _recv(self, timeout_s: float):
        until = time.perf_counter() + timeout_s
        msg = self._inbox.popleft() if self._inbox else self._next_sample(until)
        if msg is None:
            time.sleep(max(0.0, until - time.perf_counter()))
            return None
        msg = dataclasses.replace(msg, seq=self._out_seq)
        self._out_seq += 1
        return msg

    def _close(self) -> None:
        pass

    def motion_frames(self) -> list:
        return [m for m in self.sent if isinstance(m, (proto.Command, proto.Stop))]


def _profile(duration_s: float = 0.3, rate_hz: float = 50.0):
    t = np.arange(int(duration_s * rate_hz) + 1) / rate_hz
    return t, np.tile([20.0, 0.0, 90.0], (t.size, 1))


def _assert_stopped(link: MemoryController, path) -> None:
    """The last motion frame is STOP, and the recording ends with the STOP row."""
    frames = link.motion_frames()
    assert isinstance(frames[-1], proto.Stop)
    first_stop = next(i for i, m in enumerate(frames) if isinstance(m, proto.Stop))
    assert all(isinstance(m, proto.Stop) for m in frames[first_stop:])
    rec = read_recording(path)
    events = list(rec.extra["event"])
    assert "stop" in events
    assert "cmd" not in events[events.index("stop"):]


def test_a_normal_end_sends_stop_last(tmp_path):
    link = MemoryController()
    t, cmd = _profile()
    res = run_record_session(link, t, cmd, tmp_path / "r.csv", ROBOT, config=CONFIG)
    assert res.reason == "completed" and res.exit_code == 0
    assert res.commands_sent == t.size
    _assert_stopped(link, tmp_path / "r.csv")


def test_an_exception_mid_stream_sends_stop_and_keeps_what_was_recorded(tmp_path):
    link = MemoryController()
    t, cmd = _profile(1.0)

    def progress(elapsed_s, total_s, counters):
        if elapsed_s > 0.2:
            raise RuntimeError("a progress bar that breaks")

    res = run_record_session(link, t, cmd, tmp_path / "r.csv", ROBOT, config=CONFIG,
                             progress=progress)
    assert res.reason == "error" and "progress bar" in res.message
    assert 0 < res.commands_sent < t.size
    _assert_stopped(link, tmp_path / "r.csv")
    rec = read_recording(tmp_path / "r.csv")
    events = list(rec.extra["event"])
    assert events.count("cmd") == res.commands_sent and events.count("tlm") > 0
    assert json.loads((tmp_path / "r.json").read_text())["end_reason"] == "error"


def test_failing_sends_end_as_a_lost_link_with_stop(tmp_path):
    link = MemoryController(failing=frozenset(range(6, 6 + CONFIG.max_send_failures)))
    t, cmd = _profile(0.5)
    res = run_record_session(link, t, cmd, tmp_path / "r.csv", ROBOT, config=CONFIG)
    assert res.reason == "link_lost" and "sends in a row failed" in res.message
    assert res.exit_code == EXIT_CODES["link_lost"]
    _assert_stopped(link, tmp_path / "r.csv")


def test_a_lost_link_sends_stop_and_keeps_the_telemetry_before(tmp_path):
    link = MemoryController(silent_after=10)
    t, cmd = _profile(1.5)
    res = run_record_session(link, t, cmd, tmp_path / "r.csv", ROBOT, config=CONFIG)
    assert res.reason == "link_lost" and "no telemetry" in res.message
    assert res.telemetry_received == 10
    _assert_stopped(link, tmp_path / "r.csv")
    assert list(read_recording(tmp_path / "r.csv").extra["event"]).count("tlm") == 10


@pytest.mark.skipif(not MAIN_THREAD, reason="signal handlers live in the main thread")
def test_sigterm_mid_stream_sends_stop_and_ends_as_terminated(tmp_path):
    link = MemoryController()
    t, cmd = _profile(1.5)
    sent = []

    def progress(elapsed_s, total_s, counters):
        if elapsed_s > 0.2 and not sent:
            sent.append(1)
            os.kill(os.getpid(), signal.SIGTERM)

    before = signal.getsignal(signal.SIGTERM)
    res = run_record_session(link, t, cmd, tmp_path / "r.csv", ROBOT,
                             config=SessionConfig(connect_timeout_s=1.0, link_timeout_s=0.3),
                             progress=progress)
    assert res.reason == "terminated" and res.exit_code == 143
    assert res.commands_sent < t.size
    _assert_stopped(link, tmp_path / "r.csv")
    assert signal.getsignal(signal.SIGTERM) is before  # handlers put back
