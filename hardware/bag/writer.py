"""Writing a run to a ROS 2 bag (MCAP storage), crash-safe.

A bag is a folder holding ``<name>.mcap`` and, once closed, ``metadata.yaml``. MCAP
stores messages in chunks; the writer closes a chunk and hands it to the operating
system every ``flush_period`` seconds of recorded time, so a process that dies (a
crash, SIGKILL) leaves every message up to the last flush on disk, and
:class:`hardware.bag.reader.BagReader` opens such a bag. Ctrl-C and SIGTERM close the
bag properly (see :func:`agents.cli.errors.terminate`).

Times given to the writer are sample times (s from the source's clock origin); header
stamps and log times are ``clock_origin_ns`` plus them, the robot's own clock, so a
replayed bag recorded again has its original stamps.

What ROS viewers draw (``/tf``, ``/tensegrity/markers``: :mod:`hardware.bag.scene`) is
written by :meth:`MessageWriter.write_scene` where the writer was made with
``markers=True``; ``/tf_static`` then follows the header, once. The header topics and
``/tf_static`` are recorded latched (transient local: :data:`messages.LATCHED_QOS`),
as ROS 2 publishes them, so ``ros2 bag play`` hands them to late subscribers.
:class:`MessageWriter` is the part every run's stream shares, the bag and the live
view (:mod:`hardware.viewer`): the header first, then messages in time order.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import yaml
from mcap.writer import CompressionType, Writer

from hardware.bag import messages as m
from hardware.bag.codec import RobotCodec
from hardware.bag.scene import RobotScene
from tensegrity_gym.model.samples import seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping
    from types import TracebackType

    from numpy import float64
    from numpy.typing import NDArray
    from rosbags.interfaces import Qos

    from hardware.bag.codec import Encoded
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import SensorCalibration
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["BagWriter", "MessageWriter", "qos_dicts"]

log = logging.getLogger(__name__)

CHUNK_SIZE = 1 << 20
"""Bytes of records at which a chunk closes between flushes (rosbags' and ROS 2's size)."""


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
        markers: encode :meth:`write_scene`'s ``/tf`` and ``/tensegrity/markers``, and
            ``/tf_static`` after the header; False: none of them.
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
            header = self.codec.encode_header(self._calibration, self._run_info, t)
            if self.scene is not None:  # the fixed frames, once, as a latched topic is
                header = [*header, *self.scene.encode_static(t, self._calibration.camera_pose)]
            self._write(header, t)
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


def qos_dicts(profiles: Iterable[Qos]) -> list[dict[str, Any]]:
    """QoS profiles as ROS 2 (Jazzy, bag version 9) writes them in ``metadata.yaml``."""
    return [
        {
            "history": q.history.name.lower(),
            "depth": q.depth,
            "reliability": q.reliability.name.lower(),
            "durability": q.durability.name.lower(),
            "deadline": {"sec": q.deadline.sec, "nsec": q.deadline.nsec},
            "lifespan": {"sec": q.lifespan.sec, "nsec": q.lifespan.nsec},
            "liveliness": q.liveliness.name.lower(),
            "liveliness_lease_duration": {
                "sec": q.liveliness_lease_duration.sec,
                "nsec": q.liveliness_lease_duration.nsec,
            },
            "avoid_ros_namespace_conventions": q.avoid_ros_namespace_conventions,
        }
        for q in profiles
    ]


@dataclass
class _Topic:
    """One recorded topic: its MCAP channel and what ``metadata.yaml`` says of it."""

    channel: int
    msgtype: str
    digest: str
    qos: list[dict[str, Any]]
    count: int = 0


class BagWriter(MessageWriter):
    """Writes one run to a bag (see :class:`MessageWriter`). Use as a context manager,
    or call :meth:`close`.

    The ``.mcap`` file is written with mcap's own writer in the ``ros2`` profile, as
    ``ros2 bag record`` writes it: a ``ros2msg`` schema per message type, a ``cdr``
    channel per topic with its ``offered_qos_profiles`` in the channel's metadata;
    ``metadata.yaml`` (bag version 9) follows at :meth:`close`.

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
        self.path = Path(path)
        try:
            self.path.mkdir(parents=True)
        except FileExistsError:
            raise FileExistsError(
                f"{self.path}: exists; a bag is written to a new folder"
            ) from None
        self._file: BinaryIO | None = (self.path / f"{self.path.name}.mcap").open("xb")
        # zstd per MCAP chunk, which every MCAP reader understands
        compression = CompressionType.ZSTD if compress else CompressionType.NONE
        self._mcap = Writer(self._file, chunk_size=CHUNK_SIZE, compression=compression)
        self._mcap.start(profile="ros2", library="tensegrity-gym")
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _Topic] = {}
        self._first_ns: int | None = None
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
        return self._file is None

    def _topic(self, name: str) -> _Topic:
        """The channel of topic ``name``, registered (with its schema) on first use."""
        msgtype = self.codec.topics.types[name]
        schema = self._schemas.get(msgtype)
        if schema is None:
            msgdef, _ = self.codec.store.generate_msgdef(msgtype, ros_version=2)
            schema = self._mcap.register_schema(msgtype, "ros2msg", msgdef.encode())
            self._schemas[msgtype] = schema
        qos = qos_dicts([m.LATCHED_QOS] if name in m.LATCHED_TOPICS else [])
        meta = {"offered_qos_profiles": yaml.safe_dump(qos).strip()}
        channel = self._mcap.register_channel(name, "cdr", schema, meta)
        digest = self.codec.store.hash_rihs01(msgtype)
        topic = self._topics[name] = _Topic(channel, msgtype, digest, qos)
        return topic

    def _emit(self, topic: str, ns: int, raw: bytes) -> None:
        t = self._topics.get(topic) or self._topic(topic)
        self._mcap.add_message(t.channel, ns, raw, ns)
        t.count += 1

    def _opened(self, ns: int) -> None:
        self._last_flush_ns = self._first_ns = ns

    def _written(self, ns: int) -> None:
        if ns - self._last_flush_ns >= self._flush_ns:
            self.flush()
            self._last_flush_ns = ns

    def flush(self) -> None:
        """Close the pending MCAP chunk and hand it to the operating system: what bounds
        the loss on a crash (checked by tests/hardware/test_bag.py)."""
        if not self.closed:
            self._mcap.flush()  # type: ignore[no-untyped-call]

    def close(self) -> None:
        """Write the index and ``metadata.yaml``. Safe to call twice."""
        if self._file is None:
            return
        if self._last_ns is None:  # nothing written: still a valid bag with its header
            self._write([], 0.0)
        info = self._info()
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": yaml.safe_dump(info)})
        self._mcap.finish()  # type: ignore[no-untyped-call]
        self._file.close()
        self._file = None
        tmp = self.path / "metadata.yaml.tmp"
        tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}), "utf8")
        tmp.replace(self.path / "metadata.yaml")
        log.debug("closed %s: %d messages", self.path, self.message_count)

    def _info(self) -> dict[str, Any]:
        """The bag's ``rosbag2_bagfile_information`` (version 9), as rosbags writes it."""
        start = self._first_ns or 0
        duration = {"nanoseconds": max(0, (self._last_ns or 0) - start)}
        starting = {"nanoseconds_since_epoch": start}
        name = f"{self.path.name}.mcap"
        topics = [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": t.msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": t.qos,
                    "type_description_hash": t.digest,
                },
                "message_count": t.count,
            }
            for topic, t in self._topics.items()
        ]
        count = self.message_count
        return {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [name],
            "duration": duration,
            "starting_time": starting,
            "message_count": count,
            "topics_with_message_count": topics,
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": name,
                    "starting_time": starting,
                    "duration": duration,
                    "message_count": count,
                }
            ],
            "custom_data": None,
            "ros_distro": "rosbags",  # what rosbags writes: no ROS distribution wrote it
        }
