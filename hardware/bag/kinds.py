"""Sensor kinds, each declared once: its sample class, its topics and ROS types, its
encoder and decoder, its place in the canonical order and how its halves pair.

The codec, the sample assembler, the bag reader and writer, the emulator and the
driver all read this table (through a robot's :class:`TopicTable`); nothing else names
a sensor topic. A lab adds a kind of its own with :func:`register_sensor_kind`, before
it makes the codec, writer, reader or driver that should know it::

    register_sensor_kind(SensorKind(
        name="barometer", sample=BarometerSample, order=7,
        channels=(Channel("/barometer", "sensor_msgs/msg/FluidPressure"),),
        encode=encode_barometer, decode=decode_barometer,
    ))

A kind's channels are one topic each (``"/uwb/ranges"``), or one per rod
(``"/{rod}/imu/data_raw"``; the sample then has an integer ``rod``). A sample that
travels as two messages (an IMU's raw data and magnetometer, a colour and a depth
image) has two channels and a :class:`Pairing`: the halves meet on equal header stamps.

This module knows the codec only as :class:`CodecContext` (what encoders and decoders
may use), so that the codec can read the table without an import cycle. Encoders and
decoders go through its clock (``seconds``, ``stamp_ns``, ``header``): samples carry
seconds from the codec's clock origin, messages the robot's own stamps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from hardware.bag import messages as m
from tensegrity_gym.model.samples import (
    GROUND_TRUTH,
    SAMPLE_KINDS,
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    RgbdFrame,
    UwbRangeSample,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Sequence

    from numpy.typing import NDArray
    from rosbags.typesys.store import Typestore

    from tensegrity_gym.model.description import RobotDescription

__all__ = [
    "Channel",
    "CodecContext",
    "Pairing",
    "SensorKind",
    "TopicTable",
    "fixed_topic_types",
    "register_sensor_kind",
    "sample_kinds_of_topics",
    "sensor_kinds",
    "unregister_sensor_kind",
]

Decoded = tuple[int, Any]
"""(header stamp in ns, the sample, or for a paired kind the half a channel carries)."""


class CodecContext(Protocol):
    """What a kind's encoder and decoder may use of the robot's codec
    (:class:`hardware.bag.codec.RobotCodec`); decoders raise its ``MessageError``.
    Times ``t`` are sample times (s from the clock origin), stamps robot-clock ns."""

    description: RobotDescription
    store: Typestore
    rod_names: list[str]
    node_names: list[str]
    cable_names: list[str]
    actuated_names: list[str]
    origin_ns: int
    """Robot-clock ns of sample time 0."""

    def seconds(self, ns: int) -> float: ...
    def stamp_ns(self, t: float) -> int: ...
    def header(self, t: float, frame_id: str = "") -> Any: ...
    def imu(self, t: float, frame_id: str, **fields: Any) -> bytes: ...
    def magnetic_field(self, t: float, frame_id: str, field: Any) -> bytes: ...
    def serialize(self, msg: Any, msgtype: str) -> bytes: ...
    def deserialize(self, raw: m.Raw, msgtype: str) -> Any: ...
    def joint_state(self, t: float, names: Sequence[str], values: NDArray[np.float64]) -> bytes: ...
    def image(self, t: float, encoding: str, pixels: NDArray[Any], pixel_bytes: int) -> bytes: ...
    def decode_imu_raw(
        self, raw: m.Raw
    ) -> tuple[int, NDArray[np.float64], NDArray[np.float64]]: ...
    def decode_mag(self, raw: m.Raw) -> tuple[int, NDArray[np.float64]]: ...
    def decode_ahrs(self, raw: m.Raw) -> tuple[int, NDArray[np.float64]]: ...
    def decode_joint_state(self, raw: m.Raw, kind: str) -> tuple[int, NDArray[np.float64]]: ...
    def decode_uwb(self, raw: m.Raw) -> UwbRangeSample: ...
    def decode_contacts(self, raw: m.Raw) -> ContactSample: ...
    def decode_image(self, raw: m.Raw, kind: str) -> tuple[int, NDArray[Any]]: ...
    def make_frame(
        self, ns: int, rgb: NDArray[np.uint8], depth: NDArray[np.float32]
    ) -> RgbdFrame: ...


@dataclass(frozen=True)
class Channel:
    """One topic of a sensor kind."""

    pattern: str
    """The topic, ``"/uwb/ranges"``; ``{rod}`` stands for each rod's name."""
    msgtype: str
    """Its ROS 2 message type, ``"sensor_msgs/msg/Imu"`` (a type of :func:`messages.typestore`)."""
    doc: str = ""
    """What it carries, with units."""

    @property
    def per_rod(self) -> bool:
        return "{rod}" in self.pattern

    def topics(self, rod_names: Sequence[str]) -> list[str]:
        """The topic for each rod (a per-rod channel), or the one topic."""
        return [self.pattern.format(rod=r) for r in rod_names] if self.per_rod else [self.pattern]


