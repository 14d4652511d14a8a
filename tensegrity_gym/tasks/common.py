"""What the tasks share: the robot seen in a goal frame, the bound on a step, the cost.

Observation (float32, every entry bounded), in the *goal frame* (x along the task's
direction, z up, origin at the estimated CoM), lengths in units of the robot's rod
length L and time in seconds:

==============  ==========  ===================================================
slice           shape       meaning
==============  ==========  ===================================================
positions       (n, 3)      node positions relative to the CoM / L, in [-2, 2]
velocities      (n, 3)      node velocities / (L per s), in [-10, 10]
rest_lengths    (m,)        actuated rest lengths mapped to [-1, 1] over the motor range
goal            (k,)        the task's own goal features (see each task)
==============  ==========  ===================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from gymnasium import spaces

from tensegrity_gym.model.checks import check_number

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate

__all__ = [
    "POSITION_BOUND",
    "SPEED_MARGIN",
    "VELOCITY_BOUND",
    "GoalFrameTask",
    "ObservationField",
    "TaskObservation",
    "max_speed",
]

POSITION_BOUND = 2.0
VELOCITY_BOUND = 10.0
SPEED_MARGIN = 2.0
"""The CoM's travel in a period is bounded by this many times the speed of a fall from
the robot's resting span, its largest node-node distance (or its fastest motor, if
faster): see :func:`max_speed`."""


@dataclass(frozen=True)
class TaskObservation:
    """An observation split back into its parts (see the module docstring)."""

    positions: NDArray[np.float32]
    velocities: NDArray[np.float32]
    rest_lengths: NDArray[np.float32]
    goal: NDArray[np.float32]


@dataclass(frozen=True)
class ObservationField:
    """Entries ``observation[start:stop]`` that share one meaning, unit and bounds: the
    (x, y, z) of a node, one rest length, one goal feature (see
    :meth:`GoalFrameTask.observation_layout`)."""

    start: int
    stop: int
    """One past the last entry: the field is ``stop - start`` entries."""
    meaning: str
    units: str
    """``"L"`` (rod lengths), ``"L/s"``, ``"1"`` (unitless) or ``"[-1, 1] of the motor
    range"``."""
    low: float
    high: float
    """The observation space's bounds of every entry of the field."""


