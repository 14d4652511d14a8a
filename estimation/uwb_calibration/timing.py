"""The calibration's time constants from the ranging rates the data shows.

A lab's hardware seldom ranges in the 15 Hz rounds the settings' defaults are tuned
for: a recording may give each endcap-anchor pair about one range a second. A sample
(the ranges pooled as if the robot stood still) must then last long enough for a
module to range :attr:`~CalibrationConfig.min_anchor_ranges` anchors, and the start's
window long enough for each anchor to range several modules. :func:`fitted_to_rates`
measures the rates and lengthens what the defaults would leave too short; it never
shortens a setting.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from estimation.uwb_calibration.config import CalibrationConfig
    from estimation.uwb_calibration.rounds import RangeTable

__all__ = ["RangingRates", "fitted_to_rates", "ranging_rates"]

_MARGIN = 1.0
"""The distinct anchors a sample is sized to expect, over the number it needs."""
_START_MODULES = 6
"""Distinct modules each anchor should range within the start's window (three quarters
of the robot's where it has fewer than eight)."""
_FIRST_SAMPLES = 10
"""Samples (of the fitted period) the growth's first stage spans at least."""
_RATE_RANGES = 3.0
"""A pair's ranges each rate fit spans, in expectation, at least."""


@dataclass(frozen=True)
class RangingRates:
    """Robot-anchor ranges per second, as the recording shows them."""

    module: float
    """Median over the robot's modules of the ranges each gets per second, all anchors."""
    anchor: float
    """Median over the anchors of the ranges each gets per second, all modules."""
    pair: float
    """Median over the endcap-anchor pairs that ranged of each pair's ranges per second."""
    duration: float
    """Seconds from the first range to the last."""


def ranging_rates(table: RangeTable) -> RangingRates:
    """The rates of ``table``'s robot-anchor rows (0 where it has none)."""
    t = table.round_times[table.a_round] if len(table.a_round) else np.zeros(0)
    duration = float(np.ptp(t)) if len(t) > 1 else 0.0
    if duration <= 0.0:
        return RangingRates(0.0, 0.0, 0.0, duration)
    n, A = table.n_nodes, table.n_anchors
    per_module = np.bincount(table.a_module, minlength=n) / duration
    per_anchor = np.bincount(table.a_anchor, minlength=A) / duration
    per_pair = np.bincount(table.a_anchor * n + table.a_module, minlength=A * n) / duration
    ranged = per_pair[per_pair > 0]
    return RangingRates(
        float(np.median(per_module)), float(np.median(per_anchor)),
        float(np.median(ranged)) if len(ranged) else 0.0, duration,
    )  # fmt: skip


def _seconds_for(distinct: float, of: int, rate: float) -> float:
    """Seconds after which ``distinct`` of ``of`` sources, ranged at random at ``rate``
    ranges per second in all, are expected to have been seen: ``of (1 - exp(-rate T /
    of)) = distinct``; ``inf`` where the rate is 0."""
    if rate <= 0.0:
        return float("inf")
    share = min(distinct / of, 0.95)  # more than 95 % of the sources: as if all
    return float(-of / rate * np.log1p(-share))


def fitted_to_rates(
    config: CalibrationConfig, table: RangeTable, n_anchors: int
) -> tuple[CalibrationConfig, RangingRates]:
    """``config`` with ``sample_period``, ``window``, ``first_span`` and ``rate_span``
    lengthened where ``table``'s rates (rows not yet merged into samples) need it; and
    the rates."""
    rates = ranging_rates(table)
    needed = _MARGIN * config.min_anchor_ranges
    period = _seconds_for(needed, n_anchors, rates.module)
    # Several modules per anchor, however few the robot has (the 3-bar: 6 in all).
    window = _seconds_for(min(_START_MODULES, 0.75 * table.n_nodes), table.n_nodes, rates.anchor)
    # A recording too short to measure keeps the settings (it fails later, by count).
    period = config.sample_period if not np.isfinite(period) else max(config.sample_period, period)
    window = config.window if not np.isfinite(window) else max(config.window, window, period)
    first = max(config.first_span, _FIRST_SAMPLES * period)
    span = config.rate_span
    if rates.pair > 0.0:
        span = max(span, 0.5 * _RATE_RANGES / rates.pair)
    fitted = replace(config, sample_period=period, window=window, first_span=first,
                     rate_span=span)  # fmt: skip
    return fitted, rates
