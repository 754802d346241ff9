"""Benchmark of ``mecanum-hil import`` on a long ROS 2 bag (the target: 1 hour of 100 Hz
joint states imported in under 30 s).

The bag is written with the rosbags writer from a simulated drive: ``/joint_states`` at 100 Hz
(four wheels, header stamps), ``/cmd_vel`` (TwistStamped) at 20 Hz and ``/odom`` at 50 Hz.
Measured in one run, per storage (sqlite3, MCAP):

* the baseline: reading every message of the three topics with rosbags and deserializing it,
  what an importer built on rosbags does message by message (and, for reference, reading
  alone, the floor for anything built on rosbags' readers);
* ``import_source`` (read, convert, align) and ``write_recording`` (the CSV + sidecar), as the
  CLI runs them; their sum (wall time, and the process's CPU time, which a loaded machine does
  not inflate) is the figure the target is about, printed also as a ratio of the baseline.

Run: ``python bench/bench_import_bag.py [--minutes 60] [--storage sqlite3 mcap]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from mecanum_hil.importers import import_source
from mecanum_hil.io.recording import write_recording
from mecanum_hil.model import Calibration, RobotProfile, simulate
from mecanum_hil.model.kinematics import command_to_twist
from mecanum_hil.monitor.scenarios import driving_commands
from mecanum_hil.units import RPM_TO_RAD_S, rpm_to_mps

EPOCH_NS = 1_700_000_000_000_000_000
JOINTS = ["front_left_wheel_joint", "front_right_wheel_joint", "rear_left_wheel_joint",
          "rear_right_wheel_joint"]
TARGET_S = 30.0


def write_bag(path: Path, minutes: float, storage: StoragePlugin) -> int:
    """A bag of a simulated drive; returns the number of messages."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    robot = RobotProfile()
    t, cmd = driving_commands(minutes * 60.0, 100.0)
    traj = simulate(cmd, t, Calibration(), robot)
    wheels, pose = traj.wheel_rpm[0], traj.pose[0]
    twist = command_to_twist(cmd[:, 0], cmd[:, 1], cmd[:, 2])
    Time, Header, Vec3 = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"], T[
        "geometry_msgs/msg/Vector3"]
    zero3 = Vec3(x=0.0, y=0.0, z=0.0)
    n = 0
    with Writer(path, version=9, storage_plugin=storage) as w:
        c_js = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        c_cmd = w.add_connection("/cmd_vel", "geometry_msgs/msg/TwistStamped", typestore=ts)
        c_odom = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        for i in range(t.size):
            ns = EPOCH_NS + round(t[i] * 1e9)
            hdr = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="")
            if i % 5 == 0:
                tw = T["geometry_msgs/msg/Twist"](
                    linear=Vec3(x=float(rpm_to_mps(twist[i, 0], robot.wheel_radius_m)),
                                y=float(rpm_to_mps(twist[i, 1], robot.wheel_radius_m)), z=0.0),
                    angular=Vec3(x=0.0, y=0.0, z=float(np.radians(cmd[i, 1]))))
                msg = T["geometry_msgs/msg/TwistStamped"](header=hdr, twist=tw)
                w.write(c_cmd, ns, ts.serialize_cdr(msg, "geometry_msgs/msg/TwistStamped"))
                n += 1
            msg = T["sensor_msgs/msg/JointState"](
                header=hdr, name=JOINTS, position=np.zeros(4),
                velocity=wheels[i] * RPM_TO_RAD_S, effort=np.zeros(0))
            w.write(c_js, ns, ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
            n += 1
            if i % 2 == 0:
                half = np.radians(pose[i, 2]) / 2
                p = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=pose[i, 0], y=pose[i, 1], z=0.0),
                    orientation=T["geometry_msgs/msg/Quaternion"](
                        x=0.0, y=0.0, z=np.sin(half), w=np.cos(half)))
                msg = T["nav_msgs/msg/Odometry"](
                    header=hdr, child_frame_id="base_link",
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p,
                                                                  covariance=np.zeros(36)),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](
                        twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3),
                        covariance=np.zeros(36)))
                w.write(c_odom, ns, ts.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
                n += 1
    return n


def baseline_s(path: Path, deserialize: bool = True) -> float:
    """Read (and deserialize) every message with rosbags [s]."""
    t0 = time.perf_counter()
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            if deserialize:
                reader.deserialize(raw, conn.msgtype)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--storage", nargs="+", default=["sqlite3", "mcap"],
                    choices=["sqlite3", "mcap"])
    args = ap.parse_args()
    plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.storage:
            bag = Path(tmp) / f"bag_{name}"
            t0 = time.perf_counter()
            n = write_bag(bag, args.minutes, plugins[name])
            t_write_bag = time.perf_counter() - t0
            size_mb = sum(f.stat().st_size for f in bag.iterdir()) / 1e6
            print(f"{name}: {args.minutes:g} min, {n} messages, {size_mb:.0f} MB "
                  f"(written in {t_write_bag:.1f} s)")
            base = baseline_s(bag)
            raw_only = baseline_s(bag, deserialize=False)
            t0, c0 = time.perf_counter(), time.process_time()
            res = import_source(bag, "rosbag", odom_topic="/odom",
                                wheel_radius_m=RobotProfile().wheel_radius_m)
            t_import = time.perf_counter() - t0
            t0 = time.perf_counter()
            write_recording(res.recording, Path(tmp) / f"rec_{name}.csv")
            t_csv = time.perf_counter() - t0
            cpu = time.process_time() - c0
            total = t_import + t_csv
            print(f"  baseline (rosbags read + deserialize): {base:6.2f} s")
            print(f"  rosbags read only (no deserialize)   : {raw_only:6.2f} s")
            print(f"  import (read, convert, align)        : {t_import:6.2f} s "
                  f"({t_import / base:.2f}x baseline)")
            print(f"  write CSV + sidecar                  : {t_csv:6.2f} s")
            print(f"  total                                : {total:6.2f} s "
                  f"({total / base:.2f}x baseline; target < {TARGET_S:g} s: "
                  f"{'met' if total < TARGET_S else 'NOT met'}), {len(res.recording)} rows")
            print(f"  total CPU time of the process        : {cpu:6.2f} s")


if __name__ == "__main__":
    main()
