"""Writing a run to a ROS 2 bag (MCAP storage), crash-safe.

A bag is a folder holding ``<name>.mcap`` and, once closed, ``metadata.yaml``. MCAP
stores messages in chunks; the writer closes a chunk and hands it to the operating
system every ``flush_period`` seconds of recorded time, so a process that dies (a
crash, SIGKILL) leaves every message up to the last flush on disk, and
:class:`hardware.bag.reader.BagReader` opens such a bag. Ctrl-C and SIGTERM close the
bag properly (see ``agents/cli.py``).

Times given to the writer are sample times (s from the source's clock origin); header
stamps and log times are ``clock_origin_ns`` plus them, the robot's own clock, so a
replayed bag recorded again has its original stamps.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

from hardware.bag.codec import RobotCodec
from tensegrity_gym.model.samples import seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping
    from pathlib import Path
    from types import TracebackType

    from numpy import float64
    from numpy.typing import NDArray
    from rosbags.interfaces import Connection

    from hardware.bag.codec import Encoded
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["BagWriter"]

log = logging.getLogger(__name__)


class BagWriter:
    """Writes one run: the robot description, calibration and run info first, then
    samples, commands, ground truth and estimates, each at its own time.

    Messages must come in time order (the log time never goes back: a message older
    than the last one written is logged at the last one's time; its header keeps its own
    stamp). Use as a context manager, or call :meth:`close`.

    Args:
        path: the bag folder to create; it must not exist.
        description, calibration: the robot and its sensor calibration.
        run_info: what else a reader needs or a person wants to know; must hold
            ``control_period`` (s). Written as YAML.
        flush_period: seconds of recorded time between flushes to disk.
        compress: compress each chunk with zstd (a quarter of the size, read as fast).
        clock_origin_ns: the robot-clock ns of sample time 0 (the source backend's
            ``clock_origin_ns``): stamps and log times are written as this plus ``t``.
    """

    def __init__(
        self,
        path: str | Path,
        description: RobotDescription,
        calibration: SensorCalibration,
        run_info: Mapping[str, Any],
        *,
        flush_period: float = 1.0,
        compress: bool = True,
        clock_origin_ns: int = 0,
    ) -> None:
        if "control_period" not in run_info:
            raise ValueError("run_info must hold control_period (s)")
        if not flush_period > 0:
            raise ValueError(f"flush_period must be positive, got {flush_period}")
        self.codec = RobotCodec(description, clock_origin_ns)
        self._calibration = calibration
        self._run_info = dict(run_info)
        self._flush_ns = seconds_to_ns(flush_period)
        self._writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:  # zstd per MCAP chunk, which every MCAP reader understands
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self.path = self._writer.path
        self._connections: dict[str, Connection] = {}
        self._last_ns: int | None = None
        self._last_flush_ns = 0
        self.message_count = 0

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._writer.storage is None

    def _write(self, messages: Iterable[Encoded], t: float) -> None:
        if self.closed:
            raise RuntimeError(f"the bag {self.path} is closed")
        ns = self.codec.stamp_ns(t)
        if self._last_ns is None:  # the header messages open the bag, at its first time
            self._last_ns = self._last_flush_ns = ns
            self._write(self.codec.encode_header(self._calibration, self._run_info, t), t)
        ns = max(ns, self._last_ns)
        types = self.codec.topics.types
        for topic, raw in messages:
            conn = self._connections.get(topic)
            if conn is None:
                conn = self._writer.add_connection(topic, types[topic], typestore=self.codec.store)
                self._connections[topic] = conn
            self._writer.write(conn, ns, raw)
            self.message_count += 1
        self._last_ns = ns
        if ns - self._last_flush_ns >= self._flush_ns:
            self.flush()
            self._last_flush_ns = ns

    def write_samples(self, samples: Iterable[Sample]) -> None:
        """Raw samples, each at its own time (in time order)."""
        for s in samples:
            self._write(self.codec.encode_sample(s), s.t)

    def write_command(self, t: float, targets: NDArray[float64]) -> None:
        """The rest-length targets (m), (m,), sent at time ``t`` for the next period."""
        self._write([self.codec.encode_command(t, targets)], t)

    def write_truth(self, truth: GroundTruth) -> None:
        self._write(self.codec.encode_truth(truth), truth.t)

    def write_estimate(self, estimate: Estimate, t: float | None = None) -> None:
        """An estimator's output, logged at ``t`` (default: its own time)."""
        self._write(self.codec.encode_estimate(estimate), estimate.t if t is None else t)

    def flush(self) -> None:
        """Close the pending MCAP chunk and hand it to the operating system."""
        storage: Any = self._writer.storage
        if storage is None:
            return
        # rosbags' MCAP storage writes a chunk when it reaches 1 MiB; closing one early is
        # what bounds the loss on a crash (checked by tests/test_bag.py).
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and chunk.bio.tell():
            storage.close_chunk()
        storage.bio.flush()

    def close(self) -> None:
        """Write the index and ``metadata.yaml``. Safe to call twice."""
        if self.closed:
            return
        if self._last_ns is None:  # nothing written: still a valid bag with its header
            self._write([], 0.0)
        self._writer.close()
        log.debug("closed %s: %d messages", self.path, self.message_count)
