"""The hardware driver: a robot on the network as a :class:`Backend`.

Each :meth:`ZenohDriver.step` clips the command (motor range, change per period),
sends it, waits out the control period on the wall clock, and returns the samples that
arrived meanwhile, decoded and checked (:class:`~hardware.bag.assembler.SampleAssembler`
in ``"sort"`` mode): packets that overtook each other are sorted by the robot's stamps,
late and duplicated ones dropped, and each kind counted in ``info``. Zenoh delivers on
its own threads; the callback only queues the bytes, and all decoding happens in
``step``, so a flood of messages cannot interleave with the env's state.

Nothing waits forever: connecting, the robot's header (calibration), the first
samples and what the estimator needs to initialise each have a timeout; a period in
which the robot stays quiet returns on time with ``info["link_stalled"]``, and a robot
quiet for ``timeouts.link_lost`` makes ``step`` send a stop command and raise
:class:`LinkError`. Silence is judged after draining, over the time the driver
listened: a process that was suspended does not blame the robot for the gap.
``close()``, an exception in the env, or the interpreter exiting send a stop command
(hold the present rest lengths) first. A heartbeat goes out at a fixed rate from its
own thread; the robot holds its motors when heartbeats stop. Commands and heartbeats
name the driver's session (:attr:`ZenohDriver.session_id`, in their header's
``frame_id``): the robot obeys only the session that took its motors
(:mod:`hardware.link.ownership`).

Nothing the driver starts keeps the interpreter alive: the heartbeat thread is a
daemon, Zenoh calls the subscriber back on its own (non-Python) threads, and the exit
hook that stops the motors and closes the link runs before Python waits for the
threads that are left (a Zenoh callback thread of the default kind is one, and waits
for its session to close).

The robot stamps its messages with its clock (synchronised with this machine's); each
``reset`` sets the codec's clock origin (:attr:`ZenohDriver.clock_origin_ns`) to the
wall clock then, floored to a whole second, so the estimator sees small sample times,
which float seconds hold to the nanosecond. Commands and heartbeats carry the wall clock
in whole nanoseconds.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import math
import os
import threading
import time
import weakref
from collections import Counter, deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hardware.bag import messages as m
from hardware.bag.assembler import SampleAssembler
from hardware.bag.codec import MessageError, RobotCodec, description_yaml
from hardware.link.ownership import NO_SESSION, frame_id_of, new_session_id
from hardware.link.safety import CommandLimiter, check_fields
from hardware.link.wire import (
    COMMAND_TOPIC,
    HEARTBEAT_TOPIC,
    HEARTBEAT_TYPE,
    LinkAddress,
    LinkError,
    open_session,
)
from tensegrity_gym.model.description import DescriptionError, loads_robot
from tensegrity_gym.model.protocols import StepResult
from tensegrity_gym.model.samples import (
    GROUND_TRUTH,
    EncoderSample,
    ImuSample,
    RgbdFrame,
    ns_to_seconds,
)

if TYPE_CHECKING:
    from collections.abc import Callable

    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.protocols import ReadyCheck, SensorCalibration, UwbCalibration
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = ["DriverTimeouts", "LinkError", "ZenohDriver"]

log = logging.getLogger(__name__)

RESET_PERIODS = 5
"""Control periods at rest whose samples ``reset`` hands to the estimator."""


@dataclass(frozen=True)
class DriverTimeouts:
    """Seconds the driver waits before it gives up on something."""

    connect: float = 5.0
    """Opening the link, and receiving the robot's calibration."""
    first_samples: float = 5.0
    """From connecting to the first encoder reading."""
    stall: float = 0.5
    """No sensor message for this long: the step returns flagged ``link_stalled``."""
    link_lost: float = 3.0
    """No sensor message for this long: stop command, then :class:`LinkError`."""
    sensor_quiet: float = 1.0
    """A stream that published and then went quiet this long is listed in ``info``."""
    settle: float = 15.0
    """``reset`` waits at most this long for the robot to come to rest."""
    ready: float = 5.0
    """At rest, ``reset`` waits at most this long more for what the estimator needs to
    initialise (for the UKF: enough UWB ranges to anchors), then raises :class:`LinkError`."""

    def __post_init__(self) -> None:
        names = (
            "connect",
            "first_samples",
            "stall",
            "link_lost",
            "sensor_quiet",
            "settle",
            "ready",
        )
        check_fields(self, names, positive=True)
        if self.link_lost <= self.stall:
            raise ValueError(
                f"DriverTimeouts.link_lost={self.link_lost} must exceed stall={self.stall}"
            )


