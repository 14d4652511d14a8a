"""A damaged chunk loses its own messages only, and ``estimate`` goes on past a bag that
fails (issue 12, "Reliability").

A bag of several chunks has the records of one chunk in the middle overwritten: it
opens, the periods before and after the damage read as in the intact bag, and the lost
span names the chunk's topics and times (the reader, the replay's ``info``,
``metrics.json``); ``strict`` refuses it, naming them. ``estimate`` over a folder
estimates every bag it can, logs one line per bag that fails and exits 2.
"""

from __future__ import annotations

import itertools
import json
import logging
from collections import Counter
from typing import TYPE_CHECKING

import numpy as np
import pytest
from backports import zstd

from agents.cli import main as cli_main
from hardware.bag import BagError, ReplayBackend
from hardware.bag.reader import COMMAND_TOPIC
from tensegrity_gym.model.samples import ns_to_seconds
from tests.hardware.test_bag_robustness import (
    Intact,
    Message,
    _bare_bag,
    _chunk_records,
    _chunks,
    _mcap_records,
    _read,
    _rewrite,
    _same_periods,
    _write_small_bag,
)

if TYPE_CHECKING:
    from pathlib import Path

STEPS = 8  # control periods (0.1 s) of each bag; flushed every 0.2 s: five chunks
DAMAGED = 2  # the chunk whose records are overwritten


@pytest.fixture(scope="module")
def chunked(tmp_path_factory: pytest.TempPathFactory) -> dict[bool, Intact]:
    """compress -> a bag of several chunks and its periods."""
    out = {}
    for compress in (False, True):
        folder = tmp_path_factory.mktemp("zstd" if compress else "plain")
        bag = _write_small_bag(folder / "episode_000", compress=compress, steps=STEPS)
        _, periods = _read(bag)
        out[compress] = Intact(bag, (bag / "episode_000.mcap").read_bytes(), periods)
        assert len(_chunks(out[compress].mcap)) > DAMAGED + 1
    return out


def _chunk_times(data: bytes, k: int) -> tuple[int, int]:
    """(start, end) log times (ns) in the header of chunk ``k``."""
    o = _chunks(data)[k][0]
    return int.from_bytes(data[o + 9 : o + 17], "little"), _chunks(data)[k][2]


def _chunk_message_count(data: bytes, k: int) -> int:
    """Message records in chunk ``k`` (decompressed here, not by the reader)."""
    start, length = _chunk_records(data, _chunks(data)[k][0])
    records = data[start : start + length]
    if records[:4] == b"\x28\xb5\x2f\xfd":  # a zstd frame
        records = zstd.decompress(records)
    return sum(op == 0x05 for _, op, _ in _mcap_records(b"12345678" + records))


