"""MCAP storage that survives damage: a file cut off mid-write, and damaged chunks.

rosbags reads an MCAP file as a whole: one chunk that does not decompress, or whose
records do not parse, ends the read. Here each chunk is read on its own, so a damaged
one loses its own messages only, and what it held is counted as a :class:`LostSpan`
(its time span, and its topics and message counts where the file's message index
says).

- A file with its summary (the chunk index): :class:`SalvagingMcap` finds every chunk
  through the index and reads the intact ones; a damaged chunk is reported to
  ``on_damage`` when the read reaches its time.
- A file cut off by a crash (no summary, or a summary too damaged to read): the records
  are walked from the start up to the last complete one, each chunk is checked on the
  way, and rosbags scans a view of the file without the damaged chunks
  (:func:`open_recovered`). Their spans are known at once (``known_lost``).
"""

from __future__ import annotations

import heapq
import logging
import os
import struct
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, BinaryIO, NamedTuple

from rosbags.rosbag2.reader import DirectoryReader, Reader
from rosbags.rosbag2.storage_mcap import McapReader, decompress
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

from tensegrity_gym.model.samples import ns_to_seconds

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Generator, Iterator
    from pathlib import Path

    from rosbags.interfaces import Connection
    from rosbags.rosbag2.storage_mcap import ChunkInfo

__all__ = ["LostSpan", "SalvagingMcap", "mcap_walk", "open_indexed", "open_recovered"]

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = 9  # opcode (1) + length (8)
_FOOTER, _CHUNK, _MESSAGE_INDEX, _DATA_END = 0x02, 0x06, 0x07, 0x0F
_SCHEMA, _CHANNEL, _MESSAGE = 0x03, 0x04, 0x05
_EXTENSION = 0x80  # opcodes from here on are for user extensions: skipped, not damage
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end (ns), uncompressed size, CRC


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


# ---------------------------------------------------------------------- one chunk


def _string(data: bytes, pos: int) -> tuple[str, int]:
    n = int.from_bytes(data[pos : pos + 4], "little")
    if pos + 4 + n > len(data):
        raise DamagedChunkError("the compression name runs past the chunk record")
    return data[pos + 4 : pos + 4 + n].decode(errors="replace"), pos + 4 + n


def chunk_payload(body: bytes) -> tuple[int, int, bytes]:
    """(start ns, end ns, uncompressed records) of a chunk record's content ``body``."""
    if len(body) < _CHUNK_HEAD.size + 12:
        raise DamagedChunkError(f"a chunk record of {len(body)} bytes is too short")
    start, end, size, crc = _CHUNK_HEAD.unpack_from(body)
    compression, pos = _string(body, _CHUNK_HEAD.size)
    n = int.from_bytes(body[pos : pos + 8], "little")
    if pos + 8 + n > len(body):
        raise DamagedChunkError(f"compressed size {n} runs past the chunk record")
    try:
        raw = decompress(body[pos + 8 : pos + 8 + n], compression, size, crc)
    except Exception as err:  # the decompressors raise many kinds on damaged bytes
        raise DamagedChunkError(f"{compression or 'uncompressed'} data: {err}") from None
    return start, end, raw


def chunk_messages(raw: bytes, start: int, end: int) -> list[tuple[int, int, bytes]]:
    """(log time ns, channel id, message bytes) of every message in a chunk's records.

    Raises DamagedChunkError where the records do not parse, or a message's log time falls
    outside the chunk's ``start``..``end`` (ns), which bytes flipped in a record give.
    """
    out = []
    pos, size = 0, len(raw)
    while pos < size:
        if pos + _RECORD_HEAD > size:
            raise DamagedChunkError(f"a record is cut off at byte {pos} of the chunk's records")
        op, length = raw[pos], int.from_bytes(raw[pos + 1 : pos + 9], "little")
        stop = pos + _RECORD_HEAD + length
        if stop > size:
            raise DamagedChunkError(f"a record at byte {pos} of the chunk runs past its end")
        if op == _MESSAGE:
            if length < _MESSAGE_HEAD.size:
                raise DamagedChunkError(f"a message record of {length} bytes at byte {pos}")
            channel, _, logged, _ = _MESSAGE_HEAD.unpack_from(raw, pos + _RECORD_HEAD)
            if not start <= logged <= end:
                raise DamagedChunkError(
                    f"a message logged at {logged} ns, outside the chunk's {start}..{end} ns"
                )
            out.append((logged, channel, raw[pos + _RECORD_HEAD + _MESSAGE_HEAD.size : stop]))
        elif op not in (_SCHEMA, _CHANNEL) and op < _EXTENSION:
            raise DamagedChunkError(f"record opcode {op:#04x} at byte {pos} cannot be in a chunk")
        pos = stop
    return out


