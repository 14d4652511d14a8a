"""``tensegrity-gym import``: a lab's recording (its CSV logs and ranges files, read
through its lab map) written as this project's bag (:mod:`hardware.lab.importer`)."""

from __future__ import annotations

import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hardware.lab import import_recording, load_lab_map
from tensegrity_gym.envs.calibration import load_uwb_calibration, nominal_uwb_calibration
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.protocols import SensorCalibration

if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence

__all__ = ["as_bag", "import_command"]


def import_command(
    sources: Sequence[str],
    *,
    lab_map: str | None,
    robot: str | None,
    out: str,
    calibration: str | None = None,
    control_period: float | None = None,
) -> str:
    """``tensegrity-gym import``: read ``sources`` (files the lab map names, or folders
    holding them; the map defaults to a folder's ``map.yaml``) and write the bag
    ``out``; what was written, for a person.

    Raises:
        ValueError: a bad argument, map or file; one line.
    """
    if not sources:
        raise ValueError("import: give the lab's files or a folder of them")
    if lab_map is None:
        folder = Path(sources[0])
        if not (folder.is_dir() and (folder / "map.yaml").is_file()):
            raise ValueError("import: --map names the lab map (a folder's map.yaml is the default)")
        lab_map = str(folder / "map.yaml")
    if Path(out).exists():
        raise ValueError(f"import: --out {out} exists; a bag is written to a new folder")
    mapping = load_lab_map(lab_map)
    name = robot or mapping.robot
    if name is None:
        raise ValueError(f"import: {lab_map} names no robot: give --robot PRESET or YAML")
    d = load_robot(name)
    uwb = (load_uwb_calibration(calibration, d, argument="import: --calibration")
           if calibration else nominal_uwb_calibration(d))  # fmt: skip
    cal = SensorCalibration(uwb.uwb_offsets, uwb.anchors, np.eye(3), np.eye(4))
    summary = import_recording(sources, mapping, d, cal, out, control_period=control_period)
    counts = ", ".join(f"{k} {v}" for k, v in sorted(summary["samples"].items()))
    return (
        f"{out}: {summary['seconds']:g} s of {d.name}: {counts}; {summary['commands']} commands "
        f"({summary['command_source']}) every {summary['control_period']:g} s; UWB "
        f"calibration {uwb.source}"
    )


@contextmanager
def as_bag(source: str, lab_map: str | None, robot: str | None) -> Iterator[str]:
    """``source`` as this project's bag: itself without a lab map; with one, the lab's
    recording (a ROS 1 or ROS 2 bag, files, a folder) imported into a temporary bag,
    removed afterwards. What ``estimate``, ``calibrate`` and ``identify`` read."""
    if lab_map is None:
        yield source
        return
    folder = Path(tempfile.mkdtemp(prefix="tensegrity-gym-import-"))
    try:
        import_command([source], lab_map=lab_map, robot=robot, out=str(folder / "bag"))
        yield str(folder / "bag")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
