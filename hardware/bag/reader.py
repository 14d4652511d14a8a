"""Reading a bag back as control periods of samples, with clear errors and counted skips.

What is read, in log-time order, is cut into control periods at the command messages:
the start period holds everything up to the first command, and period k everything
logged after command k up to and including the time of command k+1. Within a period,
samples are put in a canonical order (time, then sensor, then rod), which is the
simulator's own order, so a recorded run reads back bit for bit.

Documented skips (counted in :attr:`BagReader.skipped`, logged once per kind and
topic; ``strict=True`` raises instead):

- ``unknown_topic``: a topic outside the topic table (``/tf``, ``/rosout``, ...);
- ``duplicate``: a message whose header stamp equals the previous one on its topic;
- ``out_of_order``: a header stamp earlier than the previous one on its topic;
- ``undecodable``: bytes that do not decode, or values that do not fit the robot
  (a wrong count, an unknown name, NaN or inf);
- ``unpaired``: a depth image without its colour image (or the reverse), ground truth
  poses without the state;
- ``trailing_command``: a last command with nothing recorded after it.

Errors (:class:`BagError`): no bag at the path, a bag too damaged to open, a known
topic with an unexpected type, a bag without a robot description (unless one is
given), and, with ``strict``, any skip. A bag whose recording was cut off (no
``metadata.yaml``, no MCAP summary) opens with everything up to its last complete
chunk, and :attr:`BagReader.recovered` says so.
"""

from __future__ import annotations

import logging
import math
import os
import statistics
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.rosbag2.storage_mcap import McapReader

from hardware.bag import messages as m
from hardware.bag.assembler import SampleAssembler
from hardware.bag.codec import MessageError, RobotCodec, run_info_from_text
from hardware.recording import RecordedRun, RecordedStep, hold_command
from tensegrity_gym.model.description import DescriptionError, RobotDescription, loads_robot
from tensegrity_gym.model.samples import (
    ns_to_seconds,
)

if TYPE_CHECKING:
    from collections.abc import Iterator

    from numpy.typing import NDArray
    from rosbags.interfaces import Connection

    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["BagError", "BagPeriod", "BagReader", "find_bags", "read_run"]

log = logging.getLogger(__name__)

_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = 9  # opcode (1) + length (8)
_DATA_END, _FOOTER = 0x0F, 0x02

COMMAND_TOPIC = "/commands/rest_length_targets"
_HEADER_TOPICS = (
    "/robot_description",
    "/tensegrity/run_info",
    "/tensegrity/calibration",
    "/camera/camera_info",
)


class BagError(ValueError):
    """A bag cannot be read as asked; the message names the bag, and the topic and time
    where one is at fault."""


def find_bags(path: str | Path) -> list[Path]:
    """The bags at ``path``: the bag itself, or the bags in a folder of episodes."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such file or folder")
    if p.is_file() or (p / "metadata.yaml").exists() or any(p.glob("*.mcap")):
        return [p]
    bags = sorted(
        q
        for q in p.iterdir()
        if q.is_dir() and ((q / "metadata.yaml").exists() or any(q.glob("*.mcap")))
    )
    if not bags:
        raise BagError(f"{p}: neither a bag (metadata.yaml or .mcap) nor a folder of bags")
    return bags


# ---------------------------------------------------------------------- recovery


def _mcap_data_end(path: Path) -> int:
    """Byte offset just past the last complete top-level MCAP record (0 if none)."""
    size = path.stat().st_size
    with path.open("rb") as f:
        if f.read(8) != _MAGIC:
            return 0
        offset = 8
        while offset + _RECORD_HEAD <= size:
            f.seek(offset)
            head = f.read(_RECORD_HEAD)
            op, length = head[0], int.from_bytes(head[1:], "little")
            if op in (_DATA_END, _FOOTER) or offset + _RECORD_HEAD + length > size:
                break
            offset += _RECORD_HEAD + length
        return offset


class _PrefixWithFooter:
    """A read-only file: the first ``end`` bytes of ``path`` and an MCAP footer with no
    summary, which makes rosbags scan the records instead of reading an index."""

    def __init__(self, path: Path, end: int) -> None:
        self._file: BinaryIO = path.open("rb")
        self._end = end
        self._tail = bytes([_FOOTER]) + (20).to_bytes(8, "little") + bytes(20) + _MAGIC
        self._pos = 0

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: self._end + len(self._tail)}
        self._pos = max(0, base[whence] + offset)
        return self._pos

    def tell(self) -> int:
        return self._pos

    def read(self, n: int = -1) -> bytes:
        total = self._end + len(self._tail)
        stop = total if n < 0 else min(total, self._pos + n)
        out = b""
        if self._pos < self._end:
            self._file.seek(self._pos)
            out = self._file.read(min(stop, self._end) - self._pos)
        if stop > self._end:
            out += self._tail[max(0, self._pos - self._end) : stop - self._end]
        self._pos = stop
        return out

    def close(self) -> None:
        self._file.close()


class _RecoveredMcap(McapReader):
    """rosbags' MCAP reader over the intact part of an MCAP file cut off mid-write."""

    def __init__(self, path: Path, end: int) -> None:
        super().__init__(path)
        self._file_path = path
        self._valid_end = end

    def open(self) -> None:
        self.bio = _PrefixWithFooter(self._file_path, self._valid_end)  # type: ignore[assignment]
        try:
            self._open()
        except BaseException:
            self.close()
            raise