@dataclass(frozen=True)
class Pairing:
    """How the two halves of a two-message sample become one (both stamped alike).

    Half of a pair waits (up to the caller's ``wait``) for its other half, and holds
    back the later halves of its rod meanwhile, so each stream stays in time order.
    """

    combine: Callable[[CodecContext, int, int, Any, Any], Any]
    """(codec, stamp ns, rod, first half, second half or None) -> the sample; raises
    MessageError when the halves do not fit together (counted ``undecodable``)."""
    lone_first: str | None = None
    """A first half whose second never came: skipped as ``unpaired`` for this reason;
    None: combined alone (``second`` None)."""
    lone_second: str | None = None
    """A second half whose first never came: skipped as ``unpaired`` for this reason;
    None: dropped without a count."""


@dataclass(frozen=True)
class SensorKind:
    """One kind of sample and everything about its messages (see the module docstring)."""

    name: str
    """Its name in :data:`tensegrity_gym.model.samples.SAMPLE_KINDS`, as estimators
    require it (``"uwb"``)."""
    sample: type
    """The dataclass; it has ``t`` (s), and ``rod`` (int) for a per-rod kind."""
    channels: tuple[Channel, ...]
    """One, or two for a paired kind (first half, second half)."""
    encode: Callable[[CodecContext, Any], list[bytes]]
    """(codec, sample) -> the CDR bytes of each channel's message, in channel order,
    stamped through the codec (``codec.header(sample.t)``, ``codec.stamp_ns``)."""
    decode: Callable[[CodecContext, int, int, m.Raw], Decoded]
    """(codec, channel index, rod index (0 for a fixed topic), CDR bytes) -> (stamp ns,
    the sample or its half); raises MessageError on bytes that do not fit the robot.
    The sample's time is ``codec.seconds(stamp)`` (s from the codec's clock origin)."""
    order: float
    """Place among samples with equal stamps (the simulator's order: imu 0 ... rgbd 6)."""
    pairing: Pairing | None = None
    marker: int = 0
    """The channel whose topic in a bag says the run has this kind."""

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise ValueError(f"sensor kind name {self.name!r} must be an identifier")
        if len(self.channels) != (2 if self.pairing is not None else 1):
            raise ValueError(
                f"sensor kind {self.name!r}: {len(self.channels)} channels; a kind has one, "
                "or two with a pairing"
            )
        if len({c.per_rod for c in self.channels}) != 1:
            raise ValueError(f"sensor kind {self.name!r}: channels mix per-rod and fixed topics")
        if not 0 <= self.marker < len(self.channels):
            raise ValueError(f"sensor kind {self.name!r}: marker {self.marker} is no channel")

    @property
    def per_rod(self) -> bool:
        return self.channels[0].per_rod


_KINDS: dict[str, SensorKind] = {}


