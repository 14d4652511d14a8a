"""A lab's recording written as this project's bag, so that the rest of the toolchain
(``estimate``, ``calibrate``, ``identify``, ``driver="bag:PATH"``) applies unchanged.

**The lab map** (YAML) says what each of the lab's files, or each topic of its ROS 1 or
ROS 2 bag (:mod:`hardware.lab.topics`), is::

    robot: superball        # optional: the description (a preset or a YAML path)
    ids:                    # the UWB ids, as hardware.lab.ranges' id map
      nodes: {"0x0A": n0}
      anchors: {"101": 0}
    files:                  # by file name (hardware.lab.logs: kinds, columns, units)
      imu.csv: {kind: imu, units: {time: ms, accel: g, gyro: deg/s}}
      motors.csv: {kind: encoders, units: {time: ms, length: mm}}
      ranges.csv: {kind: uwb, units: {time: ms, length: mm}}
    topics:                 # a bag's topics (hardware.lab.topics)
      /red/imu: {kind: imu, rod: red}

Every file of a recording shares one clock; the bag's clock origin is its first
sample's whole second. **Commands**: a ``commands`` log where the lab has one (the
rest lengths its motors were sent); else each control period's command is the
encoders' last reading, held (what the motors were holding), and the run info says so.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hardware.bag.replay import ReplayBackend
from hardware.bag.writer import BagWriter
from hardware.lab.logs import KINDS, LogSpec, read_log
from hardware.lab.ranges import IdMap, RangeRows, id_map_from_doc, identity_map, read_ranges
from hardware.lab.table import LabFileError, read_yaml
from hardware.lab.topics import TopicSpec, is_ros_bag, read_topics, topic_spec
from tensegrity_gym.model.samples import EncoderSample, ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    import os
    from collections.abc import Callable, Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import Sample

__all__ = [
    "LabMap",
    "LabRecording",
    "LabReplay",
    "import_recording",
    "load_lab_map",
    "read_recording",
]

DEFAULT_CONTROL_PERIOD = 0.1
"""s: the control period of an imported recording without commands of its own."""


@dataclass(frozen=True)
class LabMap:
    """What a lab map (YAML) says: its robot, its UWB ids, its files and bag topics."""

    robot: str | None
    ids: dict[str, Any] | None
    """The ``ids`` section as written (resolved against a description when read)."""
    files: dict[str, LogSpec]
    source: str
    topics: dict[str, TopicSpec] = field(default_factory=dict)
    """A ROS 1 or ROS 2 bag's topics (:mod:`hardware.lab.topics`)."""

    def id_map(self, description: RobotDescription) -> IdMap:
        """The UWB ids resolved against ``description`` (its module ids without any)."""
        if self.ids is None:
            return identity_map(description)
        return id_map_from_doc(self.ids, description, f"{self.source}: ids")


def load_lab_map(path: str | os.PathLike[str]) -> LabMap:
    """The lab map in ``path`` (see the module's doc).

    Raises:
        LabFileError: missing, not YAML, or a malformed field; one line naming the file
            and the field.
    """
    source = str(path)
    doc = read_yaml(path, "lab map")
    sections = ("files", "topics")
    if not isinstance(doc, dict) or not any(
        isinstance(doc.get(k), dict) and doc[k] for k in sections
    ):
        raise LabFileError(
            f"{source}: a lab map is a mapping with 'files' (file name -> kind) or 'topics' "
            "(a bag's topic -> kind)"
        )
    unknown = sorted(set(doc) - {"robot", "ids", *sections})
    if unknown:
        raise LabFileError(f"{source}: {unknown[0]}: unknown field (robot, ids, files, topics)")
    for k in sections:
        if not isinstance(doc.get(k) or {}, dict):
            raise LabFileError(f"{source}: {k}: expected a mapping")
    files = {
        str(n): _log_spec(e, f"{source}: files.{n}") for n, e in (doc.get("files") or {}).items()
    }
    topics = {
        str(n): topic_spec(e, f"{source}: topics.{n}") for n, e in (doc.get("topics") or {}).items()
    }
    ids = doc.get("ids")
    if ids is not None and not isinstance(ids, dict):
        raise LabFileError(f"{source}: ids: expected a mapping (nodes, anchors)")
    robot = doc.get("robot")
    return LabMap(None if robot is None else str(robot), ids, files, source, topics)


