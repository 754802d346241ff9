"""ROS bags in: rosbag2 (sqlite3, MCAP) and ROS 1 bags written with the rosbags writers from a
simulated Mecanum run with known commands and wheel speeds."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from mecanum_hil.cli import main
from mecanum_hil.errors import RecordingError
from mecanum_hil.importers import detect_format, import_source
from mecanum_hil.importers.rosbag import (
    parse_wheel_signs,
    twist_to_commands,
    wheel_corner,
    wheel_joints,
)
from mecanum_hil.io.recording import read_recording
from mecanum_hil.model import Calibration, RobotProfile, simulate
from mecanum_hil.model.kinematics import command_to_twist
from mecanum_hil.units import RPM_TO_RAD_S, rpm_to_mps

EPOCH_NS = 1_700_000_000_123_456_789
RADIUS_M = RobotProfile().wheel_radius_m
# published in this order; the right wheels' joint axes point the other way
JOINTS = ("rear_right_wheel_joint", "front_left_wheel_joint", "rear_left_wheel_joint",
          "front_right_wheel_joint")
WHEEL_OF_JOINT = (3, 0, 2, 1)
SIGNS = np.array([1.0, -1.0, 1.0, -1.0])  # per wheel 1 FL, 2 FR, 3 RL, 4 RR
# (start [s], n [rpm], omega [deg/s], theta [deg]); a turn on the spot keeps theta
SEGMENTS = ((0.0, 0.0, 0.0, 90.0), (0.5, 60.0, 0.0, 90.0), (1.5, 80.0, 0.0, 45.0),
            (2.5, 0.0, 60.0, 45.0), (3.5, 50.0, -30.0, 200.0), (4.5, 70.0, 0.0, 0.0),
            (5.0, 40.0, 10.0, 270.0), (5.5, 0.0, 0.0, 270.0))


def simulated_run(duration_s: float = 6.0, rate_hz: float = 100.0):
    """A simulated run: sample times, commands in force, wheel speeds and pose."""
    t = np.arange(round(duration_s * rate_hz)) / rate_hz
    cmd = np.zeros((t.size, 3))
    for start, n, omega, theta in SEGMENTS:
        cmd[t >= start - 1e-9] = (n, omega, theta)
    traj = simulate(cmd, t, Calibration(), RobotProfile())
    return t, cmd, traj.wheel_rpm[0], traj.pose[0]


def _ns(t_s: float) -> int:
    return EPOCH_NS + round(t_s * 1e9)


def bag_messages(ts, ros1: bool, stamped: bool, odom: bool = True, cmd_every: int = 5,
                 odom_every: int = 2):
    """(topic, msgtype, time_ns, message) of the simulated run, in time order."""
    t, cmd, wheels, pose = simulated_run()
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]
    Vec3 = T["geometry_msgs/msg/Vector3"]

    def header(ns: int, frame: str = ""):
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if ros1:
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    twist = command_to_twist(cmd[:, 0], cmd[:, 1], cmd[:, 2])
    out = []
    for i, ti in enumerate(t):
        ns = _ns(ti)
        if i % cmd_every == 0:
            tw = T["geometry_msgs/msg/Twist"](
                linear=Vec3(x=float(rpm_to_mps(twist[i, 0], RADIUS_M)),
                            y=float(rpm_to_mps(twist[i, 1], RADIUS_M)), z=0.0),
                angular=Vec3(x=0.0, y=0.0, z=float(np.radians(cmd[i, 1]))))
            if stamped:
                out.append(("/cmd_vel", "geometry_msgs/msg/TwistStamped", ns,
                            T["geometry_msgs/msg/TwistStamped"](header=header(ns), twist=tw)))
            else:
                out.append(("/cmd_vel", "geometry_msgs/msg/Twist", ns, tw))
        vel = np.array([wheels[i, w] * RPM_TO_RAD_S * SIGNS[w] for w in WHEEL_OF_JOINT])
        out.append(("/joint_states", "sensor_msgs/msg/JointState", ns,
                    T["sensor_msgs/msg/JointState"](header=header(ns), name=list(JOINTS),
                                                    position=np.zeros(4), velocity=vel,
                                                    effort=np.zeros(0))))
        if odom and i % odom_every == 0:
            half = np.radians(pose[i, 2]) / 2
            P = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=pose[i, 0], y=pose[i, 1], z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(half),
                                                              w=np.cos(half)))
            out.append(("/odom", "nav_msgs/msg/Odometry", ns, T["nav_msgs/msg/Odometry"](
                header=header(ns, "odom"), child_frame_id="base_link",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=P,
                                                              covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=Vec3(x=0.0, y=0.0, z=0.0),
                                                       angular=Vec3(x=0.0, y=0.0, z=0.0)),
                    covariance=np.zeros(36)))))
    return out


def write_bag2(path, storage: StoragePlugin, messages=None, stamped: bool = True):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = bag_messages(ts, ros1=False, stamped=stamped) if messages is None else messages
    with Writer2(path, version=9, storage_plugin=storage) as w:
        conns = {}
        for topic, typ, ns, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], ns, ts.serialize_cdr(msg, typ))
    return path


def write_bag1(path, stamped: bool = False, messages=None):
    ts = get_typestore(Stores.ROS1_NOETIC)
    msgs = bag_messages(ts, ros1=True, stamped=stamped) if messages is None else messages
    with Writer1(path) as w:
        conns = {}
        for topic, typ, ns, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], ns, ts.serialize_ros1(msg, typ))
    return path


def check_recovered(rec):
    t, cmd, wheels, pose = simulated_run()
    np.testing.assert_allclose(rec.t_s, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec.commands, cmd, rtol=1e-6, atol=1e-9)
    # wheel speeds exactly (to floating-point rounding of rad/s <-> rpm), order and sign
    np.testing.assert_allclose(rec.wheel_rpm, wheels, rtol=1e-12, atol=1e-12)
    odom_rows = np.arange(0, t.size, 2)
    np.testing.assert_allclose(rec.pose[odom_rows, :2], pose[odom_rows, :2], atol=1e-9)
    dphi = (rec.pose[odom_rows, 2] - pose[odom_rows, 2] + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(dphi, 0.0, atol=1e-9)


OPTIONS = {"odom_topic": "/odom", "wheel_signs": "1,-1,1,-1", "wheel_radius_m": RADIUS_M}


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP],
                         ids=["sqlite3", "mcap"])
def test_rosbag2_recovers_the_run(tmp_path, storage):
    bag = write_bag2(tmp_path / "run_bag", storage)
    assert detect_format(bag) == "rosbag"
    res = import_source(bag, **OPTIONS)
    check_recovered(res.recording)
    assert any("front_left_wheel_joint" in n for n in res.notes)  # joints detected by name
    # t_s = 0 on the bag's clock, to the microsecond (the recording's resolution)
    assert res.recording.metadata["start_time_ns"] == round(EPOCH_NS, -3)


def test_rosbag2_storage_file_alone_and_unstamped_twist(tmp_path):
    write_bag2(tmp_path / "b", StoragePlugin.MCAP, stamped=False)
    (mcap_file,) = (tmp_path / "b").glob("*.mcap")
    assert detect_format(mcap_file) == "rosbag"
    check_recovered(import_source(mcap_file, "rosbag", **OPTIONS).recording)


def test_ros1_bag_recovers_the_run(tmp_path):
    bag = write_bag1(tmp_path / "run.bag")
    assert detect_format(bag) == "rosbag"
    check_recovered(import_source(bag, **OPTIONS).recording)


def test_cli_import_writes_the_recording(tmp_path, capsys):
    bag = write_bag2(tmp_path / "bag", StoragePlugin.MCAP)
    out = tmp_path / "rec.csv"
    code = main(["import", str(bag), "--out", str(out), "--odom-topic", "/odom",
                 "--wheel-signs", "+,-,+,-", "--joints", ",".join(
                     ("front_left_wheel_joint", "front_right_wheel_joint",
                      "rear_left_wheel_joint", "rear_right_wheel_joint"))])
    assert code == 0, capsys.readouterr().err
    rec = read_recording(out)
    _, cmd, wheels, _ = simulated_run()
    np.testing.assert_allclose(rec.commands, cmd, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(rec.wheel_rpm, wheels, rtol=1e-8, atol=1e-6)  # 9 digits in CSV
    assert rec.metadata["import"]["joints"][0] == "front_left_wheel_joint"
    # what the import did is in the sidecar too, and the wheel radius it assumed is said
    err = capsys.readouterr().err
    notes = rec.metadata["notes"]
    assert notes and all(f"warning: {n}" in err for n in notes)
    assert any(f"wheel radius {rec.metadata['import']['wheel_radius_m']:g} m of robot "
               "profile tdam-stm (give --robot" in n for n in notes)
    assert main(["import", str(bag), "--out", str(out), "--robot", "tdam-stm", "--joints",
                 ",".join(rec.metadata["import"]["joints"])]) == 0
    assert not any("give --robot" in n for n in read_recording(out).metadata["notes"])


def test_twist_inverse_is_exact_and_keeps_theta_at_rest():
    rng = np.random.default_rng(3)
    n = rng.uniform(1.0, 130.0, 500)
    theta = rng.uniform(0.0, 360.0, 500)
    omega = rng.uniform(-90.0, 90.0, 500)
    tw = command_to_twist(n, omega, theta)
    back = twist_to_commands(rpm_to_mps(tw[:, 0], 0.1), rpm_to_mps(tw[:, 1], 0.1),
                             np.radians(omega), 0.1)
    np.testing.assert_allclose(back, np.column_stack([n, omega, theta]), rtol=1e-9)
    # v = 0: theta keeps its last value (90 deg before any translation)
    z = twist_to_commands([0.0, 0.1, 0.0, -0.2, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0],
                          [0.5, 0.0, 1.0, 0.0, 0.0], 0.1)
    np.testing.assert_allclose(z[:, 2], [90.0, 90.0, 90.0, 270.0, 270.0])
    np.testing.assert_allclose(z[:, 0], [0.0, 0.1 / (0.1 * RPM_TO_RAD_S), 0.0,
                                         0.2 / (0.1 * RPM_TO_RAD_S), 0.0])


@pytest.mark.parametrize("names", [
    ("front_left_wheel_joint", "front_right_wheel_joint", "rear_left_wheel_joint",
     "rear_right_wheel_joint"),
    ("wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr"),
    ("FrontLeftWheel", "FrontRightWheel", "BackLeftWheel", "BackRightWheel"),
    ("left_front_wheel", "right_front_wheel", "left_back_wheel", "right_back_wheel"),
    ("fl_wheel_joint", "fr_wheel_joint", "bl_wheel_joint", "br_wheel_joint"),
])
def test_common_joint_names_are_detected(names):
    shuffled = [names[i] for i in (2, 0, 3, 1)] + ["front_left_steering", "arm_joint"]
    assert wheel_joints(shuffled) == names
    assert [wheel_corner(n) for n in names] == [0, 1, 2, 3]


def test_wheel_signs_parse():
    np.testing.assert_array_equal(parse_wheel_signs("+1,-1,+,-"), [1, -1, 1, -1])
    with pytest.raises(RecordingError, match="four signs"):
        parse_wheel_signs("1,-1,2,1")


# -- bad input: one line naming the problem --------------------------------------------------

def test_unknown_topic(tmp_path, one_line_error):
    bag = write_bag2(tmp_path / "bag", StoragePlugin.SQLITE3)
    err = one_line_error(["import", str(bag), "--out", str(tmp_path / "r.csv"),
                                   "--cmd-topic", "/mecanum/cmd"])
    assert "no topic /mecanum/cmd" in err and "/cmd_vel" in err and "--cmd-topic" in err


def test_missing_joints_are_listed(tmp_path, one_line_error):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = [(topic, typ, ns, msg) for topic, typ, ns, msg in bag_messages(ts, False, True)]
    for _, typ, _, msg in msgs:
        if typ.endswith("JointState"):
            msg.name[:] = ["j1", "j2", "j3", "j4"]
    bag = write_bag2(tmp_path / "bag", StoragePlugin.MCAP, msgs)
    err = one_line_error(["import", str(bag), "--out", str(tmp_path / "r.csv")])
    assert "cannot tell the wheels apart" in err and "j1, j2, j3, j4" in err
    err = one_line_error(["import", str(bag), "--out", str(tmp_path / "r.csv"),
                                   "--joints", "j1,j2,j3,wheel_rr"])
    assert "wheel_rr not in /joint_states" in err and "j1, j2, j3, j4" in err


def test_bag_without_messages(tmp_path, one_line_error):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    bag = tmp_path / "empty"
    with Writer2(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        w.add_connection("/cmd_vel", "geometry_msgs/msg/Twist", typestore=ts)
    err = one_line_error(["import", str(bag), "--out", str(tmp_path / "r.csv")])
    assert "no messages" in err


@pytest.mark.parametrize("kind", ["mcap", "sqlite3", "ros1"])
def test_truncated_bag(tmp_path, one_line_error, kind):
    if kind == "ros1":
        path = write_bag1(tmp_path / "run.bag")
    else:
        storage = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        (path,) = [p for p in write_bag2(tmp_path / "bag", storage).iterdir()
                   if p.suffix in (".mcap", ".db3")]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    out = tmp_path / "r.csv"
    err = one_line_error(["import", str(path), "--format", "rosbag", "--out", str(out)])
    assert str(path) in err and ("truncated" in err or "corrupt" in err), err
    assert not out.exists()


def test_joint_state_block_decoder_matches_rosbags():
    """The CDR block decoder reads what rosbags deserializes, for any name lengths, frame,
    positions or none, and sends what it cannot read as a block to the deserializer."""
    from mecanum_hil.importers.rosbag import (
        _joint_state_values,
        _Samples,
        joint_state_layout,
    )

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(0)
    js = _Samples("/joint_states", joint_state_layout, _joint_state_values)
    expected = []
    variants = [("base_link", ["a", "bb", "ccc", "dddd"], 4), ("", ["wheel_x"] * 4, 0),
                ("odom12345", ["j1", "j2", "j3", "j4", "j5"], 5)]
    for k in range(60):
        frame, names, npos = variants[k % 3]
        names = [f"{n}{k % 2}" for n in names]  # same lengths, other bytes: off the block
        vel = rng.normal(size=len(names))
        msg = T["sensor_msgs/msg/JointState"](
            header=T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=1000 + k, nanosec=k * 7),
                frame_id=frame),
            name=names, position=rng.normal(size=npos), velocity=vel, effort=np.zeros(0))
        js.add_cdr(ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"), 5 + k)
        expected.append((tuple(names), (1000 + k) * 10**9 + k * 7, vel))
    js.finish(lambda raw: ts.deserialize_cdr(raw, "sensor_msgs/msg/JointState"))
    got = {}
    for names, t, _, stamped, vel in js.blocks:
        assert stamped.all()
        for ti, v in zip(t, vel, strict=True):
            got[int(ti)] = (names, v)
    assert len(got) == len(expected)
    for names, t, vel in expected:
        assert got[t][0] == names
        np.testing.assert_array_equal(got[t][1], vel)


def test_merge_puts_no_sample_from_before_the_first_command_on_its_row():
    """Wheel samples before the first command are dropped (a note says so), not moved onto
    the first command's row at the wrong time; two samples in one microsecond are named."""
    from mecanum_hil.importers._streams import Stream, merge_streams

    cmds = Stream.of([10_000, 20_000], [[1.0, 0.0, 90.0], [2.0, 0.0, 90.0]], 3)
    wheels = Stream.of([0, 5_000, 15_000, 15_000, 15_400],
                       [[7.0] * 4, [8.0] * 4, [9.0] * 4, [9.5] * 4, [9.7, np.nan, 9.7, 9.7]], 4)
    rec, notes = merge_streams(cmds, wheels)
    np.testing.assert_allclose(rec.t_s, [0.0, 5e-6, 10e-6])
    assert np.isnan(rec.wheel_rpm[0]).all()  # the first command's row: no wheel sample there
    np.testing.assert_array_equal(rec.wheel_rpm[1], [9.7, 9.5, 9.7, 9.7])
    assert any("dropped 2 sample(s) before the first command" in n for n in notes)
    assert any("7 wheel speed(s) replaced by a later sample" in n for n in notes)


