"""From an RGB-D frame to coloured 3-D points: endcap segmentation by hue, back-projection,
the depth noise filtering of Lu et al. 2022 section 4.5, and the ground plane by RANSAC."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "HueRange",
    "back_project",
    "drop_stray_points",
    "endcap_masks",
    "fit_ground_plane",
    "hsv",
    "rod_hues",
]


@dataclass(frozen=True)
class HueRange:
    """A colour class: hue within ``width`` degrees of ``hue``, saturation and value above
    their floors (the HSV range of Lu et al. 2022 section 4.1)."""

    hue: float
    """Degrees, [0, 360)."""
    width: float = 25.0
    min_saturation: float = 0.4
    min_value: float = 0.15


def hsv(rgb: NDArray[np.uint8]) -> NDArray[np.float64]:
    """(H, W, 3) RGB to HSV with hue in degrees and saturation, value in [0, 1]."""
    x = rgb.astype(np.float64) / 255.0
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    v = x.max(axis=-1)
    c = v - x.min(axis=-1)
    s = np.where(v > 0, c / np.where(v > 0, v, 1.0), 0.0)
    safe = np.where(c > 0, c, 1.0)
    h = np.where(
        v == r, ((g - b) / safe) % 6.0, np.where(v == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0)
    )
    h = np.where(c > 0, 60.0 * h, 0.0)
    return np.stack([h, s, v], axis=-1)


def rod_hues(description: RobotDescription) -> list[HueRange]:
    """One hue range per rod, from the colour its endcaps are painted."""
    out = []
    for rod in description.rods:
        rgb = np.array([[np.clip(np.array(rod.color[:3]) * 255.0, 0, 255)]], dtype=np.uint8)
        out.append(HueRange(float(hsv(rgb)[0, 0, 0])))
    return out


def endcap_masks(
    rgb: NDArray[np.uint8], hues: list[HueRange], roi: tuple[int, int, int, int] | None = None
) -> NDArray[np.bool_]:
    """(R, H, W) pixels of each rod's colour; ``roi`` (row0, row1, col0, col1) limits the
    search (Lu et al. 2022 draws one by hand; by default the whole image is searched).

    Hue is computed only for the few pixels saturated and bright enough for any class.
    """
    masks = np.zeros((len(hues), *rgb.shape[:2]), dtype=np.bool_)
    if not hues:
        return masks
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]  # channel-wise: far faster than max(-1)
    top = np.maximum(np.maximum(r, g), b).astype(np.int16)
    chroma = top - np.minimum(np.minimum(r, g), b)
    s_min = min(c.min_saturation for c in hues)
    v_min = min(c.min_value for c in hues)
    rows, cols = np.nonzero((chroma >= s_min * top) & (top >= v_min * 255.0) & (chroma > 0))
    if roi is not None:
        r0, r1, c0, c1 = roi
        inside = (rows >= r0) & (rows < r1) & (cols >= c0) & (cols < c1)
        rows, cols = rows[inside], cols[inside]
    if not len(rows):
        return masks
    x = hsv(rgb[rows, cols][None])[0]
    for k, c in enumerate(hues):
        dh = np.abs(x[:, 0] - c.hue)
        dh = np.minimum(dh, 360.0 - dh)
        keep = (dh <= c.width) & (x[:, 1] >= c.min_saturation) & (x[:, 2] >= c.min_value)
        masks[k, rows[keep], cols[keep]] = True
    return masks


def back_project(
    depth: NDArray[np.float32],
    intrinsics: NDArray[np.float64],
    camera_pose: NDArray[np.float64],
    mask: NDArray[np.bool_],
) -> NDArray[np.float64]:
    """World points (k, 3) of the masked pixels that have a depth return (depth > 0)."""
    v, u = np.nonzero(mask & (depth > 0))
    z = depth[v, u].astype(np.float64)
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    cam = np.stack([(u + 0.5 - cx) / fx * z, (v + 0.5 - cy) / fy * z, z], axis=-1)
    return np.asarray(cam @ camera_pose[:3, :3].T + camera_pose[:3, 3])


def drop_stray_points(
    points: NDArray[np.float64], reach: float, min_neighbours: int
) -> NDArray[np.float64]:
    """``points`` (k, 3) (m) less those with fewer than ``min_neighbours`` others within
    ``reach`` (m): pixels of a rod's colour whose depth is not the endcap's.

    A depth camera's pixels on a silhouette's edge mix the colour of the endcap with the
    depth of what lies behind it ("flying pixels": a real sensor's edges, and an
    anti-aliased render's): back-projected, they fall tens of centimetres behind the
    endcap, alone or in twos, while an endcap's own points lie together on its sphere.
    Two of them put a rod's midpoint 21 cm off at the initialisation on the other
    engine's frames."""
    if min_neighbours <= 0 or len(points) == 0:
        return points
    counts = cKDTree(points).query_ball_point(points, reach, return_length=True)
    return points[np.asarray(counts) > min_neighbours]  # each point counts itself


def project(
    points: NDArray[np.float64], intrinsics: NDArray[np.float64], camera_pose: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """World points (k, 3) as :func:`back_project` reads pixels: their columns u and
    rows v (pixel units, the pixel's corner at 0) and depths z (m, along the optical
    axis; <= 0 behind the camera), each (k,)."""
    cam = (np.asarray(points, dtype=np.float64) - camera_pose[:3, 3]) @ camera_pose[:3, :3]
    z = cam[:, 2]
    safe = np.where(z > 0.0, z, 1.0)
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    return fx * cam[:, 0] / safe + cx, fy * cam[:, 1] / safe + cy, z


def fit_ground_plane(
    points: NDArray[np.float64],
    rng: np.random.Generator,
    iterations: int = 200,
    tolerance: float = 0.01,
) -> tuple[NDArray[np.float64], float]:
    """RANSAC plane (unit normal n (3,), offset d with n.x + d = 0) through most points
    (k, 3), refined by least squares on its inliers; the normal points up (+z)."""
    if len(points) < 3:
        raise ValueError(f"{len(points)} points cannot fix a plane")
    best, best_count = None, -1
    for _ in range(iterations):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        count = int(np.sum(np.abs(points @ n - n @ a) < tolerance))
        if count > best_count:
            best, best_count = (n, -float(n @ a)), count
    if best is None:
        raise ValueError("the points are collinear: no plane")
    n, d = best
    inliers = points[np.abs(points @ n + d) < tolerance]
    centre = inliers.mean(axis=0)
    _, _, vt = np.linalg.svd(inliers - centre)
    n = vt[-1] if vt[-1][2] >= 0 else -vt[-1]
    return n, -float(n @ centre)
