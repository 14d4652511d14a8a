"""The calibrator: uncorrected UWB ranges in, anchors and offsets out (Caluwaerts et al. 2016
III-C).

:func:`calibrate_ranges` works on arrays, so that a lab can calibrate ranges its own
hardware logged; :func:`calibrate_samples` on the ``UwbRangeSample`` a bag or a
simulated run gives.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from estimation.ukf.filter import single_threaded_blas
from estimation.uwb_calibration.config import CalibrationConfig
from estimation.uwb_calibration.floor import (
    FloorHint,
    GravityRows,
    floor_from_gravity,
    floor_from_hint,
    lowest_floor,
    parse_floor_hint,
    to_floor_frame,
)
from estimation.uwb_calibration.geometry import chiral_quadruples, signed_volumes
from estimation.uwb_calibration.lm import global_covariance
from estimation.uwb_calibration.result import CalibrationError, CalibrationResult, residual_stats
from estimation.uwb_calibration.rounds import (
    at_sample_times,
    jump_outliers,
    merge_rounds,
    range_table,
    sample_rows,
)
from estimation.uwb_calibration.solve import Run, refine, refine_free, rested, solve_table
from estimation.uwb_calibration.timing import fitted_to_rates
from estimation.uwb_calibration.verdict import judge
from tensegrity_gym.model.kinematics import weighted_kabsch
from tensegrity_gym.model.samples import ImuSample, UwbRangeSample

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping, Sequence

    from numpy.typing import ArrayLike, NDArray

    from estimation.uwb_calibration.rounds import RangeTable
    from estimation.uwb_calibration.solve import Solved
    from estimation.uwb_calibration.timing import RangingRates
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["calibrate_ranges", "calibrate_samples"]

logger = logging.getLogger(__name__)


def calibrate_ranges(
    t: ArrayLike,
    module_i: ArrayLike,
    module_j: ArrayLike,
    ranges: ArrayLike,
    description: RobotDescription,
    *,
    known_anchors: Mapping[int, Sequence[float]] | NDArray[np.float64] | None = None,
    config: CalibrationConfig | None = None,
    rng: np.random.Generator | None = None,
    rounds: ArrayLike | None = None,
    gravity: GravityRows | None = None,
    floor_hint: FloorHint | str | None = None,
) -> CalibrationResult:
    """Calibrate anchors and offsets from rows ``(t, module_i, module_j, range)``.

    Args:
        t: time of each range (s), (k,).
        module_i, module_j: module ids of each range, (k,), either order: 0..n-1 the
            robot's endcap modules (n = ``description.n_nodes``), n.. the anchors (as
            many as the description lists; their positions there are not used).
        ranges: uncorrected ranges m_ij (m), (k,): true distance + o_ij + noise.
        description: the robot: rod lengths (bar terms), module offset, endcap radii
            (the floor), resting pose (the start, the handedness).
        known_anchors: anchors measured by hand, {index: (x, y, z)} or (A, 3) with NaN
            rows for unknown ones, in the lab's frame; at least 3 not on a line. The
            result is then in that frame.
        config: the settings; default :class:`CalibrationConfig`.
        rng: draws the samples; the same generator state gives the same result.
        rounds: a round index per row (all rows of one ``UwbRangeSample``); default:
            rows are grouped by time (``config.round_gap``).
        gravity: the rods' accelerometer readings, where the recording has them: they
            tell the floor when the robot did not rest on it.
        floor_hint: anchor heights above the floor (m) a lab knows, a
            :class:`~estimation.uwb_calibration.floor.FloorHint` or its text
            (``"0=4.7 1=4.5"``, ``"0,1,2,3=4.6"``); used where the robot did not rest on
            the floor.

    A robot rolled about on the floor should start at rest in its description's
    resting pose (as a simulated episode does): the floor is then the one it rests
    on. A robot carried about may start any way round; the floor then comes from
    ``gravity``, else ``floor_hint`` (see :mod:`~estimation.uwb_calibration.floor`),
    else the result says it is not known. Ideally the robot travels far across the
    anchors.

    Raises:
        CalibrationError: too few usable samples (rounds in which some module ranged
            at least 4 anchors), or an anchor no counted module ranged.
        ValueError: malformed rows, known anchors or floor hint.
    """
    clock = time.perf_counter()
    config = config or CalibrationConfig()
    rng = rng if rng is not None else np.random.default_rng(0)
    hint = parse_floor_hint(floor_hint) if isinstance(floor_hint, str) else floor_hint
    if hint is not None:
        hint.check(len(description.anchors))
    table, config, rates = _table(t, module_i, module_j, ranges, description, config, rounds)
    anchor_jumps, robot_jumps = jump_outliers(table, config.jump_threshold)
    jumps = np.concatenate([anchor_jumps, robot_jumps])
    screened = float(np.mean(jumps)) if len(jumps) else 0.0
    table = table.subset(~anchor_jumps, ~robot_jumps)
    valid, usable = _usable(table, config)
    known = _known(known_anchors, table.n_anchors)
    run = Run(table, usable, valid, description, config, rng)
    result = _solved_and_framed(run, known, gravity, hint)
    result = _handed(result, hint)
    verdict, flagged = judge(result, config)
    result = replace(result, verdict=verdict, flagged_anchors=flagged)
    extras = result.extras | {"screened_share": screened, "sample_period": config.sample_period,
                              "window": config.window, "module_rate": rates.module,
                              "pair_rate": rates.pair}  # fmt: skip
    result = replace(result, wall_time=time.perf_counter() - clock, extras=extras)
    logger.info("UWB calibration: %s (%.1f s)", result.verdict, result.wall_time)
    return result


def _solved_and_framed(
    run: Run,
    known: NDArray[np.float64] | None,
    gravity: GravityRows | None,
    hint: FloorHint | None,
) -> CalibrationResult:
    """The joint solve of ``run``, its handedness settled, in its frame: the known
    anchors', the floor the robot rested on, or (a carried robot) the floor gravity or
    the hint tells; not yet judged."""
    table, description = run.table, run.description
    to_lab: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    # The solve's dense blocks are a few hundred rows: BLAS threads only get in the way.
    with single_threaded_blas():
        solved = solve_table(run)
        carried = known is None and not rested(solved)
        if known is not None:
            solved, to_lab = _with_known(run, solved, known)
        elif carried:
            solved = refine_free(run, solved)
        solved, mirror, votes = _settle_mirror(solved, description, to_lab is None)
        result = _result(table, solved, run.usable, run.config, mirror, votes, carried)
    if to_lab is not None:
        R, shift = to_lab
        return replace(result, anchors=result.anchors @ R.T + shift, frame="known", floor="known")
    if carried:
        return _on_floor(result, solved, replace(run, on_floor=False), gravity, hint)
    return result


def calibrate_samples(
    samples: Iterable[UwbRangeSample | ImuSample], description: RobotDescription,
    **kwargs: object,
) -> CalibrationResult:  # fmt: skip
    """:func:`calibrate_ranges` on recorded or simulated ``UwbRangeSample`` rounds (each
    one round), with the ``ImuSample`` among them as its ``gravity``. ``kwargs`` as
    :func:`calibrate_ranges` takes them."""
    rows = list(samples)
    ranges_only = [s for s in rows if isinstance(s, UwbRangeSample)]
    imu = [s for s in rows if isinstance(s, ImuSample)]
    t, i, j, ranges, index = sample_rows(ranges_only)
    if imu and "gravity" not in kwargs:
        kwargs["gravity"] = GravityRows(
            np.array([s.t for s in imu]), np.array([s.rod for s in imu], dtype=np.intp),
            np.array([s.accel for s in imu], dtype=np.float64).reshape(-1, 3),
        )  # fmt: skip
    return calibrate_ranges(t, i, j, ranges, description, rounds=index, **kwargs)  # type: ignore[arg-type]


def _handed(result: CalibrationResult, hint: FloorHint | None) -> CalibrationResult:
    """``result`` with the handedness the hint's three counter-clockwise anchors give,
    where the robot's shape left it undecided (mirrored through the x-z plane where
    they turn the other way); where the shape decided it and the hint disagrees, that
    is noted for the verdict. Only in a floor frame: without up there is no "seen from
    above"."""
    if hint is None or result.frame != "floor":
        return result
    sign = hint.counterclockwise_sign(result.anchors)
    if sign == 0.0:
        return result
    if result.mirror == "undecided":
        anchors = result.anchors * np.array([1.0, -1.0, 1.0]) if sign < 0 else result.anchors
        return replace(result, anchors=anchors, mirror="hint")
    if sign < 0:
        return replace(result, extras=result.extras | {"handedness_disagrees": 1.0})
    return result


