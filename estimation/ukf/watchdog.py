"""The UKF's own judgement of its fit: when to gate, gate lock-outs and divergence.

:class:`FilterWatchdog` follows what the chi-square gate did with each update's rows.
A filter that has slid away gates out the very rows that would pull it back while the
rows it still accepts look consistent: a rod's axis or a share of the ranges gated out
several updates running is a lock-out, answered by widening the covariance (or, soon
after the last time, by starting over). Divergence (a non-finite or implausible state,
innovations too large, the anchors all disagreeing) is reported to the estimator's
:class:`~estimation.health.EstimatorHealth` by the estimator, which re-initialises.
"""

from __future__ import annotations

import enum
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from estimation.ukf.measurements import RowKind
from tensegrity_gym.model.kinematics import member_lengths

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from estimation.ukf.config import UkfConfig
    from estimation.ukf.filter import UpdateResult
    from estimation.ukf.measurements import MeasurementBatch
    from tensegrity_gym.model.description import RobotDescription

__all__ = ["JUMPED", "FilterWatchdog", "Lockout"]

JUMPED = "most anchor ranges gated out at once"
"""The divergence in which the estimate has jumped away from where the anchors put it."""


class Lockout(enum.Enum):
    """What a gate lock-out calls for."""

    NONE = enum.auto()
    RESET_COVARIANCE = enum.auto()
    """Widen the covariance so that the gated rows are heard again."""
    REINITIALISE = enum.auto()
    """A second lock-out soon after the last covariance reset: start over."""


class FilterWatchdog:
    """Gate verdicts of one filter run, from a (re-)initialisation on.

    Args:
        config: the thresholds (``gate_after``, ``lockout_*``, ``divergence_*``).
        description: the robot (rod nodes, sizes).
        rod_lengths: the rods' lengths (m), (r,).
    """

    def __init__(
        self, config: UkfConfig, description: RobotDescription, rod_lengths: NDArray[np.float64]
    ) -> None:
        self.config = config
        self.description = description
        self.rod_lengths = rod_lengths
        self._nis: deque[float] = deque(maxlen=config.divergence_window)
        self._range_rejects: deque[float] = deque(maxlen=config.lockout_updates)
        self._ranges_fit_run = 0  # updates in a row whose ranges fit (axis_fault_range_share)
        self._axis_reject_run = np.zeros(description.n_rods, dtype=np.intp)
        self._anchor_reject: float | None = None
        self._updates = 0
        self._since_reset: int | None = None  # updates since the last covariance reset

    @property
    def gating(self) -> bool:
        """Whether the chi-square gate applies: not right after (re)initialisation, when
        the state is still far off and the gate would throw away the rows that pull it
        in."""
        return self._updates >= self.config.gate_after

    def observe(self, batch: MeasurementBatch, result: UpdateResult) -> float | None:
        """Follow one update's gate verdicts; its NIS per accepted row, None without any."""
        kinds = batch.kind
        ranges = kinds == RowKind.RANGE
        fit = False
        if np.count_nonzero(ranges) >= 5:
            share = float(np.mean(~result.accepted[ranges]))
            self._range_rejects.append(share)
            fit = share <= self.config.axis_fault_range_share
        self._ranges_fit_run = self._ranges_fit_run + 1 if fit else 0
        # Ranges to the anchors place the robot; those between its own nodes only
        # shape it, and still fit when the whole estimate has jumped.
        to_anchor = (batch.range_pairs >= self.description.n_nodes).any(axis=1)
        self._anchor_reject = None
        if np.count_nonzero(to_anchor) >= 5:
            self._anchor_reject = float(np.mean(~result.accepted[ranges][to_anchor]))
        if batch.axis_rods.size:
            # Axis rows come first, three a rod.
            rejected = ~result.accepted[: 3 * batch.axis_rods.size].reshape(-1, 3).all(axis=1)
            run = self._axis_reject_run
            run[batch.axis_rods] = np.where(rejected, run[batch.axis_rods] + 1, 0)
        self._updates += 1
        accepted = int(np.count_nonzero(result.accepted))
        if not accepted:
            return None
        nis = result.nis / accepted
        self._nis.append(nis)
        return nis

    def divergence(self, x: NDArray[np.float64], P: NDArray[np.float64]) -> str | None:
        """Why the filter with state ``x`` (d,) and covariance ``P`` (d, d) has diverged, or
        None."""
        c = self.config
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
            return "non-finite state"
        d = self.description
        nodes = x[: 3 * d.n_nodes].reshape(-1, 3)
        strain = np.abs(member_lengths(nodes, d.rod_nodes) / self.rod_lengths - 1.0)
        if np.any(strain > c.divergence_rod_strain):
            return "rods stretched"
        if np.max(np.diag(P)[: 3 * d.n_nodes]) > (10.0 * d.characteristic_length) ** 2:
            return "covariance exploded"
        anchors = self._anchor_reject
        if anchors is not None and anchors > c.divergence_anchor_reject_share:
            return JUMPED
        window = self._nis
        if len(window) == window.maxlen and float(np.mean(window)) > c.divergence_nis:
            return "innovations too large"
        return None

    def lockout(self) -> Lockout:
        """Whether the gate has locked the filter out, and what that calls for; called
        once an update, after :meth:`observe` and a :meth:`divergence` of None."""
        c = self.config
        if self._since_reset is not None:
            self._since_reset += 1
        rejects = self._range_rejects
        locked = len(rejects) == rejects.maxlen and min(rejects) > c.lockout_range_share
        # An axis the gate shuts out while the ranges fit is its AHRS's fault.
        ranges_fit = self._ranges_fit_run >= c.lockout_updates
        axis_locked = bool(np.any(self._axis_reject_run >= c.lockout_updates)) and not ranges_fit
        if not (locked or axis_locked):
            return Lockout.NONE
        recent = self._since_reset
        if recent is not None and recent < 10 * c.lockout_updates:
            return Lockout.REINITIALISE
        self._range_rejects.clear()
        self._axis_reject_run[:] = 0
        self._since_reset = 0
        return Lockout.RESET_COVARIANCE
