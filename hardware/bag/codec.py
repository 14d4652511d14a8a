"""Samples, commands, ground truth and estimates to ROS 2 messages and back, for one robot.

Everything that names a rod, a cable or a node goes through the robot description,
so the same codec serves the bag writer, the bag reader and the robot link. Samples are
encoded and decoded by their kind (:mod:`hardware.bag.kinds`); the codec is the context
their encoders and decoders work in.
Decoding validates what it reads: a wrong size, an unknown name or a value that is not
finite raises :class:`MessageError`, which the callers count or report with the topic
and time.

Stamps are the robot's clock; samples carry seconds from the codec's clock origin
(``origin_ns``, the robot-clock ns of sample time 0), so that a robot stamped in Unix
time hands out small times that float seconds hold to the nanosecond. Decoding
subtracts the origin (:meth:`RobotCodec.seconds`), encoding adds it back
(:meth:`RobotCodec.stamp_ns`): a recording round-trips to its absolute stamps.
"""

from __future__ import annotations

import math
import struct
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from numpy.typing import NDArray

from hardware.bag import messages as m
from hardware.bag.kinds import TopicTable
from tensegrity_gym.model.checks import yaml_problem
from tensegrity_gym.model.description import dump_robot
from tensegrity_gym.model.estimate import Estimate
from tensegrity_gym.model.kinematics import rod_axes, rod_centres, rod_quaternion_from_axis
from tensegrity_gym.model.protocols import SensorCalibration
from tensegrity_gym.model.samples import (
    ContactSample,
    GroundTruth,
    RgbdFrame,
    UwbRangeSample,
    ns_to_seconds,
    seconds_to_ns,
)
from tensegrity_gym.model.urdf import robot_urdf

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from hardware.bag.messages import Raw
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import Sample

__all__ = ["Encoded", "MessageError", "RobotCodec", "description_yaml"]

Encoded = tuple[str, bytes]
"""(topic, CDR bytes)."""
Vec = NDArray[np.float64]

WORLD_FRAME = "world"
CAMERA_FRAME = "camera"
_NS = 1_000_000_000
_STAMP = struct.Struct("<iI")  # a std_msgs/Header's stamp, after the CDR encapsulation


class MessageError(ValueError):
    """A message could not be turned into a sample; the text says why."""


def _finite_values(values: tuple[float, ...], what: str) -> None:
    if not all(map(math.isfinite, values)):
        raise MessageError(f"{what} is not finite")


def _finite(values: NDArray[Any], what: str) -> NDArray[Any]:
    if not np.all(np.isfinite(values)):
        raise MessageError(f"{what} is not finite")
    return values


