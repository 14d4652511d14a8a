"""From a :class:`RangeTable` to the solved joint problem: start, growth, final solve.

No anchor position is needed. The frame is the floor's from the start: the robot
begins at rest in its description's resting pose (z up, the floor at z = 0), so the
anchors multilaterated from its modules in the first window come out in that frame,
up to a turn about z, which the gauge fixes (anchor 0 above the origin, anchor 1
above the +x axis). The floor terms then keep every endcap on or above z = 0 and those
that touch it on it, which pins the tilt that the anchors' heights leave loose (the
robot moves in a slab a few tenths of a metre thick).

A window's robot is small against the anchor distances, so its anchors are rough.
The solve grows from it: over the first 2 s of the run, then 4, 8, ... until it spans
the whole run, each stage starting from the last, so that the robot's travel sharpens
the constellation step by step instead of asking one solve to find it from afar.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from estimation.uwb_calibration.assemble import assemble, start_positions, with_contacts
from estimation.uwb_calibration.initialise import (
    bar_offset,
    round_windows,
    window_anchors,
    window_shape,
)
from estimation.uwb_calibration.lm import solve_joint, solve_positions
from estimation.uwb_calibration.problem import JointState

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.uwb_calibration.assemble import Assembly
    from estimation.uwb_calibration.config import CalibrationConfig
    from estimation.uwb_calibration.rounds import RangeTable
    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "Run",
    "Solved",
    "floor_gauge",
    "free_gauge",
    "gauge_mask",
    "refine",
    "refine_free",
    "rested",
    "solve_table",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Run:
    """A calibration run's data and what the solve is asked: everything every stage
    needs."""

    table: RangeTable
    usable: NDArray[np.intp]
    """(U,) rounds with a module ranging enough anchors (alpha = 1 somewhere)."""
    valid: NDArray[np.bool_]
    """(R, n) alpha of eq. 9."""
    description: RobotDescription
    config: CalibrationConfig
    rng: np.random.Generator
    on_floor: bool = True
    """The robot rests on the floor z = 0 (the floor terms); False: a free frame."""


@dataclass(frozen=True)
class Solved:
    """The final joint solve."""

    assembly: Assembly
    state: JointState
    cost: float
    """Robust cost per measurement row."""
    start: int
    """Which start won."""


def gauge_mask(
    n_anchors: int, held: NDArray[np.bool_] | None = None, third: int | None = None
) -> NDArray[np.bool_]:
    """(A, 3) anchor coordinates solved for in the floor frame: all but anchor 0's x, y
    and anchor 1's y (the turn about z and the shift along the floor); with ``held``
    (A,) anchors given, all of theirs are held and the gauge is theirs instead. With
    ``third`` (no floor: a free frame, :func:`free_gauge`) anchor 0's z, anchor 1's z
    and anchor ``third``'s z are held too."""
    free = np.ones((n_anchors, 3), dtype=bool)
    if held is not None and held.any():
        free[held] = False
        return free
    free[0, :2] = False
    free[1, 1] = False
    if third is not None:
        free[0, 2] = free[1, 2] = free[third, 2] = False
    return free


def free_gauge(anchors: NDArray[np.float64]) -> tuple[NDArray[np.float64], int]:
    """Anchors (A, 3) turned and shifted so that anchor 0 is at the origin, anchor 1
    on +x and the anchor farthest from their line (returned) in the x-y plane: the
    gauge of a frame no floor fixes (a proper turn: the handedness is kept)."""
    a = anchors - anchors[0]
    x = a[1] / np.linalg.norm(a[1])
    across = a - np.outer(a @ x, x)
    third = int(np.argmax(np.linalg.norm(across, axis=1)))
    y = across[third] / np.linalg.norm(across[third])
    out = a @ np.stack([x, y, np.cross(x, y)]).T
    out[0] = 0.0
    out[1, 1:] = out[third, 2] = 0.0  # exactly, not to the last bit
    return np.asarray(out), third


