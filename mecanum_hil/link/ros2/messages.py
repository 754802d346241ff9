"""ROS 2 message layouts as DDS types (Cyclone DDS's Python IDL), field by field.

ROS 2 maps a message ``pkg/msg/Type`` onto the DDS type ``pkg::msg::dds_::Type_`` with the
fields of its interface definition (common_interfaces, rcl_interfaces), in order, as final
(non-extensible) structs carried in plain CDR. A participant that publishes these types on
the topic ``rt/<name>`` is a ROS 2 node to every other node, whichever DDS vendor they run.

Importing this module needs the ``ros2`` extra (``cyclonedds``).
"""

# no `from __future__ import annotations`: Cyclone's IDL reads the field types themselves
from dataclasses import dataclass, field

try:
    import cyclonedds.idl as idl
    import cyclonedds.idl.annotations as annotate
    import cyclonedds.idl.types as types
except ImportError as err:  # the extra is missing: said in one line by the transport
    raise ImportError("the ros2 transport needs the ros2 extra: "
                      "pip install 'mecanum-hil[ros2]'") from err


def _zero_covariance() -> list[float]:
    return [0.0] * 36


# -- builtin_interfaces, std_msgs ---------------------------------------------------------------

@dataclass
@annotate.final
class Time(idl.IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    """builtin_interfaces/Time: ``int32 sec``, ``uint32 nanosec``."""

    sec: types.int32 = 0
    nanosec: types.uint32 = 0


@dataclass
@annotate.final
class Header(idl.IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    """std_msgs/Header: ``builtin_interfaces/Time stamp``, ``string frame_id``."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


# -- geometry_msgs ------------------------------------------------------------------------------

@dataclass
@annotate.final
class Vector3(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    """geometry_msgs/Vector3: ``float64 x, y, z``."""

    x: types.float64 = 0.0
    y: types.float64 = 0.0
    z: types.float64 = 0.0


@dataclass
@annotate.final
class Twist(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    """geometry_msgs/Twist: ``Vector3 linear`` [m/s], ``Vector3 angular`` [rad/s]."""

    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
@annotate.final
class TwistStamped(idl.IdlStruct, typename="geometry_msgs::msg::dds_::TwistStamped_"):
    """geometry_msgs/TwistStamped: ``std_msgs/Header header``, ``Twist twist``."""

    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


@dataclass
@annotate.final
class Point(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    """geometry_msgs/Point: ``float64 x, y, z`` [m]."""

    x: types.float64 = 0.0
    y: types.float64 = 0.0
    z: types.float64 = 0.0


@dataclass
@annotate.final
class Quaternion(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    """geometry_msgs/Quaternion: ``float64 x, y, z, w`` (default the identity)."""

    x: types.float64 = 0.0
    y: types.float64 = 0.0
    z: types.float64 = 0.0
    w: types.float64 = 1.0


@dataclass
@annotate.final
class Pose(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    """geometry_msgs/Pose: ``Point position``, ``Quaternion orientation``."""

    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
@annotate.final
class PoseWithCovariance(idl.IdlStruct,
                         typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    """geometry_msgs/PoseWithCovariance: ``Pose pose``, ``float64[36] covariance``."""

    pose: Pose = field(default_factory=Pose)
    covariance: types.array[types.float64, 36] = field(default_factory=_zero_covariance)


@dataclass
@annotate.final
class TwistWithCovariance(idl.IdlStruct,
                          typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    """geometry_msgs/TwistWithCovariance: ``Twist twist``, ``float64[36] covariance``."""

    twist: Twist = field(default_factory=Twist)
    covariance: types.array[types.float64, 36] = field(default_factory=_zero_covariance)


# -- sensor_msgs, nav_msgs ----------------------------------------------------------------------

@dataclass
@annotate.final
class JointState(idl.IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    """sensor_msgs/JointState: ``Header header``, ``string[] name``, ``float64[] position``
    [rad], ``float64[] velocity`` [rad/s], ``float64[] effort`` [N m]."""

    header: Header = field(default_factory=Header)
    name: types.sequence[str] = field(default_factory=list)
    position: types.sequence[types.float64] = field(default_factory=list)
    velocity: types.sequence[types.float64] = field(default_factory=list)
    effort: types.sequence[types.float64] = field(default_factory=list)


@dataclass
@annotate.final
class Odometry(idl.IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    """nav_msgs/Odometry: ``Header header``, ``string child_frame_id``,
    ``PoseWithCovariance pose``, ``TwistWithCovariance twist``."""

    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


# -- diagnostic_msgs ----------------------------------------------------------------------------

@dataclass
@annotate.final
class KeyValue(idl.IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    """diagnostic_msgs/KeyValue: ``string key``, ``string value``."""

    key: str = ""
    value: str = ""


@dataclass
@annotate.final
class DiagnosticStatus(idl.IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    """diagnostic_msgs/DiagnosticStatus: ``byte level`` (OK 0, WARN 1, ERROR 2, STALE 3),
    ``string name``, ``string message``, ``string hardware_id``, ``KeyValue[] values``.

    A ROS ``byte`` is an IDL ``octet``: an unsigned 8-bit integer on the wire.
    """

    level: types.uint8 = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: types.sequence[KeyValue] = field(default_factory=list)


@dataclass
@annotate.final
class DiagnosticArray(idl.IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    """diagnostic_msgs/DiagnosticArray: ``Header header``, ``DiagnosticStatus[] status``."""

    header: Header = field(default_factory=Header)
    status: types.sequence[DiagnosticStatus] = field(default_factory=list)


#: DiagnosticStatus levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3
