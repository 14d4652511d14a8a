"""Recording what a backend produces and what an estimator makes of it.

:class:`RecordingBackend` and :class:`RecordingEstimator` wrap the env's parts and
hand everything to a sink: :class:`MemorySink` keeps runs in memory (an estimator
study replays every variant on the same samples), :class:`BagSink` writes one ROS 2
bag per episode. The wrapped parts behave exactly as before. Times are the samples'
(seconds from the backend's clock origin); a bag gets the robot's own stamps back,
``clock_origin_ns`` plus them.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from tensegrity_gym.model.protocols import backend_can_wait
from tensegrity_gym.model.samples import ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from numpy.typing import NDArray

    from hardware.bag.writer import MessageWriter
    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.protocols import (
        Backend,
        Estimator,
        ReadyCheck,
        SensorCalibration,
        StepResult,
    )
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = [
    "EPISODE_INFO",
    "BagSink",
    "Episode",
    "FanOutSink",
    "MemorySink",
    "RecordedRun",
    "RecordedStep",
    "RecordingBackend",
    "RecordingEstimator",
    "RunSink",
    "WriterSink",
    "latest_nis",
    "wall_clock_origin_ns",
]

log = logging.getLogger(__name__)

EPISODE_INFO = ("randomization",)
"""Keys of a backend's reset info that describe the episode's world (a randomised
world's draws): written into the episode's run info."""


@dataclass
class RecordedStep:
    samples: list[Sample]
    command: NDArray[np.float64]
    """Rest-length targets (m), (m,); for the start, the lengths the motors held."""
    truth: GroundTruth | None


@dataclass
class RecordedRun:
    """The start samples and every control period after, with the truth where known."""

    description: RobotDescription
    calibration: SensorCalibration
    start: RecordedStep
    steps: list[RecordedStep] = field(default_factory=list)
    control_period: float = 0.1


class RunSink(Protocol):
    """Where a recording goes."""

    def begin(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        control_period: float,
        start: RecordedStep,
        *,
        clock_origin_ns: int = 0,
        episode_info: Mapping[str, Any] | None = None,
    ) -> None:
        """A new episode starts with these samples; ``clock_origin_ns`` is the
        robot-clock ns of its sample time 0; ``episode_info`` what the backend said of
        this episode alone (a randomised world's draws), for the run info."""
        ...

    def step(self, t_command: float, step: RecordedStep) -> None:
        """The command sent at ``t_command`` (s) and what the period produced."""
        ...

    def estimate(self, estimate: Estimate, t_log: float) -> None:
        """What the estimator made of the latest samples, known at ``t_log`` (s)."""
        ...

    def innovation(self, nis: float, t_log: float) -> None:
        """The estimator's latest normalised innovation squared per measurement row
        (see :func:`latest_nis`), known at ``t_log`` (s)."""
        ...

    def end(self) -> None:
        """No more data: finish the current episode."""
        ...


def hold_command(description: RobotDescription) -> NDArray[np.float64]:
    """The rest lengths the motors hold at the start of an episode (m), (m,)."""
    return description.rest_lengths[description.actuated].copy()


class RecordingBackend:
    """A backend that hands a copy of everything the wrapped one produced to a sink."""

    def __init__(self, inner: Backend, sink: RunSink) -> None:
        self.inner = inner
        self.sink = sink
        self.description = inner.description
        self.control_period = inner.control_period
        self._period_ns = seconds_to_ns(inner.control_period)
        self._t_ns = 0  # the end of the latest period: when the next command is sent

    def __getattr__(self, name: str) -> Any:  # the wrapped backend's own settings
        if name == "inner":  # not set yet (unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.inner, name)

    @property
    def calibration(self) -> SensorCalibration:
        return self.inner.calibration

    @property
    def clock_origin_ns(self) -> int:
        """The wrapped backend's: robot-clock ns of sample time 0 (0 for a backend
        written before it existed)."""
        return int(getattr(self.inner, "clock_origin_ns", 0))

    @property
    def t_command(self) -> float:
        """When the next command is sent (s): the end of the latest period."""
        return ns_to_seconds(self._t_ns)

    def reset(
        self, rng: np.random.Generator, *, ready: ReadyCheck | None = None, **options: Any
    ) -> StepResult:
        """Reset the wrapped backend, with ``options`` (its ``reset_options``), and begin
        an episode in the sink."""
        reset: Any = self.inner.reset  # options only where the wrapped one takes them
        if ready is not None and backend_can_wait(self.inner):
            result: StepResult = reset(rng, ready=ready, **options)
        else:
            result = reset(rng, **options)
        truth = self.inner.ground_truth()
        times = [s.t for s in result.samples] + ([truth.t] if truth is not None else [])
        self._t_ns = seconds_to_ns(max(times, default=0.0))
        start = RecordedStep(list(result.samples), hold_command(self.description), truth)
        self.sink.begin(
            self.description,
            self.inner.calibration,
            self.control_period,
            start,
            clock_origin_ns=self.clock_origin_ns,
            episode_info={k: v for k, v in result.info.items() if k in EPISODE_INFO},
        )
        return result

    def step(self, targets: NDArray[np.float64]) -> StepResult:
        t_command = self.t_command
        result = self.inner.step(targets)
        command = result.command if result.command is not None else targets
        truth = None if result.diverged else self.inner.ground_truth()
        # A robot's clock runs on its own: the next command is logged after everything
        # this period brought, which is exactly one period on for a simulation.
        newest = [s.t for s in result.samples] + ([truth.t] if truth is not None else [])
        self._t_ns = max(self._t_ns + self._period_ns, seconds_to_ns(max(newest, default=0.0)))
        step = RecordedStep(list(result.samples), np.array(command, dtype=np.float64), truth)
        self.sink.step(t_command, step)
        return result

    def ground_truth(self) -> GroundTruth | None:
        return self.inner.ground_truth()

    def render(self, width: int, height: int) -> NDArray[np.uint8]:
        return self.inner.render(width, height)

    def stop(self) -> None:
        self.inner.stop()

    def close(self) -> None:
        """End the sink's episode (and close a sink that has a ``close``, a live view's
        server), then the wrapped backend."""
        try:
            self.sink.end()
            close = getattr(self.sink, "close", None)
            if close is not None:
                close()
        finally:
            self.inner.close()


class RecordingEstimator:
    """An estimator that hands each estimate to a sink, logged at the period's end."""

    def __init__(self, inner: Estimator, sink: RunSink, backend: RecordingBackend) -> None:
        self.inner = inner
        self.sink = sink
        self.backend = backend
        self.needs_camera = inner.needs_camera
        self._updates: int | None = -1  # the inner estimator's update count at the last NIS

    def __getattr__(self, name: str) -> Any:  # the wrapped estimator's diagnostics
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> Estimate:
        estimate = self.inner.reset(description, calibration, samples, command, rng)
        self._updates = -1
        self._hand_on(estimate)
        return estimate

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        estimate = self.inner.update(samples, command)
        self._hand_on(estimate)
        return estimate

    def _hand_on(self, estimate: Estimate) -> None:
        """The estimate to the sink, and the latest innovation where there is a new one."""
        t = self.backend.t_command
        self.sink.estimate(estimate, t)
        nis = latest_nis(self.inner)
        updates = getattr(getattr(self.inner, "diagnostics", None), "updates", None)
        if nis is not None and updates != self._updates:
            self._updates = updates
            self.sink.innovation(nis, t)


def latest_nis(estimator: object) -> float | None:
    """The normalised innovation squared per accepted row of the estimator's latest
    update with one (the UKF's ``diagnostics.nis_history``), finite; None for an
    estimator that keeps none."""
    history = getattr(getattr(estimator, "diagnostics", None), "nis_history", None)
    if not history:
        return None
    nis = float(history[-1])
    return nis if np.isfinite(nis) else None


class MemorySink:
    """Keeps every episode in memory; :attr:`run` is the latest."""

    def __init__(self) -> None:
        self.runs: list[RecordedRun] = []

    @property
    def run(self) -> RecordedRun:
        if not self.runs:
            raise RuntimeError("nothing recorded yet: reset the env first")
        return self.runs[-1]

    def begin(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        control_period: float,
        start: RecordedStep,
        *,
        clock_origin_ns: int = 0,
        episode_info: Mapping[str, Any] | None = None,
    ) -> None:
        self.runs.append(RecordedRun(description, calibration, start, [], control_period))

    def step(self, t_command: float, step: RecordedStep) -> None:
        self.run.steps.append(step)

    def estimate(self, estimate: Estimate, t_log: float) -> None:
        pass

    def innovation(self, nis: float, t_log: float) -> None:
        pass

    def end(self) -> None:
        pass


class FanOutSink:
    """Hands everything to several sinks, in order (a bag and a live view)."""

    def __init__(self, sinks: Sequence[RunSink]) -> None:
        self.sinks = list(sinks)

    def begin(self, *args: Any, **kwargs: Any) -> None:
        for sink in self.sinks:
            sink.begin(*args, **kwargs)

    def step(self, t_command: float, step: RecordedStep) -> None:
        for sink in self.sinks:
            sink.step(t_command, step)

    def estimate(self, estimate: Estimate, t_log: float) -> None:
        for sink in self.sinks:
            sink.estimate(estimate, t_log)

    def innovation(self, nis: float, t_log: float) -> None:
        for sink in self.sinks:
            sink.innovation(nis, t_log)

    def end(self) -> None:
        for sink in self.sinks:
            sink.end()

    def close(self) -> None:
        """Close the sinks that have a ``close``."""
        for sink in self.sinks:
            close = getattr(sink, "close", None)
            if close is not None:
                close()


def wall_clock_origin_ns() -> int:
    """The wall clock now (Unix ns), floored to a whole second: the clock origin a
    recording gives a source whose clock starts at 0 (a simulation)."""
    return time.time_ns() // 1_000_000_000 * 1_000_000_000


@dataclass(frozen=True)
class Episode:
    """What a :class:`WriterSink` opens an episode's writer with."""

    description: RobotDescription
    calibration: SensorCalibration
    run_info: dict[str, Any]
    """Its ``/tensegrity/run_info``: the sink's, the episode's number and control period."""
    clock_origin_ns: int
    """Robot-clock ns of sample time 0 (see :attr:`WriterSink.wall_clock`)."""


class WriterSink:
    """Writes each episode through a :class:`~hardware.bag.writer.MessageWriter` that a
    subclass opens (:meth:`_open`): a bag (:class:`BagSink`), a live view
    (:class:`hardware.viewer.FoxgloveSink`).

    Each estimate is written with what viewers draw (``/tf``, ``/tensegrity/markers``)
    where ``markers`` is on: the latest ground truth, the estimate, and the goal point
    that :attr:`goal` gives (the env sets it to its task's ``goal_position``).

    Args:
        run_info: written into every episode's ``/tensegrity/run_info`` (the episode
            number and control period are added).
        markers: write ``/tf`` and ``/tensegrity/markers`` at the control rate.
        wall_clock: stamp a source whose clock starts at 0 (a simulation,
            ``clock_origin_ns`` 0) from the wall clock at the start of each episode,
            floored to a second, plus its time; False keeps stamps from 0. A source
            with a clock of its own (a robot, a replayed bag) keeps its stamps.
    """

    def __init__(
        self,
        run_info: Mapping[str, Any] | None = None,
        *,
        markers: bool = True,
        wall_clock: bool = True,
    ) -> None:
        self.run_info = dict(run_info or {})
        self.markers = markers
        self.wall_clock = wall_clock
        self.goal: Callable[[], NDArray[np.float64] | None] | None = None
        """The goal point (m), (3,), drawn with each estimate; None: no goal."""
        self.writer: MessageWriter | None = None
        self.episodes = 0
        self._truth: GroundTruth | None = None

    def _open(self, episode: Episode) -> MessageWriter:
        """The writer of a new episode."""
        raise NotImplementedError

    def _episode_number(self) -> int:
        return self.episodes

    def begin(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        control_period: float,
        start: RecordedStep,
        *,
        clock_origin_ns: int = 0,
        episode_info: Mapping[str, Any] | None = None,
    ) -> None:
        """Opens the episode's writer, its stamps ``clock_origin_ns`` plus sample times
        (see ``wall_clock``)."""
        self.end()
        if self.wall_clock and not clock_origin_ns:
            clock_origin_ns = wall_clock_origin_ns()
        number = self._episode_number()
        info = {**self.run_info, **(episode_info or {}), "episode": number,
                "control_period": control_period}  # fmt: skip
        self.writer = self._open(Episode(description, calibration, info, clock_origin_ns))
        self.episodes += 1
        self.writer.write_samples(start.samples)
        self._truth = start.truth
        if start.truth is not None:
            self.writer.write_truth(start.truth)

    def step(self, t_command: float, step: RecordedStep) -> None:
        if self.writer is None:
            raise RuntimeError(f"{type(self).__name__}.step before begin")
        self.writer.write_command(t_command, step.command)
        self.writer.write_samples(step.samples)
        self._truth = step.truth
        if step.truth is not None:
            self.writer.write_truth(step.truth)

    def estimate(self, estimate: Estimate, t_log: float) -> None:
        if self.writer is None:
            return
        self.writer.write_estimate(estimate, t_log)
        if self.markers:
            goal = self.goal() if self.goal is not None else None
            self.writer.write_scene(t_log, self._truth, estimate, goal)

    def innovation(self, nis: float, t_log: float) -> None:
        if self.writer is not None and self.markers:
            self.writer.write_innovation(t_log, nis)

    def end(self) -> None:
        writer, self.writer = self.writer, None
        if writer is not None:
            self._close(writer)

    def _close(self, writer: MessageWriter) -> None:
        """The episode of ``writer`` is over."""


class BagSink(WriterSink):
    """Writes each episode to its own bag, ``<folder>/episode_000``, ``episode_001``, ...

    Args:
        folder: where the bags go; created if missing. Existing episodes are not
            overwritten: numbering continues after the highest one present.
        run_info, markers, wall_clock: as :class:`WriterSink` takes them.
        flush_period: seconds of recorded time between flushes to disk.
    """

    def __init__(
        self,
        folder: str | Path,
        run_info: Mapping[str, Any] | None = None,
        *,
        flush_period: float = 1.0,
        markers: bool = True,
        wall_clock: bool = True,
    ) -> None:
        super().__init__(run_info, markers=markers, wall_clock=wall_clock)
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.flush_period = flush_period
        self.paths: list[Path] = []
        taken = [int(p.name[8:]) for p in self.folder.glob("episode_*") if p.name[8:].isdigit()]
        self._next = max(taken, default=-1) + 1

    def _episode_number(self) -> int:
        return self._next

    def _open(self, episode: Episode) -> MessageWriter:
        from hardware.bag.writer import BagWriter

        path = self.folder / f"episode_{self._next:03d}"
        self._next += 1
        writer = BagWriter(
            path,
            episode.description,
            episode.calibration,
            episode.run_info,
            flush_period=self.flush_period,
            clock_origin_ns=episode.clock_origin_ns,
            markers=self.markers,
        )
        self.paths.append(writer.path)
        return writer

    def _close(self, writer: MessageWriter) -> None:
        from hardware.bag.writer import BagWriter

        assert isinstance(writer, BagWriter)
        writer.close()
        log.info("wrote %s (%d messages)", writer.path, writer.message_count)