def floor_gauge(anchors: NDArray[np.float64]) -> NDArray[np.float64]:
    """Anchors (A, 3) of a frame with the floor at z = 0, turned about z and shifted
    along the floor so that anchor 0 is above the origin and anchor 1 above +x."""
    out = anchors - np.array([anchors[0, 0], anchors[0, 1], 0.0])
    angle = np.arctan2(out[1, 1], out[1, 0])
    c, s = np.cos(angle), np.sin(angle)
    turn = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    out = out @ turn.T
    out[0, :2] = out[1, 1] = 0.0  # exactly, not to the last bit
    return np.asarray(out)


def _stage(
    run: Run, rounds: NDArray[np.intp], free: NDArray[np.bool_], start: JointState, loss: str
) -> tuple[Assembly, JointState, float]:
    """One solve over samples ``rounds`` from ``start``'s anchors and offsets: the
    positions multilaterated and refined alone, then the joint solve, the floor
    contacts re-read before each pass."""
    config, table = run.config, run.table
    asm = assemble(table, rounds, run.valid, run.description, free, config, floor=run.on_floor)
    p = asm.problem
    n = table.n_nodes
    positions = start_positions(p, start.anchors, start.offsets[: table.n_anchors * n])
    state = JointState(start.anchors, start.offsets, start.mean_offset, positions)
    held = replace(p, free=np.zeros_like(free), hold_offsets=True)
    cost = np.inf
    for _ in range(config.floor_passes):
        p = with_contacts(p, state, config.floor_slab)
        state = solve_positions(replace(held, floor=p.floor), state, loss, config.loss_scale)
        solution = solve_joint(p, state, loss, config.loss_scale, config.max_iterations)
        state, cost = solution.state, solution.cost
    return replace(asm, problem=p), state, cost


