"""Shadow mode beside a ROS 2 robot driven by someone else (teleop, Nav2).

:class:`Ros2Source` hears the command topic (Twist or TwistStamped, turned into the three
commands as ``import`` turns them) and the joint states (timed by their header stamps, the
robot's clock), and publishes the monitor's verdict as ``diagnostic_msgs/DiagnosticArray``
on ``/diagnostics``, ROS's health convention (rqt_robot_monitor, diagnostic_aggregator and
Foxglove show it): once a second, and at once when the level changes. It never publishes a
command.

Levels: OK (0) while the robot follows its model (also during the warm-up), ERROR (2) while
a channel has diverged (its wheel and residual in ``values``), STALE (3) when no joint
state came for a second. When the commands stop coming (a teleop that publishes only on a
key press), the model stops the wheels after the robot's reference timeout, as the robot does.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ..errors import ConfigError, LinkLostError
from ..link.protocol import Command, Telemetry
from ..model.robot import RobotProfile
from .live import HeardSource, LiveShadow

#: Status name on /diagnostics.
STATUS_NAME = "mecanum-hil: shadow"

#: Period of the diagnostics when nothing changes [s].
DIAGNOSTICS_PERIOD_S = 1.0

#: Joint-state silence after which the status is STALE [s].
STALE_AFTER_S = 1.0

#: Direction before the first translation heard [deg] (straight ahead).
THETA_START_DEG = 90.0


class Ros2Source(HeardSource):
    """A ROS 2 robot heard passively; the monitor's verdict on ``/diagnostics``.

    Parameters
    ----------
    robot : RobotProfile
        Wheel radius (twists to commands).
    cmd_topic, cmd_type, joint_topic : str
        As ``record --transport ros2``.
    joints, wheel_signs : optional
        Wheel joints (default detected from the first joint state) and signs.
    diagnostics_topic : str
        Where the status goes.
    reference_timeout_s : float
        The robot's command timeout [s]: when the commands stop coming, the model stops the
        wheels this long after the last one, as the robot's controller does.
    domain : int, optional
        DDS domain (default ``ROS_DOMAIN_ID``, else 0).
    """

    hint = "is the robot publishing its joint states in this ROS_DOMAIN_ID?"

    def __init__(self, robot: RobotProfile, *, cmd_topic: str = "/cmd_vel",
                 cmd_type: str = "twist", joint_topic: str = "/joint_states", joints=None,
                 wheel_signs=None, diagnostics_topic: str = "/diagnostics",
                 reference_timeout_s: float = 0.5, domain: int | None = None) -> None:
        from ..importers.rosbag import parse_joints, parse_wheel_signs
        from ..link.ros2.node import Ros2Node, command_type, ros2_messages

        m = ros2_messages()
        from cyclonedds.core import ReadCondition, SampleState, WaitSet


        cmd_msg = command_type(m, cmd_type)
        self.m, self.robot = m, robot
        self.stamped = cmd_type == "twist-stamped"
        self.joint_topic = joint_topic
        self.joints = None if joints is None else parse_joints(joints)
        self.signs = np.ones(4) if wheel_signs is None else parse_wheel_signs(wheel_signs)
        self.node = Ros2Node(domain)
        self.name = f"ROS 2 domain {self.node.domain} ({cmd_topic}, {joint_topic})"
        try:
            self.cmd_reader = self.node.reader(cmd_topic, cmd_msg)
            self.joint_reader = self.node.reader(joint_topic, m.JointState)
            self.diag_writer = self.node.writer(diagnostics_topic, m.DiagnosticArray)
            self.waitset = WaitSet(self.node.participant)
            for reader in (self.cmd_reader, self.joint_reader):
                self.waitset.attach(ReadCondition(reader, SampleState.Any))
        except BaseException:
            self.node.close()
            raise
        from ..link.ros2.convert import RobotClock

        self.reference_timeout_s = reference_timeout_s
        self.clock = RobotClock()
        self.ignored = 0
        self._names_seen: set[str] = set()
        self._moving = False
        self._last_cmd_s = -math.inf
        self._theta = THETA_START_DEG
        self._seq = 0
        self._last_joint_s = -math.inf
        self._level: int | None = None
        self._next_publish = 0.0
        #: Statuses published, and those of level ERROR.
        self.published = 0
        self.errors_published = 0

    # -- hearing -----------------------------------------------------------------------------
    def receive(self, timeout_s: float) -> list[tuple[Any, float]]:
        from cyclonedds.util import duration

        from ..link.ros2.node import valid_sample

        try:
            cmds = self.cmd_reader.take(64)
            joints = self.joint_reader.take(64)
            if not cmds and not joints and timeout_s > 0:
                self.waitset.wait(duration(seconds=timeout_s))
                cmds = self.cmd_reader.take(64)
                joints = self.joint_reader.take(64)
        except Exception as err:  # the DDS library failing under us
            raise LinkLostError(f"{self.name}: link lost: {err}") from err
        now = time.time()
        out: list[tuple[Any, float]] = []
        for s in cmds:
            if valid_sample(s):
                out.append((self._command(s), now))
                self._last_cmd_s = now
        for s in joints:
            if valid_sample(s):
                out.append((self._telemetry(s, now), now))
        if self._moving and not cmds and now - self._last_cmd_s > self.reference_timeout_s:
            # the robot's own reference timeout has stopped it (a teleop that went quiet)
            self._moving = False
            out.append((Command(0.0, 0.0, self._theta, seq=self._seq),
                        self._last_cmd_s + self.reference_timeout_s))
        return [(msg, stamp) for msg, stamp in out if msg is not None]

    def _command(self, sample) -> Command | None:
        from ..link.ros2.convert import heard_command

        v, cmd = heard_command(sample, self.stamped, self.robot.wheel_radius_m, self._theta)
        if cmd is None:
            return None
        n, omega, theta = cmd
        self._theta = float(theta)
        self._seq += 1
        self._moving = any(x != 0.0 for x in v)
        return Command(float(n), float(omega), float(theta), seq=self._seq)

    def _telemetry(self, js, recv_s: float) -> Telemetry | None:
        """A joint state as telemetry; None for one without the wheel joints (another
        publisher on the topic: an arm, casters)."""
        from ..importers.rosbag import wheel_joints
        from ..link.ros2.convert import joint_wheel_rpm

        if self.joints is None:
            self.joints = wheel_joints(list(js.name))
            if self.joints is None:
                self._names_seen.update(js.name)
                if len(self._names_seen) > 64 or self.ignored > 500:
                    raise ConfigError(f"cannot tell the wheels apart in {self.joint_topic}; "
                                      f"joints found: {', '.join(sorted(self._names_seen))} "
                                      "(give --joints FL,FR,RL,RR)")
                self.ignored += 1
                return None
        if not set(self.joints) <= set(js.name):
            self.ignored += 1
            return None
        t_ns = self.clock.time_of(js, round(recv_s * 1e9))
        self._seq += 1
        self._last_joint_s = time.monotonic()
        wheels = joint_wheel_rpm(js.name, js.velocity, self.joints, self.signs)
        return Telemetry(self.clock.controller_us(t_ns), tuple(float(w) for w in wheels),
                         seq=self._seq)

    # -- the verdict on /diagnostics ---------------------------------------------------------
    def status(self, live: LiveShadow) -> tuple[int, str, list[tuple[str, str]]]:
        """``(level, message, values)`` of the monitor now."""
        m = self.m
        st = live.monitor.status()
        values = [("samples", str(st["samples"])), ("alarms", str(st["alarms"]))]
        diverged = []
        for name, ch in st["channels"].items():
            values += [(f"{name} state", ch["state"]), (f"{name} residual",
                                                        f"{ch['residual']:.4g}")]
            if ch["state"] == "DIVERGED":
                diverged.append(f"{name} residual {ch['residual']:+.3g}")
        if time.monotonic() - self._last_joint_s > STALE_AFTER_S:
            return m.STALE, f"no joint state on {self.joint_topic} for a second", values
        if diverged:
            return m.ERROR, "diverged from the model: " + ", ".join(diverged), values
        warm = all(ch["state"] == "warm-up" for ch in st["channels"].values())
        return m.OK, ("warming up" if warm or not st["channels"]
                      else "follows its model"), values

    def on_status(self, live: LiveShadow, now_s: float) -> None:
        level, message, values = self.status(live)
        if level == self._level and now_s < self._next_publish:
            return
        self._level = level
        self._next_publish = now_s + DIAGNOSTICS_PERIOD_S
        self.publish(level, message, values)

    def publish(self, level: int, message: str, values: list[tuple[str, str]]) -> None:
        """Publish one DiagnosticArray with the shadow's status."""
        from ..link.ros2.convert import ns_to_stamp

        m = self.m
        status = m.DiagnosticStatus(level, STATUS_NAME, message, self.robot.name,
                                    [m.KeyValue(k, v) for k, v in values])
        self.diag_writer.write(m.DiagnosticArray(m.Header(m.Time(*ns_to_stamp(time.time_ns())),
                                                          ""), [status]))
        self.published += 1
        self.errors_published += level == m.ERROR

    def counts(self) -> dict[str, int]:
        return {"diagnostics_published": self.published,
                "diagnostics_errors": self.errors_published,
                "joint_states_ignored": self.ignored}

    def close(self) -> None:
        from cyclonedds.util import duration

        try:
            self.diag_writer.wait_for_acks(duration(seconds=0.2))
        except Exception:
            pass
        self.node.close()
