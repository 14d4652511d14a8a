"""What the UKF keeps of its samples: the readings not yet fused, and the latest of each
sensor (with recent UWB rounds) to re-initialise from.

Samples pass the plausibility screen first. Time is the samples' own, in integer
nanoseconds: periods and windows come out the same wherever the clock started.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from estimation.ukf.measurements import RowKind, ahrs_axis
from tensegrity_gym.model.samples import (
    AhrsSample,
    CableLengthSample,
    ContactSample,
    EncoderSample,
    ImuSample,
    UwbRangeSample,
    seconds_to_ns,
)

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import NDArray

    from estimation.screen import PlausibilityScreen
    from estimation.ukf.measurements import MeasurementBatch
    from tensegrity_gym.model.samples import Sample

__all__ = ["Fresh", "Readings", "Round", "select_ranges"]


@dataclass(frozen=True, eq=False)
class Round:
    """A UWB round as the filter keeps it: only its plausible ranges."""

    t_ns: int
    """When the round ended (ns)."""
    pairs: NDArray[np.intp]
    """(k, 2) module ids."""
    ranges: NDArray[np.float64]
    """(k,) m, pair offsets included."""
    for_fit: NDArray[np.bool_]
    """(k,) False where the chi-square gate rejected the range or a divergence blamed
    its round: re-initialisation does not fit to those."""

    @classmethod
    def of(cls, sample: UwbRangeSample) -> Round:
        ranges = np.asarray(sample.ranges, dtype=np.float64).reshape(-1)
        pairs = np.asarray(sample.pairs, dtype=np.intp).reshape(-1, 2)
        return cls(seconds_to_ns(sample.t), pairs, ranges, np.ones(len(ranges), dtype=bool))


def select_ranges(
    rounds: Sequence[Round],
    allowed: NDArray[np.bool_],
    robot_ranges: bool,
    n_nodes: int,
    *,
    for_fit: bool = False,
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.intp]]:
    """The ranges of ``rounds`` the filter uses: pairs (r, 2), ranges (r,) (m), and their
    places (r,) in the rounds' ranges laid end to end.

    Only modules in ``allowed``; node-node ranges only if ``robot_ranges``; only the
    ranges still marked ``for_fit`` if ``for_fit``.
    """
    if not rounds:
        return np.zeros((0, 2), dtype=np.intp), np.zeros(0), np.zeros(0, dtype=np.intp)
    pairs = np.concatenate([r.pairs for r in rounds])
    ranges = np.concatenate([r.ranges for r in rounds])
    keep = allowed[pairs].all(axis=1)
    if not robot_ranges:
        keep &= (pairs >= n_nodes).any(axis=1)
    if for_fit:
        keep &= np.concatenate([r.for_fit for r in rounds])
    return pairs[keep], ranges[keep], np.flatnonzero(keep).astype(np.intp)


@dataclass
class Fresh:
    """Readings not yet fused: each is used by one update only."""

    axes: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    """Rod axes (3,) from the AHRS, by rod."""
    cables: NDArray[np.float64] | None = None
    """Every cable's length (m), (c,); NaN where there is no reading."""
    contacts: NDArray[np.intp] | None = None
    """Nodes in contact with the ground."""


