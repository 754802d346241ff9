"""record --transport ros2 (Cyclone DDS) against a ROS 2 robot on Fast DDS, the middleware
of most ROS 2 installs: an independent robot in C++ (fastdds_robot/robot.cpp, hand-written
type support over Fast CDR, the model A, B, C on its wheels) built with g++ once per module.

Both sides stay on the loopback (Cyclone: ros2_stand_in's configuration; the robot: one UDPv4
transport on 127.0.0.1, unicast discovery) in a domain of the test's own. The checks: the
run completes, every command the session sent reached the robot as the same twist, in order,
ending with a zero twist; wheel samples and odometry come back at the robot's rate; and the
fit of the recording recovers the robot's A, B, C.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from ros2_stand_in import loopback_config, test_domain

from mecanum_hil.link.ros2.convert import command_to_twist_si

ROBOT_SOURCE = Path(__file__).parent / "fastdds_robot" / "robot.cpp"
FASTDDS_HEADER = Path("/usr/include/fastdds/dds/domain/DomainParticipant.hpp")
ROBOT_RADIUS_M = 0.102  # the shipped tdam-stm profile's wheel radius
TRUE_ABC = {"A": 14.7, "B": 16.1, "C": 303.0}  # the robot's wheel model


@pytest.fixture(scope="module")
def robot_binary(tmp_path_factory) -> Path:
    """robot.cpp built with g++ (skipped without g++ or the Fast DDS headers): once per test
    session, the pytest-xdist workers sharing the session's folder and one build."""
    if shutil.which("g++") is None:
        pytest.skip("g++ is missing (apt-get install g++)")
    if not FASTDDS_HEADER.exists():
        pytest.skip("Fast DDS headers are missing (apt-get install libfastrtps-dev)")
    folder = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        folder = folder.parent  # this session's own, shared by its workers
    folder = folder / "fastdds_robot"
    folder.mkdir(exist_ok=True)
    out = folder / "robot"
    with (folder / "build.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one worker builds, the others wait for it
        if not out.exists():
            build = subprocess.run(["g++", "-std=c++17", "-o", str(folder / "robot.part"),
                                    str(ROBOT_SOURCE), "-lfastrtps", "-lfastcdr",
                                    "-lpthread"], capture_output=True, text=True,
                                   timeout=600)
            assert build.returncode == 0, build.stderr
            (folder / "robot.part").rename(out)
    return out


class FastDdsRobot:
    """The robot in its own process: started, ``ready`` awaited, stopped by SIGTERM."""

    def __init__(self, binary: Path, domain: int, log: Path, stderr: Path, *args: str):
        self.log, self.stderr_path = log, stderr
        self._stderr = stderr.open("w")
        self.proc = subprocess.Popen([str(binary), "--domain", str(domain), "--log", str(log),
                                      *args], stdout=subprocess.PIPE, stderr=self._stderr,
                                     text=True)
        line = self._first_line(30.0)
        assert line == "ready", (line, self.stderr())

    def _first_line(self, timeout_s: float) -> str:
        import selectors

        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        try:
            if not sel.select(timeout_s):
                return f"(nothing within {timeout_s:g} s)"
            return self.proc.stdout.readline().strip()
        finally:
            sel.close()

    def stderr(self) -> str:
        if not self._stderr.closed:
            self._stderr.flush()
        return self.stderr_path.read_text()

    def twists(self) -> np.ndarray:
        """The twists logged, one row each: linear x y z, angular x y z."""
        text = self.log.read_text() if self.log.exists() else ""
        rows = [line.split() for line in text.splitlines() if line.strip()]
        return np.array(rows, dtype=float).reshape(-1, 6)

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            code = self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait(10)
        self.proc.stdout.close()
        self._stderr.close()
        return code


@pytest.fixture
def fastdds_robot(robot_binary, tmp_path, monkeypatch):
    """Start the Fast DDS robot in a domain of this test's own; record's Cyclone participant
    reads the loopback configuration (CYCLONEDDS_URI) and that domain (ROS_DOMAIN_ID)."""
    config = tmp_path / "cyclonedds.xml"
    config.write_text(loopback_config())
    domain = test_domain()
    monkeypatch.setenv("CYCLONEDDS_URI", config.as_uri())
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    started: list[FastDdsRobot] = []

    def start(*args: str) -> FastDdsRobot:
        robot = FastDdsRobot(robot_binary, domain, tmp_path / "robot-twists.log",
                             tmp_path / "robot-stderr.log", *args)
        started.append(robot)
        return robot

    yield start
    for robot in started:
        robot.stop()


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "mecanum_hil", *args]


