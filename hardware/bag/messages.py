"""ROS 2 messages of a tensegrity robot: the topics that carry no sample, the
``tensegrity_msgs`` types, and fast CDR codecs for the IMU messages.

Standard types carry what they can (sensor_msgs/Imu, MagneticField, JointState, Image,
CameraInfo, geometry_msgs/PoseArray, std_msgs/String); a few custom ``tensegrity_msgs``
types carry the rest. What ROS viewers draw (``/tf``, ``/tf_static``, the robot as
markers, a URDF on ``/robot_description``) is written beside them (:data:`VIEW_TOPICS`);
readers pass over it. What is sent once (the header, ``/tf_static``) is recorded
latched (:data:`LATCHED_TOPICS`, :data:`LATCHED_QOS`). The sensor topics are declared
with their sample kinds (:mod:`hardware.bag.kinds`); their names come from the robot
description (rod names), so a robot's own bag needs nothing of this package to be
readable here. docs/recordings.md holds the same table for people who write bags
themselves.

``sensor_msgs/Imu`` and ``sensor_msgs/MagneticField`` (most of a run's messages) are
encoded and decoded by hand: ``struct`` on the CDR bytes is several times faster than
the generic serialiser, and the tests check that both give the same bytes and values.
"""

from __future__ import annotations

import struct
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from tensegrity_gym.model.samples import seconds_to_ns

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = [
    "COMMAND_TOPIC",
    "CUSTOM_MESSAGES",
    "DESCRIPTION_YAML_TOPIC",
    "FIXED_TOPICS",
    "HEADER_TOPICS",
    "LATCHED_QOS",
    "LATCHED_TOPICS",
    "MARKERS_TOPIC",
    "NIS_TOPIC",
    "TF_STATIC_TOPIC",
    "TF_TOPIC",
    "VIEW_TOPICS",
    "Raw",
    "decode_imu",
    "decode_magnetic_field",
    "encode_imu",
    "encode_magnetic_field",
    "stamp",
    "stamp_ns",
    "typestore",
]

# The definitions live as a ROS 2 package beside this module (tensegrity_msgs/msg/*.msg,
# with package.xml and CMakeLists.txt), so a robot's own ROS 2 workspace can build them.
_MSG_DIR = Path(__file__).parent / "tensegrity_msgs" / "msg"
CUSTOM_MESSAGES: dict[str, str] = {
    f"tensegrity_msgs/msg/{f.stem}": f.read_text() for f in sorted(_MSG_DIR.glob("*.msg"))
}

Raw = bytes | memoryview
"""A message's CDR bytes, as read from a bag or the wire."""

STRING = "std_msgs/msg/String"
IMU = "sensor_msgs/msg/Imu"
MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
JOINT_STATE = "sensor_msgs/msg/JointState"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
UWB_RANGES = "tensegrity_msgs/msg/UwbRangeArray"
CONTACTS = "tensegrity_msgs/msg/ContactFlags"
STATE = "tensegrity_msgs/msg/TensegrityState"
CALIBRATION = "tensegrity_msgs/msg/SensorCalibration"
TF = "tf2_msgs/msg/TFMessage"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
MARKER = "visualization_msgs/msg/Marker"
FLOAT64 = "std_msgs/msg/Float64"

DESCRIPTION_TOPIC = "/robot_description"
"""By ROS convention a URDF (what RViz and Foxglove load); bags written before the URDF
carry the YAML here, and readers still take it."""
DESCRIPTION_YAML_TOPIC = "/tensegrity/robot_description_yaml"
"""The robot description as this package reads it: YAML."""
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
MARKERS_TOPIC = "/tensegrity/markers"
NIS_TOPIC = "/estimate/nis"
RUN_INFO_TOPIC = "/tensegrity/run_info"
CALIBRATION_TOPIC = "/tensegrity/calibration"
CAMERA_INFO_TOPIC = "/camera/camera_info"
COMMAND_TOPIC = "/commands/rest_length_targets"
TRUTH_POSES_TOPIC = "/ground_truth/rod_poses"
TRUTH_STATE_TOPIC = "/ground_truth/state"
ESTIMATE_POSES_TOPIC = "/estimate/rod_poses"
ESTIMATE_STATE_TOPIC = "/estimate/state"