class Readings:
    """The screened samples the UKF keeps between updates.

    Args:
        screen: what passes a sample on (and counts what it drops).
        range_window: seconds of UWB rounds kept for re-initialisation.
        t_ns: the clock before the first sample (ns).
        rest: actuated rest lengths (m), (m,), until an encoder reading arrives.
    """

    def __init__(
        self, screen: PlausibilityScreen, range_window: float, t_ns: int, rest: NDArray[np.float64]
    ) -> None:
        self.screen = screen
        self._window_ns = seconds_to_ns(range_window)
        self.t_ns = t_ns
        """The newest sample's time (ns), plausible or not."""
        self.rest = rest
        self.fresh = Fresh()
        self.rounds: list[Round] = []
        """The rounds of the last ``range_window``."""
        # The latest of each reading, to re-initialise from; the chi-square gate takes
        # back what it rejects.
        self.latest_axes: dict[int, NDArray[np.float64]] = {}
        self.latest_cables: NDArray[np.float64] | None = None
        self.latest_contacts: NDArray[np.intp] | None = None
        self._axes_before: dict[int, NDArray[np.float64] | None] = {}
        self._period: list[Round] = []
        self._period_index = np.zeros(0, dtype=np.intp)

    def absorb(self, samples: Sequence[Sample]) -> tuple[list[Round], bool]:
        """Keep the latest of each sensor; return this period's UWB rounds and whether
        an encoder reading arrived. The clock advances with every sample."""
        samples = self.screen.timely(samples)
        if samples:
            self.t_ns = max(self.t_ns, seconds_to_ns(max(s.t for s in samples)))
        rounds: list[Round] = []
        ahrs: dict[int, AhrsSample] = {}
        encoders: list[EncoderSample] = []
        # Most samples are raw IMU readings, which the filter does not use; of the
        # rest only the newest of each kind counts, except the UWB rounds.
        for s in self.screen.screen(samples):
            if isinstance(s, ImuSample):
                continue
            if isinstance(s, AhrsSample):
                ahrs[s.rod] = s
            elif isinstance(s, UwbRangeSample):
                rounds.append(Round.of(s))
            elif isinstance(s, EncoderSample):
                encoders.append(s)
            elif isinstance(s, CableLengthSample):
                self.fresh.cables = self.latest_cables = np.asarray(s.lengths, dtype=np.float64)
            elif isinstance(s, ContactSample):
                contacts = np.flatnonzero(s.in_contact).astype(np.intp)
                self.fresh.contacts = self.latest_contacts = contacts
        if encoders:
            self.rest = np.asarray(encoders[-1].rest_lengths, dtype=np.float64)
        self._axes_before = {}
        for rod, sample in ahrs.items():
            q = np.asarray(sample.quaternion, dtype=np.float64)
            self._axes_before[rod] = self.latest_axes.get(rod)
            self.fresh.axes[rod] = self.latest_axes[rod] = ahrs_axis(q / np.linalg.norm(q))
        since = self.t_ns - self._window_ns
        # After a stall a period brings seconds of rounds at once; the robot has moved
        # since the older ones, and fusing them all at the period's end would stack an
        # innovation covariance over every row (a 30 s backlog of SUPERball's: 70,000
        # rows, a 40 GB matrix). Only the window's newest are fused, as kept.
        rounds = [r for r in rounds if r.t_ns >= since]
        self.rounds = [r for r in self.rounds if r.t_ns >= since] + rounds
        return rounds, bool(encoders)

    def take(self, rounds: list[Round], range_index: NDArray[np.intp]) -> Fresh:
        """The readings not yet fused, which the update fuses now with the ranges at
        ``range_index`` of this period's ``rounds`` laid end to end."""
        self._period, self._period_index = rounds, range_index
        fresh, self.fresh = self.fresh, Fresh()
        return fresh

    def blame_period(self) -> None:
        """Fit none of this period's ranges again, not even those the gate passed."""
        for r in self._period:
            r.for_fit[:] = False

    def forget_gated(self, batch: MeasurementBatch, accepted: NDArray[np.bool_]) -> None:
        """Take back from re-initialisation every reading the chi-square gate rejected
        (``accepted`` (rows,) False): a range is marked not to fit, a rod's axis reverts
        to its last accepted one, a cable's reading and a contact are dropped."""
        rejected = ~accepted
        if not rejected.any():
            return
        ranges = rejected[batch.kind == RowKind.RANGE]
        if ranges.any():
            flat = self._period_index[ranges]
            sizes = np.array([len(r.ranges) for r in self._period])
            ends = np.cumsum(sizes)
            which = np.searchsorted(ends, flat, side="right")
            for j, k in zip(which, flat - (ends - sizes)[which], strict=True):
                self._period[j].for_fit[k] = False
        if batch.axis_rods.size:
            gated = rejected[: 3 * batch.axis_rods.size].reshape(-1, 3).any(axis=1)
            for rod in batch.axis_rods[gated].tolist():
                before = self._axes_before.get(rod)
                if before is None:
                    self.latest_axes.pop(rod, None)
                else:
                    self.latest_axes[rod] = before
        cables = batch.cables[rejected[batch.kind == RowKind.CABLE_LENGTH]]
        if cables.size and self.latest_cables is not None:
            self.latest_cables = self.latest_cables.copy()
            self.latest_cables[cables] = np.nan
        contacts = batch.contact_nodes[rejected[batch.kind == RowKind.CONTACT_HEIGHT]]
        if contacts.size and self.latest_contacts is not None:
            self.latest_contacts = np.setdiff1d(self.latest_contacts, contacts)
