"""Which endcaps touch the ground: from contact sensors, or from the shape and gravity.

A robot with contact sensors says so itself (:class:`~tensegrity_gym.model.samples.ContactSample`).
One without them (Tong et al. 2024's robot used motion capture for it) has the shape in its
body frame and the direction of gravity: on flat ground the endcaps in contact are the
lowest ones. :class:`ShapeContactDetector` takes the endcaps whose height above the
lowest is within ``enter`` and keeps them until they rise above ``leave``, so that a
contact does not flicker on and off with the noise of the shape (hysteresis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = ["ContactThresholds", "ShapeContactDetector"]


@dataclass(frozen=True)
class ContactThresholds:
    """Heights (m) above the lowest endcap, along gravity, at which an endcap counts as
    touching down (``enter``) and as lifted off (``leave`` > ``enter``)."""

    enter: float
    leave: float

    def __post_init__(self) -> None:
        for name in ("enter", "leave"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"ContactThresholds.{name} must be a height >= 0 m, got {value}")
        if self.leave < self.enter:
            raise ValueError(
                f"ContactThresholds.leave ({self.leave} m) must be at least enter ({self.enter} m)"
            )

    @classmethod
    def for_rod_length(cls, length: float) -> ContactThresholds:
        """Thresholds in proportion to the robot: 1 % and 3 % of a rod's length (1.5 and
        4.4 cm on a 1.45 m robot). Measured on its forward gait (tests/estimation/test_inekf.py):
        1.5/4 cm drifted 16 %, 3/7 cm 23 %, 8/15 cm 20 %: wider thresholds take in
        endcaps that hover, whose corrections pull the pose."""
        return cls(enter=0.01 * length, leave=0.03 * length)


class ShapeContactDetector:
    """Contacts from the shape in the body frame and the up direction, with hysteresis.

    Args:
        n_nodes: endcaps of the robot.
        thresholds: see :class:`ContactThresholds`.
    """

    def __init__(self, n_nodes: int, thresholds: ContactThresholds) -> None:
        self.thresholds = thresholds
        self.in_contact = np.zeros(n_nodes, dtype=bool)
        """(n_nodes,) the current contacts."""

    def reset(self) -> None:
        self.in_contact[:] = False

    def update(self, positions: NDArray[np.float64], up: NDArray[np.float64]) -> NDArray[np.bool_]:
        """The contacts for endcap ``positions`` (n_nodes, 3) in the body frame, m, and
        the unit ``up`` vector (3,) in that frame; (n_nodes,) bool, a copy.

        The lowest endcap is always in contact: the robot rests on something."""
        heights = positions @ up
        above = heights - heights.min()
        keep = self.in_contact & (above <= self.thresholds.leave)
        self.in_contact = keep | (above <= self.thresholds.enter)
        return self.in_contact.copy()
