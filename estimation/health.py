"""How an estimator is doing: the one component every estimator reports its health into.

:class:`EstimatorHealth` counts divergences and re-initialisations by reason, adds up
the time predicted since a sensor correction was last fused (an estimate is unhealthy
after more than ``max_prediction_time`` without one), holds the counts of physically
implausible readings by kind and the failed sensor streams of the estimator's
:class:`~estimation.screen.PlausibilityScreen`, and fills the health fields of each
:class:`~tensegrity_gym.model.estimate.Estimate` (``healthy``, ``reinitialised``,
``rejected``, ``failed_streams``, ``description_mismatch``,
``reinitialised_because``).

Time is counted in integer nanoseconds, so that a sum of periods is exact and does not
depend on where the clock started.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol

from tensegrity_gym.model.samples import seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tensegrity_gym.model.estimate import Estimate

__all__ = ["EstimatorHealth", "HealthParams", "Screen"]


class Screen(Protocol):
    """What the health reads of a plausibility screen (:class:`PlausibilityScreen`)."""

    @property
    def rejected(self) -> Mapping[str, int]:
        """Readings dropped as implausible since the reset, by kind."""

    @property
    def failed(self) -> tuple[str, ...]:
        """The streams not in use, sorted."""

    @property
    def mismatches(self) -> tuple[str, ...]:
        """A line per channel whose readings contradict the description."""


@dataclass(frozen=True)
class HealthParams:
    """When an estimate counts as healthy."""

    max_prediction_time: float = 0.5
    """Seconds an estimator may go without fusing a sensor correction before its estimate
    is unhealthy; 0: every update must fuse one."""
    healthy_when_reinitialised: bool = False
    """Whether the update that re-initialised the estimator may be healthy: a tracker
    placed by a fresh frame is; a filter restarted with a wide covariance is not."""

    def __post_init__(self) -> None:
        t = self.max_prediction_time
        if not (math.isfinite(t) and t >= 0):
            raise ValueError(f"HealthParams.max_prediction_time must be >= 0 s, got {t}")


class EstimatorHealth:
    """Health book-keeping of one estimator from one reset on.

    Args:
        params: when an estimate is healthy.
        screen: the estimator's plausibility screen, whose counts and failed streams the
            estimates carry; None for an estimator without one (``rejected`` is then None).
    """

    def __init__(self, params: HealthParams, screen: Screen | None = None) -> None:
        self.params = params
        self.screen = screen
        self.divergences: dict[str, int] = {}
        """Divergences detected, by reason (e.g. ``"rods stretched"``)."""
        self.reinitialisations_by_reason: dict[str, int] = {}
        """Re-initialisations asked for, by reason (a divergence's, or a lost track's)."""
        self._max_ns = seconds_to_ns(params.max_prediction_time)
        self._uncorrected_ns = 0
        """ns predicted since a correction was last fused."""
        self._period_ns = 0
        """ns spanned by the last update that spanned any time."""
        self._pending: str | None = None
        self._reinitialised = False
        self._reason: str | None = None
        """Why this update re-initialised, where it did and the reason was asked for."""

    # ------------------------------------------------------------------ counts

    @property
    def reinitialisations(self) -> int:
        """Re-initialisations asked for since the reset, whatever their reason."""
        return sum(self.reinitialisations_by_reason.values())

    @property
    def implausible(self) -> dict[str, int]:
        """Readings dropped as physically implausible, by kind (empty without a screen)."""
        return dict(self.screen.rejected) if self.screen is not None else {}

    @property
    def failed_streams(self) -> tuple[str, ...]:
        """Sensor streams not in use because they were implausible for a while."""
        return self.screen.failed if self.screen is not None else ()

    @property
    def mismatches(self) -> tuple[str, ...]:
        """Where the readings contradict the description (kept in use), a line each."""
        return self.screen.mismatches if self.screen is not None else ()

    # ------------------------------------------------------------------ events

    def predicted(self, duration_ns: int, *, corrected: bool) -> None:
        """One update predicted over ``duration_ns`` and fused a sensor correction or not.

        An update that spans no time counts as long as the last one that did, and at
        least 1 ns when it fuses nothing: it still is an update without a correction.
        """
        if corrected:
            self._uncorrected_ns = 0
        else:
            self._uncorrected_ns += max(duration_ns if duration_ns > 0 else self._period_ns, 1)
        if duration_ns > 0:
            self._period_ns = duration_ns

    def diverged(self, reason: str) -> None:
        """Count a divergence and ask for a re-initialisation for it."""
        self.divergences[reason] = self.divergences.get(reason, 0) + 1
        self.request_reinitialisation(reason)

    def request_reinitialisation(self, reason: str) -> None:
        """Count a re-initialisation asked for (done now or at the next chance)."""
        self.reinitialisations_by_reason[reason] = (
            self.reinitialisations_by_reason.get(reason, 0) + 1
        )
        self._pending = reason

    @property
    def pending(self) -> str | None:
        """The reason of a re-initialisation asked for and not yet done, or None."""
        return self._pending

    def reinitialised(self, *, placed: bool) -> None:
        """The estimator re-initialised itself in this update; ``placed``: from samples
        just now (which counts as a correction), not by keeping its last state."""
        self._reason = self._pending
        self._pending = None
        self._reinitialised = True
        if placed:
            self._uncorrected_ns = 0

    # ------------------------------------------------------------------ estimates

    @property
    def healthy(self) -> bool:
        """Whether the estimate of this update is healthy."""
        if self._reinitialised and not self.params.healthy_when_reinitialised:
            return False
        return self._uncorrected_ns <= self._max_ns

    def fill(self, estimate: Estimate) -> Estimate:
        """``estimate`` with this update's health fields; ends the update."""
        out = replace(
            estimate,
            healthy=self.healthy,
            reinitialised=self._reinitialised,
            failed_streams=self.failed_streams,
            rejected=self.implausible if self.screen is not None else None,
            description_mismatch=self.mismatches,
            reinitialised_because=self._reason if self._reinitialised else None,
        )
        self._reinitialised = False
        self._reason = None
        return out

    def summary(self) -> dict[str, object]:
        """The counts, for a report: ``divergences`` and ``reinitialisations`` by reason,
        ``implausible`` by kind, ``failed_streams``, ``description_mismatch``."""
        return {
            "divergences": dict(self.divergences),
            "reinitialisations": dict(self.reinitialisations_by_reason),
            "implausible": self.implausible,
            "failed_streams": list(self.failed_streams),
            "description_mismatch": list(self.mismatches),
        }
