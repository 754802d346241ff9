"""The Foxglove live view: a WebSocket client subscribes and receives wheel speeds (measured and
predicted) and the shadow monitor's alarm as a ``foxglove.Log`` message."""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import uuid

import numpy as np
import pytest

from mecanum_hil.errors import ConfigError
from mecanum_hil.io.mcap_export import CHANNELS, LOG_DEBUG, LOG_WARNING
from mecanum_hil.link.can_link import CanTransport
from mecanum_hil.link.effects_file import SimEffects
from mecanum_hil.link.session import SessionConfig, run_record_session
from mecanum_hil.link.simulated import ControllerModel, SimulatedController
from mecanum_hil.model import Calibration, RobotProfile
from mecanum_hil.monitor import ShadowConfig
from mecanum_hil.monitor.foxglove import (
    FoxgloveLive,
    FoxgloveObserver,
    parse_address,
    start_live_view,
)
from mecanum_hil.monitor.live import LiveShadow, record_shadow
from mecanum_hil.monitor.scenarios import driving_commands, make_fault, simulate_run
from mecanum_hil.profiles import CommandProfile, Segment

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")

TIMEOUT_S = 60.0  # generous: the machine may be loaded; nothing here depends on speed
TOPICS = {role: CHANNELS[role].topic for role in ("wheels", "wheels_predicted", "alarms")}


async def _client(url: str, topics, done, ready: threading.Event, out: dict) -> None:
    """Subscribe to ``topics``; collect messages until ``done(received)`` holds."""
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"],
                                  close_timeout=1) as ws:
        by_topic: dict[str, dict] = {}
        while not set(topics) <= set(by_topic):
            frame = await asyncio.wait_for(ws.recv(), TIMEOUT_S)
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "advertise":
                    by_topic.update({c["topic"]: c for c in msg["channels"]})
        subs = {i + 1: by_topic[topic] for i, topic in enumerate(topics)}
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": sid, "channelId": ch["id"]} for sid, ch in subs.items()]}))
        ready.set()
        received: dict[str, list] = {t: [] for t in topics}
        out["channels"] = subs
        out["received"] = received
        while not done(received):
            frame = await asyncio.wait_for(ws.recv(), TIMEOUT_S)
            if isinstance(frame, bytes) and frame[0] == 0x01:  # message data
                sid, log_time = struct.unpack_from("<IQ", frame, 1)
                received[subs[sid]["topic"]].append((log_time, json.loads(frame[13:])))


class Viewer:
    """A WebSocket client on its own thread, subscribed before anything is published."""

    def __init__(self, live: FoxgloveLive, topics, done) -> None:
        self.out: dict = {}
        self.errors: list[BaseException] = []
        ready = threading.Event()

        def run() -> None:
            try:
                asyncio.run(_client(live.url, list(topics), done, ready, self.out))
            except BaseException as err:  # reported by the test's thread
                self.errors.append(err)
                ready.set()

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        assert ready.wait(TIMEOUT_S) and not self.errors, self.errors
        # the server has taken the subscriptions: nothing published from now on is missed
        assert live.wait_for_subscribers(topics, TIMEOUT_S)

    def join(self) -> dict[str, list]:
        self.thread.join(TIMEOUT_S)
        assert not self.thread.is_alive() and not self.errors, self.errors
        return self.out["received"]


def _has_alarm(received) -> bool:
    # the warm-up's noise estimates come first, as debug messages
    return any(m["level"] == LOG_WARNING for _, m in received[TOPICS["alarms"]])


def test_live_view_serves_wheel_speeds_and_alarms():
    live = FoxgloveLive(port=0)  # localhost, a free port
    try:
        assert live.url.startswith("ws://127.0.0.1:")
        viewer = Viewer(live, TOPICS.values(), _has_alarm)
        # a run whose wheel 2 stalls at 4 s, fed sample by sample as a session would
        t, cmd = driving_commands(6.0, 100.0)
        rec = simulate_run(t, cmd, Calibration(), make_fault("stall", 4.0), noise_rpm=0.5)
        shadow = LiveShadow(Calibration(), RobotProfile(), ShadowConfig())
        view = FoxgloveObserver(live, shadow)
        for i in range(len(rec)):
            shadow.on_telemetry(rec.t_s[i], rec.commands[i], rec.wheel_rpm[i])
            view.on_telemetry(rec.t_s[i], rec.commands[i], rec.wheel_rpm[i])
        assert shadow.monitor.alarms, "the stall must raise an alarm"
        got = viewer.join()
    finally:
        live.close()

    wheels = got[TOPICS["wheels"]]
    assert wheels, "no wheel speeds received"
    # the samples arrive in order with their values
    first_t = wheels[0][1]["t_s"]
    i0 = int(np.flatnonzero(np.isclose(rec.t_s, first_t))[0])
    for k, (_, msg) in enumerate(wheels[:50]):
        assert msg["t_s"] == pytest.approx(rec.t_s[i0 + k])
        np.testing.assert_allclose([msg[f"wheel{j}_rpm"] for j in range(1, 5)],
                                   rec.wheel_rpm[i0 + k])
    assert got[TOPICS["wheels_predicted"]]
    logs = [m for _, m in got[TOPICS["alarms"]]]
    assert {m["level"] for m in logs[:-1]} == {LOG_DEBUG}  # noise estimates of the warm-up
    alarm = logs[-1]
    assert alarm["level"] == LOG_WARNING and "ALARM" in alarm["message"]
    assert "wheel2_rpm" in alarm["message"]
    assert viewer.out["channels"][3]["schemaName"] == "foxglove.Log"
    assert viewer.out["channels"][3]["encoding"] == "json"
    log_times = [lt for lt, _ in wheels]
    assert log_times == sorted(log_times)