def sensor_kinds() -> tuple[SensorKind, ...]:
    """Every registered kind, in canonical order."""
    return tuple(sorted(_KINDS.values(), key=lambda k: k.order))


def _check_new(kind: SensorKind) -> None:
    """ValueError where ``kind`` clashes with the registered kinds or fixed topics."""
    others = [k for k in _KINDS.values() if k.name != kind.name]
    known = SAMPLE_KINDS.get(kind.name, kind.sample)
    if kind.name not in _KINDS and known is not kind.sample:
        raise ValueError(f"sample kind {kind.name!r} is {known.__name__}, not {kind.sample}")
    taken = {c.pattern for k in others for c in k.channels} | set(m.FIXED_TOPICS)
    store = m.typestore()
    for channel in kind.channels:
        if not channel.pattern.startswith("/"):
            raise ValueError(f"topic {channel.pattern!r} must start with '/'")
        try:
            channel.pattern.format(rod="r")
        except (KeyError, IndexError, ValueError):
            raise ValueError(f"topic {channel.pattern!r}: only {{rod}} may be filled in") from None
        if channel.pattern in taken:
            raise ValueError(f"topic {channel.pattern!r} is already in the topic table")
        if channel.msgtype not in store.types:
            raise ValueError(f"{channel.pattern}: {channel.msgtype!r} is not a known ROS type")
    for k in others:
        if k.sample is kind.sample or k.order == kind.order:
            raise ValueError(f"sensor kind {kind.name!r} has the class or order of {k.name!r}")


def register_sensor_kind(kind: SensorKind, *, replace: bool = False) -> SensorKind:
    """Add ``kind`` to the table (and its name to ``SAMPLE_KINDS``); ``replace`` swaps a
    kind of the same name. Codecs made before do not see it."""
    if kind.name in _KINDS and not replace:
        raise ValueError(f"sensor kind {kind.name!r} is already registered")
    _check_new(kind)
    _KINDS[kind.name] = kind
    SAMPLE_KINDS[kind.name] = kind.sample
    return kind


def unregister_sensor_kind(name: str) -> None:
    """Remove a kind registered with :func:`register_sensor_kind` (not a built-in one)."""
    if name in _BUILT_IN:
        raise ValueError(f"{name!r} is a built-in sensor kind")
    if _KINDS.pop(name, None) is not None:
        SAMPLE_KINDS.pop(name, None)


# ---------------------------------------------------------------------- topic tables


def fixed_topic_types() -> dict[str, str]:
    """Topic -> type of every topic whose name does not depend on the robot."""
    types = {topic: msgtype for topic, (msgtype, _) in m.FIXED_TOPICS.items()}
    for kind in sensor_kinds():
        types.update({c.pattern: c.msgtype for c in kind.channels if not c.per_rod})
    return types


class TopicTable:
    """Every topic of one robot, from the kinds registered when it was made."""

    def __init__(self, description: RobotDescription) -> None:
        self.types: dict[str, str] = {t: msgtype for t, (msgtype, _) in m.FIXED_TOPICS.items()}
        """Topic -> message type: the fixed topics and every sensor topic."""
        self.routes: dict[str, tuple[SensorKind, int, int]] = {}
        """Sensor topic -> (its kind, channel index, rod index (0 for a fixed topic))."""
        self.kinds = sensor_kinds()
        """In canonical order."""
        rods = [rod.name for rod in description.rods]
        for kind in self.kinds:
            for c, channel in enumerate(kind.channels):
                for r, topic in enumerate(channel.topics(rods)):
                    self.types[topic] = channel.msgtype
                    self.routes[topic] = (kind, c, r)
        self._by_key = {(k.name, c, r): t for t, (k, c, r) in self.routes.items()}
        self._by_sample = {k.sample: k for k in self.kinds}

    def topic(self, kind: str, channel: int = 0, rod: int = 0) -> str:
        """The topic of a kind's channel (for rod ``rod`` where it has one per rod)."""
        return self._by_key[(kind, channel, rod)]

    def rod_topics(self, kind: str, channel: int = 0) -> list[str]:
        """A channel's topics, rod by rod (one for a fixed topic)."""
        return [t for t, (k, c, _) in self.routes.items() if (k.name, c) == (kind, channel)]

    def kind_of(self, sample: object) -> SensorKind:
        """The kind of ``sample``; TypeError if no kind in the table has its class."""
        kind = self._by_sample.get(type(sample))
        if kind is None:
            raise TypeError(f"no message for a sample of type {type(sample).__name__}")
        return kind


