"""``tensegrity-gym calibrate``: a UWB calibration file from a bag, a lab's ranges file
(CSV or NPZ, :mod:`hardware.lab.ranges`) or a simulated run.

The simulated calibration run, its cache and the checks a cached calibration passes
live beside the env that uses them, in :mod:`tensegrity_gym.envs.calibration_run`
(``gym.make`` makes it at an env's first reset).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from estimation.uwb_calibration import CalibrationError, check_output_path, save_calibration
from estimation.uwb_calibration.floor import parse_floor_hint
from hardware.lab.ranges import SUFFIXES
from tensegrity_gym.envs.calibration_run import (
    check_seconds,
    lab_calibration,
    record_calibration_run,
)
from tensegrity_gym.model.samples import ImuSample, UwbRangeSample
from tensegrity_gym.sim.engines import DEFAULT_ENGINE

if TYPE_CHECKING:
    import os

    from tensegrity_gym.model.description import RobotDescription

__all__ = ["calibrate_command"]

logger = logging.getLogger(__name__)


def _bag_ranges(
    bag: str | os.PathLike[str], robot: str | None
) -> tuple[list[UwbRangeSample | ImuSample], RobotDescription]:
    """A bag's UWB ranges and IMU readings (the floor of a carried robot), and its robot."""
    from hardware.bag.reader import BagReader
    from tensegrity_gym.model.description import load_robot

    description = load_robot(robot) if robot else None
    with BagReader(Path(bag), description=description) as reader:
        samples = [
            s for period in reader.periods() for s in period.samples
            if isinstance(s, UwbRangeSample | ImuSample)
        ]  # fmt: skip
        d = reader.description
    return samples, d


def _file_ranges(
    path: Path, robot: str | None, ids: str | None
) -> tuple[list[UwbRangeSample | ImuSample], RobotDescription]:
    """A lab's ranges file (CSV or NPZ, :mod:`hardware.lab.ranges`) and its robot."""
    from hardware.lab import load_id_map, read_ranges
    from tensegrity_gym.model.description import load_robot

    if robot is None:
        raise ValueError(
            f"calibrate: {path} holds ranges only: name its robot (--robot PRESET or YAML)"
        )
    d = load_robot(robot)
    rows = read_ranges(path, d, load_id_map(ids, d) if ids else None)
    return list(rows.samples()), d


def _simulated_ranges(
    env_id: str, seconds: float, world_seed: int, engine: str | None = None
) -> tuple[list[UwbRangeSample | ImuSample], RobotDescription]:
    """The ranges of a calibration run of ``env_id``'s robot in the world ``world_seed``,
    simulated by ``engine`` (None: the default)."""
    import gymnasium as gym

    made = gym.make(env_id, estimator="oracle", calibration="true", world_seed=world_seed)
    d = made.unwrapped.backend.description  # type: ignore[attr-defined]
    made.close()
    seconds = check_seconds(seconds, d)  # the UWB rate is the robot's
    run = record_calibration_run(
        d, world_seed=world_seed, seconds=seconds, engine=engine or DEFAULT_ENGINE
    )
    return list(run.samples), d


def calibrate_command(
    *,
    bag: str | None,
    env_id: str | None,
    seconds: float,
    world_seed: int,
    robot: str | None,
    out: Path,
    engine: str | None = None,
    ids: str | None = None,
    floor: str | None = None,
) -> str:
    """``tensegrity-gym calibrate``: calibrate from a bag, or from a calibration run of
    ``env_id`` in the world ``world_seed`` lasting ``seconds`` (see
    :func:`~tensegrity_gym.envs.calibration_run.check_seconds`); write ``out``; what
    came out, for a person. ``bag`` may also be a lab's ranges file (``.csv``,
    ``.npz``) with its id map ``ids``; ``floor`` is a floor hint (anchor heights, for a
    robot that did not rest on the floor). Every argument is checked before anything
    is run.

    Raises:
        ValueError: a bad argument or path, or data that cannot calibrate; one line.
    """
    if (bag is None) == (env_id is None):
        raise ValueError("calibrate: give either a BAG or --env ID")
    if bag is not None and engine is not None:
        raise ValueError("calibrate: --engine simulates a calibration run (--env); a bag has none")
    if isinstance(world_seed, bool) or not isinstance(world_seed, int) or world_seed < 0:
        raise ValueError(f"calibrate: world_seed={world_seed!r} must be an int >= 0")
    seconds = check_seconds(seconds)
    out = check_output_path(out, "calibrate: --out")
    if floor is not None:
        parse_floor_hint(floor)  # a mistyped hint is refused before the solve
    if ids is not None and (bag is None or Path(bag).suffix.lower() not in SUFFIXES):
        raise ValueError("calibrate: --ids maps the ids of a ranges file (.csv, .npz)")
    if bag is not None and Path(bag).suffix.lower() in SUFFIXES:
        samples, d = _file_ranges(Path(bag), robot, ids)
    elif bag is not None:
        samples, d = _bag_ranges(bag, robot)
    elif env_id is not None:
        samples, d = _simulated_ranges(env_id, seconds, world_seed, engine)
    try:
        result = lab_calibration(samples, d, world_seed, floor)
    except CalibrationError as error:
        if env_id is None:
            raise
        raise CalibrationError(
            f"calibrate: the {seconds:g} s run of {env_id}: {error}; a longer run "
            "(seconds) gives more samples"
        ) from None
    out.parent.mkdir(parents=True, exist_ok=True)
    save_calibration(out, result, robot=d.name)
    return "\n".join([f"{out}:", *result.summary()])
