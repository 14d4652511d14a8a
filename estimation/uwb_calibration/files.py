"""A calibration in YAML: :func:`save_calibration`, :func:`load_calibration`.

The file (``version: 1``)::

    version: 1
    robot: superball            # the description's name; "" if unknown
    frame: floor                # or "known" (the lab's frame of known anchors), or
                                # "anchors" (no floor found: the anchors' own gauge)
    anchors: [[x, y, z], ...]   # m, (A, 3)
    offsets: [[...], ...]       # m, (n + A, n + A), symmetric
    camera:                     # optional: a SensorCalibration's camera
      intrinsics: [[...], ...]  # (3, 3) pixels
      pose: [[...], ...]        # (4, 4) camera to world
    result:                     # optional: what the calibrator said
      verdict: good
      ...

A bad file is one ``CalibrationFileError`` line naming the file and the field; a file
that is no calibration at all (binary, not a YAML mapping, no ``version``) says so.
:func:`save_calibration` writes a sibling ``.part`` file and renames it over the
target, so that a reader never sees half a file and a failure leaves nothing behind;
:func:`check_output_path` finds what would stop the write before a long calibration.
"""

from __future__ import annotations

import os
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from estimation.uwb_calibration.result import CalibrationResult, ResidualStats
from tensegrity_gym.model.checks import output_path_error
from tensegrity_gym.model.protocols import SensorCalibration

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = [
    "VERSION",
    "CalibrationFile",
    "CalibrationFileError",
    "check_output_path",
    "load_calibration",
    "save_calibration",
]

VERSION = 1
FRAMES = ("floor", "known", "anchors")
FLOORS = ("contacts", "gravity", "hint", "gravity+hint", "known", "none")
_STATS = ("count", "median", "spread", "rms", "outlier_fraction", "drift")


class CalibrationFileError(ValueError):
    """A calibration file is missing, not a calibration file, malformed, or cannot be
    written where asked; one line naming the file (and the field)."""


_FORMAT = "a calibration file is YAML from tensegrity-gym calibrate"


@dataclass(frozen=True)
class CalibrationFile:
    """What :func:`load_calibration` read."""

    robot: str
    frame: str
    anchors: NDArray[np.float64]
    """(A, 3) m."""
    offsets: NDArray[np.float64]
    """(n + A, n + A) m."""
    camera_intrinsics: NDArray[np.float64] | None = None
    camera_pose: NDArray[np.float64] | None = None
    result: CalibrationResult | None = None
    """The calibrator's result where the file holds one."""

    def to_calibration(self, base: SensorCalibration | None = None) -> SensorCalibration:
        """A :class:`SensorCalibration`: these anchors and offsets; the camera from the
        file, else from ``base``, else identity."""
        intrinsics = self.camera_intrinsics if self.camera_intrinsics is not None else (
            base.camera_intrinsics if base is not None else np.eye(3))  # fmt: skip
        pose = self.camera_pose if self.camera_pose is not None else (
            base.camera_pose if base is not None else np.eye(4))  # fmt: skip
        return SensorCalibration(self.offsets.copy(), self.anchors.copy(), intrinsics, pose)


def _matrix(x: NDArray[np.float64]) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(x, dtype=np.float64)]


def _result_doc(r: CalibrationResult) -> dict[str, Any]:
    pairs = {k: [[float(getattr(s, k)) for s in row] for row in r.pair_stats] for k in _STATS}
    return {
        "verdict": r.verdict,
        "floor": r.floor,
        "flagged_anchors": [int(a) for a in r.flagged_anchors],
        "mirror": r.mirror,
        "mean_offset": float(r.mean_offset),
        "anchor_sigma": [float(v) for v in r.anchor_sigma],
        "anchor_residuals": [{k: float(v) for k, v in asdict(s).items()} for s in r.anchor_stats],
        "pair_residuals": pairs,
        "robot_pair_count": r.robot_pair_count.tolist(),
        "n_samples": r.n_samples, "n_usable": r.n_usable, "n_rounds": r.n_rounds,
        "cost": float(r.cost), "wall_time": float(r.wall_time),
        "extras": {k: float(v) for k, v in r.extras.items()},
    }  # fmt: skip


