"""Stand-ins for the ROS 2 tests: DDS on the loopback only, a domain per test, and a spy.

Every participant of a test (the test's own, sim-robot's, record's, shadow's) reads the same
Cyclone DDS configuration: the loopback interface, no multicast, unicast discovery to
127.0.0.1. The domain id is one that no ROS 2 robot on a lab network uses by default and
differs per pytest-xdist worker and per test, so tests never hear each other or a user's
robot.
"""

from __future__ import annotations

import itertools
import os
import threading
import time

#: Cyclone DDS on the loopback only (no traffic leaves this machine).
LOOPBACK_CONFIG = """<CycloneDDS><Domain Id="any">
  <General><Interfaces><NetworkInterface name="lo"/></Interfaces>
    <AllowMulticast>false</AllowMulticast></General>
  <Discovery><ParticipantIndex>auto</ParticipantIndex>
    <MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>
    <Peers><Peer address="127.0.0.1"/></Peers>{tag}</Discovery>
</Domain></CycloneDDS>
"""


def loopback_config(tag: str | None = None) -> str:
    """:data:`LOOPBACK_CONFIG`, with a DDS domain tag when given: participants of other tags
    never match, so two test runs on one machine (same domain ids, same loopback) never hear
    each other. Peers of other vendors may not speak domain tags: give none for them."""
    return LOOPBACK_CONFIG.format(tag=f"<Tag>{tag}</Tag>" if tag else "")

_counter = itertools.count()


def test_domain() -> int:
    """A domain id for one test: 150-229, by xdist worker (20 apart) and a counter."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    return 150 + (index % 4) * 20 + next(_counter) % 20


test_domain.__test__ = False  # a helper, not a test


class Spy:
    """Records every message on a ROS 2 topic (reliable, keep all), on its own thread.

    Attributes
    ----------
    messages : list of (float, message)
        Receive time (monotonic [s]) and the message, in order.
    """

    def __init__(self, domain: int, topic: str, msg_type: type) -> None:
        from cyclonedds.core import ReadCondition, SampleState, WaitSet
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.qos import Policy, Qos
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic
        from cyclonedds.util import duration

        self.participant = DomainParticipant(domain)
        self.topic = Topic(self.participant, "rt/" + topic.lstrip("/"), msg_type)
        self.reader = DataReader(self.participant, self.topic, qos=Qos(
            Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.Volatile,
            Policy.History.KeepAll))
        self.waitset = WaitSet(self.participant)
        self.waitset.attach(ReadCondition(self.reader, SampleState.Any))
        self.messages: list = []
        #: Receive time of each message by the wall clock [s].
        self.wall_s: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from cyclonedds.util import duration

        while not self._stop.is_set():
            self.waitset.wait(duration(milliseconds=50))
            for s in self.reader.take(256):
                if s is not None and type(s).__name__ != "InvalidSample":
                    self.messages.append((time.monotonic(), s))
                    self.wall_s.append(time.time())

    def wait_matched(self, timeout_s: float = 10.0) -> bool:
        """Whether a publisher matched within ``timeout_s``."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.reader.get_matched_publications():
                return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        for entity in (self.reader, self.topic, self.participant):
            entity.__del__()


class StubRobot:
    """A ROS 2 robot reduced to its topics, on its own thread: JointState at ``rate_hz``
    from ``joint_messages()`` (a list of JointStates per period, so tests shape them: no
    stamps, other publishers' joints, no velocities), and a cmd_vel subscriber that keeps
    what it hears."""

    def __init__(self, domain: int, joint_messages, rate_hz: float = 50.0) -> None:
        from mecanum_hil.link.ros2 import messages as m
        from mecanum_hil.link.ros2.node import Ros2Node

        self.node = Ros2Node(domain)
        self.writer = self.node.writer("/joint_states", m.JointState)
        self.cmd = self.node.reader("/cmd_vel", m.Twist)
        self.joint_messages, self.period_s = joint_messages, 1.0 / rate_hz
        self.twists: list = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            for msg in self.joint_messages():
                self.writer.write(msg)
            self.twists += [s for s in self.cmd.take(64)
                            if s is not None and type(s).__name__ != "InvalidSample"]
            next_t += self.period_s
            time.sleep(max(0.0, next_t - time.monotonic()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.node.close()