HEADER_TOPICS = (
    DESCRIPTION_YAML_TOPIC,
    DESCRIPTION_TOPIC,
    RUN_INFO_TOPIC,
    CALIBRATION_TOPIC,
    CAMERA_INFO_TOPIC,
)
"""What makes a bag (or a robot on the link) self-contained, read before anything else."""

# topic -> (message type, what it carries): the topics that carry no sample. The sensor
# topics are the sensor kinds' (hardware.bag.kinds), added per robot by its TopicTable.
FIXED_TOPICS: dict[str, tuple[str, str]] = {
    DESCRIPTION_YAML_TOPIC: (STRING, "the robot description, YAML (once, first)"),
    DESCRIPTION_TOPIC: (STRING, "the robot as a URDF for viewers (once, first)"),
    RUN_INFO_TOPIC: (STRING, "YAML: control_period (s), env, seed, policy, ..."),
    CALIBRATION_TOPIC: (CALIBRATION, "UWB anchors and offsets, camera pose"),
    CAMERA_INFO_TOPIC: (CAMERA_INFO, "camera intrinsics (k), width, height"),
    COMMAND_TOPIC: (
        JOINT_STATE,
        "the command of each control period: actuated cables' rest-length targets (m)",
    ),
    TRUTH_POSES_TOPIC: (POSE_ARRAY, "true rod poses (centre, body z along the rod)"),
    TRUTH_STATE_TOPIC: (STATE, "true node positions and velocities, CoM, rest lengths"),
    ESTIMATE_POSES_TOPIC: (POSE_ARRAY, "estimated rod poses"),
    ESTIMATE_STATE_TOPIC: (STATE, "the estimator's output"),
    TF_TOPIC: (TF, "rod frames under world: truth/ROD and estimate/ROD (optional)"),
    TF_STATIC_TOPIC: (TF, "fixed frames: camera under world, endcaps under their rods"),
    MARKERS_TOPIC: (MARKER_ARRAY, "rods, endcaps, cables by tension, ghost, anchors, goal"),
    NIS_TOPIC: (FLOAT64, "the estimator's latest normalised innovation squared per row"),
}

VIEW_TOPICS = frozenset({TF_TOPIC, TF_STATIC_TOPIC, MARKERS_TOPIC, NIS_TOPIC})
"""What only viewers read: written where a recording asks for it (``/tf_static`` once,
the others at the control rate), passed over by every reader here."""

LATCHED_TOPICS = frozenset({*HEADER_TOPICS, TF_STATIC_TOPIC})
"""What is sent once, at the start: recorded with :data:`LATCHED_QOS`, so that
``ros2 bag play`` offers it to subscribers that join later (as robot_state_publisher
offers ``/robot_description`` and tf2's static broadcaster ``/tf_static``)."""

_INFINITE = QosTime(9_223_372_036, 854_775_807)  # rmw's "infinite" duration, as rosbag2 writes it
LATCHED_QOS = Qos(
    QosHistory.KEEP_LAST,
    1,
    QosReliability.RELIABLE,
    QosDurability.TRANSIENT_LOCAL,
    _INFINITE,
    _INFINITE,
    QosLiveliness.AUTOMATIC,
    _INFINITE,
    False,
)
"""ROS 2's latched profile: keep last 1, reliable, transient local (the bag's
``offered_qos_profiles`` of a topic in :data:`LATCHED_TOPICS`)."""


