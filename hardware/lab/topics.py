"""A lab's own ROS 1 or ROS 2 bag: its topic names and message types, read through
``rosbags`` and a topic map.

The lab map's ``topics`` section says which of the bag's topics is which kind of sample,
and where in the message its values are (a field path, ``a.b.c``; a field holding a
``Vector3`` or ``Quaternion`` gives its ``x y z (w)``)::

    topics:
      /red/imu:       {kind: imu, rod: red}          # sensor_msgs/Imu: the defaults
      /red/ahrs:      {kind: ahrs, rod: red}         # its orientation
      /motors:        {kind: encoders, values: position, names: name, units: {length: mm}}
      /strain:        {kind: cable_lengths, values: data}
      /feet:          {kind: contacts, values: data}
      /motors/target: {kind: commands, values: position, names: name}
      /uwb:           {kind: uwb, node: responder, anchor: initiator, range: distance}

Defaults: ``imu`` reads ``linear_acceleration`` and ``angular_velocity`` (``mag``, a field
path, optional), ``ahrs`` ``orientation``, the others ``values: data``. ``names``: a field
listing each value's cable (or node) name; without it the values are in the
description's order (actuated cables, cables, nodes). ``uwb``: ``node``, ``anchor`` and
``range`` fields, scalars or arrays of one length (one range or many a message), the
ids resolved by the map's ``ids``; ``times`` (optional) a field with each range's own
time (``builtin_interfaces/Time`` or float s), else the message's. Times are the
message's ``header.stamp`` where it has one, else the bag's log time (``stamp: log`` in
the entry uses the log time always).

Message definitions come from the bag itself (a ROS 1 bag and an MCAP ROS 2 bag carry
them); a ROS 2 bag without them is read with ROS 2 Humble's standard types.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np

from hardware.lab.table import LabFileError, rod_index, unit_scale
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    UwbRangeSample,
    ns_to_seconds,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from collections.abc import Callable
    from pathlib import Path

    from numpy.typing import NDArray

    from hardware.lab.ranges import IdMap
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import Sample

__all__ = ["TOPIC_KINDS", "TopicSpec", "is_ros_bag", "read_topics", "topic_spec"]

TOPIC_KINDS = ("imu", "ahrs", "encoders", "cable_lengths", "contacts", "commands", "uwb")
_FIELDS: dict[str, dict[str, str | None]] = {
    "imu": {"accel": "linear_acceleration", "gyro": "angular_velocity", "mag": None},
    "ahrs": {"quaternion": "orientation"},
    "uwb": {"node": "node", "anchor": "anchor", "range": "range", "times": None},
}
_VALUES: dict[str, str | None] = {"values": "data", "names": None}


@dataclass(frozen=True)
class TopicSpec:
    """One topic's entry in the lab map."""

    kind: str
    fields: dict[str, str | None]
    """Field paths by role (``accel``, ``values``, ``node``...); None: absent."""
    rod: str | None = None
    units: dict[str, str] = field(default_factory=dict)
    log_time: bool = False
    """Stamp samples with the bag's log time, not the message header's."""


def topic_spec(entry: Any, where: str) -> TopicSpec:
    """A topic's entry of the lab map, checked; errors name ``where`` and the field."""
    if not isinstance(entry, dict) or "kind" not in entry:
        raise LabFileError(f"{where}: expected a mapping with 'kind'")
    kind = str(entry["kind"])
    if kind not in TOPIC_KINDS:
        raise LabFileError(f"{where}.kind: {kind!r} is not one of {', '.join(TOPIC_KINDS)}")
    roles = _FIELDS.get(kind, _VALUES)
    allowed = {"kind", "units", "stamp", *roles, *(("rod",) if kind in ("imu", "ahrs") else ())}
    unknown = sorted(set(entry) - allowed)
    if unknown:
        raise LabFileError(f"{where}.{unknown[0]}: unknown field ({', '.join(sorted(allowed))})")
    if kind in ("imu", "ahrs") and "rod" not in entry:
        raise LabFileError(f"{where}.rod: missing: which rod the {kind} is on")
    stamp = str(entry.get("stamp", "header"))
    if stamp not in ("header", "log"):
        raise LabFileError(f"{where}.stamp: {stamp!r} is not header or log")
    units = entry.get("units") or {}
    if not isinstance(units, dict):
        raise LabFileError(f"{where}.units: expected a mapping")
    fields = {
        role: (str(entry[role]) if role in entry else default) for role, default in roles.items()
    }
    rod = str(entry["rod"]) if "rod" in entry else None
    return TopicSpec(kind, fields, rod, {str(k): str(v) for k, v in units.items()}, stamp == "log")


