"""The DDS participant of a ROS 2 node: the domain, topic names and QoS profiles.

ROS 2 names a topic ``/name`` on DDS as ``rt/name`` and takes its domain from
``ROS_DOMAIN_ID`` (default 0). Readers here are best effort, which matches both reliable and
best-effort publishers (robots often publish joint states and odometry with the sensor-data
QoS, which a reliable reader never matches); writers use ROS 2's default profile (reliable,
volatile, keep last 10).
"""

from __future__ import annotations

import os
import re
import time
from typing import Any

from ...errors import ConfigError, LinkError

#: Highest DDS domain id ROS 2 accepts.
MAX_DOMAIN_ID = 232

_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


def _dds():
    """Cyclone DDS's modules, or a one-line error naming the extra."""
    try:
        import cyclonedds.core
        import cyclonedds.domain
        import cyclonedds.pub
        import cyclonedds.qos
        import cyclonedds.sub
        import cyclonedds.topic
        import cyclonedds.util
    except ImportError as err:
        raise ConfigError("the ros2 transport needs the ros2 extra (Cyclone DDS): "
                          "pip install 'mecanum-hil[ros2]'") from err
    import cyclonedds

    return cyclonedds


def ros2_messages():
    """The message types (:mod:`.messages`), or a one-line error naming the extra."""
    _dds()
    from . import messages

    return messages


#: Command types by ``--cmd-type``.
CMD_TYPES = ("twist", "twist-stamped")


def command_type(messages, cmd_type: str) -> type:
    """The message type of ``--cmd-type`` (Twist or TwistStamped).

    Raises
    ------
    ConfigError
        Another name.
    """
    if cmd_type not in CMD_TYPES:
        raise ConfigError(f"--cmd-type must be one of {', '.join(CMD_TYPES)}, got {cmd_type!r}")
    return messages.TwistStamped if cmd_type == "twist-stamped" else messages.Twist


def domain_id(environ: dict[str, str] | None = None) -> int:
    """The ROS 2 domain: ``ROS_DOMAIN_ID`` (default 0), as ROS reads it.

    Raises
    ------
    ConfigError
        A value that is not a whole number from 0 to 232.
    """
    env = os.environ if environ is None else environ
    text = env.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit() or int(text) > MAX_DOMAIN_ID:
        raise ConfigError(f"ROS_DOMAIN_ID must be a whole number from 0 to {MAX_DOMAIN_ID}, "
                          f"got {text!r}")
    return int(text)


def dds_topic_name(ros_name: str) -> str:
    """The DDS topic of a ROS 2 topic: ``/cmd_vel`` -> ``rt/cmd_vel``.

    Raises
    ------
    ConfigError
        A name ROS 2 does not accept (tokens of letters, digits and underscores, not starting
        with a digit, separated by ``/``).
    """
    if not _NAME.match(ros_name or ""):
        raise ConfigError(f"{ros_name!r} is not a ROS 2 topic name (e.g. /cmd_vel)")
    return "rt/" + ros_name.lstrip("/")


def reliability_name(qos) -> str:
    """``reliable`` or ``best_effort``: the reliability of an endpoint's QoS."""
    from cyclonedds.qos import Policy

    for policy in qos:
        if isinstance(policy, Policy.Reliability.Reliable):
            return "reliable"
        if policy is Policy.Reliability.BestEffort or isinstance(
                policy, type(Policy.Reliability.BestEffort)):
            return "best_effort"
    return "reliable"


def valid_sample(sample) -> bool:
    """Whether a taken sample carries data (a writer that goes away leaves an invalid one,
    which says only that)."""
    info = getattr(sample, "sample_info", None)
    return sample is not None and (info is None or bool(info.valid_data)) and \
        type(sample).__name__ != "InvalidSample"


