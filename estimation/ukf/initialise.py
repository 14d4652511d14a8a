"""The filter's first guess of the node positions, from the first samples alone.

Two stages. First the robot's resting shape (the description's node positions) is
placed as a rigid body: its rotation from the rods' AHRS axes (Wahba's problem, solved
by SVD) or, without IMUs, the best of a fixed set of candidate rotations; its
translation by least squares on the UWB ranges. Then every node is freed and fitted
to all measurements at once (ranges, axes, rod and cable lengths, the ground), which
multilaterates each node while the shape keeps the fit well posed when packets are
scarce.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.optimize
from scipy.spatial.transform import Rotation

from tensegrity_gym.model.kinematics import member_lengths

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.ukf.measurements import MeasurementModel
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["MIN_ANCHOR_RANGES", "InitialFit", "InitialisationError", "fit_initial_shape"]

MIN_ANCHOR_RANGES = 4
"""UWB ranges to anchors the fit needs: three place a point, a fourth resolves the
mirror image through the anchors' plane."""


class InitialisationError(RuntimeError):
    """The samples do not determine where the robot is (too few ranges to anchors)."""


@dataclass(frozen=True)
class InitialFit:
    node_positions: NDArray[np.float64]
    """(n, 3) metres."""
    rms_range_residual: float
    """Root mean square of the range residuals of the fit (m)."""
    n_ranges: int


def _wahba(template: NDArray[np.float64], measured: NDArray[np.float64]) -> Rotation:
    """The rotation R minimising sum |measured_k - R template_k|^2, rows unit vectors
    (Wahba's problem; SciPy solves it by SVD, the Kabsch algorithm)."""
    rotation, _ = Rotation.align_vectors(measured, template)
    return rotation


def fit_initial_shape(
    description: RobotDescription,
    model: MeasurementModel,
    *,
    axes: dict[int, NDArray[np.float64]],
    range_pairs: NDArray[np.intp],
    ranges: NDArray[np.float64],
    range_sigma: float,
    axis_sigma: float,
    cable_lengths: NDArray[np.float64] | None = None,
    cable_sigma: float = 0.05,
    contact_nodes: NDArray[np.intp] | None = None,
) -> InitialFit:
    """Node positions (n, 3) that explain the first samples.

    Args:
        axes: rod -> measured unit axis (3,), from the AHRS.
        range_pairs, ranges: (r, 2) module ids and (r,) ranges with the pair offsets
            already subtracted (m).
        cable_lengths: (n_cables,) with NaN where none.
        contact_nodes: nodes that touch the ground.

    Raises:
        InitialisationError: fewer than :data:`MIN_ANCHOR_RANGES` ranges reach the anchors.
    """
    d = description
    n = d.n_nodes
    pairs = np.asarray(range_pairs, dtype=np.intp).reshape(-1, 2)
    ranges = np.asarray(ranges, dtype=np.float64)
    to_anchor = (pairs >= n).any(axis=1)
    if np.count_nonzero(to_anchor) < MIN_ANCHOR_RANGES:
        raise InitialisationError(
            f"{np.count_nonzero(to_anchor)} UWB ranges to anchors arrived; at least "
            f"{MIN_ANCHOR_RANGES} are needed to place the robot"
        )
    template = d.initial_positions - d.initial_positions.mean(axis=0)
    rod_len = np.array([r.length for r in d.rods])
    ground = model.ground_height

    def range_residuals(nodes: NDArray[np.float64]) -> NDArray[np.float64]:
        modules = model.module_positions(nodes[None])[0]
        dist = np.linalg.norm(modules[pairs[:, 1]] - modules[pairs[:, 0]], axis=1)
        return np.asarray((dist - ranges) / range_sigma)

    def axis_residuals(nodes: NDArray[np.float64]) -> NDArray[np.float64]:
        if not axes:
            return np.zeros(0)
        rods = np.array(sorted(axes), dtype=np.intp)
        rn = d.rod_nodes[rods]
        u = nodes[rn[:, 1]] - nodes[rn[:, 0]]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return np.asarray((u - np.array([axes[int(r)] for r in rods])).ravel() / axis_sigma)

    # Stage 1: the resting shape as a rigid body.
    if len(axes) >= 2:
        rods = np.array(sorted(axes), dtype=np.intp)
        rn = d.rod_nodes[rods]
        t_axes = template[rn[:, 1]] - template[rn[:, 0]]
        t_axes /= np.linalg.norm(t_axes, axis=1, keepdims=True)
        candidates = [_wahba(t_axes, np.array([axes[int(r)] for r in rods]))]
    else:
        # Without orientation, the 24 rotations of the cube about each of 4 yaws.
        cube = Rotation.create_group("O")
        yaws = [Rotation.from_euler("z", a) for a in np.arange(4) * np.pi / 8]
        candidates = [yaw * cube[i] for yaw in yaws for i in range(len(cube))]
    arena = model.anchors.mean(axis=0)
    best: tuple[float, NDArray[np.float64]] | None = None
    for rotation in candidates:
        shape = rotation.apply(template)
        # Lift the shape so that its lowest node rests on the ground.
        lift = float(np.max(ground - shape[:, 2]))

        def rigid(
            params: NDArray[np.float64], shape: NDArray[np.float64] = shape
        ) -> NDArray[np.float64]:
            rotated = Rotation.from_rotvec(params[:3]).apply(shape) + params[3:]
            return np.concatenate([range_residuals(rotated), axis_residuals(rotated)])

        start = np.array([0.0, 0.0, 0.0, arena[0], arena[1], lift])
        sol = scipy.optimize.least_squares(rigid, start, method="lm", max_nfev=200)
        if best is None or sol.cost < best[0]:
            rotated = Rotation.from_rotvec(sol.x[:3]).apply(shape) + sol.x[3:]
            best = (float(sol.cost), rotated)
    assert best is not None
    rigid_nodes = best[1]

    # Stage 2: every node free, all measurements, the rigid fit as a weak prior.
    cables = np.zeros(0, dtype=np.intp)
    cable_z = np.zeros(0)
    if cable_lengths is not None:
        cl = np.asarray(cable_lengths, dtype=np.float64)
        cables = np.flatnonzero(np.isfinite(cl))
        cable_z = cl[cables]
    contacts = (
        np.zeros(0, dtype=np.intp)
        if contact_nodes is None
        else np.asarray(contact_nodes, dtype=np.intp)
    )
    prior_sigma = 0.25 * d.characteristic_length
    shape_sigma = 1e-3 * d.characteristic_length

    def free(flat: NDArray[np.float64]) -> NDArray[np.float64]:
        nodes = flat.reshape(n, 3)
        below = np.minimum(nodes[:, 2] - ground, 0.0)
        parts = [
            range_residuals(nodes),
            axis_residuals(nodes),
            (member_lengths(nodes, d.rod_nodes) - rod_len) / shape_sigma,
            (member_lengths(nodes, d.cable_nodes[cables]) - cable_z) / cable_sigma,
            below / shape_sigma,
            (nodes[contacts, 2] - ground[contacts]) / (5 * shape_sigma),
            (nodes - rigid_nodes).ravel() / prior_sigma,
        ]
        return np.concatenate(parts)

    sol = scipy.optimize.least_squares(free, rigid_nodes.ravel(), method="trf", max_nfev=100)
    nodes = sol.x.reshape(n, 3)
    res = range_residuals(nodes) * range_sigma
    return InitialFit(nodes, float(np.sqrt(np.mean(res**2))), len(ranges))
