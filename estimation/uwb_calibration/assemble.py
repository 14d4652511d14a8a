"""From a :class:`RangeTable` and the samples chosen to a :class:`JointProblem`, and
the module positions of a start."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from estimation.uwb_calibration.geometry import bar_lengths, multilaterate
from estimation.uwb_calibration.problem import FloorRows, JointProblem, robot_pair_index

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.uwb_calibration.config import CalibrationConfig
    from estimation.uwb_calibration.problem import JointState
    from estimation.uwb_calibration.rounds import RangeTable
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["Assembly", "assemble", "start_positions", "with_contacts"]


@dataclass(frozen=True)
class Assembly:
    """A joint problem and how its unknowns map back to the table."""

    problem: JointProblem
    rounds: NDArray[np.intp]
    """(S,) the table's rounds used as samples."""
    slot: NDArray[np.intp]
    """(S, n): position index of each (sample, module), -1 where alpha = 0."""
    rows: NDArray[np.intp]
    """(k,) the table's robot-anchor rows in the problem, in its row order."""


def assemble(
    table: RangeTable,
    rounds: NDArray[np.intp],
    valid: NDArray[np.bool_],
    description: RobotDescription,
    free: NDArray[np.bool_],
    config: CalibrationConfig,
    *,
    use: NDArray[np.bool_] | None = None,
    floor: bool = True,
) -> Assembly:
    """The problem over samples ``rounds`` (S,) with alpha ``valid`` (R, n).

    Args:
        free: (A, 3) anchor coordinates to solve for.
        config: the sigmas and the offset prior.
        use: (k,) robot-anchor rows that may enter (outliers left out); default all.
        floor: with the floor terms (the robot rests on z = 0).
    """
    n = table.n_nodes
    slot = np.full((len(rounds), n), -1, dtype=np.intp)
    sub = valid[rounds]
    slot[sub] = np.arange(int(np.count_nonzero(sub)))
    sample_of = np.full(table.n_rounds, -1, dtype=np.intp)
    sample_of[rounds] = np.arange(len(rounds))
    s = sample_of[table.a_round]
    keep = s >= 0
    keep[keep] = slot[s[keep], table.a_module[keep]] >= 0
    if use is not None:
        keep &= use
    rows = np.flatnonzero(keep)
    j = table.a_module[rows]
    sr = sample_of[table.r_round]
    rr = sr >= 0
    rr[rr] = (slot[sr[rr], table.r_first[rr]] >= 0) & (slot[sr[rr], table.r_second[rr]] >= 0)
    first, second = table.r_first[rr], table.r_second[rr]
    rod = description.rod_nodes
    both = (slot[:, rod[:, 0]] >= 0) & (slot[:, rod[:, 1]] >= 0)
    si, ri = np.nonzero(both)
    problem = JointProblem(
        n_nodes=n,
        free=free,
        anchor_rows=(table.a_anchor[rows], j, slot[s[rows], j], table.a_range[rows]),
        robot_rows=(
            robot_pair_index(first, second, n),
            slot[sr[rr], first],
            slot[sr[rr], second],
            table.r_range[rr],
        ),
        bars=(slot[si, rod[ri, 0]], slot[si, rod[ri, 1]], bar_lengths(description)[ri]),
        position_sample=np.nonzero(sub)[0].astype(np.intp),
        range_sigma=config.range_sigma,
        bar_sigma=config.bar_sigma,
        offset_spread=config.offset_spread,
        floor=_floor_rows(slot, description, config.floor_sigma) if floor else None,
    )
    return Assembly(problem, rounds, slot, rows)


def _floor_rows(slot: NDArray[np.intp], description: RobotDescription, sigma: float) -> FloorRows:
    """A floor row per counted module of ``slot`` (S, n), no contact yet."""
    s, j = np.nonzero(slot >= 0)
    v = slot[s, j]
    delta = description.sensors.uwb.module_offset
    partner_module = np.empty(description.n_nodes, dtype=np.intp)
    rn = description.rod_nodes
    partner_module[rn[:, 0]], partner_module[rn[:, 1]] = rn[:, 1], rn[:, 0]
    w = slot[s, partner_module[j]]
    ratio = delta / bar_lengths(description)[description.node_rod[j]]
    exact = (w >= 0) if delta > 0.0 else np.ones(len(v), dtype=bool)
    return FloorRows(
        position=v,
        partner=np.where(exact & (delta > 0.0), w, v),
        scale=np.where(exact, 1.0 + ratio, 1.0),
        partner_scale=np.where(exact, ratio, 0.0),
        radius=description.node_radii[j],
        node=exact,
        contact=np.zeros(len(v), dtype=bool),
        sigma=sigma,
    )


def with_contacts(problem: JointProblem, state: JointState, slab: float) -> JointProblem:
    """``problem`` with its endcaps within ``slab`` m of the floor at ``state`` held at
    it (only those whose node height the rows know: both modules of the rod count, or
    there is no module offset)."""
    f = problem.floor
    if f is None:
        return problem
    low = f.heights(state.positions) < f.radius + slab
    return replace(problem, floor=replace(f, contact=f.node & low))


def start_positions(
    problem: JointProblem, anchors: NDArray[np.float64], offsets: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Every counted module position (V, 3) multilaterated from ``anchors`` (A, 3) and
    the robot-anchor ``offsets`` (A * n,): the start of a joint solve. Positions the
    ranges cannot place (a near-singular geometry) start at the anchors' centroid."""
    a, j, v, m = problem.anchor_rows
    pair = a * problem.n_nodes + j
    x, ok = multilaterate(v, anchors[a], m - offsets[pair], problem.n_positions)
    x[~ok] = np.mean(anchors, axis=0)
    return x