def read_chunk(bio: BinaryIO, offset: int, length: int | None, file_size: int) -> bytes:
    """The content of the chunk record at ``offset`` (whose record is ``length`` bytes
    long, where an index says)."""
    bio.seek(offset)
    head = bio.read(_RECORD_HEAD)
    if len(head) < _RECORD_HEAD or head[0] != _CHUNK:
        raise DamagedChunkError("no chunk record where the index says one starts")
    n = int.from_bytes(head[1:], "little")
    if (length is not None and n != length - _RECORD_HEAD) or offset + 9 + n > file_size:
        raise DamagedChunkError(f"the chunk record's length {n} disagrees with the file")
    return bio.read(n)


def check_chunk(body: bytes) -> None:
    """Raises DamagedChunkError unless the chunk record content ``body`` reads."""
    start, end, raw = chunk_payload(body)
    chunk_messages(raw, start, end)


# ---------------------------------------------------------------------- indexed


class SalvagingMcap(McapReader):
    """rosbags' MCAP reader whose indexed read takes each chunk on its own.

    ``on_damage(span)`` hears of each damaged chunk as the read reaches its time; it
    may raise (strict reading), which ends the read.
    """

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.on_damage: Callable[[LostSpan], None] | None = None
        """Hears of each damaged chunk; without it, a damaged chunk raises DamagedChunkError."""
        self.known_lost: list[LostSpan] = []
        """Damaged chunks found on opening (a file read without its index)."""
        self._file_size = path.stat().st_size if path.is_file() else 0

    def _span(
        self, offset: int, start: int, end: int, counts: dict[int, int], why: str
    ) -> LostSpan:
        topics: dict[str, int] = {}
        for cid, n in counts.items():
            channel = self.channels.get(cid)
            name = channel.topic if channel is not None else f"channel {cid}"
            topics[name] = topics.get(name, 0) + n
        return LostSpan(offset, start, end, why, topics, str(self.path))

    def _chunk(
        self, chunk: ChunkInfo, wanted: dict[int, Connection], start: int, stop: int
    ) -> Iterator[tuple[int, int, Connection | None, bytes]]:
        # The first item holds the merge back until the read reaches this chunk's time.
        yield chunk.message_start_time, 0, None, b""
        assert self.bio is not None
        at = chunk.chunk_start_offset
        try:
            body = read_chunk(self.bio, at, chunk.chunk_length, self._file_size)
            first, last, raw = chunk_payload(body)
            records = chunk_messages(raw, first, last)
        except DamagedChunkError as err:
            if self.on_damage is None:
                raise
            counts = chunk.channel_count
            first, last = chunk.message_start_time, chunk.message_end_time
            self.on_damage(self._span(at, first, last, counts, str(err)))
            return
        keep = [(t, at, wanted[c], d) for t, c, d in records if c in wanted and start <= t < stop]
        keep.sort(key=lambda m: m[0])
        yield from keep

    def messages(
        self,
        connections: Collection[Connection],
        start: int | None = None,
        stop: int | None = None,
    ) -> Generator[tuple[Connection, int, bytes], None, None]:
        """rosbags' :meth:`McapReader.messages`, with a damaged chunk skipped and reported."""
        if not self.chunks:  # no index: rosbags scans the records
            yield from super().messages(connections, start, stop)
            return
        wanted = {c.id: c for c in connections}
        lo = -1 if start is None else start
        hi = 2**63 if stop is None else stop
        sources = [
            self._chunk(x, wanted, lo, hi)
            for x in self.chunks
            if lo <= x.message_end_time
            and x.message_start_time < hi
            and any(x.channel_count.get(cid, 0) for cid in wanted)
        ]
        for ns, _, conn, raw in heapq.merge(*sources):
            if conn is not None:
                yield conn, ns, raw


class _SalvagingDirectory(DirectoryReader):
    STORAGE_PLUGINS = MappingProxyType({"mcap": SalvagingMcap, "sqlite3": Sqlite3Reader})


class _SalvagingReader(Reader):
    STORAGE_PLUGINS = MappingProxyType(
        {"dir": _SalvagingDirectory, ".mcap": SalvagingMcap, ".db3": Sqlite3Reader}
    )


def open_indexed(path: Path) -> tuple[Reader, list[SalvagingMcap]]:
    """rosbags' reader of the bag at ``path`` (a folder with ``metadata.yaml``, or a
    file), opened, and its MCAP storages, which read chunk by chunk."""
    reader = _SalvagingReader(path)
    reader.open()
    storage: Any = reader.storage
    storages = storage.storages if isinstance(storage, DirectoryReader) else [storage]
    return reader, [s for s in storages if isinstance(s, SalvagingMcap)]


# ---------------------------------------------------------------------- cut off


class _Damaged(NamedTuple):
    """A damaged chunk met by :func:`mcap_walk`: (record offset, record end offset,
    start and end log time ns, channel id -> messages, fault)."""

    offset: int
    stop: int
    start_ns: int
    end_ns: int
    counts: dict[int, int]
    reason: str