def sample_kinds_of_topics(topics: Iterable[str], description: RobotDescription) -> frozenset[str]:
    """The sample kinds (and ``"ground_truth"``) a set of topics carries."""
    present = set(topics)
    rods = [rod.name for rod in description.rods]
    kinds = {k.name for k in sensor_kinds() if present & set(k.channels[k.marker].topics(rods))}
    if m.TRUTH_STATE_TOPIC in present:
        kinds.add(GROUND_TRUTH)
    return frozenset(kinds)


# ---------------------------------------------------------------------- built-in kinds


def _encode_imu(ctx: CodecContext, s: ImuSample) -> list[bytes]:
    frame = ctx.rod_names[s.rod]
    return [ctx.imu(s.t, frame, gyro=s.gyro, accel=s.accel), ctx.magnetic_field(s.t, frame, s.mag)]


def _decode_imu(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> Decoded:
    if channel == 0:
        stamp, gyro, accel = ctx.decode_imu_raw(raw)
        return stamp, (gyro, accel)
    return ctx.decode_mag(raw)


def _combine_imu(ctx: CodecContext, ns: int, rod: int, raw: Any, mag: Any) -> ImuSample:
    """An ImuSample; no magnetometer message (``mag`` None) reads as NaN."""
    gyro, accel = raw
    field = mag if mag is not None else np.full(3, np.nan)
    return ImuSample(ctx.seconds(ns), rod, accel, gyro, field)


def _encode_ahrs(ctx: CodecContext, s: AhrsSample) -> list[bytes]:
    return [ctx.imu(s.t, ctx.rod_names[s.rod], orientation=s.quaternion)]


def _decode_ahrs(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> Decoded:
    stamp, quaternion = ctx.decode_ahrs(raw)
    return stamp, AhrsSample(ctx.seconds(stamp), rod, quaternion)


def _encode_encoders(ctx: CodecContext, s: EncoderSample) -> list[bytes]:
    return [ctx.joint_state(s.t, ctx.actuated_names, s.rest_lengths)]


def _decode_encoders(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> Decoded:
    stamp, values = ctx.decode_joint_state(raw, "actuated")
    return stamp, EncoderSample(ctx.seconds(stamp), values)


def _encode_cable_lengths(ctx: CodecContext, s: CableLengthSample) -> list[bytes]:
    return [ctx.joint_state(s.t, ctx.cable_names, s.lengths)]


def _decode_cable_lengths(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> Decoded:
    stamp, values = ctx.decode_joint_state(raw, "all")
    return stamp, CableLengthSample(ctx.seconds(stamp), values)


def _encode_uwb(ctx: CodecContext, s: UwbRangeSample) -> list[bytes]:
    types = ctx.store.types
    uwb_range, time = types["tensegrity_msgs/msg/UwbRange"], types["builtin_interfaces/msg/Time"]
    ranges = []
    for t, (i, j), r in zip(s.times, s.pairs, s.ranges, strict=True):
        sec, nanosec = divmod(ctx.stamp_ns(float(t)), 1_000_000_000)
        stamp = time(sec=sec, nanosec=nanosec)
        ranges.append(uwb_range(stamp=stamp, initiator=int(i), responder=int(j), range=float(r)))
    msg = types[m.UWB_RANGES](header=ctx.header(s.t), ranges=ranges)
    return [ctx.serialize(msg, m.UWB_RANGES)]


def _decode_uwb(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> Decoded:
    sample = ctx.decode_uwb(raw)
    return ctx.stamp_ns(sample.t), sample


def _encode_contacts(ctx: CodecContext, s: ContactSample) -> list[bytes]:
    msg = ctx.store.types[m.CONTACTS](
        header=ctx.header(s.t),
        nodes=list(ctx.node_names),
        in_contact=np.asarray(s.in_contact, dtype=np.bool_),
    )
    return [ctx.serialize(msg, m.CONTACTS)]


def _decode_contacts(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> Decoded:
    sample = ctx.decode_contacts(raw)
    return ctx.stamp_ns(sample.t), sample


def _encode_rgbd(ctx: CodecContext, s: RgbdFrame) -> list[bytes]:
    rgb = np.ascontiguousarray(s.rgb, dtype=np.uint8)
    depth = np.ascontiguousarray(s.depth, dtype="<f4")
    return [ctx.image(s.t, "rgb8", rgb, 3), ctx.image(s.t, "32FC1", depth, 4)]


def _decode_rgbd(ctx: CodecContext, channel: int, rod: int, raw: m.Raw) -> Decoded:
    return ctx.decode_image(raw, "color" if channel == 0 else "depth")


def _combine_rgbd(ctx: CodecContext, ns: int, rod: int, rgb: Any, depth: Any) -> RgbdFrame:
    return ctx.make_frame(ns, rgb, depth)


_BUILT_IN_KINDS = (
    SensorKind(
        "imu",
        ImuSample,
        (
            Channel("/{rod}/imu/data_raw", m.IMU, "accelerometer (m/s^2) and gyro (rad/s), body"),
            Channel("/{rod}/imu/mag", m.MAGNETIC_FIELD, "magnetometer (T), body frame"),
        ),
        _encode_imu,
        _decode_imu,
        order=0,
        pairing=Pairing(_combine_imu),
    ),
    SensorKind(
        "ahrs",
        AhrsSample,
        (Channel("/{rod}/imu/data", m.IMU, "the on-board AHRS orientation, body to world"),),
        _encode_ahrs,
        _decode_ahrs,
        order=1,
    ),
    SensorKind(
        "encoders",
        EncoderSample,
        (Channel("/motors/rest_lengths", m.JOINT_STATE, "rest lengths of actuated cables (m)"),),
        _encode_encoders,
        _decode_encoders,
        order=2,
    ),
    SensorKind(
        "cable_lengths",
        CableLengthSample,
        (Channel("/cables/lengths", m.JOINT_STATE, "cable-length sensors: every cable (m)"),),
        _encode_cable_lengths,
        _decode_cable_lengths,
        order=3,
    ),
    SensorKind(
        "contacts",
        ContactSample,
        (Channel("/contacts", m.CONTACTS, "endcap-ground contact flags"),),
        _encode_contacts,
        _decode_contacts,
        order=4,
    ),
    SensorKind(
        "uwb",
        UwbRangeSample,
        (Channel("/uwb/ranges", m.UWB_RANGES, "one UWB broadcast round"),),
        _encode_uwb,
        _decode_uwb,
        order=5,
    ),
    SensorKind(
        "rgbd",
        RgbdFrame,
        (
            Channel("/camera/color/image_raw", m.IMAGE, "RGB frame, rgb8"),
            Channel("/camera/depth/image_raw", m.IMAGE, "depth, 32FC1 metres, 0: no return"),
        ),
        _encode_rgbd,
        _decode_rgbd,
        order=6,
        pairing=Pairing(_combine_rgbd, lone_first="no depth image", lone_second="no colour image"),
        marker=1,
    ),
)
for _kind in _BUILT_IN_KINDS:
    register_sensor_kind(_kind)
_BUILT_IN = frozenset(k.name for k in _BUILT_IN_KINDS)