def _log_spec(entry: Any, where: str) -> LogSpec:
    if not isinstance(entry, dict) or "kind" not in entry:
        raise LabFileError(f"{where}: expected a mapping with 'kind'")
    unknown = sorted(set(entry) - {"kind", "columns", "units"})
    if unknown:
        raise LabFileError(f"{where}.{unknown[0]}: unknown field (kind, columns, units)")
    kind = str(entry["kind"])
    if kind not in (*KINDS, "uwb"):
        raise LabFileError(f"{where}.kind: {kind!r} is not one of {', '.join(KINDS)}, uwb")
    columns, units = entry.get("columns") or {}, entry.get("units") or {}
    for name, value in (("columns", columns), ("units", units)):
        if not isinstance(value, dict):
            raise LabFileError(f"{where}.{name}: expected a mapping")
    return LogSpec(kind, {str(k): str(v) for k, v in columns.items()},
                   {str(k): str(v) for k, v in units.items()})  # fmt: skip


@dataclass(frozen=True)
class LabRecording:
    """A lab's recording read: its samples in time order, its commands, its clock."""

    samples: list[Sample]
    commands: list[tuple[float, NDArray[np.float64]]]
    """(t s, rest-length targets (m,)), from a ``commands`` log; empty without one."""
    clock_origin_ns: int
    """The files' clock at t = 0: the first sample's whole second."""


def _files(path: Path, lab_map: LabMap) -> list[tuple[Path, LogSpec]]:
    """The files to read at ``path``: the file itself, or a folder's files the map names."""
    if path.is_dir():
        named = [(path / n, spec) for n, spec in lab_map.files.items() if (path / n).is_file()]
        if not named:
            raise LabFileError(f"{path}: holds none of the files {lab_map.source} names")
        return named
    if path.name in lab_map.files:
        return [(path, lab_map.files[path.name])]
    raise LabFileError(
        f"{path}: not one of the files {lab_map.source} names ({', '.join(lab_map.files)})"
    )


Entry = tuple[int, str, "Callable[[int], list[Sample]]"]
"""(time ns on the recording's clock, kind, the recording's origin ns -> its samples)."""


def _entries(
    path: Path, lab_map: LabMap, description: RobotDescription
) -> tuple[list[Entry], list[RangeRows]]:
    """What ``path`` holds: timed entries, and ranges files (timed on their own)."""
    if is_ros_bag(path):
        if not lab_map.topics:
            raise LabFileError(f"{path}: a bag, and {lab_map.source} names no topics")
        return read_topics(path, lab_map.topics, description, lab_map.id_map(description)), []
    entries: list[Entry] = []
    ranges: list[RangeRows] = []
    for file, spec in _files(path, lab_map):
        if spec.kind == "uwb":
            ids = lab_map.id_map(description)
            ids = IdMap(ids.modules, spec.scale("time", str(file)), spec.scale("length", str(file)))
            ranges.append(read_ranges(file, description, ids))
            continue
        timed = read_log(file, spec, description)
        entries += [
            (int(ns), spec.kind, partial(_one, timed.make, k, int(ns)))
            for k, ns in enumerate(timed.ns)
        ]
    return entries, ranges


def _one(make: Callable[[float, int], Sample], k: int, ns: int, origin_ns: int) -> list[Sample]:
    return [make(ns_to_seconds(ns - origin_ns), k)]


def read_recording(
    paths: Sequence[str | os.PathLike[str]], lab_map: LabMap, description: RobotDescription
) -> LabRecording:
    """Every file of ``paths`` (files the map names, folders holding them, ROS 1 or
    ROS 2 bags whose topics it names) read and put on one clock."""
    entries: list[Entry] = []
    ranges: list[RangeRows] = []
    for p in paths:
        more, files = _entries(Path(p), lab_map, description)
        entries += more
        ranges += files
    firsts = [e[0] for e in entries] + [r.clock_origin_ns for r in ranges]
    if not firsts:
        raise LabFileError(f"{', '.join(map(str, paths))}: no sample in the files")
    origin = min(firsts) // 1_000_000_000 * 1_000_000_000
    samples: list[Sample] = []
    commands: list[tuple[float, NDArray[np.float64]]] = []
    for _, kind, make in entries:
        for sample in make(origin):
            if kind == "commands":
                commands.append((sample.t, sample.rest_lengths))  # type: ignore[union-attr]
            else:
                samples.append(sample)
    for file in ranges:
        shift = ns_to_seconds(file.clock_origin_ns - origin)
        samples += [_shifted(s, shift) for s in file.samples()]
    samples.sort(key=lambda s: s.t)  # stable: each source's own order kept at equal times
    commands.sort(key=lambda c: c[0])
    return LabRecording(samples, commands, origin)


