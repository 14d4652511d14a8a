"""Rolling: move the estimated centre of mass along a goal heading on flat ground.

Observation (float32, every entry bounded), in the *goal frame* (x along the goal
heading, z up, origin at the estimated CoM), lengths in units of the robot's rod
length L and time in seconds:

==============  ==========  ===================================================
slice           shape       meaning
==============  ==========  ===================================================
positions       (n, 3)      node positions relative to the CoM / L, in [-2, 2]
velocities      (n, 3)      node velocities / (L per s), in [-10, 10]
rest_lengths    (m,)        actuated rest lengths mapped to [-1, 1] over the motor range
goal            (2,)        goal heading in the world frame, (cos, sin)
==============  ==========  ===================================================

Reward per step: ``progress_weight * progress / L - ctrl_cost * mean(action**2)``,
with ``progress`` the estimated CoM's displacement along the goal heading (m). A step
whose estimated CoM moved farther than the robot can travel in one period (an estimate
that jumped) earns no progress: :meth:`RollTask.implausible_step` says why.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from gymnasium import spaces

from tensegrity_gym.model.checks import check_number, check_optional_number

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription
    from tensegrity_gym.model.estimate import Estimate

__all__ = ["RollObservation", "RollTask", "max_speed"]

POSITION_BOUND = 2.0
VELOCITY_BOUND = 10.0
SPEED_MARGIN = 2.0
"""The CoM's travel in a period is bounded by this many times the speed of a fall from
the robot's own height (or its fastest motor, if faster)."""


@dataclass(frozen=True)
class RollObservation:
    """An observation split back into its parts (see the module docstring)."""

    positions: NDArray[np.float32]
    velocities: NDArray[np.float32]
    rest_lengths: NDArray[np.float32]
    goal: NDArray[np.float32]


class RollTask:
    """Reward progress of the estimated CoM along a goal heading.

    Args:
        description: the robot.
        goal_heading: heading of the goal direction (rad, world frame); ``None`` draws
            one uniformly per episode from the env's generator.
        goal_distance: if set, the episode terminates once the CoM has moved this far
            (m) along the heading: the task is done.
        ctrl_cost: weight of the mean squared action.
        progress_weight: reward per rod length of progress.
        control_period: seconds per step; bounds the progress a step can earn.
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
        self.description = description
        self.goal_heading = check_optional_number("goal_heading", goal_heading)
        self.goal_distance = check_optional_number("goal_distance", goal_distance, positive=True)
        self.ctrl_cost = check_number("ctrl_cost", ctrl_cost, non_negative=True)
        self.progress_weight = check_number("progress_weight", progress_weight)
        period = check_number("control_period", control_period, positive=True)
        self.max_step = period * max_speed(description)
        """The farthest (m) the CoM can physically travel in one period."""
        self.scale = description.characteristic_length
        lo, hi, _ = description.motor_limits
        self._rest_lo, self._rest_span = lo, hi - lo
        n, m = description.n_nodes, description.n_actuated
        low = np.concatenate(
            [
                np.full(3 * n, -POSITION_BOUND),
                np.full(3 * n, -VELOCITY_BOUND),
                np.full(m, -1.0),
                np.full(2, -1.0),
            ]
        ).astype(np.float32)
        self.observation_space = spaces.Box(low, -low, dtype=np.float32)
        self._sizes = (3 * n, 3 * n, m, 2)
        self.heading = 0.0
        self.direction = np.array([1.0, 0.0])
        self.start = np.zeros(3)

    def reset(self, estimate: Estimate, rng: np.random.Generator) -> None:
        h = self.goal_heading
        self.heading = float(rng.uniform(-np.pi, np.pi)) if h is None else float(h)
        self.direction = np.array([np.cos(self.heading), np.sin(self.heading)])
        self.start = estimate.com.copy()

    def _to_goal_frame(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        c, s = self.direction
        out = v.copy()
        out[..., 0] = c * v[..., 0] + s * v[..., 1]
        out[..., 1] = -s * v[..., 0] + c * v[..., 1]
        return out

    def observation(self, estimate: Estimate) -> NDArray[np.float32]:
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite input is cleaned below
            rel = self._to_goal_frame(estimate.node_positions - estimate.com) / self.scale
            vel = self._to_goal_frame(estimate.node_velocities) / self.scale
            rest = 2.0 * (estimate.rest_lengths - self._rest_lo) / self._rest_span - 1.0
        obs = np.concatenate([rel.ravel(), vel.ravel(), rest, self.direction])
        # nan_to_num first: a policy never sees NaN, whatever the estimator did.
        obs = np.nan_to_num(obs, nan=0.0, posinf=0.0, neginf=0.0)
        bounded = np.clip(obs, self.observation_space.low, self.observation_space.high)
        return np.asarray(bounded, dtype=np.float32)

    def decode(self, observation: NDArray[np.float32]) -> RollObservation:
        parts = np.split(np.asarray(observation), np.cumsum(self._sizes)[:-1])
        n = self.description.n_nodes
        return RollObservation(
            positions=parts[0].reshape(n, 3),
            velocities=parts[1].reshape(n, 3),
            rest_lengths=parts[2],
            goal=parts[3],
        )

    def progress(self, estimate: Estimate) -> float:
        """Distance (m) the CoM has moved along the goal heading since the reset."""
        return float((estimate.com[:2] - self.start[:2]) @ self.direction)

    def implausible_step(self, previous: Estimate, estimate: Estimate) -> str | None:
        """Why the step from ``previous`` to ``estimate`` earns no reward at all (it is
        farther than the robot can travel in a period, or not finite), else None."""
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

    def reward(self, previous: Estimate, estimate: Estimate, action: NDArray[np.float32]) -> float:
        if self.implausible_step(previous, estimate) is not None:
            return 0.0
        cost = self.ctrl_cost * float(np.mean(np.square(action)))
        step = float((estimate.com[:2] - previous.com[:2]) @ self.direction)
        return self.progress_weight * step / self.scale - cost

    def terminated(self, estimate: Estimate) -> bool:
        return self.goal_distance is not None and self.progress(estimate) >= self.goal_distance


def max_speed(description: RobotDescription) -> float:
    """A bound (m/s) on the CoM's horizontal speed: :data:`SPEED_MARGIN` times the speed
    of a fall from the robot's resting span, or of its fastest motor if that is faster."""
    x = description.initial_positions
    span = float(np.max(np.linalg.norm(x[:, None] - x[None], axis=-1)))
    fall = float(np.sqrt(2.0 * description.gravity * span))
    return SPEED_MARGIN * max(fall, float(np.max(description.motor_limits[2])))
