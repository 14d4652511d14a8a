"""What ROS viewers draw (RViz, Foxglove): the rod frames on ``/tf`` and the robot as
markers on ``/tensegrity/markers``, for one instant of a run.

``/tf`` (``tf2_msgs/TFMessage``) holds one transform per rod and tree, parent
``world``, child ``truth/<rod>`` or ``estimate/<rod>``: the rod's body frame (origin at
its centre, z along it), as on ``/ground_truth/rod_poses`` and ``/estimate/rod_poses``.
Each tree's transforms carry its own stamp (the truth's, the estimate's time).

``/tf_static`` (``tf2_msgs/TFMessage``, recorded latched: transient local) holds, once
at the start, the frames that never move relative to their parent:

- ``camera`` under ``world``: the calibration's camera pose, the frame of the camera
  images and ``/camera/camera_info`` (z along the view, as ROS optical frames);
- ``<tree>/<node>`` under ``<tree>/<rod>`` for both trees: each endcap's centre
  (the robot's nodes, where its UWB modules sit) at ``-length/2`` (the rod's first node)
  and ``+length/2`` (its second) along the rod's z, no rotation: as the URDF's endcaps.

What a ROS user gets with them: the camera's images placed in the 3D view, and TF
lookups of each endcap (``tf2_echo world truth/n0``) without the robot description.

``/tensegrity/markers`` (``visualization_msgs/MarkerArray``, frame ``world``) starts
with a DELETEALL, then draws, in namespaces ``truth/...`` and ``estimate/...``:

- ``rods``: a cylinder per rod in the rod's colour (the estimate's translucent, a ghost);
- ``endcaps``: a sphere per node, of its endcap's radius;
- ``cables``: a LINE_LIST, two points per cable, coloured by the elastic tension
  ``k * max(0, length - rest_length)``: grey where slack, yellow to red as it nears
  twice the largest tension of the pose the robot is built in (its description's node
  positions and rest lengths). The estimate's cables use its rest lengths of the
  actuated cables;

and ``anchors`` (the calibration's UWB anchors, white cubes) and ``goal`` (the task's
goal on the ground, a flat green disc) where there are some. A tree whose state is not
finite (an estimator that failed) is left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hardware.bag import messages as m
from hardware.bag.codec import CAMERA_FRAME
from tensegrity_gym.model.lie import matrix_to_quat

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from hardware.bag.codec import Encoded, RobotCodec
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.samples import GroundTruth

__all__ = [
    "ESTIMATE_TREE",
    "TRUTH_TREE",
    "WORLD_FRAME",
    "RobotScene",
    "RodPoses",
    "rod_frame",
]

WORLD_FRAME = "world"
TRUTH_TREE = "truth"
ESTIMATE_TREE = "estimate"
GHOST_ALPHA = 0.35
"""Opacity of the estimate's markers."""
SLACK_GREY = (0.55, 0.55, 0.55)
TAUT_LOW, TAUT_HIGH = (1.0, 0.85, 0.1), (0.9, 0.05, 0.05)
"""Cable colours from a tension just above 0 to :attr:`RobotScene.full_tension` and above."""
LINE_WIDTH = 0.006  # m
ANCHOR_SIZE = 0.08  # m, the side of an anchor's cube
GOAL_SIZE = (0.3, 0.3, 0.005)  # m, the goal disc's diameter and height

# visualization_msgs/Marker constants (REP: the message's own definition)
_CUBE, _SPHERE, _CYLINDER, _LINE_LIST = 1, 2, 3, 5
_ADD, _DELETEALL = 0, 3


def rod_frame(tree: str, rod: str) -> str:
    """The ``/tf`` child frame of a rod in a tree: ``truth/red``."""
    return f"{tree}/{rod}"


@dataclass(frozen=True)
class RodPoses:
    """One tree's state as drawn: rods, nodes and cables."""

    t: float
    """Sample time (s)."""
    centres: NDArray[np.float64]
    """Rod centres (m), (n_rods, 3)."""
    quaternions: NDArray[np.float64]
    """Rod orientations (x, y, z, w), (n_rods, 4), body z along the rod."""
    nodes: NDArray[np.float64]
    """Node positions (m), (n_nodes, 3)."""
    rest_lengths: NDArray[np.float64]
    """Every cable's rest length (m), (n_cables,)."""

    def is_finite(self) -> bool:
        parts = (self.centres, self.quaternions, self.nodes, self.rest_lengths)
        return all(bool(np.all(np.isfinite(p))) for p in parts)


