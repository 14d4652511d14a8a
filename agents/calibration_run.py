"""The UWB calibration a simulated lab would make (issue 15, papers/000 section III-C):
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
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from estimation.uwb_calibration import (
    CalibrationError,
    calibrate_samples,
    load_calibration,
    save_calibration,
)
from hardware.recording import MemorySink, RecordingBackend
from tensegrity_gym.envs.factory import make_env
from tensegrity_gym.model.kinematics import yaw_kabsch
from tensegrity_gym.model.protocols import UwbCalibration
from tensegrity_gym.model.samples import UwbRangeSample
from tensegrity_gym.tasks.gaits import FaceGait

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.uwb_calibration import CalibrationFile, CalibrationResult
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.sim.sensors import UwbModel

__all__ = [
    "CACHE_VARIABLE",
    "CACHE_VERSION",
    "CALIBRATION_SECONDS",
    "SPAWN_SHARE",
    "CalibrationRun",
    "cache_path",
    "estimated_uwb_calibration",
    "lab_calibration",
    "load_uwb_calibration",
    "onto_layout",
    "record_calibration_run",
]

logger = logging.getLogger(__name__)

CALIBRATION_SECONDS = 120.0
"""s of ranging the calibration run records (papers/000: a few minutes of movement)."""
EPISODE_SECONDS = 10.0
"""s per leg: the robot is put down at a random spot and heading, then rolls; so that
it stays among the anchors instead of rolling out of their area in one long run."""
LEG_GAP = 10.0
"""s between legs in the recorded times, so that no ranging round spans two legs."""
CACHE_VERSION = 2
"""Part of the cache key: raised whenever the calibrator or the calibration run changes
what they make, so that no stale calibration is read."""
CACHE_VARIABLE = "TENSEGRITY_GYM_CACHE"
"""Environment variable naming the cache folder (default ``~/.cache/tensegrity-gym``)."""


def onto_layout(anchors: NDArray[np.float64], layout: NDArray[np.float64]) -> NDArray[np.float64]:
    """``anchors`` (A, 3) of a floor frame (z = 0 the floor, up), turned about z and
    shifted in the ground plane to fit the lab's ``layout`` (A, 3) best (least squares,
    no mirror): the world frame of a lab is its floor plan's, and the plan says where
    the anchors were meant to stand."""
    R, t = yaw_kabsch(anchors, layout)
    return np.asarray(anchors @ R.T + t)


def lab_calibration(
    samples: list[UwbRangeSample], description: RobotDescription, seed: int
) -> CalibrationResult:
    """The calibrator's result on ``samples``, its anchors fitted onto the lab's floor
    plan (:func:`onto_layout`), its starts drawn from ``seed``."""
    result = calibrate_samples(samples, description, rng=np.random.default_rng(seed))
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


def record_calibration_run(
    description: RobotDescription,
    *,
    world_seed: int,
    seconds: float = CALIBRATION_SECONDS,
    control_period: float = 0.1,
    time_step: float = 0.001,
) -> CalibrationRun:
    """A calibration run in the world ``world_seed`` draws: legs of
    :data:`EPISODE_SECONDS` under the robot's gait, each from a reset drawn from the
    world seed; their times one after the other, :data:`LEG_GAP` apart."""
    env = make_env(
        description, estimator="oracle", calibration="true", world_seed=world_seed,
        spawn_radius=_spawn_radius(description), control_period=control_period,
        time_step=time_step,
    )  # fmt: skip
    world = cast("Any", env.backend).uwb
    sink = MemorySink()
    env.backend = RecordingBackend(env.backend, sink)
    rng = np.random.default_rng(world_seed)
    legs = max(1, round(seconds / EPISODE_SECONDS))
    steps = round(min(seconds, EPISODE_SECONDS) / control_period)
    clock = time.perf_counter()
    try:
        for _ in range(legs):
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
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


def cache_path(description: RobotDescription, world_seed: int, seconds: float) -> Path:
    """Where the calibration of this robot in this world is kept: the folder of
    :data:`CACHE_VARIABLE`, keyed by the robot's name and a digest of its rods and UWB
    setup, the world seed, the run's length and the calibrator's version."""
    root = os.environ.get(CACHE_VARIABLE) or Path.home() / ".cache" / "tensegrity-gym"
    # What the calibration depends on: the rods and the UWB setup, not the share of
    # packets a run loses (a lab calibrates once and then ranges in worse conditions).
    uwb = replace(description.sensors.uwb, reject_fraction=(0.0, 0.0))
    digest = hashlib.sha1(repr((description.rods, uwb)).encode()).hexdigest()[:12]
    name = f"{description.name}-{digest}-world{world_seed}-{seconds:g}s-v{CACHE_VERSION}.yaml"
    return Path(root) / "calibration" / name


def estimated_uwb_calibration(
    description: RobotDescription,
    *,
    world_seed: int = 0,
    seconds: float = CALIBRATION_SECONDS,
    control_period: float = 0.1,
    time_step: float = 0.001,
) -> UwbCalibration:
    """The anchors and offsets calibrated from a calibration run in the world
    ``world_seed`` (:func:`record_calibration_run`), from the cache where it is there."""
    path = cache_path(description, world_seed, seconds)
    if path.is_file():
        try:
            return _as_uwb(load_calibration(path), "estimated")
        except ValueError as error:  # a cache file cut off or from elsewhere: made anew
            logger.warning("calibration cache %s unreadable (%s); calibrating again", path, error)
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
    partial = path.with_suffix(f".{os.getpid()}.part")
    save_calibration(partial, result, robot=description.name)
    os.replace(partial, path)  # two workers calibrating at once: either file is whole
    return _as_uwb(result, "estimated")


def _as_uwb(result: CalibrationResult | CalibrationFile, source: str) -> UwbCalibration:
    return UwbCalibration(
        anchors=np.asarray(result.anchors, dtype=np.float64),
        uwb_offsets=np.asarray(result.offsets, dtype=np.float64),
        source=source,
    )


def load_uwb_calibration(path: str | os.PathLike[str]) -> UwbCalibration:
    """A calibration file's anchors and offsets (``calibration=PATH``); its errors name
    the file and the field."""
    return _as_uwb(load_calibration(path), str(path))


def _bag_ranges(
    bag: str | os.PathLike[str], robot: str | None
) -> tuple[list[UwbRangeSample], RobotDescription]:
    """A bag's UWB ranges and its robot."""
    from hardware.bag.reader import BagReader
    from tensegrity_gym.model.description import load_robot

    description = load_robot(robot) if robot else None
    with BagReader(Path(bag), description=description) as reader:
        samples = [
            s for period in reader.periods() for s in period.samples
            if isinstance(s, UwbRangeSample)
        ]  # fmt: skip
        d = reader.description
    return samples, d


def calibrate_command(
    *,
    bag: str | None,
    env_id: str | None,
    seconds: float,
    world_seed: int,
    robot: str | None,
    out: Path,
) -> str:
    """``tensegrity-gym calibrate``: calibrate from a bag, or from a calibration run of
    ``env_id`` in the world ``world_seed``; write ``out``; what came out, for a person."""
    if (bag is None) == (env_id is None):
        raise ValueError("calibrate: give either a BAG or --env ID")
    if bag is not None:
        samples, d = _bag_ranges(bag, robot)
    elif env_id is not None:
        import gymnasium as gym

        made = gym.make(env_id, estimator="oracle", calibration="true", world_seed=world_seed)
        d = made.unwrapped.backend.description  # type: ignore[attr-defined]
        made.close()
        samples = record_calibration_run(d, world_seed=world_seed, seconds=seconds).samples
    result = lab_calibration(samples, d, world_seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(out, result, robot=d.name)
    return "\n".join([f"{out}:", *result.summary()])
