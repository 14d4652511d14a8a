"""MCAP files read chunk by chunk with mcap's own reader, surviving damage: a file cut
off mid-write, and damaged chunks.

Each chunk is read on its own, so a damaged one (it does not decompress, its records do
not parse, or its CRC disagrees) loses its own messages only, and what it held is
counted as a :class:`LostSpan` (its time span, and its topics and message counts where
the file's message index says).

- A file with its summary: :class:`McapFile` finds every chunk through mcap's chunk
  index and reads the intact ones; a damaged chunk is reported to ``on_damage`` when
  the read reaches its time.
- A file cut off by a crash (no summary, or one too damaged to read): its records are
  walked from the start up to the last complete one, each chunk checked on the way;
  the damaged ones are known at once (``known_lost``).

mcap parses every record; here the records are only framed (opcode and length), so
that a damaged length inside one record cannot carry a read into the next.
"""

from __future__ import annotations

import dataclasses
import heapq
import io
import logging
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, BinaryIO, NamedTuple

from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, Message, MessageIndex, Schema
from mcap.stream_reader import StreamReader, breakup_chunk, get_chunk_data_stream

from tensegrity_gym.model.samples import ns_to_seconds

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Iterator
    from pathlib import Path

    from mcap.records import McapRecord

__all__ = ["MAGIC", "DamagedChunkError", "LostSpan", "McapBag", "McapFile", "Topic"]

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_HEAD = 9  # a record's opcode (1) and content length (8)
_MESSAGE_FIELDS = 22  # channel id, sequence, log time, publish time
_IN_CHUNK = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)
_EXTENSION = 0x80  # opcodes from here on are for user extensions: skipped, not damage


class DamagedChunkError(ValueError):
    """A chunk that cannot be read; the message says what is wrong with it."""


@dataclass(frozen=True)
class LostSpan:
    """The messages of one damaged chunk, which a read skipped.

    ``counts`` (topic -> messages) is what the file's message index says the chunk
    held; it is empty where the file has no message index for it.
    """

    offset: int
    """Byte offset of the damaged chunk record in its ``.mcap`` file."""
    start_ns: int
    """Log time (ns) of the chunk's first message, as its header or index says."""
    end_ns: int
    """Log time (ns) of the chunk's last message."""
    reason: str
    counts: dict[str, int] = field(default_factory=dict)
    file: str = ""
    """The ``.mcap`` file of the chunk."""

    @property
    def topics(self) -> list[str]:
        return sorted(self.counts)

    @property
    def messages(self) -> int | None:
        """Messages lost, where the index says (None if unknown)."""
        return sum(self.counts.values()) if self.counts else None

    @property
    def start(self) -> float:
        """Start of the span (s, log time)."""
        return ns_to_seconds(self.start_ns)

    @property
    def end(self) -> float:
        """End of the span (s, log time)."""
        return ns_to_seconds(self.end_ns)

    def describe(self) -> str:
        """One line: the time span, the topics and count, the fault."""
        what = "topics unknown (no message index)"
        if self.counts:
            what = f"{self.messages} messages on {', '.join(self.topics)}"
        return (
            f"damaged chunk at byte {self.offset}, t={self.start:.9f}..{self.end:.9f} s "
            f"lost: {what} ({self.reason})"
        )

    def as_dict(self) -> dict[str, Any]:
        """The span as JSON-ready values (times in s)."""
        return {
            "start_s": self.start,
            "end_s": self.end,
            "topics": dict(sorted(self.counts.items())),
            "messages": self.messages,
            "offset": self.offset,
            "reason": self.reason,
        }


class Topic(NamedTuple):
    """One channel of a bag: its topic, message type, type hash (where
    ``metadata.yaml`` gives one, else empty) and message count."""

    topic: str
    msgtype: str
    digest: str
    msgcount: int


# ---------------------------------------------------------------------- records


class _ShortReadError(Exception):
    """A read asked for bytes past the end of its record."""


class _Exact(io.BytesIO):
    """Bytes whose reads return all that was asked, or raise :class:`_ShortReadError`."""

    def __init__(self, data: bytes) -> None:
        super().__init__(data)
        self._size = len(data)

    def read(self, n: int | None = -1, /) -> bytes:
        if n is None or n < 0 or self.tell() + n > self._size:
            raise _ShortReadError
        return super().read(n)


def parse_record(data: bytes) -> McapRecord | None:
    """The one MCAP record ``data`` (opcode, length, content) as mcap parses it (None
    for an opcode mcap does not know). Raises DamagedChunkError where it does not parse."""
    records = StreamReader(_Exact(data), skip_magic=True, emit_chunks=True, record_size_limit=None)
    try:
        return next(iter(records.records), None)
    except _ShortReadError:
        raise DamagedChunkError("a field runs past the end of its record") from None
    except Exception as err:  # mcap raises many kinds on damaged bytes
        raise DamagedChunkError(f"a record does not parse: {err!r}") from None


