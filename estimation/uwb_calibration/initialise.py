"""Starting anchors without any known one, from one short window of the run.

Anchors do not range each other, so there is no anchor-anchor geometry to start from.
Instead, over a window short enough that the robot barely moves, its own modules serve
as a known constellation: their shape is the description's resting pose fitted to the
window's robot-robot ranges (less an offset guessed from the bars, whose length is
known), and each anchor is multilaterated from its ranges to them. The starts of the
joint solve come from different windows; their frames differ (each is the robot's in
its window) and are brought to the gauge before comparing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from estimation.uwb_calibration.geometry import bar_lengths, module_positions, multilaterate

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.uwb_calibration.rounds import RangeTable
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["bar_offset", "round_windows", "window_anchors", "window_shape"]


def round_windows(table: RangeTable, length: float) -> NDArray[np.intp]:
    """Window index of each round (R,): consecutive rounds spanning ``length`` s."""
    t = table.round_times
    if len(t) == 0:
        return np.zeros(0, dtype=np.intp)
    return np.asarray(np.floor((t - t[0]) / length), dtype=np.intp)


def _window_medians(
    keys: NDArray[np.intp], values: NDArray[np.float64], n_keys: int
) -> NDArray[np.float64]:
    """Median of ``values`` per key (k,) -> (n_keys,), NaN for a key without a value."""
    out = np.full(n_keys, np.nan)
    order = np.argsort(keys, kind="stable")
    k, v = keys[order], values[order]
    if len(k) == 0:
        return out
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    for s, e in zip(starts, np.r_[starts[1:], len(k)], strict=True):
        out[k[s]] = np.median(v[s:e])
    return out


def bar_offset(table: RangeTable, description: RobotDescription, rows: NDArray[np.bool_]) -> float:
    """A guess of the offset o_ij common to all pairs (m): the median over the rods of
    (median range between the rod's two modules - their known distance); 0 without
    robot-robot ranges along a rod."""
    n = table.n_nodes
    code = table.r_first * n + table.r_second
    rn = np.sort(description.rod_nodes, axis=1)
    lengths = bar_lengths(description)
    med = _window_medians(code[rows], table.r_range[rows], n * n)[rn[:, 0] * n + rn[:, 1]]
    excess = med - lengths
    excess = excess[np.isfinite(excess)]
    return float(np.median(excess)) if len(excess) else 0.0


def window_shape(
    table: RangeTable, description: RobotDescription, rows: NDArray[np.bool_], offset: float
) -> NDArray[np.float64]:
    """Module positions (n, 3) of the robot during a window, in the description's
    frame: its resting pose fitted to the window's robot-robot ranges ``rows`` less
    ``offset`` (m), the bars held to their length."""
    n = table.n_nodes
    start = module_positions(description, description.initial_positions)
    code = table.r_first[rows] * n + table.r_second[rows]
    med = _window_medians(code, table.r_range[rows], n * n)
    have = np.flatnonzero(np.isfinite(med))
    first, second, dist = have // n, have % n, med[have] - offset
    rn = description.rod_nodes
    weight = np.ones(len(have))
    bar_first, bar_second, bar_len = rn[:, 0], rn[:, 1], bar_lengths(description)

    def residuals(x: NDArray[np.float64]) -> NDArray[np.float64]:
        p = x.reshape(n, 3)
        r = np.linalg.norm(p[first] - p[second], axis=1) - dist
        b = np.linalg.norm(p[bar_first] - p[bar_second], axis=1) - bar_len
        # A weak pull to the resting pose keeps pairs the window lacks in place.
        return np.concatenate([weight * r, 10.0 * b, 0.1 * (x - start.ravel())])

    fit = least_squares(residuals, start.ravel(), loss="soft_l1", f_scale=0.05, max_nfev=50)
    return np.asarray(fit.x.reshape(n, 3))


def window_anchors(
    table: RangeTable, rows: NDArray[np.bool_], shape: NDArray[np.float64], offset: float
) -> NDArray[np.float64]:
    """Anchor positions (A, 3) in the frame of ``shape`` (n, 3), multilaterated from the
    window's robot-anchor ranges ``rows`` (median per pair, less ``offset`` m); NaN for
    an anchor that ranged fewer than 4 modules."""
    n, A = table.n_nodes, table.n_anchors
    code = table.a_anchor[rows] * n + table.a_module[rows]
    med = _window_medians(code, table.a_range[rows], A * n)
    have = np.flatnonzero(np.isfinite(med))
    anchors, _ = multilaterate(have // n, shape[have % n], med[have] - offset, A, iterations=20)
    return anchors
