"""The contracts between the env and its parts: backends, estimators and tasks."""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np
    from gymnasium import spaces
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate
    from tensegrity_gym.model.samples import GroundTruth, Sample

__all__ = [
    "ActionBase",
    "Backend",
    "Estimator",
    "InitialisationCheck",
    "ReadyCheck",
    "SensorCalibration",
    "StepResult",
    "Task",
    "UwbCalibration",
    "backend_can_wait",
    "backend_sample_kinds",
]


@dataclass(frozen=True)
class SensorCalibration:
    """Per-robot calibration an estimator may use (what a lab would have measured).

    ``uwb_offsets`` holds o_ij of Caluwaerts et al. 2016 eq. 6-7 for every module pair, symmetric,
    (n_modules, n_modules), module ids as in :class:`UwbRangeSample`.
    """

    uwb_offsets: NDArray[np.float64]
    anchors: NDArray[np.float64]
    """(n_anchors, 3) metres."""
    camera_intrinsics: NDArray[np.float64]
    """(3, 3) pixels."""
    camera_pose: NDArray[np.float64]
    """Camera to world transform, (4, 4); the camera looks along its +z axis."""


@dataclass(frozen=True)
class UwbCalibration:
    """The UWB part of a :class:`SensorCalibration` as a lab calibrates it (Caluwaerts et al. 2016
    section III-C): where the anchors stand and every pair's offset, in the world frame
    the anchors define."""

    anchors: NDArray[np.float64]
    """(n_anchors, 3) metres."""
    uwb_offsets: NDArray[np.float64]
    """(n_modules, n_modules) metres, symmetric, as :attr:`SensorCalibration.uwb_offsets`."""
    source: str = "estimated"
    """Where it came from, for ``info`` and the run info: ``"estimated"``, a file's path."""

    def applied_to(self, calibration: SensorCalibration) -> SensorCalibration:
        """``calibration`` with these anchors and offsets; refused, naming both sizes,
        where they are not the same scene's."""
        n, a = calibration.uwb_offsets.shape[0], len(calibration.anchors)
        if self.uwb_offsets.shape != (n, n) or self.anchors.shape != (a, 3):
            raise ValueError(
                f"calibration {self.source!r} has {len(self.anchors)} anchors and "
                f"{self.uwb_offsets.shape[0]} UWB modules; the scene has {a} and {n}"
            )
        return replace(calibration, anchors=self.anchors, uwb_offsets=self.uwb_offsets)


@dataclass(frozen=True)
class StepResult:
    samples: Sequence[Sample]
    """Everything the sensors produced during the control period, in time order."""
    diverged: bool = False
    """The backend's state became non-finite or absurd; the episode must end."""
    info: dict[str, object] = field(default_factory=dict)
    command: NDArray[np.float64] | None = None
    """The rest-length targets (m), (m,), that actually drove the period, where they
    differ from the ones asked for (a replayed log's recorded command); None: as asked."""
    ended: bool = False
    """The source has nothing after this period (a log's end); the episode is truncated."""


ReadyCheck = Callable[[Sequence["Sample"]], "str | None"]
"""``ready(samples) -> None`` when an estimator can initialise from ``samples``, else a
one-line description of what is missing (``"3 UWB ranges to anchors, 4 needed"``)."""