class RobotScene:
    """Encodes ``/tf`` and ``/tensegrity/markers`` for one robot.

    Args:
        codec: the robot's codec (its description, clock and type store).
        anchors: the UWB anchors (m), (n_anchors, 3), drawn as cubes.
    """

    def __init__(self, codec: RobotCodec, anchors: NDArray[np.float64]) -> None:
        self.codec = codec
        d = codec.description
        self.anchors = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
        self._types = codec.store.types
        self._rod_colours = [rod.color for rod in d.rods]
        self._node_colours = [d.rods[int(r)].color for r in d.node_rod]
        self._node_radii = d.node_radii
        self._stiffness = np.array([c.stiffness for c in d.cables])
        self._rest = d.rest_lengths
        built = self._tensions(d.initial_positions, d.rest_lengths)
        self.full_tension = float(max(2.0 * built.max(), d.total_mass * d.gravity))
        """N: the tension drawn fully red (twice the built pose's largest, at least the
        robot's weight)."""

    # ------------------------------------------------------------------ states

    def truth_poses(self, truth: GroundTruth) -> RodPoses:
        return RodPoses(
            truth.t,
            truth.rod_positions,
            truth.rod_quaternions,
            truth.node_positions,
            truth.rest_lengths,
        )

    def estimate_poses(self, estimate: Estimate) -> RodPoses:
        """The estimate as drawn; passive cables keep the description's rest lengths."""
        centres, quats = self.codec.estimate_rod_poses(estimate)
        rest = self._rest.copy()
        rest[self.codec.description.actuated] = estimate.rest_lengths
        return RodPoses(estimate.t, centres, quats, estimate.node_positions, rest)

    def trees(self, truth: GroundTruth | None, estimate: Estimate | None) -> dict[str, RodPoses]:
        """The trees to draw, by name: those given whose state is finite."""
        trees = {}
        if truth is not None:
            trees[TRUTH_TREE] = self.truth_poses(truth)
        if estimate is not None:
            trees[ESTIMATE_TREE] = self.estimate_poses(estimate)
        return {name: poses for name, poses in trees.items() if poses.is_finite()}

    # ------------------------------------------------------------------ messages

    def encode(
        self,
        t: float,
        truth: GroundTruth | None,
        estimate: Estimate | None,
        goal: NDArray[np.float64] | None = None,
    ) -> list[Encoded]:
        """``/tf`` and ``/tensegrity/markers`` at sample time ``t`` (s); ``goal`` a point
        (m), (3,), or None."""
        trees = self.trees(truth, estimate)
        transforms = [tf for name, poses in trees.items() for tf in self._transforms(name, poses)]
        tf = self._types[m.TF](transforms=transforms)
        markers = [self._marker(t, "", 0, _DELETEALL)]
        for name, poses in trees.items():
            alpha = 1.0 if name == TRUTH_TREE else GHOST_ALPHA
            markers += self._robot_markers(t, name, poses, alpha)
        markers += self._world_markers(t, goal)
        array = self._types[m.MARKER_ARRAY](markers=markers)
        return [
            (m.TF_TOPIC, self.codec.serialize(tf, m.TF)),
            (m.MARKERS_TOPIC, self.codec.serialize(array, m.MARKER_ARRAY)),
        ]

    def encode_static(self, t: float, camera_pose: NDArray[np.float64]) -> list[Encoded]:
        """``/tf_static`` stamped at sample time ``t`` (s): the camera under ``world``
        (``camera_pose``, camera to world, (4, 4); left out where not finite) and every
        endcap under its rod in both trees (see the module docstring)."""
        d = self.codec.description
        pose = np.asarray(camera_pose, dtype=np.float64)
        transforms = []
        if np.all(np.isfinite(pose)):
            quat = matrix_to_quat(pose[:3, :3])
            transforms.append(self._transform(t, WORLD_FRAME, CAMERA_FRAME, pose[:3, 3], quat))
        identity = np.array([0.0, 0.0, 0.0, 1.0])
        for tree in (TRUTH_TREE, ESTIMATE_TREE):
            for rod in d.rods:
                for node, z in zip(rod.nodes, (-0.5 * rod.length, 0.5 * rod.length), strict=True):
                    child = rod_frame(tree, d.nodes[node].name)
                    offset = np.array([0.0, 0.0, z])
                    parent = rod_frame(tree, rod.name)
                    transforms.append(self._transform(t, parent, child, offset, identity))
        tf = self._types[m.TF](transforms=transforms)
        return [(m.TF_STATIC_TOPIC, self.codec.serialize(tf, m.TF))]

    def _transforms(self, tree: str, poses: RodPoses) -> list[Any]:
        names = self.codec.rod_names
        return [
            self._transform(poses.t, WORLD_FRAME, rod_frame(tree, rod), p, q)
            for rod, p, q in zip(names, poses.centres, poses.quaternions, strict=True)
        ]

    def _transform(
        self,
        t: float,
        parent: str,
        child: str,
        xyz: NDArray[np.float64],
        quat: NDArray[np.float64],
    ) -> Any:
        """A geometry_msgs/TransformStamped at sample time ``t`` (s): ``child`` at
        ``xyz`` (m), (3,), turned by ``quat`` (x, y, z, w), (4,), in ``parent``."""
        types = self._types
        transform = types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](
                x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])
            ),
            rotation=types["geometry_msgs/msg/Quaternion"](
                x=float(quat[0]), y=float(quat[1]), z=float(quat[2]), w=float(quat[3])
            ),
        )
        return types["geometry_msgs/msg/TransformStamped"](
            header=self.codec.header(t, parent), child_frame_id=child, transform=transform
        )

    def _robot_markers(self, t: float, tree: str, poses: RodPoses, alpha: float) -> list[Any]:
        """One tree's rods, endcaps and cables."""
        d = self.codec.description
        out = []
        for k, rod in enumerate(d.rods):
            out.append(
                self._marker(t, f"{tree}/rods", k, _ADD, _CYLINDER, poses.centres[k],
                             poses.quaternions[k], (2 * rod.radius, 2 * rod.radius, rod.length),
                             (*self._rod_colours[k][:3], alpha))
            )  # fmt: skip
        for i, x in enumerate(poses.nodes):
            size = (2.0 * float(self._node_radii[i]),) * 3
            colour = (*self._node_colours[i][:3], alpha)
            out.append(self._marker(t, f"{tree}/endcaps", i, _ADD, _SPHERE, x, None, size, colour))
        ends = poses.nodes[d.cable_nodes].reshape(-1, 3)
        colours = [c for rgb in self.cable_colours(poses) for c in (rgb, rgb)]
        lines = self._marker(t, f"{tree}/cables", 0, _ADD, _LINE_LIST, scale=(LINE_WIDTH, 0, 0))
        lines.points = self._points(ends)
        lines.colors = [self._colour((*rgb, alpha)) for rgb in colours]
        return [*out, lines]

    def _tensions(
        self, nodes: NDArray[np.float64], rest: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Each cable's elastic tension (N), (n_cables,), at node positions ``nodes``."""
        ends = nodes[self.codec.description.cable_nodes]
        lengths = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=-1)
        return np.asarray(self._stiffness * np.maximum(lengths - rest, 0.0))

    def cable_colours(self, poses: RodPoses) -> list[tuple[float, float, float]]:
        """Each cable's colour (r, g, b) by its elastic tension (see the module docstring)."""
        tension = self._tensions(poses.nodes, poses.rest_lengths)
        share = np.clip(tension / self.full_tension, 0.0, 1.0)
        low, high = np.array(TAUT_LOW), np.array(TAUT_HIGH)
        out = []
        for f, s in zip(tension, share, strict=True):
            r, g, b = (float(v) for v in low + s * (high - low))
            out.append((r, g, b) if f > 0.0 else SLACK_GREY)
        return out

    def _world_markers(self, t: float, goal: NDArray[np.float64] | None) -> list[Any]:
        size = (ANCHOR_SIZE,) * 3
        out = [
            self._marker(t, "anchors", j, _ADD, _CUBE, a, None, size, (1.0, 1.0, 1.0, 1.0))
            for j, a in enumerate(self.anchors)
            if np.all(np.isfinite(a))
        ]
        if goal is not None and np.all(np.isfinite(goal)):
            out.append(self._marker(t, "goal", 0, _ADD, _CYLINDER, goal, None, GOAL_SIZE,
                                    (0.1, 0.8, 0.2, 0.8)))  # fmt: skip
        return out

    # ------------------------------------------------------------------ builders

    def _colour(self, rgba: Sequence[float]) -> Any:
        r, g, b, a = (float(v) for v in rgba)
        return self._types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=a)

    def _points(self, xyz: NDArray[np.float64]) -> list[Any]:
        point = self._types["geometry_msgs/msg/Point"]
        return [point(x=float(a), y=float(b), z=float(c)) for a, b, c in xyz]

    def _marker(
        self,
        t: float,
        ns: str,
        marker_id: int,
        action: int,
        kind: int = _CUBE,
        position: NDArray[np.float64] | None = None,
        quaternion: NDArray[np.float64] | None = None,
        scale: Sequence[float] = (1.0, 1.0, 1.0),
        rgba: Sequence[float] = (1.0, 1.0, 1.0, 1.0),
    ) -> Any:
        """A visualization_msgs/Marker in the world frame at sample time ``t`` (s)."""
        t_ = self._types
        p = np.zeros(3) if position is None else position
        q = (0.0, 0.0, 0.0, 1.0) if quaternion is None else quaternion
        pose = t_["geometry_msgs/msg/Pose"](
            position=t_["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=t_["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
            ),
        )
        sx, sy, sz = (float(v) for v in scale)
        return t_[m.MARKER](
            header=self.codec.header(t, WORLD_FRAME),
            ns=ns,
            id=marker_id,
            type=kind,
            action=action,
            pose=pose,
            scale=t_["geometry_msgs/msg/Vector3"](x=sx, y=sy, z=sz),
            color=self._colour(rgba),
            lifetime=t_["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
            frame_locked=False,
            points=[],
            colors=[],
            texture_resource="",
            texture=t_["sensor_msgs/msg/CompressedImage"](
                header=self.codec.header(t), format="", data=np.empty(0, dtype=np.uint8)
            ),
            uv_coordinates=[],
            text="",
            mesh_resource="",
            mesh_file=t_["visualization_msgs/msg/MeshFile"](
                filename="", data=np.empty(0, dtype=np.uint8)
            ),
            mesh_use_embedded_materials=False,
        )
