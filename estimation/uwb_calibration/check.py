"""Does a calibration still fit? Later ranges against fixed anchors and offsets.

An anchor moved (or blocked) after the calibration run shows in the residuals of its
ranges once the module positions are fitted with every anchor and offset held: they
shift or spread out where the other anchors' stay at the noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from estimation.ukf.filter import single_threaded_blas
from estimation.uwb_calibration.assemble import assemble, start_positions, with_contacts
from estimation.uwb_calibration.calibrate import _table
from estimation.uwb_calibration.config import CalibrationConfig
from estimation.uwb_calibration.lm import solve_positions
from estimation.uwb_calibration.problem import JointState
from estimation.uwb_calibration.result import CalibrationError, ResidualStats, residual_stats
from estimation.uwb_calibration.rounds import sample_rows
from estimation.uwb_calibration.solve import _spread
from estimation.uwb_calibration.verdict import flag_anchors

if TYPE_CHECKING:
    from collections.abc import Iterable

    from numpy.typing import ArrayLike, NDArray

    from estimation.uwb_calibration.result import CalibrationResult
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import UwbRangeSample

__all__ = ["CalibrationCheck", "check_calibration", "check_samples"]


@dataclass(frozen=True)
class CalibrationCheck:
    """Residuals of later ranges against a calibration, and what stands out."""

    anchor_stats: tuple[ResidualStats, ...]
    """Per anchor: measured less modelled range (m), module positions fitted."""
    flagged_anchors: tuple[int, ...]
    """Anchors whose residuals stand out: moved, blocked or multipath since."""
    n_samples: int
    verdict: str
    """``"fits"`` or ``"anchors A, B stand out: ..."``."""


def _pair_offsets(offsets: NDArray[np.float64], n: int, n_anchors: int) -> NDArray[np.float64]:
    """The solve's pair vector (robot-anchor ``a * n + j``, then robot-robot) from the
    (n + A, n + A) matrix."""
    iu = np.triu_indices(n, 1)
    return np.concatenate([offsets[n:, :n].ravel(), offsets[:n, :n][iu]])


def check_calibration(
    calibration: SensorCalibration | CalibrationResult,
    t: ArrayLike,
    module_i: ArrayLike,
    module_j: ArrayLike,
    ranges: ArrayLike,
    description: RobotDescription,
    *,
    config: CalibrationConfig | None = None,
    rng: np.random.Generator | None = None,
    rounds: ArrayLike | None = None,
) -> CalibrationCheck:
    """Fit the module positions of rows ``(t, module_i, module_j, range)`` (as
    :func:`calibrate_ranges` takes them) to ``calibration``'s anchors (floor frame) and
    offsets, and flag the anchors whose residuals stand out.

    Raises:
        CalibrationError: no round in which a module ranged 4 anchors.
    """
    config = config or CalibrationConfig()
    rng = rng if rng is not None else np.random.default_rng(0)
    table = _table(t, module_i, module_j, ranges, description, config, rounds)
    valid = table.valid_modules(config.min_anchor_ranges)
    usable = np.flatnonzero(valid.any(axis=1))
    if len(usable) == 0:
        raise CalibrationError(
            f"0 usable samples (rounds in which a module ranged {config.min_anchor_ranges} "
            "anchors), at least 1 needed to check a calibration"
        )
    n, A = table.n_nodes, table.n_anchors
    anchors = np.asarray(calibration.anchors, dtype=np.float64)
    offsets = _pair_offsets(np.asarray(_offsets_of(calibration)), n, A)
    held = np.zeros((A, 3), dtype=bool)
    with single_threaded_blas():
        asm = assemble(
            table, _spread(usable, config.max_samples, rng), valid, description, held, config
        )
        p = replace(asm.problem, hold_offsets=True)
        state = JointState(anchors, offsets, float(np.mean(offsets)),
                           start_positions(p, anchors, offsets[: A * n]))  # fmt: skip
        for _ in range(config.floor_passes):
            p = with_contacts(p, state, config.floor_slab)
            state = solve_positions(p, state, config.final_loss, config.loss_scale)
    a, j, v, m = p.anchor_rows
    r = m - np.linalg.norm(anchors[a] - state.positions[v], axis=1) - offsets[a * n + j]
    threshold = 2.0 * config.loss_scale * config.range_sigma
    stats = tuple(residual_stats(r[a == k], threshold) for k in range(A))
    flagged = flag_anchors(stats, config)
    names = ", ".join(map(str, flagged))
    verdict = f"anchors {names} stand out: moved or blocked since the calibration?"
    verdict = verdict if flagged else "fits"
    return CalibrationCheck(stats, flagged, len(asm.rounds), verdict)


def _offsets_of(calibration: SensorCalibration | CalibrationResult) -> NDArray[np.float64]:
    offsets = getattr(calibration, "uwb_offsets", None)
    return np.asarray(calibration.offsets if offsets is None else offsets)  # type: ignore[union-attr]


def check_samples(
    calibration: SensorCalibration | CalibrationResult,
    samples: Iterable[UwbRangeSample],
    description: RobotDescription,
    **kwargs: object,
) -> CalibrationCheck:
    """:func:`check_calibration` on ``UwbRangeSample`` rounds, one round each."""
    t, i, j, ranges, index = sample_rows(samples)
    return check_calibration(calibration, t, i, j, ranges, description, rounds=index, **kwargs)  # type: ignore[arg-type]
