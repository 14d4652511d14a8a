"""Damaged and hostile bags against the contract of hardware/bag/reader.py's docstring.

Whatever a bag holds, reading it (opening it and iterating every period) ends in one of
two ways: a :class:`BagError` whose message names the bag (and the topic and time where
one is at fault), or a documented skip counted in ``BagReader.skipped``. A recording
cut off by a crash opens with everything up to its last complete chunk, bit for bit.

"""

from __future__ import annotations

import dataclasses
import math
import shutil
import signal
import subprocess
import sys
import time
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from hardware.bag import BagError, BagReader, ReplayBackend, read_run
from hardware.bag import messages as m
from hardware.bag.codec import RobotCodec
from hardware.bag.reader import COMMAND_TOPIC
from hardware.bag.writer import BagWriter
from hardware.recording import BagSink, MemorySink, RecordingBackend
from tensegrity_gym.model.description import load_robot
from tensegrity_gym.model.samples import (
    EncoderSample,
    ImuSample,
    RgbdFrame,
    UwbRangeSample,
    ns_to_seconds,
)
from tensegrity_gym.sim.backend import SimBackend

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator, Sequence

    from numpy.typing import NDArray

    from hardware.bag import BagPeriod
    from hardware.recording import RecordedRun, RecordedStep
    from tensegrity_gym.model.samples import Sample

ROOT = Path(__file__).resolve().parents[2]
ROBOT = "three_bar"
STEPS = 6  # control periods of the module's recorded run
FLUSH = 0.1  # s of recorded time between chunks of that run

Message = tuple[str, str, int, bytes]
"""(topic, message type, log time ns, CDR bytes)."""


# ---------------------------------------------------------------------- recording


def record(
    folder: str | Path,
    steps: int,
    *,
    flush_period: float = FLUSH,
    seed: int = 0,
    pause: float = 0.0,
) -> None:
    """A simulated run of random commands to ``folder/episode_000``.

    Also the body of the recording subprocess that the SIGKILL test kills.
    """
    d = load_robot(ROBOT)
    # Stamped from 0, not the wall clock: the tests name log times as sample times.
    sink = BagSink(folder, {"note": "test"}, flush_period=flush_period, wall_clock=False)
    backend = RecordingBackend(SimBackend(d), sink)
    rng = np.random.default_rng(seed)
    backend.reset(rng)
    lo, hi, _ = d.motor_limits
    for _ in range(steps):
        backend.step(rng.uniform(lo, hi))
        if pause:
            time.sleep(pause)
    backend.close()


def reference_run(steps: int, seed: int = 0) -> RecordedRun:
    """The run :func:`record` makes, kept in memory instead of a bag."""
    d = load_robot(ROBOT)
    memory = MemorySink()
    backend = RecordingBackend(SimBackend(d), memory)
    rng = np.random.default_rng(seed)
    backend.reset(rng)
    lo, hi, _ = d.motor_limits
    for _ in range(steps):
        backend.step(rng.uniform(lo, hi))
    backend.close()
    return memory.run


@dataclasses.dataclass(frozen=True)
class Intact:
    bag: Path
    mcap: bytes
    periods: list[BagPeriod]


@pytest.fixture(scope="module")
def intact(tmp_path_factory: pytest.TempPathFactory) -> Intact:
    """One short recorded run (compressed chunks) and its periods, read once."""
    folder = tmp_path_factory.mktemp("intact")
    record(folder, STEPS)
    bag = folder / "episode_000"
    with BagReader(bag) as reader:
        periods = list(reader.periods())
        assert not reader.skipped and not reader.recovered
    assert len(periods) == STEPS + 1
    return Intact(bag, (bag / "episode_000.mcap").read_bytes(), periods)


def _write_small_bag(path: Path, *, compress: bool, steps: int = 3) -> Path:
    """A few periods written with :class:`BagWriter` directly (fast to read many times)."""
    d = load_robot(ROBOT)
    sim = SimBackend(d)
    result = sim.reset(np.random.default_rng(1))
    hold = d.rest_lengths[d.actuated]
    with BagWriter(
        path, d, sim.calibration, {"control_period": 0.1}, compress=compress, flush_period=0.2
    ) as writer:
        writer.write_samples(result.samples)
        for _ in range(steps):
            writer.write_command(max(s.t for s in result.samples), hold)
            result = sim.step(hold)
            writer.write_samples(result.samples)
            truth = sim.ground_truth()
            assert truth is not None
            writer.write_truth(truth)
    return path


@pytest.fixture(scope="module")
def small_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[bool, Path]:
    """compress -> a small bag folder."""
    bags = {}
    for compress in (False, True):
        folder = tmp_path_factory.mktemp("zstd" if compress else "plain")
        bags[compress] = _write_small_bag(folder / "episode_000", compress=compress)
    return bags


# ---------------------------------------------------------------------- helpers


def _read(path: Path, **kwargs: Any) -> tuple[BagReader, list[BagPeriod]]:
    """A bag opened and read to its end (the reader is closed; its counts stay)."""
    with BagReader(path, **kwargs) as reader:
        periods = list(reader.periods())
    return reader, periods


def _problem(path: Path, **kwargs: Any) -> str | None:
    """None if reading ``path`` to its end succeeds or gives a BagError naming the bag;
    otherwise what went wrong."""
    try:
        _read(path, **kwargs)
    except BagError as err:
        if path.name not in str(err):
            return f"BagError without the bag's name: {err}"
    except Exception as err:  # the contract: nothing else comes out
        return f"{type(err).__name__}: {err}"
    return None


def _same_values(a: Any, b: Any, where: str) -> None:
    assert type(a) is type(b), where
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f"{where}.{f.name}"
            assert np.array_equal(x, y, equal_nan=True), f"{where}.{f.name}"
        else:
            assert x == y, f"{where}.{f.name}"


def _same_command(a: NDArray[np.float64] | None, b: NDArray[np.float64] | None) -> bool:
    return a is not None and b is not None and np.array_equal(a, b)


def _same_samples(a: Sequence[Sample], b: Sequence[Sample], where: str) -> None:
    assert len(a) == len(b), f"{where}: {len(a)} samples, expected {len(b)}"
    for k, (x, y) in enumerate(zip(a, b, strict=True)):
        _same_values(x, y, f"{where} sample {k} ({type(y).__name__})")


def _same_period(a: BagPeriod, b: BagPeriod, where: str) -> None:
    _same_samples(a.samples, b.samples, where)
    assert (a.command is None) == (b.command is None), where
    if b.command is not None:
        assert _same_command(a.command, b.command), f"{where} command"
    assert (a.truth is None) == (b.truth is None), f"{where} truth"
    if b.truth is not None:
        _same_values(a.truth, b.truth, f"{where} truth")
    assert a.t_end == b.t_end, f"{where} t_end"


def _same_periods(got: Sequence[BagPeriod], want: Sequence[BagPeriod], first: int = 0) -> None:
    """Period by period, as many of each; ``first`` numbers the first in messages."""
    for k, (a, b) in enumerate(zip(got, want, strict=True)):
        _same_period(a, b, f"period {k + first}")


