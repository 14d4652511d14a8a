"""Argument checks that name what is wrong: a NaN, an infinity or a zero where a positive
number belongs is refused where it is given, not deep inside the simulation."""

from __future__ import annotations

import math
import os
from numbers import Real
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import yaml
    from numpy.typing import NDArray

__all__ = [
    "all_finite",
    "check_fraction",
    "check_number",
    "check_open",
    "check_optional_number",
    "check_whole",
    "output_path_error",
    "yaml_problem",
]


def check_number(
    name: str,
    value: object,
    *,
    positive: bool = False,
    non_negative: bool = False,
    where: str = "make",
) -> float:
    """``value`` as a float, or ValueError ``"{where}: {name}=...: must be ..."``.

    Args:
        name: the argument's name, as the user wrote it.
        value: what was given; bools are refused (``True`` is no number of metres).
        positive: refuse zero and below.
        non_negative: refuse below zero.
        where: the call that took the argument, for the message.
    """
    bound = " and > 0" if positive else " and >= 0" if non_negative else ""
    if isinstance(value, bool) or not isinstance(value, Real):
        raise ValueError(f"{where}: {name}={value!r} must be a finite number{bound}")
    x = float(value)
    if not math.isfinite(x) or (positive and x <= 0.0) or (non_negative and x < 0.0):
        raise ValueError(f"{where}: {name}={value!r} must be a finite number{bound}")
    return x


def check_whole(name: str, value: object, low: int, high: int, *, where: str = "make") -> int:
    """``value`` as an int in [``low``, ``high``], or ValueError ``"{where}: {name}=...
    must be a whole number in [low, high]"`` (bools and 8.0 are refused; numpy ints pass)."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not (low <= int(value) <= high)
    ):
        raise ValueError(f"{where}: {name}={value!r} must be a whole number in [{low}, {high}]")
    return int(value)


def check_fraction(name: str, value: object, *, where: str = "make") -> float:
    """``value`` as a float in [0, 1), or ValueError ``"{where}: {name}=...: must be a
    finite number in [0, 1)"``."""
    if isinstance(value, bool) or not isinstance(value, Real) or not 0.0 <= float(value) < 1.0:
        raise ValueError(f"{where}: {name}={value!r} must be a finite number in [0, 1)")
    return float(value)


def check_optional_number(
    name: str,
    value: object,
    *,
    positive: bool = False,
    non_negative: bool = False,
    where: str = "make",
) -> float | None:
    """As :func:`check_number`, with None passed through (an option left unset)."""
    if value is None:
        return None
    return check_number(name, value, positive=positive, non_negative=non_negative, where=where)


def check_open(closed: bool, call: str) -> None:
    """RuntimeError naming ``call`` (``"step"``, ``"reset"``) if the env was closed: a
    closed env has no world left, and would otherwise build a new, un-reset one."""
    if closed:
        raise RuntimeError(f"{call}: the env was closed; make a new one (gym.make) to run again")


def all_finite(*arrays: NDArray[np.float64]) -> bool:
    """True if no entry of ``arrays`` is NaN or infinite. Their sum is tested first (finite
    only if every term is: one reduction for the common case on a hot path); a sum that
    is not may still come of finite terms too large to add, so the entries decide then."""
    if math.isfinite(sum(float(a.sum()) for a in arrays)):
        return True
    return all(bool(np.all(np.isfinite(a))) for a in arrays)


def yaml_problem(err: yaml.YAMLError) -> str:
    """PyYAML's error in one line: ``line L, column C: what it expected`` (its own
    message spans several lines, with a quote of the text and a caret)."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None) or " ".join(str(err).split())
    context = getattr(err, "context", None)
    what = f"{context}, {problem}" if context else str(problem)
    if mark is None:
        return what
    return f"line {mark.line + 1}, column {mark.column + 1}: {what}"


def output_path_error(
    path: str | os.PathLike[str], argument: str, *, folder: bool = False, writable: bool = True
) -> str | None:
    """Why ``path``, given as ``argument`` (``"--out"``), cannot be written, in one line
    naming both (``"--out 'x' is a folder, not a file"``), or None; checked before any
    long computation.

    Args:
        folder: ``path`` is a folder to write into (it must not be a file); else a file
            (it must not be a folder).
        writable: the nearest folder that exists on the way must be writable (the
            missing ones are made when the output is written).
    """
    target = Path(path)
    where = f"{argument} {str(path)!r}"
    if folder and target.exists() and not target.is_dir():
        return f"{where} is a file, not a folder"
    if not folder and target.is_dir():
        return f"{where} is a folder, not a file"
    nearest = target if folder else target.parent
    while not nearest.exists() and nearest != nearest.parent:
        nearest = nearest.parent
    if not nearest.is_dir():
        return f"{where}: {nearest} is a file, not a folder"
    if writable and not os.access(nearest, os.W_OK | os.X_OK):
        return f"{where}: the folder {nearest} is not writable"
    return None
