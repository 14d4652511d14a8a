"""A lab's CSV logs: one file per kind of sample, with the lab's column names and units.

**Columns** of each kind (the project's names; a file may name them otherwise, the
map's ``columns`` says how):

| kind | columns |
|---|---|
| ``imu`` | ``t``, ``rod``, ``ax ay az`` (force), ``gx gy gz`` (rate), ``mx my mz`` (optional) |
| ``ahrs`` | ``t``, ``rod``, ``qx qy qz qw`` (body to world) |
| ``encoders`` | ``t``, one column per actuated cable, by cable name: its rest length |
| ``cable_lengths`` | ``t``, one column per cable, by name: its length |
| ``contacts`` | ``t``, one column per endcap, by node name: 1 touching, 0 not |
| ``commands`` | ``t``, one column per actuated cable: the rest length the motors were sent |
| ``uwb`` | the ranges file of :mod:`hardware.lab.ranges` (``t node anchor range``) |

IMU readings are in the rod's body frame (z along the rod, first node to second).
``rod`` is a rod's index or name. A log's entry in the lab map (YAML)::

    files:
      imu.csv:
        kind: imu
        columns: {ax: acc_x, ay: acc_y, az: acc_z}   # project name -> the file's
        units: {time: ms, accel: g, gyro: deg/s, mag: uT}
      motors.csv: {kind: encoders, units: {length: mm}}

Units: ``time`` s|ms|us|ns; ``length`` (encoders, cable lengths, commands, ranges)
m|cm|mm; ``accel`` m/s^2|g; ``gyro`` rad/s|deg/s; ``mag`` T|uT|G. Times are on the
file's clock; every file of one recording must share it. :func:`write_logs` writes any
samples in this format (SI units, the project's names) with the map that reads them back.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from hardware.lab.ranges import write_ranges
from hardware.lab.table import (
    UNITS,
    LabFileError,
    Table,
    nanoseconds,
    read_table,
    rod_index,
    unit_scale,
)
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    UwbRangeSample,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import Sample

__all__ = ["KINDS", "LogSpec", "Timed", "read_log", "write_logs"]

_XYZ = ("x", "y", "z")


def _vector(prefix: str) -> list[str]:
    return [prefix + a for a in _XYZ]


@dataclass(frozen=True)
class LogSpec:
    """One log file's entry in the lab map: its kind, its columns' names in the file
    (project name -> file's), and its units (quantity -> unit name)."""

    kind: str
    columns: dict[str, str] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)

    def scale(self, quantity: str, where: str) -> float:
        """The factor to SI of this file's unit of ``quantity``."""
        return unit_scale(self.units, quantity, f"{where}: units")


@dataclass(frozen=True)
class Timed:
    """A log's rows, read: times in whole ns on the file's clock, and the samples'
    values (their times filled in once the recording's clock origin is known)."""

    ns: NDArray[np.int64]
    make: Callable[[float, int], Sample]
    """(t s from the origin, row) -> the row's sample."""


def _names(description: RobotDescription, kind: str) -> list[str]:
    """The per-column names of a kind with one column per cable or endcap."""
    if kind in ("encoders", "commands"):
        return [description.cables[k].name for k in description.actuated]
    if kind == "cable_lengths":
        return [c.name for c in description.cables]
    return [n.name for n in description.nodes]


def _columns_of(kind: str, description: RobotDescription) -> tuple[list[str], list[str]]:
    """(required, optional) project column names of a kind, besides ``t``."""
    if kind == "imu":
        return ["rod", *_vector("a"), *_vector("g")], _vector("m")
    if kind == "ahrs":
        return ["rod", "qx", "qy", "qz", "qw"], []
    return _names(description, kind), []


KINDS = ("imu", "ahrs", "encoders", "cable_lengths", "contacts", "commands")
"""The kinds a CSV log may hold (UWB ranges have their own file, :mod:`hardware.lab.ranges`)."""


def _rod_index(values: NDArray[Any], description: RobotDescription, where: str) -> NDArray[np.intp]:
    names = [r.name for r in description.rods]
    return np.array([rod_index(v, names, where) for v in values.tolist()], dtype=np.intp)


def _floats(table: Table, names: Sequence[str]) -> NDArray[np.float64]:
    """Columns ``names`` as numbers, (k, len(names))."""
    return np.column_stack([table.numbers(c) for c in names]).reshape(len(table.lines), len(names))


