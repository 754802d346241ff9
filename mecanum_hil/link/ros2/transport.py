"""The ``ros2`` transport: a ROS 2 robot driven over DDS as if it spoke the wire protocol.

``record --transport ros2`` runs the same session as over serial (its safety, observers and
recording); this transport plays the controller's side of the protocol from ROS 2 topics:

- opening it joins the ROS 2 domain and waits (bounded) for a publisher on the joint topic,
  its first joint states (to detect the wheel joints and measure their rate) and a subscriber
  on the command topic (``cmd_vel`` is volatile: a command published before the match is
  lost);
- HELLO is answered at once with the measured joint-state rate, a 500 ms reference timeout
  (ros2_control's default ``cmd_vel_timeout``) and the robot profile's wheel limit;
- a COMMAND is published as Twist or TwistStamped (the exact inverse of ``import``'s
  conversion); STOP as a zero twist, five times within 0.1 s, and closing the link publishes
  it again unless the last twist already was zero;
- each JointState becomes a telemetry sample timed by its header stamp (the robot's clock,
  receive time where unset), each Odometry a :class:`~mecanum_hil.link.transport.PoseReading`.

ROS 2 has no acknowledgements, no PING and no sequence numbers: the session measures no
command latency and counts no lost samples on this link.
"""

from __future__ import annotations

import math
import time
import warnings
from collections import deque
from typing import Any, ClassVar

import numpy as np

from ...errors import ConfigError, LinkError, LinkLostError, MecanumHILWarning
from ...importers.rosbag import quaternion_yaw_deg
from ...importers.rosbag import wheel_joints as wheel_joints_of
from ...model.robot import RobotProfile
from ..protocol import PROTOCOL_VERSION, Command, Hello, HelloAck, Message, Stop, Telemetry
from ..transport import PoseReading, Transport
from .convert import RobotClock, command_to_twist_si, joint_wheel_rpm, ns_to_stamp
from .node import Ros2Node, command_type, ros2_messages, valid_sample

#: The reference timeout announced for a ROS 2 robot [ms]: ros2_control's default
#: ``cmd_vel_timeout`` (commands must come at least this often).
REFERENCE_TIMEOUT_MS = 500

#: Zero twists published for a STOP, and the time they must fit in [s] (spread over 60 %
#: of it, so that writing them never pushes the last beyond).
STOP_REPEATS, STOP_SPAN_S = 5, 0.1

#: Joint states taken during discovery to measure their rate (at least).
RATE_SAMPLES = 6

#: A lost link is this many joint-state periods of silence (at least the configured timeout).
LOST_AFTER_PERIODS = 5.0

#: Frame of the TwistStamped commands.
COMMAND_FRAME = "base_link"


def _parse_joints(joints):
    from ...importers.rosbag import parse_joints

    return None if joints is None else parse_joints(joints)


def _parse_signs(signs):
    from ...importers.rosbag import parse_wheel_signs

    return np.ones(4) if signs is None else parse_wheel_signs(signs)