class RobotCodec:
    """Encoders and decoders of one robot's messages (see :mod:`hardware.bag.messages`).

    Args:
        description: the robot.
        origin_ns: the robot-clock ns at which sample time 0 lies (see the module
            docstring); the owner may move it between episodes.
    """

    def __init__(self, description: RobotDescription, origin_ns: int = 0) -> None:
        d = description
        self.description = d
        self.origin_ns = origin_ns
        """Robot-clock ns of sample time 0."""
        self.topics = TopicTable(d)
        self.store = m.typestore()
        t = self.store.types
        self._Time, self._Header = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]
        self._Point, self._Vector3 = t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Vector3"]
        self._Pose, self._Quaternion = (
            t["geometry_msgs/msg/Pose"],
            t["geometry_msgs/msg/Quaternion"],
        )
        self.rod_names = [r.name for r in d.rods]
        self.node_names = [n.name for n in d.nodes]
        self.cable_names = [c.name for c in d.cables]
        self.actuated_names = [self.cable_names[k] for k in d.actuated]
        self._node_index = {name: i for i, name in enumerate(self.node_names)}
        self._cable_index = {name: k for k, name in enumerate(self.cable_names)}
        self._actuated_index = {name: k for k, name in enumerate(self.actuated_names)}
        self.n_modules = d.n_nodes + len(d.anchors)

    # ------------------------------------------------------------------ clock

    def seconds(self, ns: int) -> float:
        """Sample time (s from the origin) of the robot-clock stamp ``ns``."""
        return ns_to_seconds(ns - self.origin_ns)

    def stamp_ns(self, t: float) -> int:
        """The robot-clock stamp (ns) of sample time ``t`` (s from the origin)."""
        return seconds_to_ns(t) + self.origin_ns

    def _stamp_of(self, msg: Any) -> float:
        """Sample time (s) of a decoded message's header stamp."""
        return self.seconds(m.stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec))

    # ------------------------------------------------------------------ helpers

    def header(self, t: float, frame_id: str = "") -> Any:
        """A std_msgs/Header stamped at sample time ``t`` (s)."""
        sec, nanosec = divmod(self.stamp_ns(t), _NS)
        return self._Header(stamp=self._Time(sec=sec, nanosec=nanosec), frame_id=frame_id)

    def _restamped(self, raw: bytes, t: float) -> bytes:
        """A message of the fast encoders of :mod:`messages` (stamped ``t`` from 0),
        stamped at sample time ``t`` (s) on the robot's clock."""
        if not self.origin_ns:
            return raw
        return raw[:4] + _STAMP.pack(*divmod(self.stamp_ns(t), _NS)) + raw[12:]

    def imu(self, t: float, frame_id: str, **fields: Any) -> bytes:
        """A sensor_msgs/Imu at sample time ``t`` (s); ``fields`` as
        :func:`messages.encode_imu` takes them (orientation, gyro rad/s, accel m/s^2)."""
        return self._restamped(m.encode_imu(t, frame_id, **fields), t)

    def magnetic_field(self, t: float, frame_id: str, field: Any) -> bytes:
        """A sensor_msgs/MagneticField (T) at sample time ``t`` (s)."""
        return self._restamped(m.encode_magnetic_field(t, frame_id, field), t)

    def serialize(self, msg: Any, msgtype: str) -> bytes:
        return bytes(self.store.serialize_cdr(msg, msgtype))

    def _points(self, xyz: NDArray[np.float64], kind: Any) -> list[Any]:
        return [kind(x=float(a), y=float(b), z=float(c)) for a, b, c in np.asarray(xyz)]

    def joint_state(self, t: float, names: Sequence[str], values: NDArray[np.float64]) -> bytes:
        msg = self.store.types[m.JOINT_STATE](
            header=self.header(t),
            name=list(names),
            position=np.asarray(values, dtype=np.float64),
            velocity=np.empty(0),
            effort=np.empty(0),
        )
        return self.serialize(msg, m.JOINT_STATE)

    def image(self, t: float, encoding: str, pixels: NDArray[Any], pixel_bytes: int) -> bytes:
        """A sensor_msgs/Image of (H, W[, C]) pixels, little endian, rows packed."""
        h, w = pixels.shape[:2]
        msg = self.store.types[m.IMAGE](
            header=self.header(t, CAMERA_FRAME),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=pixel_bytes * w,
            data=pixels.view(np.uint8).reshape(-1),
        )
        return self.serialize(msg, m.IMAGE)

    def _pose_array(self, t: float, centres: Vec, quats: Vec) -> bytes:
        poses = [
            self._Pose(
                position=self._Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                orientation=self._Quaternion(
                    x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
                ),
            )
            for p, q in zip(centres, quats, strict=True)
        ]
        msg = self.store.types[m.POSE_ARRAY](header=self.header(t, WORLD_FRAME), poses=poses)
        return self.serialize(msg, m.POSE_ARRAY)

    def _state(
        self,
        t: float,
        nodes: NDArray[np.float64],
        velocities: NDArray[np.float64],
        com: NDArray[np.float64],
        rest_lengths: NDArray[np.float64],
        healthy: bool = True,
        reinitialised: bool = False,
    ) -> bytes:
        msg = self.store.types[m.STATE](
            header=self.header(t, WORLD_FRAME),
            node_positions=self._points(nodes, self._Point),
            node_velocities=self._points(velocities, self._Vector3),
            center_of_mass=self._Point(x=float(com[0]), y=float(com[1]), z=float(com[2])),
            rest_lengths=np.asarray(rest_lengths, dtype=np.float64),
            healthy=bool(healthy),
            reinitialised=bool(reinitialised),
        )
        return self.serialize(msg, m.STATE)

    # ------------------------------------------------------------------ encoding

    def encode_header(
        self, calibration: SensorCalibration, run_info: Mapping[str, Any], t: float
    ) -> list[Encoded]:
        """The messages that make a bag self-contained: description, run info, calibration."""
        d = self.description
        string = self.store.types[m.STRING]
        cam = d.sensors.camera
        k = np.asarray(calibration.camera_intrinsics, dtype=np.float64)
        p = np.zeros((3, 4))
        p[:, :3] = k
        info = self.store.types[m.CAMERA_INFO](
            header=self.header(t, CAMERA_FRAME),
            height=cam.height,
            width=cam.width,
            distortion_model="plumb_bob",
            d=np.zeros(5),
            k=k.reshape(9),
            r=np.eye(3).reshape(9),
            p=p.reshape(12),
            binning_x=0,
            binning_y=0,
            roi=self.store.types["sensor_msgs/msg/RegionOfInterest"](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
            ),
        )
        calib = self.store.types[m.CALIBRATION](
            header=self.header(t, WORLD_FRAME),
            anchors=self._points(np.asarray(calibration.anchors).reshape(-1, 3), self._Point),
            n_modules=int(calibration.uwb_offsets.shape[0]),
            uwb_offsets=np.asarray(calibration.uwb_offsets, dtype=np.float64).reshape(-1),
            camera_pose=np.asarray(calibration.camera_pose, dtype=np.float64).reshape(16),
        )
        run_text = yaml.safe_dump(dict(run_info), sort_keys=True)
        return [
            (m.DESCRIPTION_YAML_TOPIC, self.serialize(string(data=dump_robot(d)), m.STRING)),
            (m.DESCRIPTION_TOPIC, self.serialize(string(data=robot_urdf(d)), m.STRING)),
            (m.RUN_INFO_TOPIC, self.serialize(string(data=run_text), m.STRING)),
            (m.CALIBRATION_TOPIC, self.serialize(calib, m.CALIBRATION)),
            (m.CAMERA_INFO_TOPIC, self.serialize(info, m.CAMERA_INFO)),
        ]

    def encode_sample(self, sample: Sample) -> list[Encoded]:
        """The messages of one sample, by its kind in the topic table; TypeError if its
        class has no kind."""
        kind = self.topics.kind_of(sample)
        rod = int(getattr(sample, "rod", 0)) if kind.per_rod else 0
        payloads = kind.encode(self, sample)
        return [(self.topics.topic(kind.name, c, rod), raw) for c, raw in enumerate(payloads)]

    def encode_float(self, topic: str, value: float) -> Encoded:
        """A std_msgs/Float64 on ``topic``."""
        msg = self.store.types[m.FLOAT64](data=float(value))
        return (topic, self.serialize(msg, m.FLOAT64))

    def encode_command(self, t: float, targets: NDArray[np.float64]) -> Encoded:
        return (m.COMMAND_TOPIC, self.joint_state(t, self.actuated_names, targets))

    def encode_truth(self, truth: GroundTruth) -> list[Encoded]:
        return [
            (
                m.TRUTH_POSES_TOPIC,
                self._pose_array(truth.t, truth.rod_positions, truth.rod_quaternions),
            ),
            (
                m.TRUTH_STATE_TOPIC,
                self._state(
                    truth.t,
                    truth.node_positions,
                    truth.node_velocities,
                    truth.com,
                    truth.rest_lengths,
                ),
            ),
        ]

    def estimate_rod_poses(self, estimate: Estimate) -> tuple[Vec, Vec]:
        """The estimate's rod centres (m), (n_rods, 3), and orientations (x, y, z, w),
        (n_rods, 4): tracked ones where the estimator has them, else from the axes."""
        x = estimate.node_positions
        rod_nodes = self.description.rod_nodes
        centres = rod_centres(x, rod_nodes)
        if estimate.rod_quaternions is not None:  # tracked about the axis too
            return centres, estimate.rod_quaternions
        with np.errstate(invalid="ignore", divide="ignore"):
            return centres, rod_quaternion_from_axis(rod_axes(x, rod_nodes))

    def encode_estimate(self, estimate: Estimate) -> list[Encoded]:
        x = estimate.node_positions
        centres, quats = self.estimate_rod_poses(estimate)
        return [
            (m.ESTIMATE_POSES_TOPIC, self._pose_array(estimate.t, centres, quats)),
            (
                m.ESTIMATE_STATE_TOPIC,
                self._state(
                    estimate.t,
                    x,
                    estimate.node_velocities,
                    estimate.com,
                    estimate.rest_lengths,
                    estimate.healthy,
                    estimate.reinitialised,
                ),
            ),
        ]

    # ------------------------------------------------------------------ decoding

    def deserialize(self, raw: Raw, msgtype: str) -> Any:
        try:
            return self.store.deserialize_cdr(raw, msgtype)
        except Exception as err:  # rosbags raises assorted errors on bad bytes
            raise MessageError(f"cannot decode {len(raw)} bytes as {msgtype}: {err}") from None

    def _names_to_values(
        self, msg: Any, index: dict[str, int], names: list[str], what: str
    ) -> NDArray[np.float64]:
        position = np.asarray(msg.position, dtype=np.float64)
        if list(msg.name) == names and position.shape == (len(names),):
            return _finite(position.copy(), what)
        if len(msg.name) != len(position):
            raise MessageError(f"{len(msg.name)} names but {len(position)} positions")
        out = np.full(len(names), np.nan)
        for name, value in zip(msg.name, position, strict=True):
            if name not in index:
                raise MessageError(f"unknown {what} {name!r}; the robot has {names}")
            out[index[name]] = value
        missing = [names[k] for k in np.flatnonzero(np.isnan(out))]
        if missing:
            raise MessageError(f"no value for {what} {missing}")
        return _finite(out, what)

    def decode_joint_state(self, raw: Raw, kind: str) -> tuple[int, Vec]:
        """(stamp ns, values) of a JointState over the ``actuated`` cables or ``all`` cables."""
        msg = self.deserialize(raw, m.JOINT_STATE)
        if kind == "actuated":
            values = self._names_to_values(msg, self._actuated_index, self.actuated_names, "cable")
        else:
            values = self._names_to_values(msg, self._cable_index, self.cable_names, "cable")
        return m.stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec), values

    @staticmethod
    def _fast(decode: Any, raw: Raw) -> Any:
        """A hand-written decoder's fields; its ValueError (short bytes, a bad frame id)
        becomes a MessageError."""
        try:
            return decode(raw)
        except (ValueError, struct.error) as err:
            raise MessageError(str(err)) from None

    def decode_imu_raw(self, raw: Raw) -> tuple[int, Vec, Vec]:
        """(stamp ns, gyro (3,), accel (3,))."""
        ns, _, _, gyro, accel, provided = self._fast(m.decode_imu, raw)
        if not (provided[1] and provided[2]):
            raise MessageError("the IMU message has no angular velocity or acceleration")
        _finite_values(gyro + accel, "gyro or acceleration")
        return ns, np.array(gyro), np.array(accel)

    def decode_mag(self, raw: Raw) -> tuple[int, Vec]:
        ns, _, field = self._fast(m.decode_magnetic_field, raw)
        _finite_values(field, "magnetic field")
        return ns, np.array(field)

    def decode_ahrs(self, raw: Raw) -> tuple[int, Vec]:
        ns, _, q, _, _, provided = self._fast(m.decode_imu, raw)
        if not provided[0]:
            raise MessageError(
                "the AHRS message has orientation_covariance[0] = -1: no orientation"
            )
        _finite_values(q, "orientation")
        norm = math.sqrt(sum(v * v for v in q))
        if not 0.9 < norm < 1.1:
            raise MessageError(f"orientation quaternion has norm {norm:.3g}, not 1")
        return ns, np.array(q)

    def decode_uwb(self, raw: Raw) -> UwbRangeSample:
        msg = self.deserialize(raw, m.UWB_RANGES)
        k = len(msg.ranges)
        pairs = np.empty((k, 2), dtype=np.intp)
        ranges = np.empty(k)
        times = np.empty(k)
        for n, r in enumerate(msg.ranges):
            pairs[n] = r.initiator, r.responder
            ranges[n] = r.range
            times[n] = self.seconds(m.stamp_ns(r.stamp.sec, r.stamp.nanosec))
        if k and pairs.max() >= self.n_modules:
            raise MessageError(
                f"module id {int(pairs.max())} out of range: the robot has {self.n_modules} "
                "UWB modules (its nodes, then its anchors)"
            )
        _finite(ranges, "range")
        return UwbRangeSample(self._stamp_of(msg), times, pairs, ranges)

    def decode_contacts(self, raw: Raw) -> ContactSample:
        msg = self.deserialize(raw, m.CONTACTS)
        flags = np.asarray(msg.in_contact, dtype=np.bool_)
        if list(msg.nodes) == self.node_names and flags.shape == (len(self.node_names),):
            in_contact = flags.copy()
        else:
            if len(msg.nodes) != len(flags):
                raise MessageError(f"{len(msg.nodes)} node names but {len(flags)} flags")
            unknown = [n for n in msg.nodes if n not in self._node_index]
            if unknown or len(set(msg.nodes)) != len(self.node_names):
                raise MessageError(
                    f"contact flags for nodes {list(msg.nodes)}; the robot has {self.node_names}"
                )
            in_contact = np.zeros(len(self.node_names), dtype=np.bool_)
            for name, flag in zip(msg.nodes, flags, strict=True):
                in_contact[self._node_index[name]] = flag
        return ContactSample(self._stamp_of(msg), in_contact)

    def decode_image(self, raw: Raw, kind: str) -> tuple[int, NDArray[Any]]:
        """(stamp ns, image): ``color`` gives (H, W, 3) uint8, ``depth`` (H, W) float32."""
        msg = self.deserialize(raw, m.IMAGE)
        h, w = int(msg.height), int(msg.width)
        want = ("rgb8", 3 * w, 3) if kind == "color" else ("32FC1", 4 * w, 4)
        if msg.encoding != want[0]:
            raise MessageError(f"image encoding {msg.encoding!r}; expected {want[0]!r}")
        if msg.is_bigendian and kind == "depth":
            raise MessageError("big-endian depth images are not supported")
        if msg.step != want[1] or len(msg.data) != h * want[1]:
            raise MessageError(
                f"{len(msg.data)} bytes with step {msg.step} for a {w}x{h} {msg.encoding} image"
            )
        data = np.asarray(msg.data, dtype=np.uint8)
        image = data.reshape(h, w, 3) if kind == "color" else data.view("<f4").reshape(h, w)
        return m.stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec), image

    def decode_state(self, raw: Raw, n_rest: int) -> tuple[float, Any]:
        """(time, message) of a TensegrityState, its sizes checked against the robot
        (``n_rest`` rest lengths) and every value finite."""
        msg = self.deserialize(raw, m.STATE)
        n = self.description.n_nodes
        if len(msg.node_positions) != n or len(msg.node_velocities) != n:
            raise MessageError(
                f"{len(msg.node_positions)} node positions and {len(msg.node_velocities)} "
                f"velocities; the robot has {n} nodes"
            )
        if len(msg.rest_lengths) != n_rest:
            raise MessageError(f"{len(msg.rest_lengths)} rest lengths; expected {n_rest}")
        c = msg.center_of_mass
        values = [
            v for p in (*msg.node_positions, *msg.node_velocities, c) for v in (p.x, p.y, p.z)
        ]
        _finite_values((*values, *msg.rest_lengths), "the state")
        return self._stamp_of(msg), msg

    @staticmethod
    def _xyz(points: Sequence[Any]) -> NDArray[np.float64]:
        return np.array([[p.x, p.y, p.z] for p in points], dtype=np.float64).reshape(-1, 3)

    def decode_truth(self, state_raw: Raw, poses_raw: Raw) -> GroundTruth:
        t, state = self.decode_state(state_raw, self.description.n_cables)
        poses = self.deserialize(poses_raw, m.POSE_ARRAY)
        if len(poses.poses) != self.description.n_rods:
            raise MessageError(
                f"{len(poses.poses)} rod poses; the robot has {self.description.n_rods} rods"
            )
        quats = np.array(
            [
                [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
                for p in poses.poses
            ],
            dtype=np.float64,
        ).reshape(-1, 4)
        centres = self._xyz([p.position for p in poses.poses])
        _finite(quats, "a rod orientation")
        _finite(centres, "a rod position")
        return GroundTruth(
            t=t,
            node_positions=self._xyz(state.node_positions),
            node_velocities=self._xyz(state.node_velocities),
            rod_positions=centres,
            rod_quaternions=quats,
            com=self._xyz([state.center_of_mass])[0],
            rest_lengths=np.asarray(state.rest_lengths, dtype=np.float64).copy(),
        )

    def decode_estimate(self, raw: Raw) -> Estimate:
        t, state = self.decode_state(raw, self.description.n_actuated)
        return Estimate(
            t=t,
            node_positions=self._xyz(state.node_positions),
            node_velocities=self._xyz(state.node_velocities),
            com=self._xyz([state.center_of_mass])[0],
            rest_lengths=np.asarray(state.rest_lengths, dtype=np.float64).copy(),
            healthy=bool(state.healthy),
            reinitialised=bool(state.reinitialised),
        )

    def decode_calibration(self, raw: Raw, camera_info_raw: Raw | None) -> SensorCalibration:
        msg = self.deserialize(raw, m.CALIBRATION)
        n = int(msg.n_modules)
        offsets = np.asarray(msg.uwb_offsets, dtype=np.float64)
        if offsets.size != n * n:
            raise MessageError(f"{offsets.size} UWB offsets for {n} modules (need {n * n})")
        anchors = self._xyz(msg.anchors)
        if n != self.n_modules:
            raise MessageError(
                f"calibration for {n} UWB modules; the robot has {self.description.n_nodes} "
                f"nodes and {len(anchors)} anchors"
            )
        if camera_info_raw is not None:
            info = self.deserialize(camera_info_raw, m.CAMERA_INFO)
            intrinsics = np.asarray(info.k, dtype=np.float64).reshape(3, 3).copy()
        else:  # a robot without a camera: the description's nominal camera
            intrinsics = self.description.sensors.camera.intrinsics
        pose = np.asarray(msg.camera_pose, dtype=np.float64).reshape(4, 4).copy()
        _finite(offsets, "a UWB offset")
        _finite(anchors, "an anchor position")
        _finite(pose, "the camera pose")
        _finite(intrinsics, "the camera intrinsics (k of /camera/camera_info)")
        return SensorCalibration(
            uwb_offsets=offsets.reshape(n, n).copy(),
            anchors=anchors,
            camera_intrinsics=intrinsics,
            camera_pose=pose,
        )

    def make_frame(self, ns: int, rgb: NDArray[np.uint8], depth: NDArray[np.float32]) -> RgbdFrame:
        if rgb.shape[:2] != depth.shape:
            raise MessageError(f"colour {rgb.shape[:2]} and depth {depth.shape} sizes differ")
        return RgbdFrame(self.seconds(ns), rgb, depth)


def description_yaml(header: Mapping[str, Raw], store: Any) -> tuple[str, str] | None:
    """(topic, YAML text) of the robot description among a bag's or a robot's header
    messages (topic -> CDR bytes): its own topic, else ``/robot_description`` where an
    older writer put the YAML there (a URDF there is not ours); None where neither has
    it. Bytes that do not decode as a std_msgs/String raise :class:`MessageError`."""
    for topic in (m.DESCRIPTION_YAML_TOPIC, m.DESCRIPTION_TOPIC):
        raw = header.get(topic)
        if raw is None:
            continue
        try:
            text = str(store.deserialize_cdr(raw, m.STRING).data)
        except Exception as err:  # rosbags raises assorted errors on bad bytes
            raise MessageError(f"{topic} cannot be decoded: {err}") from None
        if topic == m.DESCRIPTION_YAML_TOPIC or not text.lstrip().startswith("<"):
            return topic, text
    return None


def run_info_from_text(text: str) -> dict[str, Any]:
    """The run info mapping of ``/tensegrity/run_info``; a clear error if it is not one."""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise MessageError(f"run info is not YAML: {yaml_problem(err)}") from None
    except RecursionError:
        raise MessageError("run info is not YAML: nested too deeply") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise MessageError(f"run info is a {type(doc).__name__}, expected a mapping")
    return doc
