"""Where the floor is, when the robot did not rest on it.

Ranges fix the anchors and the robot relative to each other, never which way is up:
a constellation turned any way fits them as well. A robot rolled about on the floor
shows the floor (its lowest endcaps touch it; :mod:`~estimation.uwb_calibration.solve`
uses them). A robot carried through the room does not; then, in this order:

- **gravity**: the rods' IMUs. At each sample the solve knows each rod's axis; an
  accelerometer's reading along its rod's axis is gravity's component there
  (``f_z = g * axis . up``, the body z axis along the rod), whatever the rod's turn
  about its axis. Over many samples, with the robot turned every way, the least
  squares of ``axes @ up = f_z / g`` give ``up``; the carrying's own accelerations
  average out.
- **a hint**: anchors' heights above the floor, tape-measured or known (anchors under
  one ceiling share a height). Three not on one line fix the floor; with gravity one
  fixes its height.
- **none**: the verdict says what to give.

With gravity alone the floor's height is a guess: the lowest endcap the robot showed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Mapping

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "Floor",
    "FloorHint",
    "GravityRows",
    "floor_from_gravity",
    "floor_from_hint",
    "lowest_floor",
    "parse_floor_hint",
    "to_floor_frame",
]

_GROUP = re.compile(r"^(\d+(?:,\d+)*)=([-+]?(?:\d+\.?\d*|\.\d+))$")
_TURN = re.compile(r"^ccw=(\d+),(\d+),(\d+)$")
HINT_FORMAT = (
    "anchor heights above the floor in m, e.g. '0=4.7 1=4.5' or '0,1,2,3=4.6', and "
    "three anchors counter-clockwise seen from above, e.g. 'ccw=0,1,2'"
)


@dataclass(frozen=True)
class FloorHint:
    """What a lab knows of its anchors without a calibration: their heights (m) above
    the floor, by anchor index (0-based, the description's order), and three anchors
    that turn counter-clockwise seen from above (the handedness, where the robot's
    shape cannot tell it)."""

    heights: Mapping[int, float]
    counterclockwise: tuple[int, int, int] | None = None

    def __post_init__(self) -> None:
        if not self.heights and self.counterclockwise is None:
            raise ValueError(f"floor hint: nothing given ({HINT_FORMAT})")
        for a, h in self.heights.items():
            if not isinstance(a, int) or a < 0 or not np.isfinite(h):
                raise ValueError(f"floor hint: anchor {a!r} height {h!r} ({HINT_FORMAT})")
        turn = self.counterclockwise
        if turn is not None and len(set(turn)) != 3:
            raise ValueError(f"floor hint: ccw={turn} must name three different anchors")

    def check(self, n_anchors: int) -> None:
        """A one-line ValueError where an anchor index is not one of ``n_anchors``."""
        bad = [a for a in (*self.heights, *(self.counterclockwise or ())) if a >= n_anchors]
        if bad:
            raise ValueError(
                f"floor hint: anchor {bad[0]} is not one of the description's {n_anchors} "
                f"anchors (0..{n_anchors - 1})"
            )

    def counterclockwise_sign(self, anchors: NDArray[np.float64]) -> float:
        """+1 where ``anchors`` (A, 3) of a floor frame turn as the hint says seen from
        above, -1 where they turn the other way (a mirror image), 0 without the hint or
        with the three on one line."""
        if self.counterclockwise is None:
            return 0.0
        a, b, c = (anchors[k, :2] for k in self.counterclockwise)
        cross = float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
        return float(np.sign(cross))


def parse_floor_hint(text: str) -> FloorHint:
    """A :class:`FloorHint` from ``"0=4.7 1=4.5"``, ``"0,1,2,3=4.6"`` (anchors at one
    height) and ``"ccw=0,1,2"``; ValueError naming the bad part."""
    heights: dict[int, float] = {}
    turn: tuple[int, int, int] | None = None
    for part in text.replace(";", " ").split():
        match, spin = _GROUP.match(part), _TURN.match(part)
        if spin is not None:
            turn = (int(spin.group(1)), int(spin.group(2)), int(spin.group(3)))
            continue
        if match is None:
            raise ValueError(f"floor hint: cannot read {part!r} ({HINT_FORMAT})")
        for a in match.group(1).split(","):
            heights[int(a)] = float(match.group(2))
    return FloorHint(heights, turn)


@dataclass(frozen=True)
class GravityRows:
    """Accelerometer readings of the rods that carry an IMU, as arrays."""

    t: NDArray[np.float64]
    """(k,) s, on the ranges' clock."""
    rod: NDArray[np.intp]
    """(k,) the rod of each reading."""
    accel: NDArray[np.float64]
    """(k, 3) specific force (m/s^2) in the rod's body frame, z along the rod."""


@dataclass(frozen=True)
class Floor:
    """The floor found in the solve's frame: ``up . x + height = `` a point's height."""

    up: NDArray[np.float64]
    """(3,) unit vector."""
    height: float
    """m: the height of the frame's origin above the floor."""
    source: str
    """``"gravity"``, ``"hint"`` or ``"gravity+hint"``."""
    known_height: bool
    """The floor's height came from the lab (a hint), not from the lowest endcap."""
    evidence: int
    """Readings (gravity) or anchors (hint) it rests on."""
    misfit: float
    """RMS (m) of the hint's heights against the anchors in the found floor frame; 0
    without a hint."""


_MIN_GRAVITY_ROWS = 20
_MAX_NORM_ERROR = 0.2  # |u| off 1 by more: the readings are not gravity along the rods


def _gravity_rows(
    positions: NDArray[np.float64],
    slot: NDArray[np.intp],
    times: NDArray[np.float64],
    gravity: GravityRows,
    description: RobotDescription,
    half_window: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(axes (k, 3), axial readings over g (k,)): one row per sample and IMU rod whose
    two modules the sample places, the readings within ``half_window`` s averaged."""
    rn = description.rod_nodes
    axes, axial = [], []
    for rod in np.unique(gravity.rod):
        mine = gravity.rod == rod
        t, f = gravity.t[mine], gravity.accel[mine, 2]
        order = np.argsort(t)
        t, f = t[order], f[order]
        first, second = slot[:, rn[rod, 0]], slot[:, rn[rod, 1]]
        seen = np.flatnonzero((first >= 0) & (second >= 0))
        lo = np.searchsorted(t, times[seen] - half_window)
        hi = np.searchsorted(t, times[seen] + half_window)
        have = hi > lo
        sums = np.r_[0.0, np.cumsum(f)]
        means = (sums[hi[have]] - sums[lo[have]]) / (hi[have] - lo[have])
        d = positions[second[seen[have]]] - positions[first[seen[have]]]
        axes.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        axial.append(means / description.gravity)
    if not axes:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(axes), np.concatenate(axial)


def floor_from_gravity(
    positions: NDArray[np.float64],
    slot: NDArray[np.intp],
    times: NDArray[np.float64],
    gravity: GravityRows,
    description: RobotDescription,
    half_window: float,
) -> tuple[NDArray[np.float64], int] | None:
    """``up`` (3,) in the solve's frame from the rods' accelerometers and the number of
    (sample, rod) rows it rests on; None where they cannot tell it (too few rows, axes
    all alike, or readings that are not gravity along the rods).

    Args:
        positions: (V, 3) module positions of the solve; ``slot`` (S, n) indexes them
            by sample and module (-1: not placed), ``times`` (S,) the samples' times.
    """
    axes, axial = _gravity_rows(positions, slot, times, gravity, description, half_window)
    if len(axes) < _MIN_GRAVITY_ROWS:
        return None
    if np.linalg.svd(axes, compute_uv=False)[-1] < 0.1 * np.sqrt(len(axes)):
        return None  # the rods kept to a plane: one direction of up is not seen
    # Robust to the carrying's jolts: a few rounds of reweighting.
    w = np.ones(len(axes))
    for _ in range(3):
        u = np.linalg.lstsq(axes * w[:, None], axial * w, rcond=None)[0]
        r = axes @ u - axial
        scale = max(1.4826 * float(np.median(np.abs(r))), 1e-3)
        w = 1.0 / np.maximum(1.0, np.abs(r) / (2.0 * scale))
    norm = float(np.linalg.norm(u))
    if abs(norm - 1.0) > _MAX_NORM_ERROR:
        return None
    return np.asarray(u / norm, dtype=np.float64), len(axes)


def lowest_floor(up: NDArray[np.float64], positions: NDArray[np.float64],
                 description: RobotDescription) -> float:  # fmt: skip
    """The height (m, along ``up`` from the origin) of a floor under the lowest
    module of ``positions`` (V, 3), less the module offset and the endcap radius: the
    floor's height where nothing else tells it."""
    reach = description.sensors.uwb.module_offset + float(np.max(description.node_radii))
    return float(np.min(positions @ up)) - reach


_ANCHOR_SLACK = 0.1  # m: an anchor further under the floor is on the wrong side of it
_MODULE_SLACK = 0.25  # m: a module placed further under it is (in numbers) the wrong side


def _hint_candidates(pts: NDArray[np.float64], h: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """The unit ``up`` vectors that put points ``pts`` (k, 3) at heights ``h`` (k,) best:
    one where the points span space; where they span a plane (three anchors, or anchors
    under one ceiling), the two that its normal leaves: ``up = u0 +- s n``, ``u0`` the
    least-norm solution in the plane."""
    P, dh = pts - pts.mean(axis=0), h - h.mean()
    _, sv, Vt = np.linalg.svd(P)
    u0 = np.linalg.lstsq(P, dh, rcond=None)[0]
    if len(sv) == 3 and sv[2] > 1e-3 * sv[0]:
        return [u0 / np.linalg.norm(u0)]
    normal = Vt[2]
    u0 = u0 - (u0 @ normal) * normal
    rest = 1.0 - float(u0 @ u0)
    if rest <= 0.0:  # the heights differ more than the anchors' spread: the steepest up
        return [u0 / np.linalg.norm(u0)]
    return [u0 + np.sqrt(rest) * normal, u0 - np.sqrt(rest) * normal]


def _fit_hint(anchors: NDArray[np.float64], hint: FloorHint,
              positions: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:  # fmt: skip
    """``up`` and the origin's height that put the hint's anchors (three or more, not
    on one line) at their heights. Anchors that span only a plane leave two mirror-image
    answers (equal heights: up or down; else two tilts); the one with the robot and the
    anchors above the floor, then the robot nearest it, wins."""
    idx = np.array(sorted(hint.heights), dtype=np.intp)
    h = np.array([hint.heights[int(a)] for a in idx])
    pts = anchors[idx]
    best: tuple[int, int, float, NDArray[np.float64], float] | None = None
    for up in _hint_candidates(pts, h):
        height = float(np.mean(h - pts @ up))
        # An anchor under the floor is impossible; a module a little under it is noise.
        sunk = int(np.count_nonzero(anchors @ up + height < -_ANCHOR_SLACK))
        below = int(np.count_nonzero(positions @ up + height < -_MODULE_SLACK))
        lift = float(np.median(positions @ up + height)) if len(positions) else 0.0
        if best is None or (sunk, below, lift) < best[:3]:
            best = (sunk, below, lift, up, height)
    assert best is not None
    return best[3], best[4]


def floor_from_hint(
    anchors: NDArray[np.float64],
    hint: FloorHint,
    positions: NDArray[np.float64],
    up: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], float, float] | None:
    """``(up, height of the origin, misfit m)`` from the hint's anchor heights: with
    ``up`` known (gravity), any one gives the height; else three not on one line are
    needed (None with fewer)."""
    if not hint.heights:
        return None
    idx = np.array(sorted(hint.heights), dtype=np.intp)
    h = np.array([hint.heights[int(a)] for a in idx])
    if up is None:
        pts = anchors[idx]
        if len(idx) < 3 or np.linalg.matrix_rank(pts - pts.mean(axis=0), tol=0.1) < 2:
            return None
        up, height = _fit_hint(anchors, hint, positions)
    else:
        height = float(np.mean(h - anchors[idx] @ up))
    misfit = float(np.sqrt(np.mean((anchors[idx] @ up + height - h) ** 2)))
    return up, height, misfit


def to_floor_frame(
    anchors: NDArray[np.float64], up: NDArray[np.float64], height: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The rotation R (3, 3) and shift (3,) taking the solve's frame to one with ``up``
    along +z and the floor at z = 0 (``x -> R x + shift``), turned about z so that
    anchor 0 is above the origin and anchor 1 above the +x axis."""
    z = up / np.linalg.norm(up)
    d = anchors[1] - anchors[0]
    x = d - (d @ z) * z
    if np.linalg.norm(x) < 1e-9:  # anchor 1 straight above anchor 0
        x = np.eye(3)[int(np.argmin(np.abs(z)))] - z * z[int(np.argmin(np.abs(z)))]
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    shift = -R @ anchors[0]
    shift[2] = height
    return R, shift