def test_record_session_feeds_the_live_view(tmp_path):
    """``record --shadow paper --foxglove``'s observers on a real session: the simulated
    controller on python-can's virtual bus."""
    channel = f"mh-fox-{uuid.uuid4().hex[:8]}"
    ctrl = SimulatedController(CanTransport("virtual", channel),
                               ControllerModel(Calibration(), RobotProfile(), SimEffects()))
    server = threading.Thread(target=ctrl.serve, daemon=True)
    server.start()
    prof = CommandProfile("fox", (Segment("hold", 0.2), Segment("step", 1.0, n_rpm=40.0)))
    t, cmd = prof.sample(50.0)
    topics = [CHANNELS["commands"].topic, TOPICS["wheels"], TOPICS["wheels_predicted"]]
    live = start_live_view("127.0.0.1:0", None)  # the address parsing of --foxglove
    try:
        shadow = record_shadow("paper", RobotProfile(), t, cmd, tmp_path / "run.csv")
        view = FoxgloveObserver(live.live, shadow)
        viewer = Viewer(live.live, topics, lambda r: min(
            len(r[TOPICS["wheels"]]), len(r[TOPICS["wheels_predicted"]])) >= 80)
        with CanTransport("virtual", channel) as link:
            result = run_record_session(link, t, cmd, tmp_path / "run.csv", RobotProfile(),
                                        config=SessionConfig(handle_sigterm=False),
                                        observers=[shadow, view])
        shadow.close()
        got = viewer.join()
    finally:
        live.live.close()
        ctrl.stop_event.set()
        server.join(5)
    assert result.exit_code == 0
    commands = [m for _, m in got[CHANNELS["commands"].topic]]
    assert commands[0]["n_cmd_rpm"] == 0.0 and 40.0 in [m["n_cmd_rpm"] for m in commands]
    wheels = [m for _, m in got[TOPICS["wheels"]]]
    assert max(m["wheel1_rpm"] for m in wheels) > 20.0  # the robot moved
    predicted = [m for _, m in got[TOPICS["wheels_predicted"]]]
    assert [m["t_s"] for m in predicted[:80]] == [m["t_s"] for m in wheels[:80]]


@pytest.mark.parametrize(("text", "expected"), [
    (None, ("127.0.0.1", 8765)), ("", ("127.0.0.1", 8765)), ("9000", ("127.0.0.1", 9000)),
    (":9001", ("127.0.0.1", 9001)), ("0.0.0.0:8766", ("0.0.0.0", 8766)),
    ("[::1]:8767", ("::1", 8767)), ("myhost", ("myhost", 8765)),
])
def test_address_parsing_defaults_to_localhost(text, expected):
    assert parse_address(text) == expected


def test_bad_address_is_one_line():
    with pytest.raises(ConfigError, match="HOST:PORT"):
        parse_address("host:port")
    with pytest.raises(ConfigError, match=r"0\.\.65535"):
        parse_address("host:70000")


def test_foxglove_option_value_may_be_left_out():
    from mecanum_hil.cli._options import fill_optional_values

    assert fill_optional_values(["record", "--foxglove", "--out", "r.csv"]) == [
        "record", "--foxglove", "", "--out", "r.csv"]
    assert fill_optional_values(["shadow", "--foxglove"]) == ["shadow", "--foxglove", ""]
    assert fill_optional_values(["record", "--foxglove", "0.0.0.0:9000"]) == [
        "record", "--foxglove", "0.0.0.0:9000"]


def test_shadow_replay_refuses_the_live_view(repo, capsys):
    from mecanum_hil.cli import main

    rec = repo / "recordings" / "samples" / "paper-step-60.csv"
    assert main(["shadow", "--replay", str(rec), "--no-events", "--foxglove"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --foxglove serves a live run") and "export" in err


def test_record_that_cannot_open_its_port_stops_the_live_view(tmp_path, capsys):
    """A serial port that does not open: one error line, and the Foxglove server it had
    started is stopped (its port can be served again in the same process)."""
    import socket

    from mecanum_hil.cli import main

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(["record", "--transport", "serial", "--port", str(tmp_path / "no-such-tty"),
                 "--profile", "paper-step-60", "--out", str(tmp_path / "r.csv"), "--no-progress",
                 "--foxglove", f"127.0.0.1:{port}"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and err.startswith("error: ") and "\n" not in err, err
    assert "no-such-tty" in err  # the port, not the profile
    with socket.socket() as c:  # nothing listens there any more
        c.settimeout(5)
        assert c.connect_ex(("127.0.0.1", port)) != 0