def _on_floor(
    result: CalibrationResult,
    solved: Solved,
    run: Run,
    gravity: GravityRows | None,
    hint: FloorHint | None,
) -> CalibrationResult:
    """``result`` of a free-frame solve (the robot did not rest on the floor) turned
    onto the floor that the IMUs' gravity and the lab's hint tell; in the anchors'
    gauge, the floor unknown, where neither does."""
    d, positions = run.description, solved.state.positions
    up: NDArray[np.float64] | None = None
    source, extras = "none", dict(result.extras)
    if gravity is not None:
        times = run.table.round_times[solved.assembly.rounds]
        found = floor_from_gravity(positions, solved.assembly.slot, times, gravity, d,
                                   0.5 * run.config.sample_period)  # fmt: skip
        if found is not None:
            up, source = found[0], "gravity"
            extras["gravity_rows"] = float(found[1])
    height = 0.0 if up is None else -lowest_floor(up, positions, d)
    fit = floor_from_hint(result.anchors, hint, positions, up) if hint is not None else None
    if fit is not None:
        up, height, misfit = fit
        source = "gravity+hint" if source == "gravity" else "hint"
        extras["floor_hint_misfit"] = misfit
    if up is None:
        return replace(result, anchors=result.anchors_in_anchor_frame(), frame="anchors",
                       floor="none", extras=extras)  # fmt: skip
    R, shift = to_floor_frame(result.anchors, up, height)
    return replace(result, anchors=result.anchors @ R.T + shift, floor=source, extras=extras)