def is_ros_bag(path: Path) -> bool:
    """A ROS 1 bag file or a ROS 2 bag folder (``metadata.yaml``)."""
    return (path.is_file() and path.suffix == ".bag") or (path / "metadata.yaml").is_file()


def _get(msg: Any, path: str, where: str) -> Any:
    """The field at dotted ``path`` of ``msg``, as an array where it is a vector."""
    value = msg
    for part in path.split("."):
        if not hasattr(value, part):
            kind = getattr(msg, "__msgtype__", type(msg).__name__)
            raise LabFileError(f"{where}: {kind} has no field {path!r}")
        value = getattr(value, part)
    if all(hasattr(value, a) for a in ("x", "y", "z")):
        xyz = [value.x, value.y, value.z] + ([value.w] if hasattr(value, "w") else [])
        return np.array(xyz, dtype=np.float64)
    return value


def _rod(name: str, description: RobotDescription, where: str) -> int:
    return rod_index(name, [r.name for r in description.rods], f"{where}.rod")


def _ordered(
    values: NDArray[np.float64], names: Any, order: list[str], where: str
) -> NDArray[np.float64]:
    """``values`` by ``names`` into the description's ``order`` (as given without names)."""
    if names is None:
        if len(values) != len(order):
            raise LabFileError(f"{where}: {len(values)} values, the description has {len(order)}")
        return values
    index = {str(n): k for k, n in enumerate(names)}
    missing = [n for n in order if n not in index]
    if missing:
        raise LabFileError(f"{where}: no value named {missing[0]!r}")
    return np.array([values[index[n]] for n in order], dtype=np.float64)


def _builder(spec: TopicSpec, description: RobotDescription, ids: IdMap,
             where: str) -> Callable[[Any, float, int], list[Sample]]:  # fmt: skip
    """(message, t s) -> its samples."""
    f, d = spec.fields, description
    if spec.kind == "imu":
        rod = _rod(spec.rod or "", d, where)
        a, g = (
            unit_scale(spec.units, "accel", f"{where}.units"),
            unit_scale(spec.units, "gyro", f"{where}.units"),
        )
        m = unit_scale(spec.units, "mag", f"{where}.units")
        return lambda msg, t, _: [ImuSample(
            t, rod, a * _get(msg, f["accel"] or "", where), g * _get(msg, f["gyro"] or "", where),
            m * _get(msg, f["mag"], where) if f["mag"] else np.zeros(3))]  # fmt: skip
    if spec.kind == "ahrs":
        rod = _rod(spec.rod or "", d, where)
        return lambda msg, t, _: [AhrsSample(t, rod, _get(msg, f["quaternion"] or "", where))]
    if spec.kind == "uwb":
        return _uwb_builder(spec, ids, where)
    order = {"encoders": [d.cables[k].name for k in d.actuated],
             "commands": [d.cables[k].name for k in d.actuated],
             "cable_lengths": [c.name for c in d.cables],
             "contacts": [n.name for n in d.nodes]}[spec.kind]  # fmt: skip
    scale = 1.0 if spec.kind == "contacts" else unit_scale(spec.units, "length", f"{where}.units")
    kind = spec.kind

    def build(msg: Any, t: float, origin_ns: int) -> list[Sample]:
        raw = np.asarray(_get(msg, f["values"] or "", where), dtype=np.float64)
        names = _get(msg, f["names"], where) if f["names"] else None
        values = _ordered(raw, names, order, where)
        if kind == "contacts":
            return [ContactSample(t, values > 0.5)]
        if kind == "cable_lengths":
            return [CableLengthSample(t, scale * values)]
        return [EncoderSample(t, scale * values)]  # encoders, or commands

    return build


