"""What keeps a robot safe whatever the policy asks: command limits and the watchdog."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from tensegrity_gym.model.description import RobotDescription

__all__ = ["CommandLimiter", "Watchdog", "check_fields"]


def check_fields(settings: object, names: tuple[str, ...], *, positive: bool) -> None:
    """Raise ValueError naming the first of ``names`` on ``settings`` that is not a
    finite number above zero (``positive``) or at least zero."""
    for name in names:
        value = getattr(settings, name)
        if not np.isfinite(value) or value < 0 or (positive and value == 0):
            bound = "positive" if positive else ">= 0"
            raise ValueError(
                f"{type(settings).__name__}.{name}={value!r} must be finite and {bound}"
            )


class CommandLimiter:
    """Clips rest-length targets (m), (m,), to the motors' range and to a maximum
    change per control period from the previous command.

    Args:
        description: the robot; its motors give the range and the default rate.
        control_period: seconds between commands.
        max_change: metres a target may move per command, a scalar or (m,); by default
            what each motor travels in one period at its maximum speed, so that a
            command never asks more than the motor can do before the next one.
    """

    def __init__(
        self,
        description: RobotDescription,
        control_period: float,
        max_change: float | NDArray[np.float64] | None = None,
    ) -> None:
        lo, hi, speed = description.motor_limits
        self.lo, self.hi = lo, hi
        step = speed * control_period if max_change is None else max_change
        self.max_change = np.broadcast_to(np.asarray(step, dtype=np.float64), lo.shape).copy()
        if not np.all(np.isfinite(self.max_change)) or np.any(self.max_change <= 0):
            raise ValueError(f"max_change must be positive and finite; got {max_change!r}")
        self.previous: NDArray[np.float64] | None = None
        self.clipped = 0
        """Commands changed by the limits so far."""

    def reset(self, current: NDArray[np.float64] | None) -> None:
        """Start from ``current`` rest lengths (m), (m,), e.g. the encoders' reading."""
        self.previous = None if current is None else np.clip(current, self.lo, self.hi)

    def __call__(self, targets: NDArray[np.float64]) -> NDArray[np.float64]:
        t = np.asarray(targets, dtype=np.float64)
        if t.shape != self.lo.shape:
            raise ValueError(f"targets have shape {t.shape}, expected {self.lo.shape}")
        if not np.all(np.isfinite(t)):
            raise ValueError(f"targets are not finite: {t.tolist()}")
        out = np.clip(t, self.lo, self.hi)
        if self.previous is not None:
            out = np.clip(out, self.previous - self.max_change, self.previous + self.max_change)
        if not np.array_equal(out, t):
            self.clipped += 1
        self.previous = out
        return out


@dataclass
class Watchdog:
    """Trips when nothing has fed it for ``timeout`` seconds (any monotonic clock)."""

    timeout: float
    last: float | None = None

    def feed(self, now: float) -> None:
        self.last = now

    def tripped(self, now: float) -> bool:
        """True before the first feed, and once ``timeout`` has passed since the last."""
        return self.last is None or now - self.last > self.timeout