def _shifted(sample: Any, shift: float) -> Any:
    """A ``UwbRangeSample`` moved ``shift`` s later (its rows' times too)."""
    from dataclasses import replace

    if shift == 0.0:
        return sample
    return replace(sample, t=sample.t + shift, times=np.asarray(sample.times) + shift)


def _held_commands(
    recording: LabRecording, description: RobotDescription, period: float
) -> list[tuple[float, NDArray[np.float64]]]:
    """A command each ``period`` s from the first sample to the last: the encoders'
    last reading, held (the description's resting rest lengths before the first)."""
    held = description.rest_lengths[description.actuated].copy()
    readings = [(s.t, s.rest_lengths) for s in recording.samples if isinstance(s, EncoderSample)]
    start, end = recording.samples[0].t, recording.samples[-1].t
    out, k = [], 0
    for j in range(1, int((end - start) / period) + 1):
        t = start + j * period
        while k < len(readings) and readings[k][0] <= t:
            held = np.asarray(readings[k][1], dtype=np.float64)
            k += 1
        out.append((t, held.copy()))
    return out


def import_recording(
    paths: Sequence[str | os.PathLike[str]],
    lab_map: LabMap,
    description: RobotDescription,
    calibration: SensorCalibration,
    out: str | os.PathLike[str],
    *,
    control_period: float | None = None,
) -> dict[str, Any]:
    """Read a lab's recording (:func:`read_recording`) and write it as a bag at ``out``
    (a new folder), with ``calibration`` as its UWB and camera calibration; what was
    written, for a person (sample counts by kind, commands, the span)."""
    recording = read_recording(paths, lab_map, description)
    if recording.commands:
        commands = recording.commands
        gaps = np.diff([t for t, _ in commands])
        median = ns_to_seconds(seconds_to_ns(float(np.median(gaps)))) if len(gaps) else None
        period = control_period or median or DEFAULT_CONTROL_PERIOD
        source = "recorded"
    else:
        period = control_period or DEFAULT_CONTROL_PERIOD
        commands = _held_commands(recording, description, period)
        source = "encoders held"
    info = {"control_period": period, "imported_from": [str(p) for p in paths],
            "lab_map": lab_map.source, "commands": source}  # fmt: skip
    counts: dict[str, int] = {}
    origin = recording.clock_origin_ns
    with BagWriter(Path(out), description, calibration, info, clock_origin_ns=origin,
                   markers=False) as writer:  # fmt: skip
        k = 0
        for t, targets in commands:
            while k < len(recording.samples) and recording.samples[k].t < t:
                s = recording.samples[k]
                writer.write_samples([s])
                counts[type(s).__name__] = counts.get(type(s).__name__, 0) + 1
                k += 1
            writer.write_command(t, targets)
        for s in recording.samples[k:]:
            writer.write_samples([s])
            counts[type(s).__name__] = counts.get(type(s).__name__, 0) + 1
    span = (recording.samples[-1].t - recording.samples[0].t) if recording.samples else 0.0
    return {"bag": str(out), "samples": counts, "commands": len(commands),
            "command_source": source, "control_period": period, "seconds": round(span, 3),
            "clock_origin_ns": recording.clock_origin_ns}  # fmt: skip


class LabReplay(ReplayBackend):
    """A lab's recording (its ROS 1/ROS 2 bag or files, read through ``lab_map``)
    replayed as :class:`~hardware.bag.replay.ReplayBackend` replays a bag: imported into
    a temporary bag, removed when the backend closes. ``gym.make(ID, driver=LabReplay(...))``
    runs an env on it, as ``driver="bag:PATH"`` does on a bag."""

    def __init__(
        self,
        sources: Sequence[str | os.PathLike[str]],
        lab_map: LabMap,
        description: RobotDescription,
        calibration: SensorCalibration,
        *,
        control_period: float | None = None,
    ) -> None:
        self._folder = Path(tempfile.mkdtemp(prefix="tensegrity-gym-replay-"))
        try:
            import_recording(sources, lab_map, description, calibration, self._folder / "bag",
                             control_period=control_period)  # fmt: skip
            super().__init__(self._folder / "bag", description=description)
        except BaseException:
            shutil.rmtree(self._folder, ignore_errors=True)
            raise

    def close(self) -> None:
        try:
            super().close()
        finally:
            shutil.rmtree(self._folder, ignore_errors=True)
