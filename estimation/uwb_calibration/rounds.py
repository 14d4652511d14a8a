"""Range rows grouped into samples (UWB broadcast rounds), split by what they connect.

Module ids follow :class:`~tensegrity_gym.model.samples.UwbRangeSample`: 0..n-1 are the
robot's endcap modules (n = ``n_nodes``), n..n+A-1 the fixed anchors. A row is one
uncorrected range m_{j,i} of Caluwaerts et al. 2016 eq. 6-7 (true distance + o_ij + noise).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Iterable

    from numpy.typing import ArrayLike, NDArray

    from tensegrity_gym.model.samples import UwbRangeSample

__all__ = [
    "RangeTable",
    "at_sample_times",
    "group_rounds",
    "jump_outliers",
    "local_rates",
    "merge_rounds",
    "range_table",
    "sample_rows",
]


@dataclass(frozen=True)
class RangeTable:
    """The rows of a calibration run, by round; robot-anchor and robot-robot apart.

    Robot-anchor rows: ``anchor`` in 0..A-1 (module id ``n_nodes + anchor``) and the
    robot ``module``; robot-robot rows: ``first < second``, both robot modules.
    """

    n_nodes: int
    n_anchors: int
    round_times: NDArray[np.float64]
    """(R,) time of each round (s): the mean of its rows' times."""
    a_round: NDArray[np.intp]
    a_anchor: NDArray[np.intp]
    a_module: NDArray[np.intp]
    a_range: NDArray[np.float64]
    """(k,) robot-anchor rows: round, anchor, robot module, uncorrected range (m)."""
    a_time: NDArray[np.float64]
    """(k,) time (s) of each robot-anchor range."""
    r_round: NDArray[np.intp]
    r_first: NDArray[np.intp]
    r_second: NDArray[np.intp]
    r_range: NDArray[np.float64]
    """(q,) robot-robot rows: round, the two robot modules, uncorrected range (m)."""
    r_time: NDArray[np.float64]
    """(q,) time (s) of each robot-robot range."""
    dropped: int = 0
    """Rows left out: not finite, or between two anchors (they carry no robot)."""

    @property
    def n_rounds(self) -> int:
        return len(self.round_times)

    def valid_modules(self, min_anchor_ranges: int) -> NDArray[np.bool_]:
        """alpha of eq. 9, (R, n): the module ranged at least ``min_anchor_ranges``
        distinct anchors in the round."""
        n, A = self.n_nodes, self.n_anchors
        code = np.unique((self.a_round * n + self.a_module) * A + self.a_anchor) // A
        counts = np.bincount(code, minlength=self.n_rounds * n).reshape(self.n_rounds, n)
        return np.asarray(counts >= min_anchor_ranges)

    def subset(self, anchor_rows: NDArray[np.bool_], robot_rows: NDArray[np.bool_]) -> RangeTable:
        """The table with only the robot-anchor rows (k,) and robot-robot rows (q,)
        where the masks hold; the others count as dropped."""
        a, r = anchor_rows, robot_rows
        dropped = self.dropped + int(np.count_nonzero(~a) + np.count_nonzero(~r))
        return RangeTable(
            self.n_nodes, self.n_anchors, self.round_times,
            self.a_round[a], self.a_anchor[a], self.a_module[a], self.a_range[a], self.a_time[a],
            self.r_round[r], self.r_first[r], self.r_second[r], self.r_range[r], self.r_time[r],
            dropped,
        )  # fmt: skip


def merge_rounds(table: RangeTable, period: float) -> RangeTable:
    """The table with its rounds merged into samples: consecutive rounds in bins of
    ``period`` s from the first. With packets lost, one round often has too few
    anchors per module for alpha (4); a few rounds together have them, while the robot
    moves millimetres to a few centimetres."""
    if table.n_rounds == 0:
        return table
    t = table.round_times
    bins = np.floor((t - t[0]) / period).astype(np.intp)
    _, merged = np.unique(bins, return_inverse=True)
    counts = np.bincount(merged)
    times = np.bincount(merged, weights=t) / counts
    return replace(
        table, round_times=times, a_round=merged[table.a_round], r_round=merged[table.r_round]
    )


def group_rounds(t: NDArray[np.float64], gap: float) -> NDArray[np.intp]:
    """Round index of each row (k,) for times ``t`` (s), (k,): a new round starts where
    a row comes ``gap`` s or more after the first row of the current round."""
    order = np.argsort(t, kind="stable")
    ts = t[order]
    rounds = np.empty(len(t), dtype=np.intp)
    k, start = -1, -np.inf
    for pos, time in enumerate(ts):
        if time - start >= gap:
            k, start = k + 1, time
        rounds[order[pos]] = k
    return rounds


