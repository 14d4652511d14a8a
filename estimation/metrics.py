"""Error metrics of the field, each as the papers define it.

Per rod (Lu et al. 2022 section 5): translation error of the rod centre, 5-DoF rotation
error (the angle between the estimated and true rod axes: a rod is symmetric about its
axis), and the share of rod poses within 2 cm and 5 degrees; the CoM error; the shape
error, the mean error of endcap-to-endcap distances.

Trajectories (Tong et al. 2024 section V): absolute trajectory error after a rigid
alignment (Umeyama, no scale), relative pose error over a fixed number of frames,
final drift and drift percentage (final drift / true path length). The pose of the
robot as a whole is its body frame (:func:`body_poses`). The ATE and RPE follow evo's
definitions (``evo_ape -a``, ``evo_rpe --delta N --delta_unit f``), which the tests
check them against.

Shapes: T time steps, n nodes, r rods.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.kinematics import weighted_kabsch

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = [
    "RodErrors",
    "TrajectoryErrors",
    "absolute_trajectory_error",
    "body_poses",
    "com_errors",
    "relative_pose_error",
    "rod_errors",
    "shape_errors",
    "trajectory_errors",
    "umeyama_alignment",
]


@dataclass(frozen=True)
class RodErrors:
    translation: NDArray[np.float64]
    """(T, r) distance between estimated and true rod centres (m)."""
    rotation: NDArray[np.float64]
    """(T, r) angle between estimated and true rod axes (rad)."""

    def share_within(self, translation: float = 0.02, rotation_deg: float = 5.0) -> float:
        """Share of rod poses within both bounds (Lu et al. 2022: 2 cm and 5 degrees)."""
        ok = (self.translation <= translation) & (self.rotation <= np.radians(rotation_deg))
        return float(np.mean(ok))


def _check(est: NDArray[np.float64], true: NDArray[np.float64], what: str) -> None:
    if est.shape != true.shape:
        raise ValueError(f"{what}: estimate has shape {est.shape}, truth {true.shape}")
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(true))):
        raise ValueError(f"{what}: non-finite values")


def rod_errors(
    est_nodes: NDArray[np.float64], true_nodes: NDArray[np.float64], rod_nodes: NDArray[np.intp]
) -> RodErrors:
    """Per-rod errors of node positions (T, n, 3) (or (n, 3)) against the truth."""
    est, true = np.asarray(est_nodes), np.asarray(true_nodes)
    if est.ndim == 2:
        est, true = est[None], true[None]
    _check(est, true, "rod_errors")
    a, b = rod_nodes[:, 0], rod_nodes[:, 1]
    centre_err = 0.5 * (est[:, a] + est[:, b]) - 0.5 * (true[:, a] + true[:, b])
    u = est[:, b] - est[:, a]
    w = true[:, b] - true[:, a]
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    w = w / np.linalg.norm(w, axis=-1, keepdims=True)
    # atan2 of |u x w| and u.w: accurate at small angles, unlike arccos.
    angle = np.arctan2(np.linalg.norm(np.cross(u, w), axis=-1), np.einsum("tri,tri->tr", u, w))
    return RodErrors(np.linalg.norm(centre_err, axis=-1), angle)


def com_errors(est_com: NDArray[np.float64], true_com: NDArray[np.float64]) -> NDArray[np.float64]:
    """(T,) distance between estimated and true centres of mass (m), from (T, 3)."""
    _check(est_com, true_com, "com_errors")
    return np.asarray(np.linalg.norm(est_com - true_com, axis=-1))


def shape_errors(
    est_nodes: NDArray[np.float64],
    true_nodes: NDArray[np.float64],
    pairs: NDArray[np.intp] | None = None,
) -> NDArray[np.float64]:
    """(T,) mean absolute error of endcap-to-endcap distances (m), every pair by default.

    Independent of the frame: it scores the shape alone (Lu et al. 2022).
    """
    est, true = np.asarray(est_nodes), np.asarray(true_nodes)
    if est.ndim == 2:
        est, true = est[None], true[None]
    _check(est, true, "shape_errors")
    if pairs is None:
        i, j = np.triu_indices(est.shape[1], 1)
    else:
        i, j = pairs[:, 0], pairs[:, 1]
    d_est = np.linalg.norm(est[:, j] - est[:, i], axis=-1)
    d_true = np.linalg.norm(true[:, j] - true[:, i], axis=-1)
    return np.asarray(np.mean(np.abs(d_est - d_true), axis=-1))


def body_poses(
    nodes: NDArray[np.float64], rod_nodes: NDArray[np.intp], node_masses: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The robot's body frame, (T, 4, 4), from node positions (T, n, 3).

    Origin at the centre of mass; z along the first rod (as Tong et al. 2024 puts its body z
    along its base rod); x toward the second rod's centre, made orthogonal to z.
    """
    x = np.asarray(nodes, dtype=np.float64)
    w = node_masses / node_masses.sum()
    com = np.einsum("tni,n->ti", x, w)
    (a0, a1), (b0, b1) = rod_nodes[0], rod_nodes[1]
    z = x[:, a1] - x[:, a0]
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    toward = 0.5 * (x[:, b0] + x[:, b1]) - 0.5 * (x[:, a0] + x[:, a1])
    ex = toward - np.einsum("ti,ti->t", toward, z)[:, None] * z
    ex /= np.linalg.norm(ex, axis=-1, keepdims=True)
    ey = np.cross(z, ex)
    out = np.zeros((len(x), 4, 4))
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2], out[:, :3, 3] = ex, ey, z, com
    out[:, 3, 3] = 1.0
    return out