def read_log(path: str | Path, spec: LogSpec, description: RobotDescription) -> Timed:
    """The rows of one CSV log (see the module's doc) as samples to be timed.

    Raises:
        LabFileError: a missing file or column, a value that is not a number, an
            unknown unit or rod; one line naming the file (and the line or column).
    """
    p = Path(path)
    where = str(p)
    if spec.kind not in KINDS:
        raise LabFileError(f"{where}: kind {spec.kind!r} is not one of {', '.join(KINDS)}, uwb")
    if not p.is_file():
        raise LabFileError(f"{where}: no such file")
    for quantity in spec.units:  # the map's mistakes before the data's
        if quantity not in UNITS:
            raise LabFileError(f"{where}: units.{quantity}: not one of {', '.join(UNITS)}")
        spec.scale(quantity, where)
    required, optional = _columns_of(spec.kind, description)
    file_name = {c: spec.columns.get(c, c) for c in ["t", *required, *optional]}
    raw = read_table(p, [file_name[c] for c in ["t", *required]],
                     [file_name[c] for c in optional])  # fmt: skip
    # The project's names for the file's columns.
    mine = {c: raw.columns[name] for c, name in file_name.items() if name in raw.columns}
    table = Table(p, mine, raw.lines)
    cols = table.columns
    ns = nanoseconds(cols["t"], spec.scale("time", where))
    if any(x is None for x in ns):
        raise LabFileError(f"{where}: a time that is not a finite number")
    stamps = np.array(ns, dtype=np.int64)
    return Timed(stamps, _maker(spec, table, required, description, where))


def _maker(
    spec: LogSpec, table: Table, required: list[str], description: RobotDescription, where: str
) -> Callable[[float, int], Sample]:
    """The sample of each row, in SI units."""
    kind, cols = spec.kind, table.columns
    if kind == "imu":
        rod = _rod_index(cols["rod"], description, where)
        accel = _floats(table, _vector("a")) * spec.scale("accel", where)
        gyro = _floats(table, _vector("g")) * spec.scale("gyro", where)
        mag = (_floats(table, _vector("m")) * spec.scale("mag", where)
               if "mx" in cols else np.zeros_like(accel))  # fmt: skip
        return lambda t, k: ImuSample(t, int(rod[k]), accel[k], gyro[k], mag[k])
    if kind == "ahrs":
        rod = _rod_index(cols["rod"], description, where)
        q = _floats(table, ["qx", "qy", "qz", "qw"])
        return lambda t, k: AhrsSample(t, int(rod[k]), q[k])
    values = _floats(table, required)
    if kind == "contacts":
        flags = values > 0.5
        return lambda t, k: ContactSample(t, flags[k].copy())
    values = values * spec.scale("length", where)
    if kind == "cable_lengths":
        return lambda t, k: CableLengthSample(t, values[k].copy())
    # encoders; commands come back as encoder-shaped samples the importer tells apart
    return lambda t, k: EncoderSample(t, values[k].copy())


def _rows(sample: Sample, kind: str) -> list[Any]:
    """One CSV row (after ``t``) of ``sample``, in the project's columns and SI units."""
    if isinstance(sample, ImuSample):
        return [sample.rod, *map(repr, map(float, np.r_[sample.accel, sample.gyro, sample.mag]))]
    if isinstance(sample, AhrsSample):
        return [sample.rod, *map(repr, map(float, sample.quaternion))]
    if isinstance(sample, EncoderSample):
        return [repr(float(v)) for v in sample.rest_lengths]
    if isinstance(sample, CableLengthSample):
        return [repr(float(v)) for v in sample.lengths]
    if isinstance(sample, ContactSample):
        return [int(v) for v in sample.in_contact]
    raise TypeError(f"no CSV log for {type(sample).__name__} ({kind})")


_KIND_OF = {ImuSample: "imu", AhrsSample: "ahrs", EncoderSample: "encoders",
            CableLengthSample: "cable_lengths", ContactSample: "contacts"}  # fmt: skip


def write_logs(
    folder: str | Path,
    samples: Sequence[Sample],
    description: RobotDescription,
    *,
    clock_origin_ns: int = 0,
    commands: Sequence[tuple[float, NDArray[np.float64]]] = (),
) -> Path:
    """``samples`` (and the motor ``commands``, (t, targets)) as one CSV log per kind in
    ``folder`` (UWB ranges as ``uwb.csv``), times in ns on the recording's clock
    (``clock_origin_ns`` + t), with the lab map ``map.yaml`` that reads them back;
    returns the map's path. RGB-D frames are left out."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, dict[str, Any]] = {}
    by_kind: dict[str, list[Sample]] = {}
    for s in samples:
        kind = _KIND_OF.get(type(s))
        if kind is not None:
            by_kind.setdefault(kind, []).append(s)
    rows = {k: [(s.t, _rows(s, k)) for s in v] for k, v in by_kind.items()}
    if commands:
        rows["commands"] = [(t, [repr(float(v)) for v in c]) for t, c in commands]
    for kind, lines in rows.items():
        required, optional = _columns_of(kind, description)
        header = ["t", *required, *(optional if kind == "imu" else [])]
        with (out / f"{kind}.csv").open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(header)
            for t, values in lines:
                w.writerow([clock_origin_ns + round(t * 1e9), *values])
        files[f"{kind}.csv"] = {"kind": kind, "units": {"time": "ns"}}
    uwb = [s for s in samples if isinstance(s, UwbRangeSample)]
    if uwb:
        write_ranges(out / "uwb.csv", uwb, description.n_nodes, clock_origin_ns=clock_origin_ns)
        files["uwb.csv"] = {"kind": "uwb", "units": {"time": "ns"}}
    path = out / "map.yaml"
    path.write_text(yaml.safe_dump({"robot": description.name, "files": files}, sort_keys=False))
    return path