def range_table(
    t: ArrayLike,
    module_i: ArrayLike,
    module_j: ArrayLike,
    ranges: ArrayLike,
    *,
    n_nodes: int,
    n_anchors: int,
    round_gap: float,
    rounds: ArrayLike | None = None,
) -> RangeTable:
    """Check rows ``(t, module_i, module_j, range)`` (each (k,)) and group them.

    Args:
        t: time of each range (s).
        module_i, module_j: the two module ids of each range, either order.
        ranges: uncorrected ranges (m).
        n_nodes, n_anchors: the robot's modules and the anchors.
        round_gap: rows within this many seconds of a round's first row belong to it.
        rounds: a round index for each row instead (rows of one ``UwbRangeSample``).

    Raises:
        ValueError: arrays of different lengths, or a module id out of range; the
            message names the first bad row.
    """
    arrays = [np.asarray(x) for x in (t, module_i, module_j, ranges)]
    if len({a.shape for a in arrays}) != 1 or arrays[0].ndim != 1:
        shapes = ", ".join(str(a.shape) for a in arrays)
        raise ValueError(f"t, module_i, module_j, ranges must be 1-D of one length: {shapes}")
    tt, m = arrays[0].astype(np.float64), arrays[3].astype(np.float64)
    i, j = arrays[1].astype(np.intp), arrays[2].astype(np.intp)
    n_modules = n_nodes + n_anchors
    bad = np.flatnonzero((i < 0) | (j < 0) | (i >= n_modules) | (j >= n_modules) | (i == j))
    if len(bad):
        k = int(bad[0])
        raise ValueError(
            f"row {k}: module pair ({i[k]}, {j[k]}) is not two distinct ids in "
            f"0..{n_modules - 1} ({n_nodes} robot modules, {n_anchors} anchors)"
        )
    keep = np.isfinite(tt) & np.isfinite(m) & ((i < n_nodes) | (j < n_nodes))
    if rounds is None:
        rid = group_rounds(tt[keep], round_gap)
    else:
        rid = np.unique(np.asarray(rounds, dtype=np.intp)[keep], return_inverse=True)[1]
    dropped = len(tt) - int(np.count_nonzero(keep))
    return _split(tt[keep], i[keep], j[keep], m[keep], rid, n_nodes, n_anchors, dropped)


def _split(
    t: NDArray[np.float64],
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    m: NDArray[np.float64],
    rid: NDArray[np.intp],
    n: int,
    n_anchors: int,
    dropped: int,
) -> RangeTable:
    """The :class:`RangeTable` of checked rows with their round ids ``rid``."""
    n_rounds = int(rid.max()) + 1 if len(rid) else 0
    counts = np.bincount(rid, minlength=n_rounds)
    times = np.bincount(rid, weights=t, minlength=n_rounds) / np.maximum(counts, 1)
    to_anchor = (i >= n) | (j >= n)
    anchor = np.maximum(i, j)[to_anchor] - n
    module = np.minimum(i, j)[to_anchor]
    robot = ~to_anchor
    return RangeTable(
        n, n_anchors, np.asarray(times, dtype=np.float64),
        rid[to_anchor], anchor, module, m[to_anchor], t[to_anchor],
        rid[robot], np.minimum(i, j)[robot], np.maximum(i, j)[robot], m[robot], t[robot],
        dropped,
    )  # fmt: skip


def sample_rows(
    samples: Iterable[UwbRangeSample],
) -> tuple[
    NDArray[np.float64], NDArray[np.intp], NDArray[np.intp], NDArray[np.float64], NDArray[np.intp]
]:
    """The rows of ``UwbRangeSample`` rounds: times (s), the two module ids, ranges (m)
    and the index of the round each came in, each (k,)."""
    rows = list(samples)
    if not rows:
        empty = np.zeros(0, dtype=np.intp)
        return np.zeros(0), empty, empty, np.zeros(0), empty
    pairs = np.concatenate([np.asarray(s.pairs, dtype=np.intp).reshape(-1, 2) for s in rows])
    return (
        np.concatenate([np.asarray(s.times, dtype=np.float64) for s in rows]),
        pairs[:, 0],
        pairs[:, 1],
        np.concatenate([np.asarray(s.ranges, dtype=np.float64) for s in rows]),
        np.concatenate([np.full(len(s.times), k, dtype=np.intp) for k, s in enumerate(rows)]),
    )


def _jumps(pair: NDArray[np.intp], order_key: NDArray[np.intp], values: NDArray[np.float64],
           neighbours: int, threshold: float) -> NDArray[np.bool_]:  # fmt: skip
    """Rows (k,) more than ``threshold`` from the median of their pair's ``neighbours``
    ranges before and after them (in ``order_key`` order)."""
    if len(values) == 0:
        return np.zeros(0, dtype=bool)
    order = np.lexsort((order_key, pair))
    p, v = pair[order], values[order]
    pad = np.full(neighbours, -1, dtype=np.intp)
    padded_p = np.concatenate([pad, p, pad])
    padded_v = np.concatenate([np.zeros(neighbours), v, np.zeros(neighbours)])
    width = 2 * neighbours + 1
    win_p = np.lib.stride_tricks.sliding_window_view(padded_p, width)
    win_v = np.lib.stride_tricks.sliding_window_view(padded_v, width)
    same = win_p == p[:, None]
    median = np.nanmedian(np.where(same, win_v, np.nan), axis=1)
    out = np.zeros(len(values), dtype=bool)
    out[order] = np.abs(v - median) > threshold
    return out


