"""What an estimator hands the task: the estimated state of the robot."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Mapping

    from numpy.typing import NDArray

__all__ = ["Estimate"]


@dataclass(frozen=True, slots=True)
class Estimate:
    t: float
    node_positions: NDArray[np.float64]
    """(n_nodes, 3) metres."""
    node_velocities: NDArray[np.float64]
    """(n_nodes, 3) m/s."""
    com: NDArray[np.float64]
    """Centre of mass, (3,)."""
    rest_lengths: NDArray[np.float64]
    """Latest measured rest lengths of the actuated cables (m), (m,)."""
    covariance: NDArray[np.float64] | None = None
    """State covariance where the method has one, (6 n_nodes, 6 n_nodes)."""
    healthy: bool = True
    """False while the estimator has lost track or has just been re-initialised."""
    reinitialised: bool = False
    """True on the update in which the estimator re-initialised itself."""
    reinitialised_because: str | None = None
    """Why, on that update, where the estimator says (``"off the ground"``, ``"rods
    stretched"``, ...); None otherwise."""
    rod_quaternions: NDArray[np.float64] | None = None
    """Rod orientations (r, 4), (x, y, z, w), body z from a rod's first node to its second,
    where the method tracks the turn about the axis; None where it does not (the axis
    alone is known: ``rod_quaternion_from_axis`` gives the canonical orientation)."""
    failed_streams: tuple[str, ...] = ()
    """Sensor streams the estimator has stopped fusing because they were implausible for a
    while (e.g. ``"uwb"``, ``"imu/red"``, ``"cable_lengths"``); empty while all are fused."""
    rejected: Mapping[str, int] | None = None
    """Measurements rejected as physically implausible since the last reset, counted by
    kind (e.g. ``"uwb_range_too_long"``); None where the method does not count them."""
    description_mismatch: tuple[str, ...] = ()
    """Where the readings contradict the robot description, a line each (``"motor 2
    (cable 'c2') reads 0.067-0.197 m, the description's motor range is 0.124-0.237
    m"``): readings kept in use, the description is what is off."""
    pose_covariance: NDArray[np.float64] | None = None
    """Covariance of the body pose where the method tracks one (the invariant EKF), (6, 6):
    rotation error (rad, world frame) then position (m)."""

    def is_finite(self) -> bool:
        return bool(
            np.all(np.isfinite(self.node_positions))
            and np.all(np.isfinite(self.node_velocities))
            and np.all(np.isfinite(self.com))
        )