@runtime_checkable
class Backend(Protocol):
    """Where samples come from: a simulation, a robot, or a log."""

    description: RobotDescription
    control_period: float
    """Seconds of robot time one :meth:`step` covers."""

    @property
    def clock_origin_ns(self) -> int:
        """Robot-clock ns of sample time 0: samples carry seconds from it (0 for the
        simulator; a bag's first log time floored to a second; for a robot, set at each
        reset). A recording adds it back, so its stamps are the robot's own."""
        ...

    @property
    def calibration(self) -> SensorCalibration: ...

    def reset(self, rng: np.random.Generator, *, ready: ReadyCheck | None = None) -> StepResult:
        """Start an episode; return the samples of the settling period.

        ``ready(samples)`` says what the estimator still lacks to initialise from
        ``samples`` (None: nothing). A backend that can wait for more waits, within its
        timeout, until it returns None; then a robot raises naming what is missing, and
        the simulator hands over what it has (the estimator starts as it can).
        """
        ...

    def step(self, targets: NDArray[np.float64]) -> StepResult:
        """Command actuated cable rest-length targets (m), (m,); advance one period."""
        ...

    def ground_truth(self) -> GroundTruth | None:
        """The true state where one exists (simulation, motion capture), else None."""
        ...

    def render(self, width: int, height: int) -> NDArray[np.uint8]:
        """A view of the scene for people, (height, width, 3)."""
        ...

    def stop(self) -> None:
        """Hold the motors where they are, now (a robot's safe state); the env calls it
        when anything fails. A no-op where nothing can move (a log)."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class InitialisationCheck(Protocol):
    """Optional for estimators: say before ``reset`` whether samples are enough to start."""

    def initialisation_missing(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
    ) -> str | None:
        """None if ``reset`` can start from ``samples``, else what is missing (one line)."""
        ...


@runtime_checkable
class Estimator(Protocol):
    """Turns samples and commands into an :class:`Estimate`. Sees nothing else."""

    needs_camera: bool
    """True if the estimator uses RGB-D frames; the backend only renders when asked."""

    def reset(
        self,
        description: RobotDescription,
        calibration: SensorCalibration,
        samples: Sequence[Sample],
        command: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> Estimate: ...

    def update(self, samples: Sequence[Sample], command: NDArray[np.float64]) -> Estimate: ...


@runtime_checkable
class ActionBase(Protocol):
    """A scripted controller whose actions a policy's correct (residual actions): the
    env commands ``base(observation) + scale * action``, clipped to [-1, 1]. Reset at
    every episode's start; called once for each observation the task makes (the reset's
    and every step's, the last included), with the task's observation (without the base
    action an env that observes it appends), before the policy acts on it; returns an
    action (m,) in [-1, 1]. :class:`~tensegrity_gym.tasks.gaits.FaceGait` is one."""

    def reset(self) -> None: ...

    def __call__(self, observation: NDArray[np.float32]) -> NDArray[np.float32]: ...


@runtime_checkable
class Task(Protocol):
    """What the robot is asked to do: the observation, the reward and the end of an
    episode, all computed from the estimator's :class:`Estimate` (never ground truth).

    The env calls, per episode, :meth:`reset` once, then per step
    :meth:`implausible_step`, :meth:`reward` (only for a plausible step: an implausible
    one earns 0), :meth:`advance`, :meth:`terminated` and :meth:`observation` in that
    order, and :meth:`progress` and :meth:`info` for ``info``.
    """

    observation_space: spaces.Box
    """Finite bounds, float32; :meth:`observation` always lies inside it."""

    def reset(self, estimate: Estimate, rng: np.random.Generator) -> None:
        """Start an episode from the first estimate; any goal is drawn from ``rng`` (the
        env's ``np_random``, so that a seed fixes it)."""
        ...

    def observation(self, estimate: Estimate) -> NDArray[np.float32]:
        """The policy's observation: finite (NaN in the estimate is cleaned), bounded."""
        ...

    def reward(self, previous: Estimate, estimate: Estimate, action: NDArray[np.float32]) -> float:
        """The reward of the step from ``previous`` to ``estimate`` under ``action``
        (in [-1, 1], (m,)); bounded, 0 progress for an implausible step."""
        ...

    def implausible_step(self, previous: Estimate, estimate: Estimate) -> str | None:
        """Why the step earns no progress (the estimate jumped, or is not finite), else
        None; goes to ``info["reward_rejected"]``."""
        ...

    def terminated(self, estimate: Estimate) -> bool:
        """The task is done: the episode ends (``terminated``)."""
        ...

    def advance(self, previous: Estimate, estimate: Estimate) -> None:
        """Move the task on after the step was rewarded, before :meth:`terminated` is
        asked (a reached goal is replaced; a jump is kept out of the progress)."""
        ...

    def progress(self, estimate: Estimate) -> float:
        """The task's progress since the reset (m), for ``info["progress"]``."""
        ...

    def info(self, estimate: Estimate) -> dict[str, Any]:
        """Task entries for ``info`` beside the env's own (e.g. the goal); may be empty."""
        ...


def backend_can_wait(backend: object) -> bool:
    """Whether ``backend.reset`` takes ``ready=`` (a Backend written before it existed
    does not, and is reset without it)."""
    try:
        params = inspect.signature(backend.reset).parameters  # type: ignore[attr-defined]
    except (AttributeError, TypeError, ValueError):
        return False
    return "ready" in params or any(p.kind is p.VAR_KEYWORD for p in params.values())


def backend_sample_kinds(backend: object) -> frozenset[str] | None:
    """The sample kinds (and ``"ground_truth"``) a backend provides, from its optional
    ``sample_kinds()``; None where it does not say or cannot know yet (a robot before it
    is reached)."""
    method = getattr(backend, "sample_kinds", None)
    if method is None:
        return None
    kinds = method()
    return None if kinds is None else frozenset(kinds)