@cache
def typestore() -> Typestore:
    """ROS 2 Jazzy's standard types plus ``tensegrity_msgs``."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in CUSTOM_MESSAGES.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


# ---------------------------------------------------------------------- stamps


def stamp(t: float) -> tuple[int, int]:
    """(sec, nanosec) of a builtin_interfaces/Time for ``t`` seconds."""
    return divmod(seconds_to_ns(t), 1_000_000_000)


def stamp_ns(sec: int, nanosec: int) -> int:
    return sec * 1_000_000_000 + nanosec


# ---------------------------------------------------------------------- fast codecs
#
# CDR, little endian: a 4-byte encapsulation header, then the fields, each aligned to
# its size (at most 8) counted from the end of that header. A std_msgs/Header is
# int32 sec, uint32 nanosec, uint32 length (NUL included) and the frame id's bytes.

_ENCAPSULATION = b"\x00\x01\x00\x00"
_TIME_LEN = struct.Struct("<iII")
_IMU_DOUBLES = struct.Struct("<37d")  # orientation 4, cov 9, gyro 3, cov 9, accel 3, cov 9
_MAG_DOUBLES = struct.Struct("<12d")  # field 3, cov 9
_NO_COVARIANCE = (0.0,) * 9
_UNKNOWN = (-1.0,) + (0.0,) * 8  # covariance[0] = -1: the field is not provided (REP 145)


def _header_bytes(t: float, frame_id: str) -> bytes:
    sec, nanosec = stamp(t)
    name = frame_id.encode() + b"\x00"
    head = _TIME_LEN.pack(sec, nanosec, len(name)) + name
    return head + b"\x00" * (-len(head) % 8)


def _read_header(raw: bytes | memoryview) -> tuple[int, str, int]:
    """(stamp in ns, frame id, offset of the first 8-aligned field after the header)."""
    if len(raw) < 16 or bytes(raw[:2]) != b"\x00\x01":
        raise ValueError("not little-endian CDR")
    sec, nanosec, n = _TIME_LEN.unpack_from(raw, 4)
    end = 16 + n
    if n == 0 or end > len(raw):
        raise ValueError(f"frame_id length {n} runs past the {len(raw)}-byte message")
    frame_id = bytes(raw[16 : end - 1]).decode()
    return stamp_ns(sec, nanosec), frame_id, 4 + (end - 4 + 7) // 8 * 8


def encode_imu(
    t: float,
    frame_id: str,
    *,
    orientation: Any = None,
    gyro: Any = None,
    accel: Any = None,
) -> bytes:
    """A sensor_msgs/Imu in CDR; fields left out are zero with covariance[0] = -1."""
    q = tuple(orientation) if orientation is not None else (0.0, 0.0, 0.0, 1.0)
    w = tuple(gyro) if gyro is not None else (0.0, 0.0, 0.0)
    a = tuple(accel) if accel is not None else (0.0, 0.0, 0.0)
    doubles = _IMU_DOUBLES.pack(
        *q,
        *(_NO_COVARIANCE if orientation is not None else _UNKNOWN),
        *w,
        *(_NO_COVARIANCE if gyro is not None else _UNKNOWN),
        *a,
        *(_NO_COVARIANCE if accel is not None else _UNKNOWN),
    )
    return _ENCAPSULATION + _header_bytes(t, frame_id) + doubles


def decode_imu(
    raw: bytes | memoryview,
) -> tuple[
    int, str, tuple[float, ...], tuple[float, ...], tuple[float, ...], tuple[bool, bool, bool]
]:
    """(stamp ns, frame id, orientation (4,), gyro (3,), accel (3,), which are provided)."""
    ns, frame_id, off = _read_header(raw)
    if off + _IMU_DOUBLES.size > len(raw):
        raise ValueError(f"{len(raw)} bytes are too few for a sensor_msgs/Imu")
    v = _IMU_DOUBLES.unpack_from(raw, off)
    provided = (v[4] != -1.0, v[16] != -1.0, v[28] != -1.0)
    return ns, frame_id, v[0:4], v[13:16], v[25:28], provided


def encode_magnetic_field(t: float, frame_id: str, field: Any) -> bytes:
    """A sensor_msgs/MagneticField (T) in CDR."""
    doubles = _MAG_DOUBLES.pack(*tuple(field), *_NO_COVARIANCE)
    return _ENCAPSULATION + _header_bytes(t, frame_id) + doubles


def decode_magnetic_field(raw: bytes | memoryview) -> tuple[int, str, tuple[float, ...]]:
    """(stamp ns, frame id, field (3,) in T)."""
    ns, frame_id, off = _read_header(raw)
    if off + _MAG_DOUBLES.size > len(raw):
        raise ValueError(f"{len(raw)} bytes are too few for a sensor_msgs/MagneticField")
    v = _MAG_DOUBLES.unpack_from(raw, off)
    return ns, frame_id, v[0:3]
