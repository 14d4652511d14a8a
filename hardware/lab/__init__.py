"""A lab's own files in: UWB ranges as CSV or NPZ (:mod:`hardware.lab.ranges`)."""

from hardware.lab.ranges import (
    COLUMNS,
    IdMap,
    LabFileError,
    RangeRows,
    identity_map,
    load_id_map,
    read_ranges,
    write_ranges,
)

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