def save_calibration(
    path: str | os.PathLike[str],
    calibration: CalibrationResult | SensorCalibration,
    *,
    robot: str = "",
) -> None:
    """Write ``calibration`` to ``path`` (YAML): a calibrator's result with its verdict
    and residuals, or a :class:`SensorCalibration` with its camera. The file appears
    whole or not at all (a ``.part`` sibling renamed over it; removed on any failure).

    Raises:
        CalibrationFileError: ``path`` cannot be written; one line naming it.
    """
    doc: dict[str, Any] = {"version": VERSION, "robot": robot}
    if isinstance(calibration, CalibrationResult):
        doc["frame"] = calibration.frame
        doc["anchors"] = _matrix(calibration.anchors)
        doc["offsets"] = _matrix(calibration.offsets)
        doc["result"] = _result_doc(calibration)
    else:
        doc["frame"] = "floor"
        doc["anchors"] = _matrix(calibration.anchors)
        doc["offsets"] = _matrix(calibration.uwb_offsets)
        camera = (calibration.camera_intrinsics, calibration.camera_pose)
        doc["camera"] = {"intrinsics": _matrix(camera[0]), "pose": _matrix(camera[1])}
    text = yaml.safe_dump(doc, sort_keys=False, width=120)
    target = Path(path)
    # Unique per writer: two processes calibrating the same world at once each rename
    # their own whole file, and either one is the result.
    part = target.with_name(f"{target.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.part")
    try:
        part.write_text(text)
        os.replace(part, target)
    except OSError as e:
        raise CalibrationFileError(f"{target}: cannot write: {e.strerror or e}") from None
    finally:
        part.unlink(missing_ok=True)


def check_output_path(
    path: str | os.PathLike[str], argument: str, *, writable: bool = True
) -> Path:
    """``path`` as a :class:`Path` where a calibration file can be written, checked
    before any calibration is made: not a folder, no file where a folder of its path
    should be, and (``writable``) the nearest existing folder writable (the missing
    ones are made when the file is written).

    Args:
        argument: how the path was given (``"--out"``, ``"calibration cache"``), for
            the message.

    Raises:
        CalibrationFileError: one line naming ``argument``, the path and what is wrong.
    """
    error = output_path_error(path, argument, writable=writable)
    if error is not None:
        raise CalibrationFileError(error)
    return Path(path)


