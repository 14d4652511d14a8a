"""What a calibration gives: :class:`CalibrationResult`, its residual statistics and
its verdict."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.protocols import SensorCalibration

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = ["CalibrationError", "CalibrationResult", "ResidualStats", "residual_stats"]


class CalibrationError(ValueError):
    """The data cannot decide a calibration; the message (one line) says what is
    missing, e.g. how many usable samples there are and how many are needed."""


@dataclass(frozen=True)
class ResidualStats:
    """Range residuals (m) of one anchor or pair at the solution: measured range less
    the modelled one (distance + offset)."""

    count: int
    median: float
    spread: float
    """1.4826 * the median absolute deviation: a robust standard deviation."""
    rms: float
    """Root mean square of the inliers (the ranges that are not outliers)."""
    outlier_fraction: float
    """Share of ranges off by more than the outlier threshold (multipath)."""
    drift: float = float("nan")
    """Largest difference (m) between the medians of the residuals in the run's four
    quarters: an anchor moved during the run shifts them from one quarter to the next."""


_QUARTER_MIN = 5  # residuals a quarter needs for its median to count


def residual_stats(
    residuals: NDArray[np.float64], threshold: float, times: NDArray[np.float64] | None = None
) -> ResidualStats:
    """:class:`ResidualStats` of ``residuals`` (m), (k,), outliers beyond ``threshold``
    m; the drift over the quarters of ``times`` (s), (k,), where given."""
    r = np.asarray(residuals, dtype=np.float64)
    if len(r) == 0:
        return ResidualStats(0, float("nan"), float("nan"), float("nan"), float("nan"))
    med = float(np.median(r))
    inlier = np.abs(r - med) <= threshold
    rms = float(np.sqrt(np.mean(r[inlier] ** 2))) if inlier.any() else float("nan")
    spread = float(1.4826 * np.median(np.abs(r - med)))
    drift = float("nan")
    if times is not None and len(r) >= 4 * _QUARTER_MIN:
        quarter = np.minimum((4 * np.argsort(np.argsort(times)) // len(r)), 3)
        medians = [np.median(r[quarter == q]) for q in range(4)]
        drift = float(np.max(medians) - np.min(medians))
    return ResidualStats(len(r), med, spread, rms, float(1.0 - inlier.mean()), drift)


@dataclass(frozen=True)
class CalibrationResult:
    """A UWB self-calibration (Caluwaerts et al. 2016 III-C), in the floor frame.

    **Frame.** ``anchors`` are in the floor frame: z up, z = 0 the floor the robot's
    endcaps rest on (an endcap centre touching it is at its radius), the origin on the
    floor below anchor 0, x toward the point of the floor below anchor 1, y = z x x. The
    estimators assume the ground at z = 0, so this is the frame
    :meth:`to_calibration` hands them. The handedness is the robot's own (its
    description's resting pose): ranges alone cannot tell a constellation from its
    mirror image, the robot's labelled shape can. With known anchors the frame is
    theirs (``frame == "known"``). :meth:`anchors_in_anchor_frame` gives the anchors in
    the anchors' own gauge (anchor 0 at the origin, anchor 1 on +x, anchor 2 in the
    x-y plane, z up).
    """

    anchors: NDArray[np.float64]
    """(A, 3) anchor positions (m)."""
    offsets: NDArray[np.float64]
    """(n + A, n + A) symmetric o_ij (m), module ids as in ``UwbRangeSample`` (like
    :attr:`SensorCalibration.uwb_offsets`). Robot-anchor and robot-robot pairs are
    solved; anchor-anchor pairs, which no range measures, hold :attr:`mean_offset`."""
    mean_offset: float
    """The offsets' common mean mu (m)."""
    anchor_sigma: NDArray[np.float64]
    """(A,) predicted standard error (m) of each anchor position in this frame, from the
    solution's normal equations, scaled by the residuals' spread."""
    anchor_stats: tuple[ResidualStats, ...]
    """Per anchor, its ranges' residuals."""
    pair_stats: tuple[tuple[ResidualStats, ...], ...]
    """Per anchor, per robot module: the pair's residuals, ``[A][n]``."""
    robot_pair_count: NDArray[np.intp]
    """(n, n) robot-robot ranges in the solve, per pair (symmetric)."""
    n_samples: int
    """Samples (UWB rounds over ``sample_period``) in the final solve."""
    n_usable: int
    """Samples with at least one module ranging 4 anchors (alpha = 1)."""
    n_rounds: int
    """Samples in the run."""
    cost: float
    """Robust cost per range in the final solve (dimensionless, residuals over sigma)."""
    verdict: str
    """``"good"``, ``"doubtful: REASONS"`` or ``"failed: REASONS"``."""
    flagged_anchors: tuple[int, ...]
    """Anchors (0-based) whose residuals stand out: moved, blocked, or multipath."""
    mirror: str
    """How the handedness was settled: ``"kept"``, ``"flipped"`` (from the robot's
    shape), ``"hint"`` (from the floor hint's counter-clockwise anchors) or
    ``"undecided"`` (too few samples show four modules at once, and no hint)."""
    frame: str = "floor"
    """``"floor"`` (z up, the floor at z = 0), ``"known"`` (the known anchors' frame) or
    ``"anchors"`` (no floor found: :meth:`anchors_in_anchor_frame`'s gauge)."""
    floor: str = "contacts"
    """How the floor was found: ``"contacts"`` (the robot rested on it), ``"gravity"``
    (the rods' IMUs; its height then the lowest endcap seen), ``"hint"`` (anchor
    heights the lab gave), ``"gravity+hint"``, ``"known"`` (the known anchors' frame)
    or ``"none"`` (see :mod:`~estimation.uwb_calibration.floor`)."""
    wall_time: float = 0.0
    """Seconds the calibration took."""
    extras: dict[str, float] = field(default_factory=dict, compare=False)
    """Further figures by name (floor contact share, votes), for reports."""

    @property
    def quality(self) -> str:
        """``"good"``, ``"doubtful"`` or ``"failed"``: the verdict's first word."""
        return self.verdict.split(":", 1)[0]

    @property
    def n_anchors(self) -> int:
        return len(self.anchors)

    @property
    def n_nodes(self) -> int:
        return len(self.offsets) - len(self.anchors)

    def residual_spread(self) -> float:
        """The typical robust residual spread over the anchors (m)."""
        return float(np.nanmedian([s.spread for s in self.anchor_stats]))

    def to_calibration(
        self,
        base: SensorCalibration | None = None,
        *,
        camera_intrinsics: NDArray[np.float64] | None = None,
        camera_pose: NDArray[np.float64] | None = None,
    ) -> SensorCalibration:
        """A :class:`SensorCalibration` with these anchors and offsets; the camera's
        from ``base`` or the arguments (identity pose, unit intrinsics without either)."""
        intrinsics = camera_intrinsics if camera_intrinsics is not None else (
            base.camera_intrinsics if base is not None else np.eye(3))  # fmt: skip
        pose = camera_pose if camera_pose is not None else (
            base.camera_pose if base is not None else np.eye(4))  # fmt: skip
        return SensorCalibration(
            uwb_offsets=self.offsets.copy(),
            anchors=self.anchors.copy(),
            camera_intrinsics=np.asarray(intrinsics, dtype=np.float64),
            camera_pose=np.asarray(pose, dtype=np.float64),
        )

    def anchors_in_anchor_frame(self) -> NDArray[np.float64]:
        """(A, 3) the anchors with anchor 0 at the origin, anchor 1 on +x, anchor 2 in
        the x-y plane and z on the floor's upper side (y of anchor 2 is then positive
        when anchors 0, 1, 2 turn counter-clockwise seen from above). Needs anchors
        0, 1, 2 not on one line."""
        a = self.anchors - self.anchors[0]
        x = a[1] / np.linalg.norm(a[1])
        normal = np.cross(x, a[2])
        if np.linalg.norm(normal) < 1e-9:
            raise ValueError("anchors 0, 1 and 2 are on one line: their frame is undefined")
        z = normal / np.linalg.norm(normal)
        if z[2] < 0.0:
            z = -z
        y = np.cross(z, x)
        return np.asarray(a @ np.stack([x, y, z]).T)

    def summary(self) -> list[str]:
        """Lines for a person: the verdict, then each anchor's position and residuals."""
        lines = [
            f"verdict: {self.verdict}",
            f"samples: {self.n_samples} used of {self.n_usable} usable ({self.n_rounds} "
            f"in all); mean offset {self.mean_offset:.3f} m; cost {self.cost:.3f}",
        ]
        for a, (p, s) in enumerate(zip(self.anchors, self.anchor_stats, strict=True)):
            flag = "  FLAGGED" if a in self.flagged_anchors else ""
            lines.append(
                f"anchor {a}: ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m +- "
                f"{self.anchor_sigma[a]:.3f}; residual median {1e3 * s.median:.1f} mm, "
                f"spread {1e3 * s.spread:.1f} mm, outliers {100 * s.outlier_fraction:.0f} % "
                f"of {s.count}{flag}"
            )
        return lines