class ZenohDriver:
    """A robot that speaks the wire protocol of :mod:`hardware.link.wire`.

    Args:
        description: the robot.
        address: ``"zenoh/tcp/HOST:PORT"`` (see :class:`LinkAddress`) or a LinkAddress.
        control_period: seconds per :meth:`step`, on the wall clock.
        timeouts: see :class:`DriverTimeouts`.
        max_change: metres a command may move per period (see :class:`CommandLimiter`).
        heartbeat_rate: heartbeats per second.
        calibration: use this instead of the robot's ``/tensegrity/calibration``.
        pair_wait: seconds half of a message pair (IMU data and magnetometer, colour
            and depth) waits at the end of a period for its other half.
        max_message_bytes: bigger messages are refused (counted as ``oversized``).
        inbox_size, inbox_bytes: messages and bytes held between steps; beyond either
            the oldest are dropped (counted as ``overflow``).
        settle_speed: ``reset`` waits until no gyro reads more than this (rad/s).
    """

    def __init__(
        self,
        description: RobotDescription,
        address: str | LinkAddress,
        *,
        control_period: float = 0.1,
        timeouts: DriverTimeouts | None = None,
        max_change: float | None = None,
        heartbeat_rate: float = 20.0,
        calibration: SensorCalibration | None = None,
        pair_wait: float = 0.03,
        max_message_bytes: int = 16 << 20,
        inbox_size: int = 200_000,
        inbox_bytes: int = 256 << 20,
        settle_speed: float = 0.05,
    ) -> None:
        if not np.isfinite(control_period) or control_period <= 0:
            raise ValueError(f"control_period={control_period!r} must be positive")
        if not np.isfinite(heartbeat_rate) or heartbeat_rate <= 0:
            raise ValueError(f"heartbeat_rate={heartbeat_rate!r} must be positive")
        self.description = description
        self.address = address if isinstance(address, LinkAddress) else LinkAddress.parse(address)
        self.control_period = control_period
        self.timeouts = timeouts or DriverTimeouts()
        self.heartbeat_rate = heartbeat_rate
        self.pair_wait = pair_wait
        self.max_message_bytes = max_message_bytes
        self.settle_speed = settle_speed
        self.codec = RobotCodec(description)
        self.limiter = CommandLimiter(description, control_period, max_change)
        self._given_calibration = calibration
        self._calibration: SensorCalibration | None = calibration
        self.uwb_calibration: UwbCalibration | None = None
        """Anchors and offsets that replace the robot's (``calibration=PATH``)."""
        self.inbox_size, self.inbox_bytes = inbox_size, inbox_bytes
        self._inbox: deque[tuple[str, bytes, float]] = deque()
        self._inbox_lock = threading.Lock()  # Zenoh calls back from its own threads
        self._inbox_used = 0  # bytes
        self._received = 0
        self._oversized = 0
        self._overflow = 0
        self._session: Any = None
        self._stop_heartbeat = threading.Event()
        self._heartbeat_thread: threading.Thread | None = None
        self._skipped: Counter[str] = Counter()
        self._assembler = SampleAssembler(self.codec, self._skip, order="sort")
        self._header: dict[str, bytes] = {}
        self._truth: GroundTruth | None = None
        self._last_frame: RgbdFrame | None = None
        self._encoders: NDArray[np.float64] | None = None
        self._encoders_at = 0.0  # monotonic time the newest reading was collected
        self._encoders_out_of_range = 0  # readings no motor could give, since reset
        self._last_activity = 0.0  # monotonic time of the newest command
        # Silence is measured on a listening clock: seconds the driver spent listening,
        # which stands still over a gap between two looks at the inbox (see _note_listening).
        self._listen_clock = 0.0
        self._drained_at: float | None = None  # monotonic time of the last look at the inbox
        self._last_sensor = 0.0  # listening clock when the newest sensor message arrived
        self._last_by_stream: dict[str, float] = {}  # ... per stream
        self._deadline: float | None = None
        self._closed = False
        self.last_heartbeat: float | None = None
        """When the last heartbeat went out: sample time (s from the clock origin)."""
        self.session_id = new_session_id()
        """This driver's session, named in every command and heartbeat (``frame_id``)."""
        _close_at_exit(self)

    # ------------------------------------------------------------------ link

    @property
    def connected(self) -> bool:
        return self._session is not None

    @property
    def clock_origin_ns(self) -> int:
        """Robot-clock ns of sample time 0: the wall clock at the latest ``reset``,
        floored to a whole second (0 before the first)."""
        return self.codec.origin_ns

    def connect(self) -> None:
        """Open the link (no-op if open); :class:`LinkError` after ``timeouts.connect``."""
        if self._session is not None:
            return
        if self._closed:
            raise LinkError(f"the driver for {self.address} was closed")
        import zenoh

        session = open_session(self.address, listen=False, timeout=self.timeouts.connect)
        key = self.address.key
        try:
            self._subscriber = session.declare_subscriber(
                self.address.everything,
                _direct_callback(_weakly(self._on_message)),
                allowed_origin=zenoh.Locality.REMOTE,
            )
            self._command_pub = session.declare_publisher(key(COMMAND_TOPIC))
            self._heartbeat_pub = session.declare_publisher(key(HEARTBEAT_TOPIC))
        except BaseException:
            session.close()  # type: ignore[no-untyped-call]
            raise
        self._session = session
        # Neither Zenoh's callback nor the heartbeat thread keeps the driver alive: an
        # env dropped without close() is collected, and this closes its session.
        release = weakref.finalize(self, _release, session, self._stop_heartbeat)
        release.atexit = False  # at exit, _close_open_drivers sends the stop command first
        self._stop_heartbeat.clear()
        self._heartbeat_thread = threading.Thread(
            target=_heartbeats, args=(weakref.ref(self),), name="tensegrity-heartbeat",
            daemon=True,
        )  # fmt: skip
        self._heartbeat_thread.start()
        log.info("robot link: connected to %s as session %s", self.address, self.session_id)

    def _on_message(self, sample: Any) -> None:
        # Zenoh's thread: queue the bytes and nothing else.
        payload = sample.payload.to_bytes()
        size = len(payload)
        with self._inbox_lock:
            self._received += 1
            if size > self.max_message_bytes:
                self._oversized += 1
                return
            inbox = self._inbox
            while inbox and (
                len(inbox) >= self.inbox_size or self._inbox_used + size > self.inbox_bytes
            ):
                self._inbox_used -= len(inbox.popleft()[1])
                self._overflow += 1
            inbox.append((str(sample.key_expr), payload, time.monotonic()))
            self._inbox_used += size

    def _beat(self) -> bool:
        """Send one heartbeat if a command went out lately; False once the session is
        closing. Heartbeats say the control loop is alive: they pause when no command
        has gone out for a while (a hung or interrupted policy, a long training
        update), and the robot holds its motors until the next command."""
        grace = max(3.0 * self.control_period, 0.5)
        if time.monotonic() - self._last_activity > grace:
            return True
        now_ns = time.time_ns()
        sec, nanosec = divmod(now_ns, 1_000_000_000)
        store = self.codec.store
        stamp = store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        msg = store.types[HEARTBEAT_TYPE](stamp=stamp, frame_id=self.session_id)
        try:
            self._heartbeat_pub.put(bytes(store.serialize_cdr(msg, HEARTBEAT_TYPE)))
        except Exception:  # the session is closing
            return False
        self.last_heartbeat = self.codec.seconds(now_ns)
        return True

    def _skip(self, kind: str, topic: str, ns: int | None, why: str) -> None:
        self._skipped[kind] += 1
        if self._skipped[kind] == 1:
            log.warning("robot link: %s on %s: %s (further ones are counted)", kind, topic, why)

    # ------------------------------------------------------------------ receiving

    def _note_listening(self, now: float) -> float:
        """Remember that the driver looks at its inbox at ``now`` (monotonic s), and
        advance the listening clock over the time since the last look.

        A gap longer than ``timeouts.stall`` since the last look (the process was
        suspended: a debugger, a laptop lid, a long GC pause; or the caller took that
        long between steps) does not advance it: what the robot sent meanwhile may still
        be in the socket or in Zenoh's threads, so its silence is judged only over the
        time the driver listened. The clock pauses over a gap; it does not start again,
        so a dead robot is still found out by a caller that is slow on every step.

        Returns the monotonic time from which arrivals count on the clock: the last
        look, or ``now`` after a gap."""
        before, self._drained_at = self._drained_at, now
        if before is None or now - before > self.timeouts.stall:
            return now
        self._listen_clock += now - before
        return before

    def _heard_at(self, arrival: float, now: float, since: float) -> float:
        """The listening clock at a message's ``arrival`` (monotonic s), drained at
        ``now`` from a look that listened from ``since``."""
        return min(self._listen_clock - (now - max(arrival, since)), self._listen_clock)

    def _listened(self, since: float) -> float:
        """Seconds the driver has listened since the listening clock read ``since``."""
        return max(self._listen_clock - since, 0.0)

    def _drain(self) -> None:
        """Decode what was queued when the call began (a bounded amount of work)."""
        now = time.monotonic()
        since = self._note_listening(now)
        with self._inbox_lock:
            batch, self._inbox = self._inbox, deque()
            self._inbox_used = 0
        topics = self.codec.topics.types
        for key, raw, arrival in batch:
            topic = self.address.topic(key)
            if topic in (COMMAND_TOPIC, HEARTBEAT_TOPIC):  # not ours: Zenoh sends us none
                who = frame_id_of(raw) or NO_SESSION
                self._skip("other_controller", topic, None, f"session {who} commands the robot too")
                continue
            if topic is None or topic not in topics:
                self._skip("unknown_topic", key, None, "not in the robot's topic table")
                continue
            if topic in m.HEADER_TOPICS:
                self._header[topic] = raw
                continue
            if self._assembler.add(topic, raw, arrival):  # a sensor is alive
                heard = self._heard_at(arrival, now, since)
                self._last_sensor = max(self._last_sensor, heard)
                self._last_by_stream[topic] = heard

    def _collect(self, now: float) -> list[Sample]:
        """Samples complete by ``now``; remembers the newest truth, frame and encoders."""
        self._drain()
        out = self._assembler.take(now, self.pair_wait)
        if out.truth is not None:
            self._truth = out.truth
        for sample in out.samples:
            if isinstance(sample, EncoderSample):
                self._encoders, self._encoders_at = sample.rest_lengths, now
                self._encoders_out_of_range += self.description.outside_motor_range(
                    sample.rest_lengths, reading=True
                )
            elif isinstance(sample, RgbdFrame):
                self._last_frame = sample
        return out.samples

    @property
    def received(self) -> int:
        """Messages received on the link since the driver was made."""
        return self._received

    @property
    def dropped(self) -> int:
        """Messages lost on this side: the inbox overflowed, or they were too big."""
        return self._overflow + self._oversized

    def link_counts(self) -> dict[str, int]:
        """Messages skipped or dropped since ``reset``, by kind, and those sorted."""
        counts = dict(self._skipped)
        counts["reordered"] = self._assembler.reordered
        counts["clock_jumps"] = self._assembler.clock_jumps
        counts["oversized"] = self._oversized
        counts["overflow"] = self._overflow
        return counts

    def _wait_for(self, what: str, ready: Any, timeout: float) -> None:
        """Collect until ``ready()``; LinkError after listening ``timeout`` seconds."""
        start = self._listen_clock
        while True:
            self._collect(time.monotonic())
            if ready():
                return
            if self._listened(start) >= timeout:
                raise LinkError(
                    f"robot at {self.address}: no {what} within {timeout:g} s "
                    f"({self._received} messages received)"
                )
            time.sleep(0.01)

    # ------------------------------------------------------------------ Backend

    @property
    def calibration(self) -> SensorCalibration:
        """The robot's, or :attr:`uwb_calibration`'s anchors and offsets where set."""
        if self._calibration is None:
            raise RuntimeError("call reset() before reading the calibration")
        if self.uwb_calibration is None:
            return self._calibration
        return self.uwb_calibration.applied_to(self._calibration)

    def _read_header(self) -> None:
        try:  # the YAML's own topic, or an older robot's YAML on /robot_description
            found = description_yaml(self._header, self.codec.store)
            theirs = None if found is None else loads_robot(found[1], f"{self.address}:{found[0]}")
        except (MessageError, DescriptionError) as err:
            raise LinkError(f"robot at {self.address}: bad robot description: {err}") from None
        if theirs is not None and (
            theirs.name != self.description.name or theirs.n_cables != self.description.n_cables
        ):
            raise LinkError(
                f"the robot at {self.address} is {theirs.name!r} ({theirs.n_cables} cables); "
                f"this env is for {self.description.name!r}"
            )
        if self._given_calibration is None:
            try:
                self._calibration = self.codec.decode_calibration(
                    self._header[m.CALIBRATION_TOPIC], self._header.get(m.CAMERA_INFO_TOPIC)
                )
            except MessageError as err:
                raise LinkError(f"robot at {self.address}: bad calibration: {err}") from None

    def reset(self, rng: np.random.Generator, *, ready: ReadyCheck | None = None) -> StepResult:
        """Connect if needed, wait for the robot's calibration and first samples, bring
        the motors to the description's rest lengths, and wait for the robot to come to
        rest. Nothing is moved by hand: the robot stays where it is.

        Returns the samples of the last :data:`RESET_PERIODS` control periods, or more
        where ``ready(samples)`` said something was missing: then ``reset`` collects
        further periods at rest until it returns None, and after ``timeouts.ready``
        seconds sends a stop command and raises :class:`LinkError` quoting it."""
        self.connect()
        self._begin_episode()
        t = self.timeouts
        wanted = m.CALIBRATION_TOPIC if self._given_calibration is None else None
        self._wait_for(
            f"{wanted or 'robot description'} message",
            lambda: wanted is None or wanted in self._header,
            t.connect,
        )
        self._read_header()
        self._wait_for("encoder reading", lambda: self._encoders is not None, t.first_samples)
        self.limiter.reset(self._encoders)
        d = self.description
        nominal = d.rest_lengths[d.actuated]
        recent, settled = self._settle(nominal)
        if not settled:
            log.warning(
                "robot at %s did not come to rest within %.1f s; starting anyway",
                self.address,
                t.settle,
            )
        samples = self._until_ready(recent, nominal, ready)
        info = {"robot_settled": settled, **self._link_info(overrun=False, stalled=False)}
        return StepResult(samples, info=info)

    def _begin_episode(self) -> None:
        """Forget what came before this episode: samples, counts, the robot's header."""
        self._deadline = None
        self._drain()  # what came before this episode is not part of it
        # Sample times count from this episode's start (whole seconds of the wall clock).
        self.codec.origin_ns = time.time_ns() // 1_000_000_000 * 1_000_000_000
        self._assembler = SampleAssembler(self.codec, self._skip, order="sort")
        self._skipped.clear()
        with self._inbox_lock:
            self._oversized = self._overflow = 0
        self._truth, self._encoders = None, None
        self._encoders_out_of_range = 0
        self._header.clear()  # the robot may have restarted: read its header anew
        self._last_by_stream.clear()

    def _settle(self, nominal: NDArray[np.float64]) -> tuple[deque[list[Sample]], bool]:
        """Command ``nominal`` (m) until the robot is at rest, at most
        ``timeouts.settle`` seconds; the last :data:`RESET_PERIODS` periods' samples,
        and whether it came to rest."""
        # The estimator starts from the last RESET_PERIODS periods at rest: enough UWB
        # rounds to place the robot even when packets are lost.
        recent: deque[list[Sample]] = deque(maxlen=RESET_PERIODS)
        start = time.monotonic()
        while time.monotonic() - start < self.timeouts.settle:
            result = self._period(self.limiter(nominal))
            recent.append(list(result.samples))
            if len(recent) == RESET_PERIODS and self._at_rest(recent[-1], nominal):
                return recent, True
        return recent, False

    def _until_ready(
        self,
        recent: deque[list[Sample]],
        nominal: NDArray[np.float64],
        ready: ReadyCheck | None,
    ) -> list[Sample]:
        """The samples of ``recent`` periods, extended by further periods at rest
        (commanding ``nominal``, m) while ``ready`` says something is missing; at most
        ``timeouts.ready`` seconds of listening, then a stop command and LinkError."""
        samples = [s for period in recent for s in period]
        missing = None if ready is None else ready(samples)
        if ready is None or missing is None:
            return samples
        timeout = self.timeouts.ready
        log.info("robot at %s: waiting for what the estimator lacks: %s", self.address, missing)
        # The window grows with the wait, up to every period of it.
        bound = RESET_PERIODS + math.ceil(timeout / self.control_period)
        window = deque(recent, maxlen=bound)
        start = self._listen_clock
        while self._listened(start) < timeout:
            window.append(list(self._period(self.limiter(nominal)).samples))
            samples = [s for period in window for s in period]
            missing = ready(samples)
            if missing is None:
                return samples
        self.stop()
        raise LinkError(
            f"robot at {self.address}: the estimator cannot initialise: {missing} "
            f"(still missing after {timeout:g} s at rest, timeouts.ready); motors told to hold"
        )

    def _at_rest(self, samples: list[Sample], nominal: NDArray[np.float64]) -> bool:
        """The motors are at ``nominal`` and no gyro turns (a robot without raw IMU
        streams is judged by its encoders alone)."""
        if self._encoders is None or not np.allclose(self._encoders, nominal, atol=2e-3):
            return False
        gyros = [float(np.linalg.norm(s.gyro)) for s in samples if isinstance(s, ImuSample)]
        return max(gyros, default=0.0) < self.settle_speed

    def step(self, targets: NDArray[np.float64]) -> StepResult:
        if self._deadline is None:
            raise RuntimeError("call reset() before step()")
        return self._period(self.limiter(targets))

    def _period(self, command: NDArray[np.float64]) -> StepResult:
        """Send ``command``, wait out the period, return what arrived."""
        now = time.monotonic()
        overrun = self._deadline is not None and now > self._deadline + self.control_period
        if self._deadline is None or overrun:
            self._deadline = now
        self._deadline += self.control_period
        self._send_command(command)
        while (left := self._deadline - time.monotonic()) > 0:
            time.sleep(min(left, 0.02))
            self._drain()  # keep the inbox short and decode while waiting
        samples = self._collect(time.monotonic())
        # Judged after draining, over the time the driver listened: a process that was
        # suspended does not blame the robot for what is still on its way.
        quiet = self._listened(self._last_sensor)
        if quiet > self.timeouts.link_lost:
            self.stop()
            raise LinkError(
                f"robot at {self.address}: no sensor message for {quiet:.1f} s "
                f"(timeouts.link_lost = {self.timeouts.link_lost:g} s); motors told to hold"
            )
        info = self._link_info(overrun, stalled=quiet > self.timeouts.stall)
        info["link_latency_s"] = time.monotonic() - self._deadline  # what the driver adds
        # How old the freshest sample is, robot clock against ours (synchronised clocks).
        info["link_newest_age_s"] = None
        if samples:
            newest = self.codec.stamp_ns(samples[-1].t)
            info["link_newest_age_s"] = ns_to_seconds(time.time_ns() - newest)
        return StepResult(samples, info=info, command=command)

    def _link_info(self, overrun: bool, stalled: bool) -> dict[str, Any]:
        quiet = sorted(
            s
            for s, t in self._last_by_stream.items()
            if self._listened(t) > self.timeouts.sensor_quiet
        )
        return {
            "link_stalled": stalled,
            "link_overrun": overrun,
            "link_quiet_topics": quiet,
            "link_counts": self.link_counts(),
            "command_clipped": self.limiter.clipped,
            "encoders_out_of_range": self._encoders_out_of_range,
        }

    def _send_command(self, targets: NDArray[np.float64]) -> None:
        # Stamped with the wall clock: the sample time of now, which the codec turns back
        # into whole ns of the wall clock exactly.
        codec = self.codec
        msg = codec.store.types[m.JOINT_STATE](
            header=codec.header(codec.seconds(time.time_ns()), self.session_id),
            name=list(codec.actuated_names),
            position=np.asarray(targets, dtype=np.float64),
            velocity=np.empty(0),
            effort=np.empty(0),
        )
        self._command_pub.put(codec.serialize(msg, m.JOINT_STATE))
        self._last_activity = time.monotonic()

    def stop(self) -> None:
        """Hold the motors where they are: command the present rest lengths."""
        if self._session is None:
            return
        # The motors' present rest lengths: the encoders if they spoke lately, else the
        # last command (an old reading would drive the motors back).
        fresh = time.monotonic() - self._encoders_at <= 2.0 * self.control_period
        hold = self._encoders if fresh and self._encoders is not None else self.limiter.previous
        if hold is None:
            return
        hold = np.clip(hold, self.limiter.lo, self.limiter.hi)
        try:
            self._send_command(hold)
        except Exception as err:  # the session is gone: the robot's watchdog holds
            log.warning("robot link: the stop command could not be sent: %s", err)
        self.limiter.previous = hold

    def ground_truth(self) -> GroundTruth | None:
        """The newest ground truth the robot's side published (motion capture), if any."""
        return self._truth

    def sample_kinds(self) -> frozenset[str]:
        """What the robot carries (its description's ``sample_kinds``), known before it
        is reached, so that ``make`` refuses an estimator the robot cannot serve.

        ``"ground_truth"`` is included too, though whether motion capture publishes it
        is not known until the robot's side speaks: the oracle's ``reset`` waits for it
        and names it when it does not come (``timeouts.ready``)."""
        return self.description.sample_kinds | {GROUND_TRUTH}

    def render(self, width: int, height: int) -> NDArray[np.uint8]:
        """The newest camera frame scaled to (height, width, 3); black without one."""
        frame = self._last_frame
        if frame is None:
            return np.zeros((height, width, 3), dtype=np.uint8)
        rows = np.arange(height) * frame.rgb.shape[0] // height
        cols = np.arange(width) * frame.rgb.shape[1] // width
        return np.ascontiguousarray(frame.rgb[rows][:, cols])

    def close(self) -> None:
        """Stop the motors, the heartbeats and the link (idempotent)."""
        if self._closed:
            return
        self._closed = True
        _OPEN_DRIVERS.discard(self)
        self.stop()
        self._stop_heartbeat.set()
        if self._heartbeat_thread is not None:
            self._heartbeat_thread.join(timeout=1.0)
        session, self._session = self._session, None
        if session is not None:
            session.close()


