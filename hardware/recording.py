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
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from tensegrity_gym.model.protocols import backend_can_wait
from tensegrity_gym.model.samples import ns_to_seconds, seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from numpy.typing import NDArray

    from hardware.bag.writer import BagWriter
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
    "MemorySink",
    "RecordedRun",
    "RecordedStep",
    "RecordingBackend",
    "RecordingEstimator",
    "RunSink",
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
        try:
            self.sink.end()
        finally:
            self.inner.close()


class RecordingEstimator:
    """An estimator that hands each estimate to a sink, logged at the period's end."""

    def __init__(self, inner: Estimator, sink: RunSink, backend: RecordingBackend) -> None:
        self.inner = inner
        self.sink = sink
        self.backend = backend
        self.needs_camera = inner.needs_camera

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
        self.sink.estimate(estimate, self.backend.t_command)
        return estimate

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate:
        estimate = self.inner.update(samples, command)
        self.sink.estimate(estimate, self.backend.t_command)
        return estimate


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

    def end(self) -> None:
        pass


class BagSink:
    """Writes each episode to its own bag, ``<folder>/episode_000``, ``episode_001``, ...

    Args:
        folder: where the bags go; created if missing. Existing episodes are not
            overwritten: numbering continues after the highest one present.
        run_info: written into every bag's ``/tensegrity/run_info`` (the episode number
            and control period are added).
        flush_period: seconds of recorded time between flushes to disk.
    """

    def __init__(
        self,
        folder: str | Path,
        run_info: Mapping[str, Any] | None = None,
        *,
        flush_period: float = 1.0,
    ) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.run_info = dict(run_info or {})
        self.flush_period = flush_period
        self.writer: BagWriter | None = None
        self.paths: list[Path] = []
        taken = [int(p.name[8:]) for p in self.folder.glob("episode_*") if p.name[8:].isdigit()]
        self._next = max(taken, default=-1) + 1

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
        """Opens the episode's bag, its stamps ``clock_origin_ns`` plus sample times."""
        from hardware.bag.writer import BagWriter

        self.end()
        path = self.folder / f"episode_{self._next:03d}"
        info = {**self.run_info, **(episode_info or {}), "episode": self._next,
                "control_period": control_period}  # fmt: skip
        self._next += 1
        self.writer = BagWriter(
            path,
            description,
            calibration,
            info,
            flush_period=self.flush_period,
            clock_origin_ns=clock_origin_ns,
        )
        self.paths.append(self.writer.path)
        self.writer.write_samples(start.samples)
        if start.truth is not None:
            self.writer.write_truth(start.truth)

    def step(self, t_command: float, step: RecordedStep) -> None:
        if self.writer is None:
            raise RuntimeError("BagSink.step before begin")
        self.writer.write_command(t_command, step.command)
        self.writer.write_samples(step.samples)
        if step.truth is not None:
            self.writer.write_truth(step.truth)

    def estimate(self, estimate: Estimate, t_log: float) -> None:
        if self.writer is not None:
            self.writer.write_estimate(estimate, t_log)

    def end(self) -> None:
        writer, self.writer = self.writer, None
        if writer is not None:
            writer.close()
            log.info("wrote %s (%d messages)", writer.path, writer.message_count)
