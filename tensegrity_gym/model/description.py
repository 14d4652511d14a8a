"""The robot description: one frozen dataclass tree per robot, loaded from YAML.

This module is the only place that parses robot geometry. The simulator builds its
bodies from a :class:`RobotDescription`, the estimators build their models from it
and the hardware driver maps topics to cables and rods with it.

Conventions: SI units, world frame z up. A rod's ``length`` is the distance between
its two endcap (node) centres; its overall length is ``length + 2 * endcap_radius``.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from tensegrity_gym.model.checks import yaml_problem
from tensegrity_gym.model.samples import SAMPLE_KINDS

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = [
    "DEFAULT_GAIT",
    "PRESETS",
    "STEER_GAIT",
    "Cable",
    "CableLengthConfig",
    "CameraConfig",
    "ContactConfig",
    "DescriptionError",
    "EncoderConfig",
    "Gait",
    "GaitFace",
    "Ground",
    "ImuConfig",
    "Motor",
    "Node",
    "RobotDescription",
    "Rod",
    "SensorSuite",
    "UwbConfig",
    "dump_robot",
    "load_robot",
    "loads_robot",
]

_ASSETS = resources.files("tensegrity_gym.model") / "assets"
PRESETS = tuple(sorted(f.name[:-5] for f in _ASSETS.iterdir() if f.name.endswith(".yaml")))
"""The preset robots: one YAML file each in ``tensegrity_gym/model/assets``, by name.
A preset's file is the one place that says what the robot is and what comes with it:
its env ids (``display_name``, ``hardware``) and its scripted gait (``gait``)."""

_DISPLAY_NAME = re.compile(r"[A-Z][A-Za-z0-9]*\Z")
_GAIT_NAME = re.compile(r"[a-z][a-z0-9_-]*\Z")

DEFAULT_GAIT = "forward"
"""The name of a robot's default gait: its YAML's ``gait`` (:attr:`RobotDescription.gait`)."""
STEER_GAIT = "steer"
"""The name of a robot's steering gait (``scripts/find_gait.py --steer``), if it has one."""

# A rod whose nodes are placed further from its length than this cannot be assembled.
_ASSEMBLY_TOLERANCE = 0.01  # relative


class DescriptionError(ValueError):
    """A robot description is malformed; the message names the file and the field."""


@dataclass(frozen=True)
class Node:
    name: str
    position: tuple[float, float, float]
    """Initial position (m) in the resting pose the robot is built in."""


@dataclass(frozen=True)
class Rod:
    name: str
    nodes: tuple[int, int]
    length: float
    """Distance between the endcap centres (m)."""
    radius: float
    endcap_radius: float
    mass: float
    color: tuple[float, float, float, float]


@dataclass(frozen=True)
class Motor:
    min_rest_length: float
    max_rest_length: float
    max_speed: float
    """Largest rate of change of the rest length (m/s)."""
    min_tension: float | None = None
    """N, optional in YAML: the motor keeps at least this tension on its cable, reeling in
    any slack (papers/002's robot: "the motors are controlled to apply a minimum torque,
    ensuring cables remain under tension"). Its rest length (what the encoder reads)
    then never exceeds the endcap distance less ``min_tension / stiffness``, so the
    encoders give the cable lengths (zero slack). None: the rest length follows the
    position command and the cable may go slack."""


@dataclass(frozen=True)
class Cable:
    name: str
    nodes: tuple[int, int]
    stiffness: float
    """N/m."""
    damping: float
    """N s/m."""
    rest_length: float
    """Initial (and, for passive cables, fixed) rest length (m)."""
    actuated: bool
    motor: Motor | None


@dataclass(frozen=True)
class Ground:
    lateral_friction: float
    rolling_friction: float
    """Rolling resistance (m): the torque is this times the normal force."""
    spinning_friction: float
    """Resistance to spinning about the contact normal (m), as rolling_friction."""
    restitution: float


@dataclass(frozen=True)
class ImuConfig:
    rate: float
    mount: str
    """Where each rod carries its IMU: ``rod_centre``."""
    accel_noise: float
    """Accelerometer white noise, standard deviation (m/s^2)."""
    gyro_noise: float
    """Gyro white noise, standard deviation (rad/s)."""
    accel_bias: float
    """Standard deviation of each accelerometer axis' constant bias (m/s^2)."""
    gyro_bias: float
    """Standard deviation of each gyro axis' constant bias (rad/s)."""
    mag_noise: float
    """Magnetometer white noise, standard deviation (T)."""
    magnetic_field: tuple[float, float, float]
    """Earth field in the world frame (T), as sensor_msgs/MagneticField carries it."""
    ahrs_gain: float
    accel_full_scale: float = 16.0 * 9.80665
    """Largest specific force the accelerometer reports (m/s^2); readings saturate there.
    Optional in YAML; 16 g, the widest range of common MEMS IMUs."""
    gyro_full_scale: float = float(np.radians(2000.0))
    """Largest angular rate the gyro reports (rad/s); optional in YAML, 2000 deg/s."""
    rods: tuple[int, ...] | None = None
    """The rods that carry one (indices; the YAML names them), in that order; None
    (absent): every rod. papers/002's robot has one, on its red rod."""


@dataclass(frozen=True)
class EncoderConfig:
    rate: float
    resolution: float
    """Quantisation step of the measured rest length (m)."""


@dataclass(frozen=True)
class CableLengthConfig:
    rate: float
    noise: float
    """Standard deviation (m) of a taut cable's length reading."""
    slack_bias: float
    """Extra error (m) of a slack cable: the sensor buckles and reads long."""


