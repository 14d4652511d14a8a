"""A lab's own files in: UWB ranges as CSV or NPZ (:mod:`hardware.lab.ranges`), CSV logs
of the other sensors (:mod:`hardware.lab.logs`), and a whole recording written as this
project's bag (:mod:`hardware.lab.importer`)."""

from hardware.lab.importer import (
    LabMap,
    LabReplay,
    import_recording,
    load_lab_map,
    read_recording,
)
from hardware.lab.logs import write_logs
from hardware.lab.ranges import (
    COLUMNS,
    IdMap,
    RangeRows,
    identity_map,
    load_id_map,
    read_ranges,
    write_ranges,
)
from hardware.lab.table import LabFileError

__all__ = [
    "COLUMNS",
    "IdMap",
    "LabFileError",
    "LabMap",
    "LabReplay",
    "RangeRows",
    "identity_map",
    "import_recording",
    "load_id_map",
    "load_lab_map",
    "read_ranges",
    "read_recording",
    "write_logs",
    "write_ranges",
]
