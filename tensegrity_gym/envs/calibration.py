"""``gym.make(..., calibration=...)``: which UWB anchors and offsets the estimators get.

- ``"estimated"`` (the default): what a lab has, its own calibration. In the simulator,
  the calibrator's result from a calibration run of the robot in this world
  (:mod:`tensegrity_gym.envs.calibration_run`, cached on disk: :func:`cache_path`),
  made at the env's first reset; a robot or a bag brings its own.
- ``"true"``: the simulator's own anchors and offsets, for ablations only.
- a path: a calibration file (YAML, from ``tensegrity-gym calibrate``).

A robot that carries no UWB has nothing to calibrate; with ``"estimated"`` the
simulator then hands the uncalibrated lab's: the anchors where the layout put them and
the nominal offset for every pair (``info["calibration"] == "nominal"``), never its own.
Every other simulated robot is calibrated whatever the estimator, so that a recording
made under one estimator replays under any other with the calibration a lab would have.

The calibration run (:mod:`tensegrity_gym.envs.calibration_run`) is reached by name,
as the estimators are: it makes envs, and the env factory imports this module. A
calibration file must be the robot's scene (its anchor and module counts), refused
at ``make`` otherwise; the cache's path is checked at ``make`` too, before any run.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from estimation.uwb_calibration import CalibrationFileError, check_output_path, load_calibration
from estimation.uwb_calibration.trust import scene_mismatch
from tensegrity_gym.model.protocols import UwbCalibration
from tensegrity_gym.model.registry import resolve

if TYPE_CHECKING:
    from estimation.uwb_calibration import CalibrationFile, CalibrationResult
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import Backend

__all__ = [
    "CACHE_VARIABLE",
    "CACHE_VERSION",
    "CALIBRATIONS",
    "CALIBRATION_SECONDS",
    "apply_calibration",
    "as_uwb",
    "cache_path",
    "check_cache_path",
    "check_calibration",
    "load_uwb_calibration",
    "nominal_uwb_calibration",
]

CALIBRATIONS = ("estimated", "true")
"""The named choices; anything else is a calibration file's path."""
ESTIMATE = "tensegrity_gym.envs.calibration_run:estimated_uwb_calibration"
"""The calibration run, by name: it makes envs, and the env factory imports this module
(an import, even inside a function, would close a cycle)."""
CACHE_VERSION = 2
"""Part of the cache key: raised whenever the calibrator or the calibration run changes
what they make, so that no stale calibration is read."""
CACHE_VARIABLE = "TENSEGRITY_GYM_CACHE"
"""Environment variable naming the cache folder (default ``~/.cache/tensegrity-gym``)."""
CALIBRATION_SECONDS = 120.0
"""s of ranging the calibration run records (Caluwaerts et al. 2016: a few minutes of movement)."""


def check_calibration(calibration: object, world_seed: object) -> None:
    """Refuse a bad ``calibration`` or ``world_seed`` by name, before anything is built."""
    if isinstance(world_seed, bool) or not isinstance(world_seed, int) or world_seed < 0:
        raise ValueError(f"make: world_seed={world_seed!r} must be an int >= 0")
    if isinstance(calibration, str) and calibration in CALIBRATIONS:
        return
    if not isinstance(calibration, (str, os.PathLike)):
        raise ValueError(
            f"make: calibration={calibration!r} must be one of {list(CALIBRATIONS)} or a "
            "calibration file's path"
        )
    if not Path(calibration).is_file():
        raise ValueError(
            f"make: calibration={str(calibration)!r} is neither one of {list(CALIBRATIONS)} "
            "nor a calibration file"
        )


def _cache_root() -> tuple[Path, str]:
    """The cache folder, and where it was set, for messages."""
    root = os.environ.get(CACHE_VARIABLE)
    if root:
        return Path(root), f"${CACHE_VARIABLE}={root}"
    default = Path.home() / ".cache" / "tensegrity-gym"
    return default, f"the default cache folder; ${CACHE_VARIABLE} moves it"