def _edit_every(topic: str, edit: Callable[[Any], None]) -> Callable[..., Iterator[Message]]:
    """A rewrite that decodes every message of ``topic``, edits it, and encodes it."""

    def transform(t: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        if t == topic:
            store = m.typestore()
            msg = store.deserialize_cdr(raw, msgtype)
            edit(msg)
            raw = bytes(store.serialize_cdr(msg, msgtype))
        yield t, msgtype, ns, raw

    return transform


def _same_as_step(a: BagPeriod, b: RecordedStep, where: str, *, partial: bool = False) -> None:
    """A period read back against the in-memory step; ``partial``: a cut-off last period,
    whose samples are a prefix of the step's."""
    if partial:
        assert len(a.samples) <= len(b.samples), where
        _same_samples(a.samples, b.samples[: len(a.samples)], where)
        return
    _same_samples(a.samples, b.samples, where)
    assert (b.truth is None) == (a.truth is None), f"{where} truth"
    if b.truth is not None:
        _same_values(a.truth, b.truth, f"{where} truth")


def _assert_prefix(got: list[BagPeriod], full: list[BagPeriod], where: str) -> None:
    """Every period but the last equals the intact one; the last holds a prefix of its
    samples (in the canonical order the reader sorts them into)."""
    assert 1 <= len(got) <= len(full), where
    for k, (a, b) in enumerate(zip(got[:-1], full, strict=False)):
        _same_period(a, b, f"{where} period {k}")
    last, model = got[-1], full[len(got) - 1]
    assert len(last.samples) <= len(model.samples), where
    _same_samples(last.samples, model.samples[: len(last.samples)], f"{where} last period")
    if model.command is not None:
        assert _same_command(last.command, model.command), f"{where} last command"


def _without(periods: list[BagPeriod], drop: Callable[[Sample], bool]) -> list[BagPeriod]:
    """``periods`` with the samples ``drop`` selects taken out (what a skip leaves)."""
    out = []
    for p in periods:
        kept = [s for s in p.samples if not drop(s)]
        out.append(dataclasses.replace(p, samples=kept))
    assert sum(map(len, (p.samples for p in out))) < sum(len(p.samples) for p in periods)
    return out


def _rewrite(src: Path, dst: Path, transform: Callable[[str, str, int, bytes], Any]) -> Path:
    """``src`` copied message by message through ``transform`` with rosbags alone
    (uncompressed): the way a foreign tool or a lab writes a bag."""
    store = m.typestore()
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as out:
        conns: dict[tuple[str, str], Any] = {}
        for conn, ns, raw in reader.messages():
            for topic, msgtype, t, data in transform(conn.topic, conn.msgtype, ns, bytes(raw)):
                key = (topic, msgtype)
                if key not in conns:
                    conns[key] = out.add_connection(topic, msgtype, typestore=store)
                out.write(conns[key], t, data)
    return dst


def _keep(topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
    yield topic, msgtype, ns, raw


def _stamp(raw: bytes) -> int:
    """The header stamp (ns) of a message that starts with a std_msgs/Header."""
    sec = int.from_bytes(raw[4:8], "little", signed=True)
    return m.stamp_ns(sec, int.from_bytes(raw[8:12], "little"))


class EditNth:
    """A transform that hands the ``n``-th message on ``topic`` (1-based) to ``edit``,
    which changes the message in place, and records that message's header stamp."""

    def __init__(self, topic: str, n: int, edit: Callable[[Any], None]) -> None:
        self.topic, self.n, self.edit = topic, n, edit
        self.seen = 0
        self.stamp: int | None = None

    def __call__(self, topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        if topic == self.topic:
            self.seen += 1
            if self.seen == self.n:
                store = m.typestore()
                msg = store.deserialize_cdr(raw, msgtype)
                self.edit(msg)
                raw = bytes(store.serialize_cdr(msg, msgtype))
                self.stamp = _stamp(raw)
        yield topic, msgtype, ns, raw


class ReplaceNth:
    """A transform that replaces the bytes of the ``n``-th message on ``topic``."""

    def __init__(self, topic: str, n: int, replace: Callable[[bytes], bytes]) -> None:
        self.topic, self.n, self.replace = topic, n, replace
        self.seen = 0
        self.stamp: int | None = None

    def __call__(self, topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        if topic == self.topic:
            self.seen += 1
            if self.seen == self.n:
                self.stamp = _stamp(raw)
                raw = self.replace(raw)
        yield topic, msgtype, ns, raw


def _at(stamp: int | None, kind: type, **attrs: Any) -> Callable[[Sample], bool]:
    assert stamp is not None
    t = ns_to_seconds(stamp)
    return lambda s: (
        type(s) is kind and s.t == t and all(getattr(s, k) == v for k, v in attrs.items())
    )


def _mcap_records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, content length) of each top-level MCAP record, up to the footer."""
    out, offset = [], 8
    while offset + 9 <= len(data):
        op, length = data[offset], int.from_bytes(data[offset + 1 : offset + 9], "little")
        out.append((offset, op, length))
        if op == 0x02:
            break
        offset += 9 + length
    return out


def _chunks(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, end offset, message_end_time ns) of each chunk record."""
    return [
        (o, o + 9 + n, int.from_bytes(data[o + 17 : o + 25], "little"))
        for o, op, n in _mcap_records(data)
        if op == 0x06
    ]


def _chunk_records(data: bytes, chunk: int) -> tuple[int, int]:
    """(offset, length) of the records inside the chunk record at ``chunk``."""
    p = chunk + 9 + 28
    p += 4 + int.from_bytes(data[p : p + 4], "little")  # the compression's name
    return p + 8, int.from_bytes(data[p : p + 8], "little")


def _bare_bag(
    tmp: Path, mcap: bytes, *, metadata: Path | None = None, name: str = "episode_000"
) -> Path:
    """A bag folder ``tmp`` holding ``mcap`` as ``<name>.mcap``, and ``metadata`` (the
    original bag's metadata.yaml, which names that file) if given."""
    tmp.mkdir()
    (tmp / f"{name}.mcap").write_bytes(mcap)
    if metadata is not None:
        shutil.copy(metadata, tmp / "metadata.yaml")
    return tmp


# ---------------------------------------------------------------------- baseline


def test_rewriting_with_rosbags_alone_changes_nothing(intact: Intact, tmp_path: Path) -> None:
    """The rewrite helper every hostile bag below is made with is faithful."""
    bag = _rewrite(intact.bag, tmp_path / "copy", _keep)
    reader, periods = _read(bag)
    assert not reader.skipped and not reader.unknown_topics and not reader.recovered
    assert len(periods) == len(intact.periods)
    _same_periods(periods, intact.periods)


# ---------------------------------------------------------------------- cut-off files


@pytest.mark.parametrize("metadata", [False, True], ids=["no_metadata", "stale_metadata"])
def test_truncated_bag_opens_with_every_complete_chunk_or_gives_bag_error(
    intact: Intact, tmp_path: Path, metadata: bool
) -> None:
    data = intact.mcap
    chunks = _chunks(data)
    assert len(chunks) >= 4, "the run should span several chunks"
    first_end = chunks[0][1]
    cuts = {int(c) for c in np.linspace(0, len(data) - 1, 40)}
    cuts |= {1, 8, 9, 30, first_end - 1, first_end, first_end + 1, chunks[1][1], len(data) - 1}
    if metadata:  # the magic alone, beside metadata.yaml: a bug, see the test after next
        cuts.discard(8)
    counts = []
    for cut in sorted(cuts):
        bag = _bare_bag(
            tmp_path / f"cut_{cut}",
            data[:cut],
            metadata=intact.bag / "metadata.yaml" if metadata else None,
        )
        complete = [end_time for _, end, end_time in chunks if end <= cut]
        if not complete:  # not even the chunk with the description and calibration
            with pytest.raises(BagError, match=f"cut_{cut}"):
                _read(bag)
            continue
        reader, periods = _read(bag)
        assert reader.recovered, cut
        assert not set(reader.skipped) - {"trailing_command"}, (cut, reader.skipped)
        _assert_prefix(periods, intact.periods, f"cut at {cut}")
        # everything up to the last complete chunk, and nothing after it
        assert periods[-1].t_end == ns_to_seconds(max(complete)), cut
        counts.append(len(periods))
    assert counts == sorted(counts), "a longer file never recovers fewer periods"
    assert counts[-1] == len(intact.periods)
    assert len(counts) >= 30


def test_sigkilled_recording_opens_as_a_bit_for_bit_prefix(tmp_path: Path) -> None:
    folder = tmp_path / "killed"
    code = (
        "import sys; from tests.hardware.test_bag_robustness import record; "
        "record(sys.argv[1], 100_000, flush_period=0.2, pause=0.02)"
    )
    mcap = folder / "episode_000" / "episode_000.mcap"
    log = (tmp_path / "recorder.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(folder)], cwd=ROOT, stdout=log, stderr=log
    )
    start = time.monotonic()
    try:
        while True:
            assert proc.poll() is None, (tmp_path / "recorder.log").read_text()[-2000:]
            elapsed = time.monotonic() - start
            if elapsed > 3.0 and mcap.exists() and mcap.stat().st_size > 150_000:
                break
            assert elapsed < 60.0, "the recorder wrote no 150 kB bag in 60 s"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
        log.close()
    assert not (folder / "episode_000" / "metadata.yaml").exists()
    reader, periods = _read(folder / "episode_000")
    assert reader.recovered
    assert len(periods) >= 10
    assert not set(reader.skipped) - {"trailing_command"}, reader.skipped
    run = reference_run(len(periods) - 1)
    steps = [run.start, *run.steps]
    for k, (period, step) in enumerate(zip(periods, steps, strict=True)):
        last = k == len(periods) - 1
        _same_as_step(period, step, f"period {k}", partial=last)
        if k:
            assert _same_command(period.command, step.command), f"period {k} command"


@pytest.mark.parametrize("where", ["bare_file", "folder_with_metadata"])
def test_an_mcap_of_nothing_but_its_magic_gives_bag_error(
    intact: Intact, tmp_path: Path, where: str
) -> None:
    if where == "bare_file":
        path = tmp_path / "magic.mcap"
        path.write_bytes(intact.mcap[:8])
    else:
        path = _bare_bag(tmp_path / "magic", intact.mcap[:8], metadata=intact.bag / "metadata.yaml")
    with pytest.raises(BagError, match="magic"):
        _read(path)


# ---------------------------------------------------------------------- damaged bytes


def _overwrite_outcomes(
    bag: Path, tmp: Path, *, metadata: bool, trials: int, seed: int
) -> list[str]:
    """Bytes overwritten at random places, ``trials`` times: what went wrong."""
    data = (bag / f"{bag.name}.mcap").read_bytes()
    rng = np.random.default_rng(seed)
    bad = []
    for trial in range(trials):
        damaged = bytearray(data)
        where = rng.integers(8, len(data), size=int(rng.integers(1, 13)))
        for pos in where:
            damaged[pos] = int(rng.integers(0, 256))
        copy = _bare_bag(
            tmp / f"trial_{trial}",
            bytes(damaged),
            metadata=bag / "metadata.yaml" if metadata else None,
        )
        problem = _problem(copy)
        if problem is not None:
            bad.append(f"bytes at {sorted(where.tolist())}: {problem}")
    return bad


@pytest.mark.parametrize("metadata", [False, True], ids=["no_metadata", "metadata"])
@pytest.mark.parametrize("compress", [False, True], ids=["plain", "zstd"])
def test_overwritten_bytes_give_bag_error_or_skips(
    small_bags: dict[bool, Path], tmp_path: Path, compress: bool, metadata: bool
) -> None:
    bad = _overwrite_outcomes(
        small_bags[compress], tmp_path, metadata=metadata, trials=30, seed=int(compress)
    )
    assert not bad, "\n".join(bad)


def _damage_chunk(data: bytes, case: str) -> bytes:
    """One precise structural fault in the second chunk of an MCAP file."""
    out = bytearray(data)
    chunk = _chunks(data)[1][0]
    start, length = _chunk_records(data, chunk)
    if case == "zstd_frame_magic":  # the chunk's compressed payload is not zstd
        out[start : start + 4] = b"\xff\xff\xff\xff"
    else:  # an uncompressed chunk: the first message record's length field
        q = start
        while out[q] != 0x05:
            q += 9 + int.from_bytes(out[q + 1 : q + 9], "little")
        size = 2**63 if case == "message_length_huge" else 10
        out[q + 1 : q + 9] = size.to_bytes(8, "little")
    assert start + length <= len(out)
    return bytes(out)


@pytest.mark.parametrize(
    ("case", "metadata"),
    [
        ("zstd_frame_magic", False),
        ("zstd_frame_magic", True),
        ("message_length_huge", False),
        ("message_length_huge", True),
        ("message_length_short", False),
        ("message_length_short", True),
    ],
)
def test_damaged_chunk_is_skipped_and_strict_names_it(
    small_bags: dict[bool, Path], tmp_path: Path, case: str, metadata: bool
) -> None:
    """The second (last) chunk is damaged: the first reads, the second is a lost span;
    ``strict`` refuses the bag, naming the chunk's topics and time span."""
    bag = small_bags[case.startswith("zstd")]
    data = (bag / f"{bag.name}.mcap").read_bytes()
    damaged = _damage_chunk(data, case)
    copy = _bare_bag(
        tmp_path / "damaged", damaged, metadata=bag / "metadata.yaml" if metadata else None
    )
    _, intact = _read(bag)
    reader, periods = _read(copy)
    [span] = reader.lost_spans
    end_ns = _chunks(data)[1][2]
    assert span.end_ns == end_ns and span.start_ns >= _chunks(data)[0][2]
    assert COMMAND_TOPIC in span.topics and reader.skipped == {"damaged_chunk": span.messages}
    kept = [p for p in intact if p.t_end < span.start]
    assert kept and len(periods) < len(intact)
    _same_periods(periods[: len(kept)], kept)
    assert periods[-1].lost == [span]
    reason = {"zstd_frame_magic": "zstd", "message_length_huge": "runs past"}
    with pytest.raises(BagError, match=reason.get(case, "message record of 10 bytes")) as err:
        _read(copy, strict=True)
    text = str(err.value)
    assert "damaged chunk" in text and COMMAND_TOPIC in text and "/red/imu/data_raw" in text
    assert f"..{ns_to_seconds(end_ns):.9f} s" in text


# ---------------------------------------------------------------------- not bags


@pytest.mark.parametrize(
    "case",
    [
        "missing",
        "empty.mcap",
        "text.mcap",
        "junk.db3",
        "empty_folder",
        "folder_with_a_text_file",
        "two_mcaps",
        "metadata_without_mcap",
        "folder_of_episodes",
        pytest.param("empty.txt"),
        pytest.param("folder_named_mcap"),
    ],
)
def test_what_is_not_a_bag_gives_bag_error(intact: Intact, tmp_path: Path, case: str) -> None:
    path = tmp_path / case
    if case.endswith((".mcap", ".db3", ".txt")):
        path.write_bytes(
            {"text": b"hello, world\n" * 50, "junk": b"\x00\x01" * 300}.get(case.split(".")[0], b"")
        )
    elif case == "empty_folder":
        path.mkdir()
    elif case == "folder_with_a_text_file":
        path.mkdir()
        (path / "notes.txt").write_text("not a bag")
    elif case == "two_mcaps":
        path.mkdir()
        for name in ("a.mcap", "b.mcap"):
            shutil.copy(intact.bag / "episode_000.mcap", path / name)
    elif case == "metadata_without_mcap":
        path.mkdir()
        shutil.copy(intact.bag / "metadata.yaml", path)
    elif case == "folder_of_episodes":
        path.mkdir()
        shutil.copytree(intact.bag, path / "episode_000")
    elif case == "folder_named_mcap":
        path.mkdir()
        (path / "x.mcap").mkdir()
    with pytest.raises(BagError, match=case):
        _read(path)


@pytest.mark.parametrize(
    "text", ["", ": : [[", "42\n", "rosbag2_bagfile_information: 5\n", "- a\n- b\n"]
)
def test_garbage_metadata_beside_an_intact_mcap_reads_every_period(
    intact: Intact, tmp_path: Path, text: str
) -> None:
    bag = _bare_bag(tmp_path / "bag", intact.mcap)
    (bag / "metadata.yaml").write_text(text)
    _, periods = _read(bag)
    assert len(periods) == len(intact.periods)
    _same_periods(periods, intact.periods)


def test_a_bare_mcap_file_reads_like_its_folder(intact: Intact) -> None:
    reader, periods = _read(intact.bag / "episode_000.mcap")
    assert not reader.recovered and not reader.skipped
    _same_periods(periods, intact.periods)


# ---------------------------------------------------------------------- topics and types


def _tf_after_imu(topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
    """``/odom_tf`` (no topic of ours: /tf is one, passed over uncounted) after each IMU
    message of the red rod."""
    yield topic, msgtype, ns, raw
    if topic == "/red/imu/data_raw":
        store = m.typestore()
        tf = store.types["tf2_msgs/msg/TFMessage"](transforms=[])
        raw_tf = bytes(store.serialize_cdr(tf, tf.__msgtype__))
        yield "/odom_tf", "tf2_msgs/msg/TFMessage", ns, raw_tf


def test_a_topic_outside_the_table_is_skipped_and_counted(intact: Intact, tmp_path: Path) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", _tf_after_imu)
    reader, periods = _read(bag)
    n_imu = sum(isinstance(s, ImuSample) and s.rod == 0 for p in periods for s in p.samples)
    assert reader.unknown_topics == {"/odom_tf": n_imu}
    assert reader.skipped == {"unknown_topic": n_imu}
    _same_periods(periods, intact.periods)


def test_strict_refuses_a_topic_outside_the_table(intact: Intact, tmp_path: Path) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", _tf_after_imu)
    with pytest.raises(BagError, match="/odom_tf"):
        _read(bag, strict=True)


def _string(types: Any) -> Any:
    return types["std_msgs/msg/String"](data="x")


def _int32(types: Any) -> Any:
    return types["std_msgs/msg/Int32"](data=5)


def _temperature(types: Any) -> Any:
    stamp = types["builtin_interfaces/msg/Time"](sec=1, nanosec=0)
    header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="red")
    return types["sensor_msgs/msg/Temperature"](header=header, temperature=20.0, variance=0.0)


@pytest.mark.parametrize(
    ("topic", "make"),
    [
        ("/contacts", _string),
        ("/red/imu/mag", _temperature),
        ("/robot_description", _int32),
        ("/tensegrity/calibration", _string),
        ("/commands/rest_length_targets", _int32),
    ],
)
def test_a_known_topic_of_another_type_gives_bag_error_naming_it(
    intact: Intact, tmp_path: Path, topic: str, make: Callable[[Any], Any]
) -> None:
    store = m.typestore()
    msg = make(store.types)
    kind = msg.__msgtype__
    replacement = bytes(store.serialize_cdr(msg, kind))

    def transform(t: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        yield (t, kind, ns, replacement) if t == topic else (t, msgtype, ns, raw)

    bag = _rewrite(intact.bag, tmp_path / "bag", transform)
    with pytest.raises(BagError, match=f"bag.*{topic}") as err:
        _read(bag)
    assert str(bag) in str(err.value)
    # given the robot, a wrong type is still refused (not skipped)
    with pytest.raises(BagError, match=f"{topic} has type {kind}"):
        _read(bag, description=load_robot(ROBOT))


def test_a_custom_type_of_another_definition_gives_bag_error(
    intact: Intact, tmp_path: Path
) -> None:
    other = get_typestore(Stores.ROS2_JAZZY)
    for name, text in m.CUSTOM_MESSAGES.items():
        if name.endswith("/ContactFlags"):
            text += "\nuint8 firmware_version\n"
        other.register(get_types_from_msg(text, name))
    kind = "tensegrity_msgs/msg/ContactFlags"
    with (
        Reader(intact.bag) as src,
        Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as out,
    ):
        conns: dict[str, Any] = {}
        for conn, ns, raw in src.messages():
            store = other if conn.topic == "/contacts" else m.typestore()
            if conn.topic not in conns:
                conns[conn.topic] = out.add_connection(conn.topic, conn.msgtype, typestore=store)
            data = bytes(raw)
            if conn.topic == "/contacts":
                old: Any = m.typestore().deserialize_cdr(data, kind)
                new = other.types[kind](
                    header=old.header,
                    nodes=old.nodes,
                    in_contact=old.in_contact,
                    firmware_version=3,
                )
                data = bytes(other.serialize_cdr(new, kind))
            out.write(conns[conn.topic], ns, data)
    with pytest.raises(BagError, match=r"/contacts.*hash"):
        _read(tmp_path / "bag")


def _drop(dropped: str) -> Any:
    def transform(topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        if topic != dropped:
            yield topic, msgtype, ns, raw

    return transform


def test_no_robot_description_gives_bag_error_unless_the_robot_is_given(
    intact: Intact, tmp_path: Path
) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", _drop(m.DESCRIPTION_YAML_TOPIC))
    with pytest.raises(BagError, match=f"no {m.DESCRIPTION_YAML_TOPIC}") as err:
        _read(bag)
    assert str(bag) in str(err.value)
    reader, periods = _read(bag, description=load_robot(ROBOT))
    assert reader.description == load_robot(ROBOT) and not reader.skipped
    _same_periods(periods, intact.periods)


def test_no_calibration_gives_bag_error(intact: Intact, tmp_path: Path) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", _drop("/tensegrity/calibration"))
    for kwargs in ({}, {"description": load_robot(ROBOT)}):
        with pytest.raises(BagError, match="no /tensegrity/calibration") as err:
            _read(bag, **kwargs)
        assert str(bag) in str(err.value)


def test_no_run_info_infers_the_control_period(intact: Intact, tmp_path: Path) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", _drop("/tensegrity/run_info"))
    reader, periods = _read(bag)
    assert reader.run_info == {} and reader.control_period == pytest.approx(0.1)
    assert len(periods) == len(intact.periods)


def test_no_camera_info_uses_the_nominal_camera(intact: Intact, tmp_path: Path) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", _drop("/camera/camera_info"))
    reader, _ = _read(bag)
    d = load_robot(ROBOT)
    assert np.array_equal(reader.calibration.camera_intrinsics, d.sensors.camera.intrinsics)


def test_the_bag_of_another_robot_given_a_description_gives_bag_error(intact: Intact) -> None:
    with pytest.raises(BagError, match="calibration"):
        _read(intact.bag, description=load_robot("superball"))


# ---------------------------------------------------------------------- time stamps


class DuplicateNth:
    """A transform that writes the ``n``-th message on ``topic`` twice."""

    def __init__(self, topic: str, n: int) -> None:
        self.topic, self.n = topic, n
        self.seen = 0
        self.stamp: int | None = None

    def __call__(self, topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        yield topic, msgtype, ns, raw
        if topic == self.topic:
            self.seen += 1
            if self.seen == self.n:
                self.stamp = _stamp(raw)
                yield topic, msgtype, ns, raw


class SwapNth:
    """A transform that writes the ``n``-th message on ``topic`` after the next one on
    it, at the latter's log time: its header stamp goes back."""

    def __init__(self, topic: str, n: int) -> None:
        self.topic, self.n = topic, n
        self.seen = 0
        self.held = b""
        self.stamp: int | None = None

    def __call__(self, topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        if topic != self.topic:
            yield topic, msgtype, ns, raw
            return
        self.seen += 1
        if self.seen == self.n:
            self.held, self.stamp = raw, _stamp(raw)
            return
        yield topic, msgtype, ns, raw
        if self.seen == self.n + 1:
            yield topic, msgtype, ns, self.held


def test_duplicated_imu_stamps_are_counted_and_strict_names_topic_and_time(
    intact: Intact, tmp_path: Path
) -> None:
    dup = DuplicateNth("/red/imu/data_raw", 20)
    bag = _rewrite(intact.bag, tmp_path / "bag", dup)
    reader, periods = _read(bag)
    assert reader.skipped == {"duplicate": 1}
    _same_periods(periods, intact.periods)
    t = ns_to_seconds(dup.stamp or 0)
    with pytest.raises(BagError, match=rf"/red/imu/data_raw at t={t:.9f} s: duplicate") as err:
        _read(bag, strict=True)
    assert str(bag) in str(err.value)


def test_out_of_order_imu_stamps_are_counted_and_strict_names_topic_and_time(
    intact: Intact, tmp_path: Path
) -> None:
    swap = SwapNth("/green/imu/data_raw", 20)
    bag = _rewrite(intact.bag, tmp_path / "bag", swap)
    reader, periods = _read(bag)
    assert reader.skipped == {"out_of_order": 1}
    expected = _without(intact.periods, _at(swap.stamp, ImuSample, rod=1))
    _same_periods(periods, expected)
    t = ns_to_seconds(swap.stamp or 0)
    with pytest.raises(BagError, match=rf"/green/imu/data_raw at t={t:.9f} s: out of order"):
        _read(bag, strict=True)


def test_a_second_command_at_the_same_time_is_a_counted_duplicate(
    intact: Intact, tmp_path: Path
) -> None:
    seen = 0

    def transform(topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        nonlocal seen
        yield topic, msgtype, ns, raw
        if topic == "/commands/rest_length_targets":
            seen += 1
            if seen == 5:  # a later stamp, the same log time
                later = bytearray(raw)
                later[8:12] = (int.from_bytes(raw[8:12], "little") + 1).to_bytes(4, "little")
                yield topic, msgtype, ns, bytes(later)

    bag = _rewrite(intact.bag, tmp_path / "bag", transform)
    reader, periods = _read(bag)
    assert reader.skipped == {"duplicate": 1}
    _same_periods(periods, intact.periods)
    with pytest.raises(BagError, match=r"/commands/rest_length_targets at t=.*duplicate"):
        _read(bag, strict=True)


def test_a_last_command_with_nothing_after_it_is_a_counted_trailing_command(
    tmp_path: Path,
) -> None:
    d = load_robot(ROBOT)
    sim = SimBackend(d)
    result = sim.reset(np.random.default_rng(0))
    with BagWriter(tmp_path / "bag", d, sim.calibration, {"control_period": 0.1}) as writer:
        writer.write_samples(result.samples)
        writer.write_command(0.5, d.rest_lengths[d.actuated])
    reader, periods = _read(tmp_path / "bag")
    assert reader.skipped == {"trailing_command": 1}
    assert len(periods) == 1 and periods[0].command is None
    _same_samples(periods[0].samples, list(result.samples), "start")
    with pytest.raises(BagError, match="trailing command"):
        _read(tmp_path / "bag", strict=True)


# ---------------------------------------------------------------------- values


def _set(path: str, value: float) -> Callable[[Any], None]:
    """An edit that sets field ``a.b`` of a message, or element ``i`` of its array ``a``
    (``a.i``)."""
    head, leaf = path.split(".")

    def edit(msg: Any) -> None:
        if leaf.isdigit():
            array = np.array(getattr(msg, head), dtype=np.float64)
            array[int(leaf)] = value
            setattr(msg, head, array)
        else:
            setattr(getattr(msg, head), leaf, value)

    return edit


@pytest.mark.parametrize(
    ("topic", "field", "kind", "attrs", "value"),
    [
        ("/red/imu/data_raw", "linear_acceleration.x", ImuSample, {"rod": 0}, math.nan),
        ("/blue/imu/data_raw", "angular_velocity.z", ImuSample, {"rod": 2}, -math.inf),
        ("/motors/rest_lengths", "position.2", EncoderSample, {}, math.nan),
        ("/motors/rest_lengths", "position.0", EncoderSample, {}, math.inf),
        ("/uwb/ranges", None, UwbRangeSample, {}, math.nan),
    ],
    ids=["accel_nan", "gyro_inf", "encoder_nan", "encoder_inf", "uwb_nan"],
)
def test_a_non_finite_value_is_skipped_and_never_reaches_a_sample(
    intact: Intact,
    tmp_path: Path,
    topic: str,
    field: str | None,
    kind: type,
    attrs: Any,
    value: float,
) -> None:
    def edit_range(msg: Any) -> None:
        msg.ranges[0].range = value

    editor = EditNth(topic, 3, edit_range if field is None else _set(field, value))
    bag = _rewrite(intact.bag, tmp_path / "bag", editor)
    reader, periods = _read(bag)
    assert reader.skipped == {"undecodable": 1}
    expected = _without(intact.periods, _at(editor.stamp, kind, **attrs))
    _same_periods(periods, expected)
    for s in (s for p in periods for s in p.samples):
        for f in dataclasses.fields(s):
            x = getattr(s, f.name)
            if isinstance(x, np.ndarray) and x.dtype.kind == "f":
                assert np.all(np.isfinite(x)), f"{type(s).__name__}.{f.name}"
    with pytest.raises(BagError, match=rf"{topic} at t=\d+\.\d+ s: undecodable"):
        _read(bag, strict=True)


def test_a_non_finite_magnetometer_reading_leaves_the_imu_sample_without_one(
    intact: Intact, tmp_path: Path
) -> None:
    """The gyro and accelerometer of that instant stay; the field reads as absent (all
    NaN, as for an IMU without a magnetometer), never the one bad component."""
    editor = EditNth("/red/imu/mag", 7, _set("magnetic_field.y", math.nan))
    bag = _rewrite(intact.bag, tmp_path / "bag", editor)
    reader, periods = _read(bag)
    assert reader.skipped == {"undecodable": 1}
    t = ns_to_seconds(editor.stamp or 0)
    got = [s for p in periods for s in p.samples if isinstance(s, ImuSample)]
    want = [s for p in intact.periods for s in p.samples if isinstance(s, ImuSample)]
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        if (a.t, a.rod) == (t, 0):
            assert np.isnan(a.mag).all()
            assert np.array_equal(a.accel, b.accel) and np.array_equal(a.gyro, b.gyro)
        else:
            _same_values(a, b, f"imu at {a.t}")


def _reverse_names(msg: Any) -> None:
    msg.name = list(reversed(msg.name))
    msg.position = np.array(msg.position[::-1])


@pytest.mark.parametrize("topic", ["/motors/rest_lengths", "/cables/lengths"])
def test_joint_states_in_another_name_order_are_mapped_by_name(
    intact: Intact, tmp_path: Path, topic: str
) -> None:
    reader, periods = _read(
        _rewrite(intact.bag, tmp_path / "bag", _edit_every(topic, _reverse_names))
    )
    assert not reader.skipped
    _same_periods(periods, intact.periods)


def _rename_first(msg: Any) -> None:
    msg.name = ["no_such_cable", *list(msg.name)[1:]]


def _repeat_first(msg: Any) -> None:
    msg.name = [msg.name[0], msg.name[0], *list(msg.name)[2:]]


def _one_more(msg: Any) -> None:
    msg.name = [*msg.name, "no_such_cable"]
    msg.position = np.append(msg.position, 1.0)


def _one_less(msg: Any) -> None:
    msg.name = list(msg.name)[:-1]
    msg.position = np.array(msg.position[:-1])


@pytest.mark.parametrize("edit", [_rename_first, _repeat_first, _one_more, _one_less])
def test_joint_states_that_do_not_fit_the_robot_are_skipped(
    intact: Intact, tmp_path: Path, edit: Callable[[Any], None]
) -> None:
    editor = EditNth("/motors/rest_lengths", 9, edit)
    bag = _rewrite(intact.bag, tmp_path / "bag", editor)
    reader, periods = _read(bag)
    assert reader.skipped == {"undecodable": 1}
    expected = _without(intact.periods, _at(editor.stamp, EncoderSample))
    _same_periods(periods, expected)


def test_a_command_with_an_unknown_cable_is_skipped(intact: Intact, tmp_path: Path) -> None:
    """The period it would have started merges into the one before: one period fewer."""
    editor = EditNth("/commands/rest_length_targets", 4, _rename_first)
    reader, periods = _read(_rewrite(intact.bag, tmp_path / "bag", editor))
    assert reader.skipped == {"undecodable": 1}
    assert len(periods) == len(intact.periods) - 1
    merged = intact.periods[3].samples + intact.periods[4].samples
    _same_samples(periods[3].samples, merged, "merged period")
    _same_periods(periods[4:], intact.periods[5:], first=4)


@pytest.mark.parametrize("module", ["initiator", "responder"])
def test_a_uwb_module_id_out_of_range_is_skipped(
    intact: Intact, tmp_path: Path, module: str
) -> None:
    n_modules = RobotCodec(load_robot(ROBOT)).n_modules

    def edit(msg: Any) -> None:
        setattr(msg.ranges[-1], module, n_modules)

    editor = EditNth("/uwb/ranges", 2, edit)
    bag = _rewrite(intact.bag, tmp_path / "bag", editor)
    reader, periods = _read(bag)
    assert reader.skipped == {"undecodable": 1}
    expected = _without(intact.periods, _at(editor.stamp, UwbRangeSample))
    _same_periods(periods, expected)
    for s in (s for p in periods for s in p.samples if isinstance(s, UwbRangeSample)):
        assert s.pairs.max() < n_modules
    with pytest.raises(BagError, match=r"/uwb/ranges at t=.*module id"):
        _read(bag, strict=True)


def test_contact_flags_in_another_node_order_are_mapped_by_name(
    intact: Intact, tmp_path: Path
) -> None:
    def reverse_nodes(msg: Any) -> None:
        msg.nodes = list(reversed(msg.nodes))
        msg.in_contact = np.array(msg.in_contact[::-1])

    bag = _rewrite(intact.bag, tmp_path / "bag", _edit_every("/contacts", reverse_nodes))
    reader, periods = _read(bag)
    assert not reader.skipped
    _same_periods(periods, intact.periods)


def _truncate(raw: bytes) -> bytes:
    return raw[:40]


def _big_endian(raw: bytes) -> bytes:
    return b"\x00\x00" + raw[2:]


def _bad_utf8_frame(raw: bytes) -> bytes:
    return raw[:16] + b"\xff" + raw[17:]


def _frame_length_huge(raw: bytes) -> bytes:
    return raw[:12] + (2**31).to_bytes(4, "little") + raw[16:]


@pytest.mark.parametrize(
    ("topic", "damage"),
    [
        ("/red/imu/data_raw", _truncate),
        ("/green/imu/mag", _big_endian),
        ("/blue/imu/data", _bad_utf8_frame),
        ("/red/imu/data_raw", _frame_length_huge),
    ],
    ids=["raw_truncated", "mag_big_endian", "ahrs_frame_not_utf8", "raw_frame_length_huge"],
)
def test_undecodable_imu_bytes_are_skipped(
    intact: Intact, tmp_path: Path, topic: str, damage: Callable[[bytes], bytes]
) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", ReplaceNth(topic, 5, damage))
    reader, _ = _read(bag)
    assert reader.skipped == {"undecodable": 1}


@pytest.mark.parametrize(
    ("topic", "damage"),
    [
        ("/motors/rest_lengths", _truncate),
        ("/uwb/ranges", _big_endian),
        ("/contacts", _truncate),
        ("/ground_truth/state", _big_endian),
    ],
)
def test_undecodable_bytes_of_other_topics_are_skipped(
    intact: Intact, tmp_path: Path, topic: str, damage: Callable[[bytes], bytes]
) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", ReplaceNth(topic, 5, damage))
    reader, periods = _read(bag)
    assert reader.skipped == {"undecodable": 1}
    assert len(periods) == len(intact.periods)
    with pytest.raises(BagError, match=rf"{topic} at t="):
        _read(bag, strict=True)


# ---------------------------------------------------------------------- pairs


def _with_frame(rgb: bool, depth: bool) -> tuple[Any, RgbdFrame]:
    """A transform adding one small RGB-D frame (either half) after an IMU message."""
    codec = RobotCodec(load_robot(ROBOT))
    rng = np.random.default_rng(2)
    frame = RgbdFrame(
        0.305,
        rng.integers(0, 256, size=(3, 4, 3), dtype=np.uint8),
        rng.uniform(0.5, 3.0, size=(3, 4)).astype(np.float32),
    )
    (t_rgb, raw_rgb), (t_depth, raw_depth) = codec.encode_sample(frame)
    done = False

    def transform(topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        nonlocal done
        yield topic, msgtype, ns, raw
        if not done and topic == "/red/imu/data_raw" and ns >= 305_000_000:
            done = True
            if rgb:
                yield t_rgb, m.IMAGE, ns, raw_rgb
            if depth:
                yield t_depth, m.IMAGE, ns, raw_depth

    return transform, frame


@pytest.mark.parametrize(("rgb", "depth"), [(True, True), (True, False), (False, True)])
def test_camera_frames_pair_colour_and_depth(
    intact: Intact, tmp_path: Path, rgb: bool, depth: bool
) -> None:
    transform, frame = _with_frame(rgb, depth)
    reader, periods = _read(_rewrite(intact.bag, tmp_path / "bag", transform))
    frames = [s for p in periods for s in p.samples if isinstance(s, RgbdFrame)]
    if rgb and depth:
        assert not reader.skipped
        assert len(frames) == 1
        _same_values(frames[0], frame, "frame")
    else:
        assert reader.skipped == {"unpaired": 1} and not frames
    others = _without(periods, lambda s: isinstance(s, RgbdFrame)) if frames else periods
    for k, (a, b) in enumerate(zip(others, intact.periods, strict=True)):
        _same_samples(a.samples, b.samples, f"period {k}")


def test_ground_truth_poses_without_the_state_are_unpaired(intact: Intact, tmp_path: Path) -> None:
    seen = 0

    def transform(topic: str, msgtype: str, ns: int, raw: bytes) -> Iterator[Message]:
        nonlocal seen
        if topic == "/ground_truth/rod_poses":
            seen += 1
            if seen == 6:
                return
        yield topic, msgtype, ns, raw

    reader, periods = _read(_rewrite(intact.bag, tmp_path / "bag", transform))
    assert reader.skipped == {"unpaired": 1}
    assert [p.truth is None for p in periods] == [k == 5 for k in range(len(periods))]


@pytest.mark.parametrize("case", ["short_rest_lengths", "nan_position"])
def test_ground_truth_that_does_not_fit_the_robot_is_skipped(
    intact: Intact, tmp_path: Path, case: str
) -> None:
    def edit(msg: Any) -> None:
        if case == "short_rest_lengths":
            msg.rest_lengths = np.array(msg.rest_lengths[:2])
        else:
            msg.node_positions[0].x = math.nan

    bag = _rewrite(intact.bag, tmp_path / "bag", EditNth("/ground_truth/state", 6, edit))
    reader, periods = _read(bag)
    assert reader.skipped == {"undecodable": 1}
    n_cables = load_robot(ROBOT).n_cables
    for p in periods:
        if p.truth is not None:
            assert p.truth.rest_lengths.shape == (n_cables,)
            assert np.all(np.isfinite(p.truth.node_positions))


# ---------------------------------------------------------------------- header messages


@pytest.mark.parametrize(
    ("topic", "edit"),
    [
        ("/tensegrity/calibration", lambda msg: setattr(msg.anchors[0], "x", math.nan)),
        ("/tensegrity/calibration", _set("uwb_offsets.0", math.inf)),
        ("/tensegrity/calibration", _set("camera_pose.3", math.nan)),
        ("/camera/camera_info", _set("k.0", math.nan)),
    ],
    ids=["anchor_nan", "uwb_offset_inf", "camera_pose_nan", "intrinsics_nan"],
)
def test_a_non_finite_calibration_gives_bag_error(
    intact: Intact, tmp_path: Path, topic: str, edit: Callable[[Any], None]
) -> None:
    bag = _rewrite(intact.bag, tmp_path / "bag", EditNth(topic, 1, edit))
    with pytest.raises(BagError, match=topic):
        _read(bag)


@pytest.mark.parametrize(
    "text",
    [
        "control_period: -0.1\n",
        "control_period: .nan\n",
        "control_period: '0.1'\n",
        "- 1\n- 2\n",
        "[unclosed\n",
        pytest.param("control_period: .inf\n"),
        pytest.param("control_period: true\n"),
        pytest.param("[" * 1000 + "]" * 1000),
    ],
    ids=["negative", "nan", "string", "list", "bad_yaml", "inf", "bool", "deep_nesting"],
)
def test_a_bad_run_info_gives_bag_error(intact: Intact, tmp_path: Path, text: str) -> None:
    def edit(msg: Any) -> None:
        msg.data = text

    bag = _rewrite(intact.bag, tmp_path / "bag", EditNth("/tensegrity/run_info", 1, edit))
    with pytest.raises(BagError, match=r"run_info|control_period") as err:
        _read(bag)
    assert str(bag) in str(err.value)


@pytest.mark.parametrize("text", ["", "rods: [1", "name: x\n", "[" * 1000 + "]" * 1000, "\x00\x01"])
def test_a_bad_robot_description_gives_bag_error(intact: Intact, tmp_path: Path, text: str) -> None:
    def edit(msg: Any) -> None:
        msg.data = text

    bag = _rewrite(intact.bag, tmp_path / "bag", EditNth(m.DESCRIPTION_YAML_TOPIC, 1, edit))
    with pytest.raises(BagError, match=m.DESCRIPTION_YAML_TOPIC) as err:
        _read(bag)
    assert str(bag) in str(err.value)


def test_read_run_of_a_recovered_bag_is_a_prefix_of_the_run(intact: Intact, tmp_path: Path) -> None:
    cut = _chunks(intact.mcap)[2][1]
    bag = _bare_bag(tmp_path / "bag", intact.mcap[:cut])
    run = read_run(bag)
    with BagReader(bag) as reader:
        assert reader.recovered
        n = sum(1 for _ in reader.periods())
    assert len(run.steps) == n - 1
    _same_samples(run.start.samples, intact.periods[0].samples, "start")
    for k, step in enumerate(run.steps[:-1]):
        _same_samples(step.samples, intact.periods[k + 1].samples, f"step {k}")
        assert _same_command(step.command, intact.periods[k + 1].command)


def test_replay_of_a_recovered_bag_plays_every_recovered_period(
    intact: Intact, tmp_path: Path
) -> None:
    chunks = _chunks(intact.mcap)
    cut = (chunks[2][1] + chunks[3][1]) // 2  # inside the fourth chunk
    bag = _bare_bag(tmp_path / "bag", intact.mcap[:cut])
    _, periods = _read(bag)
    replay = ReplayBackend(bag)
    try:
        assert replay.reader.recovered
        assert replay.steps_total == len(periods) - 1
        result = replay.reset(np.random.default_rng(0))
        _same_samples(result.samples, periods[0].samples, "start")
        for k, period in enumerate(periods[1:], start=1):
            assert not result.ended
            command = replay.next_command
            assert command is not None
            result = replay.step(command)
            assert _same_command(result.command, period.command)
            _same_samples(result.samples, period.samples, f"period {k}")
        assert result.ended
        with pytest.raises(RuntimeError, match="ended"):
            replay.step(np.zeros_like(period.command))
    finally:
        replay.close()


# ---------------------------------------------------------------------- decoders


@cache
def _valid_messages() -> dict[str, bytes]:
    """One message of each kind the codec decodes, keyed by topic."""
    d = load_robot(ROBOT)
    codec = RobotCodec(d)
    sim = SimBackend(d)
    result = sim.reset(np.random.default_rng(0))
    result = sim.step(d.rest_lengths[d.actuated])
    out: dict[str, bytes] = {}
    for s in result.samples:
        for topic, raw in codec.encode_sample(s):
            out.setdefault(topic, raw)
    truth = sim.ground_truth()
    assert truth is not None
    out.update(codec.encode_truth(truth))
    out.update(codec.encode_header(sim.calibration, {"control_period": 0.1}, 1.0))
    out.update([codec.encode_command(1.0, d.rest_lengths[d.actuated])])
    sim.close()
    return out


@cache
def _codec() -> RobotCodec:
    return RobotCodec(load_robot(ROBOT))


def _decode(topic: str, raw: bytes) -> None:
    """Decodes ``raw`` as ``topic``'s message, checking what a decoder promises."""
    codec, valid = _codec(), _valid_messages()
    if topic.endswith("/imu/data_raw"):
        _, gyro, accel = codec.decode_imu_raw(raw)
        assert np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel))
    elif topic.endswith("/imu/mag"):
        assert np.all(np.isfinite(codec.decode_mag(raw)[1]))
    elif topic.endswith("/imu/data"):
        q = codec.decode_ahrs(raw)[1]
        assert 0.9 < np.linalg.norm(q) < 1.1
    elif topic in ("/motors/rest_lengths", "/commands/rest_length_targets"):
        values = codec.decode_joint_state(raw, "actuated")[1]
        assert values.shape == (len(codec.actuated_names),) and np.all(np.isfinite(values))
    elif topic == "/cables/lengths":
        values = codec.decode_joint_state(raw, "all")[1]
        assert values.shape == (len(codec.cable_names),) and np.all(np.isfinite(values))
    elif topic == "/uwb/ranges":
        uwb = codec.decode_uwb(raw)
        assert np.all(np.isfinite(uwb.ranges))
        assert not uwb.pairs.size or uwb.pairs.max() < codec.n_modules
    elif topic == "/contacts":
        assert codec.decode_contacts(raw).in_contact.shape == (len(codec.node_names),)
    elif topic == "/ground_truth/state":
        codec.decode_truth(raw, valid["/ground_truth/rod_poses"])
    elif topic == "/ground_truth/rod_poses":
        codec.decode_truth(valid["/ground_truth/state"], raw)
    elif topic == "/tensegrity/calibration":
        codec.decode_calibration(raw, valid["/camera/camera_info"])
    elif topic == "/camera/camera_info":
        codec.decode_calibration(valid["/tensegrity/calibration"], raw)
    else:
        raise AssertionError(f"no decoder for {topic}")


_DECODED = [
    "/red/imu/data_raw",
    "/red/imu/mag",
    "/red/imu/data",
    "/motors/rest_lengths",
    "/cables/lengths",
    "/uwb/ranges",
    "/contacts",
    "/ground_truth/state",
    "/ground_truth/rod_poses",
    "/tensegrity/calibration",
    "/camera/camera_info",
    "/commands/rest_length_targets",
]


def test_every_valid_message_decodes() -> None:
    valid = _valid_messages()
    assert set(_DECODED) <= set(valid)
    for topic in _DECODED:
        _decode(topic, valid[topic])


@settings(
    max_examples=200, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(raw=st.binary(max_size=600), topic=st.sampled_from(_DECODED))
def test_decoders_on_random_bytes_raise_only_value_errors(raw: bytes, topic: str) -> None:
    for data in (raw, b"\x00\x01\x00\x00" + raw):
        try:
            _decode(topic, data)
        except ValueError:
            pass
    for decode in (m.decode_imu, m.decode_magnetic_field):
        try:
            decode(memoryview(raw))
        except ValueError:
            pass


@settings(
    max_examples=200, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    topic=st.sampled_from(_DECODED),
    edits=st.lists(st.tuples(st.integers(0, 2**20), st.integers(0, 255)), max_size=4),
    cut=st.one_of(st.none(), st.integers(0, 2**20)),
)
def test_decoders_on_damaged_messages_raise_only_value_errors(
    topic: str, edits: list[tuple[int, int]], cut: int | None
) -> None:
    raw = bytearray(_valid_messages()[topic])
    for pos, byte in edits:
        raw[pos % len(raw)] = byte
    if cut is not None:
        raw = raw[: cut % len(raw)]
    try:
        _decode(topic, bytes(raw))
    except ValueError:
        pass


@settings(max_examples=200, deadline=None, database=None)
@given(cut=st.integers(0, 10_000), kind=st.sampled_from(["imu", "ahrs", "mag"]))
def test_fast_decoders_refuse_every_strict_prefix(cut: int, kind: str) -> None:
    topic = {"imu": "/red/imu/data_raw", "ahrs": "/red/imu/data", "mag": "/red/imu/mag"}[kind]
    raw = _valid_messages()[topic]
    decode = m.decode_magnetic_field if kind == "mag" else m.decode_imu
    decode(raw)
    with pytest.raises(ValueError, match=r"CDR|runs past|too few"):
        decode(raw[: cut % len(raw)])
