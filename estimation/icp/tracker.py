"""The ICP tracker of Lu et al. 2022 (Lu et al.): rod poses from an overhead RGB-D camera
and the cable-length sensors, each frame a few iterations of a transition step (per-rod
weighted ICP of endcap model points against the rod's coloured points) and a correction
step (eq. 2: endcap positions near the transition's, cable lengths near the measured
ones, under the rod-length, rod-rod and ground constraints of section 4.3).

The state is the endcap (node) centres, (n, 3); a rod's pose follows from its two
endcaps (rods are symmetric about their axis).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product
from typing import TYPE_CHECKING, TypeAlias

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from estimation.icp.observation import (
    back_project,
    drop_stray_points,
    endcap_masks,
    fit_ground_plane,
    project,
    rod_hues,
)
from tensegrity_gym.model.kinematics import weighted_kabsch
from tensegrity_gym.model.samples import ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import RgbdFrame

__all__ = ["IcpParams", "IcpTracker", "TrackResult"]

Vec: TypeAlias = "NDArray[np.float64]"


@dataclass(frozen=True)
class IcpParams:
    """Tracker settings; defaults from Lu et al. 2022 where it gives them."""

    max_iterations: int = 4
    """Transition + correction rounds per frame at most (section 4.2; the paper's 6 gave
    the same accuracy in the benchmark here, at 38 env steps/s against 42 with 4)."""
    d_max_first: float = 0.06
    """Correspondence distance (m) of the first iteration; it shrinks linearly..."""
    d_max_last: float = 0.015
    """...to this one in the last."""
    dummy_points: int = 10
    """Point pairs carried over from the previous frame per rod (section 4.2). The paper
    takes 50 at 640x480; at 320x240 an endcap shows about 15 points, and 50 dummies
    outweighed them (the rod lagged a roll by several cm and lost track; 10 did not)."""
    dummy_weight: float = 0.5
    model_points: int = 120
    """Points sampled on each endcap sphere."""
    interleaved: bool = True
    """Correct after every transition (the proposed method); False: transitions first,
    one correction at the end (Lu et al. 2022 baseline 3)."""
    rigid_shape: bool = False
    """Baseline 2 of Lu et al. 2022: the shape from the cable lengths alone, then registered
    to the points as one rigid body; no correction step."""
    converged: float = 2e-4
    """An iteration that moves no endcap further than this (m) ends the frame's loop."""
    correction: bool = True
    rod_rod_constraint: bool = True
    ground_constraint: bool = True
    adaptive_weights: bool = True
    """Section 4.4; off: unary weight 1 and binary weight 0.25 throughout."""
    noise_filter: bool = True
    """Section 4.5: drop an endcap's points deeper than its nearest plus its radius."""
    stray_neighbours: int = 2
    """A rod's coloured point with fewer than this many others within its endcap's
    diameter is dropped before anything uses it (a flying pixel on the silhouette's
    edge, :func:`drop_stray_points`); 0 keeps every point (as Lu et al. 2022)."""
    min_fitness: float = 0.03
    """Mean share of visible model points matched under which the track is lost."""
    max_speed: float = 3.0
    """Endcap speed (m/s) beyond which a jump is not physical: the track is lost."""
    max_cable_residual: float = 0.04
    """Mean disagreement (m) between the tracked endcap distances and the cable sensors
    beyond which the track is lost: a rod caught in a wrong pose still matches some of
    its points, but not the cables. (The median missed such poses in the benchmark.)"""
    cable_gate: float | None = 0.04
    """A cable whose reading is longer than the transition's endcap distance by more (m)
    is left out of the correction (a slack cable's sensor reads its rest length); one
    reading shorter is kept: it pulls endcaps too far apart back together. None keeps
    every cable (as Lu et al. 2022)."""

    def __post_init__(self) -> None:
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if not 0 < self.d_max_last <= self.d_max_first:
            raise ValueError("need 0 < d_max_last <= d_max_first")
        if self.dummy_points < 0 or self.model_points < 8:
            raise ValueError("dummy_points must be >= 0 and model_points >= 8")
        if self.stray_neighbours < 0:
            raise ValueError(f"stray_neighbours must be >= 0, got {self.stray_neighbours}")