# -- time that runs back, non-finite values, empty odometry ----------------------------------

@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP],
                         ids=["sqlite3", "mcap"])
def test_a_receive_clock_reset_is_refused(tmp_path, one_line_error, storage):
    """rosbags reads messages sorted by receive time, which interleaves the halves of a bag
    whose clock was reset: the order in the file tells."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = bag_messages(ts, False, False)
    half = len(msgs) // 2
    msgs = msgs[:half] + [(a, b, ns - 3_000_000_000, m) for a, b, ns, m in msgs[half:]]
    bag = write_bag2(tmp_path / "bag", storage, msgs)
    err = one_line_error(["import", str(bag), "--out", str(tmp_path / "r.csv")])
    assert _first_back(msgs, half) in err and "runs back 2.9" in err, err


def test_a_ros1_receive_clock_reset_is_refused(tmp_path, one_line_error):
    """The same for a ROS 1 bag: its index gives each record's chunk and offset."""
    ts = get_typestore(Stores.ROS1_NOETIC)
    msgs = bag_messages(ts, True, False)
    half = len(msgs) // 2
    msgs = msgs[:half] + [(a, b, ns - 3_000_000_000, m) for a, b, ns, m in msgs[half:]]
    bag = write_bag1(tmp_path / "run.bag", messages=msgs)
    err = one_line_error(["import", str(bag), "--out", str(tmp_path / "r.csv")])
    assert _first_back(msgs, half) in err and "runs back 2.9" in err, err