class Ros2Node:
    """A DDS participant with ROS 2's naming; readers and writers by ROS topic name.

    Parameters
    ----------
    domain : int, optional
        DDS domain id (default :func:`domain_id`).
    """

    def __init__(self, domain: int | None = None) -> None:
        dds = _dds()
        self.domain = domain_id() if domain is None else int(domain)
        if not 0 <= self.domain <= MAX_DOMAIN_ID:
            raise ConfigError(f"ROS 2 domain must be 0..{MAX_DOMAIN_ID}, got {self.domain}")
        try:
            self.participant = dds.domain.DomainParticipant(self.domain)
        except dds.core.DDSException as err:
            raise LinkError(f"ROS 2 domain {self.domain}: cannot join it: {err}") from err
        self._entities: list[Any] = []
        self._topics: dict[str, Any] = {}

    # -- QoS profiles ------------------------------------------------------------------------
    @staticmethod
    def default_qos(depth: int = 10, *, reliable: bool = True):
        """ROS 2's default profile (reliable, volatile, keep last ``depth``), or the
        sensor-data profile (best effort) with ``reliable=False``."""
        from cyclonedds.qos import Policy, Qos
        from cyclonedds.util import duration

        return Qos(Policy.Reliability.Reliable(duration(milliseconds=100)) if reliable
                   else Policy.Reliability.BestEffort,
                   Policy.Durability.Volatile, Policy.History.KeepLast(depth))

    def _topic(self, ros_name: str, msg_type: type):
        from cyclonedds.core import DDSException
        from cyclonedds.topic import Topic

        dds_name = dds_topic_name(ros_name)
        known = self._topics.get(dds_name)
        if known is not None:
            if known[1] is not msg_type:
                raise ConfigError(f"{ros_name} is given for two message types "
                                  f"({known[1].__name__}, {msg_type.__name__})")
            return known[0]
        try:
            topic = Topic(self.participant, dds_name, msg_type)
        except DDSException as err:
            raise LinkError(f"ROS 2 domain {self.domain}: cannot create {ros_name}: "
                            f"{err}") from err
        self._topics[dds_name] = (topic, msg_type)
        return topic

    def reader(self, ros_name: str, msg_type: type, depth: int = 100):
        """A best-effort reader of ``ros_name`` (matches reliable and best-effort writers)."""
        from cyclonedds.sub import DataReader

        reader = DataReader(self.participant, self._topic(ros_name, msg_type),
                            qos=self.default_qos(depth, reliable=False))
        self._entities.append(reader)
        return reader

    def writer(self, ros_name: str, msg_type: type, depth: int = 10, *, reliable: bool = True):
        """A writer of ``ros_name`` with ROS 2's default QoS (or best effort)."""
        from cyclonedds.pub import DataWriter

        writer = DataWriter(self.participant, self._topic(ros_name, msg_type),
                            qos=self.default_qos(depth, reliable=reliable))
        self._entities.append(writer)
        return writer

    def wait_matched(self, endpoint, until: float, poll_s: float = 0.01) -> bool:
        """Wait until ``endpoint`` (reader or writer) has a matched peer, at most until the
        monotonic time ``until`` [s]; whether it has one."""
        matched = (endpoint.get_matched_publications if hasattr(endpoint, "take")
                   else endpoint.get_matched_subscriptions)
        while True:
            if matched():
                return True
            if time.monotonic() >= until:
                return False
            time.sleep(poll_s)

    def peer_qos(self, reader) -> list[str]:
        """Reliability of every publisher matched with ``reader`` (``reliable`` ...)."""
        out = []
        for handle in reader.get_matched_publications():
            try:
                data = reader.get_matched_publication_data(handle)
            except Exception:  # a publisher gone meanwhile
                continue
            if data is not None:
                out.append(reliability_name(data.qos))
        return out

    def close(self) -> None:
        """Delete the readers, writers and the participant (idempotent)."""
        for entity in reversed(self._entities):
            entity.__del__()
        self._entities.clear()
        for topic, _ in self._topics.values():
            topic.__del__()
        self._topics.clear()
        participant, self.participant = self.participant, None
        if participant is not None:
            participant.__del__()