@dataclass(frozen=True)
class UwbConfig:
    rate: float
    """Broadcast rounds per second."""
    packet_spacing: float
    """Time between two modules' packets in a round (s)."""
    module_offset: float
    """Distance of each ranging module from its endcap centre, toward the rod centre (m)."""
    timestamp_noise: float
    """Standard deviation of each DW1000 time stamp (s)."""
    clock_drift_ppm: float
    offset_mean: float
    """Mean of the per-pair ranging offsets o_ij (m), papers/000 eq. 6-7."""
    offset_std: float
    reject_fraction: tuple[float, float]
    """Range of the share of packets rejected as non-line-of-sight, drawn per episode."""
    anchors: tuple[tuple[float, float, float], ...]


@dataclass(frozen=True)
class ContactConfig:
    rate: float
    threshold: float
    """Endcap-ground gap (m) under which an endcap counts as in contact."""


@dataclass(frozen=True)
class CameraConfig:
    position: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    width: int
    height: int
    vertical_fov: float
    """Degrees."""
    near: float
    far: float
    rate: float
    depth_noise: float
    """Depth noise standard deviation at zero range (m); the total is
    ``depth_noise + depth_noise_quadratic * depth**2``."""
    depth_noise_quadratic: float
    """Depth noise growth with the square of the range (m per m^2)."""

    @property
    def intrinsics(self) -> NDArray[np.float64]:
        """Pinhole camera matrix K (3, 3), in pixels."""
        fy = 0.5 * self.height / np.tan(0.5 * np.radians(self.vertical_fov))
        return np.array(
            [[fy, 0.0, 0.5 * self.width], [0.0, fy, 0.5 * self.height], [0.0, 0.0, 1.0]]
        )


@dataclass(frozen=True)
class SensorSuite:
    imu: ImuConfig
    encoder: EncoderConfig
    cable_length: CableLengthConfig
    uwb: UwbConfig
    contact: ContactConfig
    camera: CameraConfig


@dataclass(frozen=True)
class GaitFace:
    """One face of a scripted gait's rolling cycle: resting on ``face``, contract the
    ``contract`` cables fully, and hold the others at their initial rest length
    (``"hold"``) or let them out to their maximum (``"out"``).

    A *steering* gait's entries also say where the contraction takes the robot
    (``move``, ``to``); such a gait may list a face more than once, and FaceGait
    chooses among its entries the one that carries the CoM furthest toward the goal."""

    face: tuple[int, ...]
    """Node indices of the support face, sorted, (3,)."""
    contract: tuple[int, ...]
    """Indices into :attr:`RobotDescription.actuated` of the cables to contract."""
    others: str
    """``"hold"`` or ``"out"``."""
    move: tuple[float, float, float] | None = None
    """The CoM's move over the gait period in the face's frame: x (m) from the support
    triangle's centre toward its first node (lowest index), y (m) 90° counter-clockwise
    of it, and the turn (rad, counter-clockwise): the yaw of ``to``'s triangle (the same
    way, from its centre to its lowest-index node) less this one's, wrapped to
    [-pi, pi); None: not known."""
    to: tuple[int, ...] | None = None
    """The support face the period leaves the robot on (sorted node indices, (3,))."""


@dataclass(frozen=True)
class Gait:
    """A face-to-face rolling gait (``tensegrity_gym.tasks.gaits.FaceGait`` runs it;
    ``scripts/find_gait.py`` finds one): each contraction is held ``hold_steps``
    control steps, then the initial rest lengths ``settle_steps``; commands cross the
    motors' whole range in ``ramp_steps`` control steps (0: at once)."""

    faces: tuple[GaitFace, ...]
    hold_steps: int = 25
    settle_steps: int = 10
    ramp_steps: int = 0