class Ros2Transport(Transport):
    """The host's end of a link to a ROS 2 robot (cmd_vel out, joint_states and odom in).

    Parameters
    ----------
    robot : RobotProfile or str, optional
        Wheel radius (commands to m/s) and wheel limit (default the paper's robot).
    cmd_topic, joint_topic : str
        ROS 2 topics of the commands and the joint states.
    cmd_type : str
        ``twist`` (geometry_msgs/Twist) or ``twist-stamped`` (TwistStamped, stamped now,
        frame ``base_link``).
    odom_topic : str or None
        nav_msgs/Odometry for the pose columns ("" or None: none).
    joints : str or sequence of str, optional
        Joint names of wheels 1 FL, 2 FR, 3 RL, 4 RR (default: detected by name).
    wheel_signs : str or sequence, optional
        +1 or -1 per wheel (default all +1).
    discovery_timeout_s : float
        How long opening waits for the robot [s].
    domain : int, optional
        DDS domain (default ``ROS_DOMAIN_ID``, else 0).

    Raises
    ------
    LinkError
        No publisher on the joint topic, no joint state, or no subscriber on the command
        topic within ``discovery_timeout_s``.
    ConfigError
        Wheel joints that cannot be told apart (the joints found are listed), bad options.
    """

    name: ClassVar[str] = "ros2"
    acknowledges: ClassVar[bool] = False

    def __init__(self, robot: RobotProfile | str | None = None, *, cmd_topic: str = "/cmd_vel",
                 cmd_type: str = "twist", joint_topic: str = "/joint_states",
                 odom_topic: str | None = "/odom", joints=None, wheel_signs=None,
                 discovery_timeout_s: float = 5.0, domain: int | None = None) -> None:
        super().__init__()
        m = ros2_messages()

        cmd_msg = command_type(m, cmd_type)
        if isinstance(robot, str) or robot is None:
            from ...model import load_robot_profile

            robot = load_robot_profile(robot or "tdam-stm")
        self.robot = robot
        self.cmd_topic, self.cmd_type = cmd_topic, cmd_type
        self.joint_topic, self.odom_topic = joint_topic, odom_topic or None
        self.joints = _parse_joints(joints)
        self.joints_given = self.joints is not None
        self.signs = _parse_signs(wheel_signs)
        self._m = m
        self._queue: deque[Message] = deque()
        self._hello_ack: HelloAck | None = None
        self._rx_seq = 0
        self.clock = RobotClock()
        #: Joint states without the wheel joints (another publisher on the topic), skipped.
        self.ignored_joint_states = 0
        self._last_twist_zero = True
        self.rate_hz = 0.0
        self.peer_reliability: list[str] = []
        self.node = Ros2Node(domain)
        self.port = f"ROS 2 domain {self.node.domain}"
        try:
            self._cmd = self.node.writer(cmd_topic, cmd_msg)
            self._joint_reader = self.node.reader(joint_topic, m.JointState)
            self._odom_reader = (self.node.reader(self.odom_topic, m.Odometry)
                                 if self.odom_topic else None)
            self._waitset = self._make_waitset()
            self._discover(float(discovery_timeout_s))
        except BaseException:
            self.node.close()
            raise

    @classmethod
    def from_options(cls, **options: Any) -> Ros2Transport:
        """Build it from command-line options (``robot``, ``cmd_topic``, ...)."""
        for unused in ("port", "interface", "channel", "bitrate"):
            if options.pop(unused, None) is not None:
                raise ConfigError(f"--{unused} is not an option of the ros2 transport "
                                  "(it finds the robot by its topics, in ROS_DOMAIN_ID)")
        return cls(**options)

    # -- discovery ---------------------------------------------------------------------------
    def _make_waitset(self):
        from cyclonedds.core import ReadCondition, SampleState, WaitSet

        ws = WaitSet(self.node.participant)
        for reader in (self._joint_reader, self._odom_reader):
            if reader is not None:
                ws.attach(ReadCondition(reader, SampleState.Any))
        return ws

    def _discover(self, timeout_s: float) -> None:
        until = time.monotonic() + timeout_s
        where = f"{self.joint_topic} in ROS 2 domain {self.node.domain}"
        if not self.node.wait_matched(self._joint_reader, until):
            raise LinkError(f"no publisher on {where} within {timeout_s:g} s (is the robot "
                            "running, in this ROS_DOMAIN_ID, on this network?)")
        samples: list = []
        names: set[str] = set()
        while len(self._wheel_samples(samples)) < RATE_SAMPLES:
            if time.monotonic() >= until:
                break
            for js, recv_ns in self._take(self._joint_reader, 0.05):
                samples.append((js, recv_ns))
                names.update(js.name)
            if self._odom_reader is not None:
                self._odom_reader.take(256)  # not yet wanted; a waiting sample wakes the wait
        if not samples:
            raise LinkError(f"a publisher on {where}, but no joint state within "
                            f"{timeout_s:g} s")
        self._detect_joints(samples, sorted(names))
        wheel = self._wheel_samples(samples)
        times = [self.clock.time_of(js, recv) for js, recv in wheel]
        span_s = (times[-1] - times[0]) * 1e-9
        self.rate_hz = (len(times) - 1) / span_s if len(times) > 1 and span_s > 0 else 0.0
        if not self.rate_hz > 0:
            raise LinkError(f"{where}: the wheels' joint states do not advance in time "
                            f"({len(times)} within {timeout_s:g} s)")
        if not self.node.wait_matched(self._cmd, until):
            raise LinkError(f"no subscriber on {self.cmd_topic} in ROS 2 domain "
                            f"{self.node.domain} within {timeout_s:g} s (does the robot take "
                            f"{'TwistStamped' if self.cmd_type == 'twist-stamped' else 'Twist'}"
                            " commands on this topic? see --cmd-topic, --cmd-type)")
        self.peer_reliability = self.node.peer_qos(self._joint_reader)

    def _wheel_samples(self, samples: list) -> list:
        """The ``(sample, receive time)`` pairs that carry every wheel joint."""
        if self.joints is None:
            return [(js, t) for js, t in samples if wheel_joints_of(js.name) is not None]
        return [(js, t) for js, t in samples if set(self.joints) <= set(js.name)]

    def _detect_joints(self, samples: list, names: list[str]) -> None:
        found = ", ".join(names) or "none"
        if self.joints is None:
            for js, _ in samples:
                self.joints = wheel_joints_of(js.name)
                if self.joints is not None:
                    break
            else:
                split = wheel_joints_of(names) is not None
                raise ConfigError(
                    f"{self.joint_topic}: the wheel joints come in separate messages, which "
                    f"this transport does not merge; joints found: {found}" if split else
                    f"cannot tell the wheels apart in {self.joint_topic}; joints found: "
                    f"{found} (give --joints FL,FR,RL,RR)")
        missing = [j for j in self.joints if j not in names]
        if missing:
            raise ConfigError(f"{self.joint_topic} has no joint {', '.join(missing)}; joints "
                              f"found: {found}")
        whole = [js for js, _ in self._wheel_samples(samples)]
        if not whole:
            raise ConfigError(f"{self.joint_topic}: no message carries all four wheel joints "
                              f"({', '.join(self.joints)}) together")
        wheels = joint_wheel_rpm(whole[-1].name, whole[-1].velocity, self.joints, self.signs)
        if not np.isfinite(wheels).all():
            bad = [j for j, w in zip(self.joints, wheels, strict=True) if not np.isfinite(w)]
            raise ConfigError(f"{self.joint_topic} carries no finite velocity for "
                              f"{', '.join(bad)}: its wheel speeds cannot be recorded")

    # -- receiving ---------------------------------------------------------------------------
    def set_role(self, role: str) -> None:
        """As the base, and the host also receives the robot's odometry."""
        super().set_role(role)
        if role == "host":
            self.receives = (*self.receives, PoseReading)

    def _take(self, reader, timeout_s: float) -> list[tuple[Any, int]]:
        """Samples of ``reader`` with their receive times [ns, wall clock]; waits at most
        ``timeout_s`` for the first."""
        from cyclonedds.util import duration

        samples = reader.take(64)
        if not samples and timeout_s > 0:
            self._waitset.wait(duration(seconds=timeout_s))
            samples = reader.take(64)
        now_ns = time.time_ns()
        return [(s, now_ns) for s in samples if valid_sample(s)]

    def _fill(self, timeout_s: float) -> None:
        for js, recv_ns in self._take(self._joint_reader, timeout_s):
            if not set(self.joints) <= set(js.name):
                self.ignored_joint_states += 1  # another publisher's joints (an arm, casters)
                continue
            t_ns = self.clock.time_of(js, recv_ns)
            wheels = joint_wheel_rpm(js.name, js.velocity, self.joints, self.signs)
            self._rx_seq = (self._rx_seq + 1) % self.seq_modulus
            self._queue.append(Telemetry(self.clock.controller_us(t_ns),
                                         tuple(float(w) for w in wheels), 0, 0, self._rx_seq))
        if self._odom_reader is not None:
            for od, _recv_ns in self._take(self._odom_reader, 0.0):
                p, q = od.pose.pose.position, od.pose.pose.orientation
                self._rx_seq = (self._rx_seq + 1) % self.seq_modulus
                self._queue.append(PoseReading(float(p.x), float(p.y),
                                               float(quaternion_yaw_deg(q.x, q.y, q.z, q.w)),
                                               self._rx_seq))

    def _recv(self, timeout_s: float) -> Message | None:
        if self._hello_ack is not None:
            msg, self._hello_ack = self._hello_ack, None
            return msg
        if not self._queue:
            try:
                self._fill(timeout_s)
            except Exception as err:  # the DDS library failing under us
                raise LinkLostError(f"{self.port}: {self.joint_topic}: link lost: "
                                    f"{err}") from err
        return self._queue.popleft() if self._queue else None

    # -- sending -----------------------------------------------------------------------------
    def _twist(self, vx: float, vy: float, wz: float):
        m = self._m
        twist = m.Twist(m.Vector3(vx, vy, 0.0), m.Vector3(0.0, 0.0, wz))
        if self.cmd_type == "twist":
            return twist
        # the robot's clock: ros2_control ages a TwistStamped by its own clock, and a host
        # clock seconds away would keep an old command in force or refuse every new one
        sec, nanosec = ns_to_stamp(self.clock.robot_now_ns(time.time_ns()))
        return m.TwistStamped(m.Header(m.Time(sec, nanosec), COMMAND_FRAME), twist)

    def _publish(self, vx: float, vy: float, wz: float) -> None:
        try:
            self._cmd.write(self._twist(vx, vy, wz))
        except Exception as err:
            raise LinkError(f"{self.port}: cannot publish on {self.cmd_topic}: {err}") from err
        self._last_twist_zero = vx == 0.0 and vy == 0.0 and wz == 0.0

    def publish_zero(self) -> None:
        """Publish a zero twist :data:`STOP_REPEATS` times within :data:`STOP_SPAN_S`, then
        wait (briefly) until the robot has acknowledged them (reliable QoS)."""
        from cyclonedds.util import duration

        for i in range(STOP_REPEATS):
            if i:
                time.sleep(0.6 * STOP_SPAN_S / (STOP_REPEATS - 1))
            self._publish(0.0, 0.0, 0.0)
        try:
            self._cmd.wait_for_acks(duration(seconds=STOP_SPAN_S))
        except Exception:  # no matched reader any more: nothing left to wait for
            pass

    def _send(self, msg: Message) -> None:
        if isinstance(msg, Command):
            vx, vy, wz = command_to_twist_si(msg.n_rpm, msg.omega_dps, msg.theta_deg,
                                             self.robot.wheel_radius_m)
            self._publish(vx, vy, wz)
        elif isinstance(msg, Stop):
            self.publish_zero()
        elif isinstance(msg, Hello):
            rate = max(1, round(self.rate_hz))
            # a session starts from now: what waited in the readers is not its data, and its
            # controller clock starts at its first joint state (the offset is kept)
            self._queue.clear()
            self.clock.origin_ns = self.clock.last_ns = None
            for reader in (self._joint_reader, self._odom_reader):
                while reader is not None and reader.take(256):
                    pass
            self._rx_seq = 0
            self._hello_ack = HelloAck(PROTOCOL_VERSION, rate, REFERENCE_TIMEOUT_MS,
                                       f"ROS 2 robot on {self.cmd_topic}", 0,
                                       float(self.robot.wheel_speed_max_rpm))
        # PING, HEARTBEAT and ESTOP_RESET have no ROS 2 counterpart: nothing is published

    def min_link_timeout_s(self, telemetry_rate_hz: float) -> float:
        """Five joint-state periods [s]."""
        return LOST_AFTER_PERIODS / telemetry_rate_hz

    def link_metadata(self) -> dict[str, Any]:
        """Domain, topics, joints, signs, QoS and the clock used (the sidecar's ``ros2``)."""
        return {"ros2": {
            "domain": self.node.domain if self.node.participant is not None else None,
            "cmd_topic": self.cmd_topic, "cmd_type": self.cmd_type,
            "joint_topic": self.joint_topic, "odom_topic": self.odom_topic,
            "joints": list(self.joints or ()), "joints_detected": not self.joints_given,
            "wheel_signs": [int(s) for s in self.signs],
            "joint_state_rate_hz": round(self.rate_hz, 3),
            "qos": {"commands": "reliable, volatile, keep last 10",
                    "readers": "best effort, volatile, keep last 100",
                    "joint_state_publishers": self.peer_reliability},
            "clock": self.clock.source,
            "clock_offset_s": (None if self.clock.offset_ns is None
                               else round(self.clock.offset_ns * 1e-9, 6)),
            "ignored_joint_states": self.ignored_joint_states,
            "rows": "tlm: a joint state, timed by controller_time_s (the robot's clock since "
                    "its first joint state); odom: an odometry pose at its receive time",
        }}

    def _close(self) -> None:
        try:
            if not self._last_twist_zero:
                self.publish_zero()
        except Exception as err:  # said, never raised: the link is being closed anyway
            warnings.warn(f"{self.port}: the zero twist on closing could not be published "
                          f"({err}): the robot's own reference timeout must stop it",
                          MecanumHILWarning, stacklevel=2)
        finally:
            self.node.close()
            self._waitset = None

    def wire_command(self, n_rpm: float, omega_dps: float, theta_deg: float) -> Command:
        """Commands travel as float64 twists: as given."""
        if not all(math.isfinite(v) for v in (n_rpm, omega_dps, theta_deg)):
            raise LinkError(f"{self.port}: a command that is not finite cannot be published")
        return Command(float(n_rpm), float(omega_dps), float(theta_deg))
