"""Where each part of the UKF's state vector lies: :class:`StateLayout`.

The state is the node positions (3 n) and velocities (3 n), then where the filter
estimates them, the rotation vector (3,) from the AHRS's frame to the world's, and the
description's error: m added to the rest length of each actuated cable (what its
encoder reads is off by its zero; the cable is attached elsewhere) and to each rod's
length (its endcaps' distance). A lab's description is never exact: with those lengths
fixed at the description's, encoder zeros of centimetres turned the filter's rods by
degrees and left it far more certain than it was right (docs/results/cross_world.md);
estimated, the cable-length sensors and the ranges tell them apart.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.ukf.config import UkfConfig
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["StateLayout"]


@dataclass(frozen=True, eq=False)
class StateLayout:
    """The parts of the state vector of one robot under one configuration."""

    n_nodes: int
    alignment: int | None
    """Index of the alignment's first component, or None where it is not estimated."""
    offsets: int | None
    """Index of the first rest-length offset, or None where none is estimated."""
    members: NDArray[np.intp]
    """(k,) the members (the spring-mass model's: cables in description order, then
    rods) whose rest length the state offsets, in state order: the actuated cables,
    then the rods."""
    prior_sigma: NDArray[np.float64]
    """(k,) m: the prior std of each offset."""
    dim: int

    @classmethod
    def of(cls, config: UkfConfig, description: RobotDescription) -> StateLayout:
        """The layout the configuration asks for on ``description``'s robot."""
        d, c = description, config
        dim = 6 * d.n_nodes
        alignment = None
        if c.estimates_alignment:
            alignment, dim = dim, dim + 3
        members: list[int] = []
        sigma: list[float] = []
        if c.rest_length_error_sigma is not None:
            members += d.actuated.tolist()
            sigma += [c.rest_length_error_sigma] * d.n_actuated
        if c.rod_length_error_sigma is not None:
            members += [d.n_cables + k for k in range(d.n_rods)]
            sigma += [c.rod_length_error_sigma] * d.n_rods
        offsets = dim if members else None
        return cls(
            n_nodes=d.n_nodes,
            alignment=alignment,
            offsets=offsets,
            members=np.array(members, dtype=np.intp),
            prior_sigma=np.array(sigma, dtype=np.float64),
            dim=dim + len(members),
        )

    @property
    def n_offsets(self) -> int:
        return len(self.members)

    def member_offsets(
        self, states: NDArray[np.float64], n_members: int
    ) -> NDArray[np.float64] | None:
        """(S, M) m to add to every member's rest length, per state (S, dim); None where
        the state carries none."""
        if self.offsets is None:
            return None
        x = np.atleast_2d(states)
        out = np.zeros((x.shape[0], n_members))
        out[:, self.members] = x[:, self.offsets : self.offsets + self.n_offsets]
        return out

    def rod_offsets(self, n_cables: int) -> NDArray[np.intp] | None:
        """(r,) the state index of each rod's length offset, by rod; None where rod
        lengths are not estimated."""
        if self.offsets is None:
            return None
        rods = np.flatnonzero(self.members >= n_cables)
        if not len(rods):
            return None
        return np.asarray(self.offsets + rods, dtype=np.intp)