@dataclass(frozen=True)
class RobotDescription:
    name: str
    gravity: float
    ground: Ground
    nodes: tuple[Node, ...]
    rods: tuple[Rod, ...]
    cables: tuple[Cable, ...]
    sensors: SensorSuite
    display_name: str = ""
    """The robot's name in its env ids (``ThreeBar`` in ``ThreeBarRoll-v0``); the YAML's
    ``display_name``, else ``name`` in CamelCase."""
    hardware: bool = False
    """The robot exists on the robot link: ``...Hardware-v0`` ids are registered for it."""
    gait: Gait | None = None
    """Its default scripted rolling gait ("forward"), if it has one (the YAML's ``gait``)."""
    named_gaits: tuple[tuple[str, Gait], ...] = ()
    """Its further scripted gaits, (name, gait) in the YAML's order (its ``gaits``), e.g.
    ``backward``, ``left``, ``right``. See :attr:`gaits`."""
    carries: tuple[str, ...] | None = None
    """The sample kinds (:data:`~tensegrity_gym.model.samples.SAMPLE_KINDS`) its sensors
    give, the YAML's ``carries``; None (absent): every kind. See :attr:`sample_kinds`."""
    source: str = field(default="", compare=False)
    """The file the description was read from."""

    @property
    def gaits(self) -> dict[str, Gait]:
        """Every scripted gait by name: :attr:`gait` under ``"forward"`` (where there is
        one), then :attr:`named_gaits`."""
        default = {} if self.gait is None else {DEFAULT_GAIT: self.gait}
        return default | dict(self.named_gaits)

    @property
    def sample_kinds(self) -> frozenset[str]:
        """The sample kinds the robot carries sensors for: ``carries``, else every kind
        of :data:`~tensegrity_gym.model.samples.SAMPLE_KINDS` (those a lab registered
        too). Not ``"ground_truth"``: motion capture is the lab's, not the robot's."""
        return frozenset(SAMPLE_KINDS if self.carries is None else self.carries)

    @cached_property
    def imu_rods(self) -> tuple[int, ...]:
        """The rods that carry an IMU (and its AHRS), by index: the YAML's
        ``sensors.imu.rods``, else every rod."""
        rods = self.sensors.imu.rods
        return tuple(range(self.n_rods)) if rods is None else rods

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_rods(self) -> int:
        return len(self.rods)

    @property
    def n_cables(self) -> int:
        return len(self.cables)

    @cached_property
    def actuated(self) -> NDArray[np.intp]:
        """Indices of the actuated cables, (m,)."""
        return np.array([k for k, c in enumerate(self.cables) if c.actuated], dtype=np.intp)

    @property
    def n_actuated(self) -> int:
        return len(self.actuated)

    @cached_property
    def cable_nodes(self) -> NDArray[np.intp]:
        """Node index pairs of the cables, (n_cables, 2)."""
        return np.array([c.nodes for c in self.cables], dtype=np.intp).reshape(-1, 2)

    @cached_property
    def rod_nodes(self) -> NDArray[np.intp]:
        """Node index pairs of the rods, (n_rods, 2)."""
        return np.array([r.nodes for r in self.rods], dtype=np.intp).reshape(-1, 2)

    @cached_property
    def node_rod(self) -> NDArray[np.intp]:
        """The rod each node belongs to, (n_nodes,)."""
        out = np.empty(self.n_nodes, dtype=np.intp)
        for k, rod in enumerate(self.rods):
            out[list(rod.nodes)] = k
        return out

    @cached_property
    def node_radii(self) -> NDArray[np.float64]:
        """Endcap radius at each node (m), (n_nodes,): a node is its endcap's centre."""
        out = np.zeros(self.n_nodes)
        for rod in self.rods:
            out[list(rod.nodes)] = rod.endcap_radius
        return out

    @cached_property
    def node_masses(self) -> NDArray[np.float64]:
        """Point masses at the nodes (kg), half a rod each, (n_nodes,)."""
        out = np.zeros(self.n_nodes)
        for rod in self.rods:
            out[list(rod.nodes)] += 0.5 * rod.mass
        return out

    @property
    def total_mass(self) -> float:
        return float(sum(r.mass for r in self.rods))

    @cached_property
    def initial_positions(self) -> NDArray[np.float64]:
        """Node positions of the resting pose (m), (n_nodes, 3)."""
        return np.array([n.position for n in self.nodes], dtype=np.float64)

    @cached_property
    def rest_lengths(self) -> NDArray[np.float64]:
        """Initial rest lengths of all cables (m), (n_cables,)."""
        return np.array([c.rest_length for c in self.cables], dtype=np.float64)

    @cached_property
    def motor_limits(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Minimum, maximum rest length (m) and speed (m/s) of the actuated cables, each (m,)."""
        motors = [c.motor for c in self.cables if c.motor is not None]
        return (
            np.array([m.min_rest_length for m in motors]),
            np.array([m.max_rest_length for m in motors]),
            np.array([m.max_speed for m in motors]),
        )

    @cached_property
    def motor_min_stretch(self) -> NDArray[np.float64]:
        """Each actuated cable's least stretch (m), (m,): its motor's ``min_tension`` over
        the cable's stiffness; NaN where the motor lets its cable go slack."""
        return np.array([
            np.nan if c.motor is None or c.motor.min_tension is None
            else c.motor.min_tension / c.stiffness
            for c in (self.cables[int(k)] for k in self.actuated)
        ])  # fmt: skip

    def outside_motor_range(
        self, rest_lengths: NDArray[np.float64], *, reading: bool = False
    ) -> int:
        """How many of the actuated rest lengths (m), (m,), lie outside their motor's
        range by more than one encoder step (a command or reading no motor could have).
        An encoder ``reading`` of a motor with a ``min_tension`` may lie below its range:
        it reels in slack wherever the endcaps come closer."""
        lo, hi, _ = self.motor_limits
        step = self.sensors.encoder.resolution
        x = np.asarray(rest_lengths, dtype=np.float64)
        short = x < lo - step
        if reading:
            short &= np.isnan(self.motor_min_stretch)
        return int(np.count_nonzero(short | (x > hi + step)))

    @property
    def anchors(self) -> NDArray[np.float64]:
        """Fixed UWB anchor positions (m), (n_anchors, 3)."""
        return np.array(self.sensors.uwb.anchors, dtype=np.float64).reshape(-1, 3)

    @property
    def characteristic_length(self) -> float:
        """Mean rod length (m): the scale of the robot."""
        return float(np.mean([r.length for r in self.rods]))


# ----------------------------------------------------------------------------- loading


class _Reader:
    """Walks a parsed YAML document and reports errors by file and field path."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, path: str, message: str) -> DescriptionError:
        return DescriptionError(f"{self.source}: {path}: {message}")

    def mapping(
        self, value: Any, path: str, keys: set[str], optional: frozenset[str] = frozenset()
    ) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(path, f"expected a mapping, got {type(value).__name__}")
        missing = sorted(keys - value.keys())
        if missing:
            raise self.fail(f"{path}.{missing[0]}" if path else missing[0], "missing field")
        unknown = sorted(set(value) - keys - optional)
        if unknown:
            raise self.fail(f"{path}.{unknown[0]}" if path else unknown[0], "unknown field")
        return value

    def sequence(self, value: Any, path: str, min_len: int = 1) -> list[Any]:
        if not isinstance(value, list):
            raise self.fail(path, f"expected a list, got {type(value).__name__}")
        if len(value) < min_len:
            raise self.fail(path, f"expected at least {min_len} entries, got {len(value)}")
        return value

    def number(
        self, value: Any, path: str, *, positive: bool = False, non_negative: bool = False
    ) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, f"expected a number, got {value!r}")
        x = float(value)
        if not np.isfinite(x):
            raise self.fail(path, f"must be finite, got {value!r}")
        if positive and x <= 0.0:
            raise self.fail(path, f"must be positive, got {value!r}")
        if non_negative and x < 0.0:
            raise self.fail(path, f"must not be negative, got {value!r}")
        return x

    def vector(self, value: Any, path: str, size: int, **kw: bool) -> tuple[float, ...]:
        items = self.sequence(value, path)
        if len(items) != size:
            raise self.fail(path, f"expected {size} numbers, got {len(items)}")
        return tuple(self.number(v, f"{path}[{i}]", **kw) for i, v in enumerate(items))

    def string(self, value: Any, path: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(path, f"expected a non-empty string, got {value!r}")
        return value

    def boolean(self, value: Any, path: str) -> bool:
        if not isinstance(value, bool):
            raise self.fail(path, f"expected true or false, got {value!r}")
        return value


def _node_pair(r: _Reader, value: Any, path: str, index: dict[str, int]) -> tuple[int, int]:
    names = r.sequence(value, path)
    if len(names) != 2:
        raise r.fail(path, f"expected two node names, got {len(names)}")
    out = []
    for i, name in enumerate(names):
        r.string(name, f"{path}[{i}]")
        if name not in index:
            raise r.fail(f"{path}[{i}]", f"unknown node {name!r}")
        out.append(index[name])
    if out[0] == out[1]:
        raise r.fail(path, f"both ends are node {names[0]!r}")
    return out[0], out[1]


def _sensors(r: _Reader, doc: Any, rods: list[Rod]) -> SensorSuite:
    p = "sensors"
    s = r.mapping(doc, p, {"imu", "encoder", "cable_length", "uwb", "contact", "camera"})
    imu_cfg = _imu(r, s["imu"], f"{p}.imu", rods)
    enc = r.mapping(s["encoder"], f"{p}.encoder", {"rate", "resolution"})
    enc_cfg = EncoderConfig(
        rate=r.number(enc["rate"], f"{p}.encoder.rate", positive=True),
        resolution=r.number(enc["resolution"], f"{p}.encoder.resolution", non_negative=True),
    )
    cl = r.mapping(s["cable_length"], f"{p}.cable_length", {"rate", "noise", "slack_bias"})
    cl_cfg = CableLengthConfig(
        rate=r.number(cl["rate"], f"{p}.cable_length.rate", positive=True),
        noise=r.number(cl["noise"], f"{p}.cable_length.noise", non_negative=True),
        slack_bias=r.number(cl["slack_bias"], f"{p}.cable_length.slack_bias", non_negative=True),
    )
    uwb_cfg = _uwb(r, s["uwb"], f"{p}.uwb")
    ct = r.mapping(s["contact"], f"{p}.contact", {"rate", "threshold"})
    ct_cfg = ContactConfig(
        rate=r.number(ct["rate"], f"{p}.contact.rate", positive=True),
        threshold=r.number(ct["threshold"], f"{p}.contact.threshold", non_negative=True),
    )
    cam_cfg = _camera(r, s["camera"], f"{p}.camera")
    return SensorSuite(imu_cfg, enc_cfg, cl_cfg, uwb_cfg, ct_cfg, cam_cfg)


def _imu(r: _Reader, doc: Any, q: str, rods: list[Rod]) -> ImuConfig:
    """The IMU section at path ``q``; rods named by ``rods``' names."""
    imu = r.mapping(
        doc,
        q,
        {"rate", "mount", "accel_noise", "gyro_noise", "accel_bias", "gyro_bias", "mag_noise",
         "magnetic_field", "ahrs_gain"},
        frozenset({"accel_full_scale", "gyro_full_scale", "rods"}),
    )  # fmt: skip
    if imu["mount"] != "rod_centre":
        raise r.fail(f"{q}.mount", f"only 'rod_centre' is supported, got {imu['mount']!r}")
    return ImuConfig(
        rate=r.number(imu["rate"], f"{q}.rate", positive=True),
        mount=imu["mount"],
        accel_noise=r.number(imu["accel_noise"], f"{q}.accel_noise", non_negative=True),
        gyro_noise=r.number(imu["gyro_noise"], f"{q}.gyro_noise", non_negative=True),
        accel_bias=r.number(imu["accel_bias"], f"{q}.accel_bias", non_negative=True),
        gyro_bias=r.number(imu["gyro_bias"], f"{q}.gyro_bias", non_negative=True),
        mag_noise=r.number(imu["mag_noise"], f"{q}.mag_noise", non_negative=True),
        magnetic_field=r.vector(imu["magnetic_field"], f"{q}.magnetic_field", 3),  # type: ignore[arg-type]
        ahrs_gain=r.number(imu["ahrs_gain"], f"{q}.ahrs_gain", positive=True),
        **{
            key: r.number(imu[key], f"{q}.{key}", positive=True)
            for key in ("accel_full_scale", "gyro_full_scale")
            if key in imu
        },
        rods=None if imu.get("rods") is None else _names(
            r, imu["rods"], f"{q}.rods", {rod.name: k for k, rod in enumerate(rods)}
        ),
    )  # fmt: skip


def _uwb(r: _Reader, doc: Any, q: str) -> UwbConfig:
    """The UWB section at path ``q``."""
    uwb = r.mapping(
        doc,
        q,
        {"rate", "packet_spacing", "module_offset", "timestamp_noise", "clock_drift_ppm",
         "offset_mean", "offset_std", "reject_fraction", "anchors"},
    )  # fmt: skip
    reject = r.vector(uwb["reject_fraction"], f"{q}.reject_fraction", 2, non_negative=True)
    if not reject[0] <= reject[1] < 1.0:
        raise r.fail(f"{q}.reject_fraction", f"need 0 <= low <= high < 1, got {list(reject)}")
    anchors = r.sequence(uwb["anchors"], f"{q}.anchors", min_len=0)
    uwb_cfg = UwbConfig(
        rate=r.number(uwb["rate"], f"{q}.rate", positive=True),
        packet_spacing=r.number(uwb["packet_spacing"], f"{q}.packet_spacing", positive=True),
        module_offset=r.number(uwb["module_offset"], f"{q}.module_offset", non_negative=True),
        timestamp_noise=r.number(uwb["timestamp_noise"], f"{q}.timestamp_noise", non_negative=True),
        clock_drift_ppm=r.number(uwb["clock_drift_ppm"], f"{q}.clock_drift_ppm", non_negative=True),
        offset_mean=r.number(uwb["offset_mean"], f"{q}.offset_mean"),
        offset_std=r.number(uwb["offset_std"], f"{q}.offset_std", non_negative=True),
        reject_fraction=(reject[0], reject[1]),
        anchors=tuple(
            r.vector(a, f"{q}.anchors[{i}]", 3)  # type: ignore[misc]
            for i, a in enumerate(anchors)
        ),
    )
    if 1.0 / uwb_cfg.rate < uwb_cfg.packet_spacing:
        raise r.fail(f"{q}.packet_spacing", "longer than one broadcast round")
    return uwb_cfg


def _camera(r: _Reader, doc: Any, q: str) -> CameraConfig:
    """The RGB-D camera section at path ``q``."""
    cam = r.mapping(
        doc,
        q,
        {"position", "target", "up", "width", "height", "vertical_fov", "near", "far", "rate",
         "depth_noise", "depth_noise_quadratic"},
    )  # fmt: skip
    for key in ("width", "height"):
        if not isinstance(cam[key], int) or isinstance(cam[key], bool) or cam[key] <= 0:
            raise r.fail(f"{q}.{key}", f"expected a positive integer, got {cam[key]!r}")
    cam_cfg = CameraConfig(
        position=r.vector(cam["position"], f"{q}.position", 3),  # type: ignore[arg-type]
        target=r.vector(cam["target"], f"{q}.target", 3),  # type: ignore[arg-type]
        up=r.vector(cam["up"], f"{q}.up", 3),  # type: ignore[arg-type]
        width=cam["width"],
        height=cam["height"],
        vertical_fov=r.number(cam["vertical_fov"], f"{q}.vertical_fov", positive=True),
        near=r.number(cam["near"], f"{q}.near", positive=True),
        far=r.number(cam["far"], f"{q}.far", positive=True),
        rate=r.number(cam["rate"], f"{q}.rate", positive=True),
        depth_noise=r.number(cam["depth_noise"], f"{q}.depth_noise", non_negative=True),
        depth_noise_quadratic=r.number(
            cam["depth_noise_quadratic"], f"{q}.depth_noise_quadratic", non_negative=True
        ),
    )
    if cam_cfg.far <= cam_cfg.near:
        raise r.fail(f"{q}.far", "must be greater than near")
    return cam_cfg


def _names(r: _Reader, value: Any, path: str, index: dict[str, int]) -> tuple[int, ...]:
    """Distinct names, each a key of ``index``, as their indices."""
    out: list[int] = []
    for i, name in enumerate(r.sequence(value, path)):
        r.string(name, f"{path}[{i}]")
        if name not in index:
            raise r.fail(f"{path}[{i}]", f"unknown name {name!r}; valid: {sorted(index)}")
        if index[name] in out:
            raise r.fail(f"{path}[{i}]", f"{name!r} is named twice")
        out.append(index[name])
    return tuple(out)


def _gait(r: _Reader, doc: Any, nodes: list[Node], cables: list[Cable], p: str = "gait") -> Gait:
    """A gait section at path ``p`` (``gait``, ``gaits.NAME``): faces by node names,
    cables by name (actuated only)."""
    g = r.mapping(doc, p, {"faces"}, frozenset({"hold_steps", "settle_steps", "ramp_steps"}))
    steps = {"hold_steps": 25, "settle_steps": 10, "ramp_steps": 0}
    for key, low in (("hold_steps", 1), ("settle_steps", 0), ("ramp_steps", 0)):
        value = g.get(key, steps[key])
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise r.fail(f"{p}.{key}", f"expected an integer >= {low}, got {value!r}")
        steps[key] = value
    if steps["ramp_steps"] > steps["hold_steps"]:
        raise r.fail(
            f"{p}.ramp_steps",
            f"expected at most hold_steps ({steps['hold_steps']}): a ramp longer than the "
            f"hold never reaches its contraction, got {steps['ramp_steps']}",
        )
    node_index = {n.name: i for i, n in enumerate(nodes)}
    actuated = {c.name: k for k, c in enumerate(c for c in cables if c.actuated)}
    faces: list[GaitFace] = []
    for i, item in enumerate(r.sequence(g["faces"], f"{p}.faces")):
        q = f"{p}.faces[{i}]"
        f = r.mapping(item, q, {"face", "contract", "others"}, frozenset({"move", "to"}))
        face = _face(r, f["face"], f"{q}.face", node_index)
        move = None if "move" not in f else _move(r.vector(f["move"], f"{q}.move", 3))
        to = None if "to" not in f else _face(r, f["to"], f"{q}.to", node_index)
        if (move is None) != (to is None):
            missing = "to" if to is None else "move"
            raise r.fail(f"{q}.{missing}", "missing: a steering entry gives both 'move' "
                         "and 'to', or neither")  # fmt: skip
        if to is not None and to == face:
            raise r.fail(f"{q}.to", "a move leads to another face than its own")
        if any(face == o.face and (move is None or o.move is None) for o in faces):
            raise r.fail(f"{q}.face", "this face has an entry already (only steering "
                         "entries, with 'move' and 'to', may share a face)")  # fmt: skip
        contract = _names(r, f["contract"], f"{q}.contract", actuated)
        if f["others"] not in ("hold", "out"):
            raise r.fail(f"{q}.others", f"expected 'hold' or 'out', got {f['others']!r}")
        faces.append(GaitFace(face, contract, f["others"], move, to))
    return Gait(tuple(faces), **steps)


def _move(v: tuple[float, ...]) -> tuple[float, float, float]:
    return v[0], v[1], v[2]


def _face(r: _Reader, value: Any, path: str, node_index: dict[str, int]) -> tuple[int, ...]:
    """A support face by node names: its sorted node indices, (3,)."""
    face = tuple(sorted(_names(r, value, path, node_index)))
    if len(face) != 3:
        raise r.fail(path, f"a support face has 3 nodes, got {len(face)}")
    return face


def _gaits(
    r: _Reader, top: dict[str, Any], nodes: list[Node], cables: list[Cable]
) -> tuple[tuple[str, Gait], ...]:
    """The YAML's ``gaits``: further gaits by name (lower-case words), each a ``gait``
    section; ``forward`` is the ``gait`` section's name and cannot be one of them."""
    doc = top.get("gaits")
    if doc is None:
        return ()
    if not isinstance(doc, dict) or not doc:
        raise r.fail("gaits", f"expected a mapping of gaits by name, got {doc!r}")
    out: list[tuple[str, Gait]] = []
    for name, section in doc.items():
        if not isinstance(name, str) or not _GAIT_NAME.match(name):
            raise r.fail(f"gaits.{name}", "a gait's name is a lower-case word such as 'left'")
        if name == DEFAULT_GAIT:
            raise r.fail(f"gaits.{name}", f"the {DEFAULT_GAIT!r} gait is the 'gait' section")
        out.append((name, _gait(r, section, nodes, cables, f"gaits.{name}")))
    return tuple(out)


def _display_name(r: _Reader, top: dict[str, Any]) -> str:
    """The YAML's ``display_name`` (CamelCase, for env ids), else ``name`` in CamelCase."""
    name = top.get("display_name")
    if name is None:
        return "".join(part.capitalize() for part in str(top["name"]).split("_"))
    if not isinstance(name, str) or not _DISPLAY_NAME.match(name):
        raise r.fail("display_name", f"expected a CamelCase word such as 'ThreeBar', got {name!r}")
    return name


def _ground(r: _Reader, doc: Any) -> Ground:
    """The ``ground`` section: friction coefficients (rolling and spinning in m)."""
    keys = ("lateral_friction", "rolling_friction", "spinning_friction", "restitution")
    g = r.mapping(doc, "ground", set(keys))
    return Ground(*(r.number(g[key], f"ground.{key}", non_negative=True) for key in keys))


def _nodes(r: _Reader, doc: Any) -> tuple[list[Node], dict[str, int]]:
    """The ``nodes`` section (positions in m), and each node's index by name."""
    nodes: list[Node] = []
    index: dict[str, int] = {}
    for i, item in enumerate(r.sequence(doc, "nodes", min_len=2)):
        n = r.mapping(item, f"nodes[{i}]", {"name", "position"})
        name = r.string(n["name"], f"nodes[{i}].name")
        if name in index:
            raise r.fail(f"nodes[{i}].name", f"duplicate node name {name!r}")
        index[name] = i
        pos = r.vector(n["position"], f"nodes[{i}].position", 3)
        nodes.append(Node(name, (pos[0], pos[1], pos[2])))
    return nodes, index


def _rods(
    r: _Reader, doc: Any, nodes: list[Node], index: dict[str, int]
) -> tuple[list[Rod], dict[int, str]]:
    """The ``rods`` section, checked to assemble with ``nodes`` (each node ends exactly
    one rod, at the rod's length in m), and the name of the rod each node ends."""
    positions = np.array([n.position for n in nodes])
    rods: list[Rod] = []
    owner: dict[int, str] = {}
    rod_keys = {"name", "nodes", "length", "radius", "endcap_radius", "mass", "color"}
    for i, item in enumerate(r.sequence(doc, "rods")):
        p = f"rods[{i}]"
        d = r.mapping(item, p, rod_keys)
        name = r.string(d["name"], f"{p}.name")
        pair = _node_pair(r, d["nodes"], f"{p}.nodes", index)
        for k, node in enumerate(pair):
            if node in owner:
                raise r.fail(
                    f"{p}.nodes[{k}]",
                    f"rods cannot be assembled: node {nodes[node].name!r} already ends rod "
                    f"{owner[node]!r}",
                )
            owner[node] = name
        length = r.number(d["length"], f"{p}.length", positive=True)
        gap = float(np.linalg.norm(positions[pair[1]] - positions[pair[0]]))
        if abs(gap - length) > _ASSEMBLY_TOLERANCE * length:
            raise r.fail(
                f"{p}.length",
                f"rods cannot be assembled: nodes {nodes[pair[0]].name!r} and "
                f"{nodes[pair[1]].name!r} are {gap:.4f} m apart but the rod is {length:.4f} m long",
            )
        radius = r.number(d["radius"], f"{p}.radius", positive=True)
        endcap = r.number(d["endcap_radius"], f"{p}.endcap_radius", positive=True)
        if 2.0 * endcap >= length:
            raise r.fail(f"{p}.endcap_radius", "endcaps overlap: twice the radius exceeds length")
        color = r.vector(d["color"], f"{p}.color", 4, non_negative=True)
        rods.append(
            Rod(
                name=name,
                nodes=pair,
                length=length,
                radius=radius,
                endcap_radius=endcap,
                mass=r.number(d["mass"], f"{p}.mass", positive=True),
                color=(color[0], color[1], color[2], color[3]),
            )
        )
    loose = [nodes[k].name for k in range(len(nodes)) if k not in owner]
    if loose:
        raise r.fail("rods", f"rods cannot be assembled: node {loose[0]!r} ends no rod")
    return rods, owner


def _motor(r: _Reader, doc: Any, p: str, rest: float) -> Motor:
    """The ``motor`` of the actuated cable at path ``p``, whose range (m) must hold its
    initial rest length ``rest`` (m)."""
    m = r.mapping(
        doc,
        f"{p}.motor",
        {"min_rest_length", "max_rest_length", "max_speed"},
        frozenset({"min_tension"}),
    )
    lo = r.number(m["min_rest_length"], f"{p}.motor.min_rest_length", positive=True)
    hi = r.number(m["max_rest_length"], f"{p}.motor.max_rest_length", positive=True)
    if hi <= lo:
        raise r.fail(
            f"{p}.motor.max_rest_length",
            f"{hi} must exceed min_rest_length {lo}: a motor needs a range to move in",
        )
    if not lo <= rest <= hi:
        raise r.fail(f"{p}.rest_length", f"{rest} lies outside the motor's range [{lo}, {hi}]")
    speed = r.number(m["max_speed"], f"{p}.motor.max_speed", positive=True)
    tension = m.get("min_tension")
    if tension is not None:
        tension = r.number(tension, f"{p}.motor.min_tension", positive=True)
    return Motor(lo, hi, speed, tension)


def _cables(r: _Reader, doc: Any, index: dict[str, int], owner: dict[int, str]) -> list[Cable]:
    """The ``cables`` section: each joins two rods (``owner``: node -> its rod's name),
    and at least one is actuated."""
    cables: list[Cable] = []
    cable_keys = {"name", "nodes", "stiffness", "damping", "rest_length", "actuated"}
    for i, item in enumerate(r.sequence(doc, "cables")):
        p = f"cables[{i}]"
        if not isinstance(item, dict):
            raise r.fail(p, f"expected a mapping, got {type(item).__name__}")
        actuated = (
            r.boolean(item.get("actuated", None), f"{p}.actuated") if "actuated" in item else None
        )
        if actuated is None:
            raise r.fail(f"{p}.actuated", "missing field")
        d = r.mapping(item, p, cable_keys | ({"motor"} if actuated else set()))
        pair = _node_pair(r, d["nodes"], f"{p}.nodes", index)
        if owner[pair[0]] == owner[pair[1]]:
            raise r.fail(f"{p}.nodes", f"both ends are on rod {owner[pair[0]]!r}")
        rest = r.number(d["rest_length"], f"{p}.rest_length", positive=True)
        motor = _motor(r, d["motor"], p, rest) if actuated else None
        cables.append(
            Cable(
                name=r.string(d["name"], f"{p}.name"),
                nodes=pair,
                stiffness=r.number(d["stiffness"], f"{p}.stiffness", positive=True),
                damping=r.number(d["damping"], f"{p}.damping", non_negative=True),
                rest_length=rest,
                actuated=actuated,
                motor=motor,
            )
        )
    if not any(c.actuated for c in cables):
        raise r.fail("cables", "no cable is actuated")
    return cables


def _carries(r: _Reader, top: dict[str, Any]) -> tuple[str, ...] | None:
    """The YAML's ``carries``: distinct names of :data:`SAMPLE_KINDS`, in that table's
    order; None where it is absent (the robot carries every kind)."""
    if top.get("carries") is None:
        return None
    index = {kind: i for i, kind in enumerate(SAMPLE_KINDS)}
    kinds = list(index)
    return tuple(kinds[i] for i in sorted(_names(r, top["carries"], "carries", index)))


def parse_robot(doc: Any, source: str) -> RobotDescription:
    """Validate a parsed YAML document and build the description from it."""
    r = _Reader(source)
    top = r.mapping(
        doc,
        "",
        {"name", "gravity", "ground", "nodes", "rods", "cables", "sensors"},
        frozenset({"display_name", "hardware", "gait", "gaits", "carries"}),
    )
    ground = _ground(r, top["ground"])
    nodes, index = _nodes(r, top["nodes"])
    rods, owner = _rods(r, top["rods"], nodes, index)
    cables = _cables(r, top["cables"], index, owner)
    return RobotDescription(
        name=r.string(top["name"], "name"),
        gravity=r.number(top["gravity"], "gravity", non_negative=True),
        ground=ground,
        nodes=tuple(nodes),
        rods=tuple(rods),
        cables=tuple(cables),
        sensors=_sensors(r, top["sensors"], rods),
        display_name=_display_name(r, top),
        hardware=r.boolean(top.get("hardware", False), "hardware"),
        gait=None if top.get("gait") is None else _gait(r, top["gait"], nodes, cables),
        named_gaits=_gaits(r, top, nodes, cables),
        carries=_carries(r, top),
        source=source,
    )


def robot_document(d: RobotDescription) -> dict[str, Any]:
    """The YAML document of a description: :func:`parse_robot` of it gives ``d`` back."""

    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (tuple, list)):
            return [plain(v) for v in value]
        return value

    names = [n.name for n in d.nodes]
    return {
        "name": d.name,
        "display_name": d.display_name,
        "hardware": d.hardware,
        "gravity": d.gravity,
        "ground": plain(asdict(d.ground)),
        "nodes": [{"name": n.name, "position": list(n.position)} for n in d.nodes],
        "rods": [
            {
                "name": rod.name,
                "nodes": [names[i] for i in rod.nodes],
                "length": rod.length,
                "radius": rod.radius,
                "endcap_radius": rod.endcap_radius,
                "mass": rod.mass,
                "color": list(rod.color),
            }
            for rod in d.rods
        ],
        "cables": [
            {
                "name": c.name,
                "nodes": [names[i] for i in c.nodes],
                "stiffness": c.stiffness,
                "damping": c.damping,
                "rest_length": c.rest_length,
                "actuated": c.actuated,
            }
            | ({} if c.motor is None else {"motor": _motor_document(c.motor)})
            for c in d.cables
        ],
        "sensors": _imu_rods_named(d, plain(asdict(d.sensors))),
        **({} if d.carries is None else {"carries": list(d.carries)}),
    } | _gait_sections(d)


