"""A lab's UWB ranges file: one row per range, as CSV or NPZ.

**Format.** Columns (CSV: a header row naming them, in any order, other columns
ignored; NPZ: arrays of these names, each (k,)):

- ``t``: time of the range (s, or the map's ``time`` unit), any clock origin;
- ``node``: the lab's id of the robot module that ranged;
- ``anchor``: the lab's id of the other module: an anchor, or, where the lab's robot
  ranges itself, another robot module;
- ``range``: the uncorrected range (m, or the map's ``range`` unit): true distance
  plus the pair's offset plus noise (Caluwaerts et al. 2016 eq. 6-7);
- ``stamp`` (optional): the time of the message the range came in; ranges of one
  stamp become one ``UwbRangeSample`` (without it, one per 0.1 s).

**Id map** (YAML), from the lab's ids to the description's::

    nodes:            # lab id -> endcap: its index or name in the description
      "12": 0
      "13": n1
    anchors:          # lab id -> anchor index (the description's sensors.uwb.anchors)
      "101": 0
    units: {time: s, range: m}   # optional: s|ms|us|ns and m|cm|mm (the range's)

Without a map, ids are the description's module ids (``UwbRangeSample``: nodes
0..n-1, anchors n..n+A-1). Rows whose id the map does not name are left out, with
one warning line; a range that is not finite is dropped. Times become seconds from
the first range's whole second (as a bag's), so that float seconds keep them exact.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hardware.lab.table import LabFileError, nanoseconds, read_table, read_yaml, unit_scale
from tensegrity_gym.model.samples import UwbRangeSample, ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    import os
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "COLUMNS",
    "IdMap",
    "RangeRows",
    "id_map_from_doc",
    "identity_map",
    "load_id_map",
    "read_ranges",
    "write_ranges",
]

logger = logging.getLogger(__name__)

COLUMNS = ("t", "node", "anchor", "range")
STAMP = "stamp"
"""The optional column of the time of the message (sample) a range came in."""
SUFFIXES = (".csv", ".npz")


@dataclass(frozen=True)
class IdMap:
    """The lab's module ids (as text) -> the description's module ids (nodes 0..n-1,
    anchors n..n+A-1), and the file's units (factors to s and m)."""

    modules: dict[str, int]
    time_scale: float = 1.0
    range_scale: float = 1.0

    def module_ids(self, lab_ids: NDArray[Any]) -> NDArray[np.intp]:
        """The description's module id of each lab id (k,); -1 where the map lacks it."""
        return np.array([self.modules.get(_plain(x), -1) for x in lab_ids.tolist()], dtype=np.intp)


def identity_map(description: RobotDescription) -> IdMap:
    """Ids that already are the description's module ids."""
    n = description.n_nodes + len(description.anchors)
    return IdMap({str(k): k for k in range(n)})


def _node_index(value: Any, description: RobotDescription, where: str) -> int:
    names = [node.name for node in description.nodes]
    if isinstance(value, str) and value in names:
        return names.index(value)
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < len(names):
        return value
    raise LabFileError(
        f"{where}: {value!r} is not one of {description.name}'s endcaps "
        f"(index 0..{len(names) - 1} or a name: {', '.join(names)})"
    )


def _anchor_index(value: Any, description: RobotDescription, where: str) -> int:
    A = len(description.anchors)
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < A:
        return description.n_nodes + value
    raise LabFileError(
        f"{where}: {value!r} is not one of {description.name}'s {A} anchors "
        f"(index 0..{A - 1}, the order of sensors.uwb.anchors)"
    )


def load_id_map(path: str | os.PathLike[str], description: RobotDescription) -> IdMap:
    """The id map in ``path`` (YAML, see the module's doc) for ``description``."""
    source = str(path)
    doc = read_yaml(path, "id map")
    return id_map_from_doc(doc, description, source)


