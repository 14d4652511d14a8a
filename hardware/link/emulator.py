"""A stand-in for the real robot: the simulated robot served over the robot wire in real
time, with the timing faults of a real network and real sensors.

The emulator steps the PyBullet robot in ticks of 10 ms of wall-clock time, applies the
newest rest-length command, and publishes every sample as its ROS 2 message, stamped
with the robot's clock (wall-clock time, as a robot synchronised by NTP or PTP stamps).
Faults (:class:`FaultModel`) act on the sensor messages: latency and jitter, packet
loss, reordering, and dropouts in which one sensor stream goes quiet for a while.
Like a robot's firmware, it holds its motors (targets = present rest lengths) before the
first heartbeat and whenever heartbeats stop for longer than the watchdog timeout, and
it obeys only the session that took its motors (:class:`~hardware.link.ownership.MotorOwner`):
the commands and heartbeats of another are refused, counted and logged. With a security
file (``--security``) it listens with TLS and refuses peers without the lab's
credentials; the command line logs each refusal (:func:`~hardware.link.security.forward_zenoh_log`).
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import logging
import math
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hardware.bag.codec import MessageError, RobotCodec
from hardware.link.ownership import MotorOwner, frame_id_of
from hardware.link.safety import check_fields
from hardware.link.security import forward_zenoh_log
from hardware.link.wire import COMMAND_TOPIC, HEARTBEAT_TOPIC, LinkAddress, LinkError, open_session
from tensegrity_gym.model.samples import seconds_to_ns
from tensegrity_gym.sim.backend import SimBackend

if TYPE_CHECKING:
    from collections.abc import Collection, Sequence

    from numpy.typing import NDArray

    from hardware.bag.kinds import TopicTable
    from hardware.link.safety import Watchdog
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.samples import Sample

__all__ = ["Emulator", "EmulatorStats", "FaultModel"]

log = logging.getLogger(__name__)

TICK = 0.01
"""Seconds of robot time per emulator tick (commands take effect at tick boundaries)."""
HEADER_PERIOD = 1.0
"""Seconds between republications of the description, calibration and camera info."""


@dataclass(frozen=True)
class FaultModel:
    """Timing faults applied to each sensor message.

    Attributes:
        latency: fixed delay (s) before a message is published.
        jitter: extra delay drawn uniformly from [0, jitter] (s), per message.
        loss: probability that a message is never published.
        reorder: probability that a message is held back by ``reorder_delay`` more, so
            that later ones overtake it.
        reorder_delay: seconds a reordered message is held back.
        dropout_rate: per stream and second, the rate at which a stream (one rod's IMU,
            the encoders, the UWB, ...) goes quiet.
        dropout_duration: seconds a dropout lasts.
    """

    latency: float = 0.0
    jitter: float = 0.0
    loss: float = 0.0
    reorder: float = 0.0
    reorder_delay: float = 0.02
    dropout_rate: float = 0.0
    dropout_duration: float = 0.5

    def __post_init__(self) -> None:
        names = ("latency", "jitter", "reorder_delay", "dropout_rate", "dropout_duration")
        check_fields(self, names, positive=False)
        for name in ("loss", "reorder"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"FaultModel.{name}={value!r} must be a probability in [0, 1]")

    @property
    def delays(self) -> bool:
        return self.latency > 0 or self.jitter > 0 or self.reorder > 0


@dataclass
class EmulatorStats:
    ticks: int = 0
    published: int = 0
    lost: int = 0
    reordered: int = 0
    dropped_in_dropout: int = 0
    commands: int = 0
    """Commands kept: the owner's, or any session's while nobody owns the motors (those
    move nothing unless their session takes the motors before the next tick)."""
    bad_commands: int = 0
    refused_commands: int = 0
    """Commands of a session that does not own the motors, or of none."""
    heartbeats: int = 0
    refused_heartbeats: int = 0
    """Heartbeats of a session that does not own the motors, or of none."""
    watchdog_trips: int = 0
    overruns: int = 0
    """Ticks that started late because the previous one took longer than a tick."""


def sensor_streams(topics: TopicTable, rod_names: Sequence[str]) -> dict[str, str]:
    """Sensor topic -> the stream it belongs to; a dropout silences a whole stream.

    A rod's topics are one stream (its board: IMU and AHRS), named by the rod; the two
    topics of a paired kind are one, named by their first path segment (``camera``);
    any other topic is a stream of its own."""
    streams = {}
    for topic, (kind, _, rod) in topics.routes.items():
        if kind.per_rod:
            streams[topic] = rod_names[rod]
        elif kind.pairing is not None:
            streams[topic] = kind.channels[0].pattern.strip("/").split("/")[0]
        else:
            streams[topic] = topic
    return streams


class Emulator:
    """Serves the simulated robot at ``address`` (see the module docstring).

    Args:
        description: the robot.
        address: where to listen (``LinkAddress``; its prefix namespaces the topics).
        faults: timing faults on the sensor messages.
        seed: seeds the simulation's randomness and the faults.
        camera: render and publish RGB-D frames at the camera's rate.
        truth: publish ground truth (as a motion-capture system would) every tick.
        watchdog_timeout: seconds without a heartbeat after which the motors hold.
        muted: topics never published (a sensor missing or switched off: ``/uwb/ranges``
            for a robot whose anchors are off).
    """

    def __init__(
        self,
        description: RobotDescription,
        address: LinkAddress,
        *,
        faults: FaultModel | None = None,
        seed: int = 0,
        camera: bool = False,
        truth: bool = True,
        watchdog_timeout: float = 0.15,
        muted: Collection[str] = (),
    ) -> None:
        self.description = description
        self.address = address
        self.faults = faults or FaultModel()
        self.camera = camera
        self.truth = truth
        self.codec = RobotCodec(description)
        unknown = sorted(set(muted) - set(self.codec.topics.types))
        if unknown:
            raise ValueError(f"cannot mute {unknown}: not topics of {description.name}")
        self.muted = frozenset(muted)
        self.stats = EmulatorStats()
        self.owner = MotorOwner(watchdog_timeout, log)
        """Who drives the motors; its watchdog holds them when heartbeats stop."""
        self._rng = np.random.default_rng(seed)
        self._fault_rng = np.random.default_rng([seed, 1])
        self._backend = SimBackend(description, control_period=TICK)
        self._lock = threading.Lock()
        self._command: NDArray[np.float64] | None = None
        self._command_session: str | None = None  # the session that sent it
        self._fresh_command = False  # a command came since the watchdog last tripped
        self._hold: NDArray[np.float64] | None = None
        self._stop = threading.Event()
        self._queue: list[tuple[float, int, str, bytes]] = []
        self._queue_ready = threading.Condition()
        self._seq = 0
        self._dropout_until: dict[str, float] = {}
        self._session: Any = None
        self._publishers: dict[str, Any] = {}
        rods = [rod.name for rod in description.rods]
        self._stream_of = sensor_streams(self.codec.topics, rods)
        self._streams = sorted(set(self._stream_of.values()))

    # ------------------------------------------------------------------ wire

    def _publish_now(self, topic: str, raw: bytes) -> None:
        if topic in self.muted:
            return
        self._publishers[topic].put(raw)
        self.stats.published += 1

    def _send(self, topic: str, raw: bytes, now: float, faulty: bool = True) -> None:
        f = self.faults
        if faulty:
            rng = self._fault_rng
            if self._dropout_until.get(self._stream_of.get(topic, topic), -1.0) > now:
                self.stats.dropped_in_dropout += 1
                return
            if f.loss and rng.random() < f.loss:
                self.stats.lost += 1
                return
            if f.delays:
                delay = f.latency + f.jitter * rng.random()
                if f.reorder and rng.random() < f.reorder:
                    delay += f.reorder_delay
                    self.stats.reordered += 1
                with self._queue_ready:
                    heapq.heappush(self._queue, (now + delay, self._seq, topic, raw))
                    self._seq += 1
                    self._queue_ready.notify()
                return
        self._publish_now(topic, raw)

    def _sender(self) -> None:
        """Publishes delayed messages when they fall due."""
        while not self._stop.is_set():
            with self._queue_ready:
                if not self._queue:
                    self._queue_ready.wait(0.05)
                    continue
                due = self._queue[0][0] - time.monotonic()
                if due > 0:
                    self._queue_ready.wait(due)
                    continue
                _, _, topic, raw = heapq.heappop(self._queue)
            try:
                self._publish_now(topic, raw)
            except Exception:  # the session is closing
                if not self._stop.is_set():
                    raise

    @property
    def watchdog(self) -> Watchdog:
        """Fed by the owner's heartbeats; tripped, the motors hold."""
        return self.owner.watchdog

    def _on_command(self, sample: Any) -> None:
        raw = sample.payload.to_bytes()
        session = frame_id_of(raw)  # who sent it, before anything is decoded
        if not self.owner.may_command(session, time.monotonic()):
            with self._lock:
                self.stats.refused_commands += 1
            return
        try:
            _, targets = self.codec.decode_joint_state(raw, "actuated")
        except MessageError as err:
            self.stats.bad_commands += 1
            log.warning("emulator: a command was refused: %s", err)
            return
        lo, hi, _ = self.description.motor_limits
        with self._lock:
            self._command = np.clip(targets, lo, hi)  # firmware limits, whatever is sent
            self._command_session = session
            self._fresh_command = True
            self.stats.commands += 1

    def _on_heartbeat(self, sample: Any) -> None:
        session = frame_id_of(sample.payload.to_bytes())
        fed = self.owner.heartbeat(session, time.monotonic())
        with self._lock:
            if fed:
                self.stats.heartbeats += 1
            else:
                self.stats.refused_heartbeats += 1

    # ------------------------------------------------------------------ running

    def start(self) -> None:
        """Listen, settle the robot, and publish its header; :meth:`run` then serves."""
        self._session = open_session(self.address, listen=True, timeout=5.0)
        key = self.address.key
        self._publishers = {
            topic: self._session.declare_publisher(key(topic))
            for topic in self.codec.topics.types
            if topic != COMMAND_TOPIC
        }
        self._subscribers = [
            self._session.declare_subscriber(key(COMMAND_TOPIC), self._on_command),
            self._session.declare_subscriber(key(HEARTBEAT_TOPIC), self._on_heartbeat),
        ]
        result = self._backend.reset(self._rng)
        self._sync_clock()
        self._header = self.codec.encode_header(
            self._backend.calibration, {"control_period": TICK, "emulated": True}, 0.0
        )
        self._publish_header()
        now = time.monotonic()
        for sample in result.samples:
            self._publish_sample(sample, now)
        self._sender_thread = threading.Thread(target=self._sender, daemon=True)
        self._sender_thread.start()

    def _publish_header(self) -> None:
        for topic, raw in self._header:
            self._publish_now(topic, raw)

    def _publish_sample(self, sample: Sample, now: float) -> None:
        """Its messages, stamped with the robot's clock (the codec's origin)."""
        for topic, raw in self.codec.encode_sample(sample):
            self._send(topic, raw, now)

    def _targets(self, now: float) -> NDArray[np.float64]:
        """The motors' targets this tick: the newest command, or hold where they are
        before the first heartbeat and after heartbeats stop (until a new command)."""
        with self._lock:
            tripped = self.watchdog.tripped(now)
            if (
                self._fresh_command
                and not tripped
                and not self.owner.obeys(self._command_session, now)
            ):
                # Kept while nobody owned the motors, and another session took them.
                self._fresh_command = False
            if tripped and self._fresh_command:
                self._fresh_command = False
                if self.stats.heartbeats:
                    self.stats.watchdog_trips += 1
                    log.warning(
                        "emulator: no heartbeat for %.2f s; holding the motors",
                        self.watchdog.timeout,
                    )
            command = self._command if self._fresh_command and not tripped else None
        if command is not None:
            self._hold = None
            return command
        if self._hold is None:
            self._hold = self.rest_lengths
        return self._hold

    def _start_dropouts(self, now: float) -> None:
        f = self.faults
        if not f.dropout_rate:
            return
        for stream in self._streams:
            if self._fault_rng.random() < f.dropout_rate * TICK:
                self._dropout_until[stream] = now + f.dropout_duration

    def tick(self) -> None:
        """One tick: command or hold, step the robot, publish what the sensors saw."""
        now = time.monotonic()
        self._start_dropouts(now)
        backend = self._backend
        if self.camera:
            rate = self.description.sensors.camera.rate
            t_next = backend.world.time + TICK
            backend.camera = int(t_next * rate + 1e-9) > int(backend.world.time * rate + 1e-9)
        result = backend.step(self._targets(now))
        if result.diverged:
            log.error("emulator: the simulation diverged; resetting the robot")
            backend.reset(self._rng)
            self._sync_clock()  # the simulation's time restarts at 0; stamps go on
            return
        for sample in result.samples:
            self._publish_sample(sample, now)
        if self.truth:
            truth = backend.ground_truth()
            if truth is not None:
                for topic, raw in self.codec.encode_truth(truth):
                    self._send(topic, raw, now, faulty=False)
        self.stats.ticks += 1

    def run(self, duration: float | None = None) -> None:
        """Serve in real time until :meth:`stop` (or ``duration`` seconds)."""
        start = time.monotonic()
        next_tick = start
        next_header = start + HEADER_PERIOD
        self._sync_clock()
        while not self._stop.is_set():
            now = time.monotonic()
            if duration is not None and now - start >= duration:
                break
            if now >= next_header:
                self._publish_header()
                next_header += HEADER_PERIOD
            self.tick()
            next_tick += TICK
            lag = time.monotonic() - next_tick
            if lag > 0:
                self.stats.overruns += 1
                if lag > 0.1:  # far behind: skip the lost ticks rather than race
                    next_tick = time.monotonic()
                    self._sync_clock()
            else:
                self._stop.wait(-lag)

    def _sync_clock(self) -> None:
        """Stamps are wall-clock time, as a robot's clock is: the codec's origin is the
        wall clock (ns) at simulation time 0. A tick computes the next TICK seconds of
        the robot, which are stamped as the TICK just past, so that no sample is
        published before its stamp. Where the simulation fell behind, the clock jumps
        forward (never back)."""
        behind = seconds_to_ns(TICK) + self._backend.world.time_ns
        self.codec.origin_ns = max(self.codec.origin_ns, time.time_ns() - behind)

    def stop(self) -> None:
        self._stop.set()
        with self._queue_ready:
            self._queue_ready.notify_all()

    def close(self) -> None:
        self.stop()
        thread = getattr(self, "_sender_thread", None)
        if thread is not None:
            thread.join(timeout=1.0)
        if self._session is not None:
            self._session.close()
            self._session = None
        self._backend.close()

    @property
    def rest_lengths(self) -> NDArray[np.float64]:
        """The motors' present rest lengths (m), (m,)."""
        return np.asarray(self._backend.world.rest_lengths)[self.description.actuated].copy()


