"""Go to a goal: reach points on the ground one after another, a new one after each.

Each goal is a point on the ground drawn from the env's generator at a distance in
``goal_range`` (m) from the estimated CoM, in a uniformly drawn direction. Once the
estimated CoM is within ``success_radius`` of it (on a plausible step), the goal counts
as reached and the next one is drawn from where the robot is; the episode runs until
the time limit (``terminated`` is never set).

Observation: the robot in the goal frame (:mod:`tensegrity_gym.tasks.common`), x from
the estimated CoM toward the goal, z up, followed by

==============  ==========  ===================================================
slice           shape       meaning
==============  ==========  ===================================================
goal            (3,)        the direction to the goal in the world frame
                            (cos, sin), and the distance to it / L, in
                            [0, 2 * goal_range[1] / L]
==============  ==========  ===================================================

Reward per step: ``progress_weight * progress / L - ctrl_cost * mean(action**2)``, plus
``success_bonus`` on the step that reaches a goal, with ``progress`` how much closer
(m) the estimated CoM came to the goal and ``action`` the policy's (with residual
actions, its correction of the gait before the scale). An implausible step (an
estimate that jumped, :meth:`GoToTask.implausible_step`) earns nothing and reaches no
goal.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from tensegrity_gym.model.checks import check_number
from tensegrity_gym.tasks.common import GoalFrameTask

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate

__all__ = ["GOAL_RANGE", "SUCCESS_RADIUS", "GoToTask"]

GOAL_RANGE = (2.0, 4.0)
"""Default distance range of a goal, in rod lengths L (0.65-1.3 m for the 3-bar robot,
2.9-5.8 m for the large one, 3-6 m for SUPERball)."""
SUCCESS_RADIUS = 0.5
"""Default success radius, in rod lengths L: about one roll onto the next face."""


def _check_range(value: object) -> tuple[float, float]:
    """``goal_range`` as (near, far) metres, 0 < near <= far; ValueError naming it."""
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f"make: goal_range={value!r} must be a pair (near, far) of metres")
    near = check_number("goal_range[0]", value[0], positive=True)
    far = check_number("goal_range[1]", value[1], positive=True)
    if far < near:
        raise ValueError(f"make: goal_range={value!r}: far must not be below near")
    return near, far


def _check_goal(value: object) -> NDArray[np.float64]:
    """``reset(options={"goal": ...})`` as a (2,) array (m); ValueError naming it."""
    if not isinstance(value, (tuple, list, np.ndarray)) or len(value) != 2:
        raise ValueError(f"reset: goal={value!r} must be a point (x, y) in metres")
    x = check_number("goal[0]", value[0], where="reset")
    return np.array([x, check_number("goal[1]", value[1], where="reset")])


class GoToTask(GoalFrameTask):
    """Reward the estimated CoM's approach to a goal point; a new goal after each success.

    Args:
        description: the robot.
        goal_range: (near, far), the distance (m) of each goal from the CoM; ``None``:
            :data:`GOAL_RANGE` rod lengths.
        success_radius: a goal is reached within this distance (m) of the CoM,
            horizontally; ``None``: :data:`SUCCESS_RADIUS` rod lengths. Below ``near``.
        success_bonus: reward for each goal reached.
        ctrl_cost, progress_weight, control_period: see
            :class:`~tensegrity_gym.tasks.common.GoalFrameTask`.
    """

    def __init__(
        self,
        description: RobotDescription,
        *,
        goal_range: tuple[float, float] | None = None,
        success_radius: float | None = None,
        success_bonus: float = 10.0,
        ctrl_cost: float = 0.05,
        progress_weight: float = 10.0,
        control_period: float = 0.1,
    ) -> None:
        length = description.characteristic_length
        if goal_range is None:
            goal_range = (GOAL_RANGE[0] * length, GOAL_RANGE[1] * length)
        self.goal_range = _check_range(goal_range)
        radius = SUCCESS_RADIUS * length if success_radius is None else success_radius
        self.success_radius = check_number("success_radius", radius, positive=True)
        if self.success_radius >= self.goal_range[0]:
            raise ValueError(
                f"make: success_radius={radius!r} must be below goal_range[0]="
                f"{self.goal_range[0]!r}, or a goal would be reached where it is drawn"
            )
        self.success_bonus = check_number("success_bonus", success_bonus, non_negative=True)
        far = 2.0 * self.goal_range[1] / length
        super().__init__(
            description,
            goal_low=np.array([-1.0, -1.0, 0.0]),
            goal_high=np.array([1.0, 1.0, far]),
            ctrl_cost=ctrl_cost,
            progress_weight=progress_weight,
            control_period=control_period,
        )
        self.goal = np.zeros(2)
        """The current goal (m), world frame, (2,)."""
        self.goals_reached = 0
        self._direction = np.array([1.0, 0.0])
        self._covered = 0.0  # initial distances (m) of the goals reached
        self._initial = 0.0  # distance (m) of the current goal when it was drawn
        self._rng = np.random.default_rng(0)  # replaced by the env's at reset

    def _draw(self, centre: NDArray[np.float64]) -> None:
        """A new goal around ``centre`` (m, (3,); the origin if it is not finite), from
        the env's generator."""
        if not np.all(np.isfinite(centre[:2])):
            centre = np.zeros(3)
        heading = float(self._rng.uniform(-np.pi, np.pi))
        distance = float(self._rng.uniform(*self.goal_range))
        self.goal = centre[:2] + distance * np.array([np.cos(heading), np.sin(heading)])
        self._initial = distance

    goal_feature_meanings = (
        ("cos of the direction to the goal, world frame", "1"),
        ("sin of the direction to the goal, world frame", "1"),
        ("horizontal distance from the estimated CoM to the goal", "L"),
    )
    """The goal features (:meth:`GoalFrameTask.observation_layout`): where the goal is."""

    reset_options = frozenset({"goal"})
    """The keys of ``env.reset(options=...)`` that :meth:`reset` takes."""

    def reset(self, estimate: Estimate, rng: np.random.Generator, **options: object) -> None:
        """Start an episode. ``options`` may set its first goal, ``goal`` (x, y) (m,
        world frame); the goals after it are drawn as usual."""
        self._rng = rng
        self.goals_reached, self._covered = 0, 0.0
        if "goal" in options:
            self.goal = _check_goal(options["goal"])
            initial = self.distance(estimate)  # NaN where the CoM is unknown: from the origin
            self._initial = initial if np.isfinite(initial) else float(np.linalg.norm(self.goal))
        else:
            self._draw(estimate.com)
        self._direction = np.array([1.0, 0.0])
        self.frame_direction(estimate)

    def distance(self, estimate: Estimate) -> float:
        """Horizontal distance (m) from the estimated CoM to the goal (NaN if unknown)."""
        with np.errstate(invalid="ignore", over="ignore"):
            return float(np.linalg.norm(self.goal - estimate.com[:2]))

    def frame_direction(self, estimate: Estimate) -> NDArray[np.float64]:
        """Toward the goal; the last such direction when the CoM is on it or unknown."""
        with np.errstate(invalid="ignore", over="ignore"):
            offset = self.goal - estimate.com[:2]
            norm = float(np.linalg.norm(offset))
        if np.isfinite(norm) and norm > 1e-9:
            self._direction = offset / norm
        return self._direction

    def goal_features(
        self, estimate: Estimate, direction: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return np.array([direction[0], direction[1], self.distance(estimate) / self.scale])

    def reached(self, previous: Estimate, estimate: Estimate) -> bool:
        """The step reaches the goal: plausible, and ends within the success radius."""
        if self.implausible_step(previous, estimate) is not None:
            return False
        return self.distance(estimate) <= self.success_radius

    def reward(self, previous: Estimate, estimate: Estimate, action: NDArray[np.float32]) -> float:
        if self.implausible_step(previous, estimate) is not None:
            return 0.0
        step = self.distance(previous) - self.distance(estimate)
        reward = self.progress_weight * step / self.scale - self.control_cost(action)
        return reward + (self.success_bonus if self.reached(previous, estimate) else 0.0)

    def advance(self, previous: Estimate, estimate: Estimate) -> None:
        """Count a reached goal and draw the next one from the estimated CoM."""
        if self.reached(previous, estimate):
            self.goals_reached += 1
            self._covered += self._initial
            self._draw(estimate.com)

    def terminated(self, estimate: Estimate) -> bool:
        return False

    def progress(self, estimate: Estimate) -> float:
        """Approach (m) since the reset: the drawn distances of the goals reached plus
        how much closer the CoM is to the current goal than when it was drawn."""
        return self._covered + self._initial - self.distance(estimate)

    def goal_position(self) -> NDArray[np.float64]:
        """The current goal on the ground (m, world frame), (3,), for viewers."""
        return np.array([self.goal[0], self.goal[1], 0.0])

    def info(self, estimate: Estimate) -> dict[str, Any]:
        """``goal`` (m, world frame, (2,)), ``distance_to_goal`` (m), ``goals_reached``."""
        return {
            "goal": self.goal.copy(),
            "distance_to_goal": self.distance(estimate),
            "goals_reached": self.goals_reached,
        }