def _damage(data: bytes, k: int = DAMAGED) -> bytes:
    """The records of chunk ``k`` overwritten with bytes of no meaning."""
    start, length = _chunk_records(data, _chunks(data)[k][0])
    out = bytearray(data)
    out[start : start + length] = (b"\x00\xa5\x5a\xff" * (length // 4 + 1))[:length]
    return bytes(out)


def _damaged_bag(source: Intact, folder: Path, *, index: bool, k: int = DAMAGED) -> Path:
    """A copy of ``source`` with chunk ``k`` overwritten; ``index``: with the file's
    summary and metadata.yaml (else cut before the summary: a crashed recording)."""
    data = _damage(source.mcap, k)
    if not index:
        data = data[: _chunks(data)[-1][1]]
    metadata = source.bag / "metadata.yaml" if index else None
    return _bare_bag(folder, data, metadata=metadata)


@pytest.mark.parametrize("index", [True, False], ids=["indexed", "cut_off"])
@pytest.mark.parametrize("compress", [False, True], ids=["plain", "zstd"])
def test_a_damaged_middle_chunk_loses_only_its_own_span(
    chunked: dict[bool, Intact], tmp_path: Path, compress: bool, index: bool
) -> None:
    source = chunked[compress]
    bag = _damaged_bag(source, tmp_path / "bag", index=index)
    reader, periods = _read(bag)
    assert reader.recovered is not index
    start, end = _chunk_times(source.mcap, DAMAGED)
    [span] = reader.lost_spans
    assert (span.start_ns, span.end_ns) == (start, end)
    assert span.messages == _chunk_message_count(source.mcap, DAMAGED) > 0
    assert {COMMAND_TOPIC, "/red/imu/data_raw", "/ground_truth/state"} <= set(span.topics)
    assert reader.skipped == {"damaged_chunk": span.messages}
    # before the damage and after it, the periods are the intact bag's
    before = [p for p in source.periods if p.t_end < span.start]
    pairs = itertools.pairwise(source.periods)
    after = [p for prev, p in pairs if prev.t_end >= span.end]  # began after the span
    assert before and after
    _same_periods(periods[: len(before)], before)
    _same_periods(periods[-len(after) :], after)
    # one period spans the lost time: its samples are missing there, none made up
    [gap] = [p for p in periods if p.lost]
    assert gap.lost == [span] and gap is periods[len(before)]
    inside = [s for s in gap.samples if span.start < s.t < span.end]
    assert not inside
    intact = {(type(s).__name__, s.t) for p in source.periods for s in p.samples}
    assert all((type(s).__name__, s.t) in intact for s in gap.samples)
    assert len(periods) == len(before) + 1 + len(after)


@pytest.mark.parametrize("index", [True, False], ids=["indexed", "cut_off"])
def test_strict_refuses_a_damaged_chunk_naming_its_topics_and_times(
    chunked: dict[bool, Intact], tmp_path: Path, index: bool
) -> None:
    bag = _damaged_bag(chunked[True], tmp_path / "bag", index=index)
    start, end = (ns_to_seconds(t) for t in _chunk_times(chunked[True].mcap, DAMAGED))
    with pytest.raises(BagError) as err:
        _read(bag, strict=True)
    text = str(err.value)
    assert text.startswith(str(bag)) and "damaged chunk" in text
    assert f"t={start:.9f}..{end:.9f} s" in text
    assert COMMAND_TOPIC in text and "/uwb/ranges" in text


def test_a_damaged_first_chunk_says_the_description_was_lost(
    chunked: dict[bool, Intact], tmp_path: Path
) -> None:
    source = chunked[True]
    bag = _bare_bag(
        tmp_path / "bag", _damage(source.mcap, 0), metadata=source.bag / "metadata.yaml"
    )
    lost = r"no /tensegrity/robot_description_yaml.*damaged chunk at byte"
    with pytest.raises(BagError, match=lost):
        _read(bag)


def test_replay_over_a_damaged_chunk_reports_the_lost_span(
    chunked: dict[bool, Intact], tmp_path: Path
) -> None:
    bag = _damaged_bag(chunked[True], tmp_path / "bag", index=True)
    _, periods = _read(bag)
    replay = ReplayBackend(bag)
    try:
        result = replay.reset(np.random.default_rng(0))
        infos = [result.info]
        while not result.ended:
            command = replay.next_command
            assert command is not None
            result = replay.step(command)
            infos.append(result.info)
    finally:
        replay.close()
    assert len(infos) == len(periods)
    lost = [k for k, info in enumerate(infos) if info["bag_lost"]]
    [k] = lost
    [span] = infos[k]["bag_lost"]
    start, end = (ns_to_seconds(t) for t in _chunk_times(chunked[True].mcap, DAMAGED))
    assert (span["start_s"], span["end_s"]) == (start, end)
    assert COMMAND_TOPIC in span["topics"] and span["messages"] > 0
    assert infos[k]["bag_skipped"] == {"damaged_chunk": span["messages"]}
    assert not infos[0]["bag_skipped"] and k > 1


# ---------------------------------------------------------------------- estimate


@pytest.fixture(scope="module")
def long_bag(tmp_path_factory: pytest.TempPathFactory) -> Intact:
    """A bag long enough for the estimators' 2 s of settling (3 s, 15 chunks)."""
    bag = _write_small_bag(tmp_path_factory.mktemp("long") / "episode_000", compress=True, steps=30)
    return Intact(bag, (bag / "episode_000.mcap").read_bytes(), [])


def _without_start_uwb(source: Path, dst: Path) -> Path:
    """``source`` rewritten without the UWB ranges of its start period, from which an
    estimator cannot place the robot."""
    first_command: list[int] = []

    def transform(topic: str, msgtype: str, ns: int, raw: bytes) -> list[Message]:
        if topic == COMMAND_TOPIC and not first_command:
            first_command.append(ns)
        if topic == "/uwb/ranges" and not first_command:
            return []
        return [(topic, msgtype, ns, raw)]

    return _rewrite(source, dst, transform)


def _errors(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_estimate_goes_on_past_a_bag_that_fails(
    long_bag: Intact, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Three bags, the middle one unreadable, the last with a damaged chunk: the first
    and last are estimated, the middle one is one logged line, and the exit is 2."""
    source = long_bag
    folder = tmp_path / "bags"
    folder.mkdir()
    _bare_bag(folder / "episode_000", source.mcap, metadata=source.bag / "metadata.yaml")
    _bare_bag(folder / "episode_001", _damage(source.mcap, 0)[: _chunks(source.mcap)[1][1]])
    _damaged_bag(source, folder / "episode_002", index=True, k=10)
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO):
        rc = cli_main(
            ["estimate", str(folder), "--estimator", "ukf", "--out", str(out), "--no-progress"]
        )
    assert rc == 2
    assert sorted(p.name for p in out.iterdir()) == ["episode_000", "episode_002"]
    assert not (out / "episode_001").exists()
    good = json.loads((out / "episode_000" / "metrics.json").read_text())
    salvaged = json.loads((out / "episode_002" / "metrics.json").read_text())
    assert good["lost_spans"] == [] and good["finite"]
    [span] = salvaged["lost_spans"]
    assert COMMAND_TOPIC in span["topics"] and salvaged["finite"]
    assert salvaged["skipped_messages"] == {"damaged_chunk": span["messages"]}
    assert salvaged["steps"] == good["steps"] - span["topics"][COMMAND_TOPIC]
    errors = [r.getMessage() for r in _errors(caplog)]
    assert len(errors) == 2, errors
    assert "episode_001" in errors[0] and "\n" not in errors[0]
    assert errors[1].startswith("1 of 3 bags failed") and "episode_001" in errors[1]
    assert not any(r.exc_info for r in caplog.records)


def test_estimate_of_one_bag_that_fails_is_one_line_and_exit_2(
    long_bag: Intact, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    source = long_bag
    bag = _bare_bag(tmp_path / "bag", _damage(source.mcap, 0)[: _chunks(source.mcap)[1][1]])
    with caplog.at_level(logging.INFO):
        rc = cli_main(["estimate", str(bag), "--estimator", "ukf", "--out", str(tmp_path / "o")])
    assert rc == 2
    [error] = _errors(caplog)
    assert "no /tensegrity/robot_description_yaml" in error.getMessage() and not error.exc_info
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_a_bag_whose_start_lost_its_uwb_ranges_is_estimated_from_when_they_come(
    long_bag: Intact, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bag = _without_start_uwb(long_bag.bag, tmp_path / "bag")
    with caplog.at_level(logging.INFO):
        rc = cli_main(["estimate", str(bag), "--estimator", "ukf", "--out", str(tmp_path / "o")])
    assert rc == 0 and not _errors(caplog)
    [warning] = [r for r in caplog.records if "not placed at reset" in r.getMessage()]
    assert "UWB ranges to anchors" in warning.getMessage()
    assert (tmp_path / "o" / "metrics.json").exists()


def test_a_folder_of_good_bags_still_exits_0(
    long_bag: Intact, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    folder = tmp_path / "bags"
    folder.mkdir()
    for name in ("episode_000", "episode_001"):
        _bare_bag(folder / name, long_bag.mcap, metadata=long_bag.bag / "metadata.yaml")
    rc = cli_main(["estimate", str(folder), "--estimator", "ukf", "--out", str(tmp_path / "o")])
    assert rc == 0 and not _errors(caplog)
    counts = Counter(p.parent.name for p in (tmp_path / "o").glob("*/metrics.json"))
    assert counts == {"episode_000": 1, "episode_001": 1}
