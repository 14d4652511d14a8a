"""The UWB calibration a simulated lab would make (issue 15, Caluwaerts et al. 2016 section III-C):
record the robot rolling under its gait in the lab's world, calibrate the anchors and
offsets from the recorded ranges alone, and cache the result on disk.

``gym.make(..., calibration="estimated")`` (the default) hands the estimators this
instead of the simulator's own anchors and offsets. The calibration run drives the robot
with the truth (the oracle) so that it does not depend on any estimator: a lab moves
its robot around by hand or by its gait the same way.

The calibrator fixes its frame by convention from the anchors (its floor frame: z = 0 on
the floor, up; see :mod:`estimation.uwb_calibration`). A lab's world frame is its floor
plan's, and the plan says where the anchors were meant to stand (the description's
layout): the result is turned and shifted in the ground plane to fit it best
(:func:`onto_layout`). The simulator's anchors stand near the layout, not on it, so
nothing of where they really are is handed over.

A cached calibration is trusted only after a check, as a lab checks its calibration
before a session: it must be this scene's (anchor and module counts, robot, anchors
near the floor plan: :func:`~estimation.uwb_calibration.trust.scene_mismatch`) and
explain the first :data:`CHECK_SECONDS` of ranges of a fresh run in the world within a
few times its own residuals (:func:`~estimation.uwb_calibration.trust.range_fit`);
otherwise the calibration is made again, and the log says why.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from numbers import Real
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from estimation.uwb_calibration import (
    CalibrationConfig,
    CalibrationError,
    CalibrationFileError,
    calibrate_samples,
    load_calibration,
    save_calibration,
)
from estimation.uwb_calibration.trust import FIT_MIN_RANGES, range_fit, scene_mismatch
from hardware.recording import MemorySink, RecordingBackend
from tensegrity_gym.envs.calibration import (
    CALIBRATION_SECONDS,
    as_uwb,
    cache_path,
    check_cache_path,
    check_calibration,
)
from tensegrity_gym.envs.factory import make_env
from tensegrity_gym.model.kinematics import yaw_kabsch
from tensegrity_gym.model.samples import UwbRangeSample
from tensegrity_gym.sim.engines import DEFAULT_ENGINE
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from collections.abc import Sequence
    from pathlib import Path

    from numpy.typing import NDArray

    from estimation.uwb_calibration import CalibrationFile, CalibrationResult
    from estimation.uwb_calibration.trust import RangeFit
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import UwbCalibration
    from tensegrity_gym.model.samples import ImuSample
    from tensegrity_gym.sim.sensors import UwbModel

__all__ = [
    "CALIBRATION_SECONDS",
    "CHECK_SECONDS",
    "MAX_SECONDS",
    "SPAWN_SHARE",
    "CalibrationRun",
    "check_seconds",
    "estimated_uwb_calibration",
    "lab_calibration",
    "min_seconds",
    "onto_layout",
    "record_calibration_run",
]

logger = logging.getLogger(__name__)

EPISODE_SECONDS = 10.0
"""s per leg: the robot is put down at a random spot and heading, then rolls; so that
it stays among the anchors instead of rolling out of their area in one long run."""
LEG_GAP = 10.0
"""s between legs in the recorded times, so that no ranging round spans two legs."""
MAX_SECONDS = 3600.0
"""s: the longest calibration run taken. The calibrator solves on at most
``CalibrationConfig.max_samples`` (1000) samples of 0.2 s, 200 s of ranging, spread
over the run: an hour spreads them 18 times thinner and gains nothing more, while its
simulation alone takes minutes (the 120 s run: 7 s on the 3-bar robot). Beyond it a
typo (``1e9``) would simulate for years."""
CHECK_SECONDS = 3.0
"""s of a fresh run's ranges a cached calibration is checked against: 45 UWB rounds,
650-2800 robot-anchor ranges on the presets (over 80 per anchor), in 0.1-0.3 s of
simulation (1.5 s in a process that has not settled the robot yet)."""
CHECK_STREAM = 1
"""With the world seed, seeds the check run's legs (``default_rng((world_seed,
CHECK_STREAM))``) apart from the calibration run's: the same world, other spots and
noise, so that a calibration is checked on ranges it was not fitted to."""


def min_seconds(description: RobotDescription | None = None) -> float:
    """s: the shortest calibration run that can give the calibrator its
    ``min_samples`` (60) samples: one sample per ``sample_period`` (0.2 s) or per UWB
    round where rounds are rarer (``description.sensors.uwb.rate``); 12 s at 15 Hz.
    With packets lost a run this short may still come out a few samples short (a
    ``CalibrationError`` with the counts); the default run is ten times longer."""
    config = CalibrationConfig()
    rate = description.sensors.uwb.rate if description is not None else math.inf
    return config.min_samples * max(config.sample_period, 1.0 / rate)


def check_seconds(
    seconds: object, description: RobotDescription | None = None, *, where: str = "calibrate"
) -> float:
    """``seconds`` (the calibration run's length) as a float in
    [:func:`min_seconds`, :data:`MAX_SECONDS`], or a one-line ValueError
    ``"{where}: seconds=...: must be ..."`` naming the range."""
    low = min_seconds(description)
    if not isinstance(seconds, bool) and isinstance(seconds, Real):
        value = float(seconds)
        if low <= value <= MAX_SECONDS:  # False for NaN
            return value
    raise ValueError(
        f"{where}: seconds={seconds!r} must be a number of seconds in [{low:g}, "
        f"{MAX_SECONDS:g}] (the calibrator needs {CalibrationConfig().min_samples} samples "
        f"of {CalibrationConfig().sample_period:g} s; more than an hour gains nothing)"
    )


def onto_layout(anchors: NDArray[np.float64], layout: NDArray[np.float64]) -> NDArray[np.float64]:
    """``anchors`` (A, 3) of a floor frame (z = 0 the floor, up), turned about z and
    shifted in the ground plane to fit the lab's ``layout`` (A, 3) best (least squares,
    no mirror): the world frame of a lab is its floor plan's, and the plan says where
    the anchors were meant to stand."""
    R, t = yaw_kabsch(anchors, layout)
    return np.asarray(anchors @ R.T + t)


def lab_calibration(
    samples: Sequence[UwbRangeSample | ImuSample],
    description: RobotDescription,
    seed: int,
    floor_hint: str | None = None,
) -> CalibrationResult:
    """The calibrator's result on ``samples`` (UWB rounds, and the IMUs' readings that
    tell the floor of a carried robot), its anchors fitted onto the lab's floor plan
    (:func:`onto_layout`), its starts drawn from ``seed``; ``floor_hint`` as
    :func:`~estimation.uwb_calibration.calibrate_ranges` takes it."""
    result = calibrate_samples(
        samples, description, rng=np.random.default_rng(seed), floor_hint=floor_hint
    )
    return replace(result, anchors=onto_layout(result.anchors, description.anchors))


SPAWN_SHARE = 0.4
"""Legs start within this share of the anchors' horizontal span of their centre, so
that the robot passes near every side of the constellation: seen from one spot only, an
anchor's distance trades off against its offsets (2 cm errors at 0.25 of the span on
the 3-bar robot, 1-1.4 cm at 0.4)."""


def _spawn_radius(description: RobotDescription) -> float:
    a = description.anchors
    return SPAWN_SHARE * float(np.ptp(a[:, :2], axis=0).min()) if len(a) else 0.0


@dataclass(frozen=True)
class CalibrationRun:
    """A simulated calibration run: the ranges a lab records, and (for scoring only) the
    world they were ranged in."""

    samples: list[UwbRangeSample]
    """Every UWB round of the run, legs one after the other on one clock (s)."""
    frames: list[tuple[float, NDArray[np.float64]]]
    """(t s on the samples' clock, true node positions (n, 3) m) at every control period."""
    world: UwbModel
    """The run's UWB sensor model: its world's true anchors and offsets, and ranges
    again in that world (``world.sample``)."""
    sim_seconds: float
    """Wall time (s) the simulation took."""


def _leg_steps(seconds: float, control_period: float) -> list[int]:
    """Control periods of each leg: legs of :data:`EPISODE_SECONDS`, the last one
    shorter, so that the run ranges for ``seconds`` in all."""
    total = round(seconds / control_period)
    per_leg = round(EPISODE_SECONDS / control_period)
    return [min(per_leg, total - start) for start in range(0, total, per_leg)]


def record_calibration_run(
    description: RobotDescription,
    *,
    world_seed: int,
    seconds: float = CALIBRATION_SECONDS,
    control_period: float = 0.1,
    time_step: float = 0.001,
    engine: str = DEFAULT_ENGINE,
) -> CalibrationRun:
    """A calibration run of ``seconds`` (in [:func:`min_seconds`, :data:`MAX_SECONDS`])
    in the world ``world_seed`` draws: legs of :data:`EPISODE_SECONDS` under the
    robot's gait, the last one shorter, each from a reset drawn from the world seed;
    their times one after the other, :data:`LEG_GAP` apart."""
    seconds = check_seconds(seconds, description, where="record_calibration_run")
    legs = np.random.default_rng(world_seed)
    return _simulate(description, world_seed, seconds, legs, control_period, time_step, engine)


def _simulate(
    description: RobotDescription,
    world_seed: int,
    seconds: float,
    legs: np.random.Generator,
    control_period: float,
    time_step: float,
    engine: str = DEFAULT_ENGINE,
) -> CalibrationRun:
    """:func:`record_calibration_run` of any length, ``legs`` drawing each leg's reset."""
    env = make_env(
        description, estimator="oracle", calibration="true", world_seed=world_seed,
        spawn_radius=_spawn_radius(description), control_period=control_period,
        time_step=time_step, engine=engine,
    )  # fmt: skip
    world = cast("Any", env.backend).uwb
    sink = MemorySink()
    env.backend = RecordingBackend(env.backend, sink)
    clock = time.perf_counter()
    try:
        for steps in _leg_steps(seconds, control_period):
            obs, _ = env.reset(seed=int(legs.integers(2**31)))
            gait = FaceGait(description, env.task)
            for _ in range(steps):
                obs, _, terminated, _, _ = env.step(gait(obs))
                if terminated:
                    break
    finally:
        env.close()
    elapsed = time.perf_counter() - clock
    samples: list[UwbRangeSample] = []
    frames: list[tuple[float, NDArray[np.float64]]] = []
    for k, run in enumerate(sink.runs):
        shift = k * (EPISODE_SECONDS + LEG_GAP)
        for step in [run.start, *run.steps]:
            samples += [_shifted(s, shift) for s in step.samples if isinstance(s, UwbRangeSample)]
            if step.truth is not None:
                frames.append((step.truth.t + shift, step.truth.node_positions.copy()))
    return CalibrationRun(samples, frames, world, elapsed)


def _shifted(s: UwbRangeSample, shift: float) -> UwbRangeSample:
    return UwbRangeSample(s.t + shift, s.times + shift, s.pairs, s.ranges)


def _misfit(fit: RangeFit) -> str:
    """``fit`` for the log: the worst anchor's residual against its allowance."""
    if not fit.checked:
        return f"no anchor ranged {FIT_MIN_RANGES} times in {fit.n_ranges} ranges"
    return (f"anchor {fit.anchor}'s residual {1e3 * fit.found:.0f} mm, at most "
            f"{1e3 * fit.allowed:.0f} mm allowed, over {fit.n_ranges} ranges")  # fmt: skip


_CHECKED: dict[tuple[str, int, int], CalibrationFile] = {}
"""Cache files this process found fit, by path, modification time (ns) and size: each
is checked once per process, not at every env's first reset."""


def _cached(
    path: Path, description: RobotDescription, world_seed: int, **run: float
) -> CalibrationFile | None:
    """The calibration cached at ``path`` where it may be used, else None (logged: a
    warning naming the file and why it is made again)."""
    if not path.exists():
        return None
    stat = path.stat()
    key = (str(path), stat.st_mtime_ns, stat.st_size)
    if key in _CHECKED:
        return _CHECKED[key]
    try:
        cached = load_calibration(path)
    except CalibrationFileError as error:  # cut off, or not a calibration at all
        logger.warning("calibration cache %s unreadable (%s); calibrating again", path, error)
        return None
    reason = scene_mismatch(cached, description, robot=cached.robot)
    if reason is None and cached.result is not None and cached.result.quality == "failed":
        reason = f"its verdict is {cached.result.verdict!r}"  # never cached by this module
    if reason is not None:
        logger.warning("calibration cache %s does not fit %s (%s); calibrating again",
                       path, description.name, reason)  # fmt: skip
        return None
    legs = np.random.default_rng((world_seed, CHECK_STREAM))
    checked = _simulate(description, world_seed, CHECK_SECONDS, legs, run["control_period"],
                        run["time_step"])  # fmt: skip
    fit = range_fit(cached, checked.samples, description)
    if not fit.checked:  # too few ranges to judge (a sparse robot): a new one fares no better
        logger.warning("calibration cache %s: too few ranges in %g s to check it (%d); "
                       "used as it is", path, CHECK_SECONDS, fit.n_ranges)  # fmt: skip
    elif not fit.fits:
        logger.warning("calibration cache %s does not fit the first %g s of ranges in world %d "
                       "(%s); calibrating again", path, CHECK_SECONDS, world_seed,
                       _misfit(fit))  # fmt: skip
        return None
    logger.info("calibration cache %s fits the first %g s of ranges (%s)", path, CHECK_SECONDS,
                _misfit(fit))  # fmt: skip
    _CHECKED[key] = cached
    return cached


def estimated_uwb_calibration(
    description: RobotDescription,
    *,
    world_seed: int = 0,
    seconds: float = CALIBRATION_SECONDS,
    control_period: float = 0.1,
    time_step: float = 0.001,
) -> UwbCalibration:
    """The anchors and offsets calibrated from a calibration run of ``seconds`` in the
    world ``world_seed`` (:func:`record_calibration_run`), from the cache where it is
    there and passes its check (see the module's docstring).

    Raises:
        ValueError: ``world_seed`` or ``seconds`` out of range; the cache's path
            unusable (found before any run); the calibration failed. One line each.
    """
    check_calibration("estimated", world_seed)  # the world seed, by name
    seconds = check_seconds(seconds, description, where="make")
    path = check_cache_path(cache_path(description, world_seed, seconds))
    run = {"control_period": control_period, "time_step": time_step}
    cached = _cached(path, description, world_seed, **run)
    if cached is not None:
        return as_uwb(cached, "estimated")
    check_cache_path(path, writing=True)  # before the run, not after it
    logger.info(
        "calibrating UWB for %s, world %d (%g s run)", description.name, world_seed, seconds
    )
    samples = record_calibration_run(
        description, world_seed=world_seed, seconds=seconds, control_period=control_period,
        time_step=time_step,
    ).samples  # fmt: skip
    try:
        result = lab_calibration(samples, description, world_seed)
        if result.quality == "failed":
            raise CalibrationError(result.verdict)
    except CalibrationError as error:
        raise ValueError(
            f"make: the UWB calibration run of {description.name!r} in world {world_seed} "
            f"did not calibrate ({error}); pass calibration='true' or a calibration file"
        ) from error
    if result.quality != "good":
        logger.warning("UWB calibration of %s, world %d: %s", description.name, world_seed,
                       result.verdict)  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(path, result, robot=description.name)  # whole or not at all
    return as_uwb(result, "estimated")