def _imu_rods_named(d: RobotDescription, doc: dict[str, Any]) -> dict[str, Any]:
    """The ``sensors`` section ``doc`` with the IMU's ``rods`` by name, only where not
    every rod carries one."""
    rods = doc["imu"].pop("rods")
    if rods is not None:
        doc["imu"]["rods"] = [d.rods[k].name for k in rods]
    return doc


def _motor_document(motor: Motor) -> dict[str, Any]:
    """A motor's YAML section; ``min_tension`` only where it has one."""
    doc = asdict(motor)
    if motor.min_tension is None:
        del doc["min_tension"]
    return doc


def _gait_sections(d: RobotDescription) -> dict[str, Any]:
    """The YAML's ``gait`` and ``gaits`` sections, those the description has."""
    out = {} if d.gait is None else {"gait": gait_document(d)}
    if d.named_gaits:
        out["gaits"] = {name: gait_document(d, name) for name, _ in d.named_gaits}
    return out


def gait_document(d: RobotDescription, name: str = DEFAULT_GAIT) -> dict[str, Any]:
    """The YAML section of the description's gait ``name`` (see
    :attr:`RobotDescription.gaits`), by names; ValueError if it has no such gait."""
    gait = d.gaits.get(name)
    if gait is None:
        raise ValueError(f"robot {d.name!r} has no gait {name!r}; its gaits: {sorted(d.gaits)}")
    actuated = [d.cables[int(k)].name for k in d.actuated]
    return {
        "hold_steps": gait.hold_steps,
        "settle_steps": gait.settle_steps,
        **({"ramp_steps": gait.ramp_steps} if gait.ramp_steps else {}),
        "faces": [
            {
                "face": [d.nodes[i].name for i in f.face],
                "contract": [actuated[k] for k in f.contract],
                "others": f.others,
                **(
                    {}
                    if f.move is None or f.to is None
                    else {"move": list(f.move), "to": [d.nodes[i].name for i in f.to]}
                ),
            }
            for f in gait.faces
        ],
    }