# ---------------------------------------------------------------------- command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``tensegrity-gym emulate`` (and ``python -m hardware.link.emulator``)."""
    parser.add_argument("--robot", default="three_bar", help="robot preset or YAML")
    parser.add_argument("--listen", default="tcp/127.0.0.1:7447", help="Zenoh endpoint")
    parser.add_argument("--prefix", default="", help="topic namespace (Zenoh key prefix)")
    parser.add_argument(
        "--security",
        default=None,
        metavar="FILE",
        help="the robot side's security file (TLS with mutual authentication, users; "
        "scripts/make_link_certs.py writes one): peers without the credentials are refused",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--latency", type=float, default=0.0, help="seconds added to a message")
    parser.add_argument("--jitter", type=float, default=0.0, help="up to this many seconds more")
    parser.add_argument("--loss", type=float, default=0.0, help="chance a message is lost")
    parser.add_argument("--reorder", type=float, default=0.0, help="chance a message is held back")
    parser.add_argument("--dropout-rate", type=float, default=0.0, help="dropouts per stream per s")
    parser.add_argument("--dropout-duration", type=float, default=0.5, help="seconds per dropout")
    parser.add_argument("--imu-rate", type=float, default=None, help="IMU rate (Hz) to emulate")
    parser.add_argument("--camera", action="store_true", help="render and publish RGB-D frames")
    parser.add_argument("--no-truth", action="store_true", help="publish no ground truth")
    parser.add_argument(
        "--watchdog",
        type=float,
        default=0.15,
        help="seconds without a heartbeat after which the motors hold",
    )
    parser.add_argument("--duration", type=float, default=None, help="stop after this many s")
    parser.add_argument(
        "--exit-with",
        type=int,
        default=None,
        metavar="PID",
        help="stop when process PID (the one that started this one) has ended",
    )
    parser.add_argument(
        "--mute",
        action="append",
        default=[],
        metavar="TOPIC",
        help="never publish this topic (a sensor missing or off); repeatable",
    )


def emulator_from_args(args: argparse.Namespace) -> Emulator:
    """The emulator the options of :func:`add_arguments` describe; ValueError or
    DescriptionError, one line, for a bad one."""
    from tensegrity_gym.model.description import load_robot

    for flag, value in (("--duration", args.duration), ("--watchdog", args.watchdog)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{flag} {value} must be a finite number of seconds > 0")
    options = [f"prefix={args.prefix}"] if args.prefix else []
    options += [f"security={args.security}"] if args.security else []
    query = "?" + "&".join(options) if options else ""
    address = LinkAddress.parse(f"zenoh/{args.listen}{query}")
    description = load_robot(args.robot)
    if args.imu_rate is not None:
        if not args.imu_rate > 0:
            raise ValueError(f"--imu-rate {args.imu_rate} must be positive")
        s = description.sensors
        imu = dataclasses.replace(s.imu, rate=float(args.imu_rate))
        description = dataclasses.replace(description, sensors=dataclasses.replace(s, imu=imu))
    faults = FaultModel(
        latency=args.latency,
        jitter=args.jitter,
        loss=args.loss,
        reorder=args.reorder,
        dropout_rate=args.dropout_rate,
        dropout_duration=args.dropout_duration,
    )
    return Emulator(
        description,
        address,
        faults=faults,
        seed=args.seed,
        camera=args.camera,
        truth=not args.no_truth,
        watchdog_timeout=args.watchdog,
        muted=args.mute,
    )


def run_from_args(args: argparse.Namespace) -> int:
    """Serve until SIGINT or SIGTERM (or ``--duration``); print ``ready ADDRESS`` once
    listening. Returns the process exit status.

    Zenoh's log, refused peers included, goes to this process's log: its standard
    output is taken over for that (:func:`forward_zenoh_log`), so call it only in a
    process that serves."""
    from tensegrity_gym.model.description import DescriptionError

    try:
        emulator = emulator_from_args(args)
    except (ValueError, DescriptionError) as err:
        log.error("%s", err)
        return 2

    def stop(signum: int, _frame: object) -> None:
        log.info("emulator: %s; stopping", signal.Signals(signum).name)
        emulator.stop()

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    if args.exit_with is not None:
        _stop_when_gone(args.exit_with, emulator)
    ready_out = forward_zenoh_log(log)
    try:
        emulator.start()
    except LinkError as err:
        log.error("%s", err)
        emulator.close()
        return 1
    log.info("emulating %s at %s", emulator.description.name, emulator.address)
    ready_out.write(f"ready {emulator.address}\n")
    ready_out.flush()
    try:
        emulator.run(args.duration)
    finally:
        emulator.close()
    log.info("emulator stopped: %s", emulator.stats)
    refused = emulator.owner.counts()["refused_by"]
    if refused:
        log.info("emulator: refused messages by session: %s", refused)
    return 0


def _stop_when_gone(parent: int, emulator: Emulator) -> None:
    """Stop ``emulator`` once process ``parent`` has ended (this process is then handed
    to another parent): a script or test that started it and died, or never stopped
    it, leaves no emulator running behind it."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        log.info("emulator: process %d that started it has ended; stopping", parent)
        emulator.stop()

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m hardware.link.emulator", description="Serve the simulated robot."
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return run_from_args(args)


if __name__ == "__main__":
    raise SystemExit(main())
