"""The ros2 transport, sim-robot --transport ros2 and shadow --transport ros2, over DDS on the
loopback: the message layouts against ROS's own definitions, record against a simulated ROS 2
robot in another process (Twist and TwistStamped, reliable and best-effort joint states), the
zero twist as the last command on every way out, a robot that vanishes, no robot, and the
passive shadow's verdict on /diagnostics."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from ros2_stand_in import Spy, loopback_config, test_domain

from mecanum_hil.link.ros2 import messages as m
from mecanum_hil.link.ros2.convert import command_to_twist_si
from mecanum_hil.link.sim_process import spawn_sim_robot

ROBOT_RADIUS_M = 0.102  # the shipped tdam-stm profile's wheel radius


@pytest.fixture
def dds(tmp_path, monkeypatch):
    """The environment of one test's DDS participants: loopback config, its own domain."""
    config = tmp_path / "cyclonedds.xml"
    config.write_text(loopback_config(f"mecanum-hil-test-{uuid.uuid4().hex}"))
    domain = test_domain()
    env = {"CYCLONEDDS_URI": config.as_uri(), "ROS_DOMAIN_ID": str(domain)}
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return {"domain": domain, "env": env}


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "mecanum_hil", *args]


def _listening_shadow(*args: str) -> tuple[subprocess.Popen, list[str]]:
    """``shadow --transport ros2 ARGS``, once it says it is listening (its kernels compiled:
    from an empty numba cache that takes longer than any of these tests' timelines), and the
    lines it wrote before. Ctrl-C reaches it as it reaches a command in a terminal, even where
    the test runner itself ignores SIGINT (a runner started in the background)."""
    proc = subprocess.Popen(_cli("shadow", "--transport", "ros2", *args),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    while not lines or "listening" not in lines[-1]:
        line = proc.stderr.readline()
        assert line, f"shadow ended before listening: {''.join(lines)}"
        lines.append(line)
    return proc, lines


def _record(out: Path, *extra: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(_cli("record", "--transport", "ros2", "--profile", "paper-step-60",
                               "--out", str(out), "--no-progress", *extra),
                          capture_output=True, text=True, timeout=timeout)


def _is_zero(twist) -> bool:
    t = getattr(twist, "twist", twist)
    return (t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z) == \
        (0.0,) * 6


def _rows(path: Path) -> tuple[np.ndarray, list[str]]:
    from mecanum_hil.io.recording import read_recording

    rec = read_recording(path)
    return rec, list(rec.extra["event"])


# -- layouts and conversions (no DDS traffic) ------------------------------------------------

def _ros_typestore():
    rosbags = pytest.importorskip("rosbags.typesys")
    return rosbags.get_typestore(rosbags.Stores.ROS2_HUMBLE)


@pytest.mark.parametrize("ours, ros_name, fields", [
    (m.TwistStamped(m.Header(m.Time(12, 345), "base_link"),
                    m.Twist(m.Vector3(1.5, -2.0, 0.25), m.Vector3(0.1, 0.2, -0.3))),
     "geometry_msgs/msg/TwistStamped",
     {"header.stamp.sec": 12, "header.stamp.nanosec": 345, "header.frame_id": "base_link",
      "twist.linear.x": 1.5, "twist.linear.y": -2.0, "twist.angular.z": -0.3}),
    (m.JointState(m.Header(m.Time(1, 2), "j"), ["a", "bb"], [0.5, 1.5], [2.5, -3.5], []),
     "sensor_msgs/msg/JointState",
     {"name": ["a", "bb"], "position": [0.5, 1.5], "velocity": [2.5, -3.5], "effort": []}),
    (m.Odometry(m.Header(m.Time(3, 4), "odom"), "base_link",
                m.PoseWithCovariance(m.Pose(m.Point(1.0, 2.0, 3.0),
                                            m.Quaternion(0.0, 0.0, 0.6, 0.8)),
                                     [float(i) for i in range(36)]),
                m.TwistWithCovariance(m.Twist(m.Vector3(0.5, 0, 0), m.Vector3(0, 0, 0.7)),
                                      [float(-i) for i in range(36)])),
     "nav_msgs/msg/Odometry",
     {"child_frame_id": "base_link", "pose.pose.position.y": 2.0,
      "pose.pose.orientation.z": 0.6, "pose.pose.orientation.w": 0.8,
      "pose.covariance": [float(i) for i in range(36)],
      "twist.twist.angular.z": 0.7, "twist.covariance": [float(-i) for i in range(36)]}),
    (m.DiagnosticArray(m.Header(m.Time(5, 6), ""), [
        m.DiagnosticStatus(2, "shadow", "diverged", "TDAM-STM",
                           [m.KeyValue("wheel2_rpm", "-3.9"), m.KeyValue("alarms", "1")])]),
     "diagnostic_msgs/msg/DiagnosticArray",
     {"status.0.level": 2, "status.0.name": "shadow", "status.0.hardware_id": "TDAM-STM",
      "status.0.values.1.key": "alarms", "status.0.values.0.value": "-3.9"}),
])
def test_layouts_are_ros_2s_field_by_field(ours, ros_name, fields):
    store = _ros_typestore()
    raw = ours.serialize()
    theirs = store.deserialize_cdr(raw, ros_name)
    for path, want in fields.items():
        value = theirs
        for part in path.split("."):
            value = value[int(part)] if part.isdigit() else getattr(value, part)
        got = value.tolist() if hasattr(value, "tolist") else value
        assert got == want, path
    # and back: ROS's own serialisation reads as ours, byte for byte
    assert store.serialize_cdr(theirs, ros_name) == raw
    assert type(ours).deserialize(raw) == ours


def test_twist_is_the_exact_inverse_of_imports_conversion():
    from mecanum_hil.importers.rosbag import twist_to_commands

    rng = np.random.default_rng(3)
    n = rng.uniform(0.1, 120, 200)
    omega = rng.uniform(-60, 60, 200)
    theta = rng.uniform(0, 360, 200)
    tw = np.array([command_to_twist_si(a, b, c, ROBOT_RADIUS_M)
                   for a, b, c in zip(n, omega, theta, strict=True)])
    back = twist_to_commands(tw[:, 0], tw[:, 1], tw[:, 2], ROBOT_RADIUS_M)
    np.testing.assert_allclose(back[:, 0], n, rtol=1e-9)
    np.testing.assert_allclose(back[:, 1], omega, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.mod(back[:, 2] - theta + 180, 360) - 180, 0, atol=1e-7)


def test_domain_and_topic_names_follow_ros():
    from mecanum_hil.errors import ConfigError
    from mecanum_hil.link.ros2.node import dds_topic_name, domain_id

    assert domain_id({}) == 0
    assert domain_id({"ROS_DOMAIN_ID": "42"}) == 42
    for bad in ("-1", "233", "x"):
        with pytest.raises(ConfigError, match="ROS_DOMAIN_ID"):
            domain_id({"ROS_DOMAIN_ID": bad})
    assert dds_topic_name("/cmd_vel") == "rt/cmd_vel"
    assert dds_topic_name("robot1/joint_states") == "rt/robot1/joint_states"
    with pytest.raises(ConfigError):
        dds_topic_name("/1bad")


def test_without_the_extra_the_transport_names_it_in_one_line(tmp_path):
    code = ("import sys; sys.modules['cyclonedds'] = None\n"
            "from mecanum_hil.cli import run\n"
            f"sys.argv = ['mecanum-hil', 'record', '--transport', 'ros2', '--profile', "
            f"'paper-step-60', '--out', {str(tmp_path / 'r.csv')!r}]\n"
            "run()\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [
        "error: the ros2 transport needs the ros2 extra (Cyclone DDS): "
        "pip install 'mecanum-hil[ros2]'"]
    # the core never imports it on its own
    code = ("import sys, mecanum_hil.cli, mecanum_hil.link.session, mecanum_hil.monitor.live\n"
            "print('cyclonedds' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.stdout.strip() == "False"


# -- against a simulated ROS 2 robot in another process ---------------------------------------

@pytest.fixture
def ros2_robot(dds):
    """Start ``sim-robot --transport ros2 ARGS`` in the test's domain."""
    started = []

    def start(*args: str):
        proc = spawn_sim_robot("--transport", "ros2", *args, env=dds["env"])
        started.append(proc)
        assert proc.path == f"ros2:domain {dds['domain']}"
        return proc

    yield start
    for proc in started:
        proc.stop()


def test_record_drives_the_robot_and_the_fit_recovers_it(dds, ros2_robot, tmp_path):
    ros2_robot()
    spy = Spy(dds["domain"], "/cmd_vel", m.Twist)
    try:
        out = tmp_path / "step60.csv"
        proc = _record(out)
        assert proc.returncode == 0, proc.stderr
        time.sleep(0.3)
        twists = [msg for _, msg in spy.messages]
    finally:
        spy.close()
    assert twists and _is_zero(twists[-1])
    assert sum(not _is_zero(t) for t in twists) > 100
    rec, events = _rows(out)
    duration = rec.t_s[-1] - rec.t_s[0]
    cmd_rate = events.count("cmd") / duration
    wheel_rate = events.count("tlm") / duration
    assert cmd_rate >= 20 and wheel_rate >= 40, (cmd_rate, wheel_rate)
    assert events.count("odom") > 100
    assert np.isfinite(rec.pose[np.array(events) == "odom"]).all()
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["transport"] == "ros2" and meta["end_reason"] == "completed"
    ros = meta["ros2"]
    assert ros["domain"] == dds["domain"] and ros["joints_detected"]
    assert ros["joints"][0] == "front_left_wheel_joint"
    assert ros["qos"]["joint_state_publishers"] == ["reliable"]
    fit = subprocess.run(_cli("fit", str(out), "--out", str(tmp_path / "cal.toml"), "--json"),
                         capture_output=True, text=True, timeout=300)
    assert fit.returncode == 0, fit.stderr
    got = json.loads(fit.stdout)
    for key, true in (("A", 14.7), ("B", 16.1), ("C", 303.0)):
        assert abs(got[key] / true - 1) < 0.25, (key, got[key])


@pytest.mark.slow
def test_twist_stamped_to_a_best_effort_robot_with_its_own_clock(dds, ros2_robot, tmp_path):
    # a robot without NTP: its stamps are 7 s ahead of the host's clock
    robot = ros2_robot("--cmd-type", "twist-stamped", "--best-effort", "--clock-offset", "7")
    spy = Spy(dds["domain"], "/cmd_vel", m.TwistStamped)
    try:
        out = tmp_path / "stamped.csv"
        proc = _record(out, "--cmd-type", "twist-stamped")
        assert proc.returncode == 0, proc.stderr
        time.sleep(0.3)
        stamped = [msg for _, msg in spy.messages]
        received = list(spy.wall_s)
    finally:
        spy.close()
    robot.stop()
    assert stamped and _is_zero(stamped[-1])
    assert all(s.header.frame_id == "base_link" for s in stamped)
    # stamped by the robot's clock, which ages them (sim-robot refuses stale ones)
    ahead = [s.header.stamp.sec + s.header.stamp.nanosec * 1e-9 - w
             for s, w in zip(stamped, received, strict=True)]
    assert all(6.5 < a < 7.5 for a in ahead), (min(ahead), max(ahead))
    assert "0 refused as stale" in robot.log()
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["ros2"]["qos"]["joint_state_publishers"] == ["best_effort"]
    assert meta["ros2"]["clock"] == "header stamps"
    assert 6.9 < -meta["ros2"]["clock_offset_s"] < 7.5
    _, events = _rows(out)
    assert events.count("tlm") > 200  # the robot moved and reported
    # the robot's clock maps onto the host's: telemetry keeps its place among the commands
    from mecanum_hil.io.timing import read_for_analysis

    rec = read_for_analysis(out)
    offset = rec.metadata["retimed"]["offset_s"]
    assert abs(offset) < 1.0  # the stamps' 7 s are the clock's origin, not a delay


def _run_and_signal(out: Path, sig: int, after_s: float) -> subprocess.CompletedProcess:
    proc = subprocess.Popen(_cli("record", "--transport", "ros2", "--profile",
                                 "paper-step-60", "--out", str(out), "--no-progress"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out.exists() and out.stat().st_size > 2000):
        time.sleep(0.05)
    time.sleep(after_s)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=30)
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143),
                                       (signal.SIGHUP, 143)])
