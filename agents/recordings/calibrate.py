"""``tensegrity-gym calibrate``: a UWB calibration file from a bag or a simulated run.

The simulated calibration run, its cache and the checks a cached calibration passes
live beside the env that uses them, in :mod:`tensegrity_gym.envs.calibration_run`
(``gym.make`` makes it at an env's first reset).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from estimation.uwb_calibration import CalibrationError, check_output_path, save_calibration
from tensegrity_gym.envs.calibration_run import (
    check_seconds,
    lab_calibration,
    record_calibration_run,
)
from tensegrity_gym.model.samples import UwbRangeSample
from tensegrity_gym.sim.engines import DEFAULT_ENGINE

if TYPE_CHECKING:
    import os

    from tensegrity_gym.model.description import RobotDescription

__all__ = ["calibrate_command"]

logger = logging.getLogger(__name__)


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


def _simulated_ranges(
    env_id: str, seconds: float, world_seed: int, engine: str | None = None
) -> tuple[list[UwbRangeSample], RobotDescription]:
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
    return run.samples, d


def calibrate_command(
    *,
    bag: str | None,
    env_id: str | None,
    seconds: float,
    world_seed: int,
    robot: str | None,
    out: Path,
    engine: str | None = None,
) -> str:
    """``tensegrity-gym calibrate``: calibrate from a bag, or from a calibration run of
    ``env_id`` in the world ``world_seed`` lasting ``seconds`` (see
    :func:`~tensegrity_gym.envs.calibration_run.check_seconds`); write ``out``; what
    came out, for a person. Every argument is checked before anything is run.

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
    if bag is not None:
        samples, d = _bag_ranges(bag, robot)
    elif env_id is not None:
        samples, d = _simulated_ranges(env_id, seconds, world_seed, engine)
    try:
        result = lab_calibration(samples, d, world_seed)
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