def _uwb_builder(
    spec: TopicSpec, ids: IdMap, where: str
) -> Callable[[Any, float, int], list[Sample]]:
    f = spec.fields
    scale = unit_scale(spec.units, "length", f"{where}.units")

    def build(msg: Any, t: float, origin_ns: int) -> list[Sample]:
        node = np.atleast_1d(_get(msg, f["node"] or "", where))
        anchor = np.atleast_1d(_get(msg, f["anchor"] or "", where))
        ranges = np.atleast_1d(np.asarray(_get(msg, f["range"] or "", where), dtype=np.float64))
        i, j = ids.module_ids(node), ids.module_ids(anchor)
        keep = (i >= 0) & (j >= 0) & (i != j) & np.isfinite(ranges)
        if not keep.any():
            return []
        pairs = np.column_stack([j[keep], i[keep]])
        if f["times"]:  # each range's own time, where the message has one
            stamps = np.atleast_1d(_get(msg, f["times"], where))
            ns = [_time_ns(x) for x in stamps.tolist()]
            times = np.array([ns_to_seconds(x - origin_ns) for x in ns])[keep]
        else:
            times = np.full(int(keep.sum()), t)
        return [UwbRangeSample(t, times, pairs, scale * ranges[keep])]

    return build


def _time_ns(x: Any) -> int:
    """A time as whole ns: a ``builtin_interfaces/Time`` or float seconds."""
    if hasattr(x, "sec"):
        return int(x.sec) * 1_000_000_000 + int(x.nanosec)
    return seconds_to_ns(float(x))


def _call(build: Any, msg: Any, ns: int, origin_ns: int) -> list[Sample]:
    return build(msg, ns_to_seconds(ns - origin_ns), origin_ns)  # type: ignore[no-any-return]


def read_topics(
    path: Path, topics: dict[str, TopicSpec], description: RobotDescription, ids: IdMap
) -> list[tuple[int, str, Callable[[int], list[Sample]]]]:
    """Every message of the map's ``topics`` in the ROS 1 or ROS 2 bag at ``path``:
    (its time in ns, its kind, the recording's origin ns -> its samples), in log order.

    Raises:
        LabFileError: the bag cannot be opened, lacks a topic the map names, or a
            message lacks a field; one line naming the bag and the topic.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as err:  # rosbags raises several types for a file that is no bag
        raise LabFileError(f"{path}: not a ROS 1 or ROS 2 bag: {err}") from None
    try:
        present = {c.topic for c in reader.connections}
        missing = sorted(set(topics) - present)
        if missing:
            raise LabFileError(
                f"{path}: no topic {missing[0]} (the bag has {', '.join(sorted(present))})"
            )
        builders = {t: _builder(s, description, ids, f"{path}: {t}") for t, s in topics.items()}
        out: list[tuple[int, str, Callable[[int], list[Sample]]]] = []
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, log_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            spec = topics[conn.topic]
            stamp = getattr(getattr(msg, "header", None), "stamp", None)
            ns = (
                log_ns
                if spec.log_time or stamp is None
                else stamp.sec * 1_000_000_000 + stamp.nanosec
            )
            build = builders[conn.topic]
            out.append((int(ns), spec.kind, partial(_call, build, msg, int(ns))))
        return out
    finally:
        reader.close()
