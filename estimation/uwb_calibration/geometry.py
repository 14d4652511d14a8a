"""Geometry the calibrator needs: where the modules sit on the rods, batched
multilateration, rigid alignment and the robot's handedness."""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.kinematics import uwb_module_positions as module_positions
from tensegrity_gym.model.kinematics import weighted_kabsch, yaw_kabsch

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "bar_lengths",
    "chiral_quadruples",
    "floor_frame_errors",
    "module_positions",
    "multilaterate",
    "nodes_from_modules",
    "rigid_alignment_errors",
    "rigid_alignment_rms",
    "signed_volumes",
    "tilt_degrees",
]


def bar_lengths(description: RobotDescription) -> NDArray[np.float64]:
    """Distance between the two modules of each rod (m), (n_rods,): the rod length
    less twice the module offset."""
    offset = description.sensors.uwb.module_offset
    return np.array([rod.length - 2.0 * offset for rod in description.rods])


def nodes_from_modules(
    description: RobotDescription, modules: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Node (endcap centre) positions (..., n, 3) from module positions (..., n, 3):
    each module moved ``module_offset`` outward along its rod. NaN where the module or,
    with a non-zero offset, its rod's other module is NaN."""
    offset = description.sensors.uwb.module_offset
    if offset == 0.0:
        return modules.copy()
    partner = np.empty(description.n_nodes, dtype=np.intp)
    rn = description.rod_nodes
    partner[rn[:, 0]], partner[rn[:, 1]] = rn[:, 1], rn[:, 0]
    out = modules - modules[..., partner, :]
    out /= np.linalg.norm(out, axis=-1, keepdims=True)
    return np.asarray(modules + offset * out)


def multilaterate(
    target: NDArray[np.intp],
    anchors: NDArray[np.float64],
    distances: NDArray[np.float64],
    n_targets: int,
    iterations: int = 8,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Points (M, 3) from their distances to known positions, all M at once.

    Row k says point ``target[k]`` lies ``distances[k]`` m from ``anchors[k]`` (3,).
    A linear solve (differences of squared distances) starts Gauss-Newton with Huber
    weights (scale 5 cm). Returns the points and which had at least 4 rows and a
    well-conditioned solve; the others are NaN.
    """
    counts = np.bincount(target, minlength=n_targets)
    w = np.ones(len(target))
    mean_a = _per_target(anchors, w, target, n_targets)
    mean_q = _per_target((distances**2 - np.sum(anchors**2, axis=1))[:, None], w, target, n_targets)
    # |x|^2 - 2 a.x + |a|^2 = d^2, minus its mean over the target's rows.
    G = -2.0 * (anchors - mean_a[target])
    h = (distances**2 - np.sum(anchors**2, axis=1)) - mean_q[target, 0]
    x = _solve_normal(G, h, w, target, n_targets)
    for _ in range(iterations):
        d = x[target] - anchors
        r = np.linalg.norm(d, axis=1)
        u = d / np.maximum(r, 1e-9)[:, None]
        res = distances - r
        w = np.minimum(1.0, 0.05 / np.maximum(np.abs(res), 1e-12))
        x = x + _solve_normal(u, res, w, target, n_targets)
    ok = (counts >= 4) & np.all(np.isfinite(x), axis=1)
    x[~ok] = np.nan
    return x, ok


def _per_target(
    values: NDArray[np.float64], w: NDArray[np.float64], target: NDArray[np.intp], n: int
) -> NDArray[np.float64]:
    """Weighted mean of ``values`` (k, c) over each target's rows, (n, c)."""
    total = np.zeros((n, values.shape[1]))
    np.add.at(total, target, values * w[:, None])
    weight = np.bincount(target, weights=w, minlength=n)
    return np.asarray(total / np.maximum(weight, 1e-12)[:, None])


def _solve_normal(
    G: NDArray[np.float64],
    h: NDArray[np.float64],
    w: NDArray[np.float64],
    target: NDArray[np.intp],
    n: int,
) -> NDArray[np.float64]:
    """argmin_x sum_k w_k (G_k . x_target - h_k)^2 for each target, (n, 3); NaN where
    the normal matrix is singular."""
    H = np.zeros((n, 3, 3))
    g = np.zeros((n, 3))
    np.add.at(H, target, w[:, None, None] * G[:, :, None] * G[:, None, :])
    np.add.at(g, target, (w * h)[:, None] * G)
    out = np.full((n, 3), np.nan)
    good = np.all(np.isfinite(H), axis=(1, 2)) & np.all(np.isfinite(g), axis=1)
    good[good] = np.linalg.cond(H[good]) < 1e8
    out[good] = np.linalg.solve(H[good], g[good][:, :, None])[:, :, 0]
    return out


def rigid_alignment_rms(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """RMS distance (m) between points (k, 3) after the best proper rigid motion of
    ``estimate`` onto ``truth`` (Kabsch, no reflection: a mirrored estimate stays off)."""
    return float(np.sqrt(np.mean(rigid_alignment_errors(estimate, truth) ** 2)))


def floor_frame_errors(
    estimate: NDArray[np.float64], truth: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Each point's distance (m), (k,), from the truth after the best turn about z and
    shift along the floor of ``estimate`` (k, 3) onto ``truth`` (the floor frame's own
    freedom): heights and tilt are compared as they are."""
    R, t = yaw_kabsch(estimate, truth)
    return np.asarray(np.linalg.norm(estimate @ R.T + t - truth, axis=1))


def rigid_alignment_errors(
    estimate: NDArray[np.float64], truth: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Each point's distance (m), (k,), from the truth after the best proper rigid motion
    of ``estimate`` (k, 3) onto ``truth``: the constellation's own shape error."""
    R, t = weighted_kabsch(estimate, truth, np.ones(len(estimate)))
    return np.asarray(np.linalg.norm(estimate @ R.T + t - truth, axis=1))


def tilt_degrees(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """Angle (deg) between the up (+z) of ``estimate``'s frame and the truth's, through
    the best proper rigid motion of the points (k, 3) onto the truth."""
    R, _ = weighted_kabsch(estimate, truth, np.ones(len(estimate)))
    return float(np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0))))


def signed_volumes(points: NDArray[np.float64], quads: NDArray[np.intp]) -> NDArray[np.float64]:
    """Signed volumes (m^3) of tetrahedra ``quads`` (q, 4) of ``points`` (..., n, 3),
    (..., q): their signs flip under a reflection."""
    a, b, c, d = (points[..., quads[:, k], :] for k in range(4))
    return np.asarray(np.einsum("...i,...i->...", np.cross(b - a, c - a), d - a) / 6.0)


def chiral_quadruples(
    description: RobotDescription, count: int = 12
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """The ``count`` quadruples of robot modules with the largest tetrahedra in the
    description's resting pose, (count, 4), and their signed volumes (m^3): the robot's
    handedness, which no range can tell but which fixes the mirror of a calibration."""
    modules = module_positions(description, description.initial_positions)
    quads = np.array(list(itertools.combinations(range(description.n_nodes), 4)), dtype=np.intp)
    volumes = signed_volumes(modules, quads)
    best = np.argsort(-np.abs(volumes), kind="stable")[:count]
    return quads[best], volumes[best]