def cache_path(description: RobotDescription, world_seed: int, seconds: float) -> Path:
    """Where the calibration of this robot in this world is kept: the folder of
    :data:`CACHE_VARIABLE`, keyed by the robot's name and a digest of its rods and UWB
    setup, the world seed, the run's length and the calibrator's version."""
    root, _ = _cache_root()
    # What the calibration depends on: the rods and the UWB setup, not the share of
    # packets a run loses (a lab calibrates once and then ranges in worse conditions).
    uwb = replace(description.sensors.uwb, reject_fraction=(0.0, 0.0))
    digest = hashlib.sha1(repr((description.rods, uwb)).encode()).hexdigest()[:12]
    name = f"{description.name}-{digest}-world{world_seed}-{seconds:g}s-v{CACHE_VERSION}.yaml"
    return root / "calibration" / name


def check_cache_path(path: Path, *, writing: bool = False) -> Path:
    """``path`` (a :func:`cache_path`), or a one-line ValueError naming it and the cache
    folder's setting: a folder where the file should be, a file where a folder of its
    path should be, or (``writing``) a folder that cannot be written. Checked before a
    calibration run, so that none is made only to fail at the end."""
    try:
        # A read-only cache is refused only once something must be written to it.
        return check_output_path(path, "calibration cache", writable=writing)
    except CalibrationFileError as error:
        _, origin = _cache_root()
        raise ValueError(f"make: {error} ({origin}); clear the path or point "
                         f"${CACHE_VARIABLE} at another folder") from None  # fmt: skip


def as_uwb(calibration: CalibrationResult | CalibrationFile, source: str) -> UwbCalibration:
    """The anchors and offsets of a calibrator's result or a calibration file."""
    return UwbCalibration(
        anchors=np.asarray(calibration.anchors, dtype=np.float64),
        uwb_offsets=np.asarray(calibration.offsets, dtype=np.float64),
        source=source,
    )


def load_uwb_calibration(
    path: str | os.PathLike[str],
    description: RobotDescription | None = None,
    *,
    argument: str = "calibration",
) -> UwbCalibration:
    """A calibration file's anchors and offsets (``calibration=PATH``), checked against
    ``description``'s scene where given (anchor and module counts).

    Raises:
        CalibrationFileError: one line naming ``argument``, the file and what is wrong
            (not a calibration file, a field, another scene's).
    """
    file = load_calibration(path, argument=argument)
    if description is not None:
        reason = scene_mismatch(file, description, layout_tolerance=None)
        if reason is not None:
            raise CalibrationFileError(f"{argument}={str(path)!r}: not this robot's: {reason}")
    return as_uwb(file, str(path))


def nominal_uwb_calibration(description: RobotDescription) -> UwbCalibration:
    """What a lab knows before it calibrates: its anchor layout (the description's) and
    the modules' nominal offset (``offset_mean``) for every pair."""
    d = description
    n = d.n_nodes + len(d.anchors)
    offsets = np.full((n, n), d.sensors.uwb.offset_mean)
    np.fill_diagonal(offsets, 0.0)
    return UwbCalibration(d.anchors, offsets, source="nominal")


def apply_calibration(
    backend: Backend,
    calibration: str | os.PathLike[str],
    *,
    world_seed: int,
    **run: Any,
) -> str:
    """Set what ``backend.calibration`` hands the estimators; the choice, for ``info``
    and the run info (``"estimated"``, ``"nominal"``, ``"true"`` or the file's path).
    ``run``: the simulator's ``control_period`` and ``time_step`` for the calibration
    run."""
    simulated = hasattr(backend, "true_uwb")
    if calibration == "true":
        if not simulated:
            raise ValueError(
                "make: calibration='true' is the simulator's own; a robot or a bag has only "
                "its own calibration ('estimated') or a file's"
            )
        backend.uwb_calibration = None  # type: ignore[attr-defined]
        return "true"
    if calibration == "estimated":
        if simulated and "uwb" not in backend.description.sample_kinds:
            backend.uwb_calibration = nominal_uwb_calibration(backend.description)  # type: ignore[attr-defined]
            return "nominal"
        if simulated:  # made at the first reset, which a calibration run may fail as well
            check_cache_path(cache_path(backend.description, world_seed, CALIBRATION_SECONDS))
            backend.uwb_calibration = partial(  # type: ignore[attr-defined]
                resolve(ESTIMATE), backend.description, world_seed=world_seed, **run
            )
        return "estimated"
    backend.uwb_calibration = load_uwb_calibration(  # type: ignore[attr-defined]
        calibration, backend.description, argument="make: calibration"
    )
    return str(calibration)
