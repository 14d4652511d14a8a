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

if TYPE_CHECKING:
    from collections.abc import Iterable

    from numpy.typing import ArrayLike, NDArray

    from estimation.uwb_calibration.result import CalibrationResult
    from estimation.uwb_calibration.rounds import RangeTable
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import UwbRangeSample

__all__ = ["CalibrationCheck", "check_calibration", "check_samples", "fit_residuals"]


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


def _fitted_positions(
    table: RangeTable,
    rounds: NDArray[np.intp],
    description: RobotDescription,
    anchors: NDArray[np.float64],
    offsets: NDArray[np.float64],
    config: CalibrationConfig,
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Module positions fitted to ``table``'s ranges in ``rounds`` (and to the robot's
    shape and the floor) with ``anchors`` (A, 3) m and the pair ``offsets`` (m) held:
    the (S, n) position index of each (sample, module), -1 where it does not count, and
    the positions (V, 3) m."""
    n, A = table.n_nodes, table.n_anchors
    valid = table.valid_modules(config.min_anchor_ranges)
    asm = assemble(table, rounds, valid, description, np.zeros((A, 3), dtype=bool), config)
    p = replace(asm.problem, hold_offsets=True)
    state = JointState(anchors, offsets, float(np.mean(offsets)),
                       start_positions(p, anchors, offsets[: A * n]))  # fmt: skip
    for _ in range(config.floor_passes):
        p = with_contacts(p, state, config.floor_slab)
        state = solve_positions(p, state, "cauchy", config.loss_scale)
    return asm.slot, state.positions


def _residuals_at(
    table: RangeTable,
    rounds: NDArray[np.intp],
    fitted: tuple[NDArray[np.intp], NDArray[np.float64]],
    anchors: NDArray[np.float64],
    offsets: NDArray[np.float64],
    rows: NDArray[np.bool_],
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Measured less modelled range (m) of the robot-anchor ``rows`` (k,) of ``table``
    in ``rounds`` whose module has a ``fitted`` position (:func:`_fitted_positions`),
    and the anchor of each."""
    slot, positions = fitted
    sample_of = np.full(table.n_rounds, -1, dtype=np.intp)
    sample_of[rounds] = np.arange(len(rounds))
    mine = rows & (sample_of[table.a_round] >= 0)
    at = slot[sample_of[table.a_round[mine]], table.a_module[mine]]
    seen = at >= 0
    a, j = table.a_anchor[mine][seen], table.a_module[mine][seen]
    model = np.linalg.norm(anchors[a] - positions[at[seen]], axis=1)
    return np.asarray(table.a_range[mine][seen] - model - offsets[a * table.n_nodes + j]), a


def _left_out(
    table: RangeTable,
    rounds: NDArray[np.intp],
    anchor: int,
    description: RobotDescription,
    calibration: tuple[NDArray[np.float64], NDArray[np.float64], tuple[int, ...]],
    config: CalibrationConfig,
) -> NDArray[np.float64]:
    """Residuals (m) of ``anchor``'s ranges in ``rounds`` at module positions fitted to
    the ranges of the other anchors but the flagged ones (and to the robot's shape and
    the floor) alone; ``calibration``: anchors, pair offsets, flagged anchors."""
    anchors, offsets, flagged = calibration
    left = np.isin(table.a_anchor, (anchor, *flagged))
    others = table.subset(~left, np.ones(len(table.r_range), dtype=bool))
    fitted = _fitted_positions(others, rounds, description, anchors, offsets, config)
    return _residuals_at(table, rounds, fitted, anchors, offsets, table.a_anchor == anchor)[0]


