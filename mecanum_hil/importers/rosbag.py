"""ROS bags in: rosbag2 (sqlite3 or MCAP storage) and ROS 1 bags, read with ``rosbags``.

Commands come from ``geometry_msgs/Twist`` or ``TwistStamped`` and are turned into
``(n, omega, theta)`` by the exact inverse of the three-command mapping
(:func:`twist_to_commands`); wheel speeds from ``sensor_msgs/JointState`` velocities [rad/s],
mapped to wheels 1 FL, 2 FR, 3 RL, 4 RR by name (:func:`wheel_joints`); pose, optionally, from
``nav_msgs/Odometry``. Streams are aligned as :mod:`._streams` says (docs/ros2.md).

``rosbags`` (pure Python, the ``ros`` extra) is imported inside :func:`read` only.
"""

from __future__ import annotations

import math
import re
import sqlite3
import struct
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import ConfigError, MecanumHILError, RecordingError
from ..units import RPM_TO_RAD_S, mps_to_rpm
from ._streams import Stream, check_time_order, merge_streams

NAME = "rosbag"

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"

TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
JOINT_STATE = "sensor_msgs/msg/JointState"
ODOMETRY = "nav_msgs/msg/Odometry"

#: Below this translation speed [rpm] the direction is undefined (theta keeps its last value).
V_ZERO_RPM = 1e-9

#: theta before any translation was commanded [deg]: straight ahead.
THETA_START_DEG = 90.0

WHEEL_NAMES = ("front-left", "front-right", "rear-left", "rear-right")


# -- sniffing ---------------------------------------------------------------------------------

def mcap_profile(head: bytes) -> tuple[str, str] | None:
    """``(profile, library)`` of an MCAP file's header record, or None if ``head`` is not one."""
    if not head.startswith(MCAP_MAGIC) or len(head) < 21 or head[8] != 0x01:
        return None
    try:
        (n_profile,) = struct.unpack_from("<I", head, 17)
        profile = head[21:21 + n_profile].decode("utf-8")
        (n_lib,) = struct.unpack_from("<I", head, 21 + n_profile)
        start = 25 + n_profile
        library = head[start:start + n_lib].decode("utf-8", "replace")
    except (struct.error, UnicodeDecodeError):
        return None
    return profile, library


def _is_rosbag2_sqlite(path: Path) -> bool:
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            names = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        finally:
            con.close()
    except sqlite3.Error:
        return False
    return {"topics", "messages"} <= names


