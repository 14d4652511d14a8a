"""``gym.make(..., calibration=...)``: which UWB anchors and offsets the estimators get.

- ``"estimated"`` (the default): what a lab has, its own calibration. In the simulator,
  the calibrator's result from a calibration run of the robot in this world
  (``agents.calibration_run``, cached on disk), made at the env's first reset; a robot
  or a bag brings its own.
- ``"true"``: the simulator's own anchors and offsets, for ablations only.
- a path: a calibration file (YAML, from ``tensegrity-gym calibrate``).

A robot that carries no UWB has nothing to calibrate; with ``"estimated"`` the
simulator then hands the uncalibrated lab's: the anchors where the layout put them and
the nominal offset for every pair (``info["calibration"] == "nominal"``), never its own.
Every other simulated robot is calibrated whatever the estimator, so that a recording
made under one estimator replays under any other with the calibration a lab would have.

The calibration run and the file format live above this layer; they are reached by
string entry points, as the estimators are.
"""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tensegrity_gym.model.protocols import UwbCalibration
from tensegrity_gym.model.registry import resolve

if TYPE_CHECKING:
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import Backend

__all__ = ["CALIBRATIONS", "apply_calibration", "check_calibration", "nominal_uwb_calibration"]

CALIBRATIONS = ("estimated", "true")
"""The named choices; anything else is a calibration file's path."""
ESTIMATE = "agents.calibration_run:estimated_uwb_calibration"
LOAD = "agents.calibration_run:load_uwb_calibration"


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
            backend.uwb_calibration = partial(  # type: ignore[attr-defined]
                resolve(ESTIMATE), backend.description, world_seed=world_seed, **run
            )
        return "estimated"
    backend.uwb_calibration = resolve(LOAD)(calibration)  # type: ignore[attr-defined]
    return str(calibration)