def _open_storage(path: Path) -> tuple[Any, bool]:
    """(an open rosbags reader, whether the bag was recovered from a cut-off write).

    Any failure inside rosbags (it raises many kinds on damaged bytes) becomes BagError.
    """
    mcaps = [path] if path.is_file() else sorted(p for p in path.glob("*.mcap") if p.is_file())
    if (path.is_dir() and (path / "metadata.yaml").exists()) or path.is_file():
        try:
            reader: Any = Reader(path)
            reader.open()
            return reader, False
        except Exception as err:
            if len(mcaps) != 1 or not mcaps[0].name.endswith(".mcap"):
                raise BagError(f"{path}: cannot open the bag: {err}") from None
            log.warning("%s: %s; reading what was written before the damage", path, err)
    if len(mcaps) != 1:
        raise BagError(
            f"{path}: no metadata.yaml and {len(mcaps)} .mcap files; cannot tell which to read"
        )
    try:
        end = _mcap_data_end(mcaps[0])
    except OSError as err:
        raise BagError(f"{mcaps[0]}: cannot read: {err}") from None
    if end <= 8:
        raise BagError(f"{mcaps[0]}: not an MCAP file, or cut off before its first record")
    storage = _RecoveredMcap(mcaps[0], end)
    try:
        storage.open()
    except Exception as err:
        raise BagError(f"{mcaps[0]}: cannot recover the bag: {err}") from None
    return storage, True


# ---------------------------------------------------------------------- periods


@dataclass
class BagPeriod:
    """One control period of a bag: the start period has no command."""

    samples: list[Sample]
    command: NDArray[np.float64] | None
    """The rest-length targets (m), (m,), that drove this period."""
    truth: GroundTruth | None
    """The last ground truth of the period, where the bag has one."""
    estimate: Estimate | None
    """The last estimate recorded in the period."""
    t_end: float
    """Log time (s) of the period's end: the next command, or the last message."""


