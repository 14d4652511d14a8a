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

What ROS viewers draw (``/tf``, ``/tensegrity/markers``: :mod:`hardware.bag.scene`) is
written by :meth:`MessageWriter.write_scene` where the writer was made with
``markers=True``. :class:`MessageWriter` is the part every run's stream shares, the bag
and the live view (:mod:`hardware.viewer`): the header first, then messages in time order.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

from hardware.bag import messages as m
from hardware.bag.codec import RobotCodec
from hardware.bag.scene import RobotScene
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

__all__ = ["BagWriter", "MessageWriter"]

log = logging.getLogger(__name__)


class MessageWriter:
    """Encodes one run's messages and hands them, in time order, to :meth:`_emit`: the
    robot description, calibration and run info first, then samples, commands, ground
    truth, estimates and (with ``markers``) what viewers draw, each at its own time.

    Messages must come in time order (the log time never goes back: a message older
    than the last one written is logged at the last one's time; its header keeps its own
    stamp).

    Args:
        description, calibration: the robot and its sensor calibration.
        run_info: what else a reader needs or a person wants to know; must hold
            ``control_period`` (s). Written as YAML.
        clock_origin_ns: the robot-clock ns of sample time 0 (the source backend's
            ``clock_origin_ns``): stamps and log times are written as this plus ``t``.
        markers: encode :meth:`write_scene`'s ``/tf`` and ``/tensegrity/markers``;
            False: it writes nothing.
    """

    def __init__(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        run_info: Mapping[str, Any],
        *,
        clock_origin_ns: int = 0,
        markers: bool = True,
    ) -> None:
        if "control_period" not in run_info:
            raise ValueError("run_info must hold control_period (s)")
        self.codec = RobotCodec(description, clock_origin_ns)
        self._calibration = calibration
        self._run_info = dict(run_info)
        self.scene = RobotScene(self.codec, calibration.anchors) if markers else None
        self._last_ns: int | None = None
        self.message_count = 0

    @property
    def closed(self) -> bool:
        return False

    def _emit(self, topic: str, ns: int, raw: bytes) -> None:
        """Hand one message on, logged at ``ns`` (robot-clock ns)."""
        raise NotImplementedError

    def _opened(self, ns: int) -> None:
        """The first message comes at ``ns`` (robot-clock ns)."""

    def _written(self, ns: int) -> None:
        """The messages up to ``ns`` (robot-clock ns) are handed on."""

    def _write(self, messages: Iterable[Encoded], t: float) -> None:
        if self.closed:
            raise RuntimeError(f"{self} is closed")
        ns = self.codec.stamp_ns(t)
        if self._last_ns is None:  # the header messages open the run, at its first time
            self._last_ns = ns
            self._opened(ns)
            self._write(self.codec.encode_header(self._calibration, self._run_info, t), t)
        ns = max(ns, self._last_ns)
        for topic, raw in messages:
            self._emit(topic, ns, raw)
            self.message_count += 1
        self._last_ns = ns
        self._written(ns)

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

    def write_scene(
        self,
        t: float,
        truth: GroundTruth | None,
        estimate: Estimate | None,
        goal: NDArray[float64] | None = None,
    ) -> None:
        """``/tf`` and ``/tensegrity/markers`` at ``t`` (s) (see :mod:`hardware.bag.scene`):
        the truth and the estimate where given, the goal point (m), (3,), where there is
        one. Nothing where the writer was made without markers."""
        if self.scene is not None:
            self._write(self.scene.encode(t, truth, estimate, goal), t)

    def write_innovation(self, t: float, nis: float) -> None:
        """The estimator's normalised innovation squared per measurement row at ``t``
        (s), on ``/estimate/nis``, with what viewers draw (nothing without markers)."""
        if self.scene is not None:
            self._write([self.codec.encode_float(m.NIS_TOPIC, nis)], t)


class BagWriter(MessageWriter):
    """Writes one run to a bag (see :class:`MessageWriter`). Use as a context manager,
    or call :meth:`close`.

    Args:
        path: the bag folder to create; it must not exist.
        description, calibration, run_info, clock_origin_ns, markers: as
            :class:`MessageWriter` takes them.
        flush_period: seconds of recorded time between flushes to disk.
        compress: compress each chunk with zstd (a quarter of the size, read as fast).
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
        markers: bool = True,
    ) -> None:
        if not flush_period > 0:
            raise ValueError(f"flush_period must be positive, got {flush_period}")
        super().__init__(
            description, calibration, run_info, clock_origin_ns=clock_origin_ns, markers=markers
        )
        self._flush_ns = seconds_to_ns(flush_period)
        self._writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:  # zstd per MCAP chunk, which every MCAP reader understands
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self.path = self._writer.path
        self._connections: dict[str, Connection] = {}
        self._last_flush_ns = 0

    def __str__(self) -> str:
        return f"the bag {self.path}"

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

    def _emit(self, topic: str, ns: int, raw: bytes) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            msgtype = self.codec.topics.types[topic]
            conn = self._writer.add_connection(topic, msgtype, typestore=self.codec.store)
            self._connections[topic] = conn
        self._writer.write(conn, ns, raw)

    def _opened(self, ns: int) -> None:
        self._last_flush_ns = ns

    def _written(self, ns: int) -> None:
        if ns - self._last_flush_ns >= self._flush_ns:
            self.flush()
            self._last_flush_ns = ns

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