_SLOWEST_SAMPLE = 5.0
"""s: a sample longer than this (ranging too sparse) is refused, not solved."""


def _table(
    t: ArrayLike,
    module_i: ArrayLike,
    module_j: ArrayLike,
    ranges: ArrayLike,
    description: RobotDescription,
    config: CalibrationConfig,
    rounds: ArrayLike | None,
) -> tuple[RangeTable, CalibrationConfig, RangingRates]:
    """The rows as a table of samples (each range moved to its sample's time), the
    settings fitted to the rows' ranging rates, and those rates."""
    n_anchors = len(description.anchors)
    if n_anchors < 4:
        raise CalibrationError(
            f"{description.name}: {n_anchors} anchors in the description, 4 needed to place "
            "a module (sensors.uwb.anchors lists them; their positions are not used)"
        )
    gap = config.round_gap if config.round_gap is not None else 0.5 / description.sensors.uwb.rate
    table = range_table(
        t, module_i, module_j, ranges,
        n_nodes=description.n_nodes, n_anchors=n_anchors, round_gap=gap, rounds=rounds,
    )  # fmt: skip
    config, rates = fitted_to_rates(config, table, n_anchors)
    if config.sample_period > _SLOWEST_SAMPLE:
        raise CalibrationError(
            f"the recording ranges each robot module {rates.module:.2g} times a second "
            f"(all anchors together): a module would need {config.sample_period:.0f} s to "
            f"range {config.min_anchor_ranges} anchors, over which the robot does not "
            "stand still"
        )
    table = merge_rounds(table, config.sample_period)
    # Each range moved to its sample's time, the rates fitted to the screened ranges.
    anchor_jumps, robot_jumps = jump_outliers(table, config.jump_threshold)
    table = at_sample_times(table, config.rate_span, (~anchor_jumps, ~robot_jumps))
    return table, config, rates


def _usable(
    table: RangeTable, config: CalibrationConfig
) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """alpha (R, n) and the usable rounds; CalibrationError where the data cannot decide."""
    valid = table.valid_modules(config.min_anchor_ranges)
    usable = np.flatnonzero(valid.any(axis=1))
    if len(usable) < config.min_samples:
        raise CalibrationError(
            f"{len(usable)} usable samples ({config.sample_period:g} s of UWB rounds in which "
            f"a module ranged at least {config.min_anchor_ranges} anchors) of "
            f"{table.n_rounds}, {config.min_samples} needed"
        )
    counted = valid[table.a_round, table.a_module]
    seen = np.bincount(table.a_anchor[counted], minlength=table.n_anchors)
    if (seen == 0).any():
        a = int(np.flatnonzero(seen == 0)[0])
        raise CalibrationError(
            f"anchor {a} (module {table.n_nodes + a}) has no range from a module that "
            f"ranged {config.min_anchor_ranges} anchors at once: it cannot be placed"
        )
    return valid, usable