def _window_start(
    table: RangeTable, description: RobotDescription, window: int, config: CalibrationConfig
) -> JointState:
    """Anchors from window ``window`` in the floor gauge, every offset the bars' guess."""
    windows = round_windows(table, config.window)
    robot = windows[table.r_round] == window
    offset = bar_offset(table, description, robot)
    shape = window_shape(table, description, robot, offset)
    anchors = window_anchors(table, windows[table.a_round] == window, shape, offset)
    if not np.all(np.isfinite(anchors)):
        centre = np.nanmean(anchors, axis=0) if np.isfinite(anchors).any() else np.zeros(3)
        anchors = np.where(np.isfinite(anchors), anchors, centre + 1.0)
    n, A = table.n_nodes, table.n_anchors
    offsets = np.full(A * n + n * (n - 1) // 2, offset)
    return JointState(floor_gauge(anchors), offsets, offset, np.zeros((0, 3)))


def _spread(rounds: NDArray[np.intp], count: int, rng: np.random.Generator) -> NDArray[np.intp]:
    """At most ``count`` of ``rounds`` (sorted), one drawn from each of ``count`` equal
    strata, so that the samples cover the run."""
    if len(rounds) <= count:
        return rounds
    edges = np.linspace(0, len(rounds), count + 1)
    picks = np.floor(edges[:-1] + rng.random(count) * np.diff(edges)).astype(np.intp)
    return rounds[np.minimum(picks, len(rounds) - 1)]


def _grow(run: Run, start: JointState) -> JointState:
    """Stages over the first 2, 4, 8, ... s of the run, each from the last."""
    free = gauge_mask(run.table.n_anchors)
    times = run.table.round_times[run.usable] - run.table.round_times[0]
    span, state = run.config.first_span, start
    while True:
        within = run.usable[times <= span]
        rounds = _spread(within, run.config.start_samples, run.rng)
        _, state, cost = _stage(run, rounds, free, state, run.config.loss)
        logger.debug("stage over %.0f s, %d samples: cost %.4f", span, len(rounds), cost)
        if len(within) == len(run.usable):
            return state
        span *= 2.0


def solve_table(run: Run) -> Solved:
    """Each start (one of the first windows of the run) grown over the run; the
    cheapest on a common set of samples refined on up to ``max_samples`` samples with
    the final loss."""
    table, config = run.table, run.config
    windows = round_windows(table, config.window)
    first = np.unique(windows[table.a_round])[: config.n_starts]
    free = gauge_mask(table.n_anchors)
    common = _spread(run.usable, config.start_samples, run.rng)
    best, best_key, best_start = None, (True, np.inf), 0
    for k, w in enumerate(first):
        grown = _grow(run, _window_start(table, run.description, int(w), config))
        candidates = [grown]
        if _below_floor(grown):
            candidates += [_reflected(grown, _under_floor(grown)), _reflected(grown)]
        for candidate in candidates:
            _, state, cost = _stage(run, common, free, candidate, config.loss)
            logger.debug("start %d (window %d): cost %.4f", k, w, cost)
            # An anchor under the floor is impossible whatever the cost: a solution
            # with all anchors above it is taken before any that has one below.
            key = (_below_floor(state), cost)
            if key < best_key:
                best, best_key, best_start = state, key, k
    assert best is not None
    return refine(run, best, best_start)


_FLOOR_TOLERANCE = 0.05  # m: an anchor this far below the floor is on the wrong side


def _under_floor(state: JointState) -> NDArray[np.bool_]:
    """(A,) the anchors of ``state`` that lie under the floor the robot rests on."""
    return np.asarray(state.anchors[:, 2] < -_FLOOR_TOLERANCE)


def _below_floor(state: JointState) -> bool:
    """Whether an anchor of ``state`` lies under the floor the robot rests on."""
    return bool(_under_floor(state).any())


def _reflected(state: JointState, which: NDArray[np.bool_] | None = None) -> JointState:
    """``state`` with its anchors (those of ``which`` (A,), else all) mirrored through
    the horizontal plane at the robot's mean height. The robot moves in a slab a few
    tenths of a metre thick, so ranges alone barely tell an anchor from its mirror
    image through that slab; a solve can settle on the mirror of the whole
    constellation, or of some anchors only (each is placed by its own ranges), with
    those under the floor."""
    h = float(np.mean(state.positions[:, 2])) if len(state.positions) else 0.0
    anchors = state.anchors.copy()
    rows = slice(None) if which is None else which
    anchors[rows, 2] = 2.0 * h - anchors[rows, 2]
    return replace(state, anchors=anchors, positions=np.zeros((0, 3)))


def refine(
    run: Run,
    start: JointState,
    start_index: int = 0,
    held: NDArray[np.bool_] | None = None,
    third: int | None = None,
) -> Solved:
    """The final solve from ``start`` on up to ``max_samples`` samples; ``held`` (A,)
    anchors keep their positions in ``start`` (known anchors); ``third`` as
    :func:`gauge_mask` takes it (a free frame)."""
    rounds = _spread(run.usable, run.config.max_samples, run.rng)
    free = gauge_mask(run.table.n_anchors, held, third)
    asm, state, cost = _stage(run, rounds, free, start, run.config.final_loss)
    return Solved(asm, state, cost, start_index)


_RESTED_SHARE = 0.5
"""Share of samples with an endcap on the floor above which the robot rested on it."""


def rested(solved: Solved) -> bool:
    """Whether the robot of ``solved`` rested on the floor its start assumed: an endcap
    touches it in most samples. A rolled robot stands on its base in nearly every
    sample (97-100 % on the simulated runs); a carried one, whose frame the floor terms
    only bend, touches it in a minority of them (those the bent frame squashes onto it:
    about 30 % on a carried SUPERball), though then often with several endcaps, so
    that the mean count does not tell the two apart."""
    p = solved.assembly.problem
    if p.floor is None:
        return False
    touching = p.position_sample[p.floor.position[p.floor.contact]]
    per_sample = np.bincount(touching, minlength=len(solved.assembly.rounds))
    return bool(np.mean(per_sample >= 1) > _RESTED_SHARE)


def refine_free(run: Run, solved: Solved) -> Solved:
    """``solved`` solved again without the floor, in a free frame
    (:func:`free_gauge`): for a robot that did not rest on the floor (carried)."""
    anchors, third = free_gauge(solved.state.anchors)
    start = replace(solved.state, anchors=anchors, positions=np.zeros((0, 3)))
    return refine(replace(run, on_floor=False), start, solved.start, third=third)