class BagReader:
    """A bag opened for reading: its robot, calibration and run info, then its periods.

    Args:
        path: a bag folder (``metadata.yaml`` and ``.mcap``), a bare ``.mcap`` file, or
            the folder of a recording that was cut off.
        description: the robot, for a bag that does not carry ``/robot_description``.
        strict: raise :class:`BagError` instead of skipping a bad message.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        description: RobotDescription | None = None,
        strict: bool = False,
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"{self.path}: no such bag")
        self.strict = strict
        self.skipped: Counter[str] = Counter()
        self.unknown_topics: Counter[str] = Counter()
        self._warned: set[tuple[str, str]] = set()
        self._storage, self.recovered = _open_storage(self.path)
        try:
            self._connections: list[Connection] = list(self._storage.connections)
            self._check_types({t: kind for t, (kind, _) in m.FIXED_TOPICS.items()})
            header = self._read_header()
            self.description = self._description(header, description)
            self.codec = RobotCodec(self.description)
            self._check_types(self.codec.topics.types)
            self.run_info = self._run_info(header)
            self.calibration = self._calibration(header)
            self.control_period = self._control_period()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ opening

    def close(self) -> None:
        storage, self._storage = self._storage, None
        if storage is not None:
            try:
                storage.close()
            except (ReaderError, OSError, AssertionError):  # already closed
                pass

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _messages(self, topics: set[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        conns = [c for c in self._connections if topics is None or c.topic in topics]
        if not conns:
            return
        try:
            for conn, ns, raw in self._storage.messages(conns):
                yield conn.topic, ns, raw
        except Exception as err:
            raise BagError(f"{self.path}: the bag is damaged: {err!r}") from None

    def _read_header(self) -> dict[str, bytes]:
        found: dict[str, bytes] = {}
        wanted = set(_HEADER_TOPICS)
        it = self._messages(wanted)
        for topic, _, raw in it:
            found.setdefault(topic, raw)
            if len(found) == len(wanted):
                break
        if hasattr(it, "close"):
            it.close()
        return found

    def _description(
        self, header: dict[str, bytes], given: RobotDescription | None
    ) -> RobotDescription:
        if given is not None:
            return given
        raw = header.get("/robot_description")
        if raw is None:
            raise BagError(
                f"{self.path}: no /robot_description message; pass the robot "
                "(description=..., or --robot on the command line)"
            )
        store = m.typestore()
        try:
            message: Any = store.deserialize_cdr(raw, m.STRING)
            text = str(message.data)
            return loads_robot(text, f"{self.path}:/robot_description")
        except DescriptionError as err:
            raise BagError(str(err)) from None
        except Exception as err:
            raise BagError(f"{self.path}: /robot_description cannot be decoded: {err}") from None

    def _check_types(self, types: dict[str, str]) -> None:
        for conn in self._connections:
            want = types.get(conn.topic)
            if want is not None and conn.msgtype != want:
                raise BagError(
                    f"{self.path}: topic {conn.topic} has type {conn.msgtype}; this robot's "
                    f"topic table gives {want}"
                )
            if want is not None and conn.msgtype.startswith("tensegrity_msgs/") and conn.digest:
                ours = m.typestore().hash_rihs01(conn.msgtype)
                if conn.digest != ours:
                    raise BagError(
                        f"{self.path}: topic {conn.topic}: the bag's {conn.msgtype} is not "
                        "the definition this version reads (its hash differs)"
                    )

    def _run_info(self, header: dict[str, bytes]) -> dict[str, Any]:
        raw = header.get("/tensegrity/run_info")
        if raw is None:
            return {}
        try:
            return run_info_from_text(self.codec.deserialize(raw, m.STRING).data)
        except MessageError as err:
            raise BagError(f"{self.path}: /tensegrity/run_info: {err}") from None

    def _calibration(self, header: dict[str, bytes]) -> SensorCalibration:
        raw = header.get("/tensegrity/calibration")
        if raw is None:
            raise BagError(
                f"{self.path}: no /tensegrity/calibration message (UWB anchors and offsets, "
                "camera pose); an estimator cannot run without it"
            )
        try:
            return self.codec.decode_calibration(raw, header.get("/camera/camera_info"))
        except MessageError as err:
            raise BagError(f"{self.path}: /tensegrity/calibration: {err}") from None

    def _control_period(self) -> float:
        value = self.run_info.get("control_period")
        if value is not None:
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
                or value <= 0
            ):
                raise BagError(
                    f"{self.path}: run info control_period={value!r} is not a positive number"
                )
            return float(value)
        times = []
        for _, ns, _ in self._messages({COMMAND_TOPIC}):
            times.append(ns)
            if len(times) > 100:
                break
        gaps = np.diff(times)
        if not gaps.size or not gaps.max() > 0:
            raise BagError(
                f"{self.path}: no control_period in /tensegrity/run_info and too few "
                f"{COMMAND_TOPIC} messages to infer it"
            )
        return ns_to_seconds(int(statistics.median(gaps[gaps > 0])))

    # ------------------------------------------------------------------ facts

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> message type of every connection in the bag."""
        return {c.topic: c.msgtype for c in self._connections}

    @property
    def has_truth(self) -> bool:
        return "/ground_truth/state" in self.topics

    @property
    def message_count(self) -> int:
        """Messages in the bag, all topics (as its index or a scan counted them)."""
        return sum(c.msgcount for c in self._connections)

    @property
    def command_count(self) -> int | None:
        """How many commands (control periods after the start), where the bag says."""
        counts = [c.msgcount for c in self._connections if c.topic == COMMAND_TOPIC]
        return sum(counts) if counts and all(counts) else None

    # ------------------------------------------------------------------ skips

    def _skip(self, kind: str, topic: str, ns: int | None, why: str = "") -> None:
        at = "" if ns is None else f" at t={ns_to_seconds(ns):.9f} s"
        text = f"{self.path}: {topic}{at}: {kind.replace('_', ' ')}"
        if why:
            text += f": {why}"
        if self.strict:
            raise BagError(text)
        self.skipped[kind] += 1
        if (kind, topic) not in self._warned:
            self._warned.add((kind, topic))
            log.warning("%s (skipped; further ones on this topic are only counted)", text)

    # ------------------------------------------------------------------ periods

    def periods(self) -> Iterator[BagPeriod]:
        """The start period, then one per command, in time order."""
        topics = self.codec.topics
        known = set(topics.types) - set(_HEADER_TOPICS)
        self.skipped.clear()  # counts are of this pass
        self.unknown_topics.clear()
        for conn in self._connections:
            if conn.topic not in topics.types:
                self.unknown_topics[conn.topic] += conn.msgcount
        for topic, count in sorted(self.unknown_topics.items()):
            self._skip("unknown_topic", topic, None, f"not in the topic table ({count} messages)")
            self.skipped["unknown_topic"] += count - 1
        assembler = SampleAssembler(self.codec, self._skip, order="strict")
        command: NDArray[np.float64] | None = None  # of the period being read
        boundary: int | None = None  # log time of the next period's command
        pending: NDArray[np.float64] | None = None
        last_ns = 0
        for topic, ns, raw in self._messages(known):
            if boundary is not None and ns > boundary:
                assert pending is not None
                yield self._finish(assembler, boundary, command)
                command, boundary, pending = pending, None, None
            last_ns = ns
            if topic == COMMAND_TOPIC:
                try:
                    stamp, targets = self.codec.decode_joint_state(raw, "actuated")
                except MessageError as err:
                    self._skip("undecodable", topic, ns, str(err))
                    continue
                if not assembler.accept(topic, stamp):
                    continue
                if boundary is not None:  # two commands at one log time
                    self._skip("duplicate", topic, ns, "a second command at the same time")
                    continue
                boundary, pending = ns, targets
                continue
            assembler.add(topic, raw, at_ns=ns)
        if pending is not None:
            self._skip(
                "trailing_command",
                COMMAND_TOPIC,
                boundary or last_ns,
                "nothing was recorded after it",
            )
        yield self._finish(assembler, last_ns, command)

    def _finish(self, assembler: SampleAssembler, end_ns: int, command: Any) -> BagPeriod:
        out = assembler.take()
        return BagPeriod(out.samples, command, out.truth, out.estimate, ns_to_seconds(end_ns))


def read_run(
    path: str | Path, *, description: RobotDescription | None = None, strict: bool = False
) -> RecordedRun:
    """A whole bag in memory, as the :class:`RecordedRun` an estimator study replays."""
    with BagReader(path, description=description, strict=strict) as reader:
        d = reader.description
        periods = reader.periods()
        start = next(periods)
        run = RecordedRun(
            d,
            reader.calibration,
            RecordedStep(start.samples, hold_command(d), start.truth),
            [],
            reader.control_period,
        )
        for p in periods:
            assert p.command is not None  # only the start period has none
            run.steps.append(RecordedStep(p.samples, p.command, p.truth))
    return run
