"""The quality verdict of a calibration: ``good``, ``doubtful: ...`` or ``failed: ...``."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Sequence

    from estimation.uwb_calibration.config import CalibrationConfig
    from estimation.uwb_calibration.result import CalibrationResult, ResidualStats

__all__ = ["flag_anchors", "judge"]


def flag_anchors(stats: Sequence[ResidualStats], config: CalibrationConfig) -> tuple[int, ...]:
    """Anchors whose residuals stand out from the others' (their robust spread, median,
    outlier share or drift over the run): a moved or blocked anchor, or one seeing
    multipath."""
    s = np.array([x.spread for x in stats])
    m = np.array([x.median for x in stats])
    o = np.array([x.outlier_fraction for x in stats])
    d = np.array([x.drift for x in stats])
    typical, typical_out = float(np.nanmedian(s)), float(np.nanmedian(o))
    wide = (s > config.flag_ratio * typical) & (s > config.flag_floor)
    shifted = np.abs(m) > max(config.flag_floor, config.flag_ratio * typical)
    noisy = o > max(config.outlier_fraction, 3.0 * typical_out)
    drifting = np.zeros(len(d), dtype=bool)
    if np.isfinite(d).any():
        drifting = d > max(config.flag_floor, config.flag_ratio * float(np.nanmedian(d)))
    return tuple(int(a) for a in np.flatnonzero(wide | shifted | noisy | drifting))


def _doubts(result: CalibrationResult, config: CalibrationConfig) -> list[str]:
    """What makes the result doubtful, one phrase each."""
    out = []
    spread = result.residual_spread()
    if spread > config.max_residual:
        out.append(
            f"residual spread {1e3 * spread:.0f} mm above {1e3 * config.max_residual:.0f} mm"
        )
    worst = float(np.max(result.anchor_sigma))
    if worst > config.max_anchor_sigma:
        out.append(_loose_anchor(result, config))
    thin = sum(s.count < config.min_pair_ranges for row in result.pair_stats for s in row)
    if thin:
        out.append(f"{thin} robot-anchor pairs with fewer than {config.min_pair_ranges} ranges")
    heights = result.anchors[:, 2]
    if result.frame == "floor" and float(np.min(heights)) < -0.05:
        out.append(f"anchor {int(np.argmin(heights))} below the floor ({np.min(heights):.2f} m)")
    centred = result.anchors - result.anchors.mean(axis=0)
    thickness = float(np.linalg.svd(centred, compute_uv=False)[-1]) / np.sqrt(len(centred))
    if thickness < 0.05:
        out.append(f"anchors nearly coplanar ({1e3 * thickness:.0f} mm out of their plane)")
    if result.n_usable < 2 * config.min_samples:
        out.append(f"only {result.n_usable} usable samples")
    if result.mirror == "undecided":
        out.append(
            "handedness undecided (no sample shows four modules of the robot at once): give "
            "three anchors counter-clockwise seen from above, e.g. floor hint 'ccw=0,1,2'"
        )
    if result.extras.get("handedness_disagrees"):
        out.append(
            "the hint's counter-clockwise anchors turn the other way in the robot's own "
            "handedness (a mistyped hint, or anchors mislabelled)"
        )
    return out + _floor_doubts(result, config)


def _loose_anchor(result: CalibrationResult, config: CalibrationConfig) -> str:
    """The worst-fixed anchor, with both remedies: an anchor's standard error falls as
    one over the root of its ranges' count (more ranges: a longer recording, faster
    ranging) and with the robot's travel across it (better geometry)."""
    a = int(np.argmax(result.anchor_sigma))
    worst = float(result.anchor_sigma[a])
    count = result.anchor_stats[a].count
    needed = int(np.ceil(count * (worst / config.max_anchor_sigma) ** 2))
    return (
        f"anchor {a} fixed only to +-{1e3 * worst:.0f} mm by its {count} ranges (about "
        f"{needed} would fix it to {1e3 * config.max_anchor_sigma:.0f} mm: record longer or "
        "range faster, or move the robot farther across the anchors)"
    )


_HINT = "give anchor heights, e.g. floor hint '0=4.7 1=4.5 2=0.4' (m above the floor)"


def _floor_doubts(result: CalibrationResult, config: CalibrationConfig) -> list[str]:
    """What is doubtful about the floor, with what would settle it."""
    if result.floor == "none":
        return [
            "the floor cannot be told from ranges alone (the robot never rested on it and "
            f"the recording has no IMU readings along its rods): {_HINT}"
        ]
    out = []
    if result.floor == "gravity":
        out.append(
            "the floor's height is a guess (the lowest endcap the robot showed; it never "
            "rested on the floor): give one anchor's height, e.g. floor hint '0=4.7'"
        )
    misfit = result.extras.get("floor_hint_misfit", 0.0)
    if misfit > config.max_hint_misfit:
        out.append(
            f"the hint's anchor heights disagree with the ranges by {1e3 * misfit:.0f} mm RMS "
            "(a height mistyped, or anchors not where the hint says)"
        )
    return out


def judge(result: CalibrationResult, config: CalibrationConfig) -> tuple[str, tuple[int, ...]]:
    """The verdict string and the flagged anchors of ``result``."""
    flagged = flag_anchors(result.anchor_stats, config)
    if not np.all(np.isfinite(result.anchors)) or not np.all(np.isfinite(result.offsets)):
        return "failed: the solution is not finite", flagged
    spread = result.residual_spread()
    if not spread <= 3.0 * config.max_residual:
        return (
            f"failed: residual spread {1e3 * spread:.0f} mm (ranges and geometry disagree)",
            flagged,
        )
    doubts = _doubts(result, config)
    if flagged:
        doubts.insert(
            0,
            "anchors " + ", ".join(map(str, flagged)) + " stand out (moved, blocked or multipath?)",
        )
    return ("doubtful: " + "; ".join(doubts), flagged) if doubts else ("good", flagged)