def jump_outliers(
    table: RangeTable, threshold: float, neighbours: int = 3
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Multipath outliers before any model: ranges more than ``threshold`` m from the
    median of the same pair's ``neighbours`` ranges on either side in time (a few
    tenths of a second: the robot moves little, and the median of a steady change is
    the middle value). Returns the robot-anchor (k,) and robot-robot (q,) outliers."""
    n = table.n_nodes
    anchor = _jumps(table.a_anchor * n + table.a_module, table.a_round, table.a_range,
                    neighbours, threshold)  # fmt: skip
    robot = _jumps(table.r_first * n + table.r_second, table.r_round, table.r_range,
                   neighbours, threshold)  # fmt: skip
    return anchor, robot


_MOST_NEIGHBOURS = 256
"""Rows on either side a rate fit looks at, at most (a pair ranging 128 Hz over 2 s)."""


def local_rates(
    pair: NDArray[np.intp],
    t: NDArray[np.float64],
    values: NDArray[np.float64],
    span: float,
    fit: NDArray[np.bool_],
) -> NDArray[np.float64]:
    """Each row's rate of change (m/s), (k,): the least-squares slope of its pair's
    ``values`` over times ``t`` within ``span`` s of it, of the rows where ``fit`` holds
    (0 where they have fewer than two times)."""
    k = len(values)
    if k == 0:
        return np.zeros(0)
    order = np.lexsort((t, pair))
    p, ts, v, good = pair[order], t[order], values[order], fit[order]
    # Each row's window in the sorted rows, found on a key that keeps pairs apart.
    stride = float(np.ptp(ts)) + 2.0 * span + 1.0
    key = p * stride + (ts - ts.min())
    lo = np.searchsorted(key, key - span, side="left")
    hi = np.searchsorted(key, key + span, side="right")
    rows = np.arange(k)
    reach = min(int(max(np.max(hi - 1 - rows), np.max(rows - lo))), _MOST_NEIGHBOURS)
    sums = np.zeros((5, k))  # count, sum dt, sum v, sum dt^2, sum dt v (dt from the row)
    for shift in range(-reach, reach + 1):
        other = rows + shift
        inside = (other >= lo) & (other < hi)
        o = np.where(inside, other, rows)
        inside &= good[o]
        dt = np.where(inside, ts[o] - ts, 0.0)
        w = inside.astype(np.float64)
        sums += np.stack([w, dt, w * v[o], dt * dt, dt * v[o]])
    n, st, sv, stt, stv = sums
    spread = n * stt - st * st
    slope = np.where(spread > 1e-12, (n * stv - st * sv) / np.maximum(spread, 1e-12), 0.0)
    out = np.empty(k)
    out[order] = slope
    return out


def at_sample_times(
    table: RangeTable,
    span: float,
    fit: tuple[NDArray[np.bool_], NDArray[np.bool_]] | None = None,
) -> RangeTable:
    """The table with each range moved to its sample's time (``round_times``) along
    its pair's local rate of change, fitted over ``span`` s on either side to the
    robot-anchor and robot-robot rows ``fit`` (default all: outliers left out, the
    rates they would bend are sound).

    A sample pools ranges taken up to its period apart as if the robot stood still;
    where ranging is slow (a lab's 1 Hz pairs, samples of about a second) a carried
    robot moves tens of centimetres within one. Each pair's ranges change smoothly,
    so the range it would have read at the sample's time is its own plus its rate
    times the time between; a fit over several of the pair's ranges keeps the rate's
    noise small."""
    n = table.n_nodes
    a_fit, r_fit = (
        fit
        if fit is not None
        else (np.ones(len(table.a_range), dtype=bool), np.ones(len(table.r_range), dtype=bool))
    )
    a_rate = local_rates(table.a_anchor * n + table.a_module, table.a_time, table.a_range,
                          span, a_fit)  # fmt: skip
    r_rate = local_rates(table.r_first * n + table.r_second, table.r_time, table.r_range,
                          span, r_fit)  # fmt: skip
    a_shift = table.round_times[table.a_round] - table.a_time
    r_shift = table.round_times[table.r_round] - table.r_time
    return replace(
        table,
        a_range=table.a_range + a_rate * a_shift, a_time=table.a_time + a_shift,
        r_range=table.r_range + r_rate * r_shift, r_time=table.r_time + r_shift,
    )  # fmt: skip