_OPEN_DRIVERS: weakref.WeakSet[ZenohDriver] = weakref.WeakSet()
"""Drivers not closed yet; weak, so that the exit hook keeps no forgotten driver alive."""
# A forked child (a multiprocessing worker) inherits the set but not the links: its
# exit must not close, or send stop commands through, its parent's sessions.
os.register_at_fork(after_in_child=_OPEN_DRIVERS.clear)


def _close_at_exit(driver: ZenohDriver) -> None:
    """Have ``driver`` closed (stop command first) when the interpreter exits."""
    _OPEN_DRIVERS.add(driver)


_early_hook_lock = threading.Lock()
_early_hook_registered = False


def _close_before_threads_join() -> None:
    """Close the open drivers before Python waits for non-daemon threads at exit, not
    after (atexit): where Zenoh runs the link's callback on a Python thread of its own
    (not a daemon, living until the session closes), that wait would never end. Only
    then: a driver in use by a user's own worker thread is otherwise left to it."""
    global _early_hook_registered
    with _early_hook_lock:
        if _early_hook_registered:
            return
        _early_hook_registered = True
    register = getattr(threading, "_register_atexit", None)  # private: concurrent.futures'
    if register is None:
        log.warning("robot link: no early exit hook; an unclosed driver may keep Python alive")
        return
    with contextlib.suppress(RuntimeError):  # the interpreter is already shutting down
        register(_close_open_drivers)