def _first_back(msgs, half: int) -> str:
    """How the error names the first message after the reset: its topic's message number."""
    topic = msgs[half][0]
    n = sum(1 for m in msgs[:half + 1] if m[0] == topic)
    return f"{topic} message {n} in the file"


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_a_bag_written_one_topic_after_another_is_read(tmp_path, kind):
    """Conversion scripts write all of one topic, then the next: each topic's time runs
    forward, the file's runs back between topics. That is not a clock reset."""
    if kind == "ros1":
        ts = get_typestore(Stores.ROS1_NOETIC)
        msgs = bag_messages(ts, True, False)
        msgs = sorted(msgs, key=lambda m: m[0])  # stable: each topic keeps its order
        path = write_bag1(tmp_path / "run.bag", messages=msgs)
    else:
        ts = get_typestore(Stores.ROS2_HUMBLE)
        msgs = sorted(bag_messages(ts, False, False), key=lambda m: m[0])
        plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
        path = write_bag2(tmp_path / "bag", plugin, msgs)
    assert (np.diff([m[2] for m in msgs]) < 0).any()  # the file's time runs back
    check_recovered(import_source(path, **OPTIONS).recording)


def test_header_stamps_that_run_back_are_refused(tmp_path):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = bag_messages(ts, False, True)
    for _, typ, _, m in msgs[-40:]:  # the last stamps 1.5 s back: same clock, reset
        if typ.endswith("JointState"):
            s = m.header.stamp
            ns = s.sec * 10**9 + s.nanosec - 1_500_000_000
            s.sec, s.nanosec = ns // 10**9, ns % 10**9
    bag = write_bag2(tmp_path / "bag", StoragePlugin.MCAP, msgs)
    with pytest.raises(RecordingError, match=r"/joint_states message \d+ \(received at .*runs "
                                             r"back 1\.4\d+ s .*more than 500 ms"):
        import_source(bag, **OPTIONS)


