"""ROS 2 messages of a tensegrity robot: the topic table, the ``tensegrity_msgs`` types,
and the conversions between samples and messages.

Standard types carry what they can (sensor_msgs/Imu, MagneticField, JointState, Image,
CameraInfo, geometry_msgs/PoseArray, std_msgs/String); a few custom ``tensegrity_msgs``
types carry the rest. Topic names come from the robot description (rod names), so a
robot's own bag needs nothing of this package to be readable here. The README holds the
same table for people who write bags themselves.

``sensor_msgs/Imu`` and ``sensor_msgs/MagneticField`` (most of a run's messages) are
encoded and decoded by hand: ``struct`` on the CDR bytes is several times faster than
the generic serialiser, and the tests check that both give the same bytes and values.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from tensegrity_gym.model.samples import GROUND_TRUTH, seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Iterable

    from rosbags.typesys.store import Typestore

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "CUSTOM_MESSAGES",
    "FIXED_TOPICS",
    "TOPIC_KINDS",
    "TopicTable",
    "decode_imu",
    "decode_magnetic_field",
    "encode_imu",
    "encode_magnetic_field",
    "sample_kinds_of_topics",
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

# topic -> (message type, what it carries); per-rod IMU topics are added per robot.
FIXED_TOPICS: dict[str, tuple[str, str]] = {
    "/robot_description": (STRING, "the robot description, YAML (once, first)"),
    "/tensegrity/run_info": (STRING, "YAML: control_period (s), env, seed, policy, ..."),
    "/tensegrity/calibration": (CALIBRATION, "UWB anchors and offsets, camera pose"),
    "/camera/camera_info": (CAMERA_INFO, "camera intrinsics (k), width, height"),
    "/motors/rest_lengths": (JOINT_STATE, "encoders: rest lengths of the actuated cables (m)"),
    "/cables/lengths": (JOINT_STATE, "cable-length sensors: every cable's length (m)"),
    "/uwb/ranges": (UWB_RANGES, "one UWB broadcast round"),
    "/contacts": (CONTACTS, "endcap-ground contact flags"),
    "/camera/color/image_raw": (IMAGE, "RGB frame, rgb8"),
    "/camera/depth/image_raw": (IMAGE, "depth frame, 32FC1 metres, 0 where no return"),
    "/commands/rest_length_targets": (
        JOINT_STATE,
        "the command of each control period: actuated cables' rest-length targets (m)",
    ),
    "/ground_truth/rod_poses": (POSE_ARRAY, "true rod poses (centre, body z along the rod)"),
    "/ground_truth/state": (STATE, "true node positions and velocities, CoM, rest lengths"),
    "/estimate/rod_poses": (POSE_ARRAY, "estimated rod poses"),
    "/estimate/state": (STATE, "the estimator's output"),
}

ROD_TOPICS: dict[str, tuple[str, str]] = {
    "/{rod}/imu/data_raw": (IMU, "accelerometer (m/s^2) and gyro (rad/s), body frame"),
    "/{rod}/imu/mag": (MAGNETIC_FIELD, "magnetometer (T), body frame"),
    "/{rod}/imu/data": (IMU, "the on-board AHRS orientation, body to world"),
}

TOPIC_KINDS: dict[str, str] = {
    "/{rod}/imu/data_raw": "imu",
    "/{rod}/imu/data": "ahrs",
    "/motors/rest_lengths": "encoders",
    "/cables/lengths": "cable_lengths",
    "/uwb/ranges": "uwb",
    "/contacts": "contacts",
    "/camera/depth/image_raw": "rgbd",
    "/ground_truth/state": GROUND_TRUTH,
}
"""The topic that carries each sample kind (:data:`SAMPLE_KINDS`) and ground truth."""


def sample_kinds_of_topics(topics: Iterable[str], description: RobotDescription) -> frozenset[str]:
    """The sample kinds (and ``"ground_truth"``) a set of topics carries."""
    present = set(topics)
    kinds = set()
    for pattern, kind in TOPIC_KINDS.items():
        names = {pattern.format(rod=rod.name) for rod in description.rods}
        if names & present:
            kinds.add(kind)
    return frozenset(kinds)


@cache
def typestore() -> Typestore:
    """ROS 2 Jazzy's standard types plus ``tensegrity_msgs``."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name, text in CUSTOM_MESSAGES.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@dataclass(frozen=True)
class TopicTable:
    """Every topic of one robot's bag: name -> message type, and the per-rod lookups."""

    types: dict[str, str]
    imu_raw: dict[str, int]
    """IMU topic -> rod index."""
    imu_mag: dict[str, int]
    ahrs: dict[str, int]

    @classmethod
    def for_robot(cls, description: RobotDescription) -> TopicTable:
        types = {topic: kind for topic, (kind, _) in FIXED_TOPICS.items()}
        lookups: list[dict[str, int]] = [{}, {}, {}]
        for r, rod in enumerate(description.rods):
            for lookup, (pattern, (kind, _)) in zip(lookups, ROD_TOPICS.items(), strict=True):
                topic = pattern.format(rod=rod.name)
                types[topic] = kind
                lookup[topic] = r
        return cls(types, *lookups)

    def rod_topic(self, which: str, rod: int) -> str:
        """The topic of rod ``rod``'s ``which`` stream (``imu_raw``, ``imu_mag``, ``ahrs``)."""
        lookup: dict[str, int] = getattr(self, which)
        return next(t for t, r in lookup.items() if r == rod)


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
