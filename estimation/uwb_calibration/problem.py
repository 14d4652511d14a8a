"""The joint least-squares problem of Caluwaerts et al. 2016 eq. 8-9, with bar-length terms.

Unknowns: the anchor positions N^anchor (the coordinates the gauge leaves free), one
offset o_ij per module pair (robot-anchor and robot-robot), the offsets' common mean
mu, and every counted module position N^float[t] (a module counts at a sample when
alpha = 1: it ranged at least 4 anchors). Residuals, each over its standard deviation:

- anchor range: ``|N_a^anchor - N_j^float[t]| + o_aj - m_aj[t]`` (eq. 8);
- robot range: ``|N_i^float[t] - N_j^float[t]| + o_ij - m_ij[t]`` between two counted
  modules (the paper's robot-robot offsets, here in the same solve);
- bar: ``|N_p^float[t] - N_q^float[t]| - l`` for each rod whose two modules count, with
  ``l`` the rod length less twice the module offset;
- offset prior: ``(o_ij - mu) / offset_spread`` for every pair, where the configuration
  has a spread. Eq. 9 alone leaves each anchor's distance and its offsets nearly
  interchangeable unless the robot travels far compared with the anchor distances:
  moving an anchor away by d and lowering its offsets by d changes ranges only in the
  second order of the robot's excursion. Offsets of one kind of module scatter about a
  common value; the prior says so, and the robot-robot pairs, whose distances the
  robot's shape fixes, tell mu.

Every residual is returned as a :class:`RowBlock`: its values and its derivatives with
respect to at most four global unknowns and at most two module positions of one
sample, which is the structure :mod:`estimation.uwb_calibration.lm` eliminates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = ["FloorRows", "JointProblem", "JointState", "RowBlock", "robot_pair_index"]


def robot_pair_index(first: NDArray[np.intp], second: NDArray[np.intp], n: int) -> NDArray[np.intp]:
    """Index 0..n(n-1)/2-1 of robot module pairs first < second, row by row."""
    return np.asarray(first * n - first * (first + 1) // 2 + (second - first - 1), dtype=np.intp)


@dataclass(frozen=True)
class RowBlock:
    """k residual rows of one kind, over their sigma, and their derivatives."""

    residual: NDArray[np.float64]
    """(k,)"""
    global_columns: NDArray[np.intp]
    """(k, g) global unknowns each row depends on; -1 for none."""
    global_values: NDArray[np.float64]
    """(k, g) the derivatives (0 where the column is -1)."""
    positions: NDArray[np.intp]
    """(k, l) position unknowns each row depends on (all of one sample)."""
    position_values: NDArray[np.float64]
    """(k, l, 3) the derivatives with respect to those positions."""
    robust: bool
    """The robust loss applies (measurements); a prior row stays quadratic."""


@dataclass(frozen=True)
class FloorRows:
    """The floor z = 0 of the solve frame: the robot rests on it.

    One row per counted module: the height of its endcap (node) centre,
    ``h = scale * z_module - partner_scale * z_partner`` (the module moved
    ``module_offset`` outward along its rod, the rod's modules ``l`` apart; with no
    offset, the module's own height), must not be below the endcap radius; an endcap
    taken to touch the floor (``contact``) is held at it. Where the rod's other module
    does not count in the sample, the row only keeps the module itself above the floor.
    """

    position: NDArray[np.intp]
    partner: NDArray[np.intp]
    """(f,) the rod's other module's position index (the module's own without one)."""
    scale: NDArray[np.float64]
    partner_scale: NDArray[np.float64]
    radius: NDArray[np.float64]
    """(f,) the endcap radius (m): the lowest the node can be."""
    node: NDArray[np.bool_]
    """(f,) the row gives the node's height (else only the module's, kept above)."""
    contact: NDArray[np.bool_]
    """(f,) the endcap is held at the floor."""
    sigma: float

    def heights(self, positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Node heights (m) above the floor, (f,)."""
        z = positions[:, 2]
        return np.asarray(self.scale * z[self.position] - self.partner_scale * z[self.partner])


@dataclass
class JointState:
    """A point of the joint problem."""

    anchors: NDArray[np.float64]
    """(A, 3) m."""
    offsets: NDArray[np.float64]
    """(P,) m: A * n robot-anchor pairs (``anchor * n + module``), then n(n-1)/2
    robot-robot pairs (:func:`robot_pair_index`)."""
    mean_offset: float
    """mu (m)."""
    positions: NDArray[np.float64]
    """(V, 3) m."""


@dataclass(frozen=True)
class JointProblem:
    """The structure of one joint solve: which residual touches which unknown."""

    n_nodes: int
    free: NDArray[np.bool_]
    """(A, 3): anchor coordinates solved for; the others are held (gauge, known anchors)."""
    anchor_rows: tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]
    """(anchor, module, position index, uncorrected range m), each (k,)."""
    robot_rows: tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]
    """(pair index, first position, second position, uncorrected range m), each (q,)."""
    bars: tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]
    """(first position, second position, distance m), each (b,)."""
    position_sample: NDArray[np.intp]
    """(V,) the sample of each position unknown; a sample's positions are consecutive."""
    range_sigma: float
    bar_sigma: float
    offset_spread: float | None
    """Standard deviation (m) of the offset prior; None: no prior (and mu is not solved)."""
    hold_offsets: bool = False
    """The offsets (and mu) are given, not solved for: with every anchor held too, only
    the positions are, sample by sample (a start, or a check of a calibration)."""
    floor: FloorRows | None = None
    """The floor terms; None: no floor (the frame is the anchors' gauge only)."""

    @property
    def n_anchors(self) -> int:
        return len(self.free)

    @property
    def n_positions(self) -> int:
        return len(self.position_sample)

    @property
    def n_offsets(self) -> int:
        n = self.n_nodes
        return self.n_anchors * n + n * (n - 1) // 2

    @property
    def solves_mean(self) -> bool:
        """mu is an unknown: there is a prior and the offsets are solved for."""
        return self.offset_spread is not None and not self.hold_offsets

    @property
    def n_global(self) -> int:
        """Anchor coordinates solved for, offsets and mu unless held."""
        offsets = 0 if self.hold_offsets else self.n_offsets + int(self.solves_mean)
        return int(np.count_nonzero(self.free)) + offsets

    def anchor_columns(self) -> NDArray[np.intp]:
        """(A, 3) global column of each anchor coordinate, -1 where held."""
        column = np.full(self.free.shape, -1, dtype=np.intp)
        column[self.free] = np.arange(int(np.count_nonzero(self.free)))
        return column

    def moved(self, s: JointState, step_g: NDArray[np.float64],
              step_l: NDArray[np.float64]) -> JointState:  # fmt: skip
        """``s`` moved by a global step (n_global,) and a position step (V, 3)."""
        anchors = s.anchors.copy()
        f = int(np.count_nonzero(self.free))
        anchors[self.free] += step_g[:f]
        offsets = s.offsets if self.hold_offsets else s.offsets + step_g[f : f + self.n_offsets]
        mu = s.mean_offset + (step_g[-1] if self.solves_mean else 0.0)
        return JointState(anchors, offsets, float(mu), s.positions + step_l)

    def rows(self, s: JointState) -> list[RowBlock]:
        """Every residual at ``s`` with its derivatives."""
        blocks = [self._anchor_block(s), self._robot_block(s), self._bar_block(s)]
        if self.floor is not None:
            blocks.append(self._floor_block(s))
        if self.solves_mean:
            blocks.append(self._prior_block(s))
        return blocks

    def _anchor_block(self, s: JointState) -> RowBlock:
        a, j, v, m = self.anchor_rows
        f = int(np.count_nonzero(self.free))
        d = s.anchors[a] - s.positions[v]
        dist = np.linalg.norm(d, axis=1)
        u = d / np.maximum(dist, 1e-9)[:, None] / self.range_sigma
        pair = a * self.n_nodes + j
        cols = np.concatenate([self.anchor_columns()[a], (f + pair)[:, None]], axis=1)
        vals = np.concatenate([u, np.full((len(a), 1), 1.0 / self.range_sigma)], axis=1)
        if self.hold_offsets:
            cols[:, 3] = -1
        vals[cols < 0] = 0.0
        r = (dist + s.offsets[pair] - m) / self.range_sigma
        return RowBlock(r, cols, vals, v[:, None], -u[:, None, :], robust=True)

    def _robot_block(self, s: JointState) -> RowBlock:
        pair, p, q, m = self.robot_rows
        f = int(np.count_nonzero(self.free))
        col = f + self.n_anchors * self.n_nodes + pair
        e = s.positions[p] - s.positions[q]
        dist = np.linalg.norm(e, axis=1)
        e = e / np.maximum(dist, 1e-9)[:, None] / self.range_sigma
        r = (dist + s.offsets[col - f] - m) / self.range_sigma
        vals = np.full((len(pair), 1), 0.0 if self.hold_offsets else 1.0 / self.range_sigma)
        cols = np.full_like(col, -1) if self.hold_offsets else col
        return RowBlock(r, cols[:, None], vals, np.column_stack([p, q]),
                        np.stack([e, -e], axis=1), robust=True)  # fmt: skip

    def _bar_block(self, s: JointState) -> RowBlock:
        p, q, length = self.bars
        e = s.positions[p] - s.positions[q]
        dist = np.linalg.norm(e, axis=1)
        e = e / np.maximum(dist, 1e-9)[:, None] / self.bar_sigma
        r = (dist - length) / self.bar_sigma
        none = np.full((len(p), 1), -1, dtype=np.intp)
        return RowBlock(r, none, np.zeros((len(p), 1)), np.column_stack([p, q]),
                        np.stack([e, -e], axis=1), robust=True)  # fmt: skip

    def _floor_block(self, s: JointState) -> RowBlock:
        f = self.floor
        assert f is not None
        excess = (f.heights(s.positions) - f.radius) / f.sigma
        active = f.contact | (excess < 0.0)
        r = np.where(active, excess, 0.0)
        k = len(r)
        vals = np.zeros((k, 2, 3))
        vals[:, 0, 2] = np.where(active, f.scale / f.sigma, 0.0)
        vals[:, 1, 2] = np.where(active, -f.partner_scale / f.sigma, 0.0)
        none = np.full((k, 1), -1, dtype=np.intp)
        return RowBlock(r, none, np.zeros((k, 1)), np.column_stack([f.position, f.partner]),
                        vals, robust=True)  # fmt: skip

    def _prior_block(self, s: JointState) -> RowBlock:
        assert self.offset_spread is not None
        f = int(np.count_nonzero(self.free))
        k = np.arange(self.n_offsets)
        w = 1.0 / self.offset_spread
        r = (s.offsets - s.mean_offset) * w
        cols = np.column_stack([f + k, np.full(len(k), self.n_global - 1)])
        vals = np.column_stack([np.full(len(k), w), np.full(len(k), -w)])
        return RowBlock(r, cols, vals, np.zeros((len(k), 0), dtype=np.intp),
                        np.zeros((len(k), 0, 3)), robust=False)  # fmt: skip