@dataclass(frozen=True)
class TrackResult:
    nodes: NDArray[np.float64]
    """Endcap centres (n, 3), metres, world frame."""
    fitness: NDArray[np.float64]
    """Per endcap, the share of its visible model points that found a match, (n,)."""
    lost: bool
    reason: str = ""
    """Why the track was lost, with the figures ("fitness 0.21 below 0.3")."""
    cause: str = ""
    """Why the track was lost, as a key to count by: ``"non-finite"``, ``"fitness"``,
    ``"jump"``, ``"cables"`` or ``"out of view"`` (an endcap at the image's edge or
    beyond, before or after the frame: the robot left what the camera sees); empty
    while tracked."""


def _sphere_points(n: int) -> NDArray[np.float64]:
    """n nearly even unit vectors (Fibonacci sphere), (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5**0.5) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def _closest_parameters(
    a0: NDArray[np.float64],
    a1: NDArray[np.float64],
    b0: NDArray[np.float64],
    b1: NDArray[np.float64],
) -> tuple[float, float]:
    """Parameters (s, u) in [0, 1] of the closest points of segments a and b."""
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a, e, f = float(d1 @ d1), float(d2 @ d2), float(d2 @ r)
    c, b = float(d1 @ r), float(d1 @ d2)
    denom = a * e - b * b
    s = float(np.clip((b * f - c * e) / denom, 0.0, 1.0)) if denom > 1e-12 else 0.0
    u = (b * s + f) / e
    if u < 0.0:
        u, s = 0.0, float(np.clip(-c / a, 0.0, 1.0))
    elif u > 1.0:
        u, s = 1.0, float(np.clip((b - c) / a, 0.0, 1.0))
    return s, float(u)


class IcpTracker:
    """Tracks one robot's endcaps frame by frame (see the module docstring).

    Args:
        description: rods (lengths, radii, colours), cables.
        calibration: camera intrinsics and pose.
        params: settings.
    """

    def __init__(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        params: IcpParams | None = None,
    ) -> None:
        d = description
        self.description = d
        self.calibration = calibration
        self.params = params or IcpParams()
        self.hues = rod_hues(d)
        self.rod_nodes = d.rod_nodes
        self.radius = np.array([r.endcap_radius for r in d.rods])
        self._node_radius = np.zeros(d.n_nodes)
        """Each endcap's radius (m): how far above the ground its centre stays."""
        for k, (i, j) in enumerate(d.rod_nodes):
            self._node_radius[[i, j]] = self.radius[k]
        self.rod_diameter = 2.0 * max(r.radius for r in d.rods)
        x0 = d.initial_positions
        self.node_spacing = np.linalg.norm(x0[d.rod_nodes[:, 1]] - x0[d.rod_nodes[:, 0]], axis=1)
        self.sphere = _sphere_points(self.params.model_points)
        self.camera = np.asarray(calibration.camera_pose)[:3, 3]
        self.nodes: NDArray[np.float64] | None = None
        self.rotations: NDArray[np.float64] = np.zeros((d.n_rods, 3, 3))
        """Rod orientations (r, 3, 3), body z along the rod, turned about the axis as
        little as possible from frame to frame (section 4.2)."""
        self._set_ground(np.array([0.0, 0.0, 1.0]), 0.0)
        self._dummies: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
        self._t_ns: int | None = None
        """When the last frame was tracked (ns)."""

    # ------------------------------------------------------------------ observation

    def observe(self, frame: RgbdFrame) -> list[NDArray[np.float64]]:
        """Each rod's coloured points in the world frame, [(k_r, 3)]."""
        return self._observed(frame)[0]

    def _observed(self, frame: RgbdFrame) -> tuple[list[NDArray[np.float64]], int | None]:
        """:meth:`observe`'s points, and the first rod whose colour reaches the image's
        edge (the picture cuts it: the robot is partly out of view), or None."""
        masks = endcap_masks(frame.rgb, self.hues)
        K, pose = self.calibration.camera_intrinsics, self.calibration.camera_pose
        border = np.zeros(masks.shape[1:], dtype=bool)
        border[[0, -1], :] = border[:, [0, -1]] = True
        cut = (masks & border).any(axis=(1, 2))
        edge = int(np.argmax(cut)) if cut.any() else None
        points = [
            drop_stray_points(
                back_project(frame.depth, K, pose, m), 2.0 * r, self.params.stray_neighbours
            )
            for m, r in zip(masks, self.radius, strict=True)
        ]
        return points, edge

    # ------------------------------------------------------------------ initialisation

    def initialise(
        self,
        frame: RgbdFrame,
        cable_lengths: NDArray[np.float64] | None,
        rng: np.random.Generator,
    ) -> bool:
        """Endcaps from colour segmentation of the whole frame (section 4.1), the ground by
        RANSAC; which endcap is which node is chosen by the cable lengths. False if a rod
        is not seen."""
        points, cut = self._observed(frame)
        if cut is not None:
            return False  # a robot the camera shows in part is not placed by it
        d = self.description
        nodes = np.zeros((d.n_nodes, 3))
        for k, (i, j) in enumerate(self.rod_nodes):
            p = points[k]
            if len(p) < 4:
                return False
            a, b = self._two_clusters(p)
            mid, axis = 0.5 * (a + b), b - a
            norm = np.linalg.norm(axis)
            if norm < 0.5 * self.node_spacing[k]:
                return False  # one endcap seen (the other hidden or out of the picture)
            half = 0.5 * self.node_spacing[k] * axis / norm
            nodes[i], nodes[j] = mid - half, mid + half
        nodes = self._choose_ends(nodes, cable_lengths)
        background = np.asarray(~endcap_masks(frame.rgb, self.hues).any(axis=0))
        K, pose = self.calibration.camera_intrinsics, self.calibration.camera_pose
        floor = back_project(frame.depth, K, pose, background)
        if len(floor) > 100:
            floor = floor[rng.choice(len(floor), min(len(floor), 3000), replace=False)]
            try:
                self._set_ground(*fit_ground_plane(floor, rng))
            except ValueError:
                pass
        self.nodes = nodes
        # The angle about each axis is arbitrary at first (section 4.1).
        axes = nodes[self.rod_nodes[:, 1]] - nodes[self.rod_nodes[:, 0]]
        self.rotations = np.array([self._rod_frame(np.zeros(3), a)[0] for a in axes])
        self._dummies = [(np.zeros((0, 3)), np.zeros((0, 3))) for _ in self.rod_nodes]
        self._t_ns = None  # the refinement below is not a motion: no jump test
        self.track(frame, cable_lengths, rng)
        self._t_ns = seconds_to_ns(frame.t)
        return True

    def _set_ground(self, normal: Vec, offset: float) -> None:
        """The ground plane n.x + d = 0, and the Jacobian (n_nodes, 3 n_nodes) of the
        endcaps' heights above it, which the correction uses every iteration."""
        self.ground = (normal, offset)
        n = len(self._node_radius)
        self._ground_jac = np.zeros((n, 3 * n))
        for e in range(n):
            self._ground_jac[e, 3 * e : 3 * e + 3] = normal

    @staticmethod
    def _two_clusters(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Centroids of a 2-means split, started from the two farthest-apart points."""
        a = p[np.argmax(np.linalg.norm(p - p.mean(axis=0), axis=1))]
        b = p[np.argmax(np.linalg.norm(p - a, axis=1))]
        for _ in range(10):
            near_a = np.linalg.norm(p - a, axis=1) <= np.linalg.norm(p - b, axis=1)
            if near_a.all() or not near_a.any():
                break
            a, b = p[near_a].mean(axis=0), p[~near_a].mean(axis=0)
        return a, b

    def _choose_ends(
        self, nodes: NDArray[np.float64], cable_lengths: NDArray[np.float64] | None
    ) -> NDArray[np.float64]:
        """Swap rods' ends to fit the measured cable lengths (the rest lengths without)."""
        d = self.description
        lengths = cable_lengths if cable_lengths is not None else d.rest_lengths
        cables = d.cable_nodes
        best, best_cost = nodes, np.inf
        for flips in product((False, True), repeat=d.n_rods):
            x = nodes.copy()
            for k, flip in enumerate(flips):
                if flip:
                    i, j = self.rod_nodes[k]
                    x[[i, j]] = x[[j, i]]
            cost = float(
                np.sum((np.linalg.norm(x[cables[:, 0]] - x[cables[:, 1]], axis=1) - lengths) ** 2)
            )
            if cost < best_cost:
                best, best_cost = x, cost
        return best

    # ------------------------------------------------------------------ tracking

    def track(
        self,
        frame: RgbdFrame,
        cable_lengths: NDArray[np.float64] | None,
        rng: np.random.Generator,
    ) -> TrackResult:
        """One frame: up to ``max_iterations`` transition and correction steps."""
        if self.nodes is None:
            raise RuntimeError("initialise() before track()")
        p = self.params
        previous = self.nodes.copy()
        points, cut = self._observed(frame)
        trees = [cKDTree(pts) if len(pts) else None for pts in points]
        nodes = previous.copy()
        if p.rigid_shape and cable_lengths is not None:
            nodes = self._shape_from_cables(previous, cable_lengths)
        ratio = np.zeros(len(nodes))
        matches: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
        before = nodes.copy()
        for it in range(p.max_iterations):
            share = it / max(p.max_iterations - 1, 1)
            d_max = p.d_max_first + share * (p.d_max_last - p.d_max_first)
            matches = []
            pairs = []
            for k in range(len(self.rod_nodes)):
                S, D, W, r, pair = self._correspond(k, nodes, points[k], trees[k], d_max, rng)
                i, j = self.rod_nodes[k]
                ratio[i], ratio[j] = r
                matches.append(pair)
                if p.rigid_shape:
                    pairs.append((S, D, W))
                else:
                    nodes = self._move(nodes, [i, j], S, D, W)
            if p.rigid_shape and pairs:
                S, D, W = (np.concatenate(x) for x in zip(*pairs, strict=True))
                nodes = self._move(nodes, list(range(len(nodes))), S, D, W)
            elif p.correction and p.interleaved:
                nodes = self._correct(nodes, previous, ratio, cable_lengths)
            moved = float(np.abs(nodes - before).max()) if it else np.inf
            before = nodes.copy()
            if moved < p.converged:  # section 4.2: until convergence or max_iterations
                break
        if p.correction and not p.interleaved and not p.rigid_shape:
            nodes = self._correct(nodes, previous, ratio, cable_lengths)
        nodes = self._keep_ends(nodes, previous)
        t_ns = seconds_to_ns(frame.t)
        dt = max(ns_to_seconds(t_ns - self._t_ns), 1e-3) if self._t_ns is not None else 1.0
        cause, reason = self._loss(nodes, previous, float(ratio.mean()), dt, cable_lengths)
        if cause:  # a robot leaving the picture loses its track for that reason
            if cut is not None:
                cause, reason = "out of view", f"rod {cut} cut by the image's edge ({reason})"
            elif (edge := self._first_out_of_view(previous, nodes, frame)) is not None:
                cause, reason = "out of view", f"endcap {edge} at the image's edge ({reason})"
        if not cause:
            self.nodes = nodes
            self._dummies = matches
            self._turn_rotations(nodes)
            self._t_ns = t_ns
        lost = bool(cause)
        return TrackResult(nodes if not lost else previous, ratio, lost, reason, cause)

    def _first_out_of_view(self, previous: Vec, nodes: Vec, frame: RgbdFrame) -> int | None:
        """:meth:`out_of_view` of the endcaps before the frame, else of those after."""
        edge = self.out_of_view(previous, frame.rgb.shape[:2])
        return self.out_of_view(nodes, frame.rgb.shape[:2]) if edge is None else edge

    def out_of_view(self, nodes: Vec, image: tuple[int, ...]) -> int | None:
        """The first endcap of ``nodes`` (n, 3) (m, world) that the camera does not
        show whole in an ``image`` of (rows, columns): its centre behind the camera or
        nearer the image's edge than its own radius; None where it shows them all."""
        K, pose = self.calibration.camera_intrinsics, self.calibration.camera_pose
        u, v, z = project(nodes, K, pose)
        margin = K[0, 0] * self._node_radius / np.where(z > 0.0, z, 1.0)
        rows, cols = image[0], image[1]
        out = (z <= 0.0) | (u < margin) | (u > cols - margin) | (v < margin) | (v > rows - margin)
        return int(np.argmax(out)) if out.any() else None

    def _loss(
        self,
        nodes: Vec,
        previous: Vec,
        fitness: float,
        dt: float,
        cable_lengths: NDArray[np.float64] | None,
    ) -> tuple[str, str]:
        """Why a frame's endcaps (n, 3) (m), ``dt`` seconds after ``previous``, lose the
        track: (:attr:`TrackResult.cause`, :attr:`TrackResult.reason`), empty if tracked."""
        p = self.params
        jump = float(np.linalg.norm(nodes - previous, axis=1).max())
        if not np.all(np.isfinite(nodes)):
            return "non-finite", "non-finite endcap positions"
        if fitness < p.min_fitness:
            return "fitness", f"fitness {fitness:.3f} below {p.min_fitness}"
        if jump > p.max_speed * dt:
            return "jump", f"an endcap jumped {jump:.2f} m in {dt:.2f} s"
        if cable_lengths is not None:
            residual = self._cable_residual(nodes, cable_lengths)
            if residual > p.max_cable_residual:
                return "cables", f"endcap distances disagree with the cables by {residual:.3f} m"
        return "", ""

    def _turn_rotations(self, nodes: Vec) -> None:
        """Each rod's new orientation: the previous one turned by the smallest rotation
        that takes its old axis onto the new, the rotation with the new axis nearest the
        old in SO(3) (Lu et al. 2022 section 4.2)."""
        for k, (i, j) in enumerate(self.rod_nodes):
            old = self.rotations[k][:, 2]
            new = (nodes[j] - nodes[i]) / np.linalg.norm(nodes[j] - nodes[i])
            v = np.array(
                [
                    old[1] * new[2] - old[2] * new[1],
                    old[2] * new[0] - old[0] * new[2],
                    old[0] * new[1] - old[1] * new[0],
                ]
            )
            c = float(old @ new)
            if c < -1.0 + 1e-12:  # turned end for end: any half turn will do
                R = self._rod_frame(np.zeros(3), old)[0] @ np.diag([1.0, -1.0, -1.0])
                turn = R @ self.rotations[k].T
            else:
                vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
                turn = np.eye(3) + vx + vx @ vx / (1.0 + c)
            self.rotations[k] = turn @ self.rotations[k]

    def _cable_residual(self, nodes: Vec, cable_lengths: Vec) -> float:
        """Mean |endcap distance - cable reading| over the cables (m)."""
        c = self.description.cable_nodes
        dist = np.linalg.norm(nodes[c[:, 0]] - nodes[c[:, 1]], axis=1)
        return float(np.mean(np.abs(dist - cable_lengths)))

    def _keep_ends(self, nodes: Vec, previous: Vec) -> Vec:
        """A rod's two endcaps look alike: where ICP turned a rod end for end, swap them
        back, each endcap being the one nearer its previous position."""
        out = nodes.copy()
        for i, j in self.rod_nodes:
            kept = np.linalg.norm(nodes[i] - previous[i]) + np.linalg.norm(nodes[j] - previous[j])
            swapped = np.linalg.norm(nodes[i] - previous[j])
            swapped += np.linalg.norm(nodes[j] - previous[i])
            if swapped < kept:
                out[[i, j]] = nodes[[j, i]]
        return out

    def _rod_frame(self, a: Vec, b: Vec) -> tuple[Vec, Vec]:
        """A rotation (3, 3) with z along a -> b, and the midpoint: a rod's frame."""
        z = (b - a) / np.linalg.norm(b - a)
        # x = helper x z, written out: np.cross is slow on single vectors.
        if abs(z[0]) < 0.9:  # helper (1, 0, 0)
            x = np.array([0.0, -z[2], z[1]])
        else:  # helper (0, 1, 0)
            x = np.array([z[2], 0.0, -z[0]])
        x /= np.linalg.norm(x)
        y = np.array(
            [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]]
        )
        return np.stack([x, y, z], axis=1), 0.5 * (a + b)

    def _correspond(
        self,
        k: int,
        nodes: Vec,
        observed: Vec,
        tree: cKDTree | None,
        d_max: float,
        rng: np.random.Generator,
    ) -> tuple[Vec, Vec, Vec, tuple[float, float], tuple[Vec, Vec]]:
        """Rod k's point pairs for registration: model points (k, 3), their matches (k, 3)
        and weights (k,), eq. 1, with the dummy pairs of the previous frame; each endcap's
        match ratio; and the matched pairs (model points in the rod frame, observed points)
        kept for the next frame."""
        p = self.params
        i, j = self.rod_nodes[k]
        radius = self.radius[k]
        rot, centre = self._rod_frame(nodes[i], nodes[j])
        src, dst, w, local = [], [], [], []
        ratios = []
        for e in (i, j):
            model = nodes[e] + radius * self.sphere
            visible = (model - nodes[e]) @ (self.camera - nodes[e]) > 0.0  # hidden points
            model = model[visible]
            matched = 0
            if tree is not None and len(model):
                dist, idx = tree.query(model, distance_upper_bound=d_max)
                ok = np.isfinite(dist)
                if p.noise_filter and ok.any():
                    depth = np.linalg.norm(observed[idx[ok]] - self.camera, axis=1)
                    keep = depth <= depth.min() + 2.0 * radius
                    ok[np.flatnonzero(ok)[~keep]] = False
                matched = int(ok.sum())
                src.append(model[ok])
                dst.append(observed[idx[ok]])
                w.append(1.0 - (dist[ok] / d_max) ** 2)
                local.append((model[ok] - centre) @ rot)
            ratios.append(matched / max(len(model), 1))
        pair = (
            np.concatenate(local) if local else np.zeros((0, 3)),
            np.concatenate(dst) if dst else np.zeros((0, 3)),
        )
        prev_local, prev_obs = self._dummies[k]
        if len(prev_local) and p.dummy_points:
            pick = rng.choice(len(prev_local), min(p.dummy_points, len(prev_local)), replace=False)
            src.append(prev_local[pick] @ rot.T + centre)
            dst.append(prev_obs[pick])
            w.append(np.full(len(pick), p.dummy_weight))
        empty = np.zeros((0, 3))
        S = np.concatenate(src) if src else empty
        D = np.concatenate(dst) if dst else empty
        W = np.concatenate(w) if w else np.zeros(0)
        return S, D, W, (ratios[0], ratios[1]), pair

    @staticmethod
    def _move(nodes: Vec, which: list[int], S: Vec, D: Vec, W: Vec) -> Vec:
        """Nodes ``which`` moved by the weighted Kabsch fit of S onto D (if it is fixed)."""
        if len(S) < 3 or W.sum() <= 0:
            return nodes
        R, t = weighted_kabsch(S, D, W)
        out = nodes.copy()
        out[which] = nodes[which] @ R.T + t
        return out

    def _shape_from_cables(self, previous: Vec, cable_lengths: Vec) -> Vec:
        """The shape the cable lengths give (rod lengths held), placed near ``previous``."""
        n = len(previous)
        return self._correct(
            previous,
            previous,
            np.zeros(n),
            cable_lengths,
            w_unary=np.full(n, 1e-3),
            w_bin=np.ones(len(self.description.cable_nodes)),
            physical=False,
        )

    # ------------------------------------------------------------------ correction

    def _correct(
        self,
        hat: NDArray[np.float64],
        previous: NDArray[np.float64],
        ratio: NDArray[np.float64],
        cable_lengths: NDArray[np.float64] | None,
        *,
        w_unary: Vec | None = None,
        w_bin: Vec | None = None,
        physical: bool = True,
    ) -> NDArray[np.float64]:
        """Eq. 2 by SLSQP, with the constraints of section 4.3 (``physical``: the ground
        and rod-rod ones; the rod lengths always). Weights as section 4.4 unless given."""
        p = self.params
        n = len(hat)
        if w_unary is None:
            w_unary = np.maximum(ratio, 0.1) if p.adaptive_weights else np.ones(n)
        w_bin, lengths = self._cable_weights(hat, ratio, cable_lengths, w_bin, physical)
        cables = self.description.cable_nodes
        ci, cj = cables[:, 0], cables[:, 1]

        def objective(v: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
            q = v.reshape(n, 3)
            diff = q - hat
            vec = q[ci] - q[cj]
            dist = np.linalg.norm(vec, axis=1)
            res = dist - lengths
            value = float(np.sum(w_unary * np.sum(diff**2, axis=1)) + np.sum(w_bin * res**2))
            grad = 2.0 * w_unary[:, None] * diff
            g = (2.0 * w_bin * res / np.maximum(dist, 1e-9))[:, None] * vec
            np.add.at(grad, ci, g)
            np.add.at(grad, cj, -g)
            return value, grad.ravel()

        constraints = self._rod_length_constraints(n)
        if p.ground_constraint and physical:
            normal, offset = self.ground
            floor, jac = self._node_radius, self._ground_jac
            constraints.append(
                {
                    "type": "ineq",
                    "fun": lambda v: v.reshape(n, 3) @ normal + offset - floor,
                    "jac": lambda v: jac,
                }
            )
        if p.rod_rod_constraint and physical:
            constraints += self._rod_rod_constraints(previous, n)
        result = minimize(
            objective,
            hat.ravel(),
            jac=True,
            method="SLSQP",
            constraints=constraints,
            options={"maxiter": 50, "ftol": 1e-10},
        )
        out = result.x.reshape(n, 3)
        return out if np.all(np.isfinite(out)) else hat

    def _cable_weights(
        self,
        hat: NDArray[np.float64],
        ratio: NDArray[np.float64],
        cable_lengths: NDArray[np.float64] | None,
        w_bin: Vec | None,
        physical: bool,
    ) -> tuple[Vec, Vec]:
        """Each cable's weight in eq. 2 (section 4.4's, unless ``w_bin`` is given; 0
        without readings, or for a reading the gate leaves out) and the lengths it is
        fitted to (m), both (c,)."""
        p = self.params
        cables = self.description.cable_nodes
        if cable_lengths is None:
            return np.zeros(len(cables)), np.zeros(len(cables))
        if w_bin is None:
            ri, rj = ratio[cables[:, 0]], ratio[cables[:, 1]]
            mixed = np.where((ri < 0.2) | (rj < 0.2), 0.25, 0.25 * (1.0 - 0.5 * (ri + rj)))
            adaptive = np.where((ri > 0.5) & (rj > 0.5), 0.0, mixed)
            w_bin = adaptive if p.adaptive_weights else np.full(len(cables), 0.25)
        if p.cable_gate is not None and physical:
            # A slack cable's stretch sensor reads near its rest length, longer than the
            # endcap distance; such a reading would drag the rods apart to fit it. A
            # reading shorter than the distance is no slack cable's: the endcaps are too
            # far apart (an unseen one swung off), and the cable pulls them back.
            off = cable_lengths - np.linalg.norm(hat[cables[:, 0]] - hat[cables[:, 1]], axis=1)
            w_bin = np.where(off > p.cable_gate, 0.0, w_bin)
        return w_bin, cable_lengths

    def _rod_length_constraints(self, n: int) -> list[dict[str, object]]:
        """SLSQP equality constraints holding each rod's endcaps at its length (section
        4.3), over the ``n`` endcaps' flattened positions."""
        constraints: list[dict[str, object]] = []
        for k, (i, j) in enumerate(self.rod_nodes):
            L = self.node_spacing[k]

            def rod_length(v: NDArray[np.float64], i: int = i, j: int = j, L: float = L) -> float:
                q = v.reshape(n, 3)
                return float(np.sum((q[j] - q[i]) ** 2) - L * L)

            def rod_length_jac(
                v: NDArray[np.float64], i: int = i, j: int = j
            ) -> NDArray[np.float64]:
                q = v.reshape(n, 3)
                g = np.zeros((n, 3))
                g[j], g[i] = 2.0 * (q[j] - q[i]), -2.0 * (q[j] - q[i])
                return g.ravel()

            constraints.append({"type": "eq", "fun": rod_length, "jac": rod_length_jac})
        return constraints

    def _rod_rod_constraints(
        self, previous: NDArray[np.float64], n: int
    ) -> list[dict[str, object]]:
        """Constraint (c): linearised at the previous frame's closest points, for pairs
        whose closest points are not rod ends."""
        out: list[dict[str, object]] = []
        rods = self.rod_nodes
        for a in range(len(rods)):
            for b in range(a + 1, len(rods)):
                (a0, a1), (b0, b1) = rods[a], rods[b]
                s, u = _closest_parameters(previous[a0], previous[a1], previous[b0], previous[b1])
                if s in (0.0, 1.0) or u in (0.0, 1.0):
                    continue
                ca = previous[a0] + s * (previous[a1] - previous[a0])
                cb = previous[b0] + u * (previous[b1] - previous[b0])
                gap = cb - ca
                norm = np.linalg.norm(gap)
                if norm < 1e-9:
                    continue
                direction = gap / norm
                jac = np.zeros((n, 3))
                jac[a0], jac[a1] = -(1 - s) * direction, -s * direction
                jac[b0], jac[b1] = (1 - u) * direction, u * direction
                flat = jac.ravel()
                out.append(
                    {
                        "type": "ineq",
                        "fun": lambda v, flat=flat: float(flat @ v) - self.rod_diameter,
                        "jac": lambda v, flat=flat: flat,
                    }
                )
        return out
