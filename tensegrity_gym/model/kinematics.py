"""Pure kinematics of a tensegrity: cable lengths, rod frames, centre of mass.

Functions broadcast over leading batch dimensions, e.g. sigma points ``(S, n, 3)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.lie import quat_rotate

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "center_of_mass",
    "member_lengths",
    "rod_axes",
    "rod_centres",
    "rod_node_states",
    "rod_quaternion_from_axis",
    "uwb_module_positions",
    "weighted_kabsch",
    "yaw_kabsch",
]


def member_lengths(
    node_positions: NDArray[np.float64], pairs: NDArray[np.intp]
) -> NDArray[np.float64]:
    """Distances between node pairs (m): positions (..., n, 3), pairs (m, 2) -> (..., m)."""
    u = node_positions[..., pairs[:, 1], :] - node_positions[..., pairs[:, 0], :]
    return np.asarray(np.sqrt(np.einsum("...i,...i->...", u, u)))


def rod_centres(
    node_positions: NDArray[np.float64], rod_nodes: NDArray[np.intp]
) -> NDArray[np.float64]:
    """Rod midpoints (m): (..., n, 3) -> (..., r, 3)."""
    return np.asarray(
        0.5 * (node_positions[..., rod_nodes[:, 0], :] + node_positions[..., rod_nodes[:, 1], :])
    )


def rod_axes(
    node_positions: NDArray[np.float64], rod_nodes: NDArray[np.intp]
) -> NDArray[np.float64]:
    """Unit vectors from each rod's first node to its second: (..., n, 3) -> (..., r, 3)."""
    u = node_positions[..., rod_nodes[:, 1], :] - node_positions[..., rod_nodes[:, 0], :]
    return np.asarray(u / np.linalg.norm(u, axis=-1, keepdims=True))


def uwb_module_positions(
    description: RobotDescription, nodes: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Robot UWB module positions (..., n, 3) for node positions (..., n, 3): each sits
    ``sensors.uwb.module_offset`` m from its endcap centre toward the rod centre."""
    rn = description.rod_nodes
    centres = 0.5 * (nodes[..., rn[:, 0], :] + nodes[..., rn[:, 1], :])
    toward = centres[..., description.node_rod, :] - nodes
    toward /= np.linalg.norm(toward, axis=-1, keepdims=True)
    return np.asarray(nodes + description.sensors.uwb.module_offset * toward)


def center_of_mass(
    node_positions: NDArray[np.float64], node_masses: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Mass-weighted mean of the nodes (m): (..., n, 3), (n,) -> (..., 3)."""
    w = node_masses / node_masses.sum()
    return np.asarray(np.einsum("...ni,n->...i", node_positions, w))


def rod_quaternion_from_axis(axis: NDArray[np.float64]) -> NDArray[np.float64]:
    """The smallest rotation taking +z onto each unit axis (..., 3) -> (..., 4), (x, y, z, w).

    Rods are symmetric about their axis, so this is the canonical 5-DoF orientation.
    """
    axis = np.asarray(axis, dtype=np.float64)
    z = np.zeros_like(axis)
    z[..., 2] = 1.0
    xyz = np.cross(z, axis)
    w = 1.0 + axis[..., 2:3]
    q = np.concatenate([xyz, w], axis=-1)
    # Antiparallel to +z: any half turn about a horizontal axis will do.
    flip = w[..., 0] < 1e-9
    q[flip] = np.array([1.0, 0.0, 0.0, 0.0])
    return np.asarray(q / np.linalg.norm(q, axis=-1, keepdims=True))


def rod_node_states(
    positions: ArrayLike,
    quaternions: ArrayLike,
    linear: ArrayLike,
    angular: ArrayLike,
    half_lengths: ArrayLike,
    rod_nodes: NDArray[np.intp],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Node positions (m) and velocities (m/s), each (n, 3), of rigid rods: centres
    (r, 3), quaternions (r, 4) (x, y, z, w), linear and angular velocities (r, 3) in the
    world frame, half lengths (r,) (m); a rod's first node lies at its centre minus half
    its length along its body z, its second at plus."""
    p, v = np.asarray(positions, dtype=np.float64), np.asarray(linear, dtype=np.float64)
    w = np.asarray(angular, dtype=np.float64)
    z_half = np.zeros_like(p)
    z_half[:, 2] = half_lengths
    arm = quat_rotate(quaternions, z_half)  # centre to second node (r, 3)
    spin = np.stack(  # w x arm, written out as the PyBullet world always had it
        [
            w[:, 1] * arm[:, 2] - w[:, 2] * arm[:, 1],
            w[:, 2] * arm[:, 0] - w[:, 0] * arm[:, 2],
            w[:, 0] * arm[:, 1] - w[:, 1] * arm[:, 0],
        ],
        axis=1,
    )
    n = 2 * len(rod_nodes)
    nodes, velocities = np.empty((n, 3)), np.empty((n, 3))
    nodes[rod_nodes[:, 0]], nodes[rod_nodes[:, 1]] = p - arm, p + arm
    velocities[rod_nodes[:, 0]], velocities[rod_nodes[:, 1]] = v - spin, v + spin
    return nodes, velocities


def weighted_kabsch(
    source: NDArray[np.float64], target: NDArray[np.float64], weights: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """R (3, 3), t (3,) minimising sum w |R source + t - target|^2; (k, 3) point pairs."""
    w = weights / weights.sum()
    mu_s, mu_t = w @ source, w @ target
    cov = ((target - mu_t) * w[:, None]).T @ (source - mu_s)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    return R, mu_t - R @ mu_s


def yaw_kabsch(
    source: NDArray[np.float64], target: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """R (3, 3), t (3,) minimising sum |R source + t - target|^2 over turns about z and
    shifts along the ground, (k, 3) point pairs: the rigid motions that keep the floor
    (z = 0, up) where it is, as between two frames that both stand on the same floor."""
    s, d = source[:, :2], target[:, :2]
    mu_s, mu_d = s.mean(axis=0), d.mean(axis=0)
    U, _, Vt = np.linalg.svd((s - mu_s).T @ (d - mu_d))
    turn = Vt.T @ np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    R = np.eye(3)
    R[:2, :2] = turn
    t = np.zeros(3)
    t[:2] = mu_d - turn @ mu_s
    return R, t
