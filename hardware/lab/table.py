"""A lab's CSV file as named text columns, with line numbers for its errors."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

if TYPE_CHECKING:
    import os
    from collections.abc import Sequence

    from numpy.typing import NDArray

__all__ = [
    "UNITS",
    "LabFileError",
    "Table",
    "nanoseconds",
    "read_table",
    "read_yaml",
    "rod_index",
    "unit_scale",
]

UNITS: dict[str, dict[str, float]] = {
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
    "length": {"m": 1.0, "cm": 1e-2, "mm": 1e-3},
    "accel": {"m/s^2": 1.0, "g": 9.80665},
    "gyro": {"rad/s": 1.0, "deg/s": math.pi / 180.0},
    "mag": {"T": 1.0, "uT": 1e-6, "G": 1e-4},
}
"""Each quantity's units in a lab's files and their factor to SI; the first is the default."""


class LabFileError(ValueError):
    """A lab's file or map cannot be read; one line naming the file (and the field, or
    the line)."""


def rod_index(name: Any, rod_names: Sequence[str], where: str) -> int:
    """The index of the rod a lab names by its name or its index; LabFileError naming
    ``where`` for one the robot does not have."""
    text = str(name).strip()
    if text in rod_names:
        return list(rod_names).index(text)
    if text.isdigit() and int(text) < len(rod_names):
        return int(text)
    raise LabFileError(
        f"{where}: rod {text!r} is not one of {', '.join(rod_names)} or 0..{len(rod_names) - 1}"
    )


def read_yaml(path: str | os.PathLike[str], what: str) -> Any:
    """The parsed YAML of ``path``; LabFileError naming the file and ``what`` it should
    be where it is missing or not YAML."""
    source = str(path)
    try:
        return yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise LabFileError(f"{source}: no such file") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise LabFileError(f"{source}: not a YAML {what}: {str(err).splitlines()[0]}") from None


def unit_scale(units: dict[str, Any], quantity: str, where: str) -> float:
    """The factor to SI of ``units[quantity]`` (its default unit where absent);
    LabFileError naming ``where`` for a unit the table does not know."""
    table = UNITS[quantity]
    name = units.get(quantity, next(iter(table)))
    if name not in table:
        raise LabFileError(f"{where}.{quantity}: {name!r} is not one of {', '.join(table)}")
    return float(table[name])


@dataclass(frozen=True)
class Table:
    """A CSV file's columns (text, stripped), by header name."""

    path: Path
    columns: dict[str, NDArray[np.str_]]
    lines: NDArray[np.intp]
    """(k,) the file's line number of each row (1 is the header)."""

    def numbers(self, name: str) -> NDArray[np.float64]:
        """Column ``name`` as numbers (NaN stays NaN); LabFileError at the first
        value that is not a number, naming its line."""
        values = self.columns[name]
        try:
            return np.asarray(values, dtype=np.float64)
        except ValueError:
            bad = next(k for k, v in enumerate(values.tolist()) if not _is_number(v))
            raise LabFileError(
                f"{self.path}: line {self.lines[bad]}: {name} {str(values[bad])!r} is not a number"
            ) from None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_table(path: Path, required: Sequence[str], optional: Sequence[str] = ()) -> Table:
    """The ``required`` columns of CSV file ``path`` (and those of ``optional`` its
    header names); other columns are ignored.

    Raises:
        LabFileError: the file cannot be read, is not text, lacks a required column,
            or has a row shorter than its header; one line naming the file and line.
    """
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = [h.strip() for h in next(reader, [])]
            missing = [c for c in required if c not in header]
            if missing:
                raise LabFileError(
                    f"{path}: line 1: no column {missing[0]!r} (the header must name "
                    f"{', '.join(required)})"
                )
            rows = [(k + 2, row) for k, row in enumerate(reader) if row]
    except UnicodeDecodeError:
        raise LabFileError(f"{path}: not a CSV text file") from None
    except OSError as err:
        raise LabFileError(f"{path}: cannot be read: {err.strerror}") from None
    names = [*required, *(c for c in optional if c in header)]
    at = [header.index(c) for c in names]
    values: dict[str, list[str]] = {c: [] for c in names}
    for line, row in rows:
        if len(row) < len(header):
            raise LabFileError(
                f"{path}: line {line}: {len(row)} fields, the header has {len(header)}"
            )
        for c, k in zip(names, at, strict=True):
            values[c].append(row[k].strip())
    columns = {c: np.asarray(v, dtype=str) for c, v in values.items()}
    lines = np.array([line for line, _ in rows], dtype=np.intp)
    return Table(path, columns, lines)


def nanoseconds(column: NDArray[Any], scale: float) -> list[int | None]:
    """Each time of ``column`` (text or numbers, in units of ``scale`` s) in whole
    nanoseconds, exactly where the file writes it exactly (``1465000000250`` ms or
    ``1465000000.123456789`` s are not rounded through a float); None where it is not
    a finite number."""
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