def id_map_from_doc(doc: Any, description: RobotDescription, source: str) -> IdMap:
    """An id map from its parsed YAML ``doc``; errors name ``source`` and the field."""
    if not isinstance(doc, dict) or not {"nodes", "anchors"} <= doc.keys():
        raise LabFileError(f"{source}: an id map is a mapping with 'nodes' and 'anchors'")
    unknown = sorted(set(doc) - {"nodes", "anchors", "units"})
    if unknown:
        raise LabFileError(f"{source}: {unknown[0]}: unknown field (nodes, anchors, units)")
    modules: dict[str, int] = {}
    for part, index in (("nodes", _node_index), ("anchors", _anchor_index)):
        if not isinstance(doc[part], dict):
            raise LabFileError(f"{source}: {part}: expected a mapping of lab id -> index")
        for lab_id, value in doc[part].items():
            key = str(lab_id)
            if key in modules:
                raise LabFileError(f"{source}: {part}.{key}: the lab id is named twice")
            modules[key] = index(value, description, f"{source}: {part}.{key}")
    units = doc.get("units") or {}
    if not isinstance(units, dict):
        raise LabFileError(f"{source}: units: expected a mapping (time, range)")
    return IdMap(
        modules,
        unit_scale(units, "time", f"{source}: units"),
        unit_scale({"length": units.get("range", "m")}, "length", f"{source}: units"),
    )


@dataclass(frozen=True)
class RangeRows:
    """The ranges of a lab's file, in the description's module ids."""

    t: NDArray[np.float64]
    """(k,) s from :attr:`clock_origin_ns`, sorted (by message, where the file has them)."""
    module_i: NDArray[np.intp]
    module_j: NDArray[np.intp]
    """(k,) the two module ids of each range (``UwbRangeSample``'s)."""
    ranges: NDArray[np.float64]
    """(k,) m."""
    clock_origin_ns: int
    """The file's time of t = 0 (ns on its clock)."""
    stamp: NDArray[np.float64] | None = None
    """(k,) s: the time of the message each range came in, where the file says."""

    def samples(self, period: float = 0.1) -> list[UwbRangeSample]:
        """One ``UwbRangeSample`` per message where the file has a ``stamp`` column;
        else the rows gathered into one per ``period`` s (stamped at its end), as a
        lab's ROS node gathers them."""
        if self.stamp is not None:
            cut = np.flatnonzero(np.diff(self.stamp)) + 1
            stamps = self.stamp
        else:
            bins = np.floor(self.t / period).astype(np.intp)
            cut = np.flatnonzero(np.diff(bins)) + 1
            stamps = np.array([ns_to_seconds(seconds_to_ns((b + 1) * period)) for b in bins])
        out = []
        for rows in np.split(np.arange(len(self.t)), cut):
            if len(rows) == 0:
                continue
            pairs = np.column_stack([self.module_j[rows], self.module_i[rows]])
            out.append(UwbRangeSample(float(stamps[rows[0]]), self.t[rows].copy(), pairs,
                                      self.ranges[rows].copy()))  # fmt: skip
        return out


def _columns(path: Path) -> dict[str, NDArray[Any]]:
    """The file's columns (ids as text, ranges as numbers; ``stamp`` where it has one)."""
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [c for c in COLUMNS if c not in z.files]
                if missing:
                    raise LabFileError(
                        f"{path}: no array {missing[0]!r} (needs {', '.join(COLUMNS)})"
                    )
                cols = {c: np.asarray(z[c]) for c in (*COLUMNS, STAMP) if c in z.files}
        except (OSError, ValueError) as err:
            if isinstance(err, LabFileError):
                raise
            raise LabFileError(f"{path}: not an NPZ ranges file: {err}") from None
        lengths = {c: v.shape for c, v in cols.items()}
        if len(set(lengths.values())) != 1 or cols["t"].ndim != 1:
            raise LabFileError(f"{path}: the arrays must be 1-D of one length: {lengths}")
        return cols | {k: cols[k].astype(str) for k in ("node", "anchor")}
    table = read_table(path, COLUMNS, (STAMP,))
    cols = dict(table.columns)
    cols["range"] = table.numbers("range")
    return cols


