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

from hardware.bag import messages as m
from hardware.bag.codec import MessageError, RobotCodec
from tensegrity_gym.model.samples import ns_to_seconds

if TYPE_CHECKING:
    from collections.abc import Callable

    from hardware.bag.kinds import SensorKind
    from hardware.bag.messages import Raw
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["Assembled", "SampleAssembler", "header_stamp"]

log = logging.getLogger(__name__)

CLOCK_JUMP_RUN = 50
"""Late messages in a row on one topic that are taken as its source's clock jumping."""


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
        kinds = codec.topics.kinds
        self._order = {k.sample: k.order for k in kinds}  # within a stamp: the table's
        self._halves = {k.name: (_Pending(), _Pending()) for k in kinds if k.pairing is not None}
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
        route = self.codec.topics.routes.get(topic)
        try:
            if route is not None:
                return self._add_sensor(route, topic, raw, arrival)
            if topic == m.TRUTH_STATE_TOPIC:
                self._truth_state.items[(header_stamp(raw), 0)] = (bytes(raw), arrival)
            elif topic == m.TRUTH_POSES_TOPIC:
                self._truth_poses.items[(header_stamp(raw), 0)] = (bytes(raw), arrival)
            elif topic == m.ESTIMATE_STATE_TOPIC:
                self._estimate = self.codec.decode_estimate(raw)
            # /estimate/rod_poses is for viewers; the state holds everything.
        except MessageError as err:
            self.on_skip("undecodable", topic, at_ns, str(err))
        return False

    def _add_sensor(
        self, route: tuple[SensorKind, int, int], topic: str, raw: Raw, arrival: float
    ) -> bool:
        """A message of a sensor kind's channel: a sample, or half of one, buffered."""
        kind, channel, rod = route
        stamp, value = kind.decode(self.codec, channel, rod, raw)
        if kind.pairing is None:
            if not self.accept(topic, stamp):
                return False
            self._samples.append((value, topic, stamp))
            return True
        mine, other = self._halves[kind.name][channel], self._halves[kind.name][1 - channel]
        key = (stamp, rod)
        if not self.accept(topic, stamp, key in other.items):
            return False
        mine.items[key] = (value, arrival)
        return True

    # ------------------------------------------------------------------ output

    def take(self, now: float = 0.0, wait: float = 0.0) -> Assembled:
        """Everything buffered, paired and in canonical order.

        Half of a pair that arrived less than ``wait`` seconds before ``now`` (the
        clock of :meth:`add`'s ``arrival``) stays for the next call, in case its other
        half is still on its way; an older IMU message without its magnetometer reads
        NaN there, and an older lone image or ground-truth half is skipped as
        ``unpaired``.
        """
        handed: list[tuple[Sample, str, int]] = self._samples
        self._samples = []
        young = now - wait

        def ripe(item: tuple[Any, float]) -> bool:
            return wait <= 0.0 or item[1] <= young

        for kind in self.codec.topics.kinds:
            if kind.pairing is not None:
                self._take_pairs(kind, ripe, handed)
        truth = None
        for key in sorted(self._truth_state.items):
            if key not in self._truth_poses.items:
                if ripe(self._truth_state.items[key]):
                    del self._truth_state.items[key]
                    self.on_skip("unpaired", m.TRUTH_STATE_TOPIC, key[0], "no rod poses")
                continue
            state = self._truth_state.items.pop(key)[0]
            poses = self._truth_poses.items.pop(key)[0]
            try:
                truth = self.codec.decode_truth(state, poses)
            except MessageError as err:
                self.on_skip("undecodable", m.TRUTH_STATE_TOPIC, key[0], str(err))
        for key in [k for k, v in self._truth_poses.items.items() if ripe(v)]:
            del self._truth_poses.items[key]
        for _, topic, stamp in handed:
            self._release(topic, stamp)
        order = self._order
        handed.sort(key=lambda h: (h[0].t, order[type(h[0])], getattr(h[0], "rod", 0)))
        estimate, self._estimate = self._estimate, None
        return Assembled([h[0] for h in handed], truth, estimate)

    def _take_pairs(
        self,
        kind: SensorKind,
        ripe: Callable[[tuple[Any, float]], bool],
        handed: list[tuple[Sample, str, int]],
    ) -> None:
        """The samples of a paired kind whose halves are both in, or that waited long
        enough, into ``handed``; lone halves that waited long enough are given up."""
        assert kind.pairing is not None
        pairing, topics = kind.pairing, self.codec.topics
        first, second = self._halves[kind.name]
        # A half still waiting for its other half holds back the later samples of its
        # rod, so that each stream is handed out in time order across calls.
        held: dict[int, int] = {}  # rod -> oldest waiting stamp
        for (stamp, rod), entry in [*first.items.items(), *second.items.items()]:
            if (stamp, rod) not in first.items or (stamp, rod) not in second.items:
                if not ripe(entry) and stamp < held.get(rod, stamp + 1):
                    held[rod] = stamp
        for key in sorted(first.items):
            stamp, rod = key
            other = second.items.get(key)
            if rod in held and stamp > held[rod]:
                continue
            if other is None and (pairing.lone_first is not None or not ripe(first.items[key])):
                continue
            value = first.items.pop(key)[0]
            if other is not None:
                del second.items[key]
            try:
                second_value = None if other is None else other[0]
                sample = pairing.combine(self.codec, stamp, rod, value, second_value)
            except MessageError as err:
                self.on_skip("undecodable", topics.topic(kind.name, 1, rod), stamp, str(err))
                continue
            if other is not None:
                self._release(topics.topic(kind.name, 1, rod), stamp)
            handed.append((sample, topics.topic(kind.name, 0, rod), stamp))
        for channel, (half, partner, reason) in enumerate(
            ((first, second, pairing.lone_first), (second, first, pairing.lone_second))
        ):
            if channel == 0 and reason is None:
                continue  # combined alone above
            for key in [k for k, v in half.items.items() if ripe(v) and k not in partner.items]:
                del half.items[key]
                topic = topics.topic(kind.name, channel, key[1])
                if reason is not None:
                    self.on_skip("unpaired", topic, key[0], reason)
                self._release(topic, key[0])

    def _release(self, topic: str, stamp: int) -> None:
        """``"sort"``: a message handed out (or given up) on ``topic`` raises its floor."""
        if self.order != "sort":
            return
        self._buffered.get(topic, set()).discard(stamp)
        if stamp > self._floor.get(topic, -1):
            self._floor[topic] = stamp