def _frame(raw: bytes) -> None:
    """Raises DamagedChunkError unless ``raw`` (a chunk's records) is whole records of
    the kinds a chunk holds."""
    pos, size = 0, len(raw)
    while pos < size:
        if pos + _HEAD > size:
            raise DamagedChunkError(f"a record is cut off at byte {pos} of the chunk's records")
        op, length = raw[pos], int.from_bytes(raw[pos + 1 : pos + _HEAD], "little")
        if pos + _HEAD + length > size:
            raise DamagedChunkError(f"a record at byte {pos} of the chunk runs past its end")
        if op == Opcode.MESSAGE and length < _MESSAGE_FIELDS:
            raise DamagedChunkError(f"a message record of {length} bytes at byte {pos}")
        if op not in _IN_CHUNK and op < _EXTENSION:
            raise DamagedChunkError(f"record opcode {op:#04x} at byte {pos} cannot be in a chunk")
        pos += _HEAD + length


def chunk_records(chunk: Chunk) -> list[McapRecord]:
    """The schemas, channels and messages of ``chunk``, by mcap's ``breakup_chunk``.

    Raises DamagedChunkError where the chunk does not decompress, its records are not
    whole, its CRC disagrees, or a message's log time falls outside the chunk's span
    (which bytes flipped in a record give).
    """
    try:
        stream, size = get_chunk_data_stream(chunk)
        raw = stream.read(size) if size else b""
    except Exception as err:  # the decompressors raise many kinds on damaged bytes
        raise DamagedChunkError(f"{chunk.compression or 'uncompressed'} data: {err}") from None
    if len(raw) != chunk.uncompressed_size:
        size = chunk.uncompressed_size
        raise DamagedChunkError(f"{len(raw)} bytes of records where the chunk says {size}")
    _frame(raw)
    if chunk.uncompressed_crc and zlib.crc32(raw) != chunk.uncompressed_crc:
        raise DamagedChunkError("the chunk's records do not match its CRC")
    records = breakup_chunk(dataclasses.replace(chunk, compression="", data=raw))
    start, end = chunk.message_start_time, chunk.message_end_time
    for r in records:
        if isinstance(r, Message) and not start <= r.log_time <= end:
            raise DamagedChunkError(
                f"a message logged at {r.log_time} ns, outside the chunk's {start}..{end} ns"
            )
    return records


def _top_records(f: BinaryIO, size: int) -> Iterator[tuple[int, int, bytes]]:
    """(offset, opcode, whole record) of each complete top-level record of the MCAP file
    ``f`` (``size`` bytes) from its start up to its data end."""
    offset = len(MAGIC)
    while offset + _HEAD <= size:
        f.seek(offset)
        head = f.read(_HEAD)
        op, length = head[0], int.from_bytes(head[1:], "little")
        if op in (Opcode.DATA_END, Opcode.FOOTER) or offset + _HEAD + length > size:
            return
        yield offset, op, head + f.read(length)
        offset += _HEAD + length


# ---------------------------------------------------------------------- one file


@dataclass
class _ChunkAt:
    """Where a chunk is and what it holds: channel id -> messages where known (the
    walk), else the channels the index names, with their message index offsets."""

    offset: int
    length: int | None
    start_ns: int
    end_ns: int
    counts: dict[int, int] | None = None
    index: dict[int, int] = field(default_factory=dict)

    def holds(self, channels: Collection[int]) -> bool:
        """Whether the chunk may hold messages on ``channels`` (yes, where it has no index)."""
        if self.counts is not None:
            return any(self.counts.get(c) for c in channels)
        return not self.index or any(c in self.index for c in channels)