def sniff(path: Path, head: bytes) -> bool:
    """A rosbag2 folder (``metadata.yaml``), a ``.db3``/MCAP file of one, or a ROS 1 bag."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    if head.startswith(ROS1_MAGIC):
        return True
    if head.startswith(SQLITE_MAGIC):
        # a damaged .db3 is still claimed, so that reading it names the damage
        return path.suffix == ".db3" or _is_rosbag2_sqlite(path)
    prof = mcap_profile(head)
    return prof is not None and prof[0] in ("ros2", "ros1")


# -- pure conversions -------------------------------------------------------------------------

def twist_to_commands(vx_mps, vy_mps, wz_rad_s, wheel_radius_m: float,
                      theta_start_deg: float = THETA_START_DEG) -> np.ndarray:
    """Body twists to the three commands: the exact inverse of the command mapping.

    The forward mapping (docs/conventions.md) is ``v = n f(theta)``,
    ``f = 1 / (|sin theta| + |cos theta|)``, ``vx = v sin theta``, ``vy = -v cos theta`` (wheel
    rpm units), ``wz = omega / 6``. Its inverse, for ``n >= 0``::

        n     = |vx| + |vy|                 (since v (|sin| + |cos|) = n)
        theta = atan2(vx, -vy)  in [0, 360)
        omega = wz [deg/s]

    A twist without translation (``v = 0``, below ``V_ZERO_RPM``) has no direction: theta keeps
    its last value (``theta_start_deg`` before the first translation), which the forward
    mapping maps back to the same twist whatever theta is.

    Parameters
    ----------
    vx_mps, vy_mps : array_like, shape (T,)
        Linear velocity, x forward and y left (REP-103) [m/s].
    wz_rad_s : array_like, shape (T,)
        Turning speed, counter-clockwise positive [rad/s].
    wheel_radius_m : float
        Wheel radius [m] (metres per second to wheel-rpm units).
    theta_start_deg : float
        Direction assumed before the first translation [deg].

    Returns
    -------
    ndarray, shape (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])``.
    """
    vx = mps_to_rpm(np.asarray(vx_mps, dtype=float).reshape(-1), wheel_radius_m)
    vy = mps_to_rpm(np.asarray(vy_mps, dtype=float).reshape(-1), wheel_radius_m)
    n = np.abs(vx) + np.abs(vy)
    theta = np.mod(np.degrees(np.arctan2(vx, -vy)), 360.0)
    moving = n > V_ZERO_RPM
    last = np.where(moving, np.arange(n.size), -1)
    np.maximum.accumulate(last, out=last)
    held = np.where(last >= 0, theta[np.maximum(last, 0)], theta_start_deg)
    omega = np.degrees(np.asarray(wz_rad_s, dtype=float).reshape(-1))
    return np.column_stack([n, omega, held])


_ABBREVIATIONS = {"fl": 0, "lf": 0, "fr": 1, "rf": 1, "rl": 2, "lr": 2, "bl": 2, "lb": 2,
                  "rr": 3, "br": 3, "rb": 3}


def wheel_corner(name: str) -> int | None:
    """Which wheel (0 FL, 1 FR, 2 RL, 3 RR) a joint name names, or None.

    Understands words (``front_left_wheel_joint``, ``wheel_rear_right``, ``FrontLeftWheel``,
    ``back_left``) and the two-letter corners (``fl_wheel``, ``wheel_rr``, ``lf``).
    """
    low = re.sub(r"([a-z])([A-Z])", r"\1_\2", name).lower()
    tokens = [t for t in re.split(r"[^a-z0-9]+", low) if t]
    words = set(tokens)
    front = bool(words & {"front", "fore"})
    rear = bool(words & {"rear", "back", "hind"})
    left, right = "left" in words, "right" in words
    if front != rear and left != right:
        return (0 if front else 2) + (0 if left else 1)
    joined = "".join(tokens)
    hits = {i for i, pat in enumerate((r"(front|fore)left|left(front|fore)",
                                        r"(front|fore)right|right(front|fore)",
                                        r"(rear|back|hind)left|left(rear|back|hind)",
                                        r"(rear|back|hind)right|right(rear|back|hind)"))
            if re.search(pat, joined)}
    if len(hits) == 1:
        return hits.pop()
    hits = {_ABBREVIATIONS[t] for t in tokens if t in _ABBREVIATIONS}
    return hits.pop() if len(hits) == 1 else None


def wheel_joints(names: Sequence[str]) -> tuple[str, str, str, str] | None:
    """The joints of wheels 1 FL, 2 FR, 3 RL, 4 RR among ``names``, detected by name.

    A corner with several candidates keeps those whose name says ``wheel``; None unless every
    corner ends with exactly one.
    """
    found: list[list[str]] = [[], [], [], []]
    for name in names:
        corner = wheel_corner(name)
        if corner is not None:
            found[corner].append(name)
    chosen = []
    for cands in found:
        if len(cands) > 1:
            cands = [c for c in cands if "wheel" in c.lower()]
        if len(cands) != 1:
            return None
        chosen.append(cands[0])
    return tuple(chosen)  # type: ignore[return-value]


def parse_joints(spec: str | Sequence[str]) -> tuple[str, str, str, str]:
    """``"FL,FR,RL,RR"`` (joint names in wheel order 1..4) to a tuple of four names."""
    names = [s.strip() for s in (spec.split(",") if isinstance(spec, str) else spec)]
    if len(names) != 4 or not all(names) or len(set(names)) != 4:
        raise RecordingError(f"--joints needs four different joint names in the wheel order "
                             f"1 FL, 2 FR, 3 RL, 4 RR, separated by commas; got {spec!r}")
    return tuple(names)  # type: ignore[return-value]


def parse_wheel_signs(spec: str | Sequence[float]) -> np.ndarray:
    """``"1,-1,1,-1"`` (or ``"+,-,+,-"``) to four signs, one per wheel 1..4."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    out = []
    for item in items:
        s = str(item).strip()
        value = {"+": 1.0, "-": -1.0}.get(s)
        if value is None:
            try:
                value = float(s)
            except ValueError:
                value = math.nan
        out.append(value)
    if len(out) != 4 or any(v not in (1.0, -1.0) for v in out):
        raise RecordingError(f"--wheel-signs needs four signs (+1 or -1, wheel order 1 FL, 2 FR, "
                             f"3 RL, 4 RR), separated by commas; got {spec!r}")
    return np.array(out)