def dump_robot(d: RobotDescription) -> str:
    """The description as YAML text, e.g. to travel with a recording."""
    return str(yaml.safe_dump(robot_document(d), sort_keys=False))


def loads_robot(text: str, source: str = "<text>") -> RobotDescription:
    """A description from YAML text; errors name ``source`` and the field."""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise DescriptionError(f"{source}: not valid YAML: {yaml_problem(err)}") from None
    return parse_robot(doc, source)


def load_robot(name_or_path: str | Path) -> RobotDescription:
    """Load a preset by name (see :data:`PRESETS`) or a description from a YAML file.

    Raises:
        DescriptionError: the file is missing, not YAML, or malformed; the message names
            the file and the field.
    """
    text: str
    if isinstance(name_or_path, str) and name_or_path in PRESETS:
        asset = resources.files("tensegrity_gym.model") / "assets" / f"{name_or_path}.yaml"
        source = str(asset)
        text = asset.read_text()
    else:
        path = Path(name_or_path)
        source = str(path)
        if not path.is_file():
            raise DescriptionError(f"{source}: no such file (presets are {', '.join(PRESETS)})")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as err:
            raise DescriptionError(
                f"{source}: not valid YAML: not UTF-8 text (byte {err.object[err.start]:#04x} "
                f"at offset {err.start})"
            ) from None
        except OSError as err:
            raise DescriptionError(f"{source}: cannot be read: {err}") from err
    return loads_robot(text, source)
