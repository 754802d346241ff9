"""A simulated ROS 2 Mecanum robot: cmd_vel in, joint_states and odom out.

The robot of ``sim-robot --transport ros2``: the calibration's model with its effects (and an
effects file's noise, faults and unmodelled effects, as the other simulated controllers) on
a real-time tick. It behaves as a ros2_control robot with a Mecanum drive controller does:

- each Twist (or TwistStamped) on the command topic becomes the three commands (``import``'s
  conversion) and acts from the tick it was published (its DDS source timestamp, this host's
  clock: a robot does not share the host's processor); a TwistStamped older than the
  reference timeout by the robot's clock is refused;
- without a command for the reference timeout (0.5 s) the wheels are commanded to zero;
- JointState (the four wheel joints: position [rad], velocity [rad/s]) and Odometry (the
  true pose and body twist) are published at the joint-state rate, stamped by the robot's
  clock (the host's wall clock plus an optional offset: a robot without NTP).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np

from ...model import RobotProfile, wheels_to_twist
from ...units import RPM_TO_RAD_S, rpm_to_mps
from ..simulated import ControllerModel
from .convert import (
    heard_command,
    ns_to_stamp,
    stamp_to_ns,
    wheel_rpm_to_joint_velocity,
    yaw_to_quaternion,
)
from .node import Ros2Node, valid_sample

#: Joint names published by default (wheels 1 FL, 2 FR, 3 RL, 4 RR).
DEFAULT_JOINTS = ("front_left_wheel_joint", "front_right_wheel_joint",
                  "rear_left_wheel_joint", "rear_right_wheel_joint")

#: Direction before the first translation [deg] (straight ahead).
THETA_START_DEG = 90.0


class SimulatedRos2Robot:
    """The simulated robot on a ROS 2 node (see the module docstring).

    Parameters
    ----------
    model : ControllerModel
        The robot's truth on its internal tick.
    node : Ros2Node
    cmd_topic, cmd_type, joint_topic, odom_topic : str
        Topics, and ``twist`` or ``twist-stamped`` for the commands.
    joints : sequence of str
        Joint names of wheels 1..4.
    wheel_signs : sequence of float
        +1 or -1 per wheel (a joint whose positive axis turns the wheel backwards: -1).
    joint_rate_hz : float
        Rate of JointState and Odometry [Hz].
    best_effort : bool
        Publish them best effort (ROS's sensor-data QoS) instead of reliable.
    reference_timeout_s : float
        Command silence after which the wheels are commanded to zero [s].
    clock_offset_s : float
        The robot's clock minus the host's [s].
    log : callable
        One line per event.
    """

    def __init__(self, model: ControllerModel, node: Ros2Node, *, cmd_topic: str = "/cmd_vel",
                 cmd_type: str = "twist", joint_topic: str = "/joint_states",
                 odom_topic: str = "/odom", joints=DEFAULT_JOINTS, wheel_signs=(1, 1, 1, 1),
                 joint_rate_hz: float = 50.0, best_effort: bool = False,
                 reference_timeout_s: float = 0.5, clock_offset_s: float = 0.0,
                 log: Callable[[str], None] = print) -> None:
        from cyclonedds.core import ReadCondition, SampleState, WaitSet

        from . import messages as m

        self.model, self.node, self.m, self.log = model, node, m, log
        self.robot: RobotProfile = model.robot
        self.stamped = cmd_type == "twist-stamped"
        self.joints = list(joints)
        self.signs = np.asarray(wheel_signs, dtype=float)
        self.period_ticks = max(1, round(model.rate_hz / joint_rate_hz))
        self.reference_timeout_s = reference_timeout_s
        self.clock_offset_ns = round(clock_offset_s * 1e9)
        self.cmd_reader = node.reader(cmd_topic, m.TwistStamped if self.stamped else m.Twist)
        self.joint_writer = node.writer(joint_topic, m.JointState, reliable=not best_effort)
        self.odom_writer = (node.writer(odom_topic, m.Odometry, reliable=not best_effort)
                            if odom_topic else None)
        self._waitset = WaitSet(node.participant)
        self._waitset.attach(ReadCondition(self.cmd_reader, SampleState.Any))
        self.stop_event = threading.Event()
        self.commands_received = 0
        self.stale_commands = 0
        self.timeouts = 0
        self.last_twist: tuple[float, float, float] | None = None
        self._theta = THETA_START_DEG
        self._positions = np.zeros(4)
        self._last_cmd_s = -math.inf
        self._moving = False
        self._t0 = time.monotonic()
        self._wall0_ns = time.time_ns()

    # -- clock -------------------------------------------------------------------------------
    def now_s(self) -> float:
        """Time since the robot started [s]."""
        return time.monotonic() - self._t0

    def _tick_now(self) -> int:
        return math.floor(self.now_s() * self.model.rate_hz)

    def _stamp(self, tick: int):
        t_ns = self._wall0_ns + round(tick * self.model.dt_s * 1e9) + self.clock_offset_ns
        return self.m.Time(*ns_to_stamp(t_ns))

    # -- commands ----------------------------------------------------------------------------
    def _take_commands(self, wait_s: float) -> None:
        from cyclonedds.util import duration

        samples = self.cmd_reader.take(64)
        if not samples and wait_s > 0:
            self._waitset.wait(duration(seconds=wait_s))
            samples = self.cmd_reader.take(64)
        for sample in samples:
            if not valid_sample(sample):
                continue
            if self.stamped and self._stale(sample.header.stamp):
                continue
            v, cmd = heard_command(sample, self.stamped, self.robot.wheel_radius_m, self._theta)
            if cmd is None:
                self.log(f"refused a command that is not finite: {v}")
                continue
            self._theta = float(cmd[2])
            self.model.set_command(self._arrival_tick(sample), cmd)
            self.commands_received += 1
            self.last_twist = v
            self._last_cmd_s = self.now_s()
            self._moving = any(x != 0.0 for x in v)

    def _arrival_tick(self, sample) -> int:
        """The tick a command acts from: when it was published (its DDS source timestamp,
        on this host's clock) rather than when this process got to read it. A robot has a
        processor of its own; this one shares the host's, and a starved process would read
        commands late and act as if the robot had a dead time."""
        now = self._tick_now()
        src_ns = sample.sample_info.source_timestamp
        if src_ns <= 0:
            return now
        sent = math.floor((src_ns - self._wall0_ns) * 1e-9 * self.model.rate_hz)
        return min(now, max(sent, self.model.anchor))

    def _stale(self, stamp) -> bool:
        """Whether a TwistStamped is older than the reference timeout by this robot's clock
        (as ros2_control's Mecanum drive controller ages its references); said once."""
        age_s = (self._robot_now_ns() - stamp_to_ns(stamp.sec, stamp.nanosec)) * 1e-9
        if age_s <= self.reference_timeout_s:
            return False
        self.stale_commands += 1
        if self.stale_commands == 1:
            self.log(f"refused a command stamped {age_s:.3f} s ago by this robot's clock "
                     f"(older than the {self.reference_timeout_s:g} s reference timeout)")
        return True

    def _robot_now_ns(self) -> int:
        return time.time_ns() + self.clock_offset_ns

    def _check_timeout(self) -> None:
        if self._moving and self.now_s() - self._last_cmd_s > self.reference_timeout_s:
            self.model.set_command(self._tick_now(), (0.0, 0.0, self._theta))
            self._moving = False
            self.timeouts += 1
            self.log(f"no command for {self.reference_timeout_s:g} s: wheels commanded to zero")

    # -- measurements ------------------------------------------------------------------------
    def publish(self, tick: int) -> None:
        """Publish the joint states and odometry of ``tick``."""
        m = self.m
        wheels = self.model.measured_rpm(tick)
        header = m.Header(self._stamp(tick), "")
        self._positions += (np.nan_to_num(wheels) * RPM_TO_RAD_S * self.signs
                            * self.period_ticks * self.model.dt_s)
        self.joint_writer.write(m.JointState(
            header, list(self.joints), [float(p) for p in self._positions],
            wheel_rpm_to_joint_velocity(wheels, self.signs), []))
        if self.odom_writer is None:
            return
        x, y, phi = self.model.pose(tick)
        vx, vy, wz = wheels_to_twist(self.model.wheel_rpm(tick), self.robot.k)
        r = self.robot.wheel_radius_m
        self.odom_writer.write(m.Odometry(
            m.Header(self._stamp(tick), "odom"), "base_link",
            m.PoseWithCovariance(m.Pose(m.Point(float(x), float(y), 0.0),
                                        m.Quaternion(*yaw_to_quaternion(float(phi)))),
                                 [0.0] * 36),
            m.TwistWithCovariance(m.Twist(m.Vector3(float(rpm_to_mps(vx, r)),
                                                    float(rpm_to_mps(vy, r)), 0.0),
                                          m.Vector3(0.0, 0.0, float(wz) * RPM_TO_RAD_S)),
                                  [0.0] * 36)))

    def serve(self, duration_s: float | None = None) -> None:
        """Run until :attr:`stop_event` is set or ``duration_s`` has passed [s]."""
        end = math.inf if duration_s is None else self.now_s() + duration_s
        next_tick = 0
        dt = self.model.dt_s
        while not self.stop_event.is_set() and self.now_s() < end:
            self._take_commands(max(0.0, min(0.02, next_tick * dt - self.now_s())))
            self._check_timeout()
            now_tick = self._tick_now()
            if now_tick - next_tick > 50 * self.period_ticks:
                next_tick = now_tick  # a long stall: skip, not burst
            while now_tick >= next_tick:
                self.publish(next_tick)
                next_tick += self.period_ticks