def quaternion_yaw_deg(x, y, z, w) -> np.ndarray:
    """Heading [deg] (rotation about z) of orientation quaternions."""
    x, y, z, w = (np.asarray(a, dtype=float) for a in (x, y, z, w))
    return np.degrees(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


# -- reading a bag ----------------------------------------------------------------------------

def _stamp_ns(header, receive_ns: int) -> tuple[int, bool]:
    """The header stamp [ns], or the receive time when the stamp is unset (zero)."""
    ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return (ns, True) if ns > 0 else (receive_ns, False)


# -- message decoding -------------------------------------------------------------------------
#
# A layout says where a little-endian CDR message's numbers lie: ``(meta, key, stamped,
# offsets)`` with ``key`` the byte ranges that fix the layout (strings, sequence lengths) and
# ``offsets`` those of the float64 values wanted. Messages of one length whose key bytes equal
# the first one's share its layout and are read all at once. A converter does the same from a
# deserialized message: ``(meta, time_ns, stamped, values)``, or None for a message without
# the values.

def _align(off: int, size: int) -> int:
    # CDR aligns to the field's size, counted from the end of the 4-byte encapsulation header
    return 4 + -(-(off - 4) // size) * size


def _little_endian_cdr(raw: bytes) -> bool:
    return len(raw) >= 12 and raw[0] == 0 and raw[1] == 1


def _after_header(raw: bytes) -> int:
    """Offset just after a ``std_msgs/Header`` (stamp, frame_id) at the message's start."""
    (flen,) = struct.unpack_from("<I", raw, 12)
    return 16 + flen


def joint_state_layout(raw: bytes):
    """Layout of a ``sensor_msgs/JointState``: meta is the joint names, values the velocities
    (none when the velocity count differs from the name count)."""
    if not _little_endian_cdr(raw):
        return None
    try:
        off = _align(_after_header(raw), 4)
        (count,) = struct.unpack_from("<I", raw, off)
        off += 4
        names = []
        for _ in range(count):
            off = _align(off, 4)
            (slen,) = struct.unpack_from("<I", raw, off)
            names.append(raw[off + 4:off + 3 + slen].decode("utf-8"))
            off += 4 + slen
        off = _align(off, 4)
        (npos,) = struct.unpack_from("<I", raw, off)
        pos_data = _align(off + 4, 8) if npos else off + 4
        vcount_off = _align(pos_data + 8 * npos, 4)
        (nvel,) = struct.unpack_from("<I", raw, vcount_off)
        vel_off = _align(vcount_off + 4, 8) if nvel else vcount_off + 4
    except (struct.error, UnicodeDecodeError):
        return None
    if vel_off + 8 * nvel > len(raw):
        return None
    key = ((0, 4), (12, pos_data), (vcount_off, vcount_off + 4))
    offsets = tuple(vel_off + 8 * i for i in range(nvel)) if nvel == len(names) else ()
    return tuple(names), key, True, offsets


def _joint_state_values(msg, recv_ns: int):
    vel = np.asarray(msg.velocity, dtype=float)
    if len(vel) != len(msg.name) or not len(vel):
        return None
    t, stamped = _stamp_ns(msg.header, recv_ns)
    return tuple(msg.name), t, stamped, vel


def twist_stamped_layout(raw: bytes):
    """Layout of a ``geometry_msgs/TwistStamped``: linear x, y and angular z."""
    if not _little_endian_cdr(raw):
        return None
    try:
        lin = _align(_after_header(raw), 8)
    except struct.error:
        return None
    if lin + 48 > len(raw):
        return None
    return None, ((0, 4), (12, lin)), True, (lin, lin + 8, lin + 40)


def _twist_stamped_values(msg, recv_ns: int):
    t, stamped = _stamp_ns(msg.header, recv_ns)
    tw = msg.twist
    return None, t, stamped, (tw.linear.x, tw.linear.y, tw.angular.z)


def twist_layout(raw: bytes):
    """Layout of a ``geometry_msgs/Twist`` (no header: timed by receive time)."""
    if len(raw) < 52 or raw[0] != 0 or raw[1] != 1:
        return None
    return None, ((0, 4),), False, (4, 12, 44)


def _twist_values(msg, recv_ns: int):
    return None, recv_ns, False, (msg.linear.x, msg.linear.y, msg.angular.z)


def odometry_layout(raw: bytes):
    """Layout of a ``nav_msgs/Odometry``: position x, y and the orientation quaternion."""
    if not _little_endian_cdr(raw):
        return None
    try:
        child = _align(_after_header(raw), 4)
        (clen,) = struct.unpack_from("<I", raw, child)
        pos = _align(child + 4 + clen, 8)
    except struct.error:
        return None
    if pos + 56 > len(raw):
        return None
    return None, ((0, 4), (12, pos)), True, (pos, pos + 8, pos + 24, pos + 32, pos + 40,
                                             pos + 48)


def _odometry_values(msg, recv_ns: int):
    t, stamped = _stamp_ns(msg.header, recv_ns)
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return None, t, stamped, (p.x, p.y, q.x, q.y, q.z, q.w)


class _Samples:
    """One topic's samples, as blocks ``(meta, t_ns, recv_ns, stamped, values)``.

    ROS 2 messages are kept as bytes and decoded by :meth:`finish` in blocks of one layout (a
    1-hour bag at 100 Hz is 360,000 messages: one by one, deserializing would dominate the
    import); a message off the block (another layout, big-endian) and ROS 1 messages go
    through the deserializer and the converter.
    """

    def __init__(self, name: str, layout, convert) -> None:
        self.name = name
        self._layout = layout
        self._convert = convert
        self.blocks: list[tuple] = []
        self.skipped = 0
        self._raw: list[bytes] = []
        self._raw_recv: list[int] = []
        self._slow: list[tuple] = []

    def add_cdr(self, raw, recv_ns: int) -> None:
        self._raw.append(bytes(raw))
        self._raw_recv.append(recv_ns)

    def add_message(self, msg, recv_ns: int) -> None:
        item = self._convert(msg, recv_ns)
        if item is None:
            self.skipped += 1
        else:
            self._slow.append((*item, recv_ns))

    def finish(self, deserialize) -> None:
        """Decode what was collected; ``deserialize(raw)`` for the messages off the blocks."""
        raws, recv = self._raw, np.asarray(self._raw_recv, dtype=np.int64)
        lengths = np.fromiter((len(r) for r in raws), dtype=np.int64, count=len(raws))
        for length in np.unique(lengths):
            idx = np.flatnonzero(lengths == length)
            layout = self._layout(raws[idx[0]])
            if layout is None:
                for i in idx:
                    self.add_message(deserialize(raws[i]), int(recv[i]))
                continue
            meta, key, has_stamp, offsets = layout
            buf = np.frombuffer(b"".join(raws[i] for i in idx), dtype=np.uint8).reshape(
                idx.size, int(length))
            same = np.ones(idx.size, dtype=bool)
            for a, b in key:
                same &= (buf[:, a:b] == buf[0, a:b]).all(axis=1)
            for i in idx[~same]:
                self.add_message(deserialize(raws[i]), int(recv[i]))
            if not offsets:
                self.skipped += int(same.sum())
                continue
            rows = buf[same]
            r = recv[idx[same]]
            values = np.stack([rows[:, o:o + 8].copy().view("<f8").ravel() for o in offsets],
                              axis=1)
            if has_stamp:
                sec = rows[:, 4:8].copy().view("<i4").ravel().astype(np.int64)
                nsec = rows[:, 8:12].copy().view("<u4").ravel().astype(np.int64)
                stamp = sec * 1_000_000_000 + nsec
                stamped = stamp > 0
                t = np.where(stamped, stamp, r)
            else:
                stamped, t = np.zeros(r.size, dtype=bool), r
            self.blocks.append((meta, t, r, stamped, values))
        self._raw, self._raw_recv = [], []
        by_meta: dict = {}
        for item in self._slow:
            by_meta.setdefault(item[0], []).append(item)
        for meta, items in by_meta.items():
            self.blocks.append((meta, np.array([i[1] for i in items], dtype=np.int64),
                                np.array([i[4] for i in items], dtype=np.int64),
                                np.array([i[2] for i in items], dtype=bool),
                                np.array([np.asarray(i[3], dtype=float) for i in items])))
        self._slow = []

    def __len__(self) -> int:
        return sum(b[1].size for b in self.blocks)

    def column(self, k: int) -> np.ndarray:
        """Field ``k`` of the blocks concatenated: 1 times, 2 receive times, 3 stamped."""
        if not self.blocks:
            return np.zeros(0, dtype=bool if k == 3 else np.int64)
        return np.concatenate([b[k] for b in self.blocks])

    def values(self) -> np.ndarray:
        """The values of blocks of one width, concatenated in block order."""
        return np.concatenate([b[4] for b in self.blocks])

    def offset_s(self, t_ns: np.ndarray) -> float:
        """Median receive time minus ``t_ns`` [s]."""
        if not t_ns.size:
            return 0.0
        return float(np.median(self.column(2) - t_ns)) * 1e-9


def _open_reader(path: Path):
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as err:
        raise ConfigError("reading ROS bags needs the 'ros' extra: pip install "
                          "'mecanum-hil[ros]'") from err

    head = b""
    if path.is_file():
        with path.open("rb") as fh:
            head = fh.read(len(ROS1_MAGIC))
    if head == ROS1_MAGIC and path.suffix != ".bag":
        raise RecordingError(f"{path}: a ROS 1 bag must be named *.bag to be read")
    if path.is_file() and head != ROS1_MAGIC and path.suffix not in (".db3", ".mcap"):
        raise RecordingError(f"{path}: not a readable ROS 1 bag (it does not start with "
                             f"{ROS1_MAGIC.decode().strip()!r}), and a rosbag2 storage file must "
                             "be named *.db3 or *.mcap (or give the bag's folder, with its "
                             "metadata.yaml)")
    # bags recorded without message definitions (older rosbag2 sqlite3) use the standard
    # types; the four message types read here are the same in every ROS 2 distribution
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _check_topic(topics: dict[str, str], topic: str, allowed: Sequence[str], option: str,
                 path: Path) -> str:
    if topic not in topics:
        listing = ", ".join(f"{t} [{m}]" for t, m in sorted(topics.items())) or "none"
        raise RecordingError(f"{path}: no topic {topic} in the bag (give {option}); topics: "
                             f"{listing}")
    msgtype = topics[topic]
    if msgtype not in allowed:
        raise RecordingError(f"{path}: topic {topic} carries {msgtype}, expected "
                             f"{' or '.join(allowed)} ({option})")
    return msgtype


def read_bag(path: str | Path, *, cmd_topic: str = "/cmd_vel",
             joint_topic: str = "/joint_states", joints: str | Sequence[str] | None = None,
             wheel_signs: str | Sequence[float] | None = None, odom_topic: str | None = None,
             wheel_radius_m: float) -> tuple:
    """Read a bag into a recording; returns ``(Recording, notes)``. See :func:`read`."""
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file or folder")
    signs = parse_wheel_signs(wheel_signs) if wheel_signs is not None else np.ones(4)
    mapping = parse_joints(joints) if joints is not None else None
    js = _Samples(joint_topic, joint_state_layout, _joint_state_values)
    odo = _Samples(odom_topic or "", odometry_layout, _odometry_values)
    cmd = _read_topics(p, cmd_topic, joint_topic, odom_topic, js, odo)
    notes: list[str] = []
    if not len(cmd):
        raise RecordingError(f"{p}: topic {cmd_topic} has no messages")
    if not len(js):
        raise RecordingError(f"{p}: topic {joint_topic} has no messages with velocities"
                             + (f" ({js.skipped} without)" if js.skipped else ""))
    if js.skipped:
        notes.append(f"{js.skipped} {joint_topic} message(s) without velocities skipped")
    mapping = _wheel_joints(p, js, joint_topic, mapping, notes)
    times = _sample_times((cmd, js, odo), notes)
    for tp in (cmd, js, odo):
        if len(tp):
            _check_order(p, tp, times[tp.name], notes)
    _check_receive_order(p)
    if odom_topic and not len(odo):
        notes.append(f"no odometry on {odom_topic}: no pose")
    tw = cmd.values()
    commands = twist_to_commands(tw[:, 0], tw[:, 1], tw[:, 2], wheel_radius_m)
    bad_cmd = ~np.isfinite(tw).all(axis=1)
    if bad_cmd.all():
        raise RecordingError(f"{p}: every command on {cmd_topic} has a non-finite (NaN or "
                             "infinite) linear or angular velocity")
    if bad_cmd.any():
        notes.append(f"{int(bad_cmd.sum())} of {len(cmd)} commands ({cmd_topic}) not finite: "
                     "their command columns left empty")
    wheels = _wheel_rpm(js, mapping, signs)
    bad_js = ~np.isfinite(wheels).all(axis=1)
    if bad_js.any():
        notes.append(f"{int(bad_js.sum())} of {len(js)} joint-state samples ({joint_topic}) not "
                     "finite: left empty")
    pose_stream = None
    if len(odo):
        pa = odo.values()
        pose_vals = np.column_stack([pa[:, 0], pa[:, 1], quaternion_yaw_deg(*pa[:, 2:6].T)])
        pose_stream = Stream.of(times[odo.name], pose_vals, 3)
    meta = {
        "source": f"mecanum-hil import (rosbag) {p.name}",
        "import": {"format": NAME, "cmd_topic": cmd_topic, "joint_topic": joint_topic,
                   "joints": list(mapping), "wheel_signs": signs.tolist(),
                   "odom_topic": odom_topic, "wheel_radius_m": wheel_radius_m},
    }
    rec, merge_notes = merge_streams(Stream.of(times[cmd.name], commands, 3),
                                     Stream.of(times[js.name], wheels, 4), pose_stream, meta,
                                     str(p))
    notes.extend(merge_notes)
    notes.insert(0, f"{len(cmd)} commands ({cmd_topic}), {len(js)} wheel samples "
                    f"({joint_topic})" + (f", {len(odo)} poses ({odom_topic})" if len(odo)
                                          else ""))
    return rec, tuple(notes)


def _read_topics(p: Path, cmd_topic: str, joint_topic: str, odom_topic: str | None,
                 js: _Samples, odo: _Samples) -> _Samples:
    """Read the three topics' messages into ``js``, ``odo`` and the returned command samples;
    a bag that cannot be read is a :class:`RecordingError`."""
    try:
        reader = _open_reader(p)
        with reader:
            if reader.message_count == 0:
                raise RecordingError(f"{p}: the bag holds no messages")
            topics = {c.topic: c.msgtype for c in reader.connections}
            cmd_type = _check_topic(topics, cmd_topic, (TWIST, TWIST_STAMPED), "--cmd-topic", p)
            _check_topic(topics, joint_topic, (JOINT_STATE,), "--joint-topic", p)
            if odom_topic:
                _check_topic(topics, odom_topic, (ODOMETRY,), "--odom-topic", p)
            cmd = (_Samples(cmd_topic, twist_stamped_layout, _twist_stamped_values)
                   if cmd_type == TWIST_STAMPED else _Samples(cmd_topic, twist_layout,
                                                              _twist_values))
            by_topic = {joint_topic: js, cmd_topic: cmd}
            if odom_topic:
                by_topic[odom_topic] = odo
            conns = [c for c in reader.connections if c.topic in by_topic]
            deserialize = reader.deserialize
            cdr = reader.is2  # ROS 2: bytes kept for the block decoder
            for conn, recv_ns, raw in reader.messages(connections=conns):
                if cdr:
                    by_topic[conn.topic].add_cdr(raw, recv_ns)
                else:
                    by_topic[conn.topic].add_message(deserialize(raw, conn.msgtype), recv_ns)
            for topic, samples in by_topic.items():
                msgtype = topics[topic]
                samples.finish(lambda raw, m=msgtype: deserialize(raw, m))
    except MecanumHILError:
        raise
    except FileNotFoundError as err:
        raise RecordingError(f"{p}: part of the bag is missing: {err}") from err
    except Exception as err:  # rosbags, sqlite, struct ...: a corrupt or truncated bag
        raise RecordingError(f"{p}: cannot read the bag (truncated or corrupt?): "
                             f"{type(err).__name__}: {err}") from err
    return cmd


def _wheel_joints(p: Path, js: _Samples, joint_topic: str, mapping: Sequence[str] | None,
                  notes: list[str]) -> Sequence[str]:
    """The joints of wheels 1-4: as given, or told apart by their names."""
    all_names = list(dict.fromkeys(n for b in js.blocks for n in b[0]))
    if mapping is None:
        mapping = wheel_joints(all_names)
        if mapping is None:
            raise RecordingError(
                f"{p}: cannot tell the wheels apart in {joint_topic}; joints found: "
                f"{', '.join(all_names)} (give --joints FL,FR,RL,RR)")
        notes.append("wheel joints detected: " + ", ".join(
            f"{i + 1} {w} = {j}" for i, (w, j) in enumerate(zip(WHEEL_NAMES, mapping,
                                                                 strict=True))))
    missing = [j for j in mapping if j not in all_names]
    if missing:
        raise RecordingError(f"{p}: joint(s) {', '.join(missing)} not in {joint_topic}; joints "
                             f"found: {', '.join(all_names)}")
    return mapping


def _sample_times(topics: Sequence[_Samples], notes: list[str]) -> dict[str, np.ndarray]:
    """Each topic's sample times [s]: header stamps, or receive times where they disagree."""
    # clocks: header stamps and receive times are assumed to be one clock (a bag recorded on
    # the robot); if the topics disagree by more than a second (simulated time, an unsynced
    # sensor computer), align everything on receive times instead
    used = [tp for tp in topics if len(tp)]
    times = {tp.name: tp.column(1) for tp in used}
    offsets = [tp.offset_s(times[tp.name]) for tp in used]
    if max(offsets) - min(offsets) > 1.0:
        notes.append("header stamps and receive times disagree by "
                     + ", ".join(f"{tp.name} {o:+.3g} s" for tp, o in zip(used, offsets,
                                                                          strict=True))
                     + ": aligned on receive times")
        times = {tp.name: tp.column(2) for tp in used}
    else:
        for tp in used:
            n_stamped = int(tp.column(3).sum())
            if 0 < n_stamped < len(tp):
                notes.append(f"{tp.name}: {len(tp) - n_stamped} message(s) without a "
                             "header stamp timed by receive time")
    return times


#: How far a bag's message may be stamped or received before an earlier one and still be
#: sorted into place [ns]: a ROS graph delivers through executors, queues and the network, so
#: tens of milliseconds out of order is normal (several publishers on one topic, a loaded
#: recorder); a clock stepping back by half a second or more is a reset.
BAG_BACK_TOLERANCE_NS = 500_000_000


def _check_order(p: Path, tp: _Samples, t_ns: np.ndarray, notes: list[str]) -> None:
    """A topic's times in the order it was received: more than
    :data:`BAG_BACK_TOLERANCE_NS` back is an error naming the message; less (jitter between
    stamping and receiving) is sorted."""
    recv = tp.column(2)
    order = np.argsort(recv, kind="stable")  # the bag's order (rosbags reads by receive time)
    note = check_time_order(t_ns[order], lambda i: f"{p}: {tp.name} message {i + 1} (received "
                            f"at {recv[order[i]] * 1e-9:.6f} s)", f"{tp.name} message(s)",
                            BAG_BACK_TOLERANCE_NS)
    if note:
        notes.append(note)


def _check_receive_order(p: Path) -> None:
    """Each topic's receive times in the order the recorder wrote its messages (rosbags reads
    them sorted by time, which interleaves the halves of a bag whose clock was reset): more
    than :data:`BAG_BACK_TOLERANCE_NS` back is an error. Per topic, because a bag written by a
    conversion script one topic after another runs back between topics, not within one (a
    clock reset moves every topic back). rosbag2 sqlite3 (message ids), MCAP (message indexes)
    and ROS 1 bags (index entries: chunk, offset) are checked."""
    files = ([f for f in sorted(p.iterdir()) if f.suffix in (".db3", ".mcap")] if p.is_dir()
             else [p])
    for f in files:
        if f.suffix == ".db3":
            topics = _db3_receive_times(f)
        elif f.suffix == ".mcap":
            topics = _mcap_receive_times(f)
        elif f.suffix == ".bag":
            topics = _bag1_receive_times(f)
        else:
            continue
        for topic, t in (topics or {}).items():
            check_time_order(t, lambda i, f=f, topic=topic: f"{f}: {topic} message {i + 1} in "
                             "the file (receive time)", tolerance_ns=BAG_BACK_TOLERANCE_NS)


def _db3_receive_times(f: Path) -> dict[str, np.ndarray] | None:
    """Receive times per topic, in message-id order."""
    try:
        con = sqlite3.connect(f"file:{f}?mode=ro", uri=True)
        try:
            names = dict(con.execute("SELECT id, name FROM topics").fetchall())
            rows = con.execute("SELECT topic_id, timestamp FROM messages ORDER BY id").fetchall()
        finally:
            con.close()
    except sqlite3.Error:
        return None  # read (and reported) by rosbags
    out: dict[str, list[int]] = {}
    for topic_id, stamp in rows:
        out.setdefault(str(names.get(topic_id, topic_id)), []).append(stamp)
    return {k: np.asarray(v, dtype=np.int64) for k, v in out.items()}


def _bag1_receive_times(f: Path) -> dict[str, np.ndarray] | None:
    """A ROS 1 bag's record times per topic in file order, from its index (chunk position,
    offset within the chunk; no decompression)."""
    try:
        from rosbags.rosbag1 import Reader
    except ImportError:
        return None
    try:
        with Reader(f) as bag:
            topics = {c.id: c.topic for c in bag.connections}
            per = {cid: sorted(entries, key=lambda e: (e.chunk_pos, e.offset))
                   for cid, entries in bag.indexes.items()}
    except Exception:  # a damaged index: rosbags reads (and reports) the messages
        return None
    out: dict[str, np.ndarray] = {}
    for cid, entries in per.items():
        t = np.fromiter((e.time for e in entries), dtype=np.int64, count=len(entries))
        name = topics.get(cid, str(cid))
        out[name] = np.concatenate([out[name], t]) if name in out else t
    return out


def _mcap_receive_times(f: Path) -> dict[str, np.ndarray] | None:
    """Log times per topic in file order, from the chunks' message indexes (no
    decompression)."""
    try:
        from mcap.reader import make_reader
    except ImportError:
        return None
    try:
        with f.open("rb") as fh:
            summary = make_reader(fh).get_summary()
            if summary is None:
                return None
            parts: dict[str, list[np.ndarray]] = {}
            for chunk in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
                for channel, offset in chunk.message_index_offsets.items():
                    fh.seek(offset)
                    head = fh.read(15)  # opcode, record length, channel id, records length
                    if len(head) < 15 or head[0] != 0x07:
                        return None
                    (n,) = struct.unpack_from("<I", head, 11)
                    rec = np.frombuffer(fh.read(n), dtype="<u8").reshape(-1, 2)
                    ch = summary.channels.get(channel)
                    topic = ch.topic if ch is not None else str(channel)
                    parts.setdefault(topic, []).append(
                        rec[np.argsort(rec[:, 1], kind="stable"), 0])
    except Exception:  # a damaged summary: rosbags reads (and reports) the messages
        return None
    return {k: np.concatenate(v).astype(np.int64) for k, v in parts.items()}


def _wheel_rpm(js: _Samples, mapping: Sequence[str], signs: np.ndarray) -> np.ndarray:
    """Wheel speeds 1-4 [rpm] from the joint states' velocities [rad/s]."""
    wheels = np.full((len(js), 4), np.nan)
    start = 0
    for names, t_block, _, _, vel in js.blocks:
        rows = slice(start, start + t_block.size)
        for w, joint in enumerate(mapping):
            if joint in names:
                # + 0.0: a flipped wheel at rest is 0, not -0, in the CSV
                wheels[rows, w] = vel[:, names.index(joint)] / RPM_TO_RAD_S * signs[w] + 0.0
        start += t_block.size
    return wheels


def read(path: Path, *, cmd_topic: str = "/cmd_vel", joint_topic: str = "/joint_states",
         joints: str | Sequence[str] | None = None,
         wheel_signs: str | Sequence[float] | None = None, odom_topic: str | None = None,
         wheel_radius_m: float | None = None):
    """Read a ROS bag into a recording.

    Parameters
    ----------
    path : Path
        A rosbag2 folder (sqlite3 or MCAP storage), one of its ``.db3``/``.mcap`` files, or a
        ROS 1 ``.bag``.
    cmd_topic : str
        ``geometry_msgs/Twist`` or ``TwistStamped`` commands.
    joint_topic : str
        ``sensor_msgs/JointState`` with the wheel velocities [rad/s].
    joints : str or sequence of str, optional
        Joint names of wheels 1 FL, 2 FR, 3 RL, 4 RR (``"a,b,c,d"``); detected by name if not
        given.
    wheel_signs : str or sequence of float, optional
        ``+1``/``-1`` per wheel 1..4, for joints whose positive axis turns the wheel backwards.
    odom_topic : str, optional
        ``nav_msgs/Odometry`` giving the pose.
    wheel_radius_m : float
        Wheel radius [m], to express the twist in wheel-rpm units (the CLI passes its
        ``--robot`` profile's).

    Returns
    -------
    ImportResult
    """
    from . import ImportResult

    if wheel_radius_m is None or not (wheel_radius_m > 0 and math.isfinite(wheel_radius_m)):
        raise RecordingError("reading a bag's Twist commands needs the wheel radius (a robot "
                             f"profile, --robot); got {wheel_radius_m!r}")
    rec, notes = read_bag(path, cmd_topic=cmd_topic, joint_topic=joint_topic, joints=joints,
                          wheel_signs=wheel_signs, odom_topic=odom_topic,
                          wheel_radius_m=wheel_radius_m)
    return ImportResult(rec, notes)