def fit_residuals(
    calibration: SensorCalibration | CalibrationResult,
    samples: Iterable[UwbRangeSample],
    description: RobotDescription,
    *,
    config: CalibrationConfig | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Residuals (m), (k,), of every robot-anchor range of ``samples`` at module
    positions fitted to all of them (and to the robot's shape and the floor) with
    ``calibration``'s anchors and offsets held, and the anchor (k,) of each: how well
    the calibration explains these ranges. Empty where no sample has a module that
    ranged ``config.min_anchor_ranges`` anchors."""
    config = config or CalibrationConfig()
    t, i, j, ranges, index = sample_rows(samples)
    table, config, _ = _table(t, i, j, ranges, description, config, index)
    usable = np.flatnonzero(table.valid_modules(config.min_anchor_ranges).any(axis=1))
    if len(usable) == 0:
        return np.zeros(0), np.zeros(0, dtype=np.intp)
    anchors = np.asarray(calibration.anchors, dtype=np.float64)
    offsets = _pair_offsets(_offsets_of(calibration), table.n_nodes, table.n_anchors)
    with single_threaded_blas():
        fitted = _fitted_positions(table, usable, description, anchors, offsets, config)
    every = np.ones(len(table.a_range), dtype=bool)
    return _residuals_at(table, usable, fitted, anchors, offsets, every)


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
    n_samples: int = 200,
) -> CalibrationCheck:
    """Check rows ``(t, module_i, module_j, range)`` (as :func:`calibrate_ranges` takes
    them) against ``calibration``'s anchors (floor frame) and offsets: for each anchor,
    the residuals of its ranges at module positions fitted to the other anchors alone
    (on up to ``n_samples`` samples), so that a moved anchor cannot hide in the fit; flag
    the anchors whose residuals stand out.

    Raises:
        CalibrationError: no round in which a module ranged 4 anchors.
    """
    config = config or CalibrationConfig()
    rng = rng if rng is not None else np.random.default_rng(0)
    table, config, _ = _table(t, module_i, module_j, ranges, description, config, rounds)
    usable = np.flatnonzero(table.valid_modules(config.min_anchor_ranges).any(axis=1))
    if len(usable) == 0:
        raise CalibrationError(
            f"0 usable samples (rounds in which a module ranged {config.min_anchor_ranges} "
            "anchors), at least 1 needed to check a calibration"
        )
    n, A = table.n_nodes, table.n_anchors
    anchors = np.asarray(calibration.anchors, dtype=np.float64)
    offsets = _pair_offsets(np.asarray(_offsets_of(calibration)), n, A)
    chosen = _spread(usable, n_samples, rng)
    flagged: tuple[int, ...] = ()
    with single_threaded_blas():
        while True:
            stats = tuple(
                residual_stats(
                    _left_out(table, chosen, k, description, (anchors, offsets, flagged), config),
                    2.0 * config.loss_scale * config.range_sigma,
                )
                for k in range(A)
            )
            worst = _worst(stats, flagged, config)
            if worst is None or len(flagged) >= A - 4:
                break
            flagged = (*flagged, worst)
    names = ", ".join(map(str, sorted(flagged)))
    verdict = f"anchors {names} stand out: moved or blocked since the calibration?"
    return CalibrationCheck(stats, tuple(sorted(flagged)), len(chosen),
                            verdict if flagged else "fits")  # fmt: skip


def _worst(
    stats: tuple[ResidualStats, ...], flagged: tuple[int, ...], config: CalibrationConfig
) -> int | None:
    """The anchor (not yet flagged) whose left-out residuals stand out most: shifted
    (median beyond ``flag_floor`` and half the anchors' typical spread) or spread out
    (beyond ``check_ratio`` times the typical and ``flag_floor``); None if none does."""
    rest = [k for k in range(len(stats)) if k not in flagged]
    typical = float(np.median([stats[k].spread for k in rest]))
    shift = max(config.flag_floor, 0.5 * typical)
    wide = max(config.flag_floor, config.check_ratio * typical)
    score = {k: max(abs(stats[k].median) / shift, stats[k].spread / wide) for k in rest}
    k = max(score, key=lambda a: score[a])
    return k if score[k] > 1.0 else None


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
