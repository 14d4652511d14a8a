"""Reading a bag back as control periods of samples, with clear errors and counted skips.

What is read, in log-time order, is cut into control periods at the command messages:
the start period holds everything up to the first command, and period k everything
logged after command k up to and including the time of command k+1. Within a period,
samples are put in a canonical order (time, then sensor, then rod), which is the
simulator's own order, so a recorded run reads back bit for bit.

Samples carry seconds from the bag's clock origin (:attr:`BagReader.clock_origin_ns`):
its first log time floored to a whole second. A bag recorded from the simulator, whose
clock starts at 0, reads back at the times it was recorded at; a bag stamped in Unix
time hands out small times, which float seconds hold to the nanosecond, so estimates
do not depend on where the robot's clock started. Period ends are sample times too;
skip messages and :class:`LostSpan` keep the bag's own log times.

Documented skips (counted in :attr:`BagReader.skipped`, logged once per kind and
topic; ``strict=True`` raises instead):

- ``unknown_topic``: a topic outside the topic table (``/rosout``, ...). What only
  viewers read (``/tf``, ``/tensegrity/markers``: :data:`messages.VIEW_TOPICS`) is
  passed over without a count;
- ``duplicate``: a message whose header stamp equals the previous one on its topic;
- ``out_of_order``: a header stamp earlier than the previous one on its topic;
- ``undecodable``: bytes that do not decode, or values that do not fit the robot
  (a wrong count, an unknown name, NaN or inf);
- ``unpaired``: a depth image without its colour image (or the reverse), ground truth
  poses without the state;
- ``trailing_command``: a last command with nothing recorded after it;
- ``damaged_chunk``: the messages of an MCAP chunk that does not decompress or parse
  (as many as the file's message index says it held). The rest of the bag is read: the
  chunks before it, and those after it (through the chunk index, or by walking the
  records of a file without one). Each such chunk is a :class:`LostSpan` in
  :attr:`BagReader.lost_spans` and in the ``lost`` of the periods it overlaps, naming
  its topics and its start and end times; ``strict`` raises, naming them.

Errors (:class:`BagError`): no bag at the path, a bag too damaged to open, a known
topic with an unexpected type, a bag without a robot description (unless one is
given), and, with ``strict``, any skip. A bag whose recording was cut off (no
``metadata.yaml``, no MCAP summary) opens with every intact chunk up to its last
complete one, and :attr:`BagReader.recovered` says so.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from hardware.bag import messages as m
from hardware.bag.assembler import SampleAssembler
from hardware.bag.codec import MessageError, RobotCodec, description_yaml, run_info_from_text
from hardware.bag.kinds import fixed_topic_types
from hardware.bag.salvage import LostSpan, McapBag, McapFile, Topic
from hardware.bag.sqlite_bag import Sqlite3Bag, is_sqlite3_bag
from hardware.recording import RecordedRun, RecordedStep, hold_command
from tensegrity_gym.model.description import DescriptionError, RobotDescription, loads_robot
from tensegrity_gym.model.samples import (
    ns_to_seconds,
)

if TYPE_CHECKING:
    from collections.abc import Iterator

    from numpy.typing import NDArray

    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["BagError", "BagPeriod", "BagReader", "LostSpan", "find_bags", "read_run"]

log = logging.getLogger(__name__)

COMMAND_TOPIC = m.COMMAND_TOPIC


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


# ---------------------------------------------------------------------- opening


def _metadata(path: Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` of the bag folder ``path``; empty where it has
    no ``metadata.yaml`` or one that does not read (the ``.mcap`` file says the rest)."""
    file = path / "metadata.yaml"
    if not file.exists():
        return {}
    try:
        doc = yaml.safe_load(file.read_text())
    except (OSError, ValueError, yaml.YAMLError) as err:
        log.warning(
            "%s: unreadable (%s); reading the .mcap alone", file, " ".join(str(err).split())
        )
        return {}
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    return info if isinstance(info, dict) else {}


def _bag_files(path: Path, info: dict[str, Any]) -> tuple[list[Path], dict[tuple[str, str], str]]:
    """The ``.mcap`` files of the bag at ``path``, and (topic, type) -> type hash where
    its ``metadata.yaml`` (``info``: :func:`_metadata`) gives them."""
    if path.is_file():
        return [path], {}
    storage = info.get("storage_identifier", "mcap")
    if isinstance(storage, str) and storage not in ("mcap", "sqlite3"):
        raise BagError(f"{path}: {storage!r} storage; MCAP and sqlite3 bags are read")
    names = info.get("relative_file_paths")
    listed = [path / n for n in names if isinstance(n, str)] if isinstance(names, list) else []
    mcaps = [p for p in listed if p.is_file()]
    missing = [p.name for p in listed if not p.is_file()]
    if mcaps and missing:  # a split bag short of a file would read as a shorter run
        log.warning("%s: metadata.yaml lists %s, missing; reading the rest", path, missing)
    if not mcaps:
        mcaps = sorted(p for p in path.glob("*.mcap") if p.is_file())
        if len(mcaps) != 1:
            raise BagError(
                f"{path}: no metadata.yaml naming its files and {len(mcaps)} .mcap files; "
                "cannot tell which to read"
            )
    digests = {}
    topics = info.get("topics_with_message_count")
    for t in topics if isinstance(topics, list) else []:
        meta = t.get("topic_metadata") if isinstance(t, dict) else None
        if isinstance(meta, dict) and isinstance(meta.get("type_description_hash"), str):
            digests[(str(meta.get("name")), str(meta.get("type")))] = meta["type_description_hash"]
    return mcaps, digests


