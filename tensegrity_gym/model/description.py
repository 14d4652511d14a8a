"""The robot description: one frozen dataclass tree per robot, loaded from YAML.

This module, with its YAML's schema (:mod:`tensegrity_gym.model.schema`), is the only
place that parses robot geometry. The simulator builds its bodies from a
:class:`RobotDescription`, the estimators build their models from it and the hardware
driver maps topics to cables and rods with it.

Conventions: SI units, world frame z up. A rod's ``length`` is the distance between
its two endcap (node) centres; its overall length is ``length + 2 * endcap_radius``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
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

    from tensegrity_gym.model.schema import (
        CableSection,
        CameraSection,
        GaitSection,
        MotorSection,
        NodeSection,
        RobotSection,
        RodSection,
        SensorsSection,
        UwbSection,
    )

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

    @property
    def inertia(self) -> tuple[float, float, float]:
        """Principal moments of inertia (kg m^2) about the rod's centre, in its frame
        (z along the rod): a solid cylinder's, ``m (3 r^2 + L^2) / 12`` across and
        ``m r^2 / 2`` along. The endcaps' own share is left out, as the description
        gives one mass per rod."""
        m, r, length = self.mass, self.radius, self.length
        across = m * (3.0 * r * r + length * length) / 12.0
        return across, across, 0.5 * m * r * r


@dataclass(frozen=True)
class Motor:
    min_rest_length: float
    max_rest_length: float
    max_speed: float
    """Largest rate of change of the rest length (m/s)."""
    min_tension: float | None = None
    """N, optional in YAML: the motor keeps at least this tension on its cable, reeling in
    any slack (Tong et al. 2024's robot: "the motors are controlled to apply a minimum torque,
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
    (absent): every rod. Tong et al. 2024's robot has one, on its red rod."""


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
    """Mean of the per-pair ranging offsets o_ij (m), Caluwaerts et al. 2016 eq. 6-7."""
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
    flying_pixels: float = 0.0
    """Share of the pixels on the near side of a depth edge that read a depth between the
    near surface and the far one behind it, keeping the near one's colour: a real depth
    sensor's mixed ("flying") pixels on silhouettes. 0 on the presets."""

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
    """The robot exists on the robot link: ids in the ``tensegrity_gym_hardware``
    namespace are registered for it."""
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

    def with_rod_length(self, rod: int, length: float) -> RobotDescription:
        """This description with rod ``rod``'s length set to ``length`` (m), its two
        nodes moved along the rod, about its centre, to match: a description that
        assembles (and so loads again once written) as the one it came from."""
        r = self.rods[rod]
        a, b = r.nodes
        ends = self.initial_positions[[a, b]]
        centre, half = ends.mean(axis=0), 0.5 * (ends[1] - ends[0])
        half *= length / (2.0 * float(np.linalg.norm(half)))
        nodes = list(self.nodes)
        for node, end in ((a, centre - half), (b, centre + half)):
            nodes[node] = replace(nodes[node], position=_vec3(tuple(end.tolist())))
        rods = list(self.rods)
        rods[rod] = replace(r, length=length)
        return replace(self, nodes=tuple(nodes), rods=tuple(rods))


# ----------------------------------------------------------------------------- loading


class _Reader:
    """Names the file and the field of what is wrong with a description."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, path: str, message: str) -> DescriptionError:
        """The error ``message`` about the field at dotted ``path`` (``""``: the document)."""
        return DescriptionError(
            f"{self.source}: {path}: {message}" if path else f"{self.source}: {message}"
        )


def _validated(r: _Reader, doc: Any) -> RobotSection:
    """The parsed YAML document checked field by field (types, ranges, keys) against the
    schema's models; the first problem, if any, as a :class:`DescriptionError`."""
    from pydantic import ValidationError

    from tensegrity_gym.model.schema import RobotSection, error_field

    try:
        return RobotSection.model_validate(doc)
    except ValidationError as err:
        path, message = error_field(err.errors(include_url=False)[0])
        raise r.fail(path, message) from None


def _vec3(v: tuple[float, ...]) -> tuple[float, float, float]:
    """A vector the schema gave three numbers."""
    return v[0], v[1], v[2]


def _names(r: _Reader, names: tuple[str, ...], path: str, index: dict[str, int]) -> tuple[int, ...]:
    """Distinct names, each a key of ``index``, as their indices."""
    out: list[int] = []
    for i, name in enumerate(names):
        if name not in index:
            raise r.fail(f"{path}[{i}]", f"unknown name {name!r}; valid: {sorted(index)}")
        if index[name] in out:
            raise r.fail(f"{path}[{i}]", f"{name!r} is named twice")
        out.append(index[name])
    return tuple(out)


def _node_pair(
    r: _Reader, names: tuple[str, ...], path: str, index: dict[str, int]
) -> tuple[int, int]:
    """Two node names (the schema gave two) as their indices, distinct."""
    out = []
    for i, name in enumerate(names):
        if name not in index:
            raise r.fail(f"{path}[{i}]", f"unknown node {name!r}")
        out.append(index[name])
    if out[0] == out[1]:
        raise r.fail(path, f"both ends are node {names[0]!r}")
    return out[0], out[1]


def _sensors(r: _Reader, s: SensorsSection, rods: list[Rod]) -> SensorSuite:
    """The ``sensors`` section; the IMU's rods named by ``rods``' names."""
    imu_rods = None
    if s.imu.rods is not None:
        imu_rods = _names(
            r, s.imu.rods, "sensors.imu.rods", {rod.name: k for k, rod in enumerate(rods)}
        )
    return SensorSuite(
        imu=ImuConfig(**(s.imu.model_dump() | {"rods": imu_rods})),
        encoder=EncoderConfig(**s.encoder.model_dump()),
        cable_length=CableLengthConfig(**s.cable_length.model_dump()),
        uwb=_uwb(r, s.uwb, "sensors.uwb"),
        contact=ContactConfig(**s.contact.model_dump()),
        camera=_camera(r, s.camera, "sensors.camera"),
    )


def _uwb(r: _Reader, uwb: UwbSection, q: str) -> UwbConfig:
    """The UWB section at path ``q``: its rejected shares in order, its packets in a round."""
    low, high = uwb.reject_fraction
    if not low <= high < 1.0:
        raise r.fail(f"{q}.reject_fraction", f"need 0 <= low <= high < 1, got {[low, high]}")
    if 1.0 / uwb.rate < uwb.packet_spacing:
        raise r.fail(f"{q}.packet_spacing", "longer than one broadcast round")
    return UwbConfig(**uwb.model_dump())


def _camera(r: _Reader, cam: CameraSection, q: str) -> CameraConfig:
    """The RGB-D camera section at path ``q``: its far plane beyond its near one."""
    if cam.far <= cam.near:
        raise r.fail(f"{q}.far", "must be greater than near")
    return CameraConfig(**cam.model_dump())


def _gait(
    r: _Reader, g: GaitSection, nodes: list[Node], cables: list[Cable], p: str = "gait"
) -> Gait:
    """A gait section at path ``p`` (``gait``, ``gaits.NAME``): faces by node names,
    cables by name (actuated only)."""
    if g.ramp_steps > g.hold_steps:
        raise r.fail(
            f"{p}.ramp_steps",
            f"expected at most hold_steps ({g.hold_steps}): a ramp longer than the "
            f"hold never reaches its contraction, got {g.ramp_steps}",
        )
    node_index = {n.name: i for i, n in enumerate(nodes)}
    actuated = {c.name: k for k, c in enumerate(c for c in cables if c.actuated)}
    faces: list[GaitFace] = []
    for i, f in enumerate(g.faces):
        q = f"{p}.faces[{i}]"
        face = _face(r, f.face, f"{q}.face", node_index)
        move = None if f.move is None else _vec3(f.move)
        to = None if f.to is None else _face(r, f.to, f"{q}.to", node_index)
        if (move is None) != (to is None):
            missing = "to" if to is None else "move"
            raise r.fail(f"{q}.{missing}", "missing: a steering entry gives both 'move' "
                         "and 'to', or neither")  # fmt: skip
        if to is not None and to == face:
            raise r.fail(f"{q}.to", "a move leads to another face than its own")
        if any(face == o.face and (move is None or o.move is None) for o in faces):
            raise r.fail(f"{q}.face", "this face has an entry already (only steering "
                         "entries, with 'move' and 'to', may share a face)")  # fmt: skip
        contract = _names(r, f.contract, f"{q}.contract", actuated)
        faces.append(GaitFace(face, contract, f.others, move, to))
    return Gait(tuple(faces), g.hold_steps, g.settle_steps, g.ramp_steps)


def _face(
    r: _Reader, names: tuple[str, ...], path: str, node_index: dict[str, int]
) -> tuple[int, ...]:
    """A support face by node names (the schema gave three): its sorted node indices."""
    return tuple(sorted(_names(r, names, path, node_index)))


def _gaits(
    r: _Reader, top: RobotSection, nodes: list[Node], cables: list[Cable]
) -> tuple[tuple[str, Gait], ...]:
    """The YAML's ``gaits``: further gaits by name (lower-case words), each a ``gait``
    section; ``forward`` is the ``gait`` section's name and cannot be one of them."""
    if top.gaits is None:
        return ()
    out: list[tuple[str, Gait]] = []
    for name, section in top.gaits.items():
        if name == DEFAULT_GAIT:
            raise r.fail(f"gaits.{name}", f"the {DEFAULT_GAIT!r} gait is the 'gait' section")
        out.append((name, _gait(r, section, nodes, cables, f"gaits.{name}")))
    return tuple(out)


def _display_name(top: RobotSection) -> str:
    """The YAML's ``display_name`` (CamelCase, for env ids), else ``name`` in CamelCase."""
    if top.display_name is not None:
        return top.display_name
    return "".join(part.capitalize() for part in top.name.split("_"))


def _nodes(r: _Reader, sections: tuple[NodeSection, ...]) -> tuple[list[Node], dict[str, int]]:
    """The ``nodes`` section (positions in m), and each node's index by name."""
    nodes: list[Node] = []
    index: dict[str, int] = {}
    for i, n in enumerate(sections):
        if n.name in index:
            raise r.fail(f"nodes[{i}].name", f"duplicate node name {n.name!r}")
        index[n.name] = i
        nodes.append(Node(n.name, _vec3(n.position)))
    return nodes, index


def _rods(
    r: _Reader, sections: tuple[RodSection, ...], nodes: list[Node], index: dict[str, int]
) -> tuple[list[Rod], dict[int, str]]:
    """The ``rods`` section, checked to assemble with ``nodes`` (each node ends exactly
    one rod, at the rod's length in m), and the name of the rod each node ends."""
    positions = np.array([n.position for n in nodes])
    rods: list[Rod] = []
    owner: dict[int, str] = {}
    for i, d in enumerate(sections):
        p = f"rods[{i}]"
        pair = _node_pair(r, d.nodes, f"{p}.nodes", index)
        for k, node in enumerate(pair):
            if node in owner:
                raise r.fail(
                    f"{p}.nodes[{k}]",
                    f"rods cannot be assembled: node {nodes[node].name!r} already ends rod "
                    f"{owner[node]!r}",
                )
            owner[node] = d.name
        gap = float(np.linalg.norm(positions[pair[1]] - positions[pair[0]]))
        if abs(gap - d.length) > _ASSEMBLY_TOLERANCE * d.length:
            raise r.fail(
                f"{p}.length",
                f"rods cannot be assembled: nodes {nodes[pair[0]].name!r} and "
                f"{nodes[pair[1]].name!r} are {gap:.4f} m apart but the rod is "
                f"{d.length:.4f} m long",
            )
        if 2.0 * d.endcap_radius >= d.length:
            raise r.fail(f"{p}.endcap_radius", "endcaps overlap: twice the radius exceeds length")
        color = (d.color[0], d.color[1], d.color[2], d.color[3])
        rods.append(Rod(d.name, pair, d.length, d.radius, d.endcap_radius, d.mass, color))
    loose = [nodes[k].name for k in range(len(nodes)) if k not in owner]
    if loose:
        raise r.fail("rods", f"rods cannot be assembled: node {loose[0]!r} ends no rod")
    return rods, owner


def _motor(r: _Reader, m: MotorSection, p: str, rest: float) -> Motor:
    """The ``motor`` of the actuated cable at path ``p``, whose range (m) must hold its
    initial rest length ``rest`` (m)."""
    lo, hi = m.min_rest_length, m.max_rest_length
    if hi <= lo:
        raise r.fail(
            f"{p}.motor.max_rest_length",
            f"{hi} must exceed min_rest_length {lo}: a motor needs a range to move in",
        )
    if not lo <= rest <= hi:
        raise r.fail(f"{p}.rest_length", f"{rest} lies outside the motor's range [{lo}, {hi}]")
    return Motor(lo, hi, m.max_speed, m.min_tension)


def _cables(
    r: _Reader, sections: tuple[CableSection, ...], index: dict[str, int], owner: dict[int, str]
) -> list[Cable]:
    """The ``cables`` section: each joins two rods (``owner``: node -> its rod's name),
    an actuated one has a motor and a passive one none, and at least one is actuated."""
    cables: list[Cable] = []
    for i, d in enumerate(sections):
        p = f"cables[{i}]"
        given = "motor" in d.model_fields_set
        if d.actuated and d.motor is None:
            raise r.fail(
                f"{p}.motor", "expected a mapping, got NoneType" if given else "missing field"
            )
        if not d.actuated and given:
            raise r.fail(f"{p}.motor", "unknown field")
        pair = _node_pair(r, d.nodes, f"{p}.nodes", index)
        if owner[pair[0]] == owner[pair[1]]:
            raise r.fail(f"{p}.nodes", f"both ends are on rod {owner[pair[0]]!r}")
        motor = None if d.motor is None else _motor(r, d.motor, p, d.rest_length)
        cables.append(Cable(d.name, pair, d.stiffness, d.damping, d.rest_length, d.actuated, motor))
    if not any(c.actuated for c in cables):
        raise r.fail("cables", "no cable is actuated")
    return cables


def _carries(r: _Reader, top: RobotSection) -> tuple[str, ...] | None:
    """The YAML's ``carries``: distinct names of :data:`SAMPLE_KINDS`, in that table's
    order; None where it is absent (the robot carries every kind)."""
    if top.carries is None:
        return None
    index = {kind: i for i, kind in enumerate(SAMPLE_KINDS)}
    kinds = list(index)
    return tuple(kinds[i] for i in sorted(_names(r, top.carries, "carries", index)))


def parse_robot(doc: Any, source: str) -> RobotDescription:
    """Validate a parsed YAML document and build the description from it: each field
    against the schema (:mod:`tensegrity_gym.model.schema`), then the fields together."""
    r = _Reader(source)
    top = _validated(r, doc)
    nodes, index = _nodes(r, top.nodes)
    rods, owner = _rods(r, top.rods, nodes, index)
    cables = _cables(r, top.cables, index, owner)
    return RobotDescription(
        name=top.name,
        gravity=top.gravity,
        ground=Ground(**top.ground.model_dump()),
        nodes=tuple(nodes),
        rods=tuple(rods),
        cables=tuple(cables),
        sensors=_sensors(r, top.sensors, rods),
        display_name=_display_name(top),
        hardware=top.hardware,
        gait=None if top.gait is None else _gait(r, top.gait, nodes, cables),
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