def test_every_signal_ends_with_a_zero_twist_last(dds, ros2_robot, tmp_path, sig, code):
    ros2_robot()
    spy = Spy(dds["domain"], "/cmd_vel", m.Twist)
    try:
        out = tmp_path / "cut.csv"
        proc = _run_and_signal(out, sig, 0.5)
        time.sleep(0.3)
        twists = [msg for _, msg in spy.messages]
    finally:
        spy.close()
    assert proc.returncode == code, proc.stderr
    assert any(not _is_zero(t) for t in twists)
    assert _is_zero(twists[-1])
    assert sum(_is_zero(t) for t in twists[-5:]) == 5  # five zero twists close the stream
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["exit_code"] == code


def test_a_robot_that_vanishes_ends_the_run_with_exit_4_and_keeps_its_samples(
        dds, ros2_robot, tmp_path):
    robot = ros2_robot()
    out = tmp_path / "vanish.csv"
    proc = subprocess.Popen(_cli("record", "--transport", "ros2", "--profile", "paper-step-60",
                                 "--out", str(out), "--no-progress"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out.exists() and out.stat().st_size > 4000):
        time.sleep(0.05)
    robot.proc.kill()
    killed = time.monotonic()
    proc.wait(30)
    ended_after = time.monotonic() - killed
    stderr = proc.stderr.read()
    assert proc.returncode == 4, stderr
    assert ended_after < 3.0
    assert "link lost" in stderr and "Traceback" not in stderr
    _, events = _rows(out)
    assert events.count("tlm") > 10
    assert events[-1] == "stop"
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["end_reason"] == "link_lost"


def test_no_robot_is_one_line_and_nothing_commanded(dds, tmp_path):
    spy = Spy(dds["domain"], "/cmd_vel", m.Twist)
    try:
        start = time.monotonic()
        proc = _record(tmp_path / "none.csv")
        took = time.monotonic() - start
        twists = list(spy.messages)
    finally:
        spy.close()
    assert proc.returncode != 0 and took < 15
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert "/joint_states" in lines[0] and f"domain {dds['domain']}" in lines[0]
    assert twists == []
    assert not (tmp_path / "none.csv").exists()


@pytest.mark.slow
def test_shadow_beside_a_driven_robot_raises_an_error_after_the_fault_only(
        dds, ros2_robot, tmp_path):
    effects = tmp_path / "fault.toml"
    effects.write_text("[noise]\nwheel_rpm_std = 0.5\nseed = 1\n\n[[faults]]\nat_s = 8.0\n"
                       "[faults.effects.wheel_gain]\ngains = [1.0, 0.8, 1.0, 1.0]\n")
    profile = tmp_path / "hold.toml"  # 10 s at 60 rpm: the fault, once in, stays in
    profile.write_text('[profile]\nname = "hold-60"\n\n[[segments]]\nkind = "hold"\n'
                       'duration_s = 0.5\n\n[[segments]]\nkind = "step"\nduration_s = 10.0\n'
                       'n_rpm = 60.0\n')
    events = tmp_path / "shadow.jsonl"
    shadow, said = _listening_shadow("--events", str(events), "--json")
    started = time.monotonic()  # the robot's fault clock starts after this
    ros2_robot("--effects", str(effects))
    diag = Spy(dds["domain"], "/diagnostics", m.DiagnosticArray)
    try:
        assert diag.wait_matched(60)
        driver = subprocess.run(_cli("record", "--transport", "ros2", "--profile", str(profile),
                                     "--out", str(tmp_path / "driver.csv"), "--no-progress"),
                                capture_output=True, text=True, timeout=120)
        assert driver.returncode == 0, driver.stderr
        shadow.send_signal(signal.SIGINT)  # Ctrl-C is how an open-ended listen ends
        stdout, stderr = shadow.communicate(timeout=60)
        stderr = "".join(said) + stderr
    finally:
        if shadow.poll() is None:
            shadow.kill()
        diag.close()
    assert shadow.returncode == 3, stderr
    summary = json.loads(stdout)
    assert summary["alarms"][0]["channel"] == "wheel2_rpm"
    fault_at = started + 8.0
    statuses = [(t, s.status[0]) for t, s in diag.messages]
    assert statuses, "nothing on /diagnostics"
    errors = [(t, st) for t, st in statuses if st.level == m.ERROR]
    assert errors and all(t > fault_at for t, _ in errors)
    assert any(st.level == m.OK for t, st in statuses if t < fault_at)
    first = errors[0][1]
    values = {kv.key: kv.value for kv in first.values}
    assert values["wheel2_rpm state"] == "DIVERGED"
    assert "wheel2_rpm" in first.message
    assert events.exists() and "listen-ros2" in events.read_text().splitlines()[0]
    assert not math.isnan(float(values["wheel2_rpm residual"]))


@pytest.mark.slow
def test_record_shadow_and_policy_work_as_over_serial(dds, ros2_robot, tmp_path):
    effects = tmp_path / "noise.toml"  # encoder noise, as a real robot's
    effects.write_text("[noise]\nwheel_rpm_std = 0.5\nseed = 5\n")
    ros2_robot("--effects", str(effects))
    out = tmp_path / "shadowed.csv"
    proc = _record(out, "--shadow", "paper")
    assert proc.returncode == 0, proc.stderr
    assert "0 alarm(s)" in proc.stdout  # the robot is the paper's model
    assert out.with_suffix(".shadow.jsonl").exists()
    folder = tmp_path / "episodes"
    proc = subprocess.run(_cli("record", "--transport", "ros2", "--policy", "scripted",
                               "--task", "reach", "--episodes", "1", "--out", str(folder),
                               "--no-progress", "--json"),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["success_rate"] == 1.0 and summary["end_reason"] == "completed"
    _, events = _rows(folder / "episode_000.csv")
    assert events.count("tlm") > 50
    last_stop = len(events) - 1 - events[::-1].index("stop")
    assert "cmd" not in events[last_stop:]  # the robot settles after its last STOP


def test_a_dry_run_shows_the_twists_and_opens_nothing(tmp_path):
    proc = subprocess.run(_cli("record", "--transport", "ros2", "--profile", "paper-turn",
                               "--out", str(tmp_path / "t.csv"), "--dry-run"),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "first twists" in proc.stdout and "a zero twist, five times" in proc.stdout
    assert not (tmp_path / "t.csv").exists()


WHEELS = ["front_left_wheel_joint", "front_right_wheel_joint", "rear_left_wheel_joint",
          "rear_right_wheel_joint"]


def test_unstamped_joint_states_beside_another_publisher_are_recorded(dds, tmp_path):
    """A robot that stamps nothing (times: the DDS source timestamps) and an arm's joint
    states on the same topic (skipped): the run completes, wheels recorded."""
    from ros2_stand_in import StubRobot

    def messages():
        wheels = m.JointState(m.Header(), WHEELS, [0.0] * 4, [1.0, 1.0, 1.0, 1.0], [])
        arm = m.JointState(m.Header(), ["arm_joint"], [0.3], [0.0], [])
        return [wheels, wheels, arm]  # two in one cycle: equal receive times

    robot = StubRobot(dds["domain"], messages)
    try:
        out = tmp_path / "unstamped.csv"
        proc = _record(out)
    finally:
        robot.close()
    assert proc.returncode == 0, proc.stderr
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["ros2"]["clock"] == "source timestamps"
    assert meta["ros2"]["ignored_joint_states"] > 50
    rec, events = _rows(out)
    tlm = np.array(events) == "tlm"
    assert tlm.sum() > 300
    np.testing.assert_allclose(rec.wheel_rpm[tlm], 60.0 / (2 * math.pi))
    assert _is_zero(robot.twists[-1])


def test_joint_states_without_velocities_are_refused_in_one_line(dds, tmp_path):
    from ros2_stand_in import StubRobot

    robot = StubRobot(dds["domain"], lambda: [
        m.JointState(m.Header(), WHEELS, [0.0] * 4, [], [])])
    try:
        proc = _record(tmp_path / "novel.csv")
    finally:
        robot.close()
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "no finite velocity" in lines[0], lines
    assert robot.twists == []  # nothing commanded


@pytest.mark.slow
def test_shadow_follows_a_teleop_that_goes_quiet_without_a_false_alarm(
        dds, ros2_robot, tmp_path):
    """A teleop publishes 0.2 m/s for 3 s and then nothing: the robot stops at its reference
    timeout, and so does the model, so shadow raises nothing."""
    from mecanum_hil.link.ros2.node import Ros2Node

    effects = tmp_path / "noise.toml"
    effects.write_text("[noise]\nwheel_rpm_std = 0.5\nseed = 4\n")
    ros2_robot("--effects", str(effects))
    shadow, said = _listening_shadow("--no-events", "--json")
    teleop = Ros2Node(dds["domain"])
    try:
        writer = teleop.writer("/cmd_vel", m.Twist)
        assert teleop.wait_matched(writer, time.monotonic() + 60)
        time.sleep(3.0)  # shadow's warm-up on a robot at rest
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            writer.write(m.Twist(m.Vector3(0.2, 0.0, 0.0), m.Vector3()))
            time.sleep(0.05)
        time.sleep(3.0)  # silence: the robot's reference timeout stops it
        shadow.send_signal(signal.SIGINT)
        stdout, stderr = shadow.communicate(timeout=60)
        stderr = "".join(said) + stderr
    finally:
        if shadow.poll() is None:
            shadow.kill()
        teleop.close()
    assert shadow.returncode == 0, stderr
    assert json.loads(stdout)["alarms"] == []
