"""Messages of a robot's topics in, typed samples out: shared by the bag reader and the
robot link.

A :class:`SampleAssembler` decodes each message as it comes (:meth:`add`), checks its
header stamp against the others on its topic, and buffers it; :meth:`take` pairs what
travels as two messages (an IMU's raw data and magnetometer, a colour and a depth
image, ground-truth state and rod poses) and hands out the samples in canonical order
(time, then sensor, then rod), which is the simulator's own order.

Two rules for stamps that do not increase on a topic:

- ``"strict"`` (a log, where order is the recording's): a stamp not after the previous
  message on its topic is skipped, as ``duplicate`` or ``out_of_order``.
- ``"sort"`` (a network link, where packets overtake each other): a message older than
  what was already handed out on its topic is skipped as ``late``; one whose stamp is
  already buffered or handed out is a ``duplicate``; the rest is sorted, and the ones
  that arrived behind a newer message are counted as ``reordered``.

Every skip goes to the ``on_skip`` callback with its kind, topic, stamp and reason.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from hardware.bag.codec import MessageError, RobotCodec
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    RgbdFrame,
    UwbRangeSample,
    ns_to_seconds,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from collections.abc import Callable

    from hardware.bag.codec import Raw
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["Assembled", "SampleAssembler", "header_stamp"]

log = logging.getLogger(__name__)

# Canonical order of samples that share a time stamp: the simulator's sensor order.
_KIND_ORDER = {
    ImuSample: 0,
    AhrsSample: 1,
    EncoderSample: 2,
    CableLengthSample: 3,
    ContactSample: 4,
    UwbRangeSample: 5,
    RgbdFrame: 6,
}
CLOCK_JUMP_RUN = 50
"""Late messages in a row on one topic that are taken as its source's clock jumping."""
COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
TRUTH_STATE_TOPIC = "/ground_truth/state"
TRUTH_POSES_TOPIC = "/ground_truth/rod_poses"


def header_stamp(raw: Raw) -> int:
    """The header stamp (ns) of any message that starts with a std_msgs/Header."""
    if len(raw) < 12:
        raise MessageError(f"{len(raw)} bytes cannot hold a header")
    return int.from_bytes(raw[4:8], "little", signed=True) * 1_000_000_000 + int.from_bytes(
        raw[8:12], "little"
    )


@dataclass
class Assembled:
    """What :meth:`SampleAssembler.take` hands out."""

    samples: list[Sample]
    """In canonical order."""
    truth: GroundTruth | None
    """The newest ground truth among those taken, where the source has one."""
    estimate: Estimate | None
    """The newest estimate among those taken (a log's recorded output)."""


@dataclass
class _Pending:
    """Half of a pair waiting for its other half: (stamp, rod) -> (value, arrival)."""

    items: dict[tuple[int, int], tuple[Any, float]] = field(default_factory=dict)