def umeyama_alignment(
    source: NDArray[np.float64], target: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rotation R (3, 3) and translation t (3,) minimising |target - (R source + t)|^2.

    Umeyama (1991), without scale; source and target (T, 3).
    """
    return weighted_kabsch(source, target, np.ones(len(source)))


def absolute_trajectory_error(
    est_positions: NDArray[np.float64], true_positions: NDArray[np.float64], align: bool = True
) -> NDArray[np.float64]:
    """(T,) position errors (m) after aligning the estimate to the truth (evo's APE)."""
    _check(est_positions, true_positions, "absolute_trajectory_error")
    est = est_positions
    if align:
        R, t = umeyama_alignment(est_positions, true_positions)
        est = est_positions @ R.T + t
    return np.asarray(np.linalg.norm(est - true_positions, axis=-1))


def relative_pose_error(
    est_poses: NDArray[np.float64], true_poses: NDArray[np.float64], delta: int = 1
) -> NDArray[np.float64]:
    """Translation part of the relative pose error over ``delta`` frames (m), as evo
    computes it: E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) for j = i + delta, i = 0, delta, ..."""
    _check(est_poses, true_poses, "relative_pose_error")
    if delta < 1 or delta >= len(est_poses):
        raise ValueError(f"delta must lie in [1, {len(est_poses) - 1}], got {delta}")
    i = np.arange(0, len(est_poses) - delta, delta)
    j = i + delta
    rel_true = np.linalg.inv(true_poses[i]) @ true_poses[j]
    rel_est = np.linalg.inv(est_poses[i]) @ est_poses[j]
    error = np.linalg.inv(rel_true) @ rel_est
    return np.asarray(np.linalg.norm(error[:, :3, 3], axis=-1))


@dataclass(frozen=True)
class TrajectoryErrors:
    ate_rmse: float
    """Absolute trajectory error after alignment, RMSE (m)."""
    rpe_rmse: float
    """Relative pose error (translation), RMSE (m)."""
    final_drift: float
    """Distance between the estimated and true final positions, unaligned (m)."""
    path_length: float
    """Length of the true path (m)."""

    @property
    def drift_percentage(self) -> float:
        """100 * final drift / path length (Tong et al. 2024)."""
        return 100.0 * self.final_drift / self.path_length if self.path_length > 0 else np.nan


def trajectory_errors(
    est_poses: NDArray[np.float64], true_poses: NDArray[np.float64], rpe_delta: int = 1
) -> TrajectoryErrors:
    """The trajectory metrics of Tong et al. 2024 for body poses (T, 4, 4)."""
    _check(est_poses, true_poses, "trajectory_errors")
    p_est, p_true = est_poses[:, :3, 3], true_poses[:, :3, 3]
    ate = absolute_trajectory_error(p_est, p_true)
    rpe = relative_pose_error(est_poses, true_poses, rpe_delta)
    return TrajectoryErrors(
        ate_rmse=float(np.sqrt(np.mean(ate**2))),
        rpe_rmse=float(np.sqrt(np.mean(rpe**2))),
        final_drift=float(np.linalg.norm(p_est[-1] - p_true[-1])),
        path_length=float(np.sum(np.linalg.norm(np.diff(p_true, axis=0), axis=-1))),
    )
