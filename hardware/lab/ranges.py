"""A lab's UWB ranges file: one row per range, as CSV or NPZ.

**Format.** Columns (CSV: a header row naming them, in any order, other columns
ignored; NPZ: arrays of these names, each (k,)):

- ``t``: time of the range (s, or the map's ``time`` unit), any clock origin;
- ``node``: the lab's id of the robot module that ranged;
- ``anchor``: the lab's id of the other module: an anchor, or, where the lab's robot
  ranges itself, another robot module;
- ``range``: the uncorrected range (m, or the map's ``range`` unit): true distance
  plus the pair's offset plus noise (Caluwaerts et al. 2016 eq. 6-7).

**Id map** (YAML), from the lab's ids to the description's::

    nodes:            # lab id -> endcap: its index or name in the description
      "12": 0
      "13": n1
    anchors:          # lab id -> anchor index (the description's sensors.uwb.anchors)
      "101": 0
    units: {time: s, range: m}   # optional: s|ms|us|ns and m|cm|mm

Without a map, ids are the description's module ids (``UwbRangeSample``: nodes
0..n-1, anchors n..n+A-1). Rows whose id the map does not name are left out, with
one warning line; a range that is not finite is dropped. Times become seconds from
the first range's whole second (as a bag's), so that float seconds keep them exact.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from tensegrity_gym.model.samples import UwbRangeSample, ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    import os

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "COLUMNS",
    "IdMap",
    "LabFileError",
    "RangeRows",
    "identity_map",
    "load_id_map",
    "read_ranges",
    "write_ranges",
]

logger = logging.getLogger(__name__)

COLUMNS = ("t", "node", "anchor", "range")
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
RANGE_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
SUFFIXES = (".csv", ".npz")


class LabFileError(ValueError):
    """A lab's file or id map cannot be read; one line naming the file (and the field,
    or the line)."""


@dataclass(frozen=True)
class IdMap:
    """The lab's module ids (as text) -> the description's module ids (nodes 0..n-1,
    anchors n..n+A-1), and the file's units (factors to s and m)."""

    modules: dict[str, int]
    time_scale: float = 1.0
    range_scale: float = 1.0


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


def _unit(units: dict[str, Any], key: str, table: dict[str, float], where: str) -> float:
    name = units.get(key, next(iter(table)))
    if name not in table:
        raise LabFileError(f"{where}.{key}: {name!r} is not one of {', '.join(table)}")
    return table[name]


def load_id_map(path: str | os.PathLike[str], description: RobotDescription) -> IdMap:
    """The id map in ``path`` (YAML, see the module's doc) for ``description``."""
    source = str(path)
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise LabFileError(f"{source}: no such file") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise LabFileError(f"{source}: not a YAML id map: {str(err).splitlines()[0]}") from None
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
        _unit(units, "time", TIME_UNITS, f"{source}: units"),
        _unit(units, "range", RANGE_UNITS, f"{source}: units"),
    )


@dataclass(frozen=True)
class RangeRows:
    """The ranges of a lab's file, in the description's module ids."""

    t: NDArray[np.float64]
    """(k,) s from :attr:`clock_origin_ns`, sorted."""
    module_i: NDArray[np.intp]
    module_j: NDArray[np.intp]
    """(k,) the two module ids of each range (``UwbRangeSample``'s)."""
    ranges: NDArray[np.float64]
    """(k,) m."""
    clock_origin_ns: int
    """The file's time of t = 0 (ns on its clock)."""

    def samples(self, period: float = 0.1) -> list[UwbRangeSample]:
        """The rows gathered into one ``UwbRangeSample`` per ``period`` s (stamped at
        the period's end), as a lab's ROS node gathers them."""
        bins = np.floor(self.t / period).astype(np.intp)
        cut = np.flatnonzero(np.diff(bins)) + 1
        out = []
        for rows in np.split(np.arange(len(self.t)), cut):
            if len(rows) == 0:
                continue
            stamp = ns_to_seconds(seconds_to_ns((bins[rows[0]] + 1) * period))
            pairs = np.column_stack([self.module_j[rows], self.module_i[rows]])
            out.append(UwbRangeSample(stamp, self.t[rows].copy(), pairs, self.ranges[rows].copy()))
        return out


def _columns(path: Path) -> dict[str, NDArray[Any]]:
    """The file's four columns (ids as text), raw."""
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [c for c in COLUMNS if c not in z.files]
                if missing:
                    raise LabFileError(
                        f"{path}: no array {missing[0]!r} (needs {', '.join(COLUMNS)})"
                    )
                cols = {c: np.asarray(z[c]) for c in COLUMNS}
        except (OSError, ValueError) as err:
            if isinstance(err, LabFileError):
                raise
            raise LabFileError(f"{path}: not an NPZ ranges file: {err}") from None
        lengths = {c: v.shape for c, v in cols.items()}
        if len(set(lengths.values())) != 1 or cols["t"].ndim != 1:
            raise LabFileError(f"{path}: the arrays must be 1-D of one length: {lengths}")
        return cols | {k: cols[k].astype(str) for k in ("node", "anchor")}
    return _csv_columns(path)