class McapFile:
    """One ``.mcap`` file opened for reading chunk by chunk.

    ``on_damage(span)`` hears of each damaged chunk as a read reaches its time; it may
    raise (strict reading), which ends the read. Without it a damaged chunk raises
    DamagedChunkError.

    Args:
        path: the file.
        digests: (topic, message type) -> type hash, from ``metadata.yaml``.
    """

    def __init__(self, path: Path, digests: dict[tuple[str, str], str] | None = None) -> None:
        self.path = path
        self.on_damage: Callable[[LostSpan], None] | None = None
        self.known_lost: list[LostSpan] = []
        """Damaged chunks found on opening (a file read without its index)."""
        self.recovered = False
        """Whether the file was read without its summary (cut off, or its summary damaged)."""
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunks: list[_ChunkAt] = []
        self._loose: list[tuple[int, int, int, bytes]] = []  # messages outside chunks
        self._counts: dict[int, int] = {}
        self.start_ns, self.message_count = 0, 0
        self._file: BinaryIO | None = path.open("rb")
        try:
            self._size = path.stat().st_size
            if self._file.read(len(MAGIC)) != MAGIC:
                raise ValueError(f"{path}: not an MCAP file")
            if not self._read_summary():
                self._walk()
        except BaseException:
            self.close()
            raise
        known = ((c, n) for c, n in self._counts.items() if c in self._channels)
        self.topics = [self._topic(cid, n, digests or {}) for cid, n in known]

    def close(self) -> None:
        f, self._file = self._file, None
        if f is not None:
            f.close()

    def _topic(self, cid: int, count: int, digests: dict[tuple[str, str], str]) -> Topic:
        channel = self._channels[cid]
        schema = self._schemas.get(channel.schema_id)
        msgtype = schema.name if schema is not None else "(no schema)"
        return Topic(channel.topic, msgtype, digests.get((channel.topic, msgtype), ""), count)

    def _read_summary(self) -> bool:
        """Read the file's summary; False where it has none, or none that reads."""
        assert self._file is not None
        self._file.seek(0)
        try:
            summary = make_reader(self._file).get_summary()
        except Exception as err:  # a cut-off or damaged file: mcap raises many kinds
            log.debug("%s: no summary: %r", self.path, err)
            return False
        if summary is None or summary.statistics is None:
            return False
        stats = summary.statistics
        if stats.message_count and not summary.chunk_indexes:
            return False  # messages outside chunks: the walk reads them
        self._schemas, self._channels = summary.schemas, summary.channels
        self._chunks = [self._chunk_at(x) for x in summary.chunk_indexes]
        self._counts = {c: stats.channel_message_counts.get(c, 0) for c in self._channels}
        self.start_ns, self.message_count = stats.message_start_time, stats.message_count
        return True

    @staticmethod
    def _chunk_at(x: ChunkIndex) -> _ChunkAt:
        return _ChunkAt(
            x.chunk_start_offset,
            x.chunk_length,
            x.message_start_time,
            x.message_end_time,
            index=x.message_index_offsets,
        )

    # ------------------------------------------------------------------ walk

    def _walk(self) -> None:
        """Read the records from the start up to the last complete one (no summary)."""
        assert self._file is not None
        self.recovered = True
        damaged: list[tuple[int, int, int, str, dict[int, int]]] = []
        walked = False
        lost: dict[int, int] | None = None  # of the damaged chunk just met
        for offset, op, data in _top_records(self._file, self._size):
            walked = True
            if op == Opcode.MESSAGE_INDEX and lost is not None:
                index = _parse_quietly(data)
                if isinstance(index, MessageIndex):
                    lost[index.channel_id] = lost.get(index.channel_id, 0) + len(index.records)
                continue
            lost = None
            if op == Opcode.CHUNK:
                why = self._walk_chunk(offset, data)
                if why is not None:
                    start, end = (int.from_bytes(data[a : a + 8], "little") for a in (9, 17))
                    lost = {}
                    damaged.append((offset, start, end, why, lost))
            elif op in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                self._add(_parse_quietly(data), offset)
        if not walked:
            raise ValueError(f"{self.path}: not an MCAP file, or cut off before its first record")
        self.known_lost = [
            self._span(offset, start, end, counts, why)
            for offset, start, end, why, counts in damaged
        ]
        times = [c.start_ns for c in self._chunks] + [t for t, *_ in self._loose]
        self.start_ns = min(times, default=0)
        self.message_count = sum(self._counts.values())

    def _walk_chunk(self, offset: int, data: bytes) -> str | None:
        """Check the chunk record ``data`` at ``offset`` and take in what it holds;
        the fault where it is damaged."""
        try:
            chunk = parse_record(data)
            assert isinstance(chunk, Chunk)
            records = chunk_records(chunk)
        except DamagedChunkError as err:
            return str(err)
        counts: dict[int, int] = {}
        for r in records:
            if isinstance(r, Message):
                counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
            else:
                self._add(r, offset)
        for cid, n in counts.items():
            self._counts[cid] = self._counts.get(cid, 0) + n
        start, end = chunk.message_start_time, chunk.message_end_time
        self._chunks.append(_ChunkAt(offset, len(data), start, end, counts))
        return None

    def _add(self, record: McapRecord | None, offset: int) -> None:
        """Take in a schema, a channel, or a message outside chunks, met by the walk."""
        if isinstance(record, Schema):
            self._schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self._channels.setdefault(record.id, record)
            self._counts.setdefault(record.id, 0)
        elif isinstance(record, Message):
            self._loose.append((record.log_time, offset, record.channel_id, record.data))
            self._counts[record.channel_id] = self._counts.get(record.channel_id, 0) + 1

    # ------------------------------------------------------------------ reading

    def _span(
        self, offset: int, start: int, end: int, counts: dict[int, int], why: str
    ) -> LostSpan:
        topics: dict[str, int] = {}
        for cid, n in counts.items():
            channel = self._channels.get(cid)
            name = channel.topic if channel is not None else f"channel {cid}"
            topics[name] = topics.get(name, 0) + n
        return LostSpan(offset, start, end, why, topics, str(self.path))

    def _read_chunk(self, at: _ChunkAt) -> list[McapRecord]:
        """The records of the chunk at ``at`` (DamagedChunkError where it is damaged)."""
        assert self._file is not None
        self._file.seek(at.offset)
        head = self._file.read(_HEAD)
        if len(head) < _HEAD or head[0] != Opcode.CHUNK:
            raise DamagedChunkError("no chunk record where the index says one starts")
        n = int.from_bytes(head[1:], "little")
        if (at.length is not None and n != at.length - _HEAD) or at.offset + _HEAD + n > self._size:
            raise DamagedChunkError(f"the chunk record's length {n} disagrees with the file")
        chunk = parse_record(head + self._file.read(n))
        if not isinstance(chunk, Chunk):
            raise DamagedChunkError("no chunk record where the index says one starts")
        return chunk_records(chunk)

    def _lost_counts(self, at: _ChunkAt) -> dict[int, int]:
        """Channel id -> messages of a damaged chunk, as the file's message index says."""
        if at.counts is not None:
            return at.counts
        assert self._file is not None
        counts = {}
        for cid, offset in at.index.items():
            self._file.seek(offset)
            head = self._file.read(_HEAD)
            n = int.from_bytes(head[1:], "little") if len(head) == _HEAD else -1
            index = _parse_quietly(head + self._file.read(n)) if 0 <= n < self._size else None
            if isinstance(index, MessageIndex):
                counts[cid] = len(index.records)
        return counts

    def _chunk_messages(
        self, at: _ChunkAt, wanted: dict[int, str]
    ) -> Iterator[tuple[int, int, str, bytes]]:
        # The first item holds the merge back until the read reaches this chunk's time.
        yield at.start_ns, 0, "", b""
        try:
            records = self._read_chunk(at)
        except DamagedChunkError as err:
            if self.on_damage is None:
                raise
            counts = self._lost_counts(at)
            self.on_damage(self._span(at.offset, at.start_ns, at.end_ns, counts, str(err)))
            return
        keep = [
            (r.log_time, at.offset, wanted[r.channel_id], r.data)
            for r in records
            if isinstance(r, Message) and r.channel_id in wanted
        ]
        keep.sort(key=lambda m: m[0])
        yield from keep

    def messages(self, topics: Collection[str]) -> Iterator[tuple[str, int, bytes]]:
        """(topic, log time ns, CDR bytes) of every message on ``topics``, in log-time
        order, a damaged chunk skipped and reported."""
        wanted = {cid: c.topic for cid, c in self._channels.items() if c.topic in topics}
        if not wanted:
            return
        loose = sorted((t, o, wanted[c], d) for t, o, c, d in self._loose if c in wanted)
        sources = [self._chunk_messages(x, wanted) for x in self._chunks if x.holds(wanted)]
        for ns, _, topic, raw in heapq.merge(iter(loose), *sources):
            if topic:
                yield topic, ns, raw