def read_ranges(
    path: str | os.PathLike[str], description: RobotDescription, ids: IdMap | None = None
) -> RangeRows:
    """The ranges of a lab's CSV or NPZ file (see the module's doc) in ``description``'s
    module ids, sorted by time.

    Raises:
        LabFileError: the file is missing, of another kind, or malformed, or none of
            its rows names a module the map knows; one line naming the file (and line).
    """
    p = Path(path)
    if p.suffix.lower() not in SUFFIXES:
        raise LabFileError(f"{p}: a ranges file is .csv or .npz, not {p.suffix or 'no suffix'!r}")
    if not p.is_file():
        raise LabFileError(f"{p}: no such file")
    ids = ids or identity_map(description)
    cols = _columns(p)
    node, other = ids.module_ids(cols["node"]), ids.module_ids(cols["anchor"])
    known = (node >= 0) & (other >= 0) & (node != other)
    if not known.all():
        strange = sorted(
            {str(x) for x, k in zip(cols["node"], node >= 0, strict=True) if not k}
            | {str(x) for x, k in zip(cols["anchor"], other >= 0, strict=True) if not k}
        )
        if not known.any():
            raise LabFileError(
                f"{p}: no row names two modules the id map knows (ids seen: "
                f"{', '.join(strange[:8]) or 'none'}); give an id map"
            )
        logger.warning("%s: %d rows with ids the map does not name left out (%s)", p,
                       int(np.count_nonzero(~known)), ", ".join(strange[:8]))  # fmt: skip
    ns = nanoseconds(cols["t"], ids.time_scale)
    message = nanoseconds(cols[STAMP], ids.time_scale) if STAMP in cols else None
    m = cols["range"].astype(np.float64) * ids.range_scale
    keep = known & np.array([x is not None for x in ns], dtype=bool) & np.isfinite(m)
    if message is not None:
        keep &= np.array([x is not None for x in message], dtype=bool)
    if not keep.any():
        raise LabFileError(f"{p}: no row with a finite time and range")
    stamps = np.array([x for x, k in zip(ns, keep, strict=True) if k], dtype=np.int64)
    node, other, m = node[keep], other[keep], m[keep]
    origin_ns = int(stamps.min()) // 1_000_000_000 * 1_000_000_000
    # By message (the file's order within one), else by time.
    sent = (
        None if message is None
        else np.array([x for x, k in zip(message, keep, strict=True) if k], dtype=np.int64)
    )  # fmt: skip
    order = np.argsort(stamps if sent is None else sent, kind="stable")
    # Times on whole nanoseconds from the origin's second, as a bag keeps them.
    rel = np.array([ns_to_seconds(int(x) - origin_ns) for x in stamps[order]])
    stamp = (
        None if sent is None else np.array([ns_to_seconds(int(x) - origin_ns) for x in sent[order]])
    )
    return RangeRows(rel, node[order], other[order], m[order], origin_ns, stamp)


def _plain(x: Any) -> str:
    """An id as text: ``"12"`` for 12, 12.0 or "12"."""
    text = str(x).strip()
    try:
        value = float(text)
    except ValueError:
        return text
    return str(int(value)) if value.is_integer() else text


def write_ranges(
    path: str | os.PathLike[str],
    samples: Sequence[UwbRangeSample],
    n_nodes: int,
    *,
    clock_origin_ns: int | None = None,
) -> None:
    """``samples``' robot-anchor and robot-robot ranges as a ranges file (CSV or NPZ by
    ``path``'s suffix) in the module ids of ``UwbRangeSample`` (no id map needed), with
    each sample's time as the ``stamp`` column. Times in s as the samples have them, or
    with ``clock_origin_ns`` in whole ns on the recording's clock (``units: {time: ns}``:
    exact, whatever the clock)."""
    rows = [(s.t, tk, int(a), int(b), float(r)) for s in samples
            for tk, (a, b), r in zip(s.times, np.asarray(s.pairs).reshape(-1, 2), s.ranges,
                                     strict=True)]  # fmt: skip
    # The computing robot module is the row's node (the responder of UwbRangeSample's
    # pair), the initiator its anchor: the pair's order survives the trip.
    rows = [r if r[3] < n_nodes else (r[0], r[1], r[3], r[2], r[4]) for r in rows]
    rows = [r for r in rows if r[3] < n_nodes]

    def time(x: float) -> Any:
        return repr(float(x)) if clock_origin_ns is None else clock_origin_ns + seconds_to_ns(x)

    p = Path(path)
    if p.suffix.lower() == ".npz":
        kind = np.float64 if clock_origin_ns is None else np.int64
        np.savez_compressed(
            p, t=np.array([time(r[1]) for r in rows], dtype=kind),
            node=np.array([r[3] for r in rows]), anchor=np.array([r[2] for r in rows]),
            range=np.array([r[4] for r in rows]),
            stamp=np.array([time(r[0]) for r in rows], dtype=kind),
        )  # fmt: skip
        return
    with p.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow((*COLUMNS, STAMP))
        for stamp, t, anchor, node, r in rows:
            w.writerow((time(t), node, anchor, repr(r), time(stamp)))
