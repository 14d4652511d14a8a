"""The UKF's process noise Q: per node, per contact state, larger while the robot is
driven, and optionally shared by every node (:class:`ProcessNoise`).

The spring-mass model is close for a robot at rest and rough for a rolling one: a
touch-down, a tip over an edge, a slip are where the simulator's (or a real robot's)
physics and the model part. With the noise fitted to a resting robot a rolling one was
estimated three to five times overconfident (NEES per dof 3.4 nominal, 5.7 under the
``"mild"`` randomisation), most of it in the motion of the robot as a whole; with the
noise fitted to a rolling one a resting robot's NEES fell to 0.2. Which regime holds is
known from what a lab knows, the commands: the noise is the driven one while any
actuated rest length moves and for ``driven_hold`` seconds after (a robot set tipping
keeps rolling after its motors stop), the resting one otherwise.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.ukf.config import UkfConfig
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["ProcessNoise"]


def _node_noise_scale(config: UkfConfig, d: RobotDescription) -> NDArray[np.float64]:
    """(n,) the variance factor of each node's process noise from ``node_noise_scale``;
    refused, naming both counts, where it does not list every node."""
    if config.node_noise_scale is None:
        return np.ones(d.n_nodes)
    scale = np.asarray(config.node_noise_scale, dtype=np.float64)
    if scale.shape != (d.n_nodes,):
        raise ValueError(
            f"UkfConfig.node_noise_scale has {scale.size} factors; {d.name} has {d.n_nodes} nodes"
        )
    return np.asarray(scale**2)


class ProcessNoise:
    """Q for each filter step of one robot; holds how long the motors have
    been still (made anew at each reset of the filter: a robot starts at rest).

    Args:
        config: the filter's noise settings (position and velocity noise, resting and
            driven; node and contact factors; the contact band; the hold time).
        description: the robot (rod length for the scale, node count, endcap radii).
        n_offsets: how many of the description's lengths the state carries (their
            random walk is ``description_noise``).
    """

    def __init__(
        self, config: UkfConfig, description: RobotDescription, n_offsets: int = 0
    ) -> None:
        c = config
        L = description.characteristic_length
        self.resting = np.array([c.position_noise * L, c.velocity_noise * L]) ** 2
        """(2,): position (m^2/s) and velocity (m^2/s^3) variance rates at rest."""
        self.driven = np.array([c.driven_position_noise * L, c.driven_velocity_noise * L]) ** 2
        """(2,): the same while driven."""
        n = description.n_nodes
        self.body = (c.body_position_noise * L) ** 2 * np.kron(np.ones((n, n)), np.eye(3))
        """(3 n, 3 n): position variance rates (m^2/s) shared by every node while driven:
        every node's x with every node's x, and so on, (1 1^T) kron I3."""
        self.alignment = c.alignment_noise**2 if c.estimates_alignment else 0.0
        """Variance rate (rad^2/s) of each component of the AHRS frame's alignment;
        0 where the state does not carry it."""
        self.offsets = np.full(n_offsets, c.description_noise**2)
        """(k,) variance rates (m^2/s) of the description's lengths the state carries."""
        self.driven_speed = c.driven_speed
        self.driven_hold = c.driven_hold
        self.node_scale = _node_noise_scale(c, description)
        self.contact_scale = c.contact_noise_scale**2
        self.contact_height = description.node_radii + c.contact_band
        self.still_for = math.inf
        """Seconds since an actuated rest length last moved faster than driven_speed."""

    def covariance(
        self,
        dt: float,
        rest_before: NDArray[np.float64],
        rest_after: NDArray[np.float64],
        heights: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """Q over a step of ``dt`` seconds in which the actuated rest lengths (m,) (m)
        went from ``rest_before`` to ``rest_after``, the nodes at estimated ``heights``
        (n,) (m): its diagonal (6 n,), positions then velocities (then the alignment's
        3 and the description's lengths where the state carries them), where no noise
        is shared between nodes; else the
        whole matrix, with the ``body_position_noise`` that moves every node alike while
        the robot is driven."""
        moved = float(np.max(np.abs(rest_after - rest_before), initial=0.0))
        if dt > 0 and moved > self.driven_speed * dt:
            self.still_for = 0.0
        else:
            self.still_for += dt
        driven = self.still_for <= self.driven_hold
        rates = self.driven if driven else self.resting
        scale = self.node_scale
        if self.contact_scale != 1.0:
            scale = scale * np.where(heights <= self.contact_height, self.contact_scale, 1.0)
        per_axis = np.repeat(scale, 3) * dt
        q = np.concatenate([rates[0] * per_axis, rates[1] * per_axis])
        if self.alignment:
            q = np.concatenate([q, np.full(3, self.alignment * dt)])
        if len(self.offsets):
            q = np.concatenate([q, self.offsets * dt])
        if not driven or not self.body.any():
            return q
        Q = np.diag(q)
        Q[: len(self.body), : len(self.body)] += self.body * dt
        return Q