@dataclass
class Walk:
    """The intact part of an MCAP file: the records up to ``end`` (byte offset just past
    the last complete one), less the ``damaged`` chunks among them."""

    end: int
    damaged: list[_Damaged] = field(default_factory=list)


def _damaged_chunk(f: BinaryIO, offset: int, body: bytes, size: int) -> _Damaged | None:
    """The chunk record at ``offset`` with content ``body`` as damage, or None if it reads."""
    try:
        check_chunk(body)
    except DamagedChunkError as err:
        start, end = _CHUNK_HEAD.unpack_from(body)[:2] if len(body) >= 16 else (0, 0)
        stop = offset + _RECORD_HEAD + len(body)
        return _Damaged(offset, stop, start, end, _index_counts(f, stop, size), str(err))
    return None


def _index_counts(f: BinaryIO, offset: int, size: int) -> dict[int, int]:
    """Channel id -> messages, from the message index records that follow a chunk."""
    counts: dict[int, int] = {}
    while offset + _RECORD_HEAD + 6 <= size:
        f.seek(offset)
        head = f.read(_RECORD_HEAD + 6)
        length = int.from_bytes(head[1:9], "little")
        if head[0] != _MESSAGE_INDEX or offset + _RECORD_HEAD + length > size:
            break
        cid = int.from_bytes(head[9:11], "little")
        counts[cid] = counts.get(cid, 0) + int.from_bytes(head[11:15], "little") // 16
        offset += _RECORD_HEAD + length
    return counts


def mcap_walk(path: Path) -> Walk:
    """The top-level records of the MCAP file at ``path`` from its start, each chunk
    checked on the way (end 0: not an MCAP file)."""
    size = path.stat().st_size
    walk = Walk(0)
    with path.open("rb") as f:
        if f.read(8) != MAGIC:
            return walk
        offset = 8
        while offset + _RECORD_HEAD <= size:
            f.seek(offset)
            head = f.read(_RECORD_HEAD)
            op, length = head[0], int.from_bytes(head[1:], "little")
            if op in (_DATA_END, _FOOTER) or offset + _RECORD_HEAD + length > size:
                break
            if op == _CHUNK:
                damage = _damaged_chunk(f, offset, f.read(length), size)
                if damage is not None:
                    walk.damaged.append(damage)
            offset += _RECORD_HEAD + length
        walk.end = offset
    return walk


class _SplicedFile:
    """A read-only file: the byte ranges ``pieces`` ((start, stop) offsets) of ``path``
    one after another, then an MCAP footer with no summary, which makes rosbags scan the
    records instead of reading an index."""

    def __init__(self, path: Path, pieces: list[tuple[int, int]]) -> None:
        self._file: BinaryIO = path.open("rb")
        self._pieces = [(a, b) for a, b in pieces if b > a]
        self._tail = bytes([_FOOTER]) + (20).to_bytes(8, "little") + bytes(20) + MAGIC
        self._size = sum(b - a for a, b in self._pieces) + len(self._tail)
        self._pos = 0

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: self._size}
        self._pos = max(0, base[whence] + offset)
        return self._pos

    def tell(self) -> int:
        return self._pos

    def read(self, n: int = -1) -> bytes:
        stop = self._size if n < 0 else min(self._size, self._pos + n)
        out, at = [], 0  # at: where the piece starts in this view
        for a, b in self._pieces:
            lo, hi = max(self._pos, at), min(stop, at + b - a)
            if lo < hi:
                self._file.seek(a + lo - at)
                out.append(self._file.read(hi - lo))
            at += b - a
        lo = max(self._pos, at)
        out.append(self._tail[lo - at : max(lo, stop) - at])
        self._pos = max(self._pos, stop)
        return b"".join(out)

    def close(self) -> None:
        self._file.close()


class _RecoveredMcap(SalvagingMcap):
    """rosbags' MCAP reader over the intact records of a file that lacks its summary."""

    def __init__(self, path: Path, walk: Walk) -> None:
        super().__init__(path)
        self._file_path = path
        self._walk = walk

    def open(self) -> None:
        cuts = [(d.offset, d.stop) for d in self._walk.damaged]
        starts = [0] + [stop for _, stop in cuts]
        stops = [offset for offset, _ in cuts] + [self._walk.end]
        self.bio = _SplicedFile(self._file_path, list(zip(starts, stops, strict=True)))  # type: ignore[assignment]
        try:
            self._open()
        except BaseException:
            self.close()
            raise
        for d in self._walk.damaged:
            self.known_lost.append(self._span(d.offset, d.start_ns, d.end_ns, d.counts, d.reason))


def open_recovered(path: Path, walk: Walk) -> SalvagingMcap:
    """The file at ``path`` read by scanning its intact records (see :func:`mcap_walk`)."""
    storage = _RecoveredMcap(path, walk)
    storage.open()
    return storage