def _open_storage(path: Path) -> McapBag | Sqlite3Bag:
    """The bag at ``path``: an MCAP bag opened chunk by chunk (see
    :mod:`hardware.bag.salvage`), or a sqlite3 one (:mod:`hardware.bag.sqlite_bag`)."""
    info = _metadata(path) if path.is_dir() else {}
    if is_sqlite3_bag(path, info.get("storage_identifier")):
        try:
            return Sqlite3Bag(path)
        except ValueError as err:
            raise BagError(f"{path}: cannot open the sqlite3 bag: {err}") from None
    files, digests = _bag_files(path, info)
    opened: list[McapFile] = []
    try:
        for f in files:
            opened.append(McapFile(f, digests))
    except (OSError, ValueError) as err:
        for g in opened:
            g.close()
        raise BagError(f"{path}: cannot open the bag: {err}") from None
    bag = McapBag(opened)
    if bag.recovered:
        log.info("%s: no index (a cut-off recording?); read up to its last whole record", path)
    return bag


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
    """Sample time (s from the bag's clock origin) of the period's end: the log time of
    the next command, or of the last message."""
    lost: list[LostSpan] = field(default_factory=list)
    """Damaged chunks whose time overlaps the period: their messages are missing from
    ``samples`` (nothing stands in for them)."""


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
        self._lost: dict[tuple[str, int], LostSpan] = {}
        self._counted: set[tuple[str, int]] = set()  # lost spans in this pass's skips
        self._storage: McapBag | Sqlite3Bag | None = _open_storage(self.path)
        self.recovered = self._storage.recovered
        try:
            self._known_lost = self._storage.known_lost
            self._storage.set_on_damage(self._damaged)
            for span in self._known_lost:
                self._damaged(span)
            self._connections: list[Topic] = list(self._storage.topics)
            self._check_types(fixed_topic_types())
            header = self._read_header()
            self.description = self._description(header, description)
            self.codec = RobotCodec(self.description, self._first_second())
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
            storage.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _messages(self, topics: set[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        names = {c.topic for c in self._connections if topics is None or c.topic in topics}
        if not names or self._storage is None:
            return
        try:
            yield from self._storage.messages(names)
        except BagError:
            raise
        except Exception as err:
            raise BagError(f"{self.path}: the bag is damaged: {err!r}") from None

    def _read_header(self) -> dict[str, bytes]:
        found: dict[str, bytes] = {}
        wanted = set(m.HEADER_TOPICS)
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
        try:
            found = description_yaml(header, m.typestore())
        except MessageError as err:
            raise BagError(f"{self.path}: {err}") from None
        if found is None:
            topics = f"{m.DESCRIPTION_YAML_TOPIC} (or YAML on {m.DESCRIPTION_TOPIC})"
            lost = self._lost_note(m.DESCRIPTION_YAML_TOPIC) or self._lost_note(m.DESCRIPTION_TOPIC)
            raise BagError(
                f"{self.path}: no {topics} message{lost}"
                "; pass the robot (description=..., or --robot on the command line)"
            )
        topic, text = found
        try:
            return loads_robot(text, f"{self.path}:{topic}")
        except DescriptionError as err:
            raise BagError(str(err)) from None
        except Exception as err:  # YAML too deep to parse (RecursionError), ...
            raise BagError(f"{self.path}: {topic} cannot be decoded: {err}") from None

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
        raw = header.get(m.RUN_INFO_TOPIC)
        if raw is None:
            return {}
        try:
            return run_info_from_text(self.codec.deserialize(raw, m.STRING).data)
        except MessageError as err:
            raise BagError(f"{self.path}: {m.RUN_INFO_TOPIC}: {err}") from None

    def _calibration(self, header: dict[str, bytes]) -> SensorCalibration:
        raw = header.get(m.CALIBRATION_TOPIC)
        if raw is None:
            raise BagError(
                f"{self.path}: no {m.CALIBRATION_TOPIC} message (UWB anchors and offsets, "
                "camera pose); an estimator cannot run without it"
                f"{self._lost_note(m.CALIBRATION_TOPIC)}"
            )
        try:
            return self.codec.decode_calibration(raw, header.get(m.CAMERA_INFO_TOPIC))
        except MessageError as err:
            raise BagError(f"{self.path}: {m.CALIBRATION_TOPIC}: {err}") from None

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

    def _first_second(self) -> int:
        """The bag's first log time (ns, as its index or a scan says), floored to a
        whole second; 0 for a bag without messages."""
        if self._storage is None or not self._storage.message_count:
            return 0
        return self._storage.start_ns // 1_000_000_000 * 1_000_000_000

    # ------------------------------------------------------------------ facts

    @property
    def clock_origin_ns(self) -> int:
        """The robot-clock ns (log time) of sample time 0: the first log time floored to
        a whole second (see the module docstring)."""
        return self.codec.origin_ns

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> message type of every connection in the bag."""
        return {c.topic: c.msgtype for c in self._connections}

    @property
    def has_truth(self) -> bool:
        return m.TRUTH_STATE_TOPIC in self.topics

    @property
    def message_count(self) -> int:
        """Messages in the bag, all topics (as its index or a scan counted them)."""
        return sum(c.msgcount for c in self._connections)

    @property
    def command_count(self) -> int | None:
        """How many commands (control periods after the start), where the bag says."""
        counts = [c.msgcount for c in self._connections if c.topic == COMMAND_TOPIC]
        return sum(counts) if counts and all(counts) else None

    def require_commands(self, use: str) -> None:
        """Raise :class:`BagError` naming the command topic if the bag has none of its
        messages: ``use`` (a replay, a fit) needs the run cut into control periods, and
        without commands all of it would be one start period."""
        if not any(c.topic == COMMAND_TOPIC and c.msgcount for c in self._connections):
            raise BagError(
                f"{self.path}: no {COMMAND_TOPIC} messages; {use} needs the commands the "
                "robot was sent, one a control period"
            )

    @property
    def lost_spans(self) -> list[LostSpan]:
        """The damaged chunks met so far, in time order: their time spans, and their
        topics and message counts where the file's index says. An indexed bag finds a
        damaged chunk as a read reaches it; a recovered one on opening."""
        return sorted(self._lost.values(), key=lambda s: (s.start_ns, s.offset))

    def _damaged(self, span: LostSpan) -> None:
        """A damaged chunk: raise (strict), or keep its span, warn once, and count its
        messages as ``skipped["damaged_chunk"]`` once per pass."""
        text = f"{self.path}: {span.describe()}"
        if self.strict:
            raise BagError(text)
        key = (span.file, span.offset)
        if key not in self._lost:
            self._lost[key] = span
            log.warning("%s; reading on past it", text)
        if key not in self._counted:
            self._counted.add(key)
            self.skipped["damaged_chunk"] += span.messages or 0

    def _lost_note(self, topic: str) -> str:
        """Where a missing ``topic`` went: a damaged chunk that held it, or may have."""
        for span in self.lost_spans:
            if topic in span.counts:
                return f" (it was in the {span.describe()})"
        for span in self.lost_spans:
            if not span.counts or any(t.startswith("channel ") for t in span.counts):
                return f" (it may have been in the {span.describe()})"
        return ""

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
        known = set(topics.types) - set(m.HEADER_TOPICS) - m.VIEW_TOPICS
        self.skipped.clear()  # counts are of this pass
        self.unknown_topics.clear()
        self._counted.clear()
        for span in self._known_lost:
            self._damaged(span)
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
        last_ns, start_ns = 0, -1  # start_ns: log time of this period's command
        for topic, ns, raw in self._messages(known):
            if boundary is not None and ns > boundary:
                assert pending is not None
                yield self._finish(assembler, (start_ns, boundary), command)
                start_ns = boundary
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
        yield self._finish(assembler, (start_ns, last_ns), command, last=True)

    def _finish(
        self, assembler: SampleAssembler, span: tuple[int, int], command: Any, last: bool = False
    ) -> BagPeriod:
        """The period from log time ``span[0]`` to ``span[1]`` (ns); the last one also
        takes the damaged chunks after its last message."""
        out = assembler.take()
        start, end = span
        lost = [s for s in self.lost_spans if s.end_ns > start and (last or s.start_ns <= end)]
        return BagPeriod(
            out.samples, command, out.truth, out.estimate, self.codec.seconds(end), lost
        )


def read_run(
    path: str | Path, *, description: RobotDescription | None = None, strict: bool = False
) -> RecordedRun:
    """A whole bag in memory, as the :class:`RecordedRun` an estimator study replays."""
    with BagReader(path, description=description, strict=strict) as reader:
        reader.require_commands("reading it as a run")
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