def _csv_columns(path: Path) -> dict[str, NDArray[Any]]:
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = [h.strip() for h in next(reader, [])]
            missing = [c for c in COLUMNS if c not in header]
            if missing:
                raise LabFileError(
                    f"{path}: line 1: no column {missing[0]!r} (the header must name "
                    f"{', '.join(COLUMNS)})"
                )
            at = [header.index(c) for c in COLUMNS]
            rows = [(k + 2, row) for k, row in enumerate(reader) if row]
    except UnicodeDecodeError:
        raise LabFileError(f"{path}: not a CSV text file") from None
    except OSError as err:
        raise LabFileError(f"{path}: cannot be read: {err.strerror}") from None
    values: dict[str, list[Any]] = {c: [] for c in COLUMNS}
    for line, row in rows:
        if len(row) < len(header):
            raise LabFileError(
                f"{path}: line {line}: {len(row)} fields, the header has {len(header)}"
            )
        for c, k in zip(COLUMNS, at, strict=True):
            values[c].append(row[k].strip())
    out = {c: np.asarray(values[c], dtype=str) for c in ("node", "anchor")}
    for c in ("t", "range"):
        try:
            out[c] = np.asarray(values[c] or [], dtype=np.float64)
        except ValueError:
            bad = next(k for k, v in enumerate(values[c]) if not _is_number(v))
            raise LabFileError(
                f"{path}: line {rows[bad][0]}: {c} {values[c][bad]!r} is not a number"
            ) from None
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


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
    node = np.array([ids.modules.get(_plain(x), -1) for x in cols["node"]], dtype=np.intp)
    other = np.array([ids.modules.get(_plain(x), -1) for x in cols["anchor"]], dtype=np.intp)
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
    ns = _nanoseconds(cols["t"], ids.time_scale)
    m = cols["range"].astype(np.float64) * ids.range_scale
    keep = known & np.array([x is not None for x in ns], dtype=bool) & np.isfinite(m)
    if not keep.any():
        raise LabFileError(f"{p}: no row with a finite time and range")
    stamps = np.array([x for x, k in zip(ns, keep, strict=True) if k], dtype=np.int64)
    node, other, m = node[keep], other[keep], m[keep]
    order = np.argsort(stamps, kind="stable")
    origin_ns = int(stamps.min()) // 1_000_000_000 * 1_000_000_000
    # Times on whole nanoseconds from the origin's second, as a bag keeps them.
    rel = np.array([ns_to_seconds(int(x) - origin_ns) for x in stamps[order]])
    return RangeRows(rel, node[order], other[order], m[order], origin_ns)


def _nanoseconds(column: NDArray[Any], scale: float) -> list[int | None]:
    """Each time of ``column`` (text or numbers, in units of ``scale`` s) in whole
    nanoseconds, exactly where the file writes it exactly (``1465000000250`` ms is
    not rounded through a float); None where it is not finite."""
    per_unit = Decimal(repr(scale)) * 1_000_000_000
    out: list[int | None] = []
    for x in column.tolist():
        try:
            value = Decimal(str(x))
        except InvalidOperation:
            out.append(None)
            continue
        out.append(int((value * per_unit).to_integral_value()) if value.is_finite() else None)
    return out


def _plain(x: Any) -> str:
    """An id as text: ``"12"`` for 12, 12.0 or "12"."""
    text = str(x).strip()
    try:
        value = float(text)
    except ValueError:
        return text
    return str(int(value)) if value.is_integer() else text


def write_ranges(path: str | os.PathLike[str], samples: list[UwbRangeSample],
                 n_nodes: int) -> None:  # fmt: skip
    """``samples``' robot-anchor and robot-robot ranges as a ranges file (CSV or NPZ by
    ``path``'s suffix) in the module ids of ``UwbRangeSample`` (no id map needed)."""
    t = np.concatenate([np.asarray(s.times, dtype=np.float64) for s in samples])
    pairs = np.concatenate([np.asarray(s.pairs, dtype=np.intp).reshape(-1, 2) for s in samples])
    m = np.concatenate([np.asarray(s.ranges, dtype=np.float64) for s in samples])
    # The robot's module first: it is the row's node.
    node, other = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    keep = node < n_nodes
    p = Path(path)
    if p.suffix.lower() == ".npz":
        np.savez_compressed(p, t=t[keep], node=node[keep], anchor=other[keep], range=m[keep])
        return
    with p.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for row in zip(t[keep], node[keep], other[keep], m[keep], strict=True):
            w.writerow((repr(float(row[0])), int(row[1]), int(row[2]), repr(float(row[3]))))