def test_non_finite_values_and_empty_odometry_are_said(tmp_path, one_line_error):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = bag_messages(ts, False, True, odom=False)
    js = [m for _, typ, _, m in msgs if typ.endswith("JointState")]
    for m in js[::3]:
        m.velocity[:] = np.nan
    # an /odom topic without messages
    with Writer2(tmp_path / "b2", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, typ, typestore=ts) for t, typ in (
            ("/cmd_vel", "geometry_msgs/msg/TwistStamped"),
            ("/joint_states", "sensor_msgs/msg/JointState"), ("/odom", "nav_msgs/msg/Odometry"))}
        for topic, typ, ns, m in msgs:
            w.write(conns[topic], ns, ts.serialize_cdr(m, typ))
    res = import_source(tmp_path / "b2", **OPTIONS)
    assert f"{len(js[::3])} of {len(js)} joint-state samples (/joint_states) not finite: left " \
           "empty" in res.notes
    assert "no odometry on /odom: no pose" in res.notes
    for _, typ, _, m in msgs:
        if typ.endswith("TwistStamped"):
            m.twist.linear.x = float("nan")
    bag = write_bag2(tmp_path / "nan", StoragePlugin.MCAP, msgs)
    err = one_line_error(["import", str(bag), "--out", str(tmp_path / "r.csv")])
    assert "every command on /cmd_vel has a non-finite" in err


def test_a_garbage_bag_file_is_not_a_ros1_bag(tmp_path, one_line_error):
    bag = tmp_path / "x.bag"
    bag.write_bytes(bytes(range(256)) * 4)
    err = one_line_error(["import", str(bag), "--format", "rosbag", "--out",
                          str(tmp_path / "r.csv")])
    assert "not a readable ROS 1 bag" in err
