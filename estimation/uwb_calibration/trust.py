"""May a saved calibration be used here? Checked against the scene and against ranges.

A calibration kept on disk can be well formed and still wrong for the lab it is read
for: made for another robot or another number of anchors, edited, or from another lab.
:func:`scene_mismatch` compares it with the robot description (anchor and module
counts, the robot's name, the anchors against the floor plan); :func:`range_fit`
compares it with ranges recorded now: with its anchors and offsets held, the module
positions are fitted to the ranges, and each anchor's residuals must stay within a
few times those the calibration itself left (its stored residual statistics), never
held to less than the ranging noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from estimation.uwb_calibration.check import fit_residuals
from estimation.uwb_calibration.config import CalibrationConfig

if TYPE_CHECKING:
    from collections.abc import Iterable

    from numpy.typing import NDArray

    from estimation.uwb_calibration.files import CalibrationFile
    from estimation.uwb_calibration.result import CalibrationResult
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import UwbRangeSample

__all__ = [
    "FIT_MIN_RANGES",
    "FIT_RATIO",
    "LAYOUT_TOLERANCE",
    "OWN_RESIDUAL_MOST",
    "RangeFit",
    "range_fit",
    "scene_mismatch",
]

LAYOUT_TOLERANCE = 0.5
"""m: an anchor of a calibration fitted onto the floor plan stands at most this far
from where the description's layout puts it. The simulator stands each anchor within
5 cm (standard deviation, per axis) of the layout and the calibrator leaves 1-2 cm:
0.5 m is ten such standard deviations, yet well under the 1.5 m or more between the
presets' anchors, so a constellation shifted, turned or mirrored is refused."""
FIT_RATIO = 2.0
"""An anchor's residuals on new ranges (robust RMS about zero) may reach this many
times those the calibration left on its own run (the hypot of their median and
spread), taken as at least ``range_sigma`` (3 cm): no calibration is held to better
than the ranging noise. Honest cached calibrations gave 25-35 mm on 3 s of new ranges
(1.0-1.2 times their own; 3-bar worlds 0-4, 1.45 m 3-bar and SUPERball worlds 0-2,
four draws of the ranges each): a margin of 1.7 under the 60 mm this allows. Offsets
10 cm off gave 2-5 times the allowance, offsets 5 m off 90-170 times."""
OWN_RESIDUAL_MOST = 4.0
"""An anchor's own residuals count for at most this many times ``range_sigma`` (12 cm)
in its allowance: the statistics are read from the file being checked, and a file
whose stored spread is edited (infinite, or metres) must not widen the check at will.
Honest calibrations store 1-2 times the ranging noise."""
FIT_MIN_RANGES = 10
"""Ranges an anchor needs in the new ranges for its residuals to count."""
_ROBUST = 1.4826  # median |x| of a zero-mean normal times this is its standard deviation


def scene_mismatch(
    calibration: CalibrationFile | CalibrationResult,
    description: RobotDescription,
    *,
    robot: str = "",
    layout_tolerance: float | None = LAYOUT_TOLERANCE,
) -> str | None:
    """Why ``calibration`` cannot be ``description``'s scene (one phrase), or None.

    Args:
        calibration: its ``anchors`` (A, 3) m and ``offsets`` (n + A, n + A) m.
        description: the robot: its ``n_nodes``, anchor layout ``anchors`` (A, 3) m and
            ``name``.
        robot: the robot's name the calibration was saved with; "" not to compare.
        layout_tolerance: m an anchor may stand from the layout's; None not to compare
            (a lab's own file, in whatever frame it was calibrated).
    """
    d = description
    A, modules = len(d.anchors), d.n_nodes + len(d.anchors)
    if robot and robot != d.name:
        return f"made for robot {robot!r}, not {d.name!r}"
    anchors, offsets = np.asarray(calibration.anchors), np.asarray(calibration.offsets)
    if anchors.shape != (A, 3) or offsets.shape != (modules, modules):
        return (
            f"it has {len(anchors)} anchors and {len(offsets)} UWB modules, "
            f"robot {d.name!r} has {A} and {modules}"
        )
    if layout_tolerance is not None and A:
        away = np.linalg.norm(anchors - d.anchors, axis=1)
        k = int(np.argmax(away))
        if not away[k] <= layout_tolerance:
            return (
                f"anchor {k} stands {away[k]:.2f} m from the layout's "
                f"(sensors.uwb.anchors[{k}] of {d.name!r}), at most {layout_tolerance:g} m "
                "is plausible"
            )
    return None


@dataclass(frozen=True)
class RangeFit:
    """How a calibration explains new ranges: its worst anchor against its allowance."""

    found: float
    """m: the worst anchor's robust RMS residual (1.4826 median |r|) on the new ranges;
    NaN where no anchor had :data:`FIT_MIN_RANGES`."""
    allowed: float
    """m: that anchor's allowance, :data:`FIT_RATIO` times its own residuals in the
    calibration, at least :data:`FIT_RATIO` times ``range_sigma``."""
    anchor: int
    """The worst anchor (0-based), -1 where none counted."""
    n_ranges: int
    """Robot-anchor ranges in the fit."""

    @property
    def checked(self) -> bool:
        """Some anchor had enough ranges to judge."""
        return self.anchor >= 0

    @property
    def fits(self) -> bool:
        """Every counted anchor within its allowance (False where none counted)."""
        return self.checked and self.found <= self.allowed


def _own_residuals(
    calibration: CalibrationFile | CalibrationResult, n_anchors: int, config: CalibrationConfig
) -> NDArray[np.float64]:
    """(A,) m: each anchor's residuals in the calibration (hypot of its median and
    spread), never under ``config.range_sigma`` nor over :data:`OWN_RESIDUAL_MOST` times
    it; the ranging noise where not stored."""
    result = getattr(calibration, "result", calibration)
    stats = getattr(result, "anchor_stats", None)
    if stats is None or len(stats) != n_anchors:
        return np.full(n_anchors, config.range_sigma)
    own = np.array([np.hypot(s.median, s.spread) for s in stats], dtype=np.float64)
    own = np.fmax(own, config.range_sigma)  # fmax: NaN takes the floor
    return np.asarray(np.minimum(own, OWN_RESIDUAL_MOST * config.range_sigma))


def range_fit(
    calibration: CalibrationFile | CalibrationResult,
    samples: Iterable[UwbRangeSample],
    description: RobotDescription,
    *,
    config: CalibrationConfig | None = None,
) -> RangeFit:
    """``calibration`` (anchors and offsets held) against the UWB rounds ``samples``:
    the worst anchor's residuals against its allowance (see :class:`RangeFit`).

    The residuals are those of the module positions fitted to all the ranges
    (:func:`~estimation.uwb_calibration.check.fit_residuals`); their median absolute
    value counts both a bias (offsets or an anchor's distance wrong) and a spread, and
    outliers (multipath) do not move it."""
    config = config or CalibrationConfig()
    A = len(description.anchors)
    r, anchor = fit_residuals(calibration.to_calibration(), samples, description, config=config)
    allowed = FIT_RATIO * _own_residuals(calibration, A, config)
    found = np.full(A, np.nan)
    for k in range(A):
        mine = np.abs(r[anchor == k])
        if len(mine) >= FIT_MIN_RANGES:
            found[k] = _ROBUST * float(np.median(mine))
    if not np.isfinite(found).any():
        return RangeFit(float("nan"), float("nan"), -1, len(r))
    k = int(np.nanargmax(found / allowed))
    return RangeFit(float(found[k]), float(allowed[k]), k, len(r))