def _known(
    known: Mapping[int, Sequence[float]] | NDArray[np.float64] | None, n_anchors: int
) -> NDArray[np.float64] | None:
    """Known anchors as (A, 3) with NaN rows, checked: at least 3, not on one line."""
    if known is None:
        return None
    out = np.full((n_anchors, 3), np.nan)
    if isinstance(known, np.ndarray):
        if known.shape != (n_anchors, 3):
            raise ValueError(f"known_anchors must be ({n_anchors}, 3), got {known.shape}")
        out[:] = known
    else:
        for a, xyz in known.items():
            if not 0 <= int(a) < n_anchors or len(xyz) != 3:
                raise ValueError(
                    f"known_anchors[{a!r}] must be an anchor 0..{n_anchors - 1} -> (x, y, z)"
                )
            out[int(a)] = np.asarray(xyz, dtype=np.float64)
    held = np.all(np.isfinite(out), axis=1)
    pts = out[held]
    if len(pts) < 3 or np.linalg.matrix_rank(pts - pts.mean(axis=0), tol=1e-3) < 2:
        raise ValueError(
            f"known_anchors: {int(held.sum())} anchors given, "
            "at least 3 not on one line needed to fix a frame"
        )
    return out


def _with_known(
    run: Run, solved: Solved, known: NDArray[np.float64]
) -> tuple[Solved, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """The solve with the known anchors held, in the floor frame, and the rigid motion
    (R, shift) from the floor frame to the lab's, fitted on the known anchors."""
    held = np.all(np.isfinite(known), axis=1)
    R, shift = weighted_kabsch(solved.state.anchors[held], known[held], np.ones(int(held.sum())))
    in_floor = (known - shift) @ R
    anchors = np.where(held[:, None], in_floor, solved.state.anchors)
    start = replace(solved.state, anchors=anchors)
    return refine(run, start, solved.start, held), (R, shift)


def _settle_mirror(
    solved: Solved, description: RobotDescription, may_flip: bool
) -> tuple[Solved, str, tuple[int, int]]:
    """Compare the robot's handedness in the solution with its description's, on the
    samples where four modules of one of its largest tetrahedra count; mirror the
    solution (y -> -y) where most disagree. Returns the (votes agreeing, votes)."""
    quads, volumes = chiral_quadruples(description)
    slot = solved.assembly.slot
    present = np.all(slot[:, quads] >= 0, axis=2)  # (S, q)
    s, q = np.nonzero(present)
    if len(s) == 0:
        return solved, "undecided", (0, 0)
    pos = solved.state.positions[slot[s[:, None], quads[q]]]  # (m, 4, 3)
    measured = signed_volumes(pos, np.arange(4)[None, :].astype(np.intp))[:, 0]
    agree = int(np.count_nonzero(np.sign(measured) == np.sign(volumes[q])))
    votes = (agree, len(s))
    if abs(2 * agree - len(s)) < 2.0 * np.sqrt(len(s)):
        return solved, "undecided", votes  # within two standard deviations of chance
    if 2 * agree > len(s) or not may_flip:
        return solved, "kept", votes
    flip = np.array([1.0, -1.0, 1.0])
    state = replace(solved.state, anchors=solved.state.anchors * flip,
                    positions=solved.state.positions * flip)  # fmt: skip
    return replace(solved, state=state), "flipped", votes


def _residuals(solved: Solved) -> NDArray[np.float64]:
    """Measured less modelled range (m) of every robot-anchor row of the final solve."""
    p, s = solved.assembly.problem, solved.state
    a, j, v, m = p.anchor_rows
    model = np.linalg.norm(s.anchors[a] - s.positions[v], axis=1) + s.offsets[a * p.n_nodes + j]
    return np.asarray(m - model)


def _result(
    table: RangeTable,
    solved: Solved,
    usable: NDArray[np.intp],
    config: CalibrationConfig,
    mirror: str,
    votes: tuple[int, int],
    free_frame: bool = False,
) -> CalibrationResult:
    """The result in the solve's frame, not yet judged."""
    p, s = solved.assembly.problem, solved.state
    n, A = table.n_nodes, table.n_anchors
    a, j, _, _ = p.anchor_rows
    r = _residuals(solved)
    spread = 1.4826 * float(np.median(np.abs(r - np.median(r)))) if len(r) else np.nan
    threshold = max(config.outlier_sigmas * spread, 2.0 * config.loss_scale * config.range_sigma)
    times = table.round_times[solved.assembly.rounds[p.position_sample[p.anchor_rows[2]]]]
    anchor_stats = tuple(residual_stats(r[a == k], threshold, times[a == k]) for k in range(A))
    pair_stats = tuple(
        tuple(residual_stats(r[(a == k) & (j == q)], threshold) for q in range(n)) for k in range(A)
    )
    cov = global_covariance(p, s, config.final_loss, config.loss_scale)
    sigma = _anchor_sigma(cov, p.anchor_columns(), s.anchors, free_frame) * max(
        spread / config.range_sigma, 1.0
    )
    pair, _, _, _ = p.robot_rows
    rr = np.zeros((n, n), dtype=np.intp)
    iu = np.triu_indices(n, 1)
    rr[iu] = np.bincount(pair, minlength=n * (n - 1) // 2)
    contact = p.floor.contact.mean() if p.floor is not None and len(p.floor.contact) else 0.0
    extras = {"residual_spread": spread, "outlier_threshold": threshold,
              "contact_share": float(contact), "mirror_votes": float(votes[1]),
              "mirror_agree": float(votes[0])}  # fmt: skip
    return CalibrationResult(
        anchors=s.anchors.copy(), offsets=_offset_matrix(s.offsets, s.mean_offset, n, A),
        mean_offset=float(s.mean_offset), anchor_sigma=np.asarray(sigma),
        anchor_stats=anchor_stats, pair_stats=pair_stats, robot_pair_count=rr + rr.T,
        n_samples=len(solved.assembly.rounds), n_usable=len(usable), n_rounds=table.n_rounds,
        cost=float(solved.cost), verdict="good", flagged_anchors=(), mirror=mirror, extras=extras,
    )  # fmt: skip


def _anchor_sigma(
    cov: NDArray[np.float64],
    column: NDArray[np.intp],
    anchors: NDArray[np.float64],
    free_frame: bool = False,
) -> NDArray[np.float64]:
    """Standard error (m) of each anchor (A,) from the global covariance ``cov``, with
    what a shift along the floor and a turn about z of the whole constellation would
    explain taken out (the gauge's choice of which anchors to hold); in a free frame,
    what any shift and turn would."""
    A = len(anchors)
    flat = column.ravel()
    full = np.zeros((3 * A, 3 * A))
    solved = np.flatnonzero(flat >= 0)
    full[np.ix_(solved, solved)] = cov[np.ix_(flat[solved], flat[solved])]
    rel = anchors - anchors.mean(axis=0)
    # Columns: shifts along x, y, z, then turns about z, x, y (each anchor's motion).
    motions = np.zeros((A, 3, 6))
    motions[:, 0, 0] = motions[:, 1, 1] = motions[:, 2, 2] = 1.0
    motions[:, 0, 3], motions[:, 1, 3] = -rel[:, 1], rel[:, 0]
    motions[:, 1, 4], motions[:, 2, 4] = -rel[:, 2], rel[:, 1]
    motions[:, 2, 5], motions[:, 0, 5] = -rel[:, 0], rel[:, 2]
    kept = [0, 1, 2, 3, 4, 5] if free_frame else [0, 1, 3]
    T = motions[:, :, kept].reshape(3 * A, len(kept))
    P = np.eye(3 * A) - T @ np.linalg.pinv(T)
    var = np.diag(P @ full @ P.T).reshape(A, 3).sum(axis=1)
    return np.asarray(np.sqrt(np.maximum(var, 0.0)))


def _offset_matrix(
    offsets: NDArray[np.float64], mean: float, n: int, n_anchors: int
) -> NDArray[np.float64]:
    """The symmetric (n + A, n + A) o_ij from the solve's pair vector; anchor-anchor
    pairs (never ranged) hold the mean, the diagonal 0."""
    out = np.full((n + n_anchors, n + n_anchors), mean)
    robot_anchor = offsets[: n_anchors * n].reshape(n_anchors, n)
    out[n:, :n] = robot_anchor
    out[:n, n:] = robot_anchor.T
    iu = np.triu_indices(n, 1)
    block = np.zeros((n, n))
    block[iu] = offsets[n_anchors * n :]
    out[:n, :n] = block + block.T
    np.fill_diagonal(out, 0.0)
    return out