def _wait_for(predicate, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() >= end:
            return False
        time.sleep(0.05)
    return True


@pytest.mark.parametrize("robot_args, publishers", [((), ["reliable"]),
                                                    pytest.param(("--best-effort",),
                                                                 ["best_effort"],
                                                                 marks=pytest.mark.slow)],
                         ids=["reliable", "best-effort"])
def test_record_drives_a_fast_dds_robot_and_the_fit_recovers_it(
        fastdds_robot, tmp_path, robot_args, publishers):
    from mecanum_hil.io.recording import read_recording

    robot = fastdds_robot(*robot_args)
    out = tmp_path / "step60.csv"
    started = time.monotonic()
    proc = subprocess.run(_cli("record", "--transport", "ros2", "--profile", "paper-step-60",
                               "--out", str(out), "--no-progress", "--connect-timeout", "30"),
                          capture_output=True, text=True, timeout=180)
    took = time.monotonic() - started
    assert proc.returncode == 0, (proc.stderr, robot.stderr())
    # the closing zero twists are acknowledged before record exits (reliable): wait for the
    # robot's listener to have written them
    assert _wait_for(lambda: len(robot.twists()) and not robot.twists()[-1].any(), 10.0), \
        robot.twists()[-3:]
    assert robot.stop() == 0, robot.stderr()
    logged = robot.twists()
    assert "encapsulation 0x0001" in robot.stderr()  # plain CDR, little endian

    rec = read_recording(out)
    events = list(rec.extra["event"])
    is_cmd = np.array(events) == "cmd"
    duration = rec.t_s[-1] - rec.t_s[0]
    cmd_rate = len(logged) / duration
    wheel_rate = events.count("tlm") / duration
    assert cmd_rate >= 20 and wheel_rate >= 40, (cmd_rate, wheel_rate)

    # every command reached the robot as its twist, in order (reliable: nothing lost), then
    # the zero twists of the STOP
    sent = np.array([(vx, vy, 0.0, 0.0, 0.0, wz) for vx, vy, wz in (
        command_to_twist_si(n, omega, theta, ROBOT_RADIUS_M)
        for n, omega, theta in rec.commands[is_cmd])])
    assert len(sent) > 100
    np.testing.assert_allclose(logged[:len(sent)], sent, rtol=1e-12, atol=1e-12)
    assert len(logged) > len(sent) and not logged[len(sent):].any()

    # the robot's wheels and odometry came back
    tlm = np.array(events) == "tlm"
    assert np.isfinite(rec.wheel_rpm[tlm]).all()
    assert np.abs(rec.wheel_rpm[tlm]).max() > 30  # the step of 60 rpm, seen on the wheels
    odom = np.array(events) == "odom"
    assert odom.sum() > 100 and np.isfinite(rec.pose[odom]).all()
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["end_reason"] == "completed"
    assert meta["ros2"]["joints"] == ["front_left_wheel_joint", "front_right_wheel_joint",
                                      "rear_left_wheel_joint", "rear_right_wheel_joint"]
    assert meta["ros2"]["qos"]["joint_state_publishers"] == publishers
    assert meta["ros2"]["clock"] == "header stamps"

    fit = subprocess.run(_cli("fit", str(out), "--out", str(tmp_path / "cal.toml"), "--json"),
                         capture_output=True, text=True, timeout=300)
    assert fit.returncode == 0, fit.stderr
    got = json.loads(fit.stdout)
    for key, true in TRUE_ABC.items():
        assert abs(got[key] / true - 1) < 0.25, (key, got[key], took)