class _Reader:
    """Reads fields of the parsed document; errors name the file and the field."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, field: str, message: str) -> CalibrationFileError:
        return CalibrationFileError(f"{self.source}: {field}: {message}")

    def mapping(
        self, value: Any, field: str, required: set[str], optional: set[str]
    ) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(field, f"expected a mapping, got {type(value).__name__}")
        prefix = f"{field}." if field else ""
        for key in sorted(required - value.keys()):
            raise self.fail(prefix + key, "missing field")
        for key in sorted(set(value) - required - optional):
            raise self.fail(prefix + str(key), "unknown field")
        return value

    def array(
        self, value: Any, field: str, shape: tuple[int | None, ...], *, finite: bool = True
    ) -> NDArray[np.float64]:
        try:
            out = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(field, f"expected numbers of shape {_shape(shape)}") from None
        if out.ndim != len(shape) or any(
            s is not None and s != d for s, d in zip(shape, out.shape, strict=True)
        ):
            raise self.fail(field, f"expected shape {_shape(shape)}, got {out.shape}")
        if finite and not np.all(np.isfinite(out)):
            raise self.fail(field, "must be finite")
        return out


def _shape(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("k" if s is None else str(s) for s in shape) + ")"


def _stats(values: dict[str, Any]) -> ResidualStats:
    return ResidualStats(int(values["count"]), *(float(values[k]) for k in _STATS[1:]))


_RESULT_KEYS = {
    "verdict", "flagged_anchors", "mirror", "mean_offset", "anchor_sigma", "anchor_residuals",
    "pair_residuals", "robot_pair_count", "n_samples", "n_usable", "n_rounds", "cost",
    "wall_time", "extras",
}  # fmt: skip


def _result(
    r: _Reader, doc: Any, anchors: NDArray[np.float64], offsets: NDArray[np.float64], frame: str
) -> CalibrationResult:
    """The ``result`` section as a :class:`CalibrationResult`."""
    d = r.mapping(doc, "result", _RESULT_KEYS, {"floor"})  # files before "floor": contacts
    if d.get("floor", "contacts") not in FLOORS:
        raise r.fail("result.floor", f"expected one of {', '.join(FLOORS)}, got {d['floor']!r}")
    A, n = len(anchors), len(offsets) - len(anchors)
    listed = d["anchor_residuals"] if isinstance(d["anchor_residuals"], list) else []
    if len(listed) != A:
        raise r.fail("result.anchor_residuals", f"expected {A} entries, got {len(listed)}")
    per_anchor = [
        r.mapping(s, f"result.anchor_residuals[{k}]", set(_STATS), set())
        for k, s in enumerate(listed)
    ]
    pr = r.mapping(d["pair_residuals"], "result.pair_residuals", set(_STATS), set())
    # A pair without a range has no median, an anchor no drift in a short run: NaN.
    pair = {k: r.array(pr[k], f"result.pair_residuals.{k}", (A, n), finite=False) for k in _STATS}
    pair_stats = tuple(
        tuple(_stats({k: pair[k][a, j] for k in _STATS}) for j in range(n)) for a in range(A)
    )
    count = r.array(d["robot_pair_count"], "result.robot_pair_count", (n, n))
    return CalibrationResult(
        anchors=anchors,
        offsets=offsets,
        mean_offset=float(d["mean_offset"]),
        anchor_sigma=r.array(d["anchor_sigma"], "result.anchor_sigma", (A,)),
        anchor_stats=tuple(_stats(s) for s in per_anchor),
        pair_stats=pair_stats,
        robot_pair_count=count.astype(np.intp),
        n_samples=int(d["n_samples"]),
        n_usable=int(d["n_usable"]),
        n_rounds=int(d["n_rounds"]),
        cost=float(d["cost"]),
        verdict=str(d["verdict"]),
        flagged_anchors=tuple(int(a) for a in d["flagged_anchors"]),
        mirror=str(d["mirror"]),
        frame=frame,
        floor=str(d.get("floor", "contacts")),
        wall_time=float(d["wall_time"]),
        extras={str(k): float(v) for k, v in dict(d["extras"]).items()},
    )


def load_calibration(
    path: str | os.PathLike[str], *, argument: str | None = None
) -> CalibrationFile:
    """Read a calibration written by :func:`save_calibration`.

    Args:
        argument: how the path was given (``"calibration"``, ``"make: calibration"``);
            errors then start ``argument='path'`` instead of the path alone.

    Raises:
        CalibrationFileError: the file is missing, not a calibration file (binary, not
            YAML, not a YAML mapping, no ``version``), of another version, or a field
            is missing, unknown or malformed; one line naming file and field.
    """
    source = str(path) if argument is None else f"{argument}={str(path)!r}"
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as e:
        raise CalibrationFileError(f"{source}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise CalibrationFileError(
            f"{source}: not a calibration file: binary (byte {e.object[e.start]:#04x} at "
            f"offset {e.start} is not UTF-8 text); {_FORMAT}"
        ) from None
    except yaml.YAMLError as e:
        raise CalibrationFileError(
            f"{source}: not YAML ({str(e).splitlines()[0]}); {_FORMAT}"
        ) from None
    if not isinstance(doc, dict) or "version" not in doc:
        got = "no 'version' field" if isinstance(doc, dict) else (
            "empty" if doc is None else f"a YAML {type(doc).__name__}, not a mapping")  # fmt: skip
        raise CalibrationFileError(f"{source}: not a calibration file: {got}; {_FORMAT}")
    r = _Reader(source)
    d = r.mapping(
        doc, "", {"version", "robot", "frame", "anchors", "offsets"}, {"camera", "result"}
    )
    if d["version"] != VERSION:
        raise r.fail("version", f"expected {VERSION}, got {d['version']!r}")
    if d["frame"] not in FRAMES:
        raise r.fail("frame", f"expected one of {', '.join(FRAMES)}, got {d['frame']!r}")
    anchors = r.array(d["anchors"], "anchors", (None, 3))
    offsets = r.array(d["offsets"], "offsets", (None, None))
    size = len(offsets)
    if offsets.shape != (size, size) or size <= len(anchors):
        raise r.fail(
            "offsets",
            f"expected a square matrix larger than the {len(anchors)} anchors, got {offsets.shape}",
        )
    if not np.allclose(offsets, offsets.T, atol=1e-9):
        raise r.fail("offsets", "must be symmetric (o_ij = o_ji)")
    intrinsics = pose = None
    if "camera" in d:
        cam = r.mapping(d["camera"], "camera", {"intrinsics", "pose"}, set())
        intrinsics = r.array(cam["intrinsics"], "camera.intrinsics", (3, 3))
        pose = r.array(cam["pose"], "camera.pose", (4, 4))
    try:
        result = _result(r, d["result"], anchors, offsets, d["frame"]) if "result" in d else None
    except (TypeError, ValueError, AttributeError) as e:
        if isinstance(e, CalibrationFileError):
            raise
        raise r.fail("result", f"malformed: {e}") from None
    return CalibrationFile(str(d["robot"]), d["frame"], anchors, offsets, intrinsics, pose, result)