def _parse_quietly(data: bytes) -> McapRecord | None:
    """The record ``data`` as mcap parses it, or None where it does not parse."""
    try:
        return parse_record(data)
    except DamagedChunkError:
        return None


# ---------------------------------------------------------------------- a bag


class McapBag:
    """The ``.mcap`` files of one bag, read as one: their topics, and their messages
    merged in log-time order."""

    def __init__(self, files: list[McapFile]) -> None:
        self.files = files
        self.topics = [t for f in files for t in f.topics]
        self.recovered = any(f.recovered for f in files)
        """Whether a file was read without its summary (cut off, or its summary damaged)."""
        self.known_lost = [span for f in files for span in f.known_lost]
        self.message_count = sum(f.message_count for f in files)
        self.start_ns = min((f.start_ns for f in files if f.message_count), default=0)

    def set_on_damage(self, on_damage: Callable[[LostSpan], None]) -> None:
        """Hand every damaged chunk a read meets to ``on_damage`` (see :class:`McapFile`)."""
        for f in self.files:
            f.on_damage = on_damage

    def messages(self, topics: Collection[str]) -> Iterator[tuple[str, int, bytes]]:
        """(topic, log time ns, CDR bytes) of every message on ``topics``, in log-time order."""
        if len(self.files) == 1:
            return self.files[0].messages(topics)
        return heapq.merge(*(f.messages(topics) for f in self.files), key=lambda m: m[1])

    def close(self) -> None:
        for f in self.files:
            f.close()
