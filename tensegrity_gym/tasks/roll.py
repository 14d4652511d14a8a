"""Rolling: move the estimated centre of mass along a goal heading on flat ground.

Observation: the robot in the goal frame (:mod:`tensegrity_gym.tasks.common`: node
positions (n, 3) and velocities (n, 3) in rod lengths L, rest lengths (m,) in [-1, 1]),
x along the goal heading, followed by

==============  ==========  ===================================================
slice           shape       meaning
==============  ==========  ===================================================
goal            (2,)        goal heading in the world frame, (cos, sin)
==============  ==========  ===================================================

Reward per step: ``progress_weight * progress / L - ctrl_cost * mean(action**2)``,
with ``progress`` the estimated CoM's displacement along the goal heading (m) and
``action`` the policy's (with residual actions, its correction of the gait before the
scale). A step whose estimated CoM moved farther than the robot can travel in one
period (an estimate that jumped) earns no progress: :meth:`RollTask.implausible_step`
says why.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tensegrity_gym.model.checks import check_optional_number
from tensegrity_gym.tasks.common import (
    POSITION_BOUND,
    SPEED_MARGIN,
    VELOCITY_BOUND,
    GoalFrameTask,
    max_speed,
)
from tensegrity_gym.tasks.common import TaskObservation as RollObservation

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate

__all__ = [
    "POSITION_BOUND",
    "SPEED_MARGIN",
    "VELOCITY_BOUND",
    "RollObservation",
    "RollTask",
    "max_speed",
]


class RollTask(GoalFrameTask):
    """Reward progress of the estimated CoM along a goal heading.

    Args:
        description: the robot.
        goal_heading: heading of the goal direction (rad, world frame); ``None`` draws
            one uniformly per episode from the env's generator.
        goal_distance: if set, the episode terminates once the CoM has moved this far
            (m) along the heading: the task is done.
        ctrl_cost, progress_weight, control_period: see
            :class:`~tensegrity_gym.tasks.common.GoalFrameTask`.
    """

    def __init__(
        self,
        description: RobotDescription,
        *,
        goal_heading: float | None = 0.0,
        goal_distance: float | None = None,
        ctrl_cost: float = 0.05,
        progress_weight: float = 10.0,
        control_period: float = 0.1,
    ) -> None:
        self.goal_heading = check_optional_number("goal_heading", goal_heading)
        self.goal_distance = check_optional_number("goal_distance", goal_distance, positive=True)
        super().__init__(
            description,
            goal_low=np.full(2, -1.0),
            goal_high=np.full(2, 1.0),
            ctrl_cost=ctrl_cost,
            progress_weight=progress_weight,
            control_period=control_period,
        )
        self.episode_goal_distance = self.goal_distance
        """This episode's ``goal_distance`` (m; the reset's option, else the task's)."""
        self.heading = 0.0
        self.direction = np.array([1.0, 0.0])
        self.start = np.zeros(3)
        self._jumped = 0.0  # m along the heading moved in implausible steps

    goal_feature_meanings = (
        ("cos of the goal heading, world frame", "1"),
        ("sin of the goal heading, world frame", "1"),
    )
    """The goal features (:meth:`GoalFrameTask.observation_layout`): the goal heading."""

    reset_options = frozenset({"goal_heading", "goal_distance"})
    """The keys of ``env.reset(options=...)`` that :meth:`reset` takes."""

    def reset(self, estimate: Estimate, rng: np.random.Generator, **options: object) -> None:
        """Start an episode. ``options`` may set, for this episode only, ``goal_heading``
        (rad, world frame; None draws one) and ``goal_distance`` (m; None: no end)."""
        h, self.episode_goal_distance = self.goal_heading, self.goal_distance
        if "goal_heading" in options:
            h = check_optional_number("goal_heading", options["goal_heading"], where="reset")
        if "goal_distance" in options:
            self.episode_goal_distance = check_optional_number(
                "goal_distance", options["goal_distance"], positive=True, where="reset"
            )
        self.heading = float(rng.uniform(-np.pi, np.pi)) if h is None else float(h)
        self.direction = np.array([np.cos(self.heading), np.sin(self.heading)])
        self.start = estimate.com.copy()
        self._jumped = 0.0

    def advance(self, previous: Estimate, estimate: Estimate) -> None:
        """An implausible step (an estimate that jumped) does not count as progress, so
        it can neither earn reward nor end the episode as done."""
        if self.implausible_step(previous, estimate) is None:
            return
        with np.errstate(invalid="ignore", over="ignore"):
            jump = float((estimate.com[:2] - previous.com[:2]) @ self.direction)
        if np.isfinite(jump):
            self._jumped += jump

    def frame_direction(self, estimate: Estimate) -> NDArray[np.float64]:
        return self.direction

    def goal_features(
        self, estimate: Estimate, direction: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return self.direction

    def progress(self, estimate: Estimate) -> float:
        """Distance (m) the CoM has moved along the goal heading since the reset, less
        what it moved in implausible steps (see :meth:`advance`)."""
        return float((estimate.com[:2] - self.start[:2]) @ self.direction) - self._jumped

    def reward(self, previous: Estimate, estimate: Estimate, action: NDArray[np.float32]) -> float:
        if self.implausible_step(previous, estimate) is not None:
            return 0.0
        step = float((estimate.com[:2] - previous.com[:2]) @ self.direction)
        return self.progress_weight * step / self.scale - self.control_cost(action)

    def goal_position(self) -> NDArray[np.float64]:
        """For viewers (m, world frame), (3,): the point on the ground the episode's
        goal distance ahead of the start along the heading, or 1 m ahead where the
        episode has no goal distance."""
        ahead = self.episode_goal_distance if self.episode_goal_distance is not None else 1.0
        return np.array([*(self.start[:2] + ahead * self.direction), 0.0])

    def terminated(self, estimate: Estimate) -> bool:
        goal = self.episode_goal_distance
        return goal is not None and self.progress(estimate) >= goal