class SampleAssembler:
    """Decodes one robot's messages into samples; see the module docstring.

    Args:
        codec: the robot's codec.
        on_skip: called with (kind, topic, stamp in ns or None, reason) for each
            message skipped.
        order: ``"strict"`` or ``"sort"``.
    """

    def __init__(
        self,
        codec: RobotCodec,
        on_skip: Callable[[str, str, int | None, str], None],
        order: Literal["strict", "sort"] = "strict",
    ) -> None:
        self.codec = codec
        self.on_skip = on_skip
        self.order = order
        self.reordered = 0
        """Messages accepted behind a newer one on their topic and sorted (``"sort"``)."""
        self.clock_jumps = 0
        """Topics started afresh after CLOCK_JUMP_RUN late messages in a row."""
        self._late_run: dict[str, int] = {}
        self._floor: dict[str, int] = {}  # stamps at or below are refused
        self._buffered: dict[str, set[int]] = {}  # "sort": stamps waiting, per topic
        self._newest: dict[str, int] = {}
        self._samples: list[tuple[Sample, str, int]] = []
        self._imu = _Pending()
        self._mag = _Pending()
        self._color = _Pending()
        self._depth = _Pending()
        self._truth_state = _Pending()
        self._truth_poses = _Pending()
        self._estimate: Estimate | None = None

    # ------------------------------------------------------------------ order

    def accept(self, topic: str, stamp: int, partner_waiting: bool = False) -> bool:
        """Whether a message stamped ``stamp`` (ns) on ``topic`` is taken, by the rule.
        ``partner_waiting``: the other half of its pair is buffered, so in ``"sort"``
        mode it is not late whatever was handed out since."""
        floor = self._floor.get(topic)
        if self.order == "strict":
            if floor is not None and stamp <= floor:
                kind = "duplicate" if stamp == floor else "out_of_order"
                why = f"stamp {ns_to_seconds(stamp):.9f} s after {ns_to_seconds(floor):.9f} s"
                self.on_skip(kind, topic, stamp, why)
                return False
            self._floor[topic] = stamp
            return True
        waiting = self._buffered.setdefault(topic, set())
        if stamp in waiting or (floor is not None and stamp == floor):
            self.on_skip("duplicate", topic, stamp, "a message with this stamp came before")
            return False
        if floor is not None and stamp < floor and not partner_waiting:
            why = f"stamp {ns_to_seconds(stamp):.9f} s; {ns_to_seconds(floor):.9f} s was handed out"
            self.on_skip("late", topic, stamp, why)
            run = self._late_run[topic] = self._late_run.get(topic, 0) + 1
            if run >= CLOCK_JUMP_RUN:
                # Everything on the topic is "late": the source's clock went back (or
                # one message came from far in the future). Start the topic afresh.
                log.warning("%s: %d late messages in a row; its clock jumped back", topic, run)
                self.clock_jumps += 1
                self._floor.pop(topic, None)
                self._newest.pop(topic, None)
                self._late_run[topic] = 0
            return False
        self._late_run[topic] = 0
        newest = self._newest.get(topic)
        if newest is not None and stamp < newest:
            self.reordered += 1
        else:
            self._newest[topic] = stamp
        waiting.add(stamp)
        return True

    # ------------------------------------------------------------------ input

    def add(self, topic: str, raw: Raw, arrival: float = 0.0, at_ns: int | None = None) -> bool:
        """Decode and buffer one message of a sensor, ground-truth or estimate topic
        (commands and the header topics are the caller's). ``arrival`` is when it came
        (any clock, seconds), which :meth:`take` uses to decide how long half a pair
        waits for the other half; ``at_ns`` is the time a skip is reported at. True if
        it was a sensor message and was taken."""
        codec, topics = self.codec, self.codec.topics
        try:
            if topic in topics.imu_raw:
                stamp, gyro, accel = codec.decode_imu_raw(raw)
                key = (stamp, topics.imu_raw[topic])
                if self.accept(topic, stamp, key in self._mag.items):
                    self._imu.items[key] = ((gyro, accel), arrival)
                    return True
            elif topic in topics.imu_mag:
                stamp, mag = codec.decode_mag(raw)
                key = (stamp, topics.imu_mag[topic])
                if self.accept(topic, stamp, key in self._imu.items):
                    self._mag.items[key] = (mag, arrival)
                    return True
            elif topic in topics.ahrs:
                stamp, quat = codec.decode_ahrs(raw)
                if self.accept(topic, stamp):
                    self._push(codec.make_ahrs(stamp, topics.ahrs[topic], quat), topic, stamp)
                    return True
            elif topic == "/motors/rest_lengths":
                stamp, values = codec.decode_joint_state(raw, "actuated")
                if self.accept(topic, stamp):
                    self._push(codec.make_encoder(stamp, values), topic, stamp)
                    return True
            elif topic == "/cables/lengths":
                stamp, values = codec.decode_joint_state(raw, "all")
                if self.accept(topic, stamp):
                    self._push(codec.make_cable_lengths(stamp, values), topic, stamp)
                    return True
            elif topic == "/uwb/ranges":
                uwb = codec.decode_uwb(raw)
                stamp = seconds_to_ns(uwb.t)
                if self.accept(topic, stamp):
                    self._push(uwb, topic, stamp)
                    return True
            elif topic == "/contacts":
                contact = codec.decode_contacts(raw)
                stamp = seconds_to_ns(contact.t)
                if self.accept(topic, stamp):
                    self._push(contact, topic, stamp)
                    return True
            elif topic == COLOR_TOPIC:
                stamp, image = codec.decode_image(raw, "color")
                if self.accept(topic, stamp, (stamp, 0) in self._depth.items):
                    self._color.items[(stamp, 0)] = (image, arrival)
                    return True
            elif topic == DEPTH_TOPIC:
                stamp, image = codec.decode_image(raw, "depth")
                if self.accept(topic, stamp, (stamp, 0) in self._color.items):
                    self._depth.items[(stamp, 0)] = (image, arrival)
                    return True
            elif topic == TRUTH_STATE_TOPIC:
                self._truth_state.items[(header_stamp(raw), 0)] = (bytes(raw), arrival)
            elif topic == TRUTH_POSES_TOPIC:
                self._truth_poses.items[(header_stamp(raw), 0)] = (bytes(raw), arrival)
            elif topic == "/estimate/state":
                self._estimate = codec.decode_estimate(raw)
            # /estimate/rod_poses is for viewers; the state holds everything.
        except MessageError as err:
            self.on_skip("undecodable", topic, at_ns, str(err))
        return False

    def _push(self, sample: Sample, topic: str, stamp: int) -> None:
        self._samples.append((sample, topic, stamp))

    # ------------------------------------------------------------------ output

    def take(self, now: float = 0.0, wait: float = 0.0) -> Assembled:
        """Everything buffered, paired and in canonical order.

        Half of a pair that arrived less than ``wait`` seconds before ``now`` (the
        clock of :meth:`add`'s ``arrival``) stays for the next call, in case its other
        half is still on its way; an older IMU message without its magnetometer reads
        NaN there, and an older lone image or ground-truth half is skipped as
        ``unpaired``.
        """
        codec = self.codec
        handed: list[tuple[Sample, str, int]] = self._samples
        self._samples = []
        young = now - wait

        def ripe(item: tuple[Any, float]) -> bool:
            return wait <= 0.0 or item[1] <= young

        # A half still waiting for its other half holds back the later samples of its
        # stream, so that each stream is handed out in time order across calls.
        held: dict[int, int] = {}  # rod -> oldest waiting stamp
        for (stamp, rod), entry in [*self._imu.items.items(), *self._mag.items.items()]:
            if (stamp, rod) not in self._imu.items or (stamp, rod) not in self._mag.items:
                if not ripe(entry) and stamp < held.get(rod, stamp + 1):
                    held[rod] = stamp
        for key in sorted(self._imu.items):
            entry = self._imu.items[key]
            mag = self._mag.items.get(key)
            if key[1] in held and key[0] > held[key[1]]:
                continue
            if mag is None and not ripe(entry):
                continue
            del self._imu.items[key]
            stamp, rod = key
            if mag is not None:
                del self._mag.items[key]
                self._release(codec.imu_topics[rod][1], stamp)
            gyro, accel = entry[0]
            field = None if mag is None else mag[0]
            topic = codec.imu_topics[rod][0]
            handed.append((codec.make_imu(stamp, rod, gyro, accel, field), topic, stamp))
        for key in [k for k, v in self._mag.items.items() if ripe(v) and k not in self._imu.items]:
            # A magnetometer reading without its IMU message carries nothing usable.
            del self._mag.items[key]
            self._release(codec.imu_topics[key[1]][1], key[0])
        waiting = [
            k[0]
            for half, other in ((self._color, self._depth), (self._depth, self._color))
            for k, v in half.items.items()
            if k not in other.items and not ripe(v)
        ]
        frames_until = min(waiting, default=None)
        for key in sorted(self._color.items):
            if frames_until is not None and key[0] > frames_until:
                break
            if key in self._depth.items:
                rgb, depth = self._color.items.pop(key)[0], self._depth.items.pop(key)[0]
                try:
                    frame = codec.make_frame(key[0], rgb, depth)
                except MessageError as err:
                    self.on_skip("undecodable", DEPTH_TOPIC, key[0], str(err))
                    continue
                handed.append((frame, COLOR_TOPIC, key[0]))
                self._release(DEPTH_TOPIC, key[0])
        for pending, partner, topic, other in (
            (self._color, self._depth, COLOR_TOPIC, "no depth image"),
            (self._depth, self._color, DEPTH_TOPIC, "no colour image"),
        ):
            for key in [k for k, v in pending.items.items() if ripe(v) and k not in partner.items]:
                del pending.items[key]
                self.on_skip("unpaired", topic, key[0], other)
                self._release(topic, key[0])
        truth = None
        for key in sorted(self._truth_state.items):
            if key not in self._truth_poses.items:
                if ripe(self._truth_state.items[key]):
                    del self._truth_state.items[key]
                    self.on_skip("unpaired", TRUTH_STATE_TOPIC, key[0], "no rod poses")
                continue
            state = self._truth_state.items.pop(key)[0]
            poses = self._truth_poses.items.pop(key)[0]
            try:
                truth = codec.decode_truth(state, poses)
            except MessageError as err:
                self.on_skip("undecodable", TRUTH_STATE_TOPIC, key[0], str(err))
        for key in [k for k, v in self._truth_poses.items.items() if ripe(v)]:
            del self._truth_poses.items[key]
        for _, topic, stamp in handed:
            self._release(topic, stamp)
        handed.sort(key=lambda h: (h[0].t, _KIND_ORDER[type(h[0])], getattr(h[0], "rod", 0)))
        estimate, self._estimate = self._estimate, None
        return Assembled([h[0] for h in handed], truth, estimate)

    def _release(self, topic: str, stamp: int) -> None:
        """``"sort"``: a message handed out (or given up) on ``topic`` raises its floor."""
        if self.order != "sort":
            return
        self._buffered.get(topic, set()).discard(stamp)
        if stamp > self._floor.get(topic, -1):
            self._floor[topic] = stamp