class GoalFrameTask:
    """The part of a task that does not depend on its goal: the observation of the
    robot in a goal frame, the plausibility of a step and the control cost.

    A subclass says where the goal frame points (:meth:`frame_direction`) and what the
    goal part of the observation holds (:meth:`goal_features`, bounded by ``goal_low``
    and ``goal_high``); it implements the rest of the :class:`~tensegrity_gym.model.
    protocols.Task` protocol.

    Args:
        description: the robot.
        goal_low, goal_high: bounds of the goal features, (k,).
        ctrl_cost: weight of the mean squared action: the policy's own, which with
            residual actions is its correction of the gait before the scale (the gait's
            commands are free).
        progress_weight: reward per rod length of progress.
        control_period: seconds per step; bounds the progress a step can earn.
    """

    def __init__(
        self,
        description: RobotDescription,
        *,
        goal_low: NDArray[np.float64],
        goal_high: NDArray[np.float64],
        ctrl_cost: float,
        progress_weight: float,
        control_period: float,
    ) -> None:
        self.description = description
        self.ctrl_cost = check_number("ctrl_cost", ctrl_cost, non_negative=True)
        self.progress_weight = check_number("progress_weight", progress_weight)
        period = check_number("control_period", control_period, positive=True)
        self.max_step = period * max_speed(description)
        """The farthest (m) the CoM can physically travel in one period."""
        self.scale = description.characteristic_length
        lo, hi, _ = description.motor_limits
        self._rest_lo, self._rest_span = lo, hi - lo
        n, m = description.n_nodes, description.n_actuated
        body = np.concatenate(
            [np.full(3 * n, POSITION_BOUND), np.full(3 * n, VELOCITY_BOUND), np.ones(m)]
        )
        low = np.concatenate([-body, goal_low]).astype(np.float32)
        high = np.concatenate([body, goal_high]).astype(np.float32)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self._sizes = (3 * n, 3 * n, m, len(goal_low))

    goal_feature_meanings: tuple[tuple[str, str], ...] = ()
    """(meaning, units) of each goal feature, in order, for :meth:`observation_layout`;
    a subclass names its own (where it names none: "goal feature i", unitless)."""

    def observation_layout(self) -> list[ObservationField]:
        """The observation, entry by entry in order, as fields: each node's position
        (x, y, z) relative to the CoM in L, each node's velocity in L/s, each actuated
        cable's rest length in [-1, 1] over its motor's range, then each goal feature;
        bounds from :attr:`observation_space`. The fields cover ``observation()``'s
        ``sum(sizes)`` entries exactly (what an env appends is not the task's)."""
        d = self.description
        names = [node.name for node in d.nodes]
        lo, hi, _ = d.motor_limits
        rows: list[tuple[str, str]] = []
        rows += [(f"node {x} position (x, y, z) relative to the CoM", "L") for x in names]
        rows += [(f"node {x} velocity (x, y, z)", "L/s") for x in names]
        for k, index in enumerate(d.actuated):
            cable = d.cables[int(index)]
            a, b = (names[i] for i in cable.nodes)
            rows.append((
                f"cable {cable.name} ({a}-{b}) rest length: -1 at {lo[k]:.5g} m, "
                f"1 at {hi[k]:.5g} m",
                "[-1, 1] of the motor range",
            ))  # fmt: skip
        k_goal = self._sizes[3]
        meanings = self.goal_feature_meanings
        if len(meanings) != k_goal:
            meanings = tuple((f"goal feature {i}", "1") for i in range(k_goal))
        rows += meanings
        widths = [3] * (2 * d.n_nodes) + [1] * (d.n_actuated + k_goal)
        return self._fields(rows, widths)

    def _fields(self, rows: list[tuple[str, str]], widths: list[int]) -> list[ObservationField]:
        """``rows`` (meaning, units) of ``widths`` entries each, laid end to end."""
        low, high = self.observation_space.low, self.observation_space.high
        fields, start = [], 0
        for (meaning, units), width in zip(rows, widths, strict=True):
            stop = start + width
            field = ObservationField(start, stop, meaning, units,
                                     float(low[start]), float(high[start]))  # fmt: skip
            if np.any(low[start:stop] != field.low) or np.any(high[start:stop] != field.high):
                raise ValueError(f"observation entries {start}:{stop} differ in their bounds")
            fields.append(field)
            start = stop
        return fields

    def frame_direction(self, estimate: Estimate) -> NDArray[np.float64]:
        """The goal frame's x axis in the world's ground plane, a unit (2,)."""
        raise NotImplementedError

    def goal_features(
        self, estimate: Estimate, direction: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """The goal part of the observation, (k,) (clipped to its bounds afterwards)."""
        raise NotImplementedError

    def to_frame(
        self, v: NDArray[np.float64], direction: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Vectors (..., 3) turned about z from the world into the goal frame."""
        c, s = direction
        out = v.copy()
        out[..., 0] = c * v[..., 0] + s * v[..., 1]
        out[..., 1] = -s * v[..., 0] + c * v[..., 1]
        return out

    def observation(self, estimate: Estimate) -> NDArray[np.float32]:
        direction = self.frame_direction(estimate)
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite input is cleaned below
            rel = self.to_frame(estimate.node_positions - estimate.com, direction) / self.scale
            vel = self.to_frame(estimate.node_velocities, direction) / self.scale
            rest = 2.0 * (estimate.rest_lengths - self._rest_lo) / self._rest_span - 1.0
            goal = self.goal_features(estimate, direction)
        obs = np.concatenate([rel.ravel(), vel.ravel(), rest, goal])
        # nan_to_num first: a policy never sees NaN, whatever the estimator did.
        obs = np.nan_to_num(obs, nan=0.0, posinf=0.0, neginf=0.0)
        bounded = np.clip(obs, self.observation_space.low, self.observation_space.high)
        return np.asarray(bounded, dtype=np.float32)

    def decode(self, observation: NDArray[np.float32]) -> TaskObservation:
        """An observation split back into its parts; ValueError for one of another size
        (an env's, with what it appends)."""
        observation = np.asarray(observation)
        if observation.shape != (sum(self._sizes),):
            raise ValueError(
                f"{type(self).__name__}.decode: an observation of shape {observation.shape}, "
                f"expected ({sum(self._sizes)},) (the task's own, without what an env appends)"
            )
        parts = np.split(observation, np.cumsum(self._sizes)[:-1])
        n = self.description.n_nodes
        return TaskObservation(
            positions=parts[0].reshape(n, 3),
            velocities=parts[1].reshape(n, 3),
            rest_lengths=parts[2],
            goal=parts[3],
        )

    def implausible_step(self, previous: Estimate, estimate: Estimate) -> str | None:
        """Why the step from ``previous`` to ``estimate`` earns no reward at all (it is
        farther than the robot can travel in a period, or not finite, or the estimator
        started again: the jump to where it now places the robot is no motion), else
        None."""
        if estimate.reinitialised:
            return "the estimator started again; its jump is not the robot's motion"
        with np.errstate(invalid="ignore", over="ignore"):
            moved = float(np.linalg.norm(estimate.com[:2] - previous.com[:2]))
        if not np.isfinite(moved):
            return "the estimated CoM is not finite"
        if moved > self.max_step:
            return (
                f"the estimated CoM moved {moved:.3g} m in one period; the robot cannot "
                f"travel more than {self.max_step:.3g} m"
            )
        return None

    def control_cost(self, action: NDArray[np.float32]) -> float:
        """``ctrl_cost * mean(action**2)`` for an action in [-1, 1], (m,)."""
        return self.ctrl_cost * float(np.mean(np.square(action)))

    def advance(self, previous: Estimate, estimate: Estimate) -> None:
        """Nothing to move on (a task with changing goals overrides it)."""

    def info(self, estimate: Estimate) -> dict[str, Any]:
        """No entries of its own (a task with a goal overrides it)."""
        return {}


def max_speed(description: RobotDescription) -> float:
    """A bound (m/s) on the CoM's horizontal speed: :data:`SPEED_MARGIN` times the speed
    of a fall from the robot's resting span, or of its fastest motor if that is faster."""
    x = description.initial_positions
    span = float(np.max(np.linalg.norm(x[:, None] - x[None], axis=-1)))
    fall = float(np.sqrt(2.0 * description.gravity * span))
    return SPEED_MARGIN * max(fall, float(np.max(description.motor_limits[2])))