def _close_open_drivers() -> None:
    for driver in list(_OPEN_DRIVERS):
        try:
            driver.close()
        except Exception as err:  # the next driver still gets its stop command
            log.warning("robot link: closing %s at exit failed: %s", driver.address, err)


atexit.register(_close_open_drivers)


def _heartbeats(ref: weakref.ReferenceType[ZenohDriver]) -> None:
    """The heartbeat thread: :meth:`ZenohDriver._beat` at ``heartbeat_rate`` until the
    driver stops them or is gone (held only while it beats)."""
    driver = ref()
    if driver is None:
        return
    period, stop = 1.0 / driver.heartbeat_rate, driver._stop_heartbeat
    next_beat = time.monotonic()
    del driver
    while not stop.is_set():
        next_beat += period
        driver = ref()
        if driver is None or not driver._beat():
            return
        del driver
        stop.wait(max(next_beat - time.monotonic(), 0.0))


def _release(session: Any, stop: threading.Event) -> None:
    """A collected driver's link: its heartbeats stopped and its session closed."""
    stop.set()
    with contextlib.suppress(Exception):  # closed already (close()), or shutting down
        if not session.is_closed():
            session.close()


def _weakly(method: Callable[[Any], None]) -> Callable[[Any], None]:
    """``method`` called through a weak reference to its object (nothing once it is
    gone), so that a callback held by Zenoh does not keep the object alive."""
    ref = weakref.WeakMethod(method)

    def call(arg: Any) -> None:
        bound = ref()
        if bound is not None:
            bound(arg)

    return call


def _direct_callback(function: Any) -> Any:
    """``function`` as a Zenoh callback run on Zenoh's own thread, not on a Python
    thread of its own: such a thread is not a daemon and lives until the session
    closes, so a driver never closed would keep the interpreter from exiting. The
    callback must be quick (it only queues bytes). ``indirect`` is marked unstable in
    eclipse-zenoh 1.x; without it, the exit hook still closes the session."""
    from zenoh.handlers import Callback

    try:
        return Callback(function, indirect=False)
    except TypeError:
        _close_before_threads_join()
        return function
